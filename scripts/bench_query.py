"""Query benchmark: one scripted chewing motion of the mandible against the maxilla, replayed
with every IST traversal at several ε and with coal's exact distance on the same frames; then
random poses near the occlusion, where no traversal has a previous frame to start from.

Writes ``out/bench_query.json``, ``out/bench_query.png``, ``out/bench_query_random.png`` and
``out/bench_query.md``.

    python scripts/bench_query.py                  # real pair (../shared/data/jaw) + bundled jaws
    python scripts/bench_query.py --eps 4e-4,2e-4,1e-4 --frames 2000
    python scripts/bench_query.py --pairs real --eps 5e-5/4.5e-5   # ε_A+ε_B ≤ 0.1 mm (maxilla/mandible)
    python scripts/bench_query.py --quick          # 400 frames, 200 random poses, ε 0.4 mm only
    python scripts/bench_query.py --random 0       # the motion only

Times are per frame, measured around each Python call (so they include ~2 µs of dispatch),
plus the kernel-only mean of a whole replay inside numba (what a MuJoCo callback pays).
Trees come through mjist's content-hashed cache (``scripts/benchlib.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import tree_for  # noqa: E402

import mjist  # noqa: E402
from mjist.jaw import pair as jaw  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SHARED_JAW = ROOT.parent / "shared" / "data" / "jaw"
CLENCH = 5e-5  # closed pose: 0.05 mm past first touch, so the closed phase is in contact


def pairs_available():
    out = {}
    if (SHARED_JAW / "maxilla.obj").exists():
        out["real"] = SHARED_JAW
    if (jaw.BUNDLED / "maxilla.obj").exists():
        out["bundled"] = jaw.BUNDLED
    return out


SPARSE = False  # --sparse: trees built with mjist.build(..., sparse=True)


def _tree(path, eps):
    tree, mesh, _ = tree_for(path, max_error=eps, **({"sparse": True} if SPARSE else {}))
    return tree, mesh


def timed(fn, poses):
    ts = np.empty(len(poses))
    vals = []
    I = np.eye(4)
    for k, P in enumerate(poses):
        t0 = time.perf_counter_ns()
        r = fn(I, P)
        ts[k] = (time.perf_counter_ns() - t0) * 1e-3
        vals.append(r)
    return ts, vals


def write_outputs(out: Path, name: str, payload: dict, plot, md: str) -> None:
    """``name``.json (``payload``), ``name``.png (``plot(path)``) and ``name``.md into ``out``; echo the table."""
    (out / f"{name}.json").write_text(json.dumps(payload, indent=1))
    plot(out / f"{name}.png")
    (out / f"{name}.md").write_text(md)
    print(md)
    print(f"wrote {out / name}.json, .png and .md")


def coal_replay(bvh_maxilla, bvh_mandible, poses):
    """coal's exact distance on every frame (maxilla at the identity): times (µs) and distances."""
    I = np.eye(4)
    t = np.empty(len(poses))
    d = np.empty(len(poses))
    for k, P in enumerate(poses):
        t0 = time.perf_counter_ns()
        d[k] = jaw.coal_distance(bvh_maxilla, I, bvh_mandible, P)
        t[k] = (time.perf_counter_ns() - t0) * 1e-3
    return t, d


def floor_replay(q, poses, d):
    """The plain traversal seeded with its own answer ``d`` (per frame): it opens exactly the node
    pairs whose lower bound is below the minimum, which every exact traversal of these two trees
    must open, so its time is a floor for any plain (non-coherent) distance query on them.
    Kernel time only (pose conversion and dispatch excluded, unlike the other rows)."""
    from mjist.query import traverse as tv

    I = np.eye(4)
    xf = np.zeros(12)
    pair = np.zeros(2, np.int64)
    cap = tv.stack_size(q.Na, q.Nb)
    st, sv = np.zeros((cap, 2), np.int64), np.zeros(cap)
    ts, vs = np.empty(len(poses)), np.empty(len(poses))
    for k, P in enumerate(poses):
        tv.relative_pose(I, P, xf)
        seed = d[k] * (1.0 + 1e-12) + 1e-300  # just above the answer, so its leaf pair is still taken
        t0 = time.perf_counter_ns()
        best, code, v = tv.min_distance(q.Na, q.Nb, xf, st, sv, seed, 0.0, pair, 0.0)
        ts[k] = (time.perf_counter_ns() - t0) * 1e-3
        vs[k] = v
        # the same minimum up to rounding: relative to the answer, and to the coordinates'
        # size for answers near zero (teeth a few nanometres apart)
        if code != tv.OK or abs(max(best, 0.0) - d[k]) > 1e-12 * d[k] + 1e-15:
            raise AssertionError(f"frame {k}: seeded traversal gave {best} instead of {d[k]}")
    return ts, vs


