"""Seeing the IST in MuJoCo: tree spheres and contacts drawn into an ``mjvScene``.

``overlay`` appends geoms to any ``mjvScene`` — the passive viewer's ``user_scn`` (``mjist
view``) or a ``mujoco.Renderer``'s scene after ``update_scene`` (``mjist render --spheres``):
the node spheres of each managed geom's tree at a chosen depth (leaves above that depth
included, so the layer covers the whole object), posed with the geom, and every contact of an
IST-managed pair as a point plus an arrow along its normal, coloured by depth.
"""
from __future__ import annotations

import time

import mujoco
import numpy as np

_SPHERE_RGBA = (np.array([0.20, 0.55, 0.95, 0.35], np.float32), np.array([0.95, 0.55, 0.20, 0.35], np.float32))
_POINT_RGBA = np.array([1.0, 0.1, 0.1, 1.0], np.float32)
_ARROW_RGBA = np.array([1.0, 0.85, 0.1, 1.0], np.float32)


def layer(tree, depth: int) -> np.ndarray:
    """Node indices that cut ``tree`` at ``depth``: nodes of that depth and shallower leaves.

    Their spheres enclose every leaf sphere exactly once (depth ≥ tree depth gives the leaves).
    """
    d = tree.depth_of
    is_leaf = tree.child_count == 0
    return np.flatnonzero((d == depth) | (is_leaf & (d < depth)))


def _free(scn) -> int:
    return int(scn.maxgeom - scn.ngeom)


def _add(scn, gtype, size, pos, mat, rgba) -> bool:
    if scn.ngeom >= scn.maxgeom:
        return False
    mujoco.mjv_initGeom(scn.geoms[scn.ngeom], int(gtype), np.asarray(size, np.float64),
                        np.asarray(pos, np.float64), np.asarray(mat, np.float64).ravel(), rgba)
    scn.ngeom += 1
    return True


def overlay(scn, model, data, handle, *, depth: int | None = None, contacts: bool = True,
            max_spheres: int = 5000, arrow: float | None = None) -> dict:
    """Append IST spheres and contacts to ``scn``; return how many of each were drawn.

    Parameters
    ----------
    scn : mujoco.MjvScene
        ``viewer.user_scn`` or ``renderer.scene`` (after ``update_scene``). Geoms past
        ``scn.maxgeom`` are dropped, never written out of bounds.
    handle : mjist.Handle
        The attached model's handle (its trees and geom ids).
    depth : int, optional
        Tree depth of the spheres to draw (0 = root); ``None`` draws no spheres.
    contacts : bool
        Draw the contacts of IST-managed pairs (point + normal arrow from geom1 to geom2).
    max_spheres : int
        Per geom; a deeper cut with more spheres is thinned evenly (the count says so).
    arrow : float, optional
        Arrow length in metres (default: 2.5 % of the smallest managed geom's bounding radius).
    """
    drawn = {"spheres": 0, "spheres_skipped": 0, "contacts": 0}
    if handle is None:
        return drawn
    eye = np.eye(3)
    if depth is not None:
        for k, (name, tree) in enumerate(sorted(handle.trees.items())):
            g = handle.geoms[name]
            R = data.geom_xmat[g].reshape(3, 3)
            p = data.geom_xpos[g]
            idx = layer(tree, int(depth))
            if idx.size > max_spheres:
                drawn["spheres_skipped"] += idx.size - max_spheres
                idx = idx[np.linspace(0, idx.size - 1, max_spheres).astype(np.int64)]
            C = tree.centers[idx] @ R.T + p
            rgba = _SPHERE_RGBA[k % 2]
            for c, r in zip(C, tree.radii[idx]):
                if not _add(scn, mujoco.mjtGeom.mjGEOM_SPHERE, (r, 0, 0), c, eye, rgba):
                    drawn["spheres_skipped"] += 1
                    continue
                drawn["spheres"] += 1
    if contacts and data.ncon:
        managed = {frozenset(p.ids) for p in handle.pairs}
        ids = [g for p in handle.pairs for g in p.ids]
        L = arrow if arrow is not None else 0.025 * float(min(model.geom_rbound[ids])) if ids else 0.005
        for c in data.contact[:data.ncon]:
            if frozenset((int(c.geom1), int(c.geom2))) not in managed:
                continue
            pos = np.array(c.pos)
            n = np.array(c.frame[:3])
            if _free(scn) < 2:
                break
            _add(scn, mujoco.mjtGeom.mjGEOM_SPHERE, (0.08 * L, 0, 0), pos, eye, _POINT_RGBA)
            # mjv_connector sets only type, size, pos and mat: the slot's other fields (mesh,
            # material and texture ids...) must come from mjv_initGeom, or they are whatever an
            # earlier frame left there and the renderer follows them (a segfault in mjr_render)
            _add(scn, mujoco.mjtGeom.mjGEOM_ARROW, (0, 0, 0), pos, eye, _ARROW_RGBA)
            mujoco.mjv_connector(scn.geoms[scn.ngeom - 1], int(mujoco.mjtGeom.mjGEOM_ARROW), 0.03 * L, pos, pos + L * n)
            drawn["contacts"] += 1
    return drawn


def view(scene: str, *, depth: int | None = None, key: str | None = None, native: bool = False,
         control: float | None = None, seconds: float | None = None) -> int:
    """Open MuJoCo's passive viewer on ``scene`` with IST contacts and an IST overlay.

    The simulation runs in real time; ``control`` sets every actuator's control (e.g. 1 to
    close the jaw), ``seconds`` closes the viewer after that much simulated time.
    """
    import mujoco.viewer

    from .attach import load_model

    model, handle = (mujoco.MjModel.from_xml_path(scene), None) if native else load_model(scene, progress=True)
    if handle is not None:
        print(handle.summary())
    d = mujoco.MjData(model)
    if key:
        k = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key)
        if k < 0:
            raise ValueError(f"the scene has no keyframe {key!r}")
        mujoco.mj_resetDataKeyframe(model, d, k)
    if control is not None and model.nu:
        d.ctrl[:] = control
    try:
        with mujoco.viewer.launch_passive(model, d) as v:
            v.opt.flags[mujoco.mjtVisFlag.mjVIS_CONTACTPOINT] = native
            t0 = time.perf_counter()
            while v.is_running() and (seconds is None or d.time < seconds):
                mujoco.mj_step(model, d)
                with v.lock():
                    v.user_scn.ngeom = 0
                    overlay(v.user_scn, model, d, handle, depth=depth)
                v.sync()
                lag = d.time - (time.perf_counter() - t0)
                if lag > 0:
                    time.sleep(lag)
    finally:
        if handle is not None:
            handle.detach()
    return 0
