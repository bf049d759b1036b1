"""Objects dropped into a non-convex container at MuJoCo's defaults: IST contacts against MuJoCo's own.

    python examples/container.py            # where each object settles, how fast, and the step time

A round cup (50 mm radius, 60 mm tall, 6 mm walls, 10 mm floor: one closed mesh made with
manifold3d through trimesh) stands on the ground; a ball, a capsule and a box, all meshes, fall
into it from 6-10 cm. The scene sets nothing: MuJoCo's default timestep (2 ms), ``solref`` and
``solimp``, as a user starts. Those contacts are soft: a falling object sinks several
millimetres into the floor before it is stopped, past the middle of a thin wall, and contacts
must still push it back out of the side it came in by.

MuJoCo collides mesh geoms as their convex hulls, and the hull of a cup is a closed cylinder:
the objects come to rest on an invisible lid. With ``mjist.load_model`` the same scene gets
Inner Sphere Tree contacts and the objects land on the cup's floor, with sphere contacts (the
default) and with contacts on the true surfaces (``narrowphase="surface"``). MuJoCo's mesh-SDF
geoms (``type="sdf"``) also get there, at a higher cost per step.
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

RADIUS, HEIGHT = 0.05, 0.06  # cup outside, metres
WALL, FLOOR = 0.006, 0.01
# name, mesh, start position, start orientation (euler, degrees): lying flat, apart from each other
OBJECTS = (("ball", "ball", (-0.02, 0.0, 0.06), (0, 0, 0)),
           ("capsule", "capsule", (0.015, 0.015, 0.08), (0, 90, 0)),
           ("box", "box", (0.01, -0.02, 0.10), (0, 0, 0)))
REST_HEIGHT = {"ball": FLOOR + 0.01, "capsule": FLOOR + 0.006, "box": FLOOR + 0.006}  # centre above the ground


def write_meshes(folder) -> dict[str, str]:
    """The cup (one closed, non-convex shell) and the objects' meshes as OBJ files."""
    outer = trimesh.creation.cylinder(radius=RADIUS, height=HEIGHT, sections=64)
    inner = trimesh.creation.cylinder(radius=RADIUS - WALL, height=HEIGHT, sections=64)
    inner.apply_translation((0.0, 0.0, FLOOR))
    cup = outer.difference(inner, engine="manifold")
    cup.apply_translation((0.0, 0.0, HEIGHT / 2))  # standing on the ground
    meshes = {"cup": cup, "ball": trimesh.creation.icosphere(3, radius=0.01),
              "capsule": trimesh.creation.capsule(height=0.02, radius=0.006),
              "box": trimesh.creation.box((0.02, 0.015, 0.012))}
    paths = {}
    for name, m in meshes.items():
        paths[name] = os.path.join(folder, f"{name}.obj")
        m.export(paths[name])
    return paths


def scene_xml(paths: dict[str, str], geom_type: str = "mesh") -> str:
    """The drop scene; ``geom_type="sdf"`` makes every mesh an sdf geom (MuJoCo's mesh-SDF).
    No ``<option>`` or ``<default>``: MuJoCo's defaults."""
    sdf = '\n  <option sdf_iterations="10" sdf_initpoints="40"/>' if geom_type == "sdf" else ""
    bodies = "\n".join(
        f'    <body name="{name}" pos="{x} {y} {z}" euler="{" ".join(map(str, e))}"><freejoint/>'
        f'<geom name="{name}" type="{geom_type}" mesh="{mesh}" rgba=".3 .5 .8 1"/></body>'
        for name, mesh, (x, y, z), e in OBJECTS)
    assets = "\n".join(f'    <mesh name="{k}" file="{paths[k]}"/>' for k in ("cup", "ball", "capsule", "box"))
    return f"""<mujoco model="container">{sdf}
  <asset>
{assets}
  </asset>
  <worldbody>
    <light pos="0 0 1"/>
    <geom name="ground" type="plane" size=".3 .3 .01"/>
    <geom name="cup" type="{geom_type}" mesh="cup" rgba=".8 .8 .8 1"/>
{bodies}
  </worldbody>
</mujoco>
"""


