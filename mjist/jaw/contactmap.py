"""Occlusal contact map: where the teeth touch and how close the rest is, like articulating paper.

For each arch, every vertex facing the other arch gets the IST's interval for its clearance
to the other jaw (distance to the solid, 0 where the vertex penetrates it). The other jaw's
inner spheres lie inside it, so the distance ``d`` to their union bounds the clearance from
above everywhere: ``clearance ≤ max(d, 0)`` (a vertex drawn as touching touches). Every point
of its surface is within ``ε`` of a sphere, so for a vertex outside the other jaw
``clearance ≥ d - ε``; a vertex inside it has clearance 0, which the lower bound does not
see (it can read up to ``ε`` minus the depth). The estimate shown is ``d`` minus the tree's mean surface
gap (the spheres sit that far inside the surface on average), clipped to the interval.
Exact distances (coal, signed by the ray-cast winding number) on a sample of vertices check the
interval in every map.

Colours follow articulating paper: below 0.05 mm (contact), 0.1, 0.2 and 0.4 mm; further is
the tooth's own colour.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

BANDS = (5e-5, 1e-4, 2e-4, 4e-4)  # m: the colour scale's upper edges
COLOURS = np.array([[0.75, 0.05, 0.10], [0.95, 0.35, 0.10], [0.98, 0.80, 0.15], [0.35, 0.75, 0.35], [0.90, 0.88, 0.82]])
LABELS = ("< 0.05 mm", "< 0.1 mm", "< 0.2 mm", "< 0.4 mm", "further")
CONTACT = 1e-4  # m: a vertex this close (estimate) counts towards the region's contact area
REACH = 2e-3  # m: vertices further than this from the other jaw's bounding box are not measured


@dataclass
class ArchMap:
    """One arch's map (world coordinates at the mapped pose)."""

    name: str
    vertices: np.ndarray  # (n, 3) every vertex of the arch
    faces: np.ndarray
    lower: np.ndarray  # (n,) certified interval of the distance to the other jaw (m); inf: not measured
    upper: np.ndarray
    estimate: np.ndarray
    facing: np.ndarray  # (n,) bool: the vertex faces the other arch
    regions: list = field(default_factory=list)  # per-region table rows
    check: dict = field(default_factory=dict)  # the sampled exact distances against the interval


def _vertex_areas(V, F) -> np.ndarray:
    a = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    out = np.zeros(len(V))
    for k in range(3):
        np.add.at(out, F[:, k], a / 3.0)
    return out


def _ist_distances(tree, P_other, points_world) -> np.ndarray:
    from ..query.primitive import points_distance
    from ..query.traverse import pack, stack_size

    N = pack(tree)
    T = np.linalg.inv(P_other)
    P = np.ascontiguousarray(points_world @ T[:3, :3].T + T[:3, 3])
    out = np.empty(len(P))
    xf = np.array([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0])
    points_distance(N, P, xf, np.zeros(stack_size(N), np.int64), np.zeros(3), out)
    return out


def _exact(V_other, F_other, points) -> np.ndarray:
    """Exact signed distance to the other jaw's surface (negative inside): coal's distance from
    each point to the triangles, the sign from the ray-cast winding number (``BVH.contains``,
    which grazing rays retry; trimesh's ray-based ``contains`` is two orders of magnitude slower
    on a 100 k-face jaw)."""
    import coal

    from ..geometry.bvh import BVH
    from .exact import coal_bvh

    bvh = coal_bvh(V_other, F_other)
    dot, I, req = coal.Sphere(1e-12), coal.Transform3s(), coal.DistanceRequest()
    dist = np.array([coal.distance(dot, coal.Transform3s(np.eye(3), np.asarray(p, float)), bvh, I, req, coal.DistanceResult())
                     for p in points])
    inside = BVH.of_triangles(V_other, F_other).contains(points, V_other, F_other)
    return np.where(inside, -np.abs(dist), np.abs(dist))


def _arch_map(name, V, F, normals, up_dir, tree, P_other, V_other, F_other, frame, eps, gap, sample, rng) -> ArchMap:
    n = len(V)
    lower, upper, est = (np.full(n, np.inf) for _ in range(3))
    lo, hi = V_other.min(axis=0) - REACH, V_other.max(axis=0) + REACH
    facing = (normals @ up_dir > 0.0) & ((V >= lo) & (V <= hi)).all(axis=1)
    idx = np.flatnonzero(facing)
    if idx.size:
        d = _ist_distances(tree, P_other, V[idx])
        upper[idx] = np.maximum(d, 0.0)
        lower[idx] = np.maximum(d - eps, 0.0)
        est[idx] = np.clip(d - gap, lower[idx], upper[idx])
    check = {}
    near = idx[upper[idx] < 1e-3] if idx.size else idx
    if near.size:
        pick = np.sort(rng.choice(near, min(sample, near.size), replace=False))
        s = _exact(V_other, F_other, V[pick])
        ex = np.maximum(s, 0.0)  # clearance
        above = ex > upper[pick] + 1e-9  # certified everywhere
        below = (s > 0.0) & (ex < lower[pick] - 1e-9)  # certified where the vertex does not penetrate
        check = {"sampled": int(pick.size), "penetrating": int((s <= 0.0).sum()), "above_upper": int(above.sum()),
                 "below_lower_outside": int(below.sum()),
                 "max_error_of_estimate_mm": float(np.max(np.abs(ex - est[pick])) * 1e3),
                 "median_error_of_estimate_mm": float(np.median(np.abs(ex - est[pick])) * 1e3)}
    area = _vertex_areas(V, F)
    regions = []
    names = frame.regions(V[idx]) if idx.size else []
    for r in sorted(set(names)):
        sel = idx[np.array([x == r for x in names])]
        regions.append({"region": r, "contact_area_mm2": float(area[sel][est[sel] <= CONTACT].sum() * 1e6),
                        "certain_contact_area_mm2": float(area[sel][upper[sel] <= CONTACT].sum() * 1e6),
                        "closest_mm": float(est[sel].min() * 1e3),
                        "closest_interval_mm": [float(lower[sel].min() * 1e3), float(upper[sel].min() * 1e3)]})
    return ArchMap(name, V, F, lower, upper, est, facing, regions, check)


