"""Scaling with mesh size: the procedural jaw pair polygonised at several grid spacings
(10k → 200k vertices per jaw, same shape), each built at the same ``max_error`` and replayed
along the same chewing motion against coal.

What it shows: the IST's cost follows ε (the surface area over ε²), not the triangle count;
build time grows only with the BVH queries of voxelization, while coal's exact distance grows
with the triangles it has to descend to.

Per resolution: vertices, tree build wall time and peak RSS (each build in its own process, via
``bench_build.py --child``), leaves, certified ε, coverage; coal's BVH build time; median
time per frame of the IST's plain and backtracking distance and of coal's exact distance;
max |d_IST − coal| and bound violations.

Writes ``bench_scaling.json``, ``bench_scaling.png`` and ``bench_scaling.md`` into ``--out``.

    python scripts/bench_scaling.py            # 5 resolutions, ε 0.4 mm, 1000 frames
    python scripts/bench_scaling.py --quick    # 2 resolutions, ε 1 mm, 200 frames
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_query import CLENCH, coal_replay, stats, timed, write_outputs  # noqa: E402

import mjist  # noqa: E402
from mjist.jaw import generator as jawmodel  # noqa: E402
from mjist.jaw import pair as jaw  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
FULL = {"spacings": [1.6, 1.1, 0.8, 0.5, 0.35], "max_error": 4e-4, "frames": 1000}
QUICK = {"spacings": [1.6, 0.8], "max_error": 1e-3, "frames": 200}


def _build_child(path: Path, max_error: float, save: Path, timeout: float) -> dict:
    cmd = [sys.executable, str(ROOT / "scripts" / "bench_build.py"), "--child", str(path), repr(max_error), str(save)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    line = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if not line:
        raise RuntimeError(f"build of {path} failed:\n{p.stderr[-2000:]}")
    return json.loads(line[0][7:])


def run_resolution(spacing: float, cfg: dict, work: Path, timeout: float) -> dict:
    folder = work / f"spacing_{spacing:g}"
    folder.mkdir(parents=True, exist_ok=True)
    maxi, mand, meta = jawmodel.generate(spacing)
    paths = {"maxilla": folder / "maxilla.ply", "mandible": folder / "mandible.ply"}
    for name, m in (("maxilla", maxi), ("mandible", mand)):
        m.export(paths[name])  # binary PLY keeps the float64 vertices exactly
    row = {"spacing_mm": spacing, "vertices": [int(len(maxi.vertices)), int(len(mand.vertices))],
           "faces": [int(len(maxi.faces)), int(len(mand.faces))], "builds": {}}
    trees = {}
    for name, p in paths.items():
        s = _build_child(p, cfg["max_error"], p.with_suffix(".ist.npz"), timeout)
        row["builds"][name] = {k: s[k] for k in ("wall", "peak_rss_mb", "leaves", "depth", "error_bound", "coverage")}
        mesh = mjist.load_mesh(p)
        t = time.perf_counter()
        bvh = jaw.coal_bvh(mesh.vertices, mesh.faces)
        row["builds"][name]["coal_bvh_s"] = time.perf_counter() - t
        trees[name] = (mesh, bvh)
    ta = mjist.load_tree(paths["maxilla"].with_suffix(".ist.npz"), expect_hash=trees["maxilla"][0].content_hash)
    tb = mjist.load_tree(paths["mandible"].with_suffix(".ist.npz"), expect_hash=trees["mandible"][0].content_hash)
    bx, bd = trees["maxilla"][1], trees["mandible"][1]
    touch = jaw.touching_offset(bx, bd)
    poses = jaw.chewing_motion(cfg["frames"], np.array(meta["hinge"]), contact_offset=touch + CLENCH)
    I = np.eye(4)
    coal_t, coal_d = coal_replay(bx, bd, poses)
    truth = np.maximum(coal_d, 0.0)
    q = mjist.Query(ta, tb)
    row["error_bound"] = q.error_bound
    row["coal"] = stats(coal_t)
    row["methods"] = {}
    for name in ("distance", "backtracking"):
        q.reset()
        q.distance(I, poses[0], method=name)
        q.reset()
        ts, rs = timed(lambda a, b, name=name: q.distance(a, b, method=name), poses)
        d = np.array([r.distance for r in rs])
        eb = np.array([r.error_bound for r in rs])
        row["methods"][name] = {**stats(ts), "err_max": float(np.max(d - truth)),
                                "bound_violations": int(np.sum((truth > d + 1e-9) | (d - eb > truth + 1e-9)))}
    b = row["builds"]
    print(f"  spacing {spacing:4.2f} mm: {row['vertices'][0]:>7,} / {row['vertices'][1]:>7,} vertices; build "
          f"{b['maxilla']['wall']:5.1f} + {b['mandible']['wall']:5.1f} s, peak {max(x['peak_rss_mb'] for x in b.values()):5.0f} MB, "
          f"leaves {b['maxilla']['leaves']:,} / {b['mandible']['leaves']:,}; distance {row['methods']['distance']['median_us']:.1f} µs, "
          f"backtracking {row['methods']['backtracking']['median_us']:.1f} µs, coal {row['coal']['median_us']:.0f} µs", flush=True)
    return row


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = [np.mean(r["vertices"]) for r in rows]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.3))
    ax[0].loglog(v, [r["builds"]["mandible"]["wall"] for r in rows], "o-", label="IST build (mandible)")
    ax[0].loglog(v, [r["builds"]["mandible"]["coal_bvh_s"] for r in rows], "s--", label="coal BVH build (mandible)")
    ax[0].set(xlabel="vertices per jaw", ylabel="s", title="build time vs mesh size")
    ax[1].loglog(v, [r["methods"]["distance"]["median_us"] for r in rows], "o-", label="IST distance")
    ax[1].loglog(v, [r["methods"]["backtracking"]["median_us"] for r in rows], "o-", label="IST backtracking")
    ax[1].loglog(v, [r["coal"]["median_us"] for r in rows], "s--", color="k", label="coal exact distance")
    ax[1].set(xlabel="vertices per jaw", ylabel="median µs per frame", title="query time vs mesh size")
    ax[2].semilogx(v, [r["builds"]["mandible"]["leaves"] for r in rows], "o-", label="leaves (mandible)")
    ax2 = ax[2].twinx()
    ax2.semilogx(v, [r["builds"]["mandible"]["peak_rss_mb"] for r in rows], "s--", color="C1", label="peak RSS MB")
    ax[2].set(xlabel="vertices per jaw", ylabel="leaves", title="leaves and memory vs mesh size")
    ax[2].set_ylim(bottom=0)
    ax2.set_ylabel("peak RSS (MB)")
    ax2.set_ylim(bottom=0)
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8, loc="upper left")
    ax2.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(rows, meta) -> str:
    L = [f"Scaling with mesh size (procedural jaw pair at several grid spacings; max_error {meta['max_error'] * 1e3:g} mm; "
         f"{meta['frames']} frames; {meta['machine']}; command `{meta['command']}`, {meta['seconds']:.0f} s).", "",
         "| spacing mm | vertices (maxilla / mandible) | build s | peak RSS MB | leaves | ε_A+ε_B mm | coverage | coal BVH s "
         "| distance µs | backtracking µs | coal µs | × coal | max err mm | bound viol. |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = r["builds"]
        d = r["methods"]["distance"]
        L.append(f"| {r['spacing_mm']:g} | {r['vertices'][0]:,} / {r['vertices'][1]:,} | {b['maxilla']['wall']:.1f} + {b['mandible']['wall']:.1f} "
                 f"| {max(x['peak_rss_mb'] for x in b.values()):.0f} | {b['maxilla']['leaves']:,} / {b['mandible']['leaves']:,} "
                 f"| {r['error_bound'] * 1e3:.3f} | {100 * b['maxilla']['coverage']:.0f} / {100 * b['mandible']['coverage']:.0f} % "
                 f"| {b['maxilla']['coal_bvh_s'] + b['mandible']['coal_bvh_s']:.2f} | {d['median_us']:.1f} "
                 f"| {r['methods']['backtracking']['median_us']:.1f} | {r['coal']['median_us']:.0f} "
                 f"| {r['coal']['median_us'] / d['median_us']:.0f} | {d['err_max'] * 1e3:.3f} "
                 f"| {d['bound_violations'] + r['methods']['backtracking']['bound_violations']} |")
    return "\n".join(L) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 resolutions (~10k and ~40k vertices), ε 1 mm, 200 frames")
    ap.add_argument("--out", default=str(ROOT / "out"))
    ap.add_argument("--timeout", type=float, default=900.0, help="per build (s)")
    a = ap.parse_args(argv)
    cfg = QUICK if a.quick else FULL
    out = Path(a.out)
    work = out / "scaling"
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = [run_resolution(s, cfg, work, a.timeout) for s in cfg["spacings"]]
    meta = {**cfg, "seconds": time.perf_counter() - t0,
            "command": "python scripts/bench_scaling.py" + (" --quick" if a.quick else ""),
            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"}
    write_outputs(out, "bench_scaling", {"meta": meta, "rows": rows}, lambda path: plot(rows, path), markdown(rows, meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
