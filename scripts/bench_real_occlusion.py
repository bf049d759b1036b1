"""Real occlusions: does the default occlusion search find where real teeth meet?

    python scripts/bench_real_occlusion.py [--seeds 5] [--variants stored,teeth,open,free,bundled] [--out out/bench_real_occlusion]

The shared CBCT pair (``../shared/data/jaw``, stored in occlusion) three ways, as users bring it:

* ``stored``: the files as they are (metres, +y up, condyles and fossae);
* ``teeth``: converted to millimetres with +z up and cropped 9 mm either side of the occlusal
  level (no condyles, rami or fossae; exact half-space cuts with manifold3d);
* ``open``: the stored mandible turned 8° open about its detected hinge and moved 1 mm forward
  before the search (the search must not need the stored pose to be the answer; the condyles'
  seat is then sampled, ``arch.SEAT_UNCERTAINTY``);
* ``free``: as stored, but searched as if given open (the condyles' seat sampled as for
  ``open``): where the teeth alone put the occlusion;

plus the bundled pair (its designed occlusion). Every search runs with default settings
(``occlusion.search(data=FOLDER, seed=s)`` around the pose the files give, ``--given-pose``; the
registration from the arches' shapes is ``scripts/bench_any_start.py``'s), one per seed. The reference is the stored
occlusion (for the shared pair: the stored mandible moved along up to coal's first touch; for
``open``, the same pose of the un-opened mandible). Per search: the best candidate's error
(largest tooth-point shift, rotation), the rank of the first candidate within 0.3 mm / 0.5°,
the Spearman rank correlation of score against error over all settled starts (negative: a
better score, a smaller error), how sure the search said it was, and the time (trees cached).
Writes ``OUT.json``, ``OUT.md`` and ``OUT.png``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))
SHARED = ROOT.parent / "shared" / "data" / "jaw"
TARGET_MM, TARGET_DEG = 0.3, 0.5
OPEN_DEG, OPEN_FORWARD = 8.0, 1e-3
SEAT = 2e-3  # the condyles' seat range of a pair given open (mjist.jaw.arch.SEAT_UNCERTAINTY)


def make_variants(out: Path) -> dict:
    """The shared pair's variants in ``out/<name>/``: {name: (folder, D)} with ``D`` the 4x4 jaw-frame
    move from the scene's reference keyframe to the stored occlusion (identity when they agree)."""
    import trimesh
    from byo_jaws import TO_FILE, _crop, _load

    from mjist.jaw.pair import hinge_point, load_pair

    mx, md = _load(SHARED / "maxilla.obj"), _load(SHARED / "mandible.obj")
    _, _, info = load_pair(SHARED)
    stored = info["mandible_pose"]
    md_occ = md.copy()
    md_occ.apply_transform(stored)
    y0 = float(info["arches"]["mandible"].origin[1])
    S = np.eye(4)
    S[:3, :3] = 1000.0 * TO_FILE
    out_dirs = {"stored": (SHARED, np.eye(4)), "free": (SHARED, np.eye(4), {"seat": SEAT})}
    teeth = out / "teeth"
    os.makedirs(teeth, exist_ok=True)
    for name, m in (("maxilla", _crop(mx, y0 + 9e-3, y0 - 9e-3, -1.0)), ("mandible", _crop(md_occ, y0 + 9e-3, y0 - 9e-3, -1.0))):
        c = m.copy()
        c.apply_transform(S)
        c.export(teeth / f"{name}.stl")
    out_dirs["teeth"] = (teeth, np.eye(4))
    h = hinge_point(md.vertices)
    a = np.radians(OPEN_DEG)
    O = np.eye(4)
    O[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
    O[:3, 3] = h - O[:3, :3] @ h + np.array([0.0, 0.0, OPEN_FORWARD])
    opened = out / "open"
    os.makedirs(opened, exist_ok=True)
    trimesh.Trimesh(mx.vertices, mx.faces, process=False).export(opened / "maxilla.obj")
    mo = md.copy()
    mo.apply_transform(O)
    mo.export(opened / "mandible.obj")
    try:
        _, _, info_o = load_pair(opened)
        # the opened mesh's true occlusion is stored · O⁻¹; the scene's keyframe holds it at info_o's pose
        out_dirs["open"] = (opened, stored @ np.linalg.inv(O) @ np.linalg.inv(info_o["mandible_pose"]))
    except ValueError as exc:  # mjist refuses the pair: the search is not run, the refusal is reported
        out_dirs["open"] = (opened, exc)
    return out_dirs


def true_reference(pair, D):
    """Mandible body pose (pos, quat) at the stored occlusion: the keyframe moved by ``D`` (jaw frame)."""
    from mjist.jaw.scenepair import JAW_TO_WORLD

    W = np.eye(4)
    W[:3, :3] = JAW_TO_WORLD
    return pair.body(W @ D @ np.linalg.inv(W) @ pair.reference)


def run_one(folder, D, seed: int, out: Path, **kw) -> dict:
    from mjist.jaw import occlusion

    if isinstance(D, Exception):
        raise D
    t = time.perf_counter()
    # around the pose the files give (--given-pose): scripts/bench_any_start.py measures the registration
    pair = None if folder is None else {"register": False}
    res = occlusion.search(data=None if folder is None else folder, seed=seed, progress=False, out_dir=out, pair=pair, **kw)
    wall = time.perf_counter() - t
    try:
        jp = res["_pair"]
        ref = true_reference(jp, D)
        pts = jp.sample.mandible_points
        errs = [occlusion.pose_error(jp, c["pos"], c["quat"], *ref, points=pts) for c in res["candidates"]]
        land = [dict(x, error=occlusion.pose_error(jp, x["pos"], x["quat"], *ref, points=pts)) for x in res["landscape"]]
        ok = [e["max_mm"] <= TARGET_MM and e["rotation_deg"] <= TARGET_DEG for e in errs]
        best = res["candidates"][0]
        return {"seed": seed, "best_max_mm": errs[0]["max_mm"], "best_rms_mm": errs[0]["rms_mm"],
                "best_rotation_deg": errs[0]["rotation_deg"], "best_starts": best["starts"],
                "right_basin_rank": ok.index(True) + 1 if any(ok) else None,
                "rank_correlation": occlusion.rank_correlation(land), "confidence": res["confidence"],
                "settled": res["settled"], "starts": res["starts"], "search_s": res["total_s"], "wall_s": wall,
                "coal_gap_mm": best["coal_distance_mm"], "errors": errs}
    finally:
        res["_handle"].detach()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--variants", default="stored,teeth,open,free,bundled")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_real_occlusion"))
    a = ap.parse_args(argv)
    out = Path(a.out)
    os.makedirs(out, exist_ok=True)
    wanted = a.variants.split(",")
    variants = {}
    if set(wanted) - {"bundled"}:
        if not SHARED.exists():
            print(f"{SHARED} is absent: only the bundled pair is measured")
        else:
            variants = make_variants(out / "variants")
    if "bundled" in wanted:
        variants["bundled"] = (None, np.eye(4))
    rows = {}
    for name in wanted:
        if name not in variants:
            continue
        folder, D, *kw = variants[name]
        rows[name] = []
        for seed in range(a.seeds):
            try:
                r = run_one(folder, D, seed, out / "runs" / f"{name}_{seed}", **(kw[0] if kw else {}))
            except Exception as exc:  # a refused pair is a finding, not the end of the benchmark
                print(f"{name:8s} seed {seed}: FAILED {type(exc).__name__}: {exc}", flush=True)
                rows[name].append({"seed": seed, "failed": f"{type(exc).__name__}: {exc}"})
                continue
            rows[name].append(r)
            c = r["confidence"]
            print(f"{name:8s} seed {seed}: best {r['best_max_mm']:.3f} mm / {r['best_rotation_deg']:.3f}° ({r['best_starts']} starts), "
                  f"right basin #{r['right_basin_rank']}, rank corr {r['rank_correlation']:+.2f}, margin "
                  f"{c.get('margin_mm') or 0:.4f} mm{' AMBIGUOUS' if c.get('ambiguous') else ''}, {r['settled']}/{r['starts']} settled, "
                  f"{r['search_s']:.1f} s", flush=True)
    (out.with_suffix(".json")).write_text(json.dumps(rows, indent=1))
    md = ["| pair | seeds within 0.3 mm / 0.5° | best: largest tooth-point shift (median, worst) | rotation (worst) | "
          "right basin's rank (worst) | rank correlation score–error (median, worst) | ambiguous | search s (median) |",
          "|---|---|---|---|---|---|---|---|"]
    for name, rs in rows.items():
        failed = [r for r in rs if "failed" in r]
        rs = [r for r in rs if "failed" not in r]
        if not rs:
            md.append(f"| {name} | 0/{len(failed)}: {failed[0]['failed'][:160]} | | | | | | |")
            continue
        mx = [r["best_max_mm"] for r in rs]
        rot = [r["best_rotation_deg"] for r in rs]
        rc = [r["rank_correlation"] for r in rs if r["rank_correlation"] is not None]
        ranks = [r["right_basin_rank"] for r in rs]
        within = sum(1 for r in rs if r["best_max_mm"] <= TARGET_MM and r["best_rotation_deg"] <= TARGET_DEG)
        md.append(f"| {name} | {within}/{len(rs) + len(failed)} | {np.median(mx):.3f}, {max(mx):.3f} mm | {max(rot):.3f}° | "
                  f"{'none' if None in ranks else max(ranks)} | {np.median(rc):+.2f}, {max(rc):+.2f} | "
                  f"{sum(1 for r in rs if r['confidence'].get('ambiguous'))} | {np.median([r['search_s'] for r in rs]):.1f} |")
    out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    for k, (name, rs) in enumerate(rows.items()):
        rs = [r for r in rs if "failed" not in r]
        ax.scatter(np.full(len(rs), k) + np.linspace(-0.15, 0.15, len(rs)), [r["best_max_mm"] for r in rs], label=name)
    ax.axhline(TARGET_MM, color="k", lw=0.8, ls="--")
    ax.set_xticks(range(len(rows)), list(rows))
    ax.set_ylabel("best candidate: largest tooth-point shift (mm)")
    ax.set_title("occlusion search against the stored occlusion, one dot per seed")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main())