OPEN_MAX = 3e-3  # random poses: lowered from the occlusion by up to this much, uniform (m)
TURN = np.radians(0.3)  # random poses: standard deviation of the extra turn about the hinge, per axis
SLIDE = 5e-4  # random poses: lateral and protrusive shift, uniform in ±SLIDE (m)


def near_occlusion_poses(n, hinge, bvh_maxilla, bvh_mandible, touch, seed=0):
    """``n`` random mandible poses near the occlusion, each separated from the maxilla.

    Each pose opens the hinge by up to 1°, turns the mandible about the hinge by a small random
    rotation, slides it by up to ``SLIDE`` sideways and forwards and lowers it from the first
    touch of the stored occlusion by a gap drawn uniformly from ``[0, OPEN_MAX]``. Poses where
    coal finds the meshes intersecting are drawn again. (Placing each pose at its own first
    touch would take a bisection of coal collision tests, up to 0.5 s each on the interlocked
    bundled jaws.)
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    I = np.eye(4)
    hinge = np.asarray(hinge, float)
    out = []
    while len(out) < n:
        P = jaw.hinge_pose(np.radians(rng.uniform(0.0, 1.0)), hinge, lateral=rng.uniform(-SLIDE, SLIDE),
                           protrusion=rng.uniform(-SLIDE, SLIDE), vertical=touch - rng.uniform(0.0, OPEN_MAX))
        turn = np.eye(4)
        turn[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * TURN).as_matrix()
        turn[:3, 3] = hinge - turn[:3, :3] @ hinge
        P = turn @ P
        if jaw.coal_distance(bvh_maxilla, I, bvh_mandible, P) > 0.0:
            out.append(P)
    return np.array(out)


def run_random(label, folder, eps_list, n):
    """Random poses near the occlusion: every traversal starts without a previous frame.

    Per level: ``distance`` (plain traversal from the roots), the same with ``tolerance`` 0.1 mm
    (its interval widens by that much), ``backtracking`` seeded by the previous random pose's
    pair (what a Monte Carlo over poses gets for free), and the floor (the plain traversal told
    the answer: the node pairs any exact traversal with the sphere-pair bound must open). Each
    answer's interval is checked against coal's exact distance on the same pose.
    """
    mx, md, info = jaw.load_pair(folder)
    paths = (Path(info["paths"]["maxilla"]), Path(info["paths"]["mandible"]))
    bx, bd = jaw.coal_bvh(mx.vertices, mx.faces), jaw.coal_bvh(md.vertices, md.faces)
    t0 = time.perf_counter()
    poses = near_occlusion_poses(n, info["hinge"], bx, bd, float(info["mandible_pose"][1, 3]))
    print(f"[{label}] {n} random poses near the occlusion ({time.perf_counter() - t0:.0f} s to place)", flush=True)
    coal_t, coal_d = coal_replay(bx, bd, poses)
    truth = np.maximum(coal_d, 0.0)
    res = {"poses": n, "open_max": OPEN_MAX, "turn_sd_deg": float(np.degrees(TURN)), "slide": SLIDE,
           "coal": stats(coal_t), "coal_distance": coal_d.tolist(), "coal_times": coal_t.tolist(), "levels": []}
    print(f"  coal exact distance median {np.median(coal_t):.0f} µs, p99 {np.percentile(coal_t, 99):.0f} µs; "
          f"true gap median {np.median(truth) * 1e3:.2f} mm", flush=True)
    I = np.eye(4)
    for eps_a, eps_b in eps_list:
        ta, _ = _tree(paths[0], eps_a)
        tb, _ = _tree(paths[1], eps_b)
        q = mjist.Query(ta, tb)
        lvl = {"eps_target": [eps_a, eps_b], "error_bound": q.error_bound, "leaves": [ta.num_leaves, tb.num_leaves],
               "depth": [ta.depth, tb.depth], "methods": {}, "series": {}}
        dist = None
        for name, kw, fresh in (("distance", {"method": "distance"}, True),
                                ("distance, tolerance 0.1 mm", {"method": "distance", "tolerance": 1e-4}, True),
                                ("backtracking from the previous pose", {"method": "backtracking"}, False)):
            q.reset()
            q.distance(I, poses[0], **kw)  # compile / warm

            def call(a, b, q=q, kw=kw, fresh=fresh):
                if fresh:
                    q.reset()
                return q.distance(a, b, **kw)

            q.reset()
            ts, rs = timed(call, poses)
            d = np.array([r.distance for r in rs])
            eb = np.array([r.error_bound for r in rs])
            viol = int(np.sum((truth > d + 1e-9) | (d - eb > truth + 1e-9)))
            lvl["methods"][name] = {**stats(ts), "visits_median": float(np.median([r.visits for r in rs])),
                                    "error_bound_max": float(eb.max()), "bound_violations": viol,
                                    "err_max": float((d - truth).max()), "speedup_vs_coal": float(np.median(coal_t) / np.median(ts))}
            lvl["series"][name] = ts.tolist()
            if dist is None:
                dist = d
            print(f"  ε {q.error_bound * 1e3:.3f} mm {name:36s} median {np.median(ts):8.1f} µs  p99 {np.percentile(ts, 99):8.1f}"
                  f"  × coal {np.median(coal_t) / np.median(ts):5.1f}  bound ≤ {eb.max() * 1e3:.3f} mm  violations {viol}", flush=True)
        ts, vs = floor_replay(q, poses, dist)
        lvl["methods"]["distance floor (answer known)"] = {**stats(ts), "visits_median": float(np.median(vs)),
                                                           "speedup_vs_coal": float(np.median(coal_t) / np.median(ts))}
        lvl["series"]["distance floor (answer known)"] = ts.tolist()
        print(f"  ε {q.error_bound * 1e3:.3f} mm {'distance floor (answer known)':36s} median {np.median(ts):8.1f} µs  "
              f"p99 {np.percentile(ts, 99):8.1f}  × coal {np.median(coal_t) / np.median(ts):5.1f}  "
              f"visits median {np.median(vs):.0f} (plain {lvl['methods']['distance']['visits_median']:.0f})", flush=True)
        if (eps_a, eps_b) == tuple(eps_list[0]):
            for name, x in mujoco_distance_random(mx, md, poses, max(eps_a, eps_b), truth, coal_t).items():
                lvl["series"][name] = x.pop("series")
                lvl["methods"][name] = x
        res["levels"].append(lvl)
    return res


GEOM_DISTMAX = (1e-3, 1e-2, 5e-2)  # m: mj_geomDistance cutoffs timed on the random poses


def mujoco_distance_random(mx, md, poses, eps, truth, coal_t):
    """``mj_geomDistance`` through mjist's hook on the random poses, one cutoff (``distmax``) at a
    time, with trees at ``eps`` and no contact offset (so it returns d_IST). The hook gathers the
    contact groups within the cutoff (MuJoCo passes it as the margin), so its cost grows with the
    cutoff until its candidate list is full."""
    m, d, ga, gb = _mujoco_pair([(mx.vertices, mx.faces)], [(md.vertices, md.faces)], collide=True)
    out = {}
    with mjist.attach(m, max_error=eps, offset="none") as h:
        bound = h.pairs[0].error_bound
        for dm in GEOM_DISTMAX:
            t = np.empty(len(poses))
            dist = np.empty(len(poses))
            for k, P in enumerate(poses):
                _place_mandible(m, d, P)
                t0 = time.perf_counter_ns()
                dist[k] = mujoco.mj_geomDistance(m, d, ga[0], gb[0], dm, None)
                t[k] = (time.perf_counter_ns() - t0) * 1e-3
            dd = np.maximum(dist, 0.0)
            seen = dist < dm  # else it returns distmax: nothing within the cutoff
            viol = int(np.sum(seen & ((truth > dd + 1e-9) | (dd - bound > truth + 1e-9))) + np.sum(~seen & (truth + bound < dm - 1e-9)))
            name = f"mj_geomDistance, distmax {dm * 1e3:g} mm"
            out[name] = {**stats(t), "visits_median": float("nan"), "error_bound_max": bound, "bound_violations": viol,
                         "speedup_vs_coal": float(np.median(coal_t) / np.median(t)), "series": t.tolist()}
            print(f"  ε {bound * 1e3:.3f} mm {name:36s} median {np.median(t):8.1f} µs  p99 {np.percentile(t, 99):8.1f}"
                  f"  × coal {np.median(coal_t) / np.median(t):5.1f}  violations {viol}", flush=True)
    return out


def plot_random(results, path):
    """Distribution of the time per random pose: coal and each IST method at each pair's finest level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, len(results), figsize=(7 * len(results), 4.8), squeeze=False)
    for ax, (label, r) in zip(axs[0], results.items()):
        rr = r["random"]
        fine = min(rr["levels"], key=lambda l: l["error_bound"])
        for name, ts in [("coal (exact)", rr["coal_times"])] + list(fine["series"].items()):
            x = np.sort(ts)
            ax.plot(x, np.arange(1, len(x) + 1) / len(x), lw=1.2, color="k" if name.startswith("coal") else None, label=name)
        ax.set_xscale("log")
        ax.set_xlabel("µs per pose")
        ax.set_ylabel("fraction of poses")
        ax.set_title(f"{label} pair, {rr['poses']} random poses, ε_A+ε_B = {fine['error_bound'] * 1e3:.3f} mm")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def stats(ts):
    return {"median_us": float(np.median(ts)), "p99_us": float(np.percentile(ts, 99)), "mean_us": float(np.mean(ts))}


