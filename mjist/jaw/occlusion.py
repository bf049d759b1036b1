"""Scripted occlusion search: where do the teeth fit? (``mjist occlusion``).

``search`` samples starting mandible poses around the closing path (a hinge opening, then
translations and a small rotation about a random axis, all relative to the scene's
``occlusion`` keyframe), lets each close under the scene's closing force with IST contacts in
``mujoco.rollout`` (several threads; the IST hook is thread-safe and answers do not depend on
threads), and scores every settled pose:

* **regions**: contact groups (IST multipoint, spheres closer than the contact offset) fall
  into six regions, left/right × anterior/premolar/molar, in the maxillary arch's own frame
  (its midline and front, ``mjist.jaw.arch``; not the world axes); more regions touched is better;
* **balance**: 1 − |L − R| / (L + R) over the contacts' left/right counts;
* **penetration**: the IST penetration volume (mm³), subtracted;
* **stability**: residual speed of the mandible (mm/s), subtracted (capped at 1);
* **distance field**: distances from 300 points of the mandible's occlusal surface (up-facing
  vertices within 3 mm of the maxilla at the reference pose) to the maxilla's inner spheres
  (``collision_primitive.points_distance``; each is within ε of the true distance, on average
  the maxilla's mean surface gap above it): their median, and the fraction closer than 0.3 mm
  plus that mean gap (how much of the arch meets), added twice.

``score = regions + 2·balance + 2·near − volume − min(speed, 1)``. Settled poses within 0.05 mm and
0.1° merge into one candidate (``starts`` counts them: the size of its basin). The best
``polish`` candidates get their last gap closed exactly: the mandible is turned about the
hinge to where coal's exact mesh distance reaches zero (first touch), so the reported pose does
not carry the inner spheres' surface gap. Everything is deterministic for a seed.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry.bvh import BVH
from ..mujoco.attach import load_model
from ..mujoco.scene import geom_pose, geom_pose_at, mesh_of
from ..query.api import Query
from . import pair as jawmod
from .scenes import pair_scene

SCENE = jawmod.BUNDLED / "occlusion_search.xml"
UP = np.array([0.0, 0.0, 1.0])  # world: from the mandible towards the maxilla (the jaw frame's +y)
JAW_TO_WORLD = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


@dataclass
class Candidate:
    """One settled occlusion: the mandible body's world pose and its figures."""

    rank: int
    score: float
    pos: np.ndarray
    quat: np.ndarray  # w, x, y, z
    starts: int  # starts that settled here
    contacts: int
    regions: list = field(default_factory=list)  # names of the regions touched
    region_counts: dict = field(default_factory=dict)
    balance: float = 0.0
    volume_mm3: float = 0.0
    speed_mm_s: float = 0.0
    near_fraction: float = 0.0  # occlusal points within 0.3 mm of the maxilla's spheres
    median_distance_mm: float | None = None  # their median distance
    coal_distance_mm: float | None = None  # at the polished pose
    polished_turn_deg: float | None = None  # how far polishing turned it about the hinge
    error: dict | None = None  # against the scene's occlusion keyframe

    def as_dict(self) -> dict:
        d = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}
        return d


def _reference(model):
    from .scenes import reference_pose

    pos, quat, _, hinge, _ = reference_pose(model)
    return pos, quat, hinge


def sample_starts(model, n: int, *, translation: float = 2e-3, rotation_deg: float = 3.0, opening_deg: float = 2.0,
                  seed: int = 0) -> np.ndarray:
    """Starting mandible poses ``(n, 7)`` (pos, quat w-first): open by up to ``opening_deg`` about
    the hinge, shifted by up to ``translation`` laterally and antero-posteriorly (half that
    vertically), turned by up to ``rotation_deg`` about a random axis through the hinge."""
    p0, q0, hinge = _reference(model)
    rng = np.random.default_rng(seed)
    R0 = Rotation.from_quat(q0[[1, 2, 3, 0]])
    out = np.empty((n, 7))
    for i in range(n):
        th = np.radians(rng.uniform(0.0, opening_deg))
        Rh = Rotation.from_rotvec(th * np.array([1.0, 0.0, 0.0]))  # the hinge axis is the world x axis
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        Rr = Rotation.from_rotvec(np.radians(rng.uniform(0.0, rotation_deg)) * axis)
        off = JAW_TO_WORLD @ (rng.uniform(-1.0, 1.0, 3) * translation * np.array([1.0, 0.5, 1.0]))
        R = Rr * Rh
        out[i, :3] = hinge + R.apply(p0 - hinge) + off
        x, y, z, w = (R * R0).as_quat()
        out[i, 3:] = (w, x, y, z)
    return out


