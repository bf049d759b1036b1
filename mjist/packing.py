"""Stage 3: greedy packing of non-overlapping inner spheres, largest free sphere first.

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

from .bvh import BVH, NO_SIDE, RAY_DIRS, STACK, inside_near, sphere_gap, tri_closest
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


@njit(cache=True)
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
    n = P.shape[0]
    hk = np.empty(n + 1)
    hix = np.empty(n + 1, np.int64)
    hn = 0
    for i in range(n):
        if f[i] >= r_min:
            hn = _heap_push(hk, hix, hn, f[i], i)
    alive = f >= r_min
    ns = S.shape[0]
    cend = cstart[1:].copy()
    C = np.empty((min(n, max_new), 3))
    R = np.empty(min(n, max_new))
    k = 0
    while hn > 0 and k < max_new:
        key, i, hn = _heap_pop(hk, hix, hn)
        if not alive[i]:
            continue
        if f[i] < key:  # stale entry: reinsert with the current value
            if f[i] >= r_min:
                hn = _heap_push(hk, hix, hn, f[i], i)
            else:
                alive[i] = False
            continue
        r = f[i] * (1.0 - shrink)
        c = P[i]
        if ns > 0 and not _cover_seeds(c[0], c[1], c[2], r + cover, S, ckeys, cstart, cend, origin, g):
            alive[i] = False  # every seed it reaches is covered already: it would close no gap
            continue
        C[k] = c
        R[k] = r
        k += 1
        alive[i] = False
        # lower f of every candidate within 2r (lattice box), drop the covered ones
        reach = 2.0 * f[i]
        lo0 = int(np.ceil((c[0] - reach - origin[0]) / h))
        hi0 = int(np.floor((c[0] + reach - origin[0]) / h))
        lo1 = int(np.ceil((c[1] - reach - origin[1]) / h))
        hi1 = int(np.floor((c[1] + reach - origin[1]) / h))
        lo2 = int(np.ceil((c[2] - reach - origin[2]) / h))
        hi2 = int(np.floor((c[2] + reach - origin[2]) / h))
        for a in range(max(lo0, 0), hi0 + 1):
            for b in range(max(lo1, 0), hi1 + 1):
                # the keys of one (a, b) row are contiguous in sorted order
                base = (a << (2 * KEY_BITS)) | (b << KEY_BITS)
                j0 = np.searchsorted(keys, base | max(lo2, 0))
                j1 = np.searchsorted(keys, base | hi2, side="right")
                for j in range(j0, j1):
                    if not alive[j]:
                        continue
                    gap = np.sqrt((P[j, 0] - c[0]) ** 2 + (P[j, 1] - c[1]) ** 2 + (P[j, 2] - c[2]) ** 2) - r
                    if gap < f[j]:
                        f[j] = gap
                        if gap < r_min:
                            alive[j] = False
    return C[:k].copy(), R[:k].copy()


@njit(cache=True, parallel=True)
def _band_free(P, V, F, side, tlo, thi, tleft, tright, tstart, tcount, torder, C, R, slo, shi, sleft, sright, sstart, scount, sorder, dirs, r_min):
    n = P.shape[0]
    f = np.empty(n)
    for i in prange(n):
        stack = np.empty(STACK, np.int64)
        # surface first: a band point lies within a few spacings of it, so the triangle search is
        # short, and the points too near it (a third of a band) need nothing else; then the
        # inside test where its face's side is known (no ray: bvh.inside_near), which drops the
        # outside third; the sphere search, bounded by the surface distance; the ray-cast inside
        # test last, for the few candidates left whose closest point is on an edge or a crossed face.
        d2, qx, qy, qz, tf, interior = tri_closest(P[i], V, F, tlo, thi, tleft, tright, tstart, tcount, torder, stack, np.inf)
        d = np.sqrt(d2)
        if tf < 0 or d < r_min:
            f[i] = -1.0
            continue
        known = interior and side[tf] != NO_SIDE
        if known and not inside_near(P[i], qx, qy, qz, tf, interior, side, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, stack, dirs):
            f[i] = -1.0
            continue
        g = d
        if R.shape[0] > 0:
            g, _ = sphere_gap(P[i], C, R, slo, shi, sleft, sright, sstart, scount, sorder, stack, d)
        if g < r_min or (not known and not inside_near(P[i], qx, qy, qz, tf, interior, side, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, stack, dirs)):
            f[i] = -1.0
            continue
        f[i] = g
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
