"""Where one build's time goes: the pipeline's stages per lattice level (a diagnostic, not a benchmark).

    python scripts/profile_build.py ../shared/data/jaw/mandible.obj --max-error 5e-5 --out out/profile_mandible.json

The pipeline times its own stages (``mjist.builder.pipeline``): per level ``certify`` (which
triangles are still open, the level's seeds), ``voxelize`` (the band's lattice points and
their free distances) and ``pack``; after the levels ``hierarchy`` and ``bound``. This runs
one build, prints a table and writes JSON with the totals, the per-level seconds and the
tree's figures. Compare runs in one window: this machine's timings vary between windows.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import mjist

STAGES = ("certify", "voxelize", "pack")


def profile(mesh, max_error: float) -> dict:
    t = time.perf_counter()
    tree = mjist.build(mesh, max_error=max_error)
    wall = time.perf_counter() - t
    per_level = {str(lv["level"]): {s: round(lv.get(f"{s}_seconds", 0.0), 6) for s in STAGES}
                 for lv in tree.info["levels"]}
    return {
        "mesh": str(mesh), "max_error": max_error, "wall_s": wall, "stage_s": tree.timings,
        "leaves": tree.num_leaves, "error_bound": tree.error_bound, "coverage": tree.coverage,
        "builder_version": tree.info["builder_version"], "per_level_s": per_level, "levels": tree.info["levels"],
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
    print("level " + " ".join(f"{c:>12}" for c in STAGES))
    for lv, row in res["per_level_s"].items():
        print(f"{lv:>5} " + " ".join(f"{row.get(c, 0.0):12.2f}" for c in STAGES))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1))
        print("wrote", args.out)


if __name__ == "__main__":
    main()