DISTMAX = 0.05  # m: MuJoCo's distance queries look this far (the motion opens the jaw ~10 mm)


def _mujoco_pair(parts_a, parts_b, gtype=mujoco.mjtGeom.mjGEOM_MESH, collide=False):
    """A model with the maxilla's pieces fixed and the mandible's on a mocap body (mesh geoms:
    MuJoCo collides their convex hulls; sdf geoms: MuJoCo's mesh SDF). The geoms form a
    collision pair only with ``collide`` (which is what ``mjist.attach`` manages)."""
    spec = mujoco.MjSpec()
    spec.option.sdf_initpoints = 50  # as bench_mujoco's native-sdf mode
    mocap = spec.worldbody.add_body(name="mandible", mocap=True)
    ids = ([], [])
    for k, (parts, body) in enumerate(((parts_a, spec.worldbody), (parts_b, mocap))):
        for i, (V, F) in enumerate(parts):
            name = f"{'ab'[k]}{i}"
            spec.add_mesh(name=name, uservert=np.asarray(V, float).ravel().tolist(), userface=np.asarray(F, int).ravel().tolist())
            body.add_geom(name=name, type=gtype, meshname=name, contype=int(collide), conaffinity=int(collide))
    m = spec.compile()
    for g in range(m.ngeom):
        ids[0 if m.geom_bodyid[g] == 0 else 1].append(g)
    return m, mujoco.MjData(m), np.array(ids[0]), np.array(ids[1])


