"""Build benchmark: time per stage, peak memory, leaves, ε, coverage vs max_error.

Each build runs in a fresh subprocess (peak RSS is that process's own). In the same run,
coal's OBBRSS BVH build of the same mesh is timed as a reference for preprocessing cost.
Writes ``out/bench_build.json`` and ``out/bench_build.png`` (leaves vs ε, time vs ε).

    python scripts/bench_build.py            # bundled models + ../shared/data when present
    python scripts/bench_build.py --quick    # the bundled mandible at a coarse ε only
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"

# (label, path, max_error values in mesh units; (max_error, min_coverage) also fills the interior,
# (max_error, "sparse") builds with sparse=True)
CASES = [
    ("mandible (bundled, m)", ROOT / "models" / "mandible.obj", [4e-4, 2e-4, (5e-4, 0.9)]),
    ("maxilla (bundled, m)", ROOT / "models" / "maxilla.obj", [4e-4, 2e-4]),
    ("mandible (real, m)", SHARED / "jaw" / "mandible.obj", [1e-3, 4e-4, 2e-4, 1e-4, 5e-5, (4e-4, 0.9), (5e-5, 0.9),
                                                                  (1e-4, "sparse"), (5e-5, "sparse")]),
    ("maxilla (real, m)", SHARED / "jaw" / "maxilla.obj", [1e-3, 4e-4, 2e-4, 1e-4, 5e-5, (1e-4, "sparse"), (5e-5, "sparse")]),
    ("bunny (mm)", SHARED / "stanford" / "bunny.obj", [2.0, 1.0, 0.5]),
    ("dragon (unitless)", SHARED / "stanford" / "dragon.obj", [0.01, 0.005]),
]
QUICK = {"mandible (bundled, m)": [1e-3]}  # --quick: one small build; the real meshes take minutes each


def _child(path: str, max_error: float, save: str | None = None, variant: str | None = None) -> None:
    """One build; ``variant`` is a min_coverage value or "sparse"."""
    import mjist

    kw = {"sparse": True} if variant == "sparse" else {"min_coverage": float(variant)} if variant else {}
    t = time.perf_counter()
    tree = mjist.build(path, max_error=max_error, **kw)
    wall = time.perf_counter() - t
    if save:
        tree.save(save)
    s = tree.stats()
    s["wall"] = wall
    s["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print("RESULT " + json.dumps(s))


def _coal_bvh_time(path: str) -> float:
    import coal

    import mjist

    m = mjist.load_mesh(path)
    t = time.perf_counter()
    model = coal.BVHModelOBBRSS()
    model.beginModel(len(m.faces), len(m.vertices))
    model.addVertices(m.vertices)
    model.addTriangles(m.faces.astype(np.int64))
    model.endModel()
    return time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "out"))
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument("--repeat", type=int, default=1, help="builds per row; the row reports the median wall and stages")
    ap.add_argument("--only", default="", help="';'-separated 'label@max_error' rows, e.g. 'mandible (real, m)@0.0001'")
    args = ap.parse_args()
    only = {x.strip() for x in args.only.split(";") if x.strip()}  # labels contain commas
    os.makedirs(args.out, exist_ok=True)
    # warm numba's cache once so no build below pays compile time
    subprocess.run([sys.executable, "-c", "import mjist,trimesh; mjist.build(trimesh.creation.icosphere(3), max_error=0.05)"], check=True)
    rows = []
    for label, path, errs in CASES:
        if args.quick:
            errs = QUICK.get(label, [])
        if not errs or not path.exists():
            continue
        coal_t = float(np.median([_coal_bvh_time(str(path)) for _ in range(3)]))  # the reference, same run
        for e in errs:
            e, variant = e if isinstance(e, tuple) else (e, None)
            sparse = variant == "sparse"
            fill = None if sparse else variant
            cmd = [sys.executable, __file__, "--child", str(path), repr(e), "-"] + (["sparse" if sparse else repr(fill)] if variant else [])
            label_run = label + (" sparse" if sparse else f" fill→{fill:g}" if fill else "")
            if only and f"{label_run}@{e:g}" not in only:
                continue
            runs, failed = [], None
            for _ in range(max(1, args.repeat)):
                try:
                    p = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
                except subprocess.TimeoutExpired:
                    failed = f"timeout {args.timeout}s"
                    break
                line = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
                if not line:
                    failed = p.stderr[-2000:]
                    break
                runs.append(json.loads(line[0][7:]))
            if failed is not None:
                rows.append({"mesh": label_run, "max_error": e, "error": failed})
                print(f"{label_run:22s} ε≤{e:<8g} failed: {failed[-300:]}")
                continue
            # median over the repeats (same tree every time: only the timings differ)
            s = runs[0]
            walls = [r["wall"] for r in runs]
            s["walls"] = walls
            s["wall"] = float(np.median(walls))
            s["timings"] = {k: float(np.median([r["timings"][k] for r in runs])) for k in s["timings"]}
            s["peak_rss_mb"] = float(np.median([r["peak_rss_mb"] for r in runs]))
            s.update(mesh=label_run, min_coverage=fill, sparse=sparse, path=str(path), max_error=e, coal_bvh_build_s=coal_t)
            rows.append(s)
            print(
                f"{label_run:22s} ε≤{e:<8g} ε={s['error_bound']:.3g} leaves={s['leaves']:>8d} depth={s['depth']:>2d} "
                f"coverage={100 * s['coverage']:.1f}% wall={s['wall']:.1f}s (median of {len(walls)}) peak={s['peak_rss_mb']:.0f}MB "
                f"(coal BVH {coal_t * 1e3:.0f} ms, ratio {s['wall'] / coal_t:.0f}x)",
                flush=True,
            )
    if only and not rows:
        names = [f"{lab}@{(e[0] if isinstance(e, tuple) else e):g}" for lab, _, errs in CASES for e in errs]
        print(f"--only matched no row (or its mesh is missing); rows are: {'; '.join(names)}", file=sys.stderr)
        return 2
    info = {
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "python": sys.version.split()[0],
        "command": " ".join(["python", "scripts/bench_build.py"] + (["--quick"] if args.quick else [])
                            + ([f"--repeat {args.repeat}"] if args.repeat > 1 else []) + ([f"--only '{args.only}'"] if only else [])),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
    with open(os.path.join(args.out, "bench_build.json"), "w") as fh:
        json.dump({"info": info, "rows": rows}, fh, indent=2)
    _plot(rows, os.path.join(args.out, "bench_build.png"))
    with open(os.path.join(args.out, "bench_build.md"), "w") as fh:
        fh.write(markdown(info, rows))
    print(f"wrote {args.out}/bench_build.json, bench_build.png and bench_build.md")
    return 0


def markdown(info, rows) -> str:
    """The results as a Markdown table (pasted into BENCHMARKS.md)."""
    out = [
        f"`{info['command']}` on {info['machine']}, {info['cpus']} CPUs, Python {info['python']}, {info['date']}.",
        "",
        "| mesh | max_error | certified ε | ε lower | leaves | nodes | depth | coverage | voxelize s | pack s | hierarchy s | bound s | total s | peak MB | coal BVH ms | total / coal BVH |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error_bound" not in r:
            out.append(f"| {r['mesh']} | {r['max_error']:g} | {r['error'].splitlines()[-1][:60] if r['error'] else 'failed'} |" + " |" * 13)
            continue
        t = r["timings"]
        out.append(
            f"| {r['mesh']} | {r['max_error']:g} | {r['error_bound']:.3g} | {r['error_lower']:.3g} | {r['leaves']} | {r['nodes']} | "
            f"{r['depth']} | {100 * r['coverage']:.1f} % | {t['voxelize']:.1f} | {t['pack']:.1f} | {t['hierarchy']:.1f} | "
            f"{t['bound']:.1f} | {r['wall']:.1f} | {r['peak_rss_mb']:.0f} | {1e3 * r['coal_bvh_build_s']:.0f} | {r['wall'] / r['coal_bvh_build_s']:.0f}× |"
        )
    return "\n".join(out) + "\n"


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "error_bound" in r]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    for label in dict.fromkeys(r["mesh"] for r in ok):
        rr = sorted((r for r in ok if r["mesh"] == label), key=lambda r: r["error_bound"])
        eps = [r["error_bound"] for r in rr]
        ax[0].loglog(eps, [r["leaves"] for r in rr], "o-", label=label)
        ax[1].loglog(eps, [r["wall"] for r in rr], "o-", label=label)
        ax[2].semilogx(eps, [100 * r["coverage"] for r in rr], "o-", label=label)
    ax[0].set(xlabel="certified ε (mesh units)", ylabel="leaves", title="leaves vs ε")
    ax[1].set(xlabel="certified ε (mesh units)", ylabel="build time [s]", title="build time vs ε")
    ax[2].set(xlabel="certified ε (mesh units)", ylabel="coverage [%]", title="volume coverage vs ε")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    if 4 <= len(sys.argv) <= 6 and sys.argv[1] == "--child":  # --child MESH MAX_ERROR [SAVE_TREE|-] [MIN_COVERAGE|sparse]
        a = sys.argv + [None] * (6 - len(sys.argv))
        _child(a[2], float(a[3]), a[4] if a[4] not in (None, "-") else None, a[5])
        sys.exit(0)
    sys.exit(main())
