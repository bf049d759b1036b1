"""Greedy packing of non-overlapping inner spheres, largest free sphere first.

Each candidate point ``p`` has a free distance ``f(p) = min(surface distance,
distance to the nearest placed sphere)``. The candidate with the largest ``f`` becomes a
sphere of radius ``f``: it touches the surface or another sphere and overlaps nothing.
Candidates it covers are dropped; those within ``2 r`` of it get ``f`` lowered (nothing
farther can change, because every remaining ``f`` is at most ``r``).

A binary heap with lazy updates keeps the order: a popped entry whose key is stale is
pushed back with its current value, so each sphere costs O(log n) plus its neighbourhood,
not a re-sort (the seed's O(n² log n)). Since the spheres do not overlap, the
neighbourhood work summed over all spheres is bounded by ~15x the number of candidates.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..geometry.bvh import (
    BVH,
    RAY_DIRS,
    STACK,
    ball_gap,
    box_dist2,
    closest_on_triangle,
    inside_near,
    sphere_gap_xyz,
    sphere_within_xyz,
    spheres_near,
    tri_closest,
)
from .voxelize import KEY_BITS, KEY_MASK


@njit(cache=True)
def _heap_push(hk, hi, n, key, idx):
    # max-heap on key, ties broken by the smaller index (determinism)
    i = n
    hk[i] = key
    hi[i] = idx
    while i > 0:
        p = (i - 1) >> 1
        if hk[p] > hk[i] or (hk[p] == hk[i] and hi[p] < hi[i]):
            break
        hk[p], hk[i] = hk[i], hk[p]
        hi[p], hi[i] = hi[i], hi[p]
        i = p
    return n + 1


@njit(cache=True)
def _heap_pop(hk, hi, n):
    key = hk[0]
    idx = hi[0]
    n -= 1
    hk[0] = hk[n]
    hi[0] = hi[n]
    i = 0
    while True:
        l = 2 * i + 1
        if l >= n:
            break
        c = l
        r = l + 1
        if r < n and (hk[r] > hk[l] or (hk[r] == hk[l] and hi[r] < hi[l])):
            c = r
        if hk[i] > hk[c] or (hk[i] == hk[c] and hi[i] < hi[c]):
            break
        hk[c], hk[i] = hk[i], hk[c]
        hi[c], hi[i] = hi[i], hi[c]
        i = c
    return key, idx, n


@njit(cache=True)
def _heap_of(f, r_min):
    """Heap of the candidates with free distance ``f >= r_min``, and which are alive."""
    n = f.shape[0]
    hk = np.empty(n + 1)
    hix = np.empty(n + 1, np.int64)
    hn = 0
    for i in range(n):
        if f[i] >= r_min:
            hn = _heap_push(hk, hix, hn, f[i], i)
    return hk, hix, hn, f >= r_min


@njit(cache=True)
def _pop_live(hk, hix, hn, f, alive, r_min):
    """The live candidate of largest current ``f`` (-1 when none is left) and the heap size."""
    while hn > 0:
        key, i, hn = _heap_pop(hk, hix, hn)
        if not alive[i]:
            continue
        if f[i] < key:  # stale entry: reinsert with the current value
            if f[i] >= r_min:
                hn = _heap_push(hk, hix, hn, f[i], i)
            else:
                alive[i] = False
            continue
        return i, hn
    return -1, hn


# Candidates near a new sphere are found through the sorted lattice keys: each (a, b) row of the
# lattice is a contiguous run of them. A table of where each row starts (``row_index``: one entry
# per row of the candidates' bounding rectangle, or per block of neighbouring rows when that would
# be more than ROW_TABLE_MAX_RATIO entries per candidate) turns a binary search over all
# candidates per row (~20 cache misses on millions of keys) into one over a few of them. A larger
# ratio spends memory on the table for shorter searches.
ROW_TABLE_MAX_RATIO = 2.0
ROW_TABLE_MIN = 1 << 16  # entries the table may always have


@njit(cache=True)
def _row_starts(keys, a_lo, b_lo, nbb, bs, n_rows):
    start = np.empty(n_rows + 1, np.int64)
    q = 0
    for j in range(keys.shape[0]):
        rq = ((keys[j] >> (2 * KEY_BITS)) - a_lo) * nbb + (((keys[j] >> KEY_BITS) & KEY_MASK) - b_lo) // bs
        while q <= rq:
            start[q] = j
            q += 1
    while q <= n_rows:
        start[q] = keys.shape[0]
        q += 1
    return start


def row_index(keys):
    """Where each block of lattice rows of the sorted ``keys`` starts (see ``_lower_free``):
    ``(start, a_lo, b_lo, nbb, bs)``: the rows ``(a, b)`` with ``(b - b_lo) // bs == k`` start at
    ``start[(a - a_lo) * nbb + k]``."""
    if len(keys) == 0:
        return np.zeros(2, np.int64), 0, 0, 1, 1
    a_lo, a_hi = int(keys[0] >> (2 * KEY_BITS)), int(keys[-1] >> (2 * KEY_BITS))
    b = (keys >> KEY_BITS) & KEY_MASK
    b_lo, b_hi = int(b.min()), int(b.max())
    na, nb = a_hi - a_lo + 1, b_hi - b_lo + 1
    cap = max(ROW_TABLE_MAX_RATIO * len(keys), ROW_TABLE_MIN)
    bs = max(1, int(np.ceil(na * nb / cap)))
    nbb = -(-nb // bs)
    return _row_starts(keys, a_lo, b_lo, nbb, bs, na * nbb), a_lo, b_lo, nbb, bs


@njit(cache=True)
def _lower_free(P, f, alive, keys, rows, origin, h, x, y, z, r, reach, r_min):
    """Lower ``f`` of the live candidates within ``reach`` of a new sphere ``(x, y, z), r``
    (lattice box scan through ``row_index``'s table), dropping those left below ``r_min``."""
    start, a_lo, b_lo, nbb, bs = rows
    na = (start.shape[0] - 1) // nbb
    lo0 = int(np.ceil((x - reach - origin[0]) / h))
    hi0 = int(np.floor((x + reach - origin[0]) / h))
    lo1 = int(np.ceil((y - reach - origin[1]) / h))
    hi1 = int(np.floor((y + reach - origin[1]) / h))
    lo2 = int(np.ceil((z - reach - origin[2]) / h))
    hi2 = int(np.floor((z + reach - origin[2]) / h))
    for a in range(max(lo0, a_lo), min(hi0, a_lo + na - 1) + 1):
        for b in range(max(lo1, b_lo), min(hi1, b_lo + nbb * bs - 1) + 1):
            q = (a - a_lo) * nbb + (b - b_lo) // bs
            r0 = start[q]
            r1 = start[q + 1]
            if r0 == r1:
                continue
            # the keys of one (a, b) row are contiguous in sorted order, inside their block
            base = (a << (2 * KEY_BITS)) | (b << KEY_BITS)
            blk = keys[r0:r1]
            j0 = r0 + np.searchsorted(blk, base | max(lo2, 0))
            j1 = r0 + np.searchsorted(blk, base | hi2, side="right")
            for j in range(j0, j1):
                if not alive[j]:
                    continue
                gap = np.sqrt((P[j, 0] - x) ** 2 + (P[j, 1] - y) ** 2 + (P[j, 2] - z) ** 2) - r
                if gap < f[j]:
                    f[j] = gap
                    if gap < r_min:
                        alive[j] = False


NO_SEEDS = (np.empty((0, 3), np.float32), np.empty(0, np.int64), np.zeros(1, np.int64), 1.0, 0.0)  # greedy_pack without the cover test


def seed_grid(seeds, origin, g, reach):
    """Seeds sorted into a grid of cell ``g`` for ``greedy_pack``'s cover test.

    Returns ``(S, cell_keys, cell_start, g, reach)``: the seeds in cell order (float32: a
    filter needs no more, and a fine level has tens of millions of seeds), each occupied
    cell's key (as ``voxelize.encode``) and where its seeds start in ``S``; ``reach`` is the
    gap a sphere must bring a seed below to count as covering it. ``greedy_pack`` reorders
    ``S`` within its cells: one grid per call.
    """
    if len(seeds) == 0:
        return NO_SEEDS
    k = np.zeros(len(seeds), np.int64)
    for d, shift in enumerate((2 * KEY_BITS, KEY_BITS, 0)):  # one axis at a time: no (n, 3) temporaries
        k |= np.clip(np.floor((seeds[:, d] - origin[d]) / g), 0, KEY_MASK).astype(np.int64) << shift
    o = np.argsort(k, kind="stable")
    k = k[o]
    first = np.flatnonzero(np.concatenate([[True], k[1:] != k[:-1]]))
    S = np.empty((len(o), 3), np.float32)
    for d in range(3):
        S[:, d] = seeds[o, d]
    return S, k[first], np.append(first, len(S)).astype(np.int64), float(g), float(reach)


@njit(cache=True)
def _cover_seeds(cx, cy, cz, reach, S, ckeys, cstart, cend, origin, g):
    """Remove the seeds within ``reach`` of ``c``; True if there were any.

    A removed seed is swapped behind its cell's live end (``cend``), so later scans only
    walk seeds still uncovered: most candidates near the surface reach only covered ones.
    """
    hit = False
    lo0 = max(int(np.floor((cx - reach - origin[0]) / g)), 0)
    hi0 = min(int(np.floor((cx + reach - origin[0]) / g)), KEY_MASK)
    lo1 = max(int(np.floor((cy - reach - origin[1]) / g)), 0)
    hi1 = min(int(np.floor((cy + reach - origin[1]) / g)), KEY_MASK)
    lo2 = max(int(np.floor((cz - reach - origin[2]) / g)), 0)
    hi2 = min(int(np.floor((cz + reach - origin[2]) / g)), KEY_MASK)
    r2 = reach * reach
    for a in range(lo0, hi0 + 1):
        for b in range(lo1, hi1 + 1):
            base = (a << (2 * KEY_BITS)) | (b << KEY_BITS)
            u0 = np.searchsorted(ckeys, base | lo2)
            u1 = np.searchsorted(ckeys, base | hi2, side="right")
            for u in range(u0, u1):
                j = cstart[u]
                while j < cend[u]:
                    dx = S[j, 0] - cx
                    dy = S[j, 1] - cy
                    dz = S[j, 2] - cz
                    if dx * dx + dy * dy + dz * dz <= r2:
                        e = cend[u] - 1
                        for d in range(3):
                            S[j, d], S[e, d] = S[e, d], S[j, d]
                        cend[u] = e
                        hit = True
                    else:
                        j += 1
    return hit


def greedy_pack(P, f, keys, origin, h, r_min, max_new, shrink, S, ckeys, cstart, g, cover):
    """Greedy packing over lattice candidates.

    Parameters
    ----------
    P : (n, 3) candidate centres, lattice points of spacing ``h`` about ``origin``.
    f : (n,) initial free distance (modified in place).
    keys : (n,) sorted lattice keys of ``P`` (see ``voxelize.encode``), for neighbour lookup.
    r_min : candidates whose free distance drops below this are discarded.
    max_new : stop after this many spheres.
    shrink : relative shrink of each radius, keeps rounding from creating overlaps.
    S, ckeys, cstart, g, cover : seeds (points where the surface gap is still too large) in a
        grid of cell ``g`` (see ``seed_grid``; ``S`` is reordered within its cells). When
        given, a candidate becomes a sphere only if it brings some seed not yet covered within
        ``cover`` of its surface; the others are dropped. Near the surface a band of spheres
        of the lattice's size covers each seed many times over (a sphere of radius r reaches
        a surface gap ε over a disc of radius about sqrt(2 r ε + ε²), far wider than the 2r
        spacing of its neighbours once ε > r), so this keeps the spheres that close gaps and
        drops the redundant ones.
        ``NO_SEEDS`` turns it off (level 0, interior fill).

    Returns
    -------
    centers (k, 3), radii (k,) in placement order (non-increasing radius).
    """
    return _greedy_pack(np.ascontiguousarray(P), f, keys, row_index(keys), origin, h, r_min, max_new, shrink, S, ckeys, cstart,
                        g, cover)


@njit(cache=True)
def _greedy_pack(P, f, keys, rows, origin, h, r_min, max_new, shrink, S, ckeys, cstart, g, cover):
    n = P.shape[0]
    hk, hix, hn, alive = _heap_of(f, r_min)
    ns = S.shape[0]
    cend = cstart[1:].copy()
    C = np.empty((min(n, max_new), 3))
    R = np.empty(min(n, max_new))
    k = 0
    while k < max_new:
        i, hn = _pop_live(hk, hix, hn, f, alive, r_min)
        if i < 0:
            break
        alive[i] = False
        r = f[i] * (1.0 - shrink)
        c = P[i]
        if ns > 0 and not _cover_seeds(c[0], c[1], c[2], r + cover, S, ckeys, cstart, cend, origin, g):
            continue  # every seed it reaches is covered already: it would close no gap
        C[k] = c
        R[k] = r
        k += 1
        # candidates within r + f can have their free distance lowered (all others have
        # f at most this one's, the heap's top)
        _lower_free(P, f, alive, keys, rows, origin, h, c[0], c[1], c[2], r, r + f[i], r_min)
    return C[:k].copy(), R[:k].copy()


BAND_CHUNK_POINTS = 4096  # band points per task of _band_free (consecutive: neighbours along a lattice row)


@njit(cache=True, parallel=True)
def _band_free(P, V, F, side, tlo, thi, tleft, tright, tstart, tcount, torder, C, R, slo, shi, sleft, sright, sstart, scount, sorder, dirs, r_min):
    n = P.shape[0]
    f = np.empty(n)
    tasks = (n + BAND_CHUNK_POINTS - 1) // BAND_CHUNK_POINTS
    for t in prange(tasks):
        stack = np.empty(STACK, np.int64)
        # the sphere that rejected (or was nearest to) the point before: band points come in
        # lattice-key order, so it is usually within r_min of this one too, and the BVH search
        # is skipped (the same answers: the test only asks whether any sphere is that near).
        last = -1
        for i in range(t * BAND_CHUNK_POINTS, min(n, (t + 1) * BAND_CHUNK_POINTS)):
            x, y, z = P[i, 0], P[i, 1], P[i, 2]
            # cheapest rejections first. A sphere within r_min (a large share of a fine level's
            # band: the spheres of the levels before) is found by a search that stops at the first
            # one; then the surface: the points too near it and, by its closest face's side (no ray
            # where the face is uncrossed: bvh.inside_near), those outside; only the candidates left
            # (about a tenth) need their exact gap to the spheres.
            if R.shape[0] > 0:
                if last >= 0 and ball_gap(x, y, z, C, R, last) < r_min:
                    f[i] = -1.0
                    continue
                j = sphere_within_xyz(x, y, z, C, R, slo, shi, sleft, sright, sstart, scount, sorder, stack, r_min)
                if j >= 0:
                    last = j
                    f[i] = -1.0
                    continue
            d2, qx, qy, qz, tf, feature = tri_closest(P[i], V, F, tlo, thi, tleft, tright, tstart, tcount, torder, stack, np.inf)
            d = np.sqrt(d2)
            if tf < 0 or d < r_min:
                f[i] = -1.0
                continue
            if not inside_near(P[i], qx, qy, qz, tf, feature, side, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, stack, dirs):
                f[i] = -1.0
                continue
            g = d
            if R.shape[0] > 0:
                g, j = sphere_gap_xyz(x, y, z, C, R, slo, shi, sleft, sright, sstart, scount, sorder, stack, d)
                if j >= 0:
                    last = j
            f[i] = g if g >= r_min else -1.0
    return f


def band_free_distance(P, vox, C, R, r_min, bvh: BVH | None = None):
    """Free distance ``min(surface distance, gap to spheres)`` of band points, -1 where
    the point is outside the mesh or its free distance is below ``r_min``.

    ``bvh`` is a sphere BVH of ``C, R`` to reuse (built here when not given)."""
    if bvh is not None and len(R):
        sb = bvh
    else:
        sb = BVH.of_spheres(C, R) if len(R) else BVH(np.zeros((1, 3)), np.zeros((1, 3)))
    vox.points_evaluated += len(P)
    return _band_free(
        np.ascontiguousarray(P), vox.V, vox.F, vox.side, *vox.bvh.arrays, C, R, *sb.arrays, RAY_DIRS, float(r_min)
    )


# --- grown packing: each sphere moves off the lattice to the centre of its hole --------------
#
# A lattice candidate is up to ~0.9 spacings from the best centre of the hole it lies in, so its
# sphere is smaller than the hole allows and the rest of the hole stays empty. Protosphere
# (Weller & Zachmann) moves each prototype away from its nearest obstacle until it touches
# several. Here, once per sphere, the obstacles within GROW_REACH free distances of the
# candidate are gathered (triangles, earlier spheres, this packing's spheres); the centre then
# climbs their free distance (see _climb) for up to GROW_ITERS steps, each along the direction
# that raises the distances to the obstacles within GROW_TOL of the nearest fastest.
GROW_ITERS = 12
GROW_TOL = 0.01
GROW_BUF = 256  # obstacles gathered per sphere at first (buffers double on demand)
GROW_BUF_MAX = 1 << 16  # more than this: the sphere stays on its lattice point
GROW_BATCH = 64  # candidates grown at once (in parallel; see _grown_pack)


@njit(cache=True)
def _cell_range(v, b, origin, g, dims, axis):
    lo = int(np.floor((v - b - origin[axis]) / g))
    hi = int(np.floor((v + b - origin[axis]) / g))
    return min(max(lo, 0), dims[axis] - 1), min(max(hi, 0), dims[axis] - 1)


# The spheres placed by one grown packing are registered in every cell of a uniform grid that
# their bounding box touches (``head`` per cell, linked entries ``nxt``/``sid``, grown by
# doubling). A sphere whose gap to a point x is below b touches the cube x ± b, so the cells of
# that cube hold it.
@njit(cache=True)
def _grid_insert(k, cx, cy, cz, r, head, nxt, sid, ne, origin, g, dims):
    """Register sphere ``k``; returns the (possibly reallocated) entry arrays and their count."""
    a0, a1 = _cell_range(cx, r, origin, g, dims, 0)
    b0, b1 = _cell_range(cy, r, origin, g, dims, 1)
    c0, c1 = _cell_range(cz, r, origin, g, dims, 2)
    need = ne + (a1 - a0 + 1) * (b1 - b0 + 1) * (c1 - c0 + 1)
    if need > nxt.shape[0]:
        cap = max(2 * nxt.shape[0], need)
        n2 = np.empty(cap, np.int64)
        s2 = np.empty(cap, np.int64)
        n2[:ne] = nxt[:ne]
        s2[:ne] = sid[:ne]
        nxt, sid = n2, s2
    for a in range(a0, a1 + 1):
        for b in range(b0, b1 + 1):
            for c in range(c0, c1 + 1):
                cell = (a * dims[1] + b) * dims[2] + c
                nxt[ne] = head[cell]
                sid[ne] = k
                head[cell] = ne
                ne += 1
    return nxt, sid, ne


@njit(cache=True)
def _gather(x, y, z, bound, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, C, R, head, nxt, sid, origin, g, dims,
            PC, PR, slo, shi, sleft, sright, sstart, scount, sorder, stack, OC, OR, OT):
    """Obstacles closer than ``bound`` to ``(x, y, z)``: spheres into ``OC, OR``, triangles into
    ``OT``. Returns their counts, or -1 when the buffers overflow."""
    ns = 0
    nt = 0
    cap = OR.shape[0]
    # this packing's spheres (each once: in the first cell of the scan that holds it)
    a0, a1 = _cell_range(x, bound, origin, g, dims, 0)
    b0, b1 = _cell_range(y, bound, origin, g, dims, 1)
    c0, c1 = _cell_range(z, bound, origin, g, dims, 2)
    for a in range(a0, a1 + 1):
        for b in range(b0, b1 + 1):
            for c in range(c0, c1 + 1):
                e = head[(a * dims[1] + b) * dims[2] + c]
                while e >= 0:
                    j = sid[e]
                    e = nxt[e]
                    if np.sqrt((x - C[j, 0]) ** 2 + (y - C[j, 1]) ** 2 + (z - C[j, 2]) ** 2) - R[j] >= bound:
                        continue
                    if (a != max(a0, _cell_range(C[j, 0], R[j], origin, g, dims, 0)[0])
                            or b != max(b0, _cell_range(C[j, 1], R[j], origin, g, dims, 1)[0])
                            or c != max(c0, _cell_range(C[j, 2], R[j], origin, g, dims, 2)[0])):
                        continue
                    if ns == cap:
                        return -1, -1
                    OC[ns, 0], OC[ns, 1], OC[ns, 2] = C[j, 0], C[j, 1], C[j, 2]
                    OR[ns] = R[j]
                    ns += 1
    # earlier spheres and triangles: BVH range searches (the triangle buffer holds the
    # spheres' indices first)
    b2 = bound * bound
    if PR.shape[0] > 0:
        m = spheres_near(x, y, z, PC, PR, slo, shi, sleft, sright, sstart, scount, sorder, stack, bound, OT[:cap - ns])
        if m < 0:
            return -1, -1
        for q in range(m):
            j = OT[q]
            OC[ns, 0], OC[ns, 1], OC[ns, 2] = PC[j, 0], PC[j, 1], PC[j, 2]
            OR[ns] = PR[j]
            ns += 1
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if box_dist2(x, y, z, tlo, thi, node) >= b2:
            continue
        if tleft[node] < 0:
            for i in range(tstart[node], tstart[node] + tcount[node]):
                f = torder[i]
                qx, qy, qz, _ = closest_on_triangle(x, y, z, V, F[f, 0], F[f, 1], F[f, 2])
                if (qx - x) ** 2 + (qy - y) ** 2 + (qz - z) ** 2 < b2:
                    if nt == OT.shape[0]:
                        return -1, -1
                    OT[nt] = f
                    nt += 1
            continue
        stack[sp] = tleft[node]
        stack[sp + 1] = tright[node]
        sp += 2
    return ns, nt


@njit(cache=True)
def _local_free(x, y, z, V, F, OC, OR, ns, OT, nt):
    """Free distance at ``(x, y, z)`` among the gathered obstacles."""
    best = np.inf
    for j in range(ns):
        d = np.sqrt((x - OC[j, 0]) ** 2 + (y - OC[j, 1]) ** 2 + (z - OC[j, 2]) ** 2) - OR[j]
        if d < best:
            best = d
    for i in range(nt):
        f = OT[i]
        qx, qy, qz, _ = closest_on_triangle(x, y, z, V, F[f, 0], F[f, 1], F[f, 2])
        d = np.sqrt((qx - x) ** 2 + (qy - y) ** 2 + (qz - z) ** 2)
        if d < best:
            best = d
    return best


@njit(cache=True)
def _slopes(x, y, z, V, F, OC, OR, ns, OT, nt, D, U):
    """Distance ``D`` to each gathered obstacle and its unit gradient ``U`` (away from it)."""
    for j in range(ns):
        dx, dy, dz = x - OC[j, 0], y - OC[j, 1], z - OC[j, 2]
        n = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-300)
        D[j] = n - OR[j]
        U[j, 0], U[j, 1], U[j, 2] = dx / n, dy / n, dz / n
    for i in range(nt):
        f = OT[i]
        qx, qy, qz, _ = closest_on_triangle(x, y, z, V, F[f, 0], F[f, 1], F[f, 2])
        dx, dy, dz = x - qx, y - qy, z - qz
        n = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-300)
        D[ns + i] = n
        U[ns + i, 0], U[ns + i, 1], U[ns + i, 2] = dx / n, dy / n, dz / n


