"""Proofs that a wafer (``jaw.wafer``) can be printed, seats both arches and holds the mandible.

* **printable** (``printable``): every edge shared by exactly two faces in opposite directions
  (closed, consistently wound), one shell, positive volume, embedded (``embedded``: the winding
  number just outside and just inside every face is 0 and 1), and the minimum thickness
  (``min_thickness``: between the upper and the lower face, and the rim's wall);
* **seating** (``seating``): coal's exact distance between the wafer and each arch at its
  seated pose (the maxilla as stored, the mandible at ``mandible_transform``), the deepest
  penetration where they meet (vertices inside the other mesh), and each cusp tip's distance to
  the wafer, which must be the clearance (the imprints are real, not a flat plate);
* **holding** (``holding``): a MuJoCo scene with mjist contacts — the maxilla and the wafer
  fixed (the wafer is ligated to the maxillary arch), the mandible free but for soft-tissue
  damping, no TMJ — closes the mandible onto the wafer with ``CLOSING_FORCE`` at the dentition's
  centre, then, from that seated state, pushes it with ``PUSH`` forward, back, left and right
  (four rollouts side by side). The mandible must stay within ``HOLD_MM`` / ``HOLD_DEG`` of the
  planned pose while pushed and come back when released (drifts over ``WINDOW_S``).
"""
from __future__ import annotations

import numpy as np

PENETRATION_MM = 0.02  # seating: deepest allowed overlap of an arch and the wafer
TIP_SLACK_MM = 0.05  # seating: a cusp tip lies within the clearance plus this of the wafer
CLOSING_FORCE = 50.0  # N: intermaxillary fixation (elastics or wires) closing the mandible onto the wafer
PUSH = 20.0  # N: the push forward, back and sideways
HOLD_MM, HOLD_DEG = 0.2, 0.5  # holding: largest drift of a tooth point and rotation from the planned pose
RETURN_MM = 0.05  # holding: how close to its seated pose the mandible comes back after a push
# s: seating, push ramp, push held, rest after it. The contacts are stiff (time constant 1 ms), so
# the mandible follows the force within a few ms and a 50 ms ramp is quasi-static; longer
# phases only add steps (BENCHMARKS.md, "Surgical wafers")
SEAT_S, RAMP_S, PUSH_S, REST_S = 0.1, 0.05, 0.1, 0.1
# s: drifts are means over this many seconds of steps. The surface narrow phase's contacts on a
# conforming seat change from step to step and the mandible rattles by a few µm per step, with
# rare kicks of up to 0.05 mm that die out within about 3 ms; a 5 ms mean measures where the
# mandible is held rather than one step's kick (the largest single step is recorded beside it)
WINDOW_S = 0.005
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