def contact_map(model, handle, pos, quat, *, sample: int = 200, seed: int = 0, frames: dict | None = None) -> dict:
    """The contact map of an occlusion-search scene's jaws with the mandible body at ``pos``, ``quat``.

    ``frames``: the arches' frames (``scenepair.arch_frames``) when the caller has them.

    Returns ``{"maxilla": ArchMap, "mandible": ArchMap, "error_bound_mm": {...}}``.
    """
    import trimesh

    from ..mujoco.scene import geom_pose, geom_pose_at, mesh_of
    from .scenepair import UP, arch_frames

    gmx, gmd = handle.geoms["maxilla"], handle.geoms["mandible"]
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    poses = {"maxilla": geom_pose(d, gmx), "mandible": geom_pose_at(model, gmd, pos, quat)}
    world = {}
    for name, g in (("maxilla", gmx), ("mandible", gmd)):
        V, F = mesh_of(model, g)
        P = poses[name]
        Vw = V @ P[:3, :3].T + P[:3, 3]
        world[name] = (Vw, F, trimesh.Trimesh(Vw, F, process=False).vertex_normals)
    frames = arch_frames(model, gmx, gmd) if frames is None else frames
    rng = np.random.default_rng(seed)
    out = {}
    for name, other, up_dir in (("maxilla", "mandible", -UP), ("mandible", "maxilla", UP)):
        V, F, N = world[name]
        tree = handle.trees[other]
        eps = float(tree.error_bound)
        gap = float(tree.info.get("mean_gap", 0.0))
        out[name] = _arch_map(name, V, F, N, up_dir, tree, poses[other], world[other][0], world[other][1],
                              frames[name], eps, gap, sample, rng)
    out["error_bound_mm"] = {k: float(handle.trees[k].error_bound * 1e3) for k in ("maxilla", "mandible")}
    return out


def colours(est) -> np.ndarray:
    """Articulating-paper colour (RGB, 0-1) of each distance estimate."""
    band = np.searchsorted(np.asarray(BANDS), np.asarray(est), side="right")
    return COLOURS[np.minimum(band, len(COLOURS) - 1)]


def write(cmap: dict, frames: dict, out_dir) -> list[str]:
    """``contact_map_<arch>.png`` (occlusal view), ``contact_map_<arch>.ply`` (per-vertex colour and
    distances, mm) and ``contact_map.json`` (region tables, checks) in ``out_dir``."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh
    from matplotlib.collections import PolyCollection
    from matplotlib.patches import Patch

    out = Path(out_dir)
    os.makedirs(out, exist_ok=True)
    written = []
    for name in ("maxilla", "mandible"):
        m: ArchMap = cmap[name]
        rgb = colours(m.estimate)
        tm = trimesh.Trimesh(m.vertices, m.faces, vertex_colors=np.c_[(rgb * 255).astype(np.uint8), np.full(len(rgb), 255, np.uint8)],
                             process=False)
        for key, arr in (("distance_mm", m.estimate), ("lower_mm", m.lower), ("upper_mm", m.upper)):
            tm.vertex_attributes[key] = np.where(np.isfinite(arr), arr * 1e3, -1.0).astype(np.float32)
        ply = out / f"contact_map_{name}.ply"
        tm.export(ply, include_attributes=True)
        written.append(str(ply))
        fr = frames[name]
        L = fr.local(m.vertices)  # lateral, height, behind-the-front
        F = m.faces[m.facing[m.faces].all(axis=1)]
        order = np.argsort(L[F].mean(axis=1)[:, 1] * (1 if name == "mandible" else -1))  # nearest the viewer last
        F = F[order]
        polys = np.stack([L[F][:, :, 0], -L[F][:, :, 2]], axis=-1) * 1e3
        face_rgb = colours(m.estimate[F].min(axis=1))
        fig, ax = plt.subplots(figsize=(6.5, 6))
        ax.add_collection(PolyCollection(polys, facecolors=face_rgb, edgecolors="none"))
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_xlabel("patient's left (mm) from the midline")
        ax.set_ylabel("anterior (mm) from the front of the arch")
        ax.set_title(f"{name}: occlusal contact map (ε of the other jaw {cmap['error_bound_mm']['mandible' if name == 'maxilla' else 'maxilla']:.2f} mm)")
        ax.legend(handles=[Patch(color=c, label=lab) for c, lab in zip(COLOURS, LABELS)], loc="lower center", fontsize=8, ncol=3)
        fig.tight_layout()
        png = out / f"contact_map_{name}.png"
        fig.savefig(png, dpi=110)
        plt.close(fig)
        written.append(str(png))
    summary = {"error_bound_mm": cmap["error_bound_mm"], "bands_mm": [b * 1e3 for b in BANDS],
               **{name: {"regions": cmap[name].regions, "check": cmap[name].check} for name in ("maxilla", "mandible")}}
    (out / "contact_map.json").write_text(json.dumps(summary, indent=1))
    written.append(str(out / "contact_map.json"))
    return written
