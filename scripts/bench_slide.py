"""Where a jaw pushed straight into occlusion comes to rest: sphere vs surface contacts vs mesh-SDF.

    python scripts/bench_slide.py                         # CBCT pair (../shared), default and 0.1 mm trees
    python scripts/bench_slide.py --max-errors default --steps 400
    python scripts/bench_slide.py --defaults --steps 750  # MuJoCo's timestep, solref, solimp: 1.5 s

The CBCT mandible on one slide joint along +y (superior), started 2 mm below its stored pose and
pushed up by a constant 20 m/s² (the closing muscles) against the fixed maxilla, damped; no
rotation, so coal's first touch along the slide is the exact answer: the slide position where
the meshes start to intersect, found by bisection on coal's collision test. Per contact mode and
tree error: ``mj_step`` time (median over the run and once at rest), where it rests against that
first touch (> 0: past it, into the maxilla), and coal's distance at the rest pose. MuJoCo's
mesh-SDF runs the same scene. ``surface-unheld`` is the surface narrow phase measuring every call
(``mjist_surface_hold`` 0). "Settled": the simulated time after which the slide's speed stays
below 0.1 mm/s. ``--defaults`` drops the scene's own timestep (1 ms), ``solref`` and ``solimp``
for MuJoCo's defaults. Writes ``out/bench_slide.{json,md}``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))
from benchlib import write_table  # noqa: E402

from mjist.jaw import pair as jawmod  # noqa: E402
from mjist.mujoco import attach as A  # noqa: E402

SHARED = ROOT.parent / "shared" / "data" / "jaw"
START = -0.002  # slide origin: the mandible 2 mm below its stored pose

XML = """<mujoco model="slide">
  <compiler meshdir="{meshdir}"/>
  <option {timestep}integrator="implicitfast" gravity="0 20 0"/>
  <custom>
    <text name="mjist_geoms" data="maxilla mandible"/>
    <numeric name="mjist_contacts" data="4"/>
    {max_error}
  </custom>
  <default><geom {soft}friction="0.3"/></default>
  <asset>
    <mesh name="maxilla" file="maxilla.obj"/>
    <mesh name="mandible" file="mandible.obj"/>
  </asset>
  <worldbody>
    <geom name="maxilla" type="{gtype}" mesh="maxilla"/>
    <body name="mandible" pos="0 {start} 0">
      <joint name="slide" type="slide" axis="0 1 0" damping="40"/>
      <geom name="mandible" type="{gtype}" mesh="mandible" density="1900"/>
    </body>
  </worldbody>
