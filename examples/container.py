"""Objects dropped into a non-convex container: IST contacts against MuJoCo's own.

    python examples/container.py            # prints where each object settles and the step time

An open cup (a box with a box cut out of its top, made with manifold3d through trimesh) sits
on the ground; three small mesh objects fall into it. MuJoCo collides mesh geoms as their
convex hulls, and the hull of a cup is a closed box: the objects come to rest on an invisible
lid. With ``mjist.load_model`` the same scene gets Inner Sphere Tree contacts and the objects
land on the cup's floor. MuJoCo's mesh-SDF geoms (``type="sdf"``) also get there, at a higher
cost per step.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np
import trimesh

OUTER = (0.10, 0.10, 0.06)  # cup outside, metres
WALL = 0.01  # wall and floor thickness
OBJECTS = (("ball_a", "ball", (-0.02, -0.015, 0.08)), ("ball_b", "ball", (0.018, 0.02, 0.11)),
           ("block", "block", (0.0, 0.0, 0.14)))


def write_meshes(folder) -> dict[str, str]:
    """The cup (one closed, non-convex shell) and the objects' meshes as OBJ files."""
    outer = trimesh.creation.box(OUTER)
    inner = trimesh.creation.box((OUTER[0] - 2 * WALL, OUTER[1] - 2 * WALL, OUTER[2]))
    inner.apply_translation((0.0, 0.0, WALL))
    cup = outer.difference(inner, engine="manifold")
    cup.apply_translation((0.0, 0.0, OUTER[2] / 2))  # standing on the ground
    meshes = {"cup": cup, "ball": trimesh.creation.icosphere(3, radius=0.012),
              "block": trimesh.creation.box((0.03, 0.02, 0.015))}
    paths = {}
    for name, m in meshes.items():
        paths[name] = os.path.join(folder, f"{name}.obj")
        m.export(paths[name])
    return paths


def scene_xml(paths: dict[str, str], geom_type: str = "mesh") -> str:
    """The drop scene; ``geom_type="sdf"`` makes every mesh an sdf geom (MuJoCo's mesh-SDF)."""
    sdf = ' <option sdf_iterations="10" sdf_initpoints="40"/>' if geom_type == "sdf" else ""
    bodies = "\n".join(
        f'    <body name="{name}" pos="{x} {y} {z}"><freejoint/>'
        f'<geom name="{name}" type="{geom_type}" mesh="{mesh}" rgba=".3 .5 .8 1"/></body>'
        for name, mesh, (x, y, z) in OBJECTS)
    return f"""<mujoco model="container">
  <option timestep="0.001"/>{sdf}
  <default><geom solref="0.004 1"/></default>
  <asset>
    <mesh name="cup" file="{paths['cup']}"/>
    <mesh name="ball" file="{paths['ball']}"/>
    <mesh name="block" file="{paths['block']}"/>
  </asset>
  <worldbody>
    <light pos="0 0 1"/>
    <geom name="ground" type="plane" size=".3 .3 .01"/>
    <geom name="cup" type="{geom_type}" mesh="cup" rgba=".8 .8 .8 1"/>
{bodies}
  </worldbody>
</mujoco>
"""


def drop(model, seconds: float = 1.0) -> dict:
    """Let the objects fall; their final heights (m) and the median step time (µs)."""
    d = mujoco.MjData(model)
    n = int(round(seconds / model.opt.timestep))
    times = np.empty(n)
    for i in range(n):
        t = time.perf_counter()
        mujoco.mj_step(model, d)
        times[i] = time.perf_counter() - t
    where = {name: _where(d.body(name).xpos) for name, _, _ in OBJECTS}
    heights = {name: float(d.body(name).xpos[2]) for name, _, _ in OBJECTS}
    return {"where": where, "heights_m": heights, "step_us_median": float(np.median(times) * 1e6)}


def _where(p) -> str:
    """'in the cup' (between its walls, below the rim), 'on the lid' (above the rim, over the
    cup) or 'outside'."""
    half = 0.5 * OUTER[0]
    over = abs(p[0]) < half and abs(p[1]) < half
    if over and p[2] > OUTER[2]:
        return "on the lid"
    inner = half - WALL
    return "in the cup" if abs(p[0]) < inner and abs(p[1]) < inner and p[2] < OUTER[2] else "outside"


def run(folder=None, seconds: float = 1.0) -> dict:
    """The drop with IST contacts, MuJoCo's convex hulls and MuJoCo's mesh-SDF."""
    import mjist

    folder = folder or tempfile.mkdtemp(prefix="mjist-container-")
    paths = write_meshes(folder)
    xml = Path(folder) / "container.xml"
    xml.write_text(scene_xml(paths))
    sdf_xml = Path(folder) / "container_sdf.xml"
    sdf_xml.write_text(scene_xml(paths, "sdf"))
    out = {}
    model, handle = mjist.load_model(xml)
    try:
        out["ist"] = drop(model, seconds)
        out["ist"]["error_bound_mm"] = max(p.error_bound for p in handle.pairs) * 1e3
    finally:
        handle.detach()
    out["native hull"] = drop(mujoco.MjModel.from_xml_path(str(xml)), seconds)
    out["native mesh-SDF"] = drop(mujoco.MjModel.from_xml_path(str(sdf_xml)), seconds)
    return out


def main() -> int:
    res = run()
    for mode, r in res.items():
        objs = ", ".join(f"{k} {r['where'][k]} (z {1e3 * v:.0f} mm)" for k, v in r["heights_m"].items())
        print(f"{mode:16s} {r['step_us_median']:8.1f} µs/step   {objs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