def _separate(model, q: Query, gmx, gmd, Pmx, start: np.ndarray, step: float = 2e-4) -> np.ndarray:
    """Move a start down (away from the maxilla) until the inner spheres no longer overlap."""
    s = start.copy()
    for _ in range(100):
        if q.distance(Pmx, geom_pose_at(model, gmd, s[:3], s[3:])).distance > 0.0:
            return s
        s[:3] -= step * UP
    return s


NEAR = 3e-4  # m: an occlusal point this close to the maxilla's spheres counts as meeting it


def occlusal_points(model, gmx, gmd, n: int = 300, reach: float = 3e-3) -> np.ndarray:
    """Points of the mandible's occlusal surface (its geom frame): up-facing vertices within
    ``reach`` of the maxilla at the scene's reference pose (the teeth facing each other, not
    the rami), ``n`` of them spread evenly along the list."""
    import trimesh

    V, F = mesh_of(model, gmd)
    normals = trimesh.Trimesh(V, F, process=False).vertex_normals
    p0, q0, _ = _reference(model)
    P = geom_pose_at(model, gmd, p0, q0)
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    Px = geom_pose(d, gmx)
    up = P[:3, :3].T @ UP  # world up in the mandible's geom frame
    cand = np.flatnonzero(normals @ up > 0.5)
    cand = cand[np.linspace(0, cand.size - 1, min(4000, cand.size)).astype(np.int64)] if cand.size else cand
    T = np.linalg.inv(Px) @ P  # mandible geom frame -> maxilla geom frame
    Vx, Fx = mesh_of(model, gmx)
    dist = BVH.of_triangles(Vx, Fx).distance(V[cand] @ T[:3, :3].T + T[:3, 3], Vx, Fx)
    keep = cand[dist < reach]
    if keep.size == 0:
        return V[:0]
    return V[keep[np.linspace(0, keep.size - 1, min(n, keep.size)).astype(np.int64)]]


def _distance_field(Nmx, Pmx, Pmd, pts, st, g, out):
    from ..query.primitive import points_distance

    T = np.linalg.inv(Pmx) @ Pmd  # mandible geom frame -> maxilla tree frame
    P = pts @ T[:3, :3].T + T[:3, 3]
    xf = np.array([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0])
    points_distance(Nmx, P, xf, st, g, out[:len(P)])
    return out[:len(P)]


def _score_pose(model, q: Query, gmx, gmd, Pmx, pos, quat, vel, offset, frame, field) -> dict:
    Pmd = geom_pose_at(model, gmd, pos, quat)
    c = q.contacts(Pmx, Pmd, max_contacts=32, split_depth=4, margin=offset)
    vol = q.penetration_volume(Pmx, Pmd).volume
    counts: dict = {}
    for key in frame.regions(c.positions) if c.count else []:
        counts[key] = counts.get(key, 0) + 1
    names = sorted(counts)
    left = sum(v for k, v in counts.items() if k.startswith("left"))
    right = sum(v for k, v in counts.items() if k.startswith("right"))
    balance = 1.0 - abs(left - right) / (left + right) if left + right else 0.0
    speed = float(np.linalg.norm(vel[:3]) * 1e3)  # mm/s
    dist, gap = field(Pmd)
    near = float(np.mean(dist < NEAR + gap)) if dist.size else 0.0  # the spheres sit ~gap inside
    score = len(names) + 2.0 * balance + 2.0 * near - vol * 1e9 - min(speed, 1.0)
    return {"score": float(score), "contacts": int(c.count), "regions": names, "region_counts": counts,
            "balance": float(balance), "volume_mm3": float(vol * 1e9), "speed_mm_s": speed,
            "near_fraction": near, "median_distance_mm": float(np.median(dist) * 1e3) if dist.size else None}