@njit(cache=True)
def _min_rate(U, act, na, dx, dy, dz):
    m = np.inf
    for a in range(na):
        j = act[a]
        m = min(m, U[j, 0] * dx + U[j, 1] * dy + U[j, 2] * dz)
    return m


@njit(cache=True)
def _try_direction(U, act, na, dx, dy, dz, tiny, best, bx, by, bz):
    """The better of the direction ``(dx, dy, dz)``, normalized (skipped if shorter than
    ``tiny``), and the best so far ``(bx, by, bz)`` with rate ``best``."""
    n = np.sqrt(dx * dx + dy * dy + dz * dz)
    if n > tiny:
        dx, dy, dz = dx / n, dy / n, dz / n
        r = _min_rate(U, act, na, dx, dy, dz)
        if r > best:
            return r, dx, dy, dz
    return best, bx, by, bz


@njit(cache=True)
def _ascent(U, act, na):
    """Unit direction that raises the distances to the active obstacles fastest (max-min rate).

    The optimum is the gradient of one obstacle, the bisector of two or the equal-rate
    direction of three of them: all are tried, the best kept. Returns it and its rate."""
    bx = by = bz = 0.0
    best = -np.inf
    for a in range(na):
        j = act[a]
        r = _min_rate(U, act, na, U[j, 0], U[j, 1], U[j, 2])
        if r > best:
            best, bx, by, bz = r, U[j, 0], U[j, 1], U[j, 2]
        for b in range(a + 1, na):
            k = act[b]
            best, bx, by, bz = _try_direction(U, act, na, U[j, 0] + U[k, 0], U[j, 1] + U[k, 1], U[j, 2] + U[k, 2],
                                              1e-9, best, bx, by, bz)
            for c in range(b + 1, na):
                l = act[c]
                # d with U_j.d = U_k.d = U_l.d = 1 (Cramer's rule), then normalized
                a0, a1, a2 = U[j, 0], U[j, 1], U[j, 2]
                b0, b1, b2 = U[k, 0], U[k, 1], U[k, 2]
                c0, c1, c2 = U[l, 0], U[l, 1], U[l, 2]
                det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
                if abs(det) < 1e-9:
                    continue
                # inverse by cross products: d = (b x c + c x a + a x b) / det
                d0 = ((b1 * c2 - b2 * c1) + (c1 * a2 - c2 * a1) + (a1 * b2 - a2 * b1)) / det
                d1 = ((b2 * c0 - b0 * c2) + (c2 * a0 - c0 * a2) + (a2 * b0 - a0 * b2)) / det
                d2 = ((b0 * c1 - b1 * c0) + (c0 * a1 - c1 * a0) + (a0 * b1 - a1 * b0)) / det
                best, bx, by, bz = _try_direction(U, act, na, d0, d1, d2, 1e-12, best, bx, by, bz)
    return bx, by, bz, best


