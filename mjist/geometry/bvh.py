"""Bounding volume hierarchies over triangles and spheres (numba kernels).

Used at build time only: the voxelizer asks the triangle BVH for closest points and
ray-cast winding-number inside tests, the packer and the error certificate ask the sphere BVH for
the distance to the union of spheres.

Layout (structure of arrays, node 0 is the root):
``lo, hi (m, 3)`` node boxes, ``left, right (m,)`` child node ids (-1 for leaves),
``start, count (m,)`` leaf ranges into ``order`` (the primitive permutation).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import get_num_threads, njit, prange

LEAF_SIZE = 4
STACK = 128  # depth bound: median splits give depth ~log2(n/LEAF_SIZE) < 40
NO_SIDE = -(1 << 40)  # a face whose sides need a ray per point (selfintersect.face_sides)


@njit(cache=True)
def _select(order, cen, axis, a, b, k):
    """Reorder ``order[a:b]`` so that ``order[k]`` has rank ``k - a`` by ``cen[:, axis]``, the
    smaller keys before it and the larger after (Wirth's quickselect, median-of-three pivot:
    linear time per node where a sort is n log n, deterministic)."""
    lo = a
    hi = b - 1
    while hi > lo:
        x0 = cen[order[lo], axis]
        x1 = cen[order[(lo + hi) >> 1], axis]
        x2 = cen[order[hi], axis]
        pivot = max(min(x0, x1), min(max(x0, x1), x2))
        i = lo
        j = hi
        while i <= j:
            while cen[order[i], axis] < pivot:
                i += 1
            while cen[order[j], axis] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break


@njit(cache=True)
def _split(prim_lo, prim_hi, cen, order, lo, hi, start, count, node, a, b):
    """Box of ``node`` over ``order[a:b]``; a leaf (returns -1) or split at the median of its
    centres' widest axis (``order[a:b]`` partitioned, returns the split index)."""
    for k in range(3):
        lo[node, k] = np.inf
        hi[node, k] = -np.inf
    c0 = c1 = c2 = np.inf
    d0 = d1 = d2 = -np.inf
    for i in range(a, b):
        j = order[i]
        for k in range(3):
            lo[node, k] = min(lo[node, k], prim_lo[j, k])
            hi[node, k] = max(hi[node, k], prim_hi[j, k])
        c0, d0 = min(c0, cen[j, 0]), max(d0, cen[j, 0])
        c1, d1 = min(c1, cen[j, 1]), max(d1, cen[j, 1])
        c2, d2 = min(c2, cen[j, 2]), max(d2, cen[j, 2])
    if b - a <= LEAF_SIZE:
        start[node] = a
        count[node] = b - a
        return -1
    axis = 0
    if d1 - c1 > d0 - c0:
        axis = 1
    if d2 - c2 > max(d0 - c0, d1 - c1):
        axis = 2
    mid = (a + b) // 2
    _select(order, cen, axis, a, b, mid)
    return mid


@njit(cache=True)
def _build_subtree(prim_lo, prim_hi, cen, order, lo, hi, left, right, start, count, node, a, b, m):
    """The subtree of ``node`` over ``order[a:b]``, depth first, its new nodes numbered from ``m``
    (children ``m, m + 1``; the right one is built first, so its descendants come next)."""
    st_node = np.empty(STACK, np.int64)
    st_a = np.empty(STACK, np.int64)
    st_b = np.empty(STACK, np.int64)
    st_node[0] = node
    st_a[0] = a
    st_b[0] = b
    sp = 1
    while sp > 0:
        sp -= 1
        node = st_node[sp]
        a = st_a[sp]
        b = st_b[sp]
        mid = _split(prim_lo, prim_hi, cen, order, lo, hi, start, count, node, a, b)
        if mid < 0:
            continue
        left[node] = m
        right[node] = m + 1
        st_node[sp] = m
        st_a[sp] = a
        st_b[sp] = mid
        st_node[sp + 1] = m + 1
        st_a[sp + 1] = mid
        st_b[sp + 1] = b
        sp += 2
        m += 2


@njit(cache=True, parallel=True)
def _split_many(prim_lo, prim_hi, cen, order, lo, hi, start, count, tn, ta, tb):
    mids = np.empty(tn.shape[0], np.int64)
    for t in prange(tn.shape[0]):
        mids[t] = _split(prim_lo, prim_hi, cen, order, lo, hi, start, count, tn[t], ta[t], tb[t])
    return mids


