"""MuJoCo step time and contact error: IST (spheres, surface; mesh and sdf geoms) vs native hull, mesh-SDF and CoACD.

    python scripts/bench_mujoco.py                      # bundled jaws (+ CBCT pair when ../shared is there)
    python scripts/bench_mujoco.py --pairs bundled --quick

Same scene and motion for every mode (``models/jaw_closure.xml``: the jaw closed from 8° by
its muscles), one run. Per frame: ``mj_step`` wall time; every ``--every`` frames the exact
mesh distance from coal at that frame's pose against what the mode reports for the pair
(IST: ``mj_geomDistance`` with the contact offset added back, i.e. the IST distance d_IST,
whose interval [d_IST - ε1 - ε2, d_IST] must hold the coal distance; native: its deepest
contact). ``ist-surface`` is ``ist-mesh`` with ``mjist_narrowphase='surface'`` (its distance is
the meshes' own, still inside that interval). At the end, coal's distance at the rest pose: the
true gap (> 0) or 0 when the meshes intersect, and how far the hinge rests past the angle where
coal finds the meshes first touching with the rest's other joints (> 0: closed past it, into the
maxilla; < 0: resting open of it). Writes ``out/bench_mujoco.{json,md,png}``.

``native-coacd`` (when ``coacd`` is installed): each jaw replaced by its CoACD convex pieces
(MuJoCo's documented workaround for non-convex meshes), decomposed once and cached in
``out/coacd/`` by mesh content and threshold; the decomposition time is reported.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import mujoco
import numpy as np

from mjist.jaw import pair as jawmod
from mjist.jaw.scenes import pair_scene
from mjist.mujoco import attach as A
from mjist.mujoco.scene import geom_pose, mesh_of

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data" / "jaw"


def _spec_model(scene: Path, gtype: str, octree: int | None):
    spec = mujoco.MjSpec.from_file(str(scene))
    for g in spec.geoms:
        if g.name in ("maxilla", "mandible") and gtype == "sdf":
            g.type = mujoco.mjtGeom.mjGEOM_SDF
    if octree is not None:
        for mesh in spec.meshes:
            mesh.octree_maxdepth = octree
    if gtype == "sdf":
        spec.option.sdf_initpoints = 50
    t = time.perf_counter()
    m = spec.compile()
    return m, time.perf_counter() - t


def coacd_cache_path(V, F, threshold: float, cache: Path) -> Path:
    """Where ``coacd_pieces`` keeps the decomposition of this mesh (content + threshold)."""
    import hashlib

    key = hashlib.sha256(np.ascontiguousarray(V, np.float64).tobytes() + np.ascontiguousarray(F, np.int64).tobytes()
                         + repr((threshold, "off")).encode()).hexdigest()[:20]
    return cache / f"{key}.npz"


def coacd_pieces(V, F, threshold: float, cache: Path):
    """CoACD convex pieces of a mesh (cached by content + threshold): list of (V, F), seconds."""
    path = coacd_cache_path(V, F, threshold, cache)
    if path.exists():
        z = np.load(path)
        n = int(z["n"])
        return [(z[f"v{i}"], z[f"f{i}"]) for i in range(n)], float(z["seconds"])
    import coacd

    coacd.set_log_level("error")
    t = time.perf_counter()
    # our meshes are validated closed; CoACD's own manifold check rejects multi-shell jaws and
    # would remesh them on a 50³ grid first, losing the cusps, so its preprocessing is off
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int32)), threshold=threshold,
                            preprocess_mode="off", seed=0)
    sec = time.perf_counter() - t
    os.makedirs(cache, exist_ok=True)
    arrays = {"n": len(parts), "seconds": sec}
    for i, (pv, pf) in enumerate(parts):
        arrays[f"v{i}"], arrays[f"f{i}"] = np.asarray(pv), np.asarray(pf)
    np.savez(path, **arrays)
    return [(np.asarray(pv), np.asarray(pf)) for pv, pf in parts], sec


def _jaw_meshes(spec, scene: Path):
    """(geom, vertices, faces) of the scene's two jaw geoms, as the mesh files hold them (scaled)."""
    import trimesh

    folder = Path(scene).parent / (spec.meshdir or "")
    for g in [g for g in spec.geoms if g.name in ("maxilla", "mandible")]:
        mesh = next(m for m in spec.meshes if m.name == g.meshname)
        src = trimesh.load(folder / mesh.file, force="mesh", process=False)
        yield g, src.vertices * np.asarray(mesh.scale), src.faces


