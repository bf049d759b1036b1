"""Scripted occlusion search: where do the teeth fit? (``mjist occlusion``).

``search`` samples starting mandible poses around the closing path (a hinge opening, then
translations and a small rotation about a random axis, all relative to the scene's
``occlusion`` keyframe), lets each close under the scene's closing force with IST contacts in
``mujoco.rollout`` until it settles (the IST hook is thread-safe and its answers do not depend
on threads), and judges every settled pose on the true surfaces (``ranking``): turned about
the hinge to where the arches just touch, how far apart the occlusal surfaces stay over the
dentition, every region counting the same. The most closed pose at zero penetration ranks first.

Settled poses within ``BASIN_MM`` of each other (largest tooth-point shift) form one basin;
each basin is a candidate, its best-judged start the reported pose, its size how many starts
settled there. The answer says how sure it is: the margin to the runner-up basin against the
scores' spread inside both basins; within that, the result is "ambiguous" and both are shown.
The best ``polish`` candidates are brought to touch with every occlusal vertex and checked with
coal (exact triangle collision); where an edge still crosses an edge, they are opened to coal's
first touch. Deterministic for a seed.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from ..mujoco.attach import load_model
from ..query.api import Query
from . import pair as jawmod
from . import ranking
from .exact import near_faces
from .ranking import Candidate, shift_mm
from .scenepair import JAW_TO_WORLD, UP, ScenePair, apply_pose, file_transform, resolve
from .scenes import pair_scene

SCENE = jawmod.BUNDLED / "occlusion_search.xml"
BASIN_MM = 0.2  # settled poses closer than this (largest tooth-point shift at touch) are one basin
SETTLED = 0.1  # mm/s: a start has settled when no tooth point moves faster (last step, and last CHUNK_S on average)
FIRST_CHUNK_S = 0.3  # s of closing before the first settle check; then CHUNK_S at a time
CHUNK_S = 0.1
AMBIGUOUS_FLOOR_MM = 0.002  # the margin below which two basins are never told apart (point sampling noise)
# the starts' spread around a registered pair's occlusion (``register``): the registration has placed
# the shared arches up to 2.0 mm / 2.7° from their occlusion (tests/jaw/test_register.py), which the
# starts must cover; wider spends starts on poses the teeth are far from
REGISTERED_TRANSLATION = 3e-3
REGISTERED_ROTATION_DEG = 5.0
# a pose the files gave is one more start when it is within this of the registered occlusion
# (largest tooth-point shift, mm; rotation, degrees): a pair given open or moved a little, not one
# given in an unrelated frame
GIVEN_REACH_MM, GIVEN_REACH_DEG = 15.0, 20.0


def _rounds(starts: int) -> list[tuple[int, float]]:
    """The search's rounds: (starts, share of ``translation``). Half the starts sample the
    condyles' seat over the whole range, then a quarter within a quarter of it around the best
    pose so far, then the rest within a sixteenth: the seat is found to about a tenth of a
    millimetre with the starts one wide round would spend."""
    a = max(1, starts // 2)
    b = max(0, min(starts - a, starts // 4))
    return [(m, s) for m, s in ((a, 1.0), (b, 0.25), (starts - a - b, 0.0625)) if m > 0]


def sample_starts(pair: ScenePair, n: int, *, translation: float = 2e-3, rotation_deg: float = 3.0, opening_deg: float = 2.0,
                  seed=0, centre: tuple | None = None) -> np.ndarray:
    """Starting mandible poses ``(n, 7)`` (pos, quat w-first): open by up to ``opening_deg`` about
    the hinge, shifted by up to ``translation`` laterally and antero-posteriorly (half that
    vertically), turned by up to ``rotation_deg`` about a random axis through the hinge; around
    the reference occlusion, or around ``centre`` (mandible body ``(pos, quat)``)."""
    p0, q0 = (pair.reference_pos, pair.reference_quat) if centre is None else (np.asarray(centre[0]), np.asarray(centre[1]))
    hinge = condyle_seats(pair, np.r_[p0, q0])[0]
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


def condyle_seats(pair: ScenePair, X) -> np.ndarray:
    """Where the condylar axis' centre stands (world, ``(n, 3)``) for each mandible body pose ``X[i]``.

    The search's TMJ holds the condyles at a seat (the scene's mocap body ``condyles``). A pair
    given in occlusion has them seated; a pair given open says where they were, not where they
    seat, so the search samples the seat forward and back around this point of its best pose.
    """
    R0 = Rotation.from_quat(pair.reference_quat[[1, 2, 3, 0]])
    local = R0.inv().apply(pair.hinge - pair.reference_pos)  # the hinge in the mandible body's frame
    X = np.atleast_2d(np.asarray(X, float))
    R = Rotation.from_quat(X[:, [4, 5, 6, 3]])
    return X[:, :3] + R.apply(local)


def _separate(pair: ScenePair, q: Query, start: np.ndarray, step: float = 2e-4) -> np.ndarray:
    """Move a start down (away from the maxilla) until the inner spheres no longer overlap."""
    s = start.copy()
    for _ in range(100):
        if q.distance(pair.maxilla_pose, pair.pose(s[:3], s[3:])).distance > 0.0:
            return s
        s[:3] -= step * UP
    return s


def pose_error(pair: ScenePair, pos, quat, ref_pos=None, ref_quat=None, points=None) -> dict:
    """Difference of two mandible poses over tooth points: largest and RMS shift (mm), rotation (°).

    ``points`` (mandible geom frame) default to the occlusal points of the pair's sample; the
    reference pose defaults to the scene's ``occlusion`` keyframe.
    """
    ref_pos = pair.reference_pos if ref_pos is None else np.asarray(ref_pos, float)
    ref_quat = pair.reference_quat if ref_quat is None else np.asarray(ref_quat, float)
    Pa, Pb = pair.pose(pos, quat), pair.pose(ref_pos, ref_quat)
    S = np.asarray(points, float)
    dv = np.linalg.norm(S @ Pa[:3, :3].T + Pa[:3, 3] - (S @ Pb[:3, :3].T + Pb[:3, 3]), axis=1)
    ang = Rotation.from_matrix(Pa[:3, :3] @ Pb[:3, :3].T).magnitude()
    return {"rotation_deg": float(np.degrees(ang)), "origin_mm": float(np.linalg.norm(np.asarray(pos) - ref_pos) * 1e3),
            "rms_mm": float(np.sqrt(np.mean(dv ** 2)) * 1e3), "max_mm": float(dv.max() * 1e3)}


POLISH_GJK_TOL = 1e-9  # coal's collision test in the polish (its default 1e-6 touches at ~1 µm)
# how far past the occlusal vertices' touch coal's first touch is sought (an edge crossing an edge
# between vertices penetrates by a fraction of an edge's sag) and to what precision: ~8 µm and
# ~0.2 µm at the incisors; each halving is one coal test
POLISH_REACH_DEG = 0.005
POLISH_TOL_DEG = 1e-4


def _near_faces(pair: ScenePair, P, hinge, reach: float):
    """coal BVHs of the only faces that can meet while the mandible, at ``P``, turns by at most
    ``reach`` (rad) about the hinge (``exact.near_faces`` with that turn's largest move, its
    farthest vertex's arc), or None when that keeps most faces anyway."""

    (Vx, Fx), (Vd, Fd) = pair.maxilla, pair.mandible
    Wd = apply_pose(P, Vd)
    move = reach * float(np.linalg.norm(Wd - hinge, axis=1).max()) * (1.0 + 1e-6) + 1e-9
    kx, kd = near_faces((apply_pose(pair.maxilla_pose, Vx), Fx), (Wd, Fd), move)
    if kx.sum() + kd.sum() > 0.5 * (len(Fx) + len(Fd)) or not (kx.any() and kd.any()):
        return None
    return jawmod.coal_bvh(Vx, Fx[kx]), jawmod.coal_bvh(Vd, Fd[kd])


def _polish(pair: ScenePair, bvh, P, reach_deg: float = POLISH_REACH_DEG):
    """The pose brought to touch with every occlusal vertex, then checked with coal.

    The ranking touches with a sample of the occlusal points; here every vertex of both occlusal
    surfaces takes part (``ranking.touch`` on a dense sample), and coal's triangle test, which
    also sees an edge crossing an edge between vertices, checks the result: a pose coal finds
    apart is kept; one it finds touching is opened about the hinge to coal's first touch
    (bisection within ``reach_deg`` to ``POLISH_TOL_DEG``). Coal's GJK tolerance is tightened
    (``POLISH_GJK_TOL``): at its default, meshes 1 µm apart already collide. The tests within
    ``reach_deg`` see only the faces that can meet there (``_near_faces``); on the whole arches
    a test costs seconds on 340 k-vertex scans. Returns (pose, extra opening in degrees, coal
    distance there).
    """
    dense = _sample(pair, P, n=None)
    P, turn = ranking.touch(dense, P)
    near = _near_faces(pair, P, dense.hinge, np.radians(reach_deg))

    def touches(phi, within=True):
        b = near if within and near is not None else bvh
        return jawmod.coal_collides(b[0], pair.maxilla_pose, b[1], ranking.hinge_turn(dense, P, phi), tol=POLISH_GJK_TOL)

    apart, touching = np.radians(reach_deg), 0.0
    if touches(0.0):
        while touches(apart, apart <= np.radians(reach_deg)) and apart < np.radians(1.0):  # deeper: widen the bracket
            touching, apart = apart, 4.0 * apart
        if apart > np.radians(reach_deg):
            near = None  # beyond the reach the faces kept are not enough: the whole meshes
        while apart - touching > np.radians(POLISH_TOL_DEG):
            mid = 0.5 * (apart + touching)
            if touches(mid):
                touching = mid
            else:
                apart = mid
    else:
        apart = 0.0
    Q = ranking.hinge_turn(dense, P, apart)
    return Q, float(np.degrees(turn + apart)), jawmod.coal_distance(bvh[0], pair.maxilla_pose, bvh[1], Q)


def search(scene=None, *, data=None, starts: int = 64, translation: float | None = None, rotation_deg: float | None = None,
           opening_deg: float = 2.0, seconds: float = 2.0, seed: int = 0, threads: int | None = None,
           top: int = 5, polish: int = 1, seat: float | None = None, progress: bool = True, cache_dir=None, out_dir=None,
           pair: dict | None = None) -> dict:
    """Sample, close and rank mandible poses; return ``{"candidates": [...], ...}`` (best first).

    Parameters
    ----------
    scene : path, optional
        An occlusion-search scene (default ``models/occlusion_search.xml``); or ``data``: a jaw
        pair folder whose scene is generated into ``out_dir``, read with ``pair`` options
        (units, up, hinge, repair, tmj, register: ``scenes.pair_scene``). A pair folder is
        registered from the arches' shapes (``register``) unless ``pair`` says ``register=False``:
        the search starts from the anatomy, and the pose the files gave is one more start.
    starts : int
        Starting poses, sampled with ``seed`` within ``translation`` (m), ``rotation_deg`` and
        ``opening_deg`` of the scene's ``occlusion`` keyframe (defaults: 2 mm and 3°, or
        ``REGISTERED_TRANSLATION`` and ``REGISTERED_ROTATION_DEG`` around a registration).
    seconds : float
        Most simulated closing time per start; a start stops once settled (``SETTLED``).
    threads : int, optional
        ``mujoco.rollout`` threads (default: the CPU count); results do not depend on it.
    top, polish : int
        Candidates (basins) returned; how many of the best are brought to touch with every
        occlusal vertex and checked with coal (``_polish``).
    seat : float, optional
        How far forward or back of the reference the condyles may seat (m). Default: the scene's
        ``pair.json`` (``arch.SEAT_UNCERTAINTY`` for a pair given open), else 0: the condyles stay
        where the reference has them. Above 0 the search runs in rounds (``_rounds``), each
        sampling the seat more narrowly around the best pose so far.

    Returns
    -------
    dict
        ``candidates`` (``ranking.Candidate.as_dict``, best first), ``confidence`` (margin to the
        runner-up basin, both basins' sizes and spreads, ``ambiguous``), ``landscape`` (every
        start: settled pose, score, settle figures, error against the reference), timings,
        ``arches`` (both arch frames), ``error_bound_mm`` of the IST trees used to close.
    """
    if data is not None or (pair or {}).get("maxilla"):
        scene = pair_scene(data, out_dir or "out/occlusion", "occlusion", progress=progress, **{"register": True, **(pair or {})})
    scene = Path(scene or SCENE)
    meta = scene.parent / "pair.json"  # a scene made from a user's pair: its hinge, how sure it is
    meta = json.loads(meta.read_text()) if meta.exists() else {}
    registered = bool(meta.get("registration", {}).get("used"))
    if translation is None:
        translation = REGISTERED_TRANSLATION if registered else 2e-3
    if rotation_deg is None:
        rotation_deg = REGISTERED_ROTATION_DEG if registered else 3.0
    if seat is None:
        seat = float(meta.get("seat_uncertainty_mm") or 0.0) * 1e-3
    t0 = time.perf_counter()
    model, handle = load_model(scene, progress=progress, cache_dir=cache_dir)
    try:
        jp = resolve(model, handle)
        q = Query(handle.trees["maxilla"], handle.trees["mandible"])
        jp.sample = _sample(jp, jp.reference)
        given = _given_start(jp, meta)
        setup_s = time.perf_counter() - t0

        nthread = int(threads or os.cpu_count() or 1)
        X, final, settle, judged = np.empty((0, 7)), [], [], []
        timing = {"sim": 0.0, "rank": 0.0}
        picked = jp.reference

        def close_round(Xr, seats):
            """Close the starts ``Xr`` with the condyles at ``seats``, judge them, and return the
            best start so far (the occlusal sample re-picked where it closed, when it moved)."""
            nonlocal X, final, settle, judged, picked
            Xr = np.array([_separate(jp, q, x) for x in Xr])
            t1 = time.perf_counter()
            fr, sr = _close(jp, Xr, seconds, nthread, progress, seats)
            timing["sim"] += time.perf_counter() - t1
            t2 = time.perf_counter()
            X, final, settle = np.vstack([X, Xr]), final + fr, settle + sr
            judged += _judge_all(jp, fr)
            # the occlusal surfaces are those that meet: re-pick them where the best start closed
            # (a pair given far from its occlusion has its reference where only the front teeth meet)
            best = _best(judged, settle)
            if shift_mm(judged[best].pose, picked, jp.sample.mandible_points) > BASIN_MM:
                picked = judged[best].pose
                jp.sample = _sample(jp, picked)
                judged = _judge_all(jp, final)
                best = _best(judged, settle)
            timing["rank"] += time.perf_counter() - t2
            return best, judged

        centre = None
        for r, (m, scale) in enumerate(_rounds(starts) if seat > 0 else [(starts, 1.0)]):
            # each round samples the condyles' seat around the best pose so far, more narrowly
            turn = rotation_deg * max(scale, 0.25) if registered else rotation_deg  # a registration's turn narrows too
            Xr = sample_starts(jp, m, translation=translation * scale, rotation_deg=turn, opening_deg=opening_deg,
                               seed=(seed, r) if r else seed, centre=centre)
            if r == 0 and given.get("start") is not None:  # the pose the files gave: one more start
                Xr = np.vstack([Xr, given["start"]])
            seats = np.tile(jp.hinge, (len(Xr), 1))
            if registered:
                # a registration places the teeth, not the condyles: each start seats them where it
                # puts them (side and front-back; the discs hold their height)
                seats[:, :2] = condyle_seats(jp, Xr)[:, :2]
            else:  # forward or back only: the discs hold the condyles' height, the fossae their side
                if centre is not None:
                    seats[:, 1] = condyle_seats(jp, np.r_[centre[0], centre[1]])[0, 1]
                seats[:, 1] += np.random.default_rng((seed, r, 1)).uniform(-1.0, 1.0, len(Xr)) * seat * scale
            best, _ = close_round(Xr, seats)
            centre = jp.body(judged[best].pose)
        sim_s, rank_s = timing["sim"], timing["rank"]
        t2 = time.perf_counter()
        basins = _basins(jp, judged, settle)
        rank_s += time.perf_counter() - t2
        bvh = (jawmod.coal_bvh(*jp.maxilla), jawmod.coal_bvh(*jp.mandible))
        cands = []
        for rank, b in enumerate(basins[:top]):
            j, members = b["judgement"], b["members"]
            lead = settle[members[0]]
            c = Candidate(rank + 1, j.score, *jp.body(j.pose), len(members), j.interocclusal_mm, j.contact_fraction,
                          j.regions_in_contact, j.region_mm, j.balance, j.turn_deg, b["settled"],
                          float(np.median([settle[i]["drift_mm_s"] for i in members])), lead["last_step_mm"], b["spread"])
            if rank < polish:
                Q, extra, dist = _polish(jp, bvh, j.pose)
                c.pos, c.quat = jp.body(Q)
                c.turn_deg += extra
                c.coal_distance_mm = dist * 1e3
            c.error = pose_error(jp, c.pos, c.quat, points=jp.sample.mandible_points)
            cands.append(c)
        res = {
            "scene": str(scene), "starts": starts, "seed": seed, "threads": nthread, "max_seconds": seconds,
            "translation_mm": translation * 1e3, "rotation_deg": rotation_deg, "opening_deg": opening_deg,
            "setup_s": setup_s, "simulate_s": sim_s, "rank_s": rank_s, "starts_per_second": starts / sim_s,
            "settled": int(sum(s["settled"] for s in settle)), "unstable": int(sum(s["unstable"] for s in settle)),
            "total_s": time.perf_counter() - t0,
            "error_bound_mm": handle.pairs[0].error_bound * 1e3, "offset_mm": handle.pairs[0].offset * 1e3,
            "reference_pos": jp.reference_pos.tolist(), "reference_quat": jp.reference_quat.tolist(),
            "hinge": jp.hinge.tolist(), "arches": {k: f.as_dict() for k, f in jp.frames.items()},
            "midline_offset_mm": float((jp.frames["mandible"].origin - jp.frames["maxilla"].origin) @ jp.frames["maxilla"].left * 1e3),
            "occlusal_points": [len(jp.sample.mandible_points), len(jp.sample.maxilla_points)],
            "confidence": _confidence(cands),
            "candidates": [c.as_dict() for c in cands],
            "landscape": [_landscape_row(jp, X[i], final[i], judged[i], settle[i]) for i in range(len(X))],
        }
        res["rank_correlation"] = rank_correlation(res["landscape"])
        if meta:
            res["hinge_source"], res["hinge_uncertainty_mm"] = meta.get("hinge_source"), meta.get("hinge_uncertainty_mm")
        res["seat_uncertainty_mm"] = seat * 1e3
        if "registration" in meta:
            res["registration"] = meta["registration"]
        if registered:
            res["given"] = {k: v for k, v in given.items() if k not in ("start", "pose")}
            if cands and given.get("pose") is not None:
                res["given"]["best_from_given"] = pose_error(jp, cands[0].pos, cands[0].quat, *jp.body(given["pose"]),
                                                             points=jp.sample.mandible_points)
                meta["result_from_given"] = res["given"]["best_from_given"]  # pair.json says it too
                (scene.parent / "pair.json").write_text(json.dumps(meta, indent=1))
        if meta:
            res["mandible_transform"] = [file_transform(meta, jp.pose(c.pos, c.quat), jp.reference).tolist() for c in cands]
        res["_model"], res["_handle"], res["_pair"] = model, handle, jp
        return res
    except Exception:
        handle.detach()
        raise


def _given_start(jp: ScenePair, meta: dict) -> dict:
    """Where the files put the mandible of a registered pair (``pair.json``'s ``given_from_reference``):
    its world pose, how far it is from the registered occlusion, whether the arches were given
    touching, and the start it makes when within ``GIVEN_REACH_MM`` / ``GIVEN_REACH_DEG`` (else None)."""
    if "given_from_reference" not in meta or not meta.get("registration", {}).get("used"):
        return {}
    W = np.eye(4)
    W[:3, :3] = JAW_TO_WORLD
    P = W @ np.asarray(meta["given_from_reference"], float) @ W.T @ jp.reference
    pos, quat = jp.body(P)
    e = pose_error(jp, pos, quat, points=jp.sample.mandible_points)
    near = e["max_mm"] <= GIVEN_REACH_MM and e["rotation_deg"] <= GIVEN_REACH_DEG
    return {"pose": P, "from_registration": e, "touching": bool(meta["registration"].get("given_touching")),
            "start": np.r_[pos, quat] if near else None, "is_start": bool(near)}


def _landscape_row(jp: ScenePair, start, final: dict, j: ranking.Judgement, settle: dict) -> dict:
    """One start: where it began, settled and touched (mandible body poses), its score and settling."""
    pos, quat = jp.body(j.pose)
    return {"start": start.tolist(), "settled_pos": final["pos"].tolist(), "settled_quat": final["quat"].tolist(),
            "pos": pos.tolist(), "quat": quat.tolist(), "score": j.score, "interocclusal_mm": j.interocclusal_mm, **settle,
            "error": pose_error(jp, pos, quat, points=jp.sample.mandible_points)}


def rank_correlation(landscape: list[dict]) -> float | None:
    """Spearman rank correlation of score against error (largest tooth-point shift) over the
    settled poses: −1 when a better score always means a smaller error."""
    from scipy.stats import spearmanr

    if len(landscape) < 3:
        return None
    r = spearmanr([x["score"] for x in landscape], [x["error"]["max_mm"] for x in landscape]).statistic
    return None if not np.isfinite(r) else float(r)


def _sample(jp: ScenePair, mandible_pose, n: int | None = ranking.POINTS) -> ranking.OcclusalSample:
    """The pair's occlusal points where the arches meet at ``mandible_pose`` (``n``: how many per
    arch, spread evenly; None: every one)."""
    return ranking.occlusal_sample(jp.maxilla, jp.mandible, jp.maxilla_pose, mandible_pose, jp.frames["maxilla"], jp.hinge,
                                   surfaces=jp.surfaces, n=n if n is not None else 1 << 62)


def _best(judged: list[ranking.Judgement], settle: list[dict]) -> int:
    """The best-scored start that MuJoCo did not reset (0 when every one was)."""
    return max((i for i in range(len(judged)) if not settle[i]["unstable"]), key=lambda i: judged[i].score, default=0)


def _judge_all(jp: ScenePair, final: list[dict]) -> list[ranking.Judgement]:
    return [ranking.judge(jp.sample, jp.pose(f["pos"], f["quat"])) for f in final]


def _basins(jp: ScenePair, judged: list[ranking.Judgement], settle: list[dict]) -> list[dict]:
    """Starts grouped into basins, best first.

    Stable starts, best judged first, join the first basin whose best start is within
    ``BASIN_MM`` (largest tooth-point shift); each basin's pose is the mean of its starts' poses
    brought to touch and judged again (the settled poses of one basin scatter by about a tenth
    of a millimetre wherever friction held them; their centre is the estimate). Basins where some
    start settled rank before basins where none did: an occlusion is a rest position.
    """
    order = sorted((i for i in range(len(judged)) if not settle[i]["unstable"]), key=lambda i: (-judged[i].score, i))
    pts = jp.sample.mandible_points
    groups: list[list[int]] = []
    for i in order:
        for g in groups:
            if shift_mm(judged[i].pose, judged[g[0]].pose, pts) < BASIN_MM:
                g.append(i)
                break
        else:
            groups.append([i])
    basins = []
    for g in groups:
        P = np.mean([judged[i].pose for i in g], axis=0)
        R = Rotation.from_matrix([judged[i].pose[:3, :3] for i in g]).mean().as_matrix()
        P[:3, :3] = R
        P[3] = (0.0, 0.0, 0.0, 1.0)
        j = ranking.judge(jp.sample, P) if len(g) > 1 else judged[g[0]]
        scores = [judged[i].score for i in g]
        basins.append({"members": g, "judgement": j, "settled": any(settle[i]["settled"] for i in g),
                       "spread": float(max(scores) - min(scores))})
    basins.sort(key=lambda b: (not b["settled"], -b["judgement"].score))
    return basins


def _confidence(cands: list[Candidate]) -> dict:
    """How sure the answer is: the best basin's margin over the runner-up against the spread of
    the scores inside both (what the settling leaves uncertain); "ambiguous" within it."""
    if len(cands) < 2:
        return {"margin_mm": None, "ambiguous": False, "basin_starts": [c.starts for c in cands]}
    a, b = cands[0], cands[1]
    margin = a.score - b.score
    noise = max(a.score_spread, b.score_spread, AMBIGUOUS_FLOOR_MM)
    return {"margin_mm": float(margin), "uncertainty_mm": float(noise), "ambiguous": bool(margin < noise),
            "basin_starts": [a.starts, b.starts], "runner_up_shift_mm": None}


def _close(jp: ScenePair, X, seconds: float, nthread: int, progress: bool, seats=None) -> tuple[list[dict], list[dict]]:
    """Each start ``X[i]`` (mandible qpos) closed with ``mujoco.rollout`` until it settles or
    ``seconds`` pass: its final body pose, and how settled it is. ``seats[i]`` (world) is where
    the start's TMJ holds the condyles, when the scene has the mocap body ``condyles``.

    A start has settled when its tooth points move slower than ``SETTLED`` (mm/s) both over its last
    step and on average over the last ``CHUNK_S``: at rest, not sliding and not chattering (a jaw
    balanced on cusp slopes keeps flipping between them, which a rest position does not). Reported
    per start: ``settled``, ``drift_mm_s`` (that average), ``speed_mm_s`` and ``last_step_mm``
    (the last step's largest tooth-point move), ``seconds`` simulated, and ``unstable`` when
    MuJoCo reset the start after a numerical blow-up (its pose then means nothing).
    """
    from mujoco import rollout

    model = jp.model
    dt = model.opt.timestep
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    n = len(X)
    d = mujoco.MjData(model)
    state = np.empty((n, mujoco.mj_stateSize(model, spec)))
    for i in range(n):
        mujoco.mj_resetData(model, d)
        d.qpos[:7] = X[i]
        mujoco.mj_getState(model, d, state[i], spec)
    datas = [mujoco.MjData(model) for _ in range(nthread)]
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "condyles")
    control, mocap = None, int(mujoco.mjtState.mjSTATE_MOCAP_POS)
    if seats is not None and body >= 0 and model.body_mocapid[body] >= 0:
        mujoco.mj_resetData(model, d)  # every mocap body where the model puts it, in mocap order
        control = np.tile(d.mocap_pos.ravel(), (n, 1, 1))
        k = model.body_mocapid[body]  # the other mocap bodies (a user's scene) stay where they are
        control[:, 0, 3 * k:3 * k + 3] = seats
    pts = jp.sample.mandible_points
    settle = [{"settled": False, "unstable": False, "drift_mm_s": float("inf"), "speed_mm_s": float("inf"),
               "last_step_mm": float("inf"), "seconds": 0.0} for _ in range(n)]
    active = np.arange(n)
    elapsed = 0.0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, desc="closing", unit="start", leave=False)

    def pose(x):
        return jp.pose(x[:3], x[3:] / np.linalg.norm(x[3:]))

    while active.size and elapsed < seconds - 1e-9:
        chunk = min(FIRST_CHUNK_S if elapsed == 0.0 else CHUNK_S, seconds - elapsed)
        nstep = max(2, int(round(chunk / dt)))
        back = min(nstep - 1, int(round(CHUNK_S / dt)))  # rollout returns the states after each step
        t_end = state[active, 0] + nstep * dt
        if control is None:
            st, _ = rollout.rollout(model, datas, state[active], nstep=nstep)
        else:
            st, _ = rollout.rollout(model, datas, state[active], control[active], control_spec=mocap, nstep=nstep)
        state[active] = st[:, -1, :]
        elapsed += nstep * dt
        still = []
        for k, i in enumerate(active):
            last, prev, ago = st[k, -1, 1:8], st[k, -2, 1:8], st[k, -1 - back, 1:8]
            if not np.all(np.isfinite(st[k, -1])) or st[k, -1, 0] < t_end[k] - 0.5 * dt:  # reset after a blow-up
                settle[i].update(unstable=True, seconds=elapsed)
                continue
            step = shift_mm(pose(last), pose(prev), pts)
            drift = shift_mm(pose(last), pose(ago), pts) / (back * dt)
            settle[i].update(drift_mm_s=drift, speed_mm_s=step / dt, last_step_mm=step, seconds=elapsed)
            if drift < SETTLED and step / dt < SETTLED:
                settle[i]["settled"] = True
            else:
                still.append(i)
        if bar is not None:
            bar.update(len(active) - len(still))
        active = np.array(still, np.int64)
    if bar is not None:
        bar.close()
    final = []
    for i in range(n):
        qp = state[i, 1:8]
        final.append({"pos": qp[:3].copy(), "quat": qp[3:] / np.linalg.norm(qp[3:])})
    return final, settle


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
    err = np.array([x["error"]["max_mm"] for x in L])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    p = ax[0].scatter(jaw[:, 0] * 1e3, jaw[:, 2] * 1e3, c=sc, cmap="viridis", s=25)
    fig.colorbar(p, ax=ax[0], label="score of the settled pose")
    ax[0].set_xlabel("start: lateral offset from the reference occlusion (mm)")
    ax[0].set_ylabel("start: antero-posterior offset (mm)")
    ax[0].set_title("where each start settles: score")
    ax[1].scatter(err, sc, s=15)
    ax[1].set_xlabel("settled pose: largest tooth-point shift from the reference occlusion (mm)")
    ax[1].set_ylabel("score (−interocclusal distance, mm)")
    rc = res.get("rank_correlation")
    ax[1].set_title("score landscape" + (f" (rank correlation {rc:+.2f})" if rc is not None else ""))
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


