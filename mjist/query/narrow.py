"""Surface narrow phase: the IST's contact groups measured on the meshes themselves.

A traversal with threshold ``margin + ε_A + ε_B`` finds every place where the two surfaces can
be within ``margin`` of each other (each such place has a leaf pair below that threshold, so it
lies in a contact group). The groups with the smallest IST distances are then measured on the
meshes (``geometry.surface.local_distance``, started at the group's deepest leaf pair's contact
point) both ways (B's points in A, A's points in B): a signed distance, a point and a normal of
the true surfaces. Which groups are measured is decided by the surfaces too (``screen``: a few
grid queries at each group's start point), not by the spheres' distances. The MuJoCo hook and
``Query`` share these kernels.

What is certified and what is measured: a measured value is the signed distance of a point of
B's surface to A's surface, so a positive one is never below the meshes' true distance and a
negative one is a true depth of that point; that a descent reaches its group's local minimum is
measured (docs/mujoco.md), not proved.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..geometry import surface as sf
from . import traverse as tv

# surface queries of A per measured group at most (all but the first are walks over the
# meshes' adjacency, a few µs each): more reach the surfaces' closest points from farther
# starts (coarser trees), at a linear cost ...
ITERS = 30
# ... stopping once a step would move less than this fraction of ε_A + ε_B
TOL = 1e-3
# contacts closer than this fraction of ε_A + ε_B are one: groups whose descents met at one point
SAME = 1e-2
# a group's row: ``traverse.leaf_geometry``'s (normal at 0:3, point at 9:12 become the measured
# ones), then the way it was measured (``surface.contact_distance``)
WAY = tv.GEOM_W
GEOM_W = tv.GEOM_W + 1


@njit(cache=True)
def deepest(cand, cval, n, k):
    """Moves the ``k`` groups with the smallest IST distances to the front of ``cand`` (and
    ``cval``), in order, and returns their count (≤ n); ties keep the traversal's order."""
    k = min(n, k)
    for j in range(k):
        b = j
        for i in range(j + 1, n):
            if cval[i] < cval[b]:
                b = i
        if b != j:
            cval[j], cval[b] = cval[b], cval[j]
            for c in range(4):
                cand[j, c], cand[b, c] = cand[b, c], cand[j, c]
    return k


@njit(cache=True)
def screen(SA, SB, Na, Nb, xf, cand, cval, n, keep, geom, tmp, sst):
    """Moves the ``keep`` groups of the ``n`` that are deepest by the surfaces to the front of
    ``cand`` and ``cval`` and returns their count: each group's IST distance in ``cval`` is
    replaced by the surfaces' distance at its deepest leaf pair's contact point
    (``surface.start_distance``: a few grid queries, no descent), so that the groups measured
    are picked by the meshes rather than by the spheres (whose distances are up to ε_A + ε_B
    off the surfaces'). With ``n`` ≤ ``keep`` all are kept as they are."""
    if n <= keep:
        return n
    for i in range(n):
        g = geom[i]
        tv.leaf_geometry(Na, Nb, xf, cand[i, 2], cand[i, 3], g)
        cval[i] = sf.start_distance(SA, SB, xf, g[9], g[10], g[11], sst, tmp)
    return deepest(cand, cval, n, keep)


@njit(cache=True)
def measure(SA, SB, Na, Nb, xf, cand, n, below, eps, geom, sval, tmp, res, sst, ways):
    """Each of the ``n`` groups measured on the surfaces ``SA``, ``SB`` (``surface.unpack``),
    from its deepest leaf pair's contact point. The groups closer than ``below`` are compacted to
    the front of ``cand``, ``geom`` (normal at 0:3, point at 9:12, A's frame) and ``sval``; returns
    their count and the count of groups whose surface query failed (those are dropped)."""
    # a typed zero: typing the loop's call with a literal 0 first would compile measure_from twice
    m = np.int64(0)
    failed = 0
    for i in range(n):
        g = geom[i]
        tv.leaf_geometry(Na, Nb, xf, cand[i, 2], cand[i, 3], g)
        m, ok = measure_from(SA, SB, xf, g[9], g[10], g[11], below, eps, i, cand, geom, sval, m, tmp, res, sst,
                             ways)
        failed += not ok
    return m, failed


@njit(cache=True)
def measure_from(SA, SB, xf, x, y, z, below, eps, src, cand, geom, sval, m, tmp, res, sst, ways):
    """The surfaces' distance measured from the start point ``(x, y, z)`` (A's frame,
    ``surface.contact_distance`` the ``ways`` given) and, when it is below ``below``, kept as row
    ``m`` of ``geom`` (normal at 0:3, the way it was measured at ``WAY``, point at 9:12), ``sval``
    and ``cand`` (a copy of ``cand[src]``). Returns the count of rows kept and whether the surface
    query succeeded."""
    way = sf.contact_distance(SA, SB, xf, x, y, z, ITERS, eps, TOL * eps, sst, tmp, res, ways)
    if way == 0:
        return m, False
    if not res[0] < below:
        return m, True
    row = geom[m]
    for r in range(3):
        row[r] = res[4 + r]
        row[9 + r] = res[1 + r]
    for c in range(4):
        cand[m, c] = cand[src, c]
    row[WAY] = way
    sval[m] = res[0]
    return m + 1, True


@njit(cache=True)
def distinct(geom, chosen, k, eps):
    """Drops from ``chosen[:k]`` the picks whose point (``geom[:, 9:12]``) lies within
    ``SAME * eps`` of an earlier pick's, keeping the order; returns the count left."""
    same2 = (SAME * eps) ** 2
    kk = 0
    for j in range(k):
        i = chosen[j]
        dup = False
        for jj in range(kk):
            q = chosen[jj]
            d2 = (geom[i, 9] - geom[q, 9]) ** 2 + (geom[i, 10] - geom[q, 10]) ** 2 + (geom[i, 11] - geom[q, 11]) ** 2
            if d2 <= same2:
                dup = True
                break
        if not dup:
            chosen[kk] = i
            kk += 1
    return kk


@njit(cache=True)
def smallest(sval, m):
    """Index of the smallest of ``sval[:m]`` (-1 when ``m`` is 0)."""
    if m == 0:
        return -1
    j = 0
    for i in range(1, m):
        if sval[i] < sval[j]:
            j = i
    return j
