"""A new user's first run: fresh venv, ``pip install`` of this checkout, empty caches, ``mjist demo``.

    python scripts/bench_first_run.py [--out out/bench_first_run] [--keep]

Builds a wheel of this checkout, installs it into a new virtual environment outside the
repository, then runs ``mjist demo`` twice from an empty folder with an empty tree cache
(``MJIST_CACHE``) and a package that has never compiled its numba kernels: the first run pays
for the trees and the compilation, the second shows a returning user's time. Reports the
install time, both demo times (wall), the tree-building time the demo printed, and the rest
(mostly numba compiling). Writes ``OUT.json`` and ``OUT.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _timed(cmd, cwd, env, log) -> tuple[float, str]:
    t = time.perf_counter()
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    dt = time.perf_counter() - t
    log.write(f"$ {' '.join(map(str, cmd))}  ({dt:.1f} s, exit {p.returncode})\n{p.stdout}\n{p.stderr}\n")
    if p.returncode:
        raise RuntimeError(f"{cmd[0]} failed ({p.returncode}): {p.stderr.strip().splitlines()[-1:] }")
    return dt, p.stdout


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_first_run"))
    ap.add_argument("--keep", action="store_true", help="keep the temporary venv and caches")
    a = ap.parse_args(argv)
    out = Path(a.out)
    os.makedirs(out.parent, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="mjist-first-run-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MJIST_", "NUMBA_CACHE"))}
    env.update(MJIST_CACHE=str(tmp / "cache"), MUJOCO_GL=env.get("MUJOCO_GL", "egl"))
    res = {}
    with open(out.with_suffix(".log"), "w") as log:
        try:
            res["wheel_s"], _ = _timed([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"), str(ROOT)],
                                       tmp, env, log)
            _timed([sys.executable, "-m", "venv", str(tmp / "venv")], tmp, env, log)
            py = tmp / "venv" / "bin" / "python"
            wheel = next((tmp / "dist").glob("mjist-*.whl"))
            res["install_s"], _ = _timed([str(py), "-m", "pip", "install", "-q", str(wheel)], tmp, env, log)
            work = tmp / "work"
            work.mkdir()
            for k in ("first", "second"):
                dt, text = _timed([str(tmp / "venv" / "bin" / "mjist"), "demo", "--no-picture", "-q", "--out-dir", str(work / k)],
                                  work, env, log)
                m = re.search(r"\((\d+) from cache, ([\d.]+) s building\)", text)
                res[f"demo_{k}_s"] = dt
                res[f"demo_{k}_trees_s"] = float(m.group(2)) if m else None
                gap = re.search(r"coal distance ([+-][\d.]+) mm", text)
                res[f"demo_{k}_coal_gap_mm"] = float(gap.group(1)) if gap else None
        finally:
            if not a.keep:
                shutil.rmtree(tmp, ignore_errors=True)
    res["demo_first_other_s"] = res["demo_first_s"] - (res["demo_first_trees_s"] or 0.0)
    out.with_suffix(".json").write_text(json.dumps(res, indent=1))
    md = ["| step | seconds |", "|---|---|",
          f"| pip install of the wheel into a new venv | {res['install_s']:.0f} |",
          f"| first `mjist demo` (empty caches) | {res['demo_first_s']:.0f} |",
          f"| of which building the two trees | {res['demo_first_trees_s'] or 0:.0f} |",
          f"| of which the rest (mostly numba compiling) | {res['demo_first_other_s']:.0f} |",
          f"| second `mjist demo` | {res['demo_second_s']:.1f} |"]
    out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