def holding(scene, wafer_file, planned, points, centre, directions: dict, *, closing_force: float = CLOSING_FORCE,
            push: float = PUSH, narrowphase: str = "surface", cache_dir=None, progress: bool = False,
            friction: float | None = None, timestep: float = TIMESTEP, solref=SOLREF, solimp=None,
            threads: int | None = None, trace: bool = False, **settings) -> dict:
    """Close the mandible onto the wafer in the occlusion scene ``scene`` and push it.

    The mandible first closes onto the wafer under the closing force alone (``SEAT_S``). Each
    push then starts from that seated state: the push ramps up, is held, ramps down, and the
    mandible rests under the closing force alone. The four pushes are independent rollouts
    (``mujoco.rollout``, bit-identical whatever the thread count), so they run side by side.

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
    threads : int, optional
        Threads for the pushes (default: one per core, at most four).
    trace : bool
        Also return each push's drift at every step (``"trace"``: mm, one row per push).
    """
    import os

    import mujoco
    from mujoco import rollout
    from scipy.spatial.transform import Rotation

    from ..mujoco.attach import attach
    from ..mujoco.config import SDF_OCTREE_DEPTH

    spec = mujoco.MjSpec.from_file(str(scene))
    spec.option.gravity = [0.0, 0.0, 0.0]
    for e in list(spec.equalities):
        spec.delete(e)
    seat = spec.body("condyles")
    if seat is not None:
        spec.delete(seat)
    # the mandible as an sdf geom backed by its mesh: MuJoCo caps a mesh-mesh pair at 4 contacts,
    # a mesh-sdf pair at sdf_initpoints (≤ 50), and an arch seats on the wafer at tens of cusps.
    # The mesh geom of a mesh-sdf pair is the surface narrow phase's A, whose outward direction
    # is the contact normal: the wafer's imprints (offsets of the teeth, rounded) give normals
    # that turn smoothly as a cusp slides in them; the cusps' own are sharp
    spec.mesh("mandible").octree_maxdepth = SDF_OCTREE_DEPTH
    spec.geom("mandible").type = mujoco.mjtGeom.mjGEOM_SDF
    settings.setdefault("contacts", CONTACTS)
    settings.setdefault("surface_groups", SURFACE_GROUPS)
    spec.option.sdf_initpoints = max(int(spec.option.sdf_initpoints), int(settings["contacts"]))
    spec.add_mesh(name="wafer", file=str(wafer_file))
    spec.worldbody.add_geom(name="wafer", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="wafer", rgba=[0.55, 0.75, 0.95, 1.0])
    model = spec.compile()
    if friction is not None:
        model.geom_friction[:, 0] = friction
    model.opt.timestep = timestep
    model.geom_solref[:] = solref
    if solimp is not None:
        model.geom_solimp[:] = solimp
    # measured on every step: with held contacts the CBCT mandible came back 0.062 mm short of its
    # seat after a push (0.016 mm measured every step), past the proof's limit
    settings = {"surface_hold": 0.0, **settings} if narrowphase == "surface" else settings
    handle = attach(model, geoms=["maxilla", "mandible", "wafer"], narrowphase=narrowphase, cache_dir=cache_dir,
                    progress=progress, **settings)
    try:
        d = mujoco.MjData(model)
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "mandible")
        adr = int(model.jnt_qposadr[model.body_jntadr[b]])  # slides x, y, z then a ball: the body's position and quaternion
        pos0, quat0 = (np.asarray(a, float) for a in planned)
        d.qpos[adr:adr + 3], d.qpos[adr + 3:adr + 7] = pos0, quat0
        mujoco.mj_forward(model, d)
        R0 = d.xmat[b].reshape(3, 3).copy()
        local = (np.asarray(points, float) - pos0) @ R0  # tooth points in the body frame
        up = np.asarray(directions["up"], float)

        window = max(1, int(round(WINDOW_S / timestep)))

        def teeth(q):
            """Tooth points (k, n, 3) and rotations (k, 3, 3) of the mandible's poses ``q`` (k, 7)."""
            R = Rotation.from_quat(q[:, [4, 5, 6, 3]]).as_matrix()
            return np.einsum("kij,nj->kni", R, local) + q[:, None, :3], R

        def mean(x):
            """Means of ``x`` over ``window`` consecutive steps (k - window + 1 rows)."""
            c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
            return (c[window:] - c[:-window]) / window

        def apart(P, R, P_ref, R_ref):
            """Largest tooth-point distance (mm) and rotation (°) of each row from the reference."""
            mm = np.linalg.norm(P - P_ref, axis=-1).max(axis=-1) * 1e3
            c = (np.einsum("kij,ij->k", R, R_ref) - 1.0) / 2.0
            return mm, np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))

        def wrench(F, at):
            """``xfrc_applied`` of the force ``F`` through the dentition's centre, the body's centre of mass at ``at``."""
            return np.concatenate([F, np.cross(np.asarray(centre, float) - at, F)])

        P0 = local @ R0.T + pos0  # the planned tooth points
        close = closing_force * up
        d.xfrc_applied[b] = wrench(close, d.xipos[b])
        nseat = max(window, int(round(SEAT_S / timestep)))
        seat_q = np.empty((nseat, 7))
        for k in range(nseat):
            mujoco.mj_step(model, d)
            seat_q[k] = d.qpos[adr:adr + 7]
        if not np.all(np.isfinite(seat_q)):
            raise RuntimeError("the holding simulation diverged while seating")
        P, R = teeth(seat_q[-window:])
        Ps = P.mean(axis=0)  # the seated tooth points: their mean over the last window
        seated_mm, seated_deg = (float(v.mean()) for v in apart(P, R, P0, R0))

        # the pushes: one open-loop wrench sequence each, from the seated state
        ramp, held, rest = (int(round(s / timestep)) for s in (RAMP_S, PUSH_S, REST_S))
        rest = max(rest, window)
        n = 2 * ramp + held + rest
        scale = np.concatenate([np.linspace(0.0, 1.0, ramp + 1)[1:], np.ones(held),
                                np.linspace(1.0, 0.0, ramp + 1)[1:], np.zeros(rest)])
        names = (("forward", 1, "forward"), ("back", -1, "forward"), ("left", 1, "left"), ("right", -1, "left"))
        control = np.zeros((len(names), n, model.nbody * 6))
        for i, (_, sign, key) in enumerate(names):
            F = sign * push * np.asarray(directions[key], float)
            control[i, :, b * 6:b * 6 + 6] = [wrench(close + s * F, d.xipos[b]) for s in scale]
        full = mujoco.mjtState.mjSTATE_FULLPHYSICS
        state0 = np.empty(mujoco.mj_stateSize(model, full))
        mujoco.mj_getState(model, d, state0, full)
        threads = max(1, min(len(names), threads or os.cpu_count() or 1))
        datas = [mujoco.MjData(model) for _ in range(threads)]
        states, _ = rollout.rollout(model, datas, state0[None], control,
                                    control_spec=mujoco.mjtState.mjSTATE_XFRC_APPLIED,
                                    initial_warmstart=d.qacc_warmstart[None].copy())
        q0 = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_TIME)  # qpos follows the time in a state
        qpos = states[:, :, q0 + adr:q0 + adr + 7]
        if not np.all(np.isfinite(qpos)):
            raise RuntimeError("the holding simulation diverged under a push")
        rows, traces = [], []
        for i, (name, _, _) in enumerate(names):
            P, R = teeth(qpos[i])
            step_mm, _ = apart(P, R, P0, R0)
            mm, deg = apart(mean(P), R, P0, R0)
            deg = mean(deg)
            back_mm = float(np.linalg.norm(P[-window:].mean(axis=0) - Ps, axis=-1).max() * 1e3)
            traces.append(step_mm)
            rows.append({"push": name, "max_drift_mm": float(mm.max()), "max_rotation_deg": float(deg.max()),
                         "max_drift_any_step_mm": float(step_mm.max()), "after_mm": back_mm,
                         "ok": bool(mm.max() <= HOLD_MM and deg.max() <= HOLD_DEG and back_mm <= RETURN_MM)})
        # rattle: how far the tooth points move per step at rest (the end of each push's rest)
        rattle = np.median([np.linalg.norm(np.diff(teeth(qpos[i, -window:])[0], axis=0), axis=-1).max(axis=-1)
                            for i in range(len(names))]) * 1e3
        out = {"closing_force_n": closing_force, "push_n": push, "narrowphase": narrowphase,
               "timestep_s": float(model.opt.timestep), "window_s": window * float(model.opt.timestep),
               "seated_drift_mm": seated_mm, "seated_rotation_deg": seated_deg,
               "seated_pos": seat_q[-1, :3].tolist(), "seated_quat": seat_q[-1, 3:].tolist(),
               "rattle_mm_per_step": float(rattle),
               "pushes": rows, "limits": {"drift_mm": HOLD_MM, "rotation_deg": HOLD_DEG, "return_mm": RETURN_MM},
               "ok": seated_mm <= HOLD_MM and seated_deg <= HOLD_DEG and all(r["ok"] for r in rows)}
        if trace:
            out["trace"] = np.array(traces)
        return out
    finally:
        handle.detach()