def arch_frames(model, gmx, gmd) -> dict:
    """Both arches' frames (world coordinates) at the scene's reference occlusion (``arch.arch_frame``)."""
    from .arch import arch_frame, occlusal_points

    p0, q0, _ = _reference(model)
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    world = {}
    for g, P in ((gmx, geom_pose(d, gmx)), (gmd, geom_pose_at(model, gmd, p0, q0))):
        V, F = mesh_of(model, g)
        world[g] = (V @ P[:3, :3].T + P[:3, 3], F)
    (Vx, Fx), (Vd, Fd) = world[gmx], world[gmd]
    return {"maxilla": arch_frame(occlusal_points(Vx, Vd, Fd, up=UP), UP), "mandible": arch_frame(occlusal_points(Vd, Vx, Fx, up=UP), UP)}


def pose_error(model, gmd, pos, quat, ref_pos, ref_quat, sample: np.ndarray) -> dict:
    """Difference of two mandible poses: rotation angle, origin shift, RMS and max tooth-point shift."""
    Pa = geom_pose_at(model, gmd, pos, quat)
    Pb = geom_pose_at(model, gmd, ref_pos, ref_quat)
    A = sample @ Pa[:3, :3].T + Pa[:3, 3]
    B = sample @ Pb[:3, :3].T + Pb[:3, 3]
    dv = np.linalg.norm(A - B, axis=1)
    ang = (Rotation.from_quat(np.asarray(quat)[[1, 2, 3, 0]]) * Rotation.from_quat(np.asarray(ref_quat)[[1, 2, 3, 0]]).inv()).magnitude()
    return {"rotation_deg": float(np.degrees(ang)), "origin_mm": float(np.linalg.norm(np.asarray(pos) - ref_pos) * 1e3),
            "rms_mm": float(np.sqrt(np.mean(dv ** 2)) * 1e3), "max_mm": float(dv.max() * 1e3)}


def _hinge_turn(pos, quat, hinge, phi):
    """Body pose turned by ``phi`` (rad) about the hinge axis (world x through ``hinge``)."""
    R = Rotation.from_rotvec(phi * np.array([1.0, 0.0, 0.0]))
    x, y, z, w = (R * Rotation.from_quat(np.asarray(quat)[[1, 2, 3, 0]])).as_quat()
    return hinge + R.apply(np.asarray(pos) - hinge), np.array([w, x, y, z])


POLISH_GJK_TOL = 1e-9  # coal's collision test in the polish (its default 1e-6 touches at ~1 µm)


def _polish(model, gmd, Pmx, bvh, pos, quat, hinge, reach_deg: float = 2.0):
    """Turn the pose about the hinge to coal's first touch (to 1e-5°, ~10 nm at the incisors).

    The settled pose stops short of the true surfaces by about the inner spheres' surface gap
    (the offset is a mean): the last bit of the closing path is taken with exact geometry.
    Touch is coal's collision test (triangle against triangle), not its distance reaching
    zero: coal's BVH distance can return 0 for meshes a few hundredths of a millimetre apart
    (its collision test and its own nearest points disagree), which would stop the bisection short.
    Its GJK tolerance is tightened (``POLISH_GJK_TOL``): at coal's default, meshes 1 µm apart
    already collide.
    Returns (pos, quat, turn in degrees, coal distance there).
    """
    def pose(phi):
        p, q = _hinge_turn(pos, quat, hinge, phi)
        return geom_pose_at(model, gmd, p, q)

    def touches(phi):
        return jawmod.coal_collides(bvh[0], Pmx, bvh[1], pose(phi), tol=POLISH_GJK_TOL)

    reach = np.radians(reach_deg)
    t0 = touches(0.0)
    # closing turns by a negative angle (the scenes open by a positive one about +x)
    apart, touching = (reach, 0.0) if t0 else (0.0, -reach)
    if touches(apart) or not touches(touching):
        return pos, quat, 0.0, jawmod.coal_distance(bvh[0], Pmx, bvh[1], pose(0.0))  # no crossing within reach
    for _ in range(60):
        if abs(touching - apart) < np.radians(1e-5):
            break
        mid = 0.5 * (apart + touching)
        if touches(mid):
            touching = mid
        else:
            apart = mid
    p, q = _hinge_turn(pos, quat, hinge, apart)
    return p, q, float(np.degrees(apart)), jawmod.coal_distance(bvh[0], Pmx, bvh[1], pose(apart))