@njit(cache=True, parallel=True)
def _build_many(prim_lo, prim_hi, cen, order, lo, hi, left, right, start, count, tn, ta, tb, tm):
    for t in prange(tn.shape[0]):
        _build_subtree(prim_lo, prim_hi, cen, order, lo, hi, left, right, start, count, tn[t], ta[t], tb[t], tm[t])


@lru_cache(maxsize=None)
def _leaves(c: int) -> int:
    """Leaves of the median-split subtree over ``c`` primitives (its shape depends on c only)."""
    return 1 if c <= LEAF_SIZE else _leaves(c // 2) + _leaves(c - c // 2)


PARALLEL_MIN = 50_000  # primitives per subtree worth a task of its own


def build_bvh(prim_lo, prim_hi):
    """Median-split BVH over axis-aligned boxes ``prim_lo, prim_hi (n, 3)``.

    Node ids are those of a depth-first build (children ``m, m + 1`` of a node, the right
    subtree numbered first). Every subtree's shape, hence its id range, depends only on its
    primitive count, so the top nodes are split level by level and the subtrees below them
    built at once, one thread each: the same arrays as one thread builds, ~2x faster on 2 cores.
    """
    n = prim_lo.shape[0]
    m_max = max(1, 2 * n)
    lo = np.empty((m_max, 3))
    hi = np.empty((m_max, 3))
    left = np.full(m_max, -1, np.int64)
    right = np.full(m_max, -1, np.int64)
    start = np.zeros(m_max, np.int64)
    count = np.zeros(m_max, np.int64)
    order = np.arange(n)
    cen = 0.5 * (prim_lo + prim_hi)
    args = (prim_lo, prim_hi, cen, order, lo, hi)
    tasks = [(0, 0, n, 1)]  # (node, a, b, first free id when it is built)
    while len(tasks) < 4 * get_num_threads() and tasks[0][2] - tasks[0][1] >= 2 * PARALLEL_MIN:
        tn, ta, tb, tm = (np.array(col, np.int64) for col in zip(*tasks))
        mids = _split_many(*args, start, count, tn, ta, tb)
        nxt = []
        for (node, a, b, m), mid in zip(tasks, mids):
            if mid < 0:
                continue
            left[node], right[node] = m, m + 1
            nxt.append((m, a, mid, m + 2 + 2 * _leaves(b - mid) - 2))  # after the right subtree
            nxt.append((m + 1, mid, b, m + 2))
        tasks = nxt
    if tasks:
        tn, ta, tb, tm = (np.array(col, np.int64) for col in zip(*tasks))
        _build_many(*args, left, right, start, count, tn, ta, tb, tm)
    m = 2 * _leaves(n) - 1
    return lo[:m].copy(), hi[:m].copy(), left[:m].copy(), right[:m].copy(), start[:m].copy(), count[:m].copy(), order


@njit(cache=True)
def box_dist2(p0, p1, p2, lo, hi, node):
    d2 = 0.0
    v = lo[node, 0] - p0
    if v > 0:
        d2 += v * v
    else:
        v = p0 - hi[node, 0]
        if v > 0:
            d2 += v * v
    v = lo[node, 1] - p1
    if v > 0:
        d2 += v * v
    else:
        v = p1 - hi[node, 1]
        if v > 0:
            d2 += v * v
    v = lo[node, 2] - p2
    if v > 0:
        d2 += v * v
    else:
        v = p2 - hi[node, 2]
        if v > 0:
            d2 += v * v
    return d2


@njit(cache=True)
def _dot(ax, ay, az, bx, by, bz):
    return ax * bx + ay * by + az * bz


@njit(cache=True)
def ball_gap(px, py, pz, C, R, j):
    """Signed distance from a point to sphere ``j`` (negative inside it)."""
    return np.sqrt((px - C[j, 0]) ** 2 + (py - C[j, 1]) ** 2 + (pz - C[j, 2]) ** 2) - R[j]


@njit(cache=True)
def face_normal(V, F, f):
    """Outward normal ``(b - a) x (c - a)`` of triangle ``f`` (not normalized)."""
    a = F[f, 0]
    e1x, e1y, e1z = V[F[f, 1], 0] - V[a, 0], V[F[f, 1], 1] - V[a, 1], V[F[f, 1], 2] - V[a, 2]
    e2x, e2y, e2z = V[F[f, 2], 0] - V[a, 0], V[F[f, 2], 1] - V[a, 1], V[F[f, 2], 2] - V[a, 2]
    return e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x


# the feature of a triangle a closest point lies on (``closest_on_triangle``)
VERT_A, VERT_B, VERT_C, EDGE_AB, EDGE_AC, EDGE_BC, FACE, INTERIOR = range(8)


@njit(cache=True)
def closest_on_triangle(px, py, pz, V, i0, i1, i2):
    """Closest point to p on triangle (V[i0], V[i1], V[i2]) (Ericson, RTCD 5.1.5), scalar form.

    Returns ``(x, y, z, feature)``: the vertex (``VERT_A..C``), edge (``EDGE_AB, EDGE_AC,
    EDGE_BC``) or face it lies on. ``INTERIOR`` is a face point at least 1e-9 (barycentric) from
    the edges, where ``p - q`` is along the face normal and rounding cannot have picked the
    wrong feature; ``FACE`` a face point closer to an edge than that.
    """
    return closest_on_triangle_xyz(px, py, pz, V[i0, 0], V[i0, 1], V[i0, 2], V[i1, 0], V[i1, 1], V[i1, 2],
                                  V[i2, 0], V[i2, 1], V[i2, 2])


@njit(cache=True)
def _closest_on_segment(px, py, pz, ax, ay, az, bx, by, bz):
    """Closest point of segment ``ab`` to ``p`` and its parameter along it (0 at ``a``)."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    uu = ux * ux + uy * uy + uz * uz
    t = ((px - ax) * ux + (py - ay) * uy + (pz - az) * uz) / uu if uu > 0.0 else 0.0
    t = min(max(t, 0.0), 1.0)
    return ax + t * ux, ay + t * uy, az + t * uz, t


@njit(cache=True)
def _closest_on_sliver(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """``closest_on_triangle_xyz`` of a zero-area triangle: the nearest of its three edges (a
    degenerate face in a mesh that closing or a conversion left must not divide by zero)."""
    x, y, z, t = _closest_on_segment(px, py, pz, ax, ay, az, bx, by, bz)
    best = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
    qx, qy, qz = x, y, z
    feature = VERT_A if t <= 0.0 else (VERT_B if t >= 1.0 else EDGE_AB)
    x, y, z, t = _closest_on_segment(px, py, pz, ax, ay, az, cx, cy, cz)
    d = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
    if d < best:
        best, qx, qy, qz = d, x, y, z
        feature = VERT_A if t <= 0.0 else (VERT_C if t >= 1.0 else EDGE_AC)
    x, y, z, t = _closest_on_segment(px, py, pz, bx, by, bz, cx, cy, cz)
    d = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
    if d < best:
        qx, qy, qz = x, y, z
        feature = VERT_B if t <= 0.0 else (VERT_C if t >= 1.0 else EDGE_BC)
    return qx, qy, qz, feature


@njit(cache=True)
def closest_on_triangle_xyz(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """``closest_on_triangle`` of the triangle with corners ``a, b, c`` given as floats."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = _dot(abx, aby, abz, apx, apy, apz)
    d2 = _dot(acx, acy, acz, apx, apy, apz)
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, VERT_A
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = _dot(abx, aby, abz, bpx, bpy, bpz)
    d4 = _dot(acx, acy, acz, bpx, bpy, bpz)
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, VERT_B
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3) if d1 - d3 > 0.0 else 0.0  # zero: a and b coincide
        return ax + v * abx, ay + v * aby, az + v * abz, EDGE_AB
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = _dot(abx, aby, abz, cpx, cpy, cpz)
    d6 = _dot(acx, acy, acz, cpx, cpy, cpz)
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, VERT_C
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6) if d2 - d6 > 0.0 else 0.0
        return ax + w * acx, ay + w * acy, az + w * acz, EDGE_AC
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        e = (d4 - d3) + (d5 - d6)
        w = (d4 - d3) / e if e > 0.0 else 0.0
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), EDGE_BC
    if va + vb + vc <= 0.0:  # a zero-area triangle (its corners on a line) the tests above did not place
        return _closest_on_sliver(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    feature = INTERIOR if v > 1e-9 and w > 1e-9 and v + w < 1.0 - 1e-9 else FACE
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, feature


@njit(cache=True)
def tri_closest(p, V, F, lo, hi, left, right, start, count, order, stack, best=np.inf):
    """Squared distance from ``p`` to the mesh, the closest point (x, y, z), its triangle and
    the triangle's feature it lies on (see ``closest_on_triangle``).

    ``best`` is an initial squared bound: when nothing is closer it is returned unchanged,
    with triangle -1.
    """
    qx = qy = qz = 0.0
    bf = -1
    feature = INTERIOR
    px, py, pz = p[0], p[1], p[2]
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if box_dist2(px, py, pz, lo, hi, node) >= best:
            continue
        if left[node] < 0:
            for i in range(start[node], start[node] + count[node]):
                f = order[i]
                x, y, z, feat = closest_on_triangle(px, py, pz, V, F[f, 0], F[f, 1], F[f, 2])
                d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
                if d2 < best:
                    best = d2
                    qx, qy, qz = x, y, z
                    bf = f
                    feature = feat
            continue
        l = left[node]
        r = right[node]
        dl = box_dist2(px, py, pz, lo, hi, l)
        dr = box_dist2(px, py, pz, lo, hi, r)
        # push the farther child first so the nearer one is popped next
        if dl < dr:
            stack[sp] = r
            stack[sp + 1] = l
        else:
            stack[sp] = l
            stack[sp + 1] = r
        sp += 2
    return best, qx, qy, qz, bf, feature


# Ray directions for inside tests: generic (no two components equal, irrational-looking)
# so axis-aligned meshes are never hit exactly along an edge; the next one is used when a
# ray grazes an edge or vertex.
RAY_DIRS = np.array(
    [
        [0.5773502, 0.5773913, 0.5773094],
        [-0.3129583, 0.8021761, 0.5084637],
        [0.7071234, -0.2983417, 0.6409611],
        [-0.6015492, -0.5224315, 0.6044712],
        [0.1357911, 0.2468024, -0.9594929],
        [-0.8801234, 0.3217865, -0.3491273],
        [0.4203981, -0.8812355, -0.2160357],
    ]
)
for _k in range(RAY_DIRS.shape[0]):
    RAY_DIRS[_k] /= np.linalg.norm(RAY_DIRS[_k])


@njit(cache=True)
def _ray_box(o, inv, lo, hi, node):
    tmin = 0.0
    tmax = np.inf
    for k in range(3):
        t1 = (lo[node, k] - o[k]) * inv[k]
        t2 = (hi[node, k] - o[k]) * inv[k]
        if t1 > t2:
            t1, t2 = t2, t1
        tmin = max(tmin, t1)
        tmax = min(tmax, t2)
    return tmin <= tmax


@njit(cache=True)
def _ray_triangle(ox, oy, oz, dx, dy, dz, V, F, f):
    """``ray_triangle_xyz`` for face ``f`` of ``V``, ``F``."""
    a, b, c = F[f, 0], F[f, 1], F[f, 2]
    return ray_triangle_xyz(ox, oy, oz, dx, dy, dz, V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1], V[b, 2],
                            V[c, 0], V[c, 1], V[c, 2])