def coacd_cached(scene: Path, threshold: float) -> bool:
    """Are both jaws' CoACD decompositions already in ``out/coacd``?"""
    spec = mujoco.MjSpec.from_file(str(scene))
    return all(coacd_cache_path(V, F, threshold, ROOT / "out" / "coacd").exists() for _, V, F in _jaw_meshes(spec, scene))


def _coacd_model(scene: Path, threshold: float):
    """The scene with each jaw's collision geom replaced by its CoACD pieces (visual mesh kept)."""
    spec = mujoco.MjSpec.from_file(str(scene))
    seconds, pieces = 0.0, 0
    for g, V, F in list(_jaw_meshes(spec, scene)):
        parts, sec = coacd_pieces(V, F, threshold, ROOT / "out" / "coacd")
        seconds += sec
        body = g.parent
        for i, (pv, pf) in enumerate(parts):
            name = f"{g.name}_coacd{i}"
            spec.add_mesh(name=name, uservert=np.asarray(pv, float).ravel().tolist(), userface=np.asarray(pf, int).ravel().tolist())
            p = body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name, pos=g.pos, quat=g.quat,
                              contype=g.contype, conaffinity=g.conaffinity, group=3, density=0.0)
            p.solref, p.solimp, p.friction, p.margin = g.solref, g.solimp, g.friction, g.margin
            pieces += 1
        g.contype = g.conaffinity = 0
    t = time.perf_counter()
    m = spec.compile()
    return m, time.perf_counter() - t, seconds, pieces



def _first_touch_hinge(m, probe, q, gmx, gmd, ba, bb) -> float:
    """The hinge angle (rad) where the meshes first touch with the rest pose's other joints:
    bisection on coal's collision test within 1° of the rest."""
    def hits(h):
        probe.qpos[:] = q
        probe.qpos[0] = h
        mujoco.mj_forward(m, probe)
        return jawmod.coal_collides(ba, geom_pose(probe, gmx), bb, geom_pose(probe, gmd))

    lo, hi = q[0] + np.radians(1.0), q[0] - np.radians(1.0)  # open (apart) .. closed (intersecting)
    if hits(lo) or not hits(hi):
        return float("nan")
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if hits(mid) else (mid, hi)
    return 0.5 * (lo + hi)