@njit(cache=True)
def _climb(x0, y0, z0, cur, reach, iters, tol, V, F, OC, OR, ns, OT, nt, D, U, act):
    """Climb the free distance of the gathered obstacles from a candidate of free distance ``cur``.

    The obstacles are all those within ``reach * cur`` of the start; moving by ``m`` changes
    the free distance by at most ``m``, so within ``(reach - 1) / 2 * cur`` of the start the
    local free distance is the true one: the centre stays in that ball. Each step goes along
    the ascent direction of the obstacles within ``tol`` of the nearest, as far as the lower
    envelope of the distances' tangent lines keeps rising (distances to spheres and triangles
    are convex along a line, so the free distance there is at least that envelope: it never
    drops, and it stays positive, so the centre stays inside the solid).
    """
    x, y, z = x0, y0, z0
    no = ns + nt
    mv = 0.5 * (reach - 1.0) * cur
    for _ in range(iters):
        _slopes(x, y, z, V, F, OC, OR, ns, OT, nt, D, U)
        cur = np.inf
        for j in range(no):
            cur = min(cur, D[j])
        # the direction raises the obstacles within t of the nearest: t = tol first (fewer,
        # longer steps); where they block each other, a tighter t (the envelope steps past the
        # ones left out, up to where they tie)
        moved = False
        t = tol
        while t > 1e-7 and not moved:
            na = 0
            for j in range(no):
                if D[j] <= cur * (1.0 + t) and na < act.shape[0]:
                    act[na] = j
                    na += 1
            t *= 0.1
            dx, dy, dz, rho = _ascent(U, act, na)
            if rho <= 1e-3:
                continue
            # farthest s with the envelope cur + rho*s still the minimum of all tangent lines
            s = np.inf
            for j in range(no):
                m = U[j, 0] * dx + U[j, 1] * dy + U[j, 2] * dz
                if m < rho:
                    s = min(s, max(D[j] - cur, 0.0) / (rho - m))
            # and inside the ball where the gathered obstacles are all that matter
            wx, wy, wz = x - x0, y - y0, z - z0
            wd = wx * dx + wy * dy + wz * dz
            disc = wd * wd - (wx * wx + wy * wy + wz * wz - mv * mv)
            s = min(s, -wd + np.sqrt(max(disc, 0.0)))
            if s > 1e-6 * cur:
                x, y, z = x + s * dx, y + s * dy, z + s * dz
                moved = True
        if not moved:  # no direction raises them all: the centre of its hole
            break
    return x, y, z, _local_free(x, y, z, V, F, OC, OR, ns, OT, nt)


