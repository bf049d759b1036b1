"""Proof that a wafer can be printed: every edge shared by exactly two faces in opposite
directions (closed, consistently wound), one shell, positive volume, embedded (the winding
number just outside and just inside every face is 0 and 1), and the minimum thickness (between
the upper and the lower face, and the rim's wall)."""
from __future__ import annotations

import numpy as np


def printable(V, F, thickness: float, up) -> dict:
    """Closed, one shell, positive volume, embedded (no face crossing another); its minimum
    thickness between its upper and lower faces (m in, mm out)."""
    import trimesh

    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    m = trimesh.Trimesh(V, F, process=False)
    edges = np.sort(m.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    closed = bool(np.all(counts == 2)) and bool(m.is_winding_consistent)
    shells = len(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(F)), min_len=1))
    winding = embedded(V, F)
    faces, rim = min_thickness(V, F, up)
    t = min(faces, rim)
    ok = closed and shells == 1 and m.volume > 0 and winding["ok"] and t >= thickness * (1 - 1e-9)
    return {"watertight": closed, "shells": shells, "volume_mm3": float(m.volume) * 1e9, "winding": winding,
            "min_thickness_mm": t * 1e3, "between_faces_mm": faces * 1e3, "rim_height_mm": rim * 1e3,
            "vertices": len(V), "faces": len(F), "ok": ok}


FACING = 0.3  # a face whose normal is within acos(0.3) = 72.5° of up (down) is on the upper (lower) face
WINDING_TOL = 0.05  # a winding number within this of 0 or 1 is that number


def min_thickness(V, F, up) -> tuple[float, float]:
    """The wafer's minimum thickness (m): the least distance between its upper face (faces turned
    up by more than ``FACING``) and its lower face (turned down), from every vertex of each to
    the other's triangles; and the least height of its rim, the vertical wall around it (both
    faces reach the wall: at the wall they are the wall's height apart)."""
    from ...geometry.bvh import BVH

    u = np.asarray(up, float) / np.linalg.norm(up)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    c = (n @ u) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    wall = np.abs(c) < 1e-6
    on_wall = np.zeros(len(V), bool)
    on_wall[F[wall].ravel()] = True
    faces = np.inf
    for a, b in ((c > FACING, c < -FACING), (c < -FACING, c > FACING)):
        Fb = np.ascontiguousarray(F[b])
        src = np.unique(F[a])
        src = src[~on_wall[src]]
        if len(src) == 0 or len(Fb) == 0:
            return 0.0, 0.0
        faces = min(faces, float(BVH.of_triangles(V, Fb).distance(np.ascontiguousarray(V[src]), V, Fb).min()))
    rim = np.inf
    if on_wall.any():  # the wall's columns: its vertices that share a place across up
        W = np.flatnonzero(on_wall)
        flat = V[W] - np.outer(V[W] @ u, u)
        _, col = np.unique(np.round(flat * 1e9).astype(np.int64), axis=0, return_inverse=True)
        h = V[W] @ u
        top = np.full(col.max() + 1, -np.inf)
        bot = np.full(col.max() + 1, np.inf)
        np.maximum.at(top, col, h)
        np.minimum.at(bot, col, h)
        rim = float((top - bot).min())
    return faces, rim


def embedded(V, F, offset: float = 1e-6) -> dict:
    """Whether the closed surface crosses itself: the generalized winding number (libigl's fast
    winding number) just outside and just inside every face must be 0 and 1. Where the surface
    crosses itself, points beside the crossing faces lie inside another part (2) or behind an
    inverted one (-1)."""
    import igl

    T = V[F]
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    c = T.mean(axis=1)
    P = np.ascontiguousarray(np.vstack([c + offset * n, c - offset * n]))
    w = igl.fast_winding_number(np.ascontiguousarray(V), np.ascontiguousarray(F), P)
    out, inn = w[:len(F)], w[len(F):]
    bad = (np.abs(out) > WINDING_TOL) | (np.abs(inn - 1.0) > WINDING_TOL)
    return {"faces_not_0_1": int(bad.sum()), "outside_max": float(np.abs(out).max()),
            "inside_range": [float(inn.min()), float(inn.max())], "ok": not bad.any()}
