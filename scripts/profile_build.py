"""Where one build's time goes: every stage function timed per lattice level (a diagnostic, not a benchmark).

    python scripts/profile_build.py ../shared/data/jaw/mandible.obj --max-error 5e-5 --out out/profile_mandible.json

Wraps the functions ``mjist.build`` calls per level (certification, band keys, band free
distances, grown packing, final bound) with timers and runs one build; prints a table and writes
JSON with the totals, the per-level seconds and the tree's figures. A level's certification is
the one that finds its seeds (it runs before that level's band). Compare runs in one window:
this machine's timings vary ±15 % between windows.
"""
from __future__ import annotations

import argparse
import collections
import importlib
import json
import time
from pathlib import Path

import mjist
from mjist import voxelize

B = importlib.import_module("mjist.build")
STAGES = ("certify_faces", "band_free_distance", "grown_pack", "tight_bound", "surface_gaps")


def profile(mesh, max_error: float) -> dict:
    seconds: dict = collections.defaultdict(float)
    level = [0]
    saved = {name: getattr(B, name) for name in STAGES}
    saved_keys = voxelize.Voxelizer.band_keys

    def timed(name, fn):
        def run(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                # certification runs before its level's band: it belongs to the next level
                lv = level[0] + 1 if name == "certify_faces" else level[0]
                seconds[(lv, name)] += time.perf_counter() - t
        return run

    def band_keys(self, lv, *a, **k):
        level[0] = lv
        t = time.perf_counter()
        try:
            return saved_keys(self, lv, *a, **k)
        finally:
            seconds[(lv, "band_keys")] += time.perf_counter() - t

    for name in STAGES:
        setattr(B, name, timed(name, saved[name]))
    voxelize.Voxelizer.band_keys = band_keys
    try:
        t = time.perf_counter()
        tree = mjist.build(mesh, max_error=max_error)
        wall = time.perf_counter() - t
    finally:
        for name, fn in saved.items():
            setattr(B, name, fn)
        voxelize.Voxelizer.band_keys = saved_keys
    per_level: dict = collections.defaultdict(dict)
    for (lv, name), s in sorted(seconds.items()):
        per_level[lv][name] = round(s, 3)
    return {
        "mesh": str(mesh), "max_error": max_error, "wall_s": wall, "stage_s": tree.timings,
        "leaves": tree.num_leaves, "error_bound": tree.error_bound, "coverage": tree.coverage,
        "builder_version": tree.info["builder_version"], "per_level_s": {str(k): v for k, v in per_level.items()},
        "levels": tree.info["levels"],
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("--max-error", type=float, required=True, help="mesh units (metres for the CBCT jaws: 5e-5)")
    ap.add_argument("--out", type=Path, help="JSON file to write")
    args = ap.parse_args(argv)
    res = profile(args.mesh, args.max_error)
    print(f"{args.mesh}: {res['wall_s']:.1f} s, {res['leaves']} leaves, ε {res['error_bound']:.4g}, "
          f"coverage {res['coverage']:.1%}, builder {res['builder_version']}")
    print("stages:", {k: round(v, 2) for k, v in res["stage_s"].items()})
    cols = ("certify_faces", "band_keys", "band_free_distance", "grown_pack")
    print("level " + " ".join(f"{c:>18}" for c in cols))
    for lv, row in res["per_level_s"].items():
        print(f"{lv:>5} " + " ".join(f"{row.get(c, 0.0):18.2f}" for c in cols))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1))
        print("wrote", args.out)


if __name__ == "__main__":
    main()
