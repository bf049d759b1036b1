"""Regenerate the bundled jaw models: models/maxilla.obj, models/mandible.obj, models/occlusion.json.

    python scripts/make_jaws.py            # then: MUJOCO_GL=egl python scripts/render_jaws.py
    python scripts/make_jaws.py --trees    # only models/trees: the closure scene's prebuilt trees

``--trees`` (also done after regenerating the meshes) rebuilds the trees, exit directions and
surface grids the bundled closure scene attaches with into ``models/trees``; they ship in the wheel so that a new
user's first ``mjist demo`` loads them (``mjist.cache.prebuilt_folders``). Rerun it whenever the
builder or the tree format changes: a test says when they no longer match.

Deterministic: the same mjist version writes the same files (see mjist/jaw/generator.py for the design).
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from mjist.jaw import generator as jawmodel
from mjist.jaw import pair as jaw

ROOT = Path(__file__).resolve().parent.parent


def write(out: Path, spacing: float = jawmodel.DEFAULT_SPACING) -> dict:
    maxilla, mandible, meta = jawmodel.generate(spacing)
    out.mkdir(parents=True, exist_ok=True)
    for name, m in (("maxilla", maxilla), ("mandible", mandible)):
        (out / f"{name}.obj").write_text(m.export(file_type="obj", digits=9, include_normals=False, include_texture=False))
    # the measured state of the ground-truth pose, for the record
    bx = jaw.coal_bvh(maxilla.vertices, maxilla.faces)
    bd = jaw.coal_bvh(mandible.vertices, mandible.faces)
    I = np.eye(4)
    meta.update({
        "maxilla_pose": I.tolist(),
        "mandible_pose": I.tolist(),
        "ground_truth": "centric occlusion: the design pose, teeth touching at the designed contacts",
        "coal_distance_at_ground_truth_m": float(jaw.coal_distance(bx, I, bd, I)),
        "vertices": {"maxilla": int(len(maxilla.vertices)), "mandible": int(len(mandible.vertices))},
        "shells": {"maxilla": int(maxilla.body_count), "mandible": int(mandible.body_count)},
    })
    (out / "occlusion.json").write_text(json.dumps(meta, indent=1) + "\n")
    return meta


def write_trees(models: Path) -> list[str]:
    """The bundled closure scene's trees, exit directions and surface grids, built afresh into
    ``models/trees``."""
    import mujoco

    import mjist
    from mjist import cache

    cache.PREBUILT = []  # build them, do not find the old ones
    with tempfile.TemporaryDirectory() as tmp:
        model = mujoco.MjModel.from_xml_path(str(models / "jaw_closure.xml"))
        mjist.attach(model, cache_dir=tmp, narrowphase="surface").detach()  # the demo's: with the grids
        out = models / "trees"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir()
        names = sorted(p.name for p in Path(tmp).iterdir())
        for name in names:
            shutil.copyfile(Path(tmp) / name, out / name)
    return names


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "models"))
    ap.add_argument("--spacing", type=float, default=jawmodel.DEFAULT_SPACING, help="marching-cubes spacing, mm")
    ap.add_argument("--trees", action="store_true", help="only rebuild the prebuilt trees of the closure scene")
    a = ap.parse_args()
    if not a.trees:
        meta = write(Path(a.out), a.spacing)
        print(json.dumps({k: meta[k] for k in ("vertices", "shells", "coal_distance_at_ground_truth_m", "hinge")}, indent=1))
    print("prebuilt:", ", ".join(write_trees(Path(a.out))))


if __name__ == "__main__":
    main()
