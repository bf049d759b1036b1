"""Numerical stability under stress: long runs, slams, bad timesteps, a drifting device, and
attach/detach cycles, each checked against coal's exact meshes.

    python scripts/bench_stress.py [--quick] [--out out/bench_stress]

Cases (bundled jaws, IST sphere contacts as the scenes set them):

* ``closure``: the jaw-closure scene (``models/jaw_closure.xml``) clenched for 100 s of 1 ms steps
  (``--quick``: 10 s): finite, the hinge's spread over the second half (creep or oscillation),
  the final hinge, coal's distance or deepest penetration at the end, the hook's failure counters;
* ``timestep``: the same closure for 1 s at 0.5, 1, 2, 5 and 10 ms steps (MuJoCo's default is 2 ms):
  finite, settled, where it rests against the 1 ms run (holds: within 0.1°), coal at the end;
* ``slam``: the haptic handle driven straight up into the teeth at 0.05 to 2 m/s (0.05 to 2 mm per
  1 ms step): how far past the designed occlusion the mandible got, coal's penetration at the
  deepest step against the IST's depth + ε, and whether it rests on the teeth afterwards;
* ``chewing``: 100 s of chewing cycles (``--quick``: 20 s) with the handle's quaternion drifting
  ±5 % off unit length: finite, and the last cycles' largest speed and contact force against the
  first ones' (energy growth);
* ``attach``: 1,000 attach / step / detach cycles (``--quick``: 100): the collision table back to
  MuJoCo's each time, resident memory growth.

Writes ``OUT/bench_stress.json`` and ``OUT/bench_stress.md``.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import write_table  # noqa: E402

from mjist.jaw import haptic
from mjist.jaw.demo import run_closure
from mjist.jaw.exact import coal_bvh, coal_depth, coal_distance
from mjist.mujoco import attach as A
from mjist.mujoco import registry
from mjist.mujoco.scene import geom_pose, geom_pose_at, mesh_of

ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"


def _true_gap_mm(model, d, bvh) -> float:
    """coal at the pair's current poses: the distance (> 0) or minus the deepest penetration (mm)."""
    g1, g2 = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("maxilla", "mandible"))
    P1, P2 = geom_pose(d, g1), geom_pose(d, g2)
    dist = coal_distance(bvh[0], P1, bvh[1], P2)
    return dist * 1e3 if dist > 0 else -coal_depth(bvh[0], P1, bvh[1], P2) * 1e3


def _bvhs(model):
    return [coal_bvh(*mesh_of(model, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n))) for n in ("maxilla", "mandible")]