def search(scene=None, *, data=None, starts: int = 64, translation: float = 2e-3, rotation_deg: float = 3.0,
           opening_deg: float = 2.0, seconds: float = 0.4, seed: int = 0, threads: int | None = None,
           top: int = 5, polish: int = 3, progress: bool = True, cache_dir=None, out_dir=None, pair: dict | None = None) -> dict:
    """Sample, close and rank mandible poses; return ``{"candidates": [...], ...}`` (best first).

    Parameters
    ----------
    scene : path, optional
        An occlusion-search scene (default ``models/occlusion_search.xml``); or ``data``: a jaw
        pair folder whose scene is generated into ``out_dir``, read with ``pair`` options
        (units, up, hinge, repair, tmj: ``scenes.pair_scene``).
    starts : int
        Starting poses, sampled with ``seed`` within ``translation`` (m), ``rotation_deg`` and
        ``opening_deg`` of the scene's ``occlusion`` keyframe.
    seconds : float
        Simulated closing time per start.
    threads : int, optional
        ``mujoco.rollout`` threads (default: the CPU count); results do not depend on it.
    top, polish : int
        Candidates returned; how many of the best are polished with coal.
    """
    if data is not None:
        scene = pair_scene(data, out_dir or "out/occlusion", "occlusion", progress=progress, **(pair or {}))
    scene = Path(scene or SCENE)
    t0 = time.perf_counter()
    model, handle = load_model(scene, progress=progress, cache_dir=cache_dir)
    try:
        gmx = handle.geoms["maxilla"]
        gmd = handle.geoms["mandible"]
        q = Query(handle.trees["maxilla"], handle.trees["mandible"])
        d = mujoco.MjData(model)
        mujoco.mj_forward(model, d)
        Pmx = geom_pose(d, gmx)
        ref_pos, ref_quat, hinge = _reference(model)
        V, _ = mesh_of(model, gmd)
        frames = arch_frames(model, gmx, gmd)
        sample = V[np.random.default_rng(0).choice(len(V), min(2000, len(V)), replace=False)]
        setup_s = time.perf_counter() - t0

        X = sample_starts(model, starts, translation=translation, rotation_deg=rotation_deg, opening_deg=opening_deg, seed=seed)
        X = np.array([_separate(model, q, gmx, gmd, Pmx, x) for x in X])
        nthread = int(threads or os.cpu_count() or 1)
        nstep = int(round(seconds / model.opt.timestep))
        t1 = time.perf_counter()
        final = _close(model, X, nstep, nthread, progress)
        sim_s = time.perf_counter() - t1

        field = _field_of(model, handle, gmx, gmd, Pmx)
        scored = _score_all(model, handle, q, gmx, gmd, Pmx, final, X, frames["maxilla"], field)
        clusters = _cluster(model, gmd, scored, sample)
        bvh = (jawmod.coal_bvh(*mesh_of(model, gmx)), jawmod.coal_bvh(*mesh_of(model, gmd)))
        cands = []
        for rank, (i, members) in enumerate(clusters[:top]):
            s = scored[i]
            c = Candidate(rank + 1, s["score"], s["pos"], s["quat"], len(members), s["contacts"], s["regions"],
                          s["region_counts"], s["balance"], s["volume_mm3"], s["speed_mm_s"], s["near_fraction"],
                          s["median_distance_mm"])
            if rank < polish:
                c.pos, c.quat, turn, dist = _polish(model, gmd, Pmx, bvh, s["pos"], s["quat"], hinge)
                c.polished_turn_deg, c.coal_distance_mm = turn, dist * 1e3
            c.error = pose_error(model, gmd, c.pos, c.quat, ref_pos, ref_quat, sample)
            cands.append(c)
        res = {
            "scene": str(scene), "starts": starts, "seed": seed, "threads": nthread, "steps_per_start": nstep,
            "translation_mm": translation * 1e3, "rotation_deg": rotation_deg, "opening_deg": opening_deg,
            "setup_s": setup_s, "simulate_s": sim_s, "starts_per_second": starts / sim_s, "total_s": time.perf_counter() - t0,
            "error_bound_mm": handle.pairs[0].error_bound * 1e3, "offset_mm": handle.pairs[0].offset * 1e3,
            "reference_pos": ref_pos.tolist(), "reference_quat": ref_quat.tolist(),
            "arches": {k: f.as_dict() for k, f in frames.items()},
            "midline_offset_mm": float((frames["mandible"].origin - frames["maxilla"].origin) @ frames["maxilla"].left * 1e3),
            "candidates": [c.as_dict() for c in cands],
            "landscape": [{"start": s["start"].tolist(), "score": s["score"], "pos": s["pos"].tolist(),
                           "error": pose_error(model, gmd, s["pos"], s["quat"], ref_pos, ref_quat, sample[:200])}
                          for s in scored],
        }
        res["_model"], res["_handle"] = model, handle
        return res
    except Exception:
        handle.detach()
        raise