def run_mode(scene, mode, steps, every, coal_pair, coacd_threshold=0.05):
    if mode == "ist-mesh":
        m, t_compile = _spec_model(scene, "mesh", None)
        h = A.attach(m)
    elif mode == "ist-surface":
        m, t_compile = _spec_model(scene, "mesh", None)
        h = A.attach(m, narrowphase="surface")
    elif mode == "ist-sdf":
        m, t_compile = _spec_model(scene, "sdf", 1)
        h = A.attach(m)
    elif mode == "native-hull":
        m, t_compile = _spec_model(scene, "mesh", None)
        h = None
    elif mode == "native-coacd":
        m, t_compile, t_decomp, npieces = _coacd_model(scene, coacd_threshold)
        h = None
    else:  # native mesh-SDF with MuJoCo's default octree
        m, t_compile = _spec_model(scene, "sdf", None)
        h = None
    gmx = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "maxilla")
    gmd = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "mandible")
    jaws = {m.geom_bodyid[gmx], m.geom_bodyid[gmd]}  # CoACD pieces are other geoms of the same bodies
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "open"))
    d.ctrl[:] = 1.0
    probe = mujoco.MjData(m)
    times = np.empty(steps)
    err = []
    ba, bb = coal_pair
    offset = h.pairs[0].offset if h is not None and h.pairs else 0.0
    eps = h.pairs[0].error_bound if h is not None and h.pairs else float("nan")
    for i in range(steps):
        t = time.perf_counter()
        mujoco.mj_step(m, d)
        times[i] = time.perf_counter() - t
        if i % every == 0:
            cons = [c.dist for c in d.contact[:d.ncon] if {m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]} == jaws]
            if h is not None:
                # the IST distance on a probe MjData at the stepped one's new qpos (the hook keeps
                # a query's coherence state apart from the steps', and the probe keeps the timed
                # steps free of anything but this Python)
                probe.qpos[:] = d.qpos
                mujoco.mj_forward(m, probe)
                at = probe
                rep = mujoco.mj_geomDistance(m, probe, gmx, gmd, 0.01, None) + offset  # d_IST
            else:  # the contacts were found at the step's start pose, which d.geom_xpos still holds
                at = d
                rep = min(cons) if cons else float("nan")
            true_d = jawmod.coal_distance(ba, geom_pose(at, gmx), bb, geom_pose(at, gmd))
            hit = jawmod.coal_collides(ba, geom_pose(at, gmx), bb, geom_pose(at, gmd))
            err.append({"frame": i, "coal": float(true_d), "coal_hit": bool(hit), "reported": float(rep),
                        "contacts": len(cons)})
    q = d.qpos.copy()
    probe.qpos[:] = q
    mujoco.mj_forward(m, probe)  # the rest pose's geoms (d's are the last step's start)
    rest = jawmod.coal_distance(ba, geom_pose(probe, gmx), bb, geom_pose(probe, gmd))
    touch = _first_touch_hinge(m, probe, q, gmx, gmd, ba, bb)
    res = {
        "mode": mode, "compile_s": t_compile, "steps": steps,
        "step_us_median": float(np.median(times) * 1e6),
        "step_us_mean": float(np.mean(times) * 1e6),
        "step_us_p90": float(np.percentile(times, 90) * 1e6),
        "step_us_median_closed": float(np.median(times[steps // 2:]) * 1e6),
        "final_hinge_deg": float(np.degrees(q[0])), "final_protrusion_mm": float(q[1] * 1e3), "final_lateral_mm": float(q[2] * 1e3),
        "final_coal_mm": float(rest * 1e3),
        "hinge_past_touch_deg": float(np.degrees(touch - q[0])),  # the hinge opens the jaw as it grows
        "error_bound": eps, "offset": offset, "frames": err,
    }
    if mode == "native-coacd":
        res.update(decompose_s=t_decomp, pieces=npieces, coacd_threshold=coacd_threshold)
    if h is not None:
        sep = [e for e in err if e["coal"] > 0 and np.isfinite(e["reported"])]
        res["bound_violations"] = int(sum(1 for e in sep if not (e["reported"] - eps - 1e-9 <= e["coal"] <= e["reported"] + 1e-9)))
        res["abs_err_mm_median"] = float(np.median([abs(e["reported"] - e["coal"]) for e in sep]) * 1e3) if sep else None
        res["abs_err_mm_max"] = float(max(abs(e["reported"] - e["coal"]) for e in sep) * 1e3) if sep else None
        res["hook"] = h.stats()
        res["surface_build_s"] = h.surface_seconds
        res["trees"] = {k: {"leaves": t.num_leaves, "eps_mm": t.error_bound * 1e3} for k, t in h.trees.items()}
        h.detach()
    else:
        both = [e for e in err if np.isfinite(e["reported"])]
        res["false_contact_frames"] = int(sum(1 for e in both if not e["coal_hit"] and e["coal"] > 0))
        res["median_reported_depth_mm"] = float(np.median([e["reported"] for e in both]) * 1e3) if both else None
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", default="bundled,real")
    ap.add_argument("--modes", default="ist-mesh,ist-surface,ist-sdf,native-hull,native-sdf,native-coacd")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="200 steps, no native mesh-SDF, CoACD only if already decomposed")
    ap.add_argument("--coacd-threshold", type=float, default=0.05, help="CoACD concavity threshold (its default 0.05)")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_mujoco"))
    a = ap.parse_args()
    if a.quick:
        a.steps = 200
        a.modes = a.modes.replace(",native-sdf", "")
    try:
        import coacd  # noqa: F401
    except ImportError:
        if "native-coacd" in a.modes:
            print("skip native-coacd: pip install coacd")
        a.modes = ",".join(x for x in a.modes.split(",") if x != "native-coacd")
    scenes = {}
    for p in a.pairs.split(","):
        if p == "bundled":
            scenes[p] = ROOT / "models" / "jaw_closure.xml"
        elif p == "real":
            if SHARED.exists():
                scenes[p] = pair_scene(SHARED, ROOT / "out" / "scene_real", "closure")
            else:
                print(f"skip real: {SHARED} not present")
    results = {"mujoco": mujoco.__version__, "cases": {}}
    for name, scene in scenes.items():
        m0 = mujoco.MjModel.from_xml_path(str(scene))
        coal_pair = tuple(jawmod.coal_bvh(*mesh_of(m0, mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_GEOM, g))) for g in ("maxilla", "mandible"))
        results["cases"][name] = {}
        for mode in a.modes.split(","):
            if mode == "native-coacd" and a.quick and not coacd_cached(scene, a.coacd_threshold):
                print(f"{name:8s} native-coacd skipped in --quick: no cached decomposition (the full run makes one, 1-2 min)")
                continue
            r = run_mode(scene, mode, a.steps, a.every, coal_pair, a.coacd_threshold)
            results["cases"][name][mode] = r
            extra = f"  ({r['pieces']} CoACD pieces, {r['decompose_s']:.0f} s to decompose)" if "pieces" in r else ""
            print(f"{name:8s} {mode:12s} compile {r['compile_s']:6.1f} s  step median {r['step_us_median']:8.1f} µs "
                  f"mean {r['step_us_mean']:8.1f} (closed {r['step_us_median_closed']:8.1f})  hinge {r['final_hinge_deg']:+.3f}°  "
                  + (f"violations {r['bound_violations']} err med/max {r['abs_err_mm_median']}/{r['abs_err_mm_max']} mm"
                     if "bound_violations" in r else f"false-contact frames {r['false_contact_frames']}") + extra, flush=True)
    out = Path(a.out)
    os.makedirs(out.parent, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=1))
    lines = ["| pair | mode | compile s | step µs median | mean | once closed | final hinge ° | past coal's first touch ° "
             "| final coal gap mm | bound violations / false contacts | |err| median / max mm |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, case in results["cases"].items():
        for mode, r in case.items():
            viol = r.get("bound_violations", r.get("false_contact_frames"))
            err = f"{r['abs_err_mm_median']:.3f} / {r['abs_err_mm_max']:.3f}" if r.get("abs_err_mm_median") is not None else "–"
            lines.append(f"| {name} | {mode} | {r['compile_s']:.1f} | {r['step_us_median']:.1f} | {r['step_us_mean']:.1f} | {r['step_us_median_closed']:.1f} | "
                         f"{r['final_hinge_deg']:+.3f} | {r['hinge_past_touch_deg']:+.3f} | {r['final_coal_mm']:.3f} | "
                         f"{viol} | {err} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results["cases"]), figsize=(6 * len(results["cases"]), 4), squeeze=False)
    for ax, (name, case) in zip(axes[0], results["cases"].items()):
        for mode, r in case.items():
            f = r["frames"]
            ax.plot([e["frame"] for e in f], [e["reported"] * 1e3 for e in f], label=f"{mode} ({r['step_us_median']:.0f} µs)")
        f = next(iter(case.values()))["frames"]
        ax.plot([e["frame"] for e in f], [e["coal"] * 1e3 for e in f], "k--", label="coal (exact, IST-mesh run)")
        ax.set_xlabel("step")
        ax.set_ylabel("reported distance / deepest contact (mm)")
        ax.set_title(f"{name} jaw closure")
        ax.set_ylim(-2, 3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=120)
    print(out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