@njit(cache=True)
def ray_triangle_xyz(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Möller–Trumbore terms of the ray ``o + t d`` and the triangle ``a, b, c``: the
    determinant (0 or tiny: the ray runs along the triangle's plane), the barycentric ``u``,
    ``v``, the ray parameter ``t`` (meaningless when the determinant is 0) and the lengths of
    the edges ab, ac."""
    e1x, e1y, e1z = bx - ax, by - ay, bz - az
    e2x, e2y, e2z = cx - ax, cy - ay, cz - az
    # pv = d x e2
    pvx = dy * e2z - dz * e2y
    pvy = dz * e2x - dx * e2z
    pvz = dx * e2y - dy * e2x
    det = e1x * pvx + e1y * pvy + e1z * pvz
    l1 = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    l2 = np.sqrt(e2x * e2x + e2y * e2y + e2z * e2z)
    if det == 0.0:
        return det, 0.0, 0.0, 0.0, l1, l2
    inv_det = 1.0 / det
    tx, ty, tz = ox - ax, oy - ay, oz - az
    u = (tx * pvx + ty * pvy + tz * pvz) * inv_det
    qx = ty * e1z - tz * e1y
    qy = tz * e1x - tx * e1z
    qz = tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv_det
    t = (e2x * qx + e2y * qy + e2z * qz) * inv_det
    return det, u, v, t, l1, l2


@njit(cache=True)
def ray_winding(o, d, V, F, lo, hi, left, right, start, count, order, stack, tol, skip=-1):
    """Winding number of ``o`` from the triangle crossings of the ray ``o + t d`` (t > 0).

    Möller–Trumbore; a crossing counts +1 where the ray leaves through a triangle's outer
    side, -1 where it enters (the sign of the determinant). On a closed surface the sum is
    the winding number: 1 inside, 0 outside, 2 where two shells overlap, 0 or -1 in the
    inverted sliver beyond a self-intersection (where parity says inside).

    Returns ``(winding, ambiguous)``; ``ambiguous`` is True when some hit lies within
    ``tol`` (barycentric) of an edge or vertex, or the ray is nearly in a triangle's plane,
    or the origin is on a triangle: the caller then retries with another direction.
    Triangle ``skip`` is ignored (a ray cast from a point of that face).
    """
    inv = np.empty(3)
    for k in range(3):
        inv[k] = 1.0 / d[k] if d[k] != 0.0 else 1e300
    dx, dy, dz = d[0], d[1], d[2]
    ox, oy, oz = o[0], o[1], o[2]
    n = 0
    amb = False
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if not _ray_box(o, inv, lo, hi, node):
            continue
        if left[node] >= 0:
            stack[sp] = left[node]
            stack[sp + 1] = right[node]
            sp += 2
            continue
        for i in range(start[node], start[node] + count[node]):
            f = order[i]
            if f == skip:
                continue
            det, u, v, t, l1, l2 = _ray_triangle(ox, oy, oz, dx, dy, dz, V, F, f)
            if abs(det) <= 1e-12 * l1 * l2:
                # ray (nearly) in the triangle's plane: ambiguous only if the origin is in that plane
                a = F[f, 0]
                e1x, e1y, e1z = V[F[f, 1], 0] - V[a, 0], V[F[f, 1], 1] - V[a, 1], V[F[f, 1], 2] - V[a, 2]
                e2x, e2y, e2z = V[F[f, 2], 0] - V[a, 0], V[F[f, 2], 1] - V[a, 1], V[F[f, 2], 2] - V[a, 2]
                nx = e1y * e2z - e1z * e2y
                ny = e1z * e2x - e1x * e2z
                nz = e1x * e2y - e1y * e2x
                if abs((ox - V[a, 0]) * nx + (oy - V[a, 1]) * ny + (oz - V[a, 2]) * nz) <= 1e-9 * l1 * l2 * (l1 + l2):
                    amb = True
                continue
            if u < -tol or u > 1.0 + tol or v < -tol or u + v > 1.0 + tol:
                continue
            tscale = tol * (l1 + l2)
            if t < -tscale:
                continue
            if t <= tscale:
                amb = True  # origin on the surface
                continue
            if u <= tol or v <= tol or u + v >= 1.0 - tol:
                amb = True
                continue
            n += 1 if det < 0.0 else -1  # det = -d.(e1 x e2): leaving through the outer side
    return n, amb


@njit(cache=True, parallel=True)
def first_hits(O, d, V, F, lo, hi, left, right, start, count, order):
    """How far each ray ``O[i] + t d`` (t ≥ 0, one direction ``d`` for all) runs before it meets
    a triangle of ``(V, F)`` (Möller–Trumbore, edges and corners count as hits; inf: none)."""
    n = O.shape[0]
    out = np.empty(n)
    inv = np.empty(3)
    for k in range(3):
        inv[k] = 1.0 / d[k] if d[k] != 0.0 else 1e300
    dx, dy, dz = d[0], d[1], d[2]
    for r in prange(n):
        stack = np.empty(STACK, np.int64)
        o = O[r]
        ox, oy, oz = o[0], o[1], o[2]
        best = np.inf
        stack[0] = 0
        sp = 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if not _ray_box(o, inv, lo, hi, node):
                continue
            if left[node] >= 0:
                stack[sp] = left[node]
                stack[sp + 1] = right[node]
                sp += 2
                continue
            for i in range(start[node], start[node] + count[node]):
                det, u, v, t, _, _ = _ray_triangle(ox, oy, oz, dx, dy, dz, V, F, order[i])
                if det != 0.0 and 0.0 <= u <= 1.0 and v >= 0.0 and u + v <= 1.0 and 0.0 <= t < best:
                    best = t
        out[r] = best
    return out


@njit(cache=True)
def inside(p, V, F, lo, hi, left, right, start, count, order, stack, dirs):
    """Inside test by the ray-cast winding number, nonzero rule (shells overlapping count as a
    union, the inverted sliver beyond a self-intersection as solid: both are enclosed by the
    surface, so spheres there stay behind it), retried along the next direction while a ray grazes."""
    votes = 0
    for k in range(dirs.shape[0]):
        n, amb = ray_winding(p, dirs[k], V, F, lo, hi, left, right, start, count, order, stack, 1e-9)
        if not amb:
            return n != 0
        votes += n != 0
    # every direction grazed something (point essentially on the surface): majority vote
    return 2 * votes > dirs.shape[0]


@njit(cache=True)
def inside_near(p, qx, qy, qz, tf, feature, side, V, F, lo, hi, left, right, start, count, order, stack, dirs):
    """``inside`` for a point whose closest surface point ``q`` (on ``feature`` of triangle ``tf``) is known.

    When ``q`` lies inside a face that no other face touches, ``p`` is on that face's outer
    side (winding number ``side[tf]``) or its inner side (``side[tf] + 1``): no ray is cast
    (see ``selfintersect``). Faces crossed by others (``side == NO_SIDE``: CBCT fins whose two
    sides cross, overlapping shells) and closest points on an edge or vertex take the ray cast.
    """
    if feature == INTERIOR:
        w = side[tf]
        if w != NO_SIDE:
            nx, ny, nz = face_normal(V, F, tf)
            if (p[0] - qx) * nx + (p[1] - qy) * ny + (p[2] - qz) * nz < 0.0:
                w += 1
            return w != 0
    return inside(p, V, F, lo, hi, left, right, start, count, order, stack, dirs)


@njit(cache=True, parallel=True)
def unsigned_distance(P, V, F, lo, hi, left, right, start, count, order, bound2=np.inf):
    """Distance of points ``P (n, 3)`` to the triangles ``(V, F)`` (any mesh, closed or not);
    ``sqrt(bound2)`` for a point with nothing closer (the bound prunes the search)."""
    n = P.shape[0]
    out = np.empty(n)
    for i in prange(n):
        stack = np.empty(STACK, np.int64)
        out[i] = np.sqrt(tri_closest(P[i], V, F, lo, hi, left, right, start, count, order, stack, bound2)[0])
    return out


@njit(cache=True, parallel=True)
def points_inside(P, V, F, lo, hi, left, right, start, count, order, dirs):
    """``inside`` for each of the points ``P (n, 3)``: the ray-cast winding number, nonzero rule."""
    n = P.shape[0]
    out = np.empty(n, np.bool_)
    for i in prange(n):
        stack = np.empty(STACK, np.int64)
        out[i] = inside(P[i], V, F, lo, hi, left, right, start, count, order, stack, dirs)
    return out


@njit(cache=True, parallel=True)
def signed_distance(P, V, F, side, lo, hi, left, right, start, count, order, dirs):
    """Signed distance of points ``P (n, 3)`` to a closed mesh: positive inside.

    Magnitude from the BVH closest point, sign from that point's face (``side``: winding
    numbers beside each face, ``selfintersect.face_sides``) or the ray-cast winding number
    (robust retries): see ``inside_near``.
    """
    n = P.shape[0]
    out = np.empty(n)
    for i in prange(n):
        stack = np.empty(STACK, np.int64)
        d2, qx, qy, qz, tf, feature = tri_closest(P[i], V, F, lo, hi, left, right, start, count, order, stack)
        d = np.sqrt(d2)
        if inside_near(P[i], qx, qy, qz, tf, feature, side, V, F, lo, hi, left, right, start, count, order, stack, dirs):
            out[i] = d
        else:
            out[i] = -d
    return out


@njit(cache=True)
def sphere_gap_xyz(px, py, pz, C, R, lo, hi, left, right, start, count, order, stack, bound):
    """Distance from ``(px, py, pz)`` to the union of spheres, clamped at 0, searched below ``bound``.

    Returns ``(gap, index)``; ``index`` is -1 when no sphere comes closer than ``bound``.
    Node boxes enclose their spheres, so the box distance is a lower bound of the gap.
    """
    best = bound
    bi = -1
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        bd = box_dist2(px, py, pz, lo, hi, node)
        if bd >= best * best:
            continue
        if left[node] < 0:
            for i in range(start[node], start[node] + count[node]):
                j = order[i]
                g = ball_gap(px, py, pz, C, R, j)
                if g < best:
                    best = g
                    bi = j
                    if g <= 0.0:
                        return 0.0, j
            continue
        l = left[node]
        r = right[node]
        dl = box_dist2(px, py, pz, lo, hi, l)
        dr = box_dist2(px, py, pz, lo, hi, r)
        if dl < dr:
            stack[sp] = r
            stack[sp + 1] = l
        else:
            stack[sp] = l
            stack[sp + 1] = r
        sp += 2
    return max(best, 0.0), bi


@njit(cache=True)
def _near_scan(px, py, pz, C, R, lo, hi, left, right, start, count, order, stack, bound, out):
    """The spheres whose gap from ``(px, py, pz)`` is below ``bound`` into ``out``, until it is
    full: returns ``(n, j)``, ``j`` the sphere found with ``out`` already full (-1: all found)."""
    b2 = bound * bound
    n = 0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if box_dist2(px, py, pz, lo, hi, node) >= b2:
            continue
        if left[node] < 0:
            for i in range(start[node], start[node] + count[node]):
                j = order[i]
                if ball_gap(px, py, pz, C, R, j) < bound:
                    if n == out.shape[0]:
                        return n, j
                    out[n] = j
                    n += 1
            continue
        stack[sp] = left[node]
        stack[sp + 1] = right[node]
        sp += 2
    return n, -1


@njit(cache=True)
def spheres_near(px, py, pz, C, R, lo, hi, left, right, start, count, order, stack, bound, out):
    """Indices of the spheres whose gap from ``(px, py, pz)`` is below ``bound``, into ``out``.

    Returns how many, or -1 as soon as one more is found than ``out`` holds.
    """
    n, more = _near_scan(px, py, pz, C, R, lo, hi, left, right, start, count, order, stack, bound, out)
    return -1 if more >= 0 else n


@njit(cache=True)
def sphere_within_xyz(px, py, pz, C, R, lo, hi, left, right, start, count, order, stack, bound):
    """A sphere whose gap from ``(px, py, pz)`` is below ``bound``, or -1 (stops at the first
    one: a rejection test, cheaper than ``sphere_gap_xyz``'s nearest search)."""
    return _near_scan(px, py, pz, C, R, lo, hi, left, right, start, count, order, stack, bound, stack[:0])[1]


@njit(cache=True)
def sphere_gap(p, C, R, lo, hi, left, right, start, count, order, stack, bound):
    """``sphere_gap_xyz`` at the point ``p (3,)``."""
    return sphere_gap_xyz(p[0], p[1], p[2], C, R, lo, hi, left, right, start, count, order, stack, bound)


class BVH:
    """A BVH over triangles ``(V, F)`` or over spheres ``(C, R)`` (build-time helper)."""

    def __init__(self, lo, hi):
        (self.lo, self.hi, self.left, self.right, self.start, self.count, self.order) = build_bvh(
            np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64)
        )

    @property
    def arrays(self):
        return self.lo, self.hi, self.left, self.right, self.start, self.count, self.order

    @classmethod
    def of_triangles(cls, V, F):
        T = V[F]
        return cls(T.min(axis=1), T.max(axis=1))

    def distance(self, P, V, F, within: float = np.inf):
        """Unsigned distance of points ``P (n, 3)`` to the triangles ``(V, F)`` this BVH was built on;
        ``within`` for the points farther than ``within`` (a bound makes far points cheap)."""
        P = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 3)
        return unsigned_distance(P, np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64),
                                 *self.arrays, float(within) ** 2)

    def first_hits(self, O, d, V, F):
        """How far rays from the points ``O (n, 3)`` along the direction ``d`` run before they meet
        the triangles ``(V, F)`` this BVH was built on (inf: never)."""
        O = np.ascontiguousarray(O, dtype=np.float64).reshape(-1, 3)
        return first_hits(O, np.ascontiguousarray(d, dtype=np.float64), np.ascontiguousarray(V, dtype=np.float64),
                          np.ascontiguousarray(F, dtype=np.int64), *self.arrays)

    def contains(self, P, V, F):
        """Whether each point ``P (n, 3)`` is inside the closed mesh ``(V, F)`` this BVH was built on."""
        P = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 3)
        return points_inside(P, np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64),
                             *self.arrays, RAY_DIRS)

    @classmethod
    def of_spheres(cls, C, R):
        r = R[:, None]
        return cls(C - r, C + r)