@njit(cache=True, parallel=True)
def _grow_batch(P, f, alive, keys, rows, origin, h, r_min, shrink, members, nb, C, R, head, nxt, sid, gorigin, g, gdims, V, F, tlo,
                thi, tleft, tright, tstart, tcount, torder, PC, PR, slo, shi, sleft, sright, sstart, scount, sorder, iters, tol,
                reach_f, buf, S, ckeys, cstart, cend, cg, cover, out):
    """Grow the candidates ``members[:nb]`` at once: ``out[b] = x, y, z, r`` (r = -1 when the
    sparse cover test drops it), and lower the free distance of the candidates around each.

    Each member reads only the spheres placed before the batch and the mesh, and writes only
    the candidates within ``(reach_f + 1) * f`` of its lattice point, which no other member's
    region meets (see ``_grown_pack``): the threads share nothing they write.
    """
    nseeds = S.shape[0]
    for b in prange(nb):
        i = members[b]
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        start = f[i]
        cur = start
        alive[i] = False
        if iters > 0:
            stack = np.empty(STACK, np.int64)
            cap = buf
            while True:
                OC = np.empty((cap, 3))
                OR = np.empty(cap)
                OT = np.empty(cap, np.int64)
                ns, nt = _gather(x, y, z, reach_f * start, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, C, R,
                                 head, nxt, sid, gorigin, g, gdims, PC, PR, slo, shi, sleft, sright, sstart, scount, sorder,
                                 stack, OC, OR, OT)
                if ns >= 0 or cap >= GROW_BUF_MAX:
                    break
                cap *= 2  # a large sphere near a fine surface
            if ns >= 0:  # else too crowded to gather: stays on its lattice point
                x, y, z, cur = _climb(x, y, z, start, reach_f, iters, tol, V, F, OC, OR, ns, OT, nt,
                                      np.empty(2 * cap), np.empty((2 * cap, 3)), np.empty(16, np.int64))
        r = cur * (1.0 - shrink)
        out[b, 0], out[b, 1], out[b, 2], out[b, 3] = x, y, z, r
        if nseeds > 0 and not _cover_seeds(x, y, z, r + cover, S, ckeys, cstart, cend, origin, cg):
            out[b, 3] = -1.0  # every seed it reaches is covered already: it would close no gap
            continue
        # the candidates within r + start can have their free distance lowered: all others
        # have f <= start, except the ones held back from this batch (_grown_pack lowers those)
        _lower_free(P, f, alive, keys, rows, origin, h, x, y, z, r, r + start, r_min)


