"""Haptic loop time and force error: IST penalty laws along scripted device motions, coal as reference.

    python scripts/bench_haptic.py                 # bundled jaws (+ the CBCT pair when ../shared is there)
    python scripts/bench_haptic.py --quick

For each jaw pair, penalty law (``contacts``; ``surface``: the contacts law on depths measured on
the meshes, ``mjist_narrowphase='surface'``; ``volume``) and tree resolution (``--max-errors``),
every scripted trajectory is run through ``mjist.jaw.haptic.run`` (mocap update → ``mj_step`` →
force readout, timed per step). Every ``--every`` steps in contact, coal's exact collision
with contacts gives the deepest triangle-pair penetration δ_coal at that pose; the reference
force is the contacts law applied to it, ``k·δ_coal``, against the IST's ``k·δ_IST`` of its
deepest group (so the error is k·|δ_IST − δ_coal|; the certified part of it is ≤ k·(ε1+ε2)).
Writes ``out/bench_haptic.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import mujoco
import numpy as np

from mjist.jaw import haptic
from mjist.jaw import pair as jawmod
from mjist.jaw.exact import coal_depth
from mjist.jaw.scenes import pair_scene
from mjist.mujoco import attach as A
from mjist.mujoco import config
from mjist.mujoco.scene import geom_pose, geom_pose_at, mesh_of

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data" / "jaw"


def run_case(scene, law, max_error, trajectories, every, steps_cap):
    # 'surface': the contacts law on depths measured on the meshes (mjist_narrowphase='surface')
    narrow = "surface" if law == "surface" else "spheres"
    model, h = A.load_model(scene, penalty="contacts" if law == "surface" else law, narrowphase=narrow,
                            max_error=max_error, progress=True)
    gmx, gmd = h.geoms["maxilla"], h.geoms["mandible"]
    ba, bb = (jawmod.coal_bvh(*mesh_of(model, g)) for g in (gmx, gmd))
    d0 = mujoco.MjData(model)
    mujoco.mj_forward(model, d0)
    Pmx = geom_pose(d0, gmx)
    k = config.DEFAULT_STIFFNESS["contacts"]
    out = {"law": law, "max_error": max_error, "eps_mm": h.pairs[0].error_bound * 1e3,
           "leaves": {n: t.num_leaves for n, t in h.trees.items()}, "trajectories": {}}
    for name in trajectories:
        path = haptic.scripted(model, name)
        if steps_cap:
            path = haptic.DevicePath(path.name, path.pos[:steps_cap], path.quat[:steps_cap], path.dt)
        log = haptic.run(model, h, path)
        log.pop("_data")
        s = haptic.summary(log)
        err, coal_t = [], []
        idx = np.flatnonzero(log["contacts"] > 0)[::every]
        for i in idx:
            Pmd = geom_pose_at(model, gmd, log["mandible_pos"][i], log["mandible_quat"][i])
            t = time.perf_counter()
            dc = coal_depth(ba, Pmx, bb, Pmd)
            coal_t.append(time.perf_counter() - t)
            di = float(log["depth"][i])
            err.append({"step": int(i), "ist_depth": di, "coal_depth": dc, "force_err_N": k * abs(di - dc)})
        s["force_check"] = err
        s["coal_collide_ms_median"] = float(np.median(coal_t) * 1e3) if coal_t else None
        s["depth_err_mm_median"] = float(np.median([abs(e["ist_depth"] - e["coal_depth"]) for e in err]) * 1e3) if err else None
        s["depth_err_mm_max"] = float(max(abs(e["ist_depth"] - e["coal_depth"]) for e in err) * 1e3) if err else None
        s["ist_deeper_than_coal"] = int(sum(e["ist_depth"] > e["coal_depth"] + 1e-9 for e in err))
        s["hook"] = h.stats()
        out["trajectories"][name] = s
        out["trajectories"][name]["_series"] = {"t": log["time"].tolist()[::5],
                                                "device_N": np.linalg.norm(log["coupling_force"], axis=1).tolist()[::5],
                                                "contact_N": np.linalg.norm(log["contact_force"], axis=1).tolist()[::5]}
        print(f"  {law:8s} ε {out['eps_mm']:.2f} mm {name:13s} loop {s['loop_us_median']:7.1f} µs median, "
              f"{s['loop_us_p99']:7.1f} p99 | device ≤ {s['device_force_max_N']:.2f} N, contact ≤ {s['contact_force_max_N']:.2f} N, "
              f"max |ΔF|/step {s['force_step_max_N']:.2f} N | |δ_IST−δ_coal| med/max "
              f"{s['depth_err_mm_median']}/{s['depth_err_mm_max']} mm (coal {s['coal_collide_ms_median']} ms)", flush=True)
    h.detach()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", default="bundled,real")
    ap.add_argument("--laws", default="contacts,surface,volume",
                    help="penalty laws; 'surface' is the contacts law on depths measured on the meshes")
    ap.add_argument("--max-errors", default="default,0.0003,0.0005",
                    help="metres per tree; 'default' = the scene's; a value equal to the scene's is run once")
    ap.add_argument("--trajectories", default="close,lateral_left,lateral_right,protrusion,chewing")
    ap.add_argument("--every", type=int, default=20, help="coal check every N in-contact steps")
    ap.add_argument("--quick", action="store_true", help="bundled only, default ε, 500 steps per trajectory")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_haptic"))
    a = ap.parse_args()
    steps_cap = 500 if a.quick else 0
    if a.quick:
        a.pairs, a.max_errors = "bundled", "default"
    scenes = {}
    for p in a.pairs.split(","):
        if p == "bundled":
            scenes[p] = haptic.SCENE
        elif p == "real":
            if SHARED.exists():
                scenes[p] = pair_scene(SHARED, ROOT / "out" / "scene_real_haptic", "haptic")
            else:
                print(f"skip real: {SHARED} not present")
    results = {"mujoco": mujoco.__version__, "cases": []}
    t0 = time.perf_counter()
    for name, scene in scenes.items():
        m0 = mujoco.MjModel.from_xml_path(str(scene))
        own = config.read_config(m0).max_error
        seen = set()
        for me in a.max_errors.split(","):
            value = own if me == "default" else float(me)
            if value in seen:
                continue
            seen.add(value)
            for law in a.laws.split(","):
                r = run_case(scene, law, None if me == "default" else float(me), a.trajectories.split(","), a.every, steps_cap)
                r["pair"] = name
                results["cases"].append(r)
    results["seconds"] = time.perf_counter() - t0
    out = Path(a.out)
    os.makedirs(out.parent, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=1))
    lines = ["| pair | law | ε1+ε2 mm | trajectory | loop µs median | p99 | max | device N max | max ΔF/step N | |δ_IST−δ_coal| median / max mm |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in results["cases"]:
        for tn, s in c["trajectories"].items():
            e = f"{s['depth_err_mm_median']:.3f} / {s['depth_err_mm_max']:.3f}" if s["depth_err_mm_median"] is not None else "–"
            lines.append(f"| {c['pair']} | {c['law']} | {c['eps_mm']:.2f} | {tn} | {s['loop_us_median']:.1f} | {s['loop_us_p99']:.1f} | "
                         f"{s['loop_us_max']:.0f} | {s['device_force_max_N']:.2f} | {s['force_step_max_N']:.2f} | {e} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = [c for c in results["cases"]]
    fig, axes = plt.subplots(len(cases), 1, figsize=(10, 2.6 * len(cases)), squeeze=False)
    for ax, c in zip(axes[:, 0], cases):
        off = 0.0
        for tn, s in c["trajectories"].items():
            ser = s["_series"]
            t = np.asarray(ser["t"]) + off
            ax.plot(t, ser["device_N"], lw=0.8, label=f"{tn} device")
            ax.plot(t, ser["contact_N"], lw=0.6, alpha=0.6)
            off = t[-1] + 0.1 if len(t) else off
        ax.set_title(f"{c['pair']} {c['law']} law, ε1+ε2 {c['eps_mm']:.2f} mm (device force solid, contact force faint)", fontsize=9)
        ax.set_ylabel("N")
        ax.legend(fontsize=6, ncol=5)
    axes[-1, 0].set_xlabel("simulated time, trajectories back to back (s)")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)
    print(out.with_suffix(".md").read_text())
    print(f"total {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
