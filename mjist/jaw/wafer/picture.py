"""The wafer's picture: on the maxilla from below (occlusal view) and from the side, rendered by MuJoCo."""
from __future__ import annotations

import numpy as np


def render(scene, wafer_file, planned, out) -> str:
    """The wafer on the maxilla from below (occlusal view) and from the side, the mandible
    faded in the side view at ``planned``, its body's ``(pos, quat)`` seated on the wafer."""
    import matplotlib
    import mujoco

    spec = mujoco.MjSpec.from_file(str(scene))
    spec.add_mesh(name="wafer", file=str(wafer_file))
    spec.worldbody.add_geom(name="wafer", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="wafer", rgba=[0.35, 0.6, 0.95, 1.0],
                            contype=0, conaffinity=0)
    model = spec.compile()
    d = mujoco.MjData(model)
    g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "mandible")
    gw = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "wafer")
    d.qpos[:3], d.qpos[3:7] = planned
    mujoco.mj_forward(model, d)
    centre = d.geom_xpos[gw].copy()
    views = []
    r = mujoco.Renderer(model, 600, 700)
    try:
        for alpha, az, el in ((0.0, 90.0, 89.0), (0.35, 180.0, 0.0)):
            model.geom_rgba[g, 3] = alpha
            cam = mujoco.MjvCamera()
            cam.lookat[:] = centre
            cam.distance = 0.13
            cam.azimuth, cam.elevation = az, el
            r.update_scene(d, camera=cam)
            views.append(r.render())
    finally:
        r.close()
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(out, np.concatenate(views, axis=1))
    return str(out)
