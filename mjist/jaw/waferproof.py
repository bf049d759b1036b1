"""Proofs that a wafer (``jaw.wafer``) can be printed, seats both arches and holds the mandible.

* **printable** (``printable``): every edge shared by exactly two faces in opposite directions
  (closed, consistently wound), one shell, positive volume, no face crossing another
  (``geometry.selfintersect``), and the minimum thickness: at every vertex the largest ball
  inside the wafer touching it there (bisection on exact distances), doubled;
* **seating** (``seating``): coal's exact distance between the wafer and each arch at its
  seated pose (the maxilla as stored, the mandible at ``mandible_transform``), the deepest
  penetration where they meet (vertices inside the other mesh), and each cusp tip's distance to
  the wafer, which must be the clearance (the imprints are real, not a flat plate);
* **holding** (``holding``): a MuJoCo scene with mjist contacts — the maxilla and the wafer
  fixed (the wafer is ligated to the maxillary arch), the mandible free but for soft-tissue
  damping, no TMJ — closes the mandible onto the wafer with ``CLOSING_FORCE`` at the dentition's
  centre, then pushes it with ``PUSH`` forward, back, left and right. The mandible must stay
  within ``HOLD_MM`` / ``HOLD_DEG`` of the planned pose while pushed and come back when released.
"""
from __future__ import annotations

import numpy as np

PENETRATION_MM = 0.02  # seating: deepest allowed overlap of an arch and the wafer
TIP_SLACK_MM = 0.05  # seating: a cusp tip lies within the clearance plus this of the wafer
CLOSING_FORCE = 50.0  # N: intermaxillary fixation (elastics or wires) closing the mandible onto the wafer
PUSH = 20.0  # N: the push forward, back and sideways
HOLD_MM, HOLD_DEG = 0.2, 0.5  # holding: largest drift of a tooth point and rotation from the planned pose
RETURN_MM = 0.05  # holding: how close to its seated pose the mandible comes back after a push
SEAT_S, RAMP_S, PUSH_S, REST_S = 0.3, 0.15, 0.2, 0.25  # s: seating, push ramp (quasi-static), push held, rest after it
# the proof scene's contacts: enamel and resin are rigid, so the contacts are as stiff as the step
# resolves (time constant four steps). Softer ones add MuJoCo's contact compliance to the drift a
# push causes (BENCHMARKS.md, "Surgical wafers"); stiffer ones cost proportionally more steps
TIMESTEP, SOLREF = 2.5e-4, (0.001, 1.0)
CONTACTS, SURFACE_GROUPS = 16, 32


def printable(V, F, thickness: float, up) -> dict:
    """Closed, one shell, positive volume, embedded (no face crossing another); its minimum
    thickness between its upper and lower faces (m in, mm out)."""
    import trimesh

    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    m = trimesh.Trimesh(V, F, process=False)
    edges = np.sort(m.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    closed = bool(np.all(counts == 2)) and bool(m.is_winding_consistent)
    shells = len(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(F)), min_len=1))
    winding = embedded(V, F)
    faces, rim = min_thickness(V, F, up)
    t = min(faces, rim)
    ok = closed and shells == 1 and m.volume > 0 and winding["ok"] and t >= thickness * (1 - 1e-9)
    return {"watertight": closed, "shells": shells, "volume_mm3": float(m.volume) * 1e9, "winding": winding,
            "min_thickness_mm": t * 1e3, "between_faces_mm": faces * 1e3, "rim_height_mm": rim * 1e3,
            "vertices": len(V), "faces": len(F), "ok": ok}


FACING = 0.3  # a face whose normal is within acos(0.3) = 72.5° of up (down) is on the upper (lower) face
WINDING_TOL = 0.05  # a winding number within this of 0 or 1 is that number


def min_thickness(V, F, up) -> tuple[float, float]:
    """The wafer's minimum thickness (m): the least distance between its upper face (faces turned
    up by more than ``FACING``) and its lower face (turned down), from every vertex of each to
    the other's triangles; and the least height of its rim, the vertical wall around it (both
    faces reach the wall: at the wall they are the wall's height apart)."""
    from ..geometry.bvh import BVH

    u = np.asarray(up, float) / np.linalg.norm(up)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    c = (n @ u) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    wall = np.abs(c) < 1e-6
    on_wall = np.zeros(len(V), bool)
    on_wall[F[wall].ravel()] = True
    faces = np.inf
    for a, b in ((c > FACING, c < -FACING), (c < -FACING, c > FACING)):
        Fb = np.ascontiguousarray(F[b])
        src = np.unique(F[a])
        src = src[~on_wall[src]]
        if len(src) == 0 or len(Fb) == 0:
            return 0.0, 0.0
        faces = min(faces, float(BVH.of_triangles(V, Fb).distance(np.ascontiguousarray(V[src]), V, Fb).min()))
    rim = np.inf
    if on_wall.any():  # the wall's columns: its vertices that share a place across up
        W = np.flatnonzero(on_wall)
        flat = V[W] - np.outer(V[W] @ u, u)
        _, col = np.unique(np.round(flat * 1e9).astype(np.int64), axis=0, return_inverse=True)
        h = V[W] @ u
        top = np.full(col.max() + 1, -np.inf)
        bot = np.full(col.max() + 1, np.inf)
        np.maximum.at(top, col, h)
        np.minimum.at(bot, col, h)
        rim = float((top - bot).min())
    return faces, rim