def closure(seconds: float, cache) -> dict:
    model, h = A.load_model(MODELS / "jaw_closure.xml", cache_dir=cache)
    try:
        bvh = _bvhs(model)
        d = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, d, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "open"))
        d.ctrl[:] = 1.0
        n = int(round(seconds / model.opt.timestep))
        hinge = np.empty(n)
        t0 = time.perf_counter()
        for i in range(n):
            mujoco.mj_step(model, d)
            hinge[i] = d.qpos[0]
        wall = time.perf_counter() - t0
        tail = np.degrees(hinge[n // 2:])
        stats = h.stats()
        finite = bool(np.all(np.isfinite(hinge)) and np.all(np.isfinite(d.qvel)))
        row = {"case": "closure", "setting": f"{seconds:g} s of 1 ms steps", "finite": finite,
               "hinge_spread_deg": float(np.ptp(tail)), "final_hinge_deg": float(tail[-1]),
               "true_gap_mm": _true_gap_mm(model, d, bvh), "error_bound_mm": h.pairs[0].error_bound * 1e3,
               "failed": stats["failed"], "bad_pose": stats["bad_pose"], "wall_s": wall}
        row["ok"] = bool(finite and row["hinge_spread_deg"] < 0.05 and abs(row["final_hinge_deg"]) < 1.0
                         and row["true_gap_mm"] > -row["error_bound_mm"] and not stats["failed"] and not stats["bad_pose"])
        return row
    finally:
        h.detach()


def timesteps(steps_ms, cache) -> list[dict]:
    rows, ref = [], None
    for dt in steps_ms:
        model, h = A.load_model(MODELS / "jaw_closure.xml", cache_dir=cache)
        try:
            model.opt.timestep = dt * 1e-3
            r = run_closure(model, seconds=1.0, handle=h)
            bvh = _bvhs(model)
            gap = _true_gap_mm(model, r.pop("_data"), bvh)
            finite = bool(np.isfinite(r["final_hinge_deg"]) and np.isfinite(r["drift_mm_s"]))
            row = {"case": "timestep", "setting": f"{dt:g} ms", "finite": finite, "settled": r["settled"],
                   "final_hinge_deg": r["final_hinge_deg"], "drift_mm_s": r["drift_mm_s"], "true_gap_mm": gap,
                   "error_bound_mm": r["error_bound_mm"], "step_us_median": r["step_us_median"]}
            if dt == 1.0:
                ref = row["final_hinge_deg"]
            rows.append(row)
        finally:
            h.detach()
    for row in rows:
        row["hinge_vs_1ms_deg"] = row["final_hinge_deg"] - ref if ref is not None else None
        row["ok"] = bool(row["finite"] and row["settled"] and row["hinge_vs_1ms_deg"] is not None
                         and abs(row["hinge_vs_1ms_deg"]) < 0.1 and row["true_gap_mm"] > -row["error_bound_mm"])
    return rows


def _straight_path(model, v, start=-4e-3, stop=2e-3, hold=300):
    """The handle moved straight up (jaw frame) at ``v`` m/s from ``start`` below the occlusion to
    ``stop`` past it, then held."""
    from scipy.spatial.transform import Rotation

    p0, R0, _, _, R_jaw = haptic._occlusion(model)
    dt = float(model.opt.timestep)
    s = np.concatenate([np.arange(start, stop, v * dt), np.full(hold, stop)])
    x, y, z, w = Rotation.from_matrix(R0).as_quat()
    path = haptic.DevicePath(f"straight {v} m/s", p0 + s[:, None] * R_jaw[:, 1], np.tile([w, x, y, z], (len(s), 1)), dt)
    return path, p0, R_jaw[:, 1]


def slams(speeds, cache) -> list[dict]:
    model, h = A.load_model(MODELS / "haptic_jaw.xml", cache_dir=cache)
    rows = []
    try:
        bvh = _bvhs(model)
        gmx, gmd = h.geoms["maxilla"], h.geoms["mandible"]
        d = mujoco.MjData(model)
        mujoco.mj_forward(model, d)
        Pmx = geom_pose(d, gmx)
        eps = h.pairs[0].error_bound
        for v in speeds:
            path, p0, up = _straight_path(model, v)
            log = haptic.run(model, h, path)
            s = haptic.summary(log)
            past = float(((log["mandible_pos"] - p0) @ up).max()) * 1e3
            speed = np.linalg.norm(np.diff(log["mandible_pos"], axis=0), axis=1) / path.dt
            i = int(np.argmax(log["depth"]))
            true = coal_depth(bvh[0], Pmx, bvh[1], geom_pose_at(model, gmd, log["mandible_pos"][i], log["mandible_quat"][i]))
            row = {"case": "slam", "setting": f"{v:g} m/s", "finite": s["finite"], "impact_speed_m_s": float(speed.max()),
                   "past_occlusion_mm": past, "ist_depth_mm": float(log["depth"][i]) * 1e3, "true_depth_mm": true * 1e3,
                   "error_bound_mm": eps * 1e3, "rest_speed_mm_s": float(speed[-50:].max()) * 1e3,
                   "contacts_at_end": int(log["contacts"][-1])}
            row["ok"] = bool(s["finite"] and past < 1.0 and true <= log["depth"][i] + eps and row["contacts_at_end"] > 0
                             and row["rest_speed_mm_s"] < 50.0)
            rows.append(row)
    finally:
        h.detach()
    return rows


def chewing(seconds: float, cache) -> dict:
    model, h = A.load_model(MODELS / "haptic_jaw.xml", cache_dir=cache)
    try:
        path = haptic.scripted(model, "chewing", seconds)
        k = 1.0 + 0.05 * np.sin(np.linspace(0.0, 7.0, path.steps))  # the quaternion's norm drifting ±5 %
        path = haptic.DevicePath(path.name + " (drifting quaternion)", path.pos, path.quat * k[:, None], path.dt)
        t0 = time.perf_counter()
        log = haptic.run(model, h, path)
        wall = time.perf_counter() - t0
        s = haptic.summary(log)
        per = int(round(2.0 / path.dt))  # the pattern repeats every 2 s
        cycles = path.steps // per
        speed = np.linalg.norm(np.diff(log["mandible_pos"], axis=0), axis=1) / path.dt
        vmax = [speed[c * per:(c + 1) * per - 1].max() for c in range(cycles)]
        fmax = [np.linalg.norm(log["contact_force"][c * per:(c + 1) * per], axis=1).max() for c in range(cycles)]
        row = {"case": "chewing", "setting": f"{seconds:g} s, quaternion ±5 %", "finite": s["finite"],
               "contact_steps": s["contact_steps"], "steps": s["steps"],
               "speed_last_over_first": float(max(vmax[-3:]) / max(vmax[1:4])),
               "force_last_over_first": float(max(fmax[-3:]) / max(fmax[1:4])),
               "loop_us_median": s["loop_us_median"], "wall_s": wall}
        row["ok"] = bool(s["finite"] and row["speed_last_over_first"] <= 1.05 and row["force_last_over_first"] <= 1.2)
        return row
    finally:
        h.detach()


def attach_cycles(n: int, cache) -> dict:
    model, h = A.load_model(MODELS / "jaw_closure.xml", cache_dir=cache)
    h.detach()
    d = mujoco.MjData(model)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    restored = True
    t0 = time.perf_counter()
    for _ in range(n):
        h = A.attach(model, cache_dir=cache)
        mujoco.mj_step(model, d)
        h.detach()
        restored &= registry.table_is_original()
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0 - before
    return {"case": "attach", "setting": f"{n} attach / step / detach", "finite": bool(np.all(np.isfinite(d.qpos))),
            "table_restored": bool(restored), "rss_growth_mb": grown, "ms_per_cycle": (time.perf_counter() - t0) / n * 1e3,
            "ok": bool(restored and grown < 50.0)}


def _figures(r: dict) -> str:
    keys = {"closure": ("hinge_spread_deg", "final_hinge_deg", "true_gap_mm", "failed"),
            "timestep": ("settled", "final_hinge_deg", "hinge_vs_1ms_deg", "true_gap_mm", "step_us_median"),
            "slam": ("impact_speed_m_s", "past_occlusion_mm", "ist_depth_mm", "true_depth_mm", "rest_speed_mm_s"),
            "chewing": ("contact_steps", "speed_last_over_first", "force_last_over_first", "loop_us_median"),
            "attach": ("table_restored", "rss_growth_mb", "ms_per_cycle")}[r["case"]]

    def f(v):
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    return ", ".join(f"{k} {f(r[k])}" for k in keys)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter runs (closure 10 s, chewing 20 s, 100 cycles)")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_stress"))
    ap.add_argument("--cache-dir", default=None)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = args.cache_dir
    rows = [closure(10.0 if args.quick else 100.0, cache)]
    rows += timesteps([0.5, 1.0, 2.0, 5.0, 10.0], cache)
    rows += slams([0.05, 0.2, 0.5, 1.0, 2.0], cache)
    rows.append(chewing(20.0 if args.quick else 100.0, cache))
    rows.append(attach_cycles(100 if args.quick else 1000, cache))
    (out / "bench_stress.json").write_text(json.dumps(rows, indent=1))
    write_table(out / "bench_stress.md", ["case", "setting", "finite", "figures", "holds"],
                [[r["case"], r["setting"], "yes" if r["finite"] else "NO", _figures(r), "yes" if r["ok"] else "NO"]
                 for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