@njit(cache=True)
def _grown_pack(P, f, keys, rows, origin, h, r_min, max_new, shrink, V, F, tlo, thi, tleft, tright, tstart, tcount, torder,
                PC, PR, slo, shi, sleft, sright, sstart, scount, sorder, gorigin, g, gdims, iters, tol, reach_f, buf, batch,
                S, ckeys, cstart, cg, cover):
    n = P.shape[0]
    hk, hix, hn, alive = _heap_of(f, r_min)
    C = np.empty((min(n, max_new), 3))
    R = np.empty(min(n, max_new))
    head = np.full(gdims[0] * gdims[1] * gdims[2], -1, np.int64)
    nxt = np.empty(1024, np.int64)
    sid = np.empty(1024, np.int64)
    ne = 0
    members = np.empty(batch, np.int64)
    held = np.empty(4 * batch, np.int64)
    out = np.empty((batch, 4))
    cend = cstart[1:].copy()
    sep = reach_f + 1.0
    k = 0
    while k < max_new:
        # The batch: the largest live candidates, in heap order, whose growth cannot meet. A
        # sphere grown from i lies within reach_f * f[i] of P[i] (its centre moves at most
        # (reach_f - 1) / 2 * f[i] and its radius grows at most as much) and lowers candidates
        # within (reach_f + 1) * f[i]; candidate j looks for obstacles within reach_f * f[j].
        # Candidates farther apart than (reach_f + 1) * (f[i] + f[j]) neither see each other's
        # spheres nor touch each other's free distances, so growing them at once is growing
        # them one by one in heap order. Nearer ones are held for a later batch.
        nb = 0
        nh = 0
        while nb < min(batch, max_new - k) and nh < held.shape[0]:
            i, hn = _pop_live(hk, hix, hn, f, alive, r_min)
            if i < 0:
                break
            near = False
            for q in range(nb):
                j = members[q]
                lim = sep * (f[i] + f[j])
                if (P[i, 0] - P[j, 0]) ** 2 + (P[i, 1] - P[j, 1]) ** 2 + (P[i, 2] - P[j, 2]) ** 2 < lim * lim:
                    near = True
                    break
            if near:
                held[nh] = i
                nh += 1
            else:
                members[nb] = i
                nb += 1
        if nb == 0:
            break
        _grow_batch(P, f, alive, keys, rows, origin, h, r_min, shrink, members, nb, C[:k], R[:k], head, nxt, sid, gorigin, g,
                    gdims, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, PC, PR, slo, shi, sleft, sright, sstart,
                    scount, sorder, iters, tol, reach_f, buf, S, ckeys, cstart, cend, cg, cover, out)
        for b in range(nb):
            r = out[b, 3]
            if r < 0.0:
                continue
            x, y, z = out[b, 0], out[b, 1], out[b, 2]
            C[k, 0], C[k, 1], C[k, 2] = x, y, z
            R[k] = r
            nxt, sid, ne = _grid_insert(k, x, y, z, r, head, nxt, sid, ne, gorigin, g, gdims)
            k += 1
            for q in range(nh):  # held candidates may have f above this member's reach
                j = held[q]
                gap = np.sqrt((P[j, 0] - x) ** 2 + (P[j, 1] - y) ** 2 + (P[j, 2] - z) ** 2) - r
                if gap < f[j]:
                    f[j] = gap
        for q in range(nh):  # back into the heap (or dropped: too little room left)
            j = held[q]
            if f[j] >= r_min:
                hn = _heap_push(hk, hix, hn, f[j], j)
            else:
                alive[j] = False
    return C[:k].copy(), R[:k].copy()