def embedded(V, F, offset: float = 1e-6) -> dict:
    """Whether the closed surface crosses itself: the generalized winding number (libigl's fast
    winding number) just outside and just inside every face must be 0 and 1. Where the surface
    crosses itself, points beside the crossing faces lie inside another part (2) or behind an
    inverted one (-1)."""
    import igl

    T = V[F]
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    c = T.mean(axis=1)
    P = np.ascontiguousarray(np.vstack([c + offset * n, c - offset * n]))
    w = igl.fast_winding_number(np.ascontiguousarray(V), np.ascontiguousarray(F), P)
    out, inn = w[:len(F)], w[len(F):]
    bad = (np.abs(out) > WINDING_TOL) | (np.abs(inn - 1.0) > WINDING_TOL)
    return {"faces_not_0_1": int(bad.sum()), "outside_max": float(np.abs(out).max()),
            "inside_range": [float(inn.min()), float(inn.max())], "ok": not bad.any()}


def seating(maxilla, mandible, wafer, clearance: float, tips: dict) -> dict:
    """Each arch against the wafer, all ``(V, F)`` in one frame (the mandible at its seated pose):
    coal's distance, the deepest overlap and the cusp tips' distances to the wafer (m in, mm out)."""
    from ..geometry.bvh import BVH
    from .exact import coal_bvh, coal_distance

    Vw, Fw = (np.ascontiguousarray(a) for a in wafer)
    bw = coal_bvh(Vw, Fw)
    wbvh = BVH.of_triangles(Vw, Fw)
    I4 = np.eye(4)
    out = {}
    for name, (V, F) in (("maxilla", maxilla), ("mandible", mandible)):
        V = np.ascontiguousarray(V, dtype=np.float64)
        F = np.ascontiguousarray(F, dtype=np.int64)
        gap = coal_distance(coal_bvh(V, F), I4, bw, I4)
        abvh = BVH.of_triangles(V, F)
        # the deepest overlap: wafer vertices inside the arch, arch vertices inside the wafer
        depth = 0.0
        if gap <= 0.0:
            inside_a = abvh.contains(np.ascontiguousarray(Vw), V, F)
            if inside_a.any():
                depth = max(depth, float(abvh.distance(np.ascontiguousarray(Vw[inside_a]), V, F).max()))
            inside_w = wbvh.contains(V, Vw, Fw)
            if inside_w.any():
                depth = max(depth, float(wbvh.distance(np.ascontiguousarray(V[inside_w]), Vw, Fw).max()))
        T = np.ascontiguousarray(tips[name], dtype=np.float64).reshape(-1, 3)
        td = wbvh.distance(T, Vw, Fw) if len(T) else np.empty(0)
        out[name] = {"coal_distance_mm": float(gap) * 1e3, "penetration_mm": depth * 1e3, "cusp_tips": len(T),
                     "tip_distance_median_mm": float(np.median(td)) * 1e3 if len(td) else None,
                     "tip_distance_max_mm": float(td.max()) * 1e3 if len(td) else None,
                     "ok": depth * 1e3 <= PENETRATION_MM and len(td) >= 3
                     and float(td.max()) * 1e3 <= clearance * 1e3 + TIP_SLACK_MM}
    out["ok"] = out["maxilla"]["ok"] and out["mandible"]["ok"]
    return out