def main(scene=None, data=None, starts=64, translation=None, rotation_deg=None, threads=None, seed=0, top=5,
         out="out/occlusion", progress=True, pair: dict | None = None, contact_map: bool = True, picture: bool = True) -> int:
    res = search(scene, data=data, starts=starts, translation=translation, rotation_deg=rotation_deg,
                 threads=threads, seed=seed, top=top, progress=progress, out_dir=out, pair=pair)
    try:
        print(f"{res['starts']} starts closed in {res['simulate_s']:.1f} s on {res['threads']} thread(s), "
              f"{res['settled']} settled (tooth points < {SETTLED} mm/s within {res['max_seconds']:g} s); closed with IST "
              f"contacts (ε1+ε2 {res['error_bound_mm']:.2f} mm), judged on the meshes")
        for c in res["candidates"]:
            e = c["error"]
            coal = f", coal gap {c['coal_distance_mm']:.4f} mm" if c["coal_distance_mm"] is not None else ""
            print(f"#{c['rank']} interocclusal {c['interocclusal_mm']:.3f} mm  {c['starts']} start(s)  "
                  f"{100 * c['contact_fraction']:.1f}% of occlusal points in contact, in {', '.join(c['regions']) or 'no region'}"
                  f"{'' if c['settled'] else '  NOT SETTLED'}  vs reference: {e['max_mm']:.3f} mm max, {e['rotation_deg']:.3f}°{coal}")
        conf = res["confidence"]
        if conf.get("margin_mm") is not None:
            verdict = "AMBIGUOUS: #1 and #2 are within the scores' spread" if conf["ambiguous"] else "clear"
            print(f"confidence    margin to #2 {conf['margin_mm']:.4f} mm (spread {conf['uncertainty_mm']:.4f} mm; basins of "
                  f"{conf['basin_starts'][0]} and {conf['basin_starts'][1]} starts): {verdict}")
        if "registration" in res and "given" in res:
            g, reg = res["given"], res["registration"]
            moved = g.get("best_from_given")
            print(f"registered    from the arches' shapes in {reg['seconds']:.1f} s (docking {reg['score_mm']:.3f} mm); the files "
                  f"gave the mandible apart, {g['from_registration']['max_mm']:.1f} mm / "
                  f"{g['from_registration']['rotation_deg']:.1f}° from it ({'one more start' if g['is_start'] else 'too far to start from'})"
                  + (f"; the best lies {moved['max_mm']:.2f} mm / {moved['rotation_deg']:.2f}° from the given pose" if moved else ""))
        elif "registration" in res:
            print(f"registered    from the arches' shapes: {res['registration']['from_given_mm']:.2f} mm from the given pose; the "
                  "arches were given touching, so the search started from that pose")
        written = write_outputs(res, out, picture=picture)
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
        from .. import report

        written.append(report.build_or_say(out))
        for f in written:
            print(f"written       {f}")
    finally:
        res["_handle"].detach()
    return 0

