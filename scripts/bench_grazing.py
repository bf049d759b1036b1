"""Grazing contacts: surface contacts against coal at poses around the bundled occlusion.

    python scripts/bench_grazing.py                    # 2 x 112 poses, 8/16/32 measured groups
    python scripts/bench_grazing.py --groups 8 --poses 40

The bundled jaw-closure scene (default trees, ``mjist_narrowphase="surface"``), the mandible set
at random poses near its designed occlusion (hinge -0.3..+0.6°, protrusion and lateral ±0.3 mm;
seeds 1 and 2, the poses of ``tests/mujoco/test_surface_contacts.py``), one ``mj_forward`` each
on a fresh ``MjData`` (a first touch: no contacts held from the pose before).
Where coal finds the meshes colliding, a pose without a contact is a miss. The reference depth is
the deepest vertex of either mesh inside the other (exact point-to-triangle distances, the
deepest checked against coal's point distance): a lower bound of the true penetration, so
"deepest vertex − deepest contact" > 0 is depth the contacts did not report (< 0: the contact is
deeper than any vertex, between vertices). Per ``mjist_surface_groups``: misses, their vertex
depths, that depth error's median / 90th percentile / max, and the median ``mj_forward`` time.
Writes ``OUT/bench_grazing.{json,md}``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))
from benchlib import write_table  # noqa: E402

from mjist.geometry import surface as sf  # noqa: E402
from mjist.jaw import BUNDLED  # noqa: E402
from mjist.jaw import pair as jawmod  # noqa: E402
from mjist.mujoco import attach as A  # noqa: E402
from mjist.mujoco.scene import geom_pose, mesh_of  # noqa: E402


def _point_distance(bvh, pose, x):
    import coal

    tf = coal.Transform3s()
    tf.setTranslation(pose[:3, :3].T @ (np.asarray(x, float) - pose[:3, 3]))
    return coal.distance(bvh, coal.Transform3s(), coal.Sphere(1e-12), tf, coal.DistanceRequest(),
                         coal.DistanceResult()) + 1e-12


def run(groups: int, poses: int, seeds=(1, 2)) -> dict:
    model, h = A.load_model(BUNDLED / "jaw_closure.xml", narrowphase="surface", surface_groups=groups)
    try:
        gmx, gmd = h.geoms["maxilla"], h.geoms["mandible"]
        mesh = {g: mesh_of(model, g) for g in (gmx, gmd)}
        surf = {g: sf.build_surface(*mesh[g]) for g in (gmx, gmd)}
        bvh = {g: jawmod.coal_bvh(*mesh[g]) for g in (gmx, gmd)}
        d = mujoco.MjData(model)
        occ = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "occlusion")
        rows, times = [], []
        for seed in seeds:
            rng = np.random.default_rng(seed)
            for _ in range(poses):
                d = mujoco.MjData(model)  # each pose a first touch: no contacts held from the last one
                h.forget(d)  # (a freed MjData's slot, at the same address and time, would carry them over)
                mujoco.mj_resetDataKeyframe(model, d, occ)
                d.qpos[:3] += [np.radians(rng.uniform(-0.3, 0.6)), rng.uniform(-3e-4, 3e-4), rng.uniform(-3e-4, 3e-4)]
                t = time.perf_counter()
                mujoco.mj_forward(model, d)
                times.append(time.perf_counter() - t)
                P = {gmx: geom_pose(d, gmx), gmd: geom_pose(d, gmd)}
                if not jawmod.coal_collides(bvh[gmx], P[gmx], bvh[gmd], P[gmd]):
                    continue
                deepest = 0.0
                for on, into in ((gmd, gmx), (gmx, gmd)):
                    # the vertices of `on` in the frame of `into`
                    R = P[into][:3, :3].T @ P[on][:3, :3]
                    t_ = P[into][:3, :3].T @ (P[on][:3, 3] - P[into][:3, 3])
                    dist, _ = sf.signed_distances(surf[into], mesh[on][0] @ R.T + t_)
                    i = int(np.argmin(dist))
                    if -dist[i] > deepest:
                        w = mesh[on][0][i] @ P[on][:3, :3].T + P[on][:3, 3]
                        assert abs(_point_distance(bvh[into], P[into], w) + dist[i]) < 1e-9  # coal agrees
                        deepest = -float(dist[i])
                cons = [-c.dist for c in d.contact[:d.ncon] if {int(c.geom1), int(c.geom2)} == {gmx, gmd}]
                rows.append((deepest, max(cons) if cons else np.nan))
        stats = h.stats()
    finally:
        h.detach()
    r = np.array(rows)
    miss = np.isnan(r[:, 1])
    err = (r[~miss, 0] - r[~miss, 1]) * 1e3
    return {"groups": groups, "poses": poses * len(seeds), "colliding": int(len(r)), "missed": int(miss.sum()),
            "missed_vertex_depths_mm": [round(float(x) * 1e3, 4) for x in r[miss, 0]],
            "depth_error_mm_median": float(np.median(err)), "depth_error_mm_p90": float(np.percentile(err, 90)),
            "depth_error_mm_max": float(err.max()), "forward_us_median": float(np.median(times) * 1e6),
            "failed": int(stats["failed"])}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--groups", default="8,16,32", help="mjist_surface_groups values")
    ap.add_argument("--poses", type=int, default=112, help="poses per seed (seeds 1 and 2)")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_grazing"))
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = []
    for g in [int(x) for x in a.groups.split(",")]:
        r = run(g, a.poses)
        res.append(r)
        print(f"groups {g:3d}: {r['colliding']} colliding, {r['missed']} missed {r['missed_vertex_depths_mm']}, "
              f"depth error median {r['depth_error_mm_median']:.4f} p90 {r['depth_error_mm_p90']:.4f} "
              f"max {r['depth_error_mm_max']:.4f} mm, mj_forward {r['forward_us_median']:.0f} µs", flush=True)
    (out / "bench_grazing.json").write_text(json.dumps(res, indent=1))
    write_table(out / "bench_grazing.md",
                ["measured groups", "colliding poses", "missed", "missed: deepest vertex mm",
                 "deepest vertex − deepest contact mm (median / p90 / max)", "mj_forward µs median"],
                [[r["groups"], r["colliding"], r["missed"], ", ".join(f"{x:.4f}" for x in r["missed_vertex_depths_mm"]) or "–",
                  f"{r['depth_error_mm_median']:.4f} / {r['depth_error_mm_p90']:.4f} / {r['depth_error_mm_max']:.4f}",
                  f"{r['forward_us_median']:.0f}"] for r in res])


if __name__ == "__main__":
    main()