def _place_mandible(m, d, P):
    """The mocap mandible of a ``_mujoco_pair`` model at pose ``P``, geoms posed (kinematics only)."""
    d.mocap_pos[0] = P[:3, 3]
    mujoco.mju_mat2Quat(d.mocap_quat[0], P[:3, :3].ravel())
    mujoco.mj_kinematics(m, d)


def mujoco_reference(name, parts_a, parts_b, poses, gtype=mujoco.mjtGeom.mjGEOM_MESH):
    """MuJoCo's own distance on the same frames: ``mj_geomDistance`` between convex pieces
    (one piece = the convex hull, as MuJoCo collides meshes; several = a CoACD decomposition,
    pairs pruned by their bounding spheres as a broad phase would) or between mesh SDFs (which
    report only contacts: ``DISTMAX`` when apart). Times exclude kinematics."""
    m, d, ga, gb = _mujoco_pair(parts_a, parts_b, gtype)
    t = np.empty(len(poses))
    dist = np.empty(len(poses))
    for k, P in enumerate(poses):
        _place_mandible(m, d, P)
        t0 = time.perf_counter_ns()
        best = DISTMAX
        if len(ga) * len(gb) > 1:
            ca, cb = d.geom_xpos[ga], d.geom_xpos[gb]
            lb = np.linalg.norm(ca[:, None] - cb[None], axis=2) - m.geom_rbound[ga][:, None] - m.geom_rbound[gb][None]
            for i, j in zip(*np.nonzero(lb < best)):
                if lb[i, j] < best:
                    best = min(best, mujoco.mj_geomDistance(m, d, ga[i], gb[j], best, None))
        else:
            best = mujoco.mj_geomDistance(m, d, ga[0], gb[0], DISTMAX, None)
        t[k] = (time.perf_counter_ns() - t0) * 1e-3
        dist[k] = best
    return {"name": name, "pieces": [len(parts_a), len(parts_b)], **stats(t), "distance": dist.tolist()}


