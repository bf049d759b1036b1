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

from .bvh import BVH, RAY_DIRS, STACK, inside_near, sphere_gap, tri_closest


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
def greedy_pack(P, f, keys, origin, h, r_min, max_new, shrink):
    """Greedy packing over lattice candidates.

    Parameters
    ----------
    P : (n, 3) candidate centres, lattice points of spacing ``h`` about ``origin``.
    f : (n,) initial free distance (modified in place).
    keys : (n,) sorted lattice keys of ``P`` (see ``voxelize.encode``), for neighbour lookup.
    r_min : candidates whose free distance drops below this are discarded.
    max_new : stop after this many spheres.
    shrink : relative shrink of each radius, keeps rounding from creating overlaps.

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
                base = (a << 42) | (b << 21)
                j0 = np.searchsorted(keys, base | max(lo2, 0))
                j1 = np.searchsorted(keys, base | hi2, side="right")
                for j in range(j0, j1):
                    if not alive[j]:
                        continue
                    g = np.sqrt((P[j, 0] - c[0]) ** 2 + (P[j, 1] - c[1]) ** 2 + (P[j, 2] - c[2]) ** 2) - r
                    if g < f[j]:
                        f[j] = g
                        if g < r_min:
                            alive[j] = False
    return C[:k].copy(), R[:k].copy()


@njit(cache=True, parallel=True)
def _band_free(P, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, C, R, slo, shi, sleft, sright, sstart, scount, sorder, dirs, r_min):
    n = P.shape[0]
    f = np.empty(n)
    for i in prange(n):
        stack = np.empty(STACK, np.int64)
        # cheapest test first: most band points lie in or near an existing sphere
        if R.shape[0] > 0:
            g, _ = sphere_gap(P[i], C, R, slo, shi, sleft, sright, sstart, scount, sorder, stack, np.inf)
        else:
            g = np.inf
        if g < r_min:
            f[i] = -1.0
            continue
        # surface distance only matters below g: bounded search
        d2, qx, qy, qz, tf, interior = tri_closest(P[i], V, F, tlo, thi, tleft, tright, tstart, tcount, torder, stack, g * g)
        if tf < 0:
            # no surface within g of p, but a sphere (inside the solid) is: the segment to it
            # crosses no surface, so p is inside and its free distance is g
            f[i] = g
            continue
        d = np.sqrt(d2)
        if d < r_min:
            f[i] = -1.0
            continue
        if not inside_near(P[i], qx, qy, qz, tf, interior, V, F, tlo, thi, tleft, tright, tstart, tcount, torder, stack, dirs):
            f[i] = -1.0
            continue
        f[i] = d
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
        np.ascontiguousarray(P), vox.V, vox.F, *vox.bvh.arrays, C, R, *sb.arrays, RAY_DIRS, float(r_min)
    )