def _close(model, X, nstep: int, nthread: int, progress: bool) -> np.ndarray:
    """Each start ``X[i]`` (mandible qpos) closed for ``nstep`` steps with ``mujoco.rollout``; final states."""
    from mujoco import rollout

    starts = len(X)
    d = mujoco.MjData(model)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    x0 = np.empty((starts, mujoco.mj_stateSize(model, spec)))
    for i in range(starts):
        mujoco.mj_resetData(model, d)
        d.qpos[:7] = X[i]
        mujoco.mj_getState(model, d, x0[i], spec)
    datas = [mujoco.MjData(model) for _ in range(nthread)]
    final = np.empty_like(x0)
    chunk = max(1, min(starts, 32))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=starts, desc="closing", unit="start", leave=False)
    for a in range(0, starts, chunk):
        st, _ = rollout.rollout(model, datas, x0[a:a + chunk], nstep=nstep)
        final[a:a + chunk] = st[:, -1, :]
        if bar is not None:
            bar.update(min(chunk, starts - a))
    if bar is not None:
        bar.close()
    return final


def _field_of(model, handle, gmx, gmd, Pmx):
    """The distance-field score's function of a mandible pose: (occlusal point distances, mean gap)."""
    from ..query.traverse import pack, stack_size

    Nmx = pack(handle.trees["maxilla"])
    pts = occlusal_points(model, gmx, gmd)
    st = np.zeros(stack_size(Nmx), np.int64)
    g = np.zeros(3)
    buf = np.zeros(max(len(pts), 1))
    gap = float(handle.trees["maxilla"].info.get("mean_gap", 0.0))

    def field(Pmd):
        return _distance_field(Nmx, Pmx, Pmd, pts, st, g, buf), gap

    return field


def _score_all(model, handle, q, gmx, gmd, Pmx, final, X, frame, field) -> list[dict]:
    """Every settled pose's scores (state layout: time, qpos (nq), qvel (nv), ...)."""
    nq, nv = model.nq, model.nv
    qpos = final[:, 1:1 + nq]
    qvel = final[:, 1 + nq:1 + nq + nv]
    offset = handle.pairs[0].offset
    scored = []
    for i in range(len(final)):
        quat = qpos[i, 3:7] / np.linalg.norm(qpos[i, 3:7])
        s = _score_pose(model, q, gmx, gmd, Pmx, qpos[i, :3], quat, qvel[i], offset, frame, field)
        s.update(pos=qpos[i, :3].copy(), quat=quat, start=X[i])
        scored.append(s)
    return scored


def _cluster(model, gmd, scored: list[dict], sample) -> list[tuple[int, list[int]]]:
    """Settled poses within 0.05 mm and 0.1° merged, best score first: (representative, members)."""
    order = sorted(range(len(scored)), key=lambda i: (-scored[i]["score"], i))
    clusters = []
    for i in order:
        for c in clusters:
            r = scored[c[0]]
            if (np.linalg.norm(scored[i]["pos"] - r["pos"]) < 5e-5
                    and pose_error(model, gmd, scored[i]["pos"], scored[i]["quat"], r["pos"], r["quat"], sample[:1])["rotation_deg"] < 0.1):
                c[1].append(i)
                break
        else:
            clusters.append((i, [i]))
    return clusters