GRID_MAX_CELLS = 1 << 23  # cells of the sphere grid of a grown packing (8 bytes each)
# Obstacles are gathered within GROW_REACH start radii (the centre moves up to two): a smaller
# reach misses obstacles a grown sphere would meet and places more, smaller spheres; a larger
# one gathers more for little gain in leaves or coverage.
GROW_REACH = 5.0


def grown_pack(P, f, keys, origin, h, r_min, max_new, shrink, vox, prior=None, seeds=NO_SEEDS, iters=None):
    """Greedy packing whose spheres grow off the lattice into the centre of their holes.

    Like ``greedy_pack`` (largest free candidate first, ``f`` lowered in place), but each
    popped candidate's centre then climbs the free distance (see ``GROW_ITERS``) before its
    sphere is placed: a sphere touches three or four obstacles instead of one, so fewer, larger
    spheres fill the same solid.

    Candidates grow in batches of up to ``GROW_BATCH``, in parallel: the largest ones whose
    growth cannot meet (see ``_grown_pack``), so a batch gives the spheres that growing its
    members one by one gives, and the result does not depend on the number of threads. A
    candidate held back from a batch (too near a member) waits for the next one, behind
    smaller members: the order is heap order up to these swaps.

    Parameters
    ----------
    P, f, keys, origin, h, r_min, max_new, shrink
        As ``greedy_pack``; every candidate must lie inside the solid with ``f`` its exact
        free distance.
    vox : voxelize.Voxelizer
        The mesh (its triangle BVH gives the obstacles off the lattice).
    prior : (C, R, BVH) or None
        Spheres placed before (by coarser levels), obstacles too.
    seeds : tuple
        ``seed_grid``'s output: keep only the grown spheres that cover a seed (see
        ``greedy_pack``); ``NO_SEEDS`` keeps all.
    iters : int, optional
        Climbing steps per sphere (default ``GROW_ITERS``; 0 places spheres on the lattice).
    """
    lo = vox.V.min(axis=0) - h
    ext = vox.V.max(axis=0) + h - lo
    g = max(float(h), float(np.cbrt(np.prod(ext) / GRID_MAX_CELLS)))
    gdims = np.maximum(np.ceil(ext / g).astype(np.int64), 1)
    if prior is not None and len(prior[1]):
        PC, PR, sb = prior
    else:
        PC, PR, sb = np.zeros((0, 3)), np.zeros(0), BVH(np.zeros((1, 3)), np.zeros((1, 3)))
    return _grown_pack(
        np.ascontiguousarray(P), f, keys, row_index(keys), origin, float(h), float(r_min), int(max_new), float(shrink), vox.V, vox.F,
        *vox.bvh.arrays, PC, PR, *sb.arrays, lo, g, gdims, int(GROW_ITERS if iters is None else iters),
        float(GROW_TOL), float(GROW_REACH), int(GROW_BUF), int(GROW_BATCH), *seeds,
    )