def drop(model, seconds: float = 1.5) -> dict:
    """Let the objects fall: each one's final position (m), where that is, its speed over the
    last 0.1 s (m/s), how deep it sank below its resting height on the way; the median step (µs)."""
    d = mujoco.MjData(model)
    n = int(round(seconds / model.opt.timestep))
    times = np.empty(n)
    low = {name: np.inf for name, *_ in OBJECTS}
    tail = max(1, int(round(0.1 / model.opt.timestep)))
    before = {}
    for i in range(n):
        if i == n - tail:
            before = {name: d.body(name).xpos.copy() for name, *_ in OBJECTS}
        t = time.perf_counter()
        mujoco.mj_step(model, d)
        times[i] = time.perf_counter() - t
        for name in low:
            low[name] = min(low[name], float(d.body(name).xpos[2]))
    out = {"objects": {}, "step_us_median": float(np.median(times) * 1e6)}
    for name, *_ in OBJECTS:
        p = d.body(name).xpos.copy()
        out["objects"][name] = {"pos_m": p.tolist(), "where": _where(p),
                                "speed_m_s": float(np.linalg.norm(p - before[name]) / (tail * model.opt.timestep)),
                                "sank_mm": float((REST_HEIGHT[name] - low[name]) * 1e3)}
    return out


def _where(p) -> str:
    """'in the cup' (inside its wall, below the rim, above the floor's middle), 'on the lid' (above
    the rim, over the cup) or 'outside' (fell through, or out)."""
    r = float(np.hypot(p[0], p[1]))
    if r < RADIUS and p[2] > HEIGHT:
        return "on the lid"
    return "in the cup" if r < RADIUS - WALL and FLOOR / 2 < p[2] < HEIGHT else "outside"


def run(folder=None, seconds: float = 1.5) -> dict:
    """The drop with IST contacts (sphere contacts, ``mjist.load_model``'s default, and
    ``narrowphase="surface"``), MuJoCo's convex hulls and MuJoCo's mesh-SDF."""
    import mjist

    folder = folder or tempfile.mkdtemp(prefix="mjist-container-")
    paths = write_meshes(folder)
    xml = Path(folder) / "container.xml"
    xml.write_text(scene_xml(paths))
    sdf_xml = Path(folder) / "container_sdf.xml"
    sdf_xml.write_text(scene_xml(paths, "sdf"))
    out = {}
    for mode, narrowphase in (("ist", "spheres"), ("ist surface", "surface")):
        model, handle = mjist.load_model(xml, narrowphase=narrowphase)
        try:
            out[mode] = drop(model, seconds)
            out[mode]["error_bound_mm"] = max(p.error_bound for p in handle.pairs) * 1e3
        finally:
            handle.detach()
    out["native hull"] = drop(mujoco.MjModel.from_xml_path(str(xml)), seconds)
    out["native mesh-SDF"] = drop(mujoco.MjModel.from_xml_path(str(sdf_xml)), seconds)
    ref = out["native mesh-SDF"]["objects"]
    for mode in out:
        for name, o in out[mode]["objects"].items():
            o["from_sdf_mm"] = float(np.linalg.norm(np.subtract(o["pos_m"], ref[name]["pos_m"])) * 1e3)
            o["height_from_sdf_mm"] = float((o["pos_m"][2] - ref[name]["pos_m"][2]) * 1e3)
    return out


def main() -> int:
    res = run()
    for mode, r in res.items():
        objs = ", ".join(f"{k} {o['where']} (z {1e3 * o['pos_m'][2]:.2f} mm, {o['from_sdf_mm']:.2f} mm from mesh-SDF, "
                         f"sank {o['sank_mm']:.1f} mm)" for k, o in r["objects"].items())
        print(f"{mode:16s} {r['step_us_median']:8.1f} µs/step   {objs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