</mujoco>
"""


SETTLED = 1e-4  # m/s: the slide counts as at rest below this speed


def _model(meshdir, gtype, max_error, defaults=False):
    me = f'<numeric name="mjist_max_error" data="{max_error:g}"/>' if max_error else ""
    own = {"timestep": 'timestep="0.001" ', "soft": 'solref="0.004 1" solimp="0.95 0.99 0.0005" '}
    spec = mujoco.MjSpec.from_string(XML.format(meshdir=meshdir, gtype=gtype, max_error=me, start=START,
                                                **({"timestep": "", "soft": ""} if defaults else own)))
    if gtype == "sdf":
        spec.option.sdf_initpoints = 50
    return spec.compile()


def first_touch(meshdir):
    """Slide position (from ``START``) where coal first finds the stored pair intersecting, and
    the coal models."""
    import trimesh

    def bvh(name):
        m = trimesh.load(Path(meshdir) / f"{name}.obj", force="mesh", process=False)
        return jawmod.coal_bvh(m.vertices, m.faces)

    bx, bm = bvh("maxilla"), bvh("mandible")
    eye = np.eye(4)

    def hits(q):
        P = np.eye(4)
        P[1, 3] = START + q
        return jawmod.coal_collides(bx, eye, bm, P)

    lo, hi = 0.0, -START  # apart at the start, intersecting in the stored pose
    assert not hits(lo) and hits(hi), "the stored pair must intersect and clear 2 mm below"
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if hits(mid) else (mid, hi)
    return 0.5 * (lo + hi), (bx, bm)


def run(meshdir, mode, max_error, steps, touch, coal, surface_groups=8, defaults=False):
    gtype = "sdf" if mode == "native-sdf" else "mesh"
    m = _model(meshdir, gtype, max_error, defaults)
    t0 = time.perf_counter()
    h = None
    if mode in ("spheres", "surface", "surface-unheld"):
        h = A.attach(m, narrowphase=mode.split("-")[0], surface_groups=surface_groups,
                     surface_hold=0.0 if mode == "surface-unheld" else None)
    attach_s = time.perf_counter() - t0
    d = mujoco.MjData(m)
    times = np.empty(steps)
    settled = 0.0
    for i in range(steps):
        t = time.perf_counter()
        mujoco.mj_step(m, d)
        times[i] = time.perf_counter() - t
        if not abs(d.qvel[0]) < SETTLED:
            settled = d.time
    q = float(d.qpos[0])
    P = np.eye(4)
    P[1, 3] = START + q
    bx, bm = coal
    gap = jawmod.coal_distance(bx, np.eye(4), bm, P)
    res = {
        "mode": mode, "max_error_mm": max_error * 1e3 if max_error else None, "steps": steps, "attach_s": attach_s,
        "step_us_median": float(np.median(times) * 1e6), "step_us_median_rest": float(np.median(times[steps // 2:]) * 1e6),
        "rest_past_first_touch_mm": (q - touch) * 1e3, "rest_coal_distance_mm": float(gap * 1e3),
        "final_speed_mm_s": float(abs(d.qvel[0]) * 1e3), "contacts": int(d.ncon),
        "settled_s": settled if settled < d.time else None, "timestep_s": m.opt.timestep,
    }
    if h is not None:
        res["error_bound_mm"] = h.pairs[0].error_bound * 1e3
        res["hook"] = h.stats()
        res["surface_build_s"] = h.surface_seconds
        h.detach()
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--modes", default="spheres,surface,native-sdf")
    ap.add_argument("--max-errors", default="default,0.0001", help="per-tree max_error in metres, 'default': the layer's")
    ap.add_argument("--steps", type=int, default=800)
    ap.add_argument("--surface-groups", type=int, default=8, help="mjist_surface_groups of the surface contacts")
    ap.add_argument("--defaults", action="store_true", help="MuJoCo's default timestep, solref and solimp")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_slide"))
    a = ap.parse_args()
    out = Path(a.out)
    os.makedirs(out.parent, exist_ok=True)
    if not SHARED.exists():
        msg = f"skipped: {SHARED} not present (the CBCT pair lives in ../shared/data/jaw)"
        out.with_suffix(".md").write_text(msg + "\n")
        print(msg)
        return
    touch, coal = first_touch(SHARED)
    print(f"coal first touch {touch * 1e3:.4f} mm up the slide ({(START + touch) * 1e3:+.4f} mm from the stored pose)")
    rows = []
    for me in a.max_errors.split(","):
        max_error = None if me == "default" else float(me)
        for mode in a.modes.split(","):
            if mode == "native-sdf" and rows and any(r["mode"] == "native-sdf" for r in rows):
                continue  # one mesh-SDF run: it has no tree
            r = run(SHARED, mode, max_error, a.steps, touch, coal, a.surface_groups, a.defaults)
            rows.append(r)
            eb = f"ε1+ε2 {r['error_bound_mm']:.3f} mm" if "error_bound_mm" in r else "no tree"
            print(f"{mode:10s} {eb:18s} step median {r['step_us_median']:8.1f} µs (at rest {r['step_us_median_rest']:8.1f})  "
                  f"rest {r['rest_past_first_touch_mm']:+.4f} mm past first touch, coal distance "
                  f"{r['rest_coal_distance_mm']:.4f} mm, speed {r['final_speed_mm_s']:.3f} mm/s, settled "
                  f"{'no' if r['settled_s'] is None else format(r['settled_s'], '.3f') + ' s'}", flush=True)
    out.with_suffix(".json").write_text(json.dumps({"first_touch_mm": touch * 1e3, "start_mm": START * 1e3,
                                                    "mujoco": mujoco.__version__, "defaults": a.defaults, "runs": rows},
                                                   indent=1))
    sdf = next((r["step_us_median_rest"] for r in rows if r["mode"] == "native-sdf"), None)
    table = []
    for r in rows:
        ratio = f"{sdf / r['step_us_median_rest']:.1f}" if sdf and r["mode"] != "native-sdf" else "–"
        eb = f"{r['error_bound_mm']:.3f}" if "error_bound_mm" in r else "–"
        table.append([r["mode"], eb, f"{r['step_us_median']:.1f}", f"{r['step_us_median_rest']:.1f}", ratio,
                      f"{r['rest_past_first_touch_mm']:+.4f}", f"{r['rest_coal_distance_mm']:.4f}",
                      f"{r['final_speed_mm_s']:.3f}", "not" if r["settled_s"] is None else f"{r['settled_s']:.3f}"])
    write_table(out.with_suffix(".md"), ["contacts", "ε1+ε2 mm", "step µs median", "at rest", "× faster than mesh-SDF at rest",
                                         "rest past coal's first touch mm", "coal distance at rest mm",
                                         "speed at the end mm/s", "settled s"], table)


if __name__ == "__main__":
    main()
