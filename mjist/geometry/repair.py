"""Close an open surface (a scan with holes or an open rim) into a solid, and say what was added.

An intraoral scan is the crowns and a strip of gingiva: an open surface with one long rim and
often many small holes. An Inner Sphere Tree needs an inside, so the surface is closed with
MeshFix (``pymeshfix``): every connected piece on its own (MeshFix's default keeps only the
largest piece of a mesh, which loses most of a multi-piece scan), by its hole filling (every
input face stays), by its full repair only when that leaves holes; then the closed pieces are
joined by an exact boolean union (``manifold3d``) when they overlap.

The report says what survived (vertices of the input still on the output surface) and what
was added (area, centre and extent of the faces that lie off the input surface). The tree's
certified ε holds for the closed surface; the added faces are not anatomy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..errors import MeshError

MIN_KEPT = 0.95  # fraction of the input's vertices that must stay on the closed surface


@dataclass
class Closure:
    """What closing an open surface did."""

    pieces: int  # connected pieces of the input
    kept_fraction: float  # input vertices still on the output surface
    added_area: float  # area of the faces off the input surface (mesh units squared)
    added_centre: np.ndarray
    added_extent: np.ndarray
    boundary_edges: int  # open edges of the input

    def describe(self, unit: str = "") -> str:
        u = f" {unit}" if unit else ""
        c = ", ".join(f"{a:.4g}" for a in self.added_centre)
        e = " x ".join(f"{a:.3g}" for a in self.added_extent)
        return (f"closed {self.boundary_edges} open edges in {self.pieces} piece(s) with MeshFix: added "
                f"{self.added_area:.4g}{u}² of surface around ({c}), spanning {e}{u}; kept "
                f"{100 * self.kept_fraction:.1f}% of the input vertices")


def _meshfix(piece: trimesh.Trimesh) -> trimesh.Trimesh:
    """One piece closed by MeshFix: its hole filling first (keeps every input face), its full
    repair (which also removes self-intersecting parts) only when holes remain."""
    import pymeshfix

    v, f = np.asarray(piece.vertices, np.float64), np.asarray(piece.faces, np.int32)
    fix = pymeshfix.MeshFix(v, f)
    fix.fill_holes(0, refine=True)  # 0: every hole
    out = trimesh.Trimesh(np.asarray(fix.points, np.float64), np.asarray(fix.faces, np.int64), process=False)
    if out.is_watertight:
        return out
    fix = pymeshfix.MeshFix(v, f)
    fix.repair(joincomp=False, remove_smallest_components=False)
    return trimesh.Trimesh(np.asarray(fix.points, np.float64), np.asarray(fix.faces, np.int64), process=False)


def _union(pieces: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Exact union of closed pieces whose bounding boxes overlap; others are kept as separate shells."""
    import manifold3d

    def to_manifold(m):
        return manifold3d.Manifold(manifold3d.Mesh(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)))

    def overlaps(a, b):
        return bool(np.all(a.bounds[0] <= b.bounds[1]) and np.all(b.bounds[0] <= a.bounds[1]))

    if len(pieces) == 1 or not any(overlaps(a, b) for i, a in enumerate(pieces) for b in pieces[i + 1:]):
        return trimesh.util.concatenate(pieces)
    out = manifold3d.Manifold.batch_boolean([to_manifold(p) for p in pieces], manifold3d.OpType.Add).to_mesh()
    return trimesh.Trimesh(np.asarray(out.vert_properties[:, :3], np.float64), np.asarray(out.tri_verts, np.int64))


def close_surface(tm: trimesh.Trimesh) -> tuple[trimesh.Trimesh, Closure]:
    """The open surface ``tm`` closed into a solid, with a report of what was added.

    Raises
    ------
    MeshError
        MeshFix could not close it, or the closed surface lost more than ``1 - MIN_KEPT`` of the
        input's vertices (MeshFix removes self-intersecting and degenerate parts).
    """
    from .bvh import BVH

    _, counts = np.unique(np.sort(tm.edges, axis=1), axis=0, return_counts=True)
    boundary = int((counts == 1).sum())
    pieces = tm.split(only_watertight=False)
    closed = [p if p.is_watertight else _meshfix(p) for p in pieces]
    closed = [p for p in closed if len(p.faces)]
    if not closed:
        raise MeshError("MeshFix could not close the surface (nothing left): clean the scan or close it in a mesh editor")
    out = _union(closed)
    if not out.is_watertight:
        raise MeshError("MeshFix left the surface open: close it in a mesh editor (e.g. MeshLab's hole filling)")
    scale = float(np.linalg.norm(np.ptp(tm.vertices, axis=0)))
    tol = 1e-5 * scale
    Vo, Fo = np.asarray(out.vertices, np.float64), np.asarray(out.faces, np.int64)
    kept = BVH.of_triangles(Vo, Fo).distance(np.asarray(tm.vertices, np.float64), Vo, Fo) < tol
    Vi, Fi = np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64)
    off = BVH.of_triangles(Vi, Fi).distance(out.triangles_center, Vi, Fi) > tol
    area = out.area_faces[off]
    centre = (out.triangles_center[off] * area[:, None]).sum(0) / area.sum() if off.any() else np.zeros(3)
    extent = np.ptp(out.triangles_center[off], axis=0) if off.any() else np.zeros(3)
    report = Closure(len(pieces), float(kept.mean()), float(area.sum()), centre, extent, boundary)
    if report.kept_fraction < MIN_KEPT:
        raise MeshError(
            f"closing the open surface kept only {100 * report.kept_fraction:.1f}% of its vertices (MeshFix removes "
            "self-intersecting and degenerate parts): clean the scan first (remove loose fragments and "
            "self-intersections), or close it in a mesh editor")
    return out, report
