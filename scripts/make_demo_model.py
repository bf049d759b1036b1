"""Write models/molar.stl: a procedural molar crown (non-convex, cusps and a central fossa).

A stand-in test object until the procedural jaw models land. Units: metres (crown ~10 mm).
Deterministic: the same script always writes the same file.

    python scripts/make_demo_model.py
"""
from pathlib import Path

import numpy as np
import trimesh


def molar() -> trimesh.Trimesh:
    body = trimesh.creation.cylinder(radius=0.0045, height=0.006, sections=64)
    body.apply_translation([0, 0, 0.0])
    root = trimesh.creation.cone(radius=0.0035, height=0.008, sections=64)
    root.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
    root.apply_translation([0, 0, -0.003])
    parts = [body, root]
    for ang in np.deg2rad([45, 135, 225, 315]):
        cusp = trimesh.creation.icosphere(subdivisions=4, radius=0.0022)
        cusp.apply_translation([0.0026 * np.cos(ang), 0.0026 * np.sin(ang), 0.0032])
        parts.append(cusp)
    crown = trimesh.boolean.union(parts, engine="manifold")
    fossa = trimesh.creation.icosphere(subdivisions=4, radius=0.0016)
    fossa.apply_translation([0, 0, 0.0046])
    return trimesh.boolean.difference([crown, fossa], engine="manifold")


if __name__ == "__main__":
    m = molar()
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    out = Path(__file__).resolve().parent.parent / "models" / "molar.stl"
    m.export(out)
    print(f"wrote {out}: {len(m.vertices)} vertices, {len(m.faces)} faces, volume {m.volume:.3e} m^3")