def references(mx, md, poses, truth, coacd_cache, decompose=True):
    """Convex hull (MuJoCo's mesh collision), mesh SDF and, with ``coacd`` installed, CoACD pieces
    (decomposed here unless ``decompose`` is False: then only from the cache)."""
    hull = [(mx.trimesh().convex_hull.vertices, mx.trimesh().convex_hull.faces)], [(md.trimesh().convex_hull.vertices, md.trimesh().convex_hull.faces)]
    out = {"mujoco hull": mujoco_reference("mujoco hull", *hull, poses),
           "mujoco mesh-sdf": mujoco_reference("mujoco mesh-sdf", [(mx.vertices, mx.faces)], [(md.vertices, md.faces)],
                                               poses, mujoco.mjtGeom.mjGEOM_SDF)}
    try:
        import coacd  # noqa: F401
    except ImportError:
        print("  (CoACD reference skipped: pip install -e '.[bench]')", flush=True)
        return _errors(out, truth)
    else:
        from bench_mujoco import coacd_cache_path, coacd_pieces

        cached = all(coacd_cache_path(m.vertices, m.faces, 0.05, coacd_cache).exists() for m in (mx, md))
        if not (decompose or cached):
            print("  (CoACD reference skipped in --quick: no cached decomposition; the full run makes one)", flush=True)
            return _errors(out, truth)
        pa, sa = coacd_pieces(mx.vertices, mx.faces, 0.05, coacd_cache)
        pb, sb = coacd_pieces(md.vertices, md.faces, 0.05, coacd_cache)
        out["mujoco coacd"] = mujoco_reference("mujoco coacd", pa, pb, poses)
        out["mujoco coacd"]["decompose_s"] = sa + sb
    return _errors(out, truth)


def _errors(out, truth):
    """Each reference's error against coal, false and missed contacts (in place); ``out``."""
    for name, r in out.items():
        dm = np.array(r["distance"])
        valid = (truth < DISTMAX) & (dm < DISTMAX)  # frames where MuJoCo gave a value
        err = np.abs(np.maximum(dm, 0.0) - truth)[valid]
        r.update(err_max=float(err.max()) if err.size else float("nan"), err_median=float(np.median(err)) if err.size else float("nan"),
                 answered=int(valid.sum()),
                 false_contacts=int(np.sum((dm <= 0) & (truth > 0))), missed_contacts=int(np.sum((dm > 0) & (truth <= 0))))
        print(f"  {name:16s} median {r['median_us']:8.1f} µs  max |err| {r['err_max'] * 1e3:.3f} mm on {r['answered']} frames  "
              f"false contacts {r['false_contacts']}, missed {r['missed_contacts']} / {len(truth)}", flush=True)
    return out


