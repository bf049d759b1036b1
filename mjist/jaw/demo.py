"""Jaw closure with IST contacts in plain MuJoCo: the ``mjist demo`` command.

Loads the jaw-closure scene (bundled jaws, or a folder with a maxilla + mandible pair),
attaches the IST, opens the jaw, switches the closing muscles on and runs ``mj_step``.
Reports contacts, step time, the final occlusion against the ground truth (the scene's
``occlusion`` keyframe) with coal's exact mesh distance there, and writes a picture.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import mujoco
import numpy as np

from ..mujoco.attach import load_model
from ..mujoco.handle import Handle
from ..mujoco.scene import geom_pose
from . import pair as jawmod
from .scenes import pair_scene

SCENE = jawmod.BUNDLED / "jaw_closure.xml"
SETTLED = 0.1  # mm/s: the jaw has come to rest when no point of the mandible drifts faster over DRIFT_S
DRIFT_S = 0.1  # s: contact chatter of a few µm averages out over this, a slide does not


def _mesh_bvh(model, g):
    from ..mujoco.scene import mesh_of

    V, F = mesh_of(model, g)
    return jawmod.coal_bvh(V, F)



def run_closure(model, *, seconds: float = 1.0, handle: Handle | None = None) -> dict:
    """Close the jaw from the ``open`` keyframe with all muscles on; return the figures."""
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "open"))
    d.ctrl[:] = 1.0
    n = int(round(seconds / model.opt.timestep))
    times = np.empty(n)
    ncon = np.empty(n, np.int64)
    back = min(n - 1, int(round(DRIFT_S / model.opt.timestep)))
    qpos_back = d.qpos.copy()
    for i in range(n):
        t = time.perf_counter()
        mujoco.mj_step(model, d)
        times[i] = time.perf_counter() - t
        ncon[i] = d.ncon
        if i == n - 1 - back:
            qpos_back = d.qpos.copy()
    gmx = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "maxilla")
    gmd = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "mandible")
    true_d = jawmod.coal_distance(_mesh_bvh(model, gmx), geom_pose(d, gmx), _mesh_bvh(model, gmd), geom_pose(d, gmd))
    coll = jawmod.coal_collides(_mesh_bvh(model, gmx), geom_pose(d, gmx), _mesh_bvh(model, gmd), geom_pose(d, gmd))
    q = d.qpos
    contacts = [c for c in d.contact[:d.ncon] if {c.geom1, c.geom2} == {gmx, gmd}]
    # the fastest mandible point at the end: the slides' speed plus the hinge rate times the
    # farthest vertex from the hinge axis
    from ..mujoco.scene import mesh_of

    V, _ = mesh_of(model, gmd)
    P = geom_pose(d, gmd)
    W = V @ P[:3, :3].T + P[:3, 3]
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "hinge")
    axis_pt, axis = d.xanchor[j], d.xaxis[j]
    r = W - axis_pt
    reach = float(np.linalg.norm(r - np.outer(r @ axis, axis), axis=1).max())
    speed = (abs(d.qvel[0]) * reach + float(np.linalg.norm(d.qvel[1:3]))) * 1e3
    dq = d.qpos[:3] - qpos_back[:3]
    drift = (abs(dq[0]) * reach + float(np.linalg.norm(dq[1:3]))) * 1e3 / max(back * model.opt.timestep, 1e-12)
    tail = times[n // 2:]  # settled half: the jaw is closed and clenching
    res = {
        "contacts": "ist" if handle is not None and handle.pairs else "native",
        "steps": n,
        "timestep": float(model.opt.timestep),
        "step_us_median": float(np.median(times) * 1e6),
        "step_us_median_closed": float(np.median(tail) * 1e6),
        "steps_per_second": float(1.0 / np.median(times)),
        "final_contacts": len(contacts),
        "final_contact_depths_mm": [round(-c.dist * 1e3, 4) for c in contacts],
        "mean_contacts": float(ncon.mean()),
        "final_hinge_deg": float(np.degrees(q[0])),
        "final_protrusion_mm": float(q[1] * 1e3),
        "final_lateral_mm": float(q[2] * 1e3),
        "final_speed_mm_s": float(speed),
        "drift_mm_s": float(drift),
        "settled": bool(drift < SETTLED),
        "true_distance_mm": float(true_d * 1e3),
        "true_collision": bool(coll),
        "error_bound_mm": float(handle.pairs[0].error_bound * 1e3) if handle is not None and handle.pairs else None,
        "offset_mm": float(handle.pairs[0].offset * 1e3) if handle is not None and handle.pairs else None,
        "surface_contacts": bool(handle is not None and handle.surfaces),
    }
    if handle is not None and handle.pairs:
        res["hook"] = handle.stats()
    res["_data"] = d
    return res


def render(model, d, out, size=(1500, 500), *, handle: Handle | None = None, depth: int | None = None) -> str:
    """Front, oblique and side close-up views with contacts drawn.

    With ``handle`` the IST contacts are drawn as points with normal arrows and, with
    ``depth``, the tree spheres at that depth (``mjist.view.overlay``); without it MuJoCo
    draws its own contact points.
    """
    from ..mujoco.view import overlay

    w, h = size
    r = mujoco.Renderer(model, h, w // 3, max_geom=20000)
    try:
        opt = mujoco.MjvOption()
        opt.flags[mujoco.mjtVisFlag.mjVIS_CONTACTPOINT] = handle is None
        model.vis.scale.contactwidth = 0.04
        model.vis.scale.contactheight = 0.01
        centre = d.geom_xpos.mean(axis=0)
        span = 2.2 * float(np.max(model.geom_rbound))
        views = []
        # front, oblique, and a close-up of the premolars and molars from the side
        for az, el, dist, look in ((90.0, 0.0, 0.85, centre), (150.0, -15.0, 1.05, centre),
                                   (180.0, -5.0, 0.45, centre)):
            cam = mujoco.MjvCamera()
            cam.lookat[:] = look
            cam.distance = dist * span
            cam.azimuth = az
            cam.elevation = el
            r.update_scene(d, camera=cam, scene_option=opt)
            overlay(r.scene, model, d, handle, depth=depth)
            views.append(r.render())
    finally:
        r.close()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    plt.imsave(out, np.concatenate(views, axis=1))
    return str(out)


def format_summary(res: dict) -> str:
    lines = [
        f"contacts      {res['contacts']}: {res['final_contacts']} at the end (depths {res['final_contact_depths_mm']} mm), "
        f"{res['mean_contacts']:.1f} per step on average",
        f"speed         {res['step_us_median']:.1f} µs per mj_step median ({res['steps_per_second']:.0f} steps/s), "
        f"{res['step_us_median_closed']:.1f} µs once closed; {res['steps']} steps of {res['timestep'] * 1e3:g} ms",
        f"occlusion     hinge {res['final_hinge_deg']:+.3f}°, protrusion {res['final_protrusion_mm']:+.3f} mm, "
        f"lateral {res['final_lateral_mm']:+.3f} mm (ground truth 0, 0, 0); "
        f"{'settled' if res['settled'] else 'still moving'} (drift {res['drift_mm_s']:.3f} mm/s over the last "
        f"{DRIFT_S:g} s, {res['final_speed_mm_s']:.3f} mm/s in the last step)",
        f"true surfaces coal distance {res['true_distance_mm']:+.4f} mm, meshes intersect: {res['true_collision']}",
    ]
    if res.get("error_bound_mm") is not None and res.get("surface_contacts"):
        lines.append(f"IST bound     ε1+ε2 = {res['error_bound_mm']:.3f} mm (true distance ∈ [d_IST − ε1 − ε2, d_IST]); "
                     "the trees find where contact can be, the meshes give the contacts")
    elif res.get("error_bound_mm") is not None:
        lines.append(f"IST bound     ε1+ε2 = {res['error_bound_mm']:.3f} mm, contact offset {res['offset_mm']:.3f} mm "
                     "(true distance ∈ [d_IST − ε1 − ε2, d_IST])")
    return "\n".join(lines)


def main(scene=None, data=None, native=False, seconds=1.0, out="out/demo", picture=True, max_error=None, progress=True,
         pair: dict | None = None, narrowphase: str = "surface") -> int:
    """``mjist demo``: ``data`` is a jaw-pair folder read with ``pair`` options (units, up, hinge,
    repair: ``scenes.pair_scene``). ``narrowphase``: ``surface`` (the jaws rest on the meshes'
    true surfaces) or ``spheres`` (on the trees' spheres, a mean surface gap off them)."""
    out = Path(out)
    if data is not None or (pair or {}).get("maxilla"):
        scene = pair_scene(data, out, "closure", progress=progress, **(pair or {}))
    scene = Path(scene or SCENE)
    t = time.perf_counter()
    if native:
        model, handle = mujoco.MjModel.from_xml_path(str(scene)), None
    else:
        model, handle = load_model(scene, progress=progress, max_error=max_error, narrowphase=narrowphase)
        print(handle.summary())
    print(f"scene         {scene} ready in {time.perf_counter() - t:.1f} s")
    res = run_closure(model, seconds=seconds, handle=handle)
    d = res.pop("_data")
    res["scene"], res["final_qpos"] = str(scene.resolve()), d.qpos.tolist()  # where it came to rest (the report reads it)
    meta = scene.parent / "pair.json"
    if (data is not None or (pair or {}).get("maxilla")) and meta.exists():  # the hinge the scene was made with, and how sure it is
        j = json.loads(meta.read_text())
        res["hinge"] = {"source": j["hinge_source"], "uncertainty_mm": j.get("hinge_uncertainty_mm")}
    print(format_summary(res))
    os.makedirs(out, exist_ok=True)
    tag = "native" if native else "ist"
    (out / f"closure_{tag}.json").write_text(json.dumps(res, indent=2))
    if picture:
        try:
            print(f"picture       {render(model, d, out / f'closure_{tag}.png', handle=handle)}")
        except Exception as exc:  # no GL on this machine: the numbers still stand
            print(f"picture       skipped ({type(exc).__name__}: {exc}); set MUJOCO_GL=egl or osmesa")
    if handle is not None:
        handle.detach()
    if data is not None or (pair or {}).get("maxilla"):
        from .. import report

        print(f"written       {report.build_or_say(out)}")
    return 0
