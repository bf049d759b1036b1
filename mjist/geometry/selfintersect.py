"""Self-intersections of a closed mesh and the winding number beside each face (numba kernels).

CBCT segmentations are closed and consistently wound but not always embedded: a thin fin's two
sides can cross, leaving an inverted sliver (winding number -1) beyond the crossing, and teeth
segmented separately overlap (winding number 2). Inside is the nonzero rule (``bvh.inside``):
every such region is enclosed by the surface, so a sphere there stays behind it and the IST
distance bound holds against the triangles.

A face that no other face touches has one winding number ``w`` all along its outer side and
``w + 1`` along its inner side (its neighbourhood on either side is connected and crossing the
face changes the number by one). A point whose closest surface point lies inside such a face is
on one of those sides (nothing lies between them), so its winding number costs no ray:
``face_sides`` computes ``w`` once per face with one ray cast from its centroid, and
``crossed_faces`` finds the faces another face touches, which keep the per-point ray cast.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .bvh import NO_SIDE, STACK, ray_winding

SHRINK = 1e-6  # faces sharing a vertex are shrunk by this fraction towards their centroids
TOL = 1e-9  # touching tolerance, a fraction of the pair's size (touching counts as crossing)


@njit(cache=True)
def _sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


@njit(cache=True)
def _cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(cache=True)
def _unit_normal(T):
    e1 = _sub(T[1], T[0])
    e2 = _sub(T[2], T[0])
    nx, ny, nz = _cross(e1[0], e1[1], e1[2], e2[0], e2[1], e2[2])
    ln = np.sqrt(nx * nx + ny * ny + nz * nz)
    if ln == 0.0:
        return 0.0, 0.0, 0.0
    return nx / ln, ny / ln, nz / ln


@njit(cache=True)
def _orient(a, b, x, nx, ny, nz):
    """Signed distance of ``x`` from the line ``a b`` within the plane of normal ``n`` (left > 0)."""
    ex, ey, ez = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    cx, cy, cz = _cross(ex, ey, ez, x[0] - a[0], x[1] - a[1], x[2] - a[2])
    le = np.sqrt(ex * ex + ey * ey + ez * ez)
    if le == 0.0:
        return 0.0
    return (cx * nx + cy * ny + cz * nz) / le


@njit(cache=True)
def _point_in_tri(x, T, nx, ny, nz, tol):
    """``x`` (in the plane of ``T``) inside ``T`` or within ``tol`` of it."""
    for i in range(3):
        if _orient(T[i], T[(i + 1) % 3], x, nx, ny, nz) < -tol:
            return False
    return True


@njit(cache=True)
def _segs_cross(a, b, c, d, nx, ny, nz, tol):
    """Segments ``a b`` and ``c d`` of one plane meet (within ``tol``; collinear: boxes overlap)."""
    o1 = _orient(a, b, c, nx, ny, nz)
    o2 = _orient(a, b, d, nx, ny, nz)
    o3 = _orient(c, d, a, nx, ny, nz)
    o4 = _orient(c, d, b, nx, ny, nz)
    if (o1 > tol and o2 > tol) or (o1 < -tol and o2 < -tol):
        return False
    if (o3 > tol and o4 > tol) or (o3 < -tol and o4 < -tol):
        return False
    for k in range(3):
        if max(a[k], b[k]) < min(c[k], d[k]) - tol or max(c[k], d[k]) < min(a[k], b[k]) - tol:
            return False
    return True


@njit(cache=True)
def _seg_in_plane_meets_tri(p, q, T, nx, ny, nz, tol):
    if _point_in_tri(p, T, nx, ny, nz, tol) or _point_in_tri(q, T, nx, ny, nz, tol):
        return True
    for i in range(3):
        if _segs_cross(p, q, T[i], T[(i + 1) % 3], nx, ny, nz, tol):
            return True
    return False


@njit(cache=True)
def _seg_meets_tri(p, q, T, nx, ny, nz, tol):
    """Segment ``p q`` touches triangle ``T`` (unit normal ``n``), within ``tol``."""
    dp = (p[0] - T[0, 0]) * nx + (p[1] - T[0, 1]) * ny + (p[2] - T[0, 2]) * nz
    dq = (q[0] - T[0, 0]) * nx + (q[1] - T[0, 1]) * ny + (q[2] - T[0, 2]) * nz
    if (dp > tol and dq > tol) or (dp < -tol and dq < -tol):
        return False
    if abs(dp) <= tol and abs(dq) <= tol:
        # the segment lies in the triangle's plane: project it there
        pp = np.empty(3)
        qq = np.empty(3)
        for k in range(3):
            pp[k] = p[k] - dp * (nx, ny, nz)[k]
            qq[k] = q[k] - dq * (nx, ny, nz)[k]
        return _seg_in_plane_meets_tri(pp, qq, T, nx, ny, nz, tol)
    t = dp / (dp - dq)
    x = np.empty(3)
    for k in range(3):
        x[k] = p[k] + t * (q[k] - p[k])
    return _point_in_tri(x, T, nx, ny, nz, tol)


@njit(cache=True)
def _sides(T, P, nx, ny, nz, tol):
    """How many vertices of ``T`` lie above / below the plane through ``P[0]`` of normal ``n``."""
    above = 0
    below = 0
    for i in range(3):
        d = (T[i, 0] - P[0, 0]) * nx + (T[i, 1] - P[0, 1]) * ny + (T[i, 2] - P[0, 2]) * nz
        above += d > tol
        below += d < -tol
    return above, below


@njit(cache=True)
def tris_touch(A, B, tol):
    """Triangles ``A, B (3, 3)`` intersect or come within ``tol`` of it.

    Separating planes first (the common case), then the six edge-triangle tests (two
    non-coplanar triangles meet iff an edge of one meets the other), or, when ``B`` lies in
    ``A``'s plane, vertex-in-triangle and edge-edge tests in that plane.
    """
    anx, any_, anz = _unit_normal(A)
    bnx, bny, bnz = _unit_normal(B)
    if (anx == 0.0 and any_ == 0.0 and anz == 0.0) or (bnx == 0.0 and bny == 0.0 and bnz == 0.0):
        return True  # degenerate triangle: no side to speak of
    above, below = _sides(B, A, anx, any_, anz, tol)
    if above == 3 or below == 3:
        return False
    if above == 0 and below == 0:
        for i in range(3):
            if _point_in_tri(B[i], A, anx, any_, anz, tol) or _point_in_tri(A[i], B, anx, any_, anz, tol):
                return True
            for j in range(3):
                if _segs_cross(A[i], A[(i + 1) % 3], B[j], B[(j + 1) % 3], anx, any_, anz, tol):
                    return True
        return False
    above, below = _sides(A, B, bnx, bny, bnz, tol)
    if above == 3 or below == 3:
        return False
    for i in range(3):
        if _seg_meets_tri(B[i], B[(i + 1) % 3], A, anx, any_, anz, tol):
            return True
        if _seg_meets_tri(A[i], A[(i + 1) % 3], B, bnx, bny, bnz, tol):
            return True
    return False


@njit(cache=True)
def _load(V, F, f, shrink, T):
    for i in range(3):
        for k in range(3):
            T[i, k] = V[F[f, i], k]
    if shrink > 0.0:
        for k in range(3):
            c = (T[0, k] + T[1, k] + T[2, k]) / 3.0
            for i in range(3):
                T[i, k] = c + (1.0 - shrink) * (T[i, k] - c)


@njit(cache=True, parallel=True)
def crossed_faces(V, F, lo, hi, left, right, start, count, order):
    """Faces that some other face touches beyond the vertices they share (bool per face).

    Faces sharing vertices are both shrunk by ``SHRINK`` towards their centroids first, so a
    shared edge or vertex alone does not count; a crossing within ``SHRINK`` of a shared vertex
    is the one thing missed. Everything else that touches within ``TOL`` counts (conservative:
    a flagged face only costs a ray per point).
    """
    nf = F.shape[0]
    out = np.zeros(nf, np.bool_)
    for f in prange(nf):
        stack = np.empty(STACK, np.int64)
        A = np.empty((3, 3))
        B = np.empty((3, 3))
        _load(V, F, f, 0.0, A)
        blo = np.empty(3)
        bhi = np.empty(3)
        for k in range(3):
            blo[k] = min(A[0, k], A[1, k], A[2, k])
            bhi[k] = max(A[0, k], A[1, k], A[2, k])
        size = max(bhi[0] - blo[0], bhi[1] - blo[1], bhi[2] - blo[2])
        pad = TOL * size
        stack[0] = 0
        sp = 1
        hit = False
        while sp > 0 and not hit:
            sp -= 1
            node = stack[sp]
            if (lo[node, 0] > bhi[0] + pad or hi[node, 0] < blo[0] - pad or lo[node, 1] > bhi[1] + pad
                    or hi[node, 1] < blo[1] - pad or lo[node, 2] > bhi[2] + pad or hi[node, 2] < blo[2] - pad):
                continue
            if left[node] >= 0:
                stack[sp] = left[node]
                stack[sp + 1] = right[node]
                sp += 2
                continue
            for i in range(start[node], start[node] + count[node]):
                g = order[i]
                if g == f:
                    continue
                shared = 0
                for a in range(3):
                    for b in range(3):
                        shared += F[f, a] == F[g, b]
                if shared >= 3:
                    hit = True  # a duplicate face
                    break
                s = SHRINK if shared > 0 else 0.0
                _load(V, F, f, s, A)
                _load(V, F, g, s, B)
                gsize = 0.0
                for k in range(3):
                    gsize = max(gsize, max(B[0, k], B[1, k], B[2, k]) - min(B[0, k], B[1, k], B[2, k]))
                if tris_touch(A, B, TOL * max(size, gsize)):
                    hit = True
                    break
        out[f] = hit
    return out


@njit(cache=True, parallel=True)
def face_sides(V, F, crossed, lo, hi, left, right, start, count, order, dirs):
    """Winding number just outside each face that nothing crosses (``NO_SIDE`` for the others).

    One ray from the face's centroid into its outer half-space, the face itself skipped,
    retried along other directions while it grazes; a face whose every ray grazes keeps
    ``NO_SIDE`` (its points are ray-cast one by one).
    """
    nf = F.shape[0]
    out = np.full(nf, NO_SIDE, np.int64)
    for f in prange(nf):
        if crossed[f]:
            continue
        stack = np.empty(STACK, np.int64)
        T = np.empty((3, 3))
        _load(V, F, f, 0.0, T)
        nx, ny, nz = _unit_normal(T)
        if nx == 0.0 and ny == 0.0 and nz == 0.0:
            continue
        c = np.empty(3)
        d = np.empty(3)
        for k in range(3):
            c[k] = (T[0, k] + T[1, k] + T[2, k]) / 3.0
        for j in range(dirs.shape[0]):
            s = dirs[j, 0] * nx + dirs[j, 1] * ny + dirs[j, 2] * nz
            if abs(s) < 0.2:
                continue  # nearly along the face: could graze its neighbours
            for k in range(3):
                d[k] = dirs[j, k] if s > 0.0 else -dirs[j, k]
            w, amb = ray_winding(c, d, V, F, lo, hi, left, right, start, count, order, stack, 1e-9, f)
            if not amb:
                out[f] = w
                break
    return out