def write_outputs(res: dict, out_dir, picture: bool = True) -> list[str]:
    """JSON of the candidates, the score landscape plot, a picture of the best occlusion."""
    out = Path(out_dir)
    os.makedirs(out, exist_ok=True)
    written = []
    clean = {k: v for k, v in res.items() if not k.startswith("_")}
    (out / "occlusion.json").write_text(json.dumps(clean, indent=1))
    written.append(str(out / "occlusion.json"))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    L = res["landscape"]
    st = np.array([x["start"][:3] for x in L])
    jaw = (st - np.asarray(res["reference_pos"])) @ JAW_TO_WORLD  # world offsets -> jaw frame (rows: J^T v)
    sc = np.array([x["score"] for x in L])
    err = np.array([x["error"]["rms_mm"] for x in L])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    p = ax[0].scatter(jaw[:, 0] * 1e3, jaw[:, 2] * 1e3, c=sc, cmap="viridis", s=25)
    fig.colorbar(p, ax=ax[0], label="score of the settled pose")
    ax[0].set_xlabel("start: lateral offset from the reference occlusion (mm)")
    ax[0].set_ylabel("start: antero-posterior offset (mm)")
    ax[0].set_title("where each start settles: score")
    ax[1].scatter(err, sc, s=15)
    ax[1].set_xlabel("settled pose: RMS tooth shift from the reference occlusion (mm)")
    ax[1].set_ylabel("score")
    ax[1].set_title("score landscape")
    fig.tight_layout()
    fig.savefig(out / "landscape.png", dpi=110)
    plt.close(fig)
    written.append(str(out / "landscape.png"))
    if picture and res["candidates"]:
        from .demo import render

        model, handle = res["_model"], res["_handle"]
        d = mujoco.MjData(model)
        best = res["candidates"][0]
        d.qpos[:3] = best["pos"]
        d.qpos[3:7] = best["quat"]
        mujoco.mj_forward(model, d)
        try:
            written.append(render(model, d, out / "best.png", handle=handle))
        except Exception as exc:  # no GL: the numbers still stand
            print(f"picture skipped ({type(exc).__name__}: {exc}); set MUJOCO_GL=egl or osmesa")
    return written


def write_contact_map(res: dict, out_dir) -> tuple[dict, list[str]]:
    """The contact map of a search's best candidate (``contactmap.contact_map``) and its files in ``out_dir``."""
    from . import contactmap
    from .arch import ArchFrame

    best = res["candidates"][0]
    model, handle = res["_model"], res["_handle"]
    frames = {k: ArchFrame.from_dict(v) for k, v in res["arches"].items()}
    cmap = contactmap.contact_map(model, handle, best["pos"], best["quat"], frames=frames)
    return cmap, contactmap.write(cmap, frames, out_dir)


def main(scene=None, data=None, starts=64, translation=2e-3, rotation_deg=3.0, threads=None, seed=0, top=5,
         out="out/occlusion", progress=True, pair: dict | None = None, contact_map: bool = True) -> int:
    res = search(scene, data=data, starts=starts, translation=translation, rotation_deg=rotation_deg,
                 threads=threads, seed=seed, top=top, progress=progress, out_dir=out, pair=pair)
    try:
        print(f"{res['starts']} starts closed in {res['simulate_s']:.1f} s on {res['threads']} thread(s) "
              f"({res['starts_per_second']:.1f} starts/s), IST ε1+ε2 {res['error_bound_mm']:.2f} mm")
        for c in res["candidates"]:
            e = c["error"]
            pol = (f", polished {c['polished_turn_deg']:+.3f}° (coal gap {c['coal_distance_mm']:.4f} mm)"
                   if c["polished_turn_deg"] is not None else "")
            print(f"#{c['rank']} score {c['score']:.2f}  {c['starts']} start(s)  {c['contacts']} contacts in "
                  f"{', '.join(c['regions']) or 'no region'}  vs reference: {e['rms_mm']:.3f} mm RMS, {e['rotation_deg']:.3f}°{pol}")
        written = write_outputs(res, out)
        if contact_map and res["candidates"]:
            cmap, files = write_contact_map(res, out)
            written += files
            for name in ("maxilla", "mandible"):
                rows = ", ".join(f"{r['region']} {r['contact_area_mm2']:.1f} mm² (closest {r['closest_mm']:.3f} mm)"
                                 for r in cmap[name].regions if r["closest_mm"] < 0.4)
                ck = cmap[name].check
                print(f"contact map   {name}: {rows or 'nothing within 0.4 mm'}; "
                      f"exact check on {ck.get('sampled', 0)} vertices: {ck.get('above_upper', 0)} above the certified upper "
                      f"bound, {ck.get('below_lower_outside', 0)} non-penetrating below the lower bound, estimate within "
                      f"{ck.get('max_error_of_estimate_mm', 0):.3f} mm")
        for f in written:
            print(f"written       {f}")
    finally:
        res["_handle"].detach()
    return 0