def run_pair(label, folder, eps_list, frames, coacd_cache, decompose=True):
    mx, md, info = jaw.load_pair(folder)
    paths = (Path(info["paths"]["maxilla"]), Path(info["paths"]["mandible"]))
    print(f"[{label}] {paths[0]} + {paths[1]} (occlusion: {info['source']})", flush=True)
    bx, bd = jaw.coal_bvh(mx.vertices, mx.faces), jaw.coal_bvh(md.vertices, md.faces)
    hinge = info["hinge"]
    touch = float(info["mandible_pose"][1, 3])  # both pairs' occlusion is a vertical offset
    poses = jaw.chewing_motion(frames, hinge, contact_offset=touch + CLENCH)
    I = np.eye(4)
    # coal on the same frames
    coal_t, coal_d = coal_replay(bx, bd, poses)
    truth = np.maximum(coal_d, 0.0)
    res = {
        "maxilla": str(paths[0].name), "mandible": str(paths[1].name),
        "vertices": [int(len(mx.vertices)), int(len(md.vertices))],
        "frames": frames, "hinge": np.asarray(hinge).tolist(), "touching_offset": touch, "clench": CLENCH,
        "coal": {**stats(coal_t), "colliding_frames": int((coal_d <= 0).sum())},
        "coal_times": coal_t.tolist(), "coal_distance": coal_d.tolist(), "levels": [],
    }
    res["references"] = references(mx, md, poses, truth, coacd_cache, decompose)
    for eps_a, eps_b in eps_list:
        ta, _ = _tree(paths[0], eps_a)
        tb, _ = _tree(paths[1], eps_b)
        q = mjist.Query(ta, tb)
        lvl = {
            "eps_target": [eps_a, eps_b], "error_bound": q.error_bound,
            "leaves": [ta.num_leaves, tb.num_leaves], "depth": [ta.depth, tb.depth],
            "coverage": [ta.coverage, tb.coverage], "methods": {},
        }
        series = {}
        dvals = {}
        for name, kw in (
            ("distance", {"method": "distance"}),
            ("backtracking", {"method": "backtracking"}),
            ("backtracking+skip", {"method": "backtracking", "skip": True}),
        ):
            q.reset()
            q.distance(I, poses[0], **kw)  # compile / warm
            q.reset()
            ts, rs = timed(lambda a, b, q=q, kw=kw: q.distance(a, b, **kw), poses)
            d = np.array([r.distance for r in rs])
            eb = np.array([r.error_bound for r in rs])
            viol = int(np.sum((truth > d + 1e-9) | (d - eb > truth + 1e-9)))
            exact = np.array([not r.skipped for r in rs])
            err = d[exact] - truth[exact]
            lvl["methods"][name] = {
                **stats(ts), "visits_mean": float(np.mean([r.visits for r in rs])),
                "visits_median": float(np.median([r.visits for r in rs])),
                "skipped": int((~exact).sum()), "bound_violations": viol,
                "err_max": float(err.max()), "err_median": float(np.median(err)),
                "speedup_vs_coal": float(np.median(coal_t) / np.median(ts)),
            }
            series[name] = ts
            dvals[name] = d
            print(f"  ε {q.error_bound * 1e3:.3f} mm {name:18s} median {np.median(ts):8.1f} µs  p99 {np.percentile(ts, 99):8.1f}"
                  f"  max err {err.max() * 1e3:.3f} mm  violations {viol}", flush=True)
        ts, vs = floor_replay(q, poses, dvals["distance"])
        fl = lvl["methods"]["distance"]
        lvl["methods"]["distance floor (answer known)"] = {
            **stats(ts), "visits_mean": float(vs.mean()), "visits_median": float(np.median(vs)),
            "speedup_vs_coal": float(np.median(coal_t) / np.median(ts)),
        }
        print(f"  ε {q.error_bound * 1e3:.3f} mm {'distance floor':18s} median {np.median(ts):8.1f} µs  "
              f"visits median {np.median(vs):.0f} (plain traversal {fl['visits_median']:.0f})", flush=True)
        for name, m in (("distance", "distance"), ("backtracking", "backtracking")):
            q.reset()
            q.distance_batch(I, poses[:2], method=m)
            q.reset()
            t0 = time.perf_counter()
            out = q.distance_batch(I, poses, method=m)
            lvl["methods"][name]["kernel_mean_us"] = (time.perf_counter() - t0) / frames * 1e6
            # the one-call replay gives exactly the per-call answers
            if not np.array_equal(out["distance"], dvals[name]):
                raise AssertionError(f"distance_batch({m}) disagrees with per-call distance()")
        q.reset()
        q.contacts(I, poses[0])
        ts, rs = timed(lambda a, b, q=q: q.contacts(a, b, max_contacts=4, split_depth=3), poses)
        lvl["methods"]["multipoint"] = {**stats(ts), "contacts_mean": float(np.mean([r.count for r in rs])),
                                        "candidates_max": int(max(r.candidates for r in rs))}
        series["multipoint"] = ts
        q.penetration_volume(I, poses[0])
        ts, rs = timed(q.penetration_volume, poses)
        vol = np.array([r.volume for r in rs])
        lvl["methods"]["penetration_volume"] = {**stats(ts), "volume_max_mm3": float(vol.max() * 1e9),
                                                "pairs_max": int(max(r.pairs for r in rs))}
        series["penetration_volume"] = ts
        bt = lvl["methods"]
        lvl["backtracking_speedup"] = bt["distance"]["median_us"] / bt["backtracking"]["median_us"]
        lvl["series"] = {k: v.tolist() for k, v in series.items()}
        lvl["ist_distance"] = [float(x) for x in q.distance_batch(I, poses, method="distance")["distance"]]
        for k in ("multipoint", "penetration_volume"):
            print(f"  ε {q.error_bound * 1e3:.3f} mm {k:18s} median {bt[k]['median_us']:8.1f} µs  p99 {bt[k]['p99_us']:8.1f}", flush=True)
        res["levels"].append(lvl)
    print(f"  coal exact distance median {np.median(coal_t):.0f} µs, p99 {np.percentile(coal_t, 99):.0f} µs", flush=True)
    return res


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(2, 3, figsize=(17, 9.5))
    colors = {"distance": "C0", "backtracking": "C1", "backtracking+skip": "C2", "multipoint": "C3", "penetration_volume": "C4"}
    for pi, (label, r) in enumerate(results.items()):
        ls = "-" if pi == 0 else "--"
        lv = r["levels"]
        leaves = [np.sqrt(l["leaves"][0] * l["leaves"][1]) for l in lv]
        depth = [0.5 * (l["depth"][0] + l["depth"][1]) for l in lv]
        for m in colors:
            med = [l["methods"][m]["median_us"] for l in lv]
            axs[0, 1].plot(leaves, med, ls, marker="o", color=colors[m], label=f"{label} {m}")
            axs[0, 2].plot(depth, med, ls, marker="o", color=colors[m], label=f"{label} {m}")
        axs[0, 1].axhline(r["coal"]["median_us"], color="k", ls=ls, lw=1, label=f"{label} coal")
        axs[0, 2].axhline(r["coal"]["median_us"], color="k", ls=ls, lw=1)
        eb = [l["error_bound"] * 1e3 for l in lv]
        emax = [l["methods"]["distance"]["err_max"] * 1e3 for l in lv]
        emed = [l["methods"]["distance"]["err_median"] * 1e3 for l in lv]
        axs[1, 0].plot(leaves, eb, ls, marker="s", color="C3", label=f"{label} bound ε_A+ε_B")
        axs[1, 0].plot(leaves, emax, ls, marker="o", color="C0", label=f"{label} max |IST-coal|")
        axs[1, 0].plot(leaves, emed, ls, marker="^", color="C2", label=f"{label} median |IST-coal|")
        x = np.arange(len(lv)) + 0.35 * pi
        axs[1, 1].bar(x, [l["backtracking_speedup"] for l in lv], width=0.35, label=f"{label} backtracking / distance")
        axs[1, 1].set_xticks(np.arange(len(lv)), [f"ε {l['error_bound'] * 1e3:.2f}" for l in lv])
        if pi == 0:
            fine = lv[-1]
            fr = np.arange(r["frames"])
            axs[0, 0].semilogy(fr, r["coal_times"], color="k", lw=0.6, label="coal")
            for m in colors:
                axs[0, 0].semilogy(fr, fine["series"][m], color=colors[m], lw=0.6, label=m)
            axs[0, 0].set_title(f"{label} pair, ε_A+ε_B = {fine['error_bound'] * 1e3:.2f} mm: time per frame")
            axs[1, 2].plot(fr, np.array(r["coal_distance"]) * 1e3, color="k", lw=1, label="coal (exact)")
            d = np.array(fine["ist_distance"]) * 1e3
            axs[1, 2].plot(fr, d, color="C0", lw=1, label="IST distance")
            axs[1, 2].fill_between(fr, d - fine["error_bound"] * 1e3, d, color="C0", alpha=0.2, label="IST bound")
            axs[1, 2].set_title("distance along the motion")
    axs[0, 0].set_xlabel("frame")
    axs[0, 0].set_ylabel("µs")
    for ax, xl in ((axs[0, 1], "leaves (geometric mean of the two trees)"), (axs[0, 2], "mean tree depth")):
        ax.set_xlabel(xl)
        ax.set_ylabel("median µs per frame")
        ax.set_yscale("log")
    axs[0, 1].set_xscale("log")
    axs[0, 1].set_title("speed vs number of leaves")
    axs[0, 2].set_title("speed vs tree depth")
    axs[1, 0].set_xscale("log")
    axs[1, 0].set_xlabel("leaves")
    axs[1, 0].set_ylabel("mm")
    axs[1, 0].set_title("error vs number of leaves")
    axs[1, 1].set_title("backtracking speedup (median)")
    axs[1, 2].set_xlabel("frame")
    axs[1, 2].set_ylabel("mm")
    for ax in axs.flat:
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def markdown(results, meta):
    trees = "; sparse trees (build(..., sparse=True))" if meta.get("sparse") else ""
    lines = [f"Query benchmark ({meta['frames']} frames of one chewing motion; {meta['machine']}{trees}).", ""]
    lines.append("| pair | ε_A+ε_B mm | leaves | depth | method | median µs | p99 µs | kernel µs | visits (median) | × coal | max err mm | bound viol. |")
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for label, r in results.items():
        for l in r["levels"]:
            for m, s in l["methods"].items():
                lines.append(
                    f"| {label} | {l['error_bound'] * 1e3:.3f} | {l['leaves'][0]:,} / {l['leaves'][1]:,} | {l['depth'][0]}/{l['depth'][1]} "
                    f"| {m} | {s['median_us']:.1f} | {s['p99_us']:.1f} | {s.get('kernel_mean_us', float('nan')):.1f} "
                    f"| {s.get('visits_median', float('nan')):.0f} | {s.get('speedup_vs_coal', float('nan')):.0f} | {s.get('err_max', float('nan')) * 1e3:.3f} | {s.get('bound_violations', '')} |"
                )
        lines.append(f"| {label} | exact | | | coal distance | {r['coal']['median_us']:.0f} | {r['coal']['p99_us']:.0f} | | | 1 | 0 | |")
        for name, x in r.get("references", {}).items():
            lines.append(f"| {label} | (none) | {x['pieces'][0]} / {x['pieces'][1]} pieces | | {name} | {x['median_us']:.1f} | {x['p99_us']:.1f} | | "
                         f"| {r['coal']['median_us'] / x['median_us']:.0f} | {x['err_max'] * 1e3:.3f} "
                         f"| {x['false_contacts']} false / {x['missed_contacts']} missed contacts, distance on {x['answered']} frames |")
    if any("random" in r for r in results.values()):
        lines += ["", "Random poses near the occlusion (no previous frame): each pose's hinge opened by up to 1°, turned "
                  "about it, slid sideways and lowered from the occlusion by up to 3 mm; intersecting poses drawn again.", "",
                  "| pair | poses | ε_A+ε_B mm | leaves | method | median µs | p99 µs | visits (median) | × coal | bound ≤ mm | bound viol. |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for label, r in results.items():
            rr = r.get("random")
            if rr is None:
                continue
            for l in rr["levels"]:
                for m, x in l["methods"].items():
                    lines.append(f"| {label} | {rr['poses']} | {l['error_bound'] * 1e3:.3f} | {l['leaves'][0]:,} / {l['leaves'][1]:,} | {m} "
                                 f"| {x['median_us']:.1f} | {x['p99_us']:.1f} | {x['visits_median']:.0f} | {x['speedup_vs_coal']:.1f} "
                                 f"| {x.get('error_bound_max', float('nan')) * 1e3:.3f} | {x.get('bound_violations', '')} |")
            lines.append(f"| {label} | {rr['poses']} | exact | | coal distance | {rr['coal']['median_us']:.0f} | {rr['coal']['p99_us']:.0f} | | 1 | 0 | |")
    return "\n".join(lines) + "\n"


def parse_eps(text):
    """``'4e-4'`` -> (4e-4, 4e-4); ``'5e-5/4.5e-5'`` -> (maxilla, mandible)."""
    parts = [float(x) for x in text.split("/")]
    if len(parts) not in (1, 2) or not all(np.isfinite(x) and x > 0 for x in parts):
        raise SystemExit(f"--eps entry {text!r}: a positive max_error in metres, or 'maxilla/mandible'")
    return (parts[0], parts[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--eps", default="4e-4,2e-4",
                    help="per-tree max_error list in metres (default 4e-4,2e-4); 'A/B' gives the maxilla A and the mandible B")
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--pairs", default="real,bundled")
    ap.add_argument("--quick", action="store_true", help="400 frames, ε 4e-4 only, CoACD only if already decomposed")
    ap.add_argument("--out", default=str(ROOT / "out"))
    ap.add_argument("--sparse", action="store_true", help="build the trees with sparse=True (same ε, fewer leaves)")
    ap.add_argument("--random", type=int, default=1000, help="random poses near the occlusion (default 1000; 0: none)")
    ap.add_argument("--random-eps", default="5e-5/4.5e-5",
                    help="extra levels for the random poses only, as --eps (default 5e-5/4.5e-5: ε_A+ε_B about 0.1 mm)")
    a = ap.parse_args(argv)
    global SPARSE
    SPARSE = a.sparse
    eps = [(4e-4, 4e-4)] if a.quick else [parse_eps(x) for x in a.eps.split(",")]
    frames = 400 if a.quick else a.frames
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    avail = pairs_available()
    want = [p for p in a.pairs.split(",") if p in avail]
    if not want:
        print(f"no jaw pair found (looked for {SHARED_JAW} and {jaw.BUNDLED})", file=sys.stderr)
        return 2
    results = {p: run_pair(p, avail[p], eps, frames, out / "coacd", decompose=not a.quick) for p in want}
    n_random = min(a.random, 200) if a.quick else a.random
    if n_random > 0:
        extra = [] if a.quick or not a.random_eps else [parse_eps(x) for x in a.random_eps.split(",")]
        for p in want:
            results[p]["random"] = run_random(p, avail[p], eps + [e for e in extra if e not in eps], n_random)
    meta = {"frames": frames, "random_poses": n_random, "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
            "mjist": mjist.__version__, "sparse": SPARSE, "numba_threads": int(os.environ.get("NUMBA_NUM_THREADS", 0) or 0)}
    (out / "bench_query.json").write_text(json.dumps({"meta": meta, "results": results}))
    plot(results, out / "bench_query.png")
    if n_random > 0:
        plot_random(results, out / "bench_query_random.png")
    (out / "bench_query.md").write_text(markdown(results, meta))
    print(markdown(results, meta))
    print(f"wrote {out / 'bench_query.json'}, {out / 'bench_query.png'}, {out / 'bench_query.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
