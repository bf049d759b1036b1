"""report.html: file size, time to write it, and time to its first drawn frame in headless Chromium.

    python scripts/bench_report.py OUT_DIR [OUT_DIR ...] [--runs 3] [--out out/bench_report]

Each OUT_DIR is the output folder of ``mjist occlusion``, ``mjist wafer`` or ``mjist demo --data``.
The report is rebuilt (``mjist.report.build``, timed), then opened ``--runs`` times in a fresh
headless Chromium (software WebGL, SwiftShader) without a virtual time budget: the page records
``performance.now()`` when plotly has drawn its first frame (``data-first-frame-ms``), read back
from the dumped DOM. Quotes medians. Writes ``OUT.json`` and ``OUT.md``. Reference measured in the
same run: the same Chromium loading an empty page (its start-up, which the first frame includes).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
         "--window-size=1400,1000", "--disable-background-networking", "--no-first-run", "--disable-component-update"]


def first_frame_ms(browser: str, page: Path) -> tuple[float | None, float]:
    """(the page's first-frame time in ms, or None; the browser's wall time in s)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as profile:
        p = subprocess.run([browser, *FLAGS, f"--user-data-dir={profile}", "--dump-dom", page.resolve().as_uri()],
                           capture_output=True, text=True, timeout=300)
    wall = time.perf_counter() - t0
    m = re.search(r'data-first-frame-ms="(\d+)"', p.stdout)
    return (float(m.group(1)) if m else None), wall


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_report"))
    a = ap.parse_args(argv)
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        print("no Chromium on this machine (apt install chromium): nothing measured")
        return 0
    from mjist import report

    with tempfile.TemporaryDirectory() as d:
        empty = Path(d) / "empty.html"
        empty.write_text("<html><body data-first-frame-ms=\"0\"></body></html>")
        base = statistics.median(first_frame_ms(browser, empty)[1] for _ in range(a.runs))
    rows = []
    for folder in map(Path, a.folders):
        t0 = time.perf_counter()
        page = report.build(folder)
        build_s = time.perf_counter() - t0
        r = report.read_output(folder)
        shots = [first_frame_ms(browser, page) for _ in range(a.runs)]
        frames = [f for f, _ in shots if f is not None]
        rows.append({"folder": str(folder), "kind": r.kind, "size_mb": page.stat().st_size / 1e6, "build_s": build_s,
                     "faces_drawn": int(sum(len(L.faces) for L in r.layers)),
                     "first_frame_s": statistics.median(frames) / 1e3 if frames else None,
                     "browser_wall_s": statistics.median(w for _, w in shots), "empty_page_wall_s": base})
        x = rows[-1]
        print(f"{folder}: {x['size_mb']:.1f} MB, written in {build_s:.1f} s, {x['faces_drawn']} faces drawn, first frame "
              f"{x['first_frame_s']} s (browser {x['browser_wall_s']:.1f} s; empty page {base:.1f} s)", flush=True)
    out = Path(a.out)
    os.makedirs(out.parent, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    md = ["| output | kind | file MB | written in s | faces drawn | first frame s (median) | Chromium wall s (empty page) |",
          "|---|---|---|---|---|---|---|"]
    md += [f"| {Path(x['folder']).name} | {x['kind']} | {x['size_mb']:.1f} | {x['build_s']:.1f} | {x['faces_drawn']:,} | "
           f"{x['first_frame_s']:.2f} | {x['browser_wall_s']:.1f} ({x['empty_page_wall_s']:.1f}) |" for x in rows]
    out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