def _angle_deg(Ra, Rb) -> float:
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def holding(scene, wafer_file, planned, points, centre, directions: dict, *, closing_force: float = CLOSING_FORCE,
            push: float = PUSH, narrowphase: str = "surface", cache_dir=None, progress: bool = False,
            friction: float | None = None, timestep: float = TIMESTEP, solref=SOLREF, solimp=None, **settings) -> dict:
    """Close the mandible onto the wafer in the occlusion scene ``scene`` and push it.

    Parameters
    ----------
    scene : path
        The pair's occlusion-search scene (``jaw.scenes.occlusion_search_xml``); its TMJ and its
        closing acceleration are taken out, the wafer added as a fixed geom.
    wafer_file : path
        The wafer mesh in the scene's world frame.
    planned : (pos, quat)
        The mandible body's planned pose (seated on the wafer).
    points : (n, 3)
        Tooth points of the mandible at the planned pose (world), where drift is measured.
    centre : (3,)
        Where the closing force and the pushes act (world): the dentition's centre.
    directions : dict
        ``{"up": ..., "forward": ..., "left": ...}`` unit vectors (world).
    """
    import mujoco
    from scipy.spatial.transform import Rotation

    from ..mujoco.attach import attach

    spec = mujoco.MjSpec.from_file(str(scene))
    spec.option.gravity = [0.0, 0.0, 0.0]
    for e in list(spec.equalities):
        spec.delete(e)
    seat = spec.body("condyles")
    if seat is not None:
        spec.delete(seat)
    spec.add_mesh(name="wafer", file=str(wafer_file))
    spec.worldbody.add_geom(name="wafer", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="wafer", rgba=[0.55, 0.75, 0.95, 1.0])
    model = spec.compile()
    if friction is not None:
        model.geom_friction[:, 0] = friction
    model.opt.timestep = timestep
    model.geom_solref[:] = solref
    if solimp is not None:
        model.geom_solimp[:] = solimp
    settings.setdefault("contacts", CONTACTS)
    settings.setdefault("surface_groups", SURFACE_GROUPS)
    handle = attach(model, geoms=["maxilla", "mandible", "wafer"], narrowphase=narrowphase, cache_dir=cache_dir,
                    progress=progress, **settings)
    try:
        d = mujoco.MjData(model)
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "mandible")
        pos0, quat0 = (np.asarray(a, float) for a in planned)
        d.qpos[:3], d.qpos[3:7] = pos0, quat0
        mujoco.mj_forward(model, d)
        R0 = d.xmat[b].reshape(3, 3).copy()
        local = (np.asarray(points, float) - pos0) @ R0  # tooth points in the body frame
        up = np.asarray(directions["up"], float)

        def pose():
            return d.xpos[b].copy(), d.xmat[b].reshape(3, 3).copy()

        def drift(ref_pos, ref_R):
            p, R = pose()
            return float(np.linalg.norm((local @ R.T + p) - (local @ ref_R.T + ref_pos), axis=1).max()) * 1e3, _angle_deg(R, ref_R)

        def force(F):
            d.xfrc_applied[b, :3] = F
            d.xfrc_applied[b, 3:] = np.cross(np.asarray(centre) - d.xipos[b], F)

        def run(seconds, F_of_t, watch=None):
            n = int(round(seconds / model.opt.timestep))
            worst = (0.0, 0.0)
            for k in range(n):
                force(F_of_t(k * model.opt.timestep))
                mujoco.mj_step(model, d)
                if watch is not None and k % 5 == 0:
                    m, a = drift(*watch)
                    worst = (max(worst[0], m), max(worst[1], a))
                if not np.all(np.isfinite(d.qpos)):
                    raise RuntimeError("the holding simulation diverged")
            return worst

        close = closing_force * up
        run(SEAT_S, lambda t: close)
        seated = pose()
        seated_mm, seated_deg = drift(pos0, R0)
        rows = []
        for name, sign, key in (("forward", 1, "forward"), ("back", -1, "forward"), ("left", 1, "left"), ("right", -1, "left")):
            F = sign * push * np.asarray(directions[key], float)
            ramp = lambda t, F=F: close + F * min(1.0, t / RAMP_S)  # noqa: E731
            worst = run(RAMP_S + PUSH_S, ramp, watch=(pos0, R0))
            run(RAMP_S, lambda t, F=F: close + F * max(0.0, 1.0 - t / RAMP_S))
            run(REST_S, lambda t: close)
            back_mm, back_deg = drift(*seated)
            rows.append({"push": name, "max_drift_mm": worst[0], "max_rotation_deg": worst[1],
                         "after_mm": back_mm, "after_deg": back_deg,
                         "ok": worst[0] <= HOLD_MM and worst[1] <= HOLD_DEG and back_mm <= RETURN_MM})
        q = Rotation.from_matrix(seated[1]).as_quat()
        return {"closing_force_n": closing_force, "push_n": push, "narrowphase": narrowphase,
                "timestep_s": float(model.opt.timestep), "seated_drift_mm": seated_mm, "seated_rotation_deg": seated_deg,
                "seated_pos": seated[0].tolist(), "seated_quat": [q[3], q[0], q[1], q[2]],
                "pushes": rows, "limits": {"drift_mm": HOLD_MM, "rotation_deg": HOLD_DEG, "return_mm": RETURN_MM},
                "ok": seated_mm <= HOLD_MM and seated_deg <= HOLD_DEG and all(r["ok"] for r in rows)}
    finally:
        handle.detach()
