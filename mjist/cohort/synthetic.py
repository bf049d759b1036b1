"""A synthetic cohort whose answers are known: procedural jaw pairs with their designed occlusion.

Each patient is ``generator.generate`` of an ``Anatomy`` drawn from a seeded distribution
(patient 0 is the bundled design): arch width and depth ±8 %, crown size ±6 %, crowding in
half the patients, class I (60 %), II or III (20 % each) with a 1.5–3.5 mm shift, a posterior
crossbite on one side in 30 %, one missing premolar or molar in 30 %. The pair is written in
the jaw frame (metres, +y up) as ``maxilla.obj`` and ``mandible.obj``, with ``design.json``: the
anatomy, the designed mandible pose (the files' own), the hinge, and how far coal says the
polygonised jaws sit from first touch at that pose (marching cubes moves the surfaces by a
few µm at 0.5 mm spacing). ``design.json`` is not ``occlusion.json``: the cohort loads each
pair as a user's scan (occlusion from coal's first touch along up) and only scores the search
against the design afterwards.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..jaw import generator

DESIGN_FILE = "design.json"


def anatomy(seed: int, index: int) -> generator.Anatomy:
    """Patient ``index`` of the synthetic cohort ``seed`` (patient 0: the bundled design)."""
    if index == 0:
        return generator.Anatomy()
    rng = np.random.default_rng([seed, index])
    u = lambda a, b: float(round(rng.uniform(a, b), 3))
    kind = rng.choice(3, p=[0.6, 0.2, 0.2])
    shift = [u(-0.5, 0.5), u(1.5, 3.5), -u(1.5, 3.5)][kind]
    crossbite = str(rng.choice(["none", "left", "right"], p=[0.7, 0.15, 0.15]))
    missing = ()
    if rng.uniform() < 0.3:
        missing = ((str(rng.choice(["maxilla", "mandible"])), str(rng.choice(generator.SIDES)), int(rng.integers(3, 7))),)
    return generator.Anatomy(arch_width=u(0.92, 1.08), arch_depth=u(0.92, 1.08), tooth_size=u(0.94, 1.06),
                             crowding=u(0.3, 1.5) if rng.uniform() < 0.5 else 0.0, class_shift=shift,
                             crossbite=crossbite, missing=missing)


def patient_name(index: int) -> str:
    return f"synthetic-{index:04d}"


def write_patient(folder, anat: generator.Anatomy, spacing: float = generator.DEFAULT_SPACING) -> dict:
    """Generate one pair into ``folder``; ``design.json`` is written last (its presence means done)."""
    from ..jaw.pair import coal_bvh, touching_offset

    folder = Path(folder)
    os.makedirs(folder, exist_ok=True)
    maxilla, mandible, meta = generator.generate(spacing, anat)
    for name, m in (("maxilla", maxilla), ("mandible", mandible)):
        m.export(folder / f"{name}.obj")
    touch = touching_offset(coal_bvh(maxilla.vertices, maxilla.faces), coal_bvh(mandible.vertices, mandible.faces))
    design = {"anatomy": anat.as_dict(), "mandible_pose": np.eye(4).tolist(), "hinge": meta["hinge"],
              "designed_contacts": meta["designed_contacts"], "teeth_per_jaw": meta["teeth_per_jaw"],
              "spacing_mm": spacing, "first_touch_from_design_mm": touch * 1e3,
              "frame": meta["frame"], "units": meta["units"]}
    tmp = folder / f"{DESIGN_FILE}.tmp"
    tmp.write_text(json.dumps(design, indent=1))
    os.replace(tmp, folder / DESIGN_FILE)
    return design


def generated(folder) -> bool:
    return (Path(folder) / DESIGN_FILE).exists()
