"""Contact selection: which of many candidate contacts to write when a pair may write ``k``.

MuJoCo takes at most ``mj_maxContact`` contacts per pair. The choice keeps the deepest
candidate, then repeatedly the one farthest from those already picked (farthest-point
sampling), so the written contacts span the contact region instead of piling up at its
deepest spot. Ties go to the deeper candidate, then the lower index: the choice depends only
on the candidates, not on threads or history.
"""
from __future__ import annotations

import math

from numba import njit


@njit(cache=True)
def spread(points, col, cval, n, k_max, chosen, dmin):
    """Pick up to ``k_max`` of the ``n`` candidates into ``chosen``; returns the count.

    Parameters
    ----------
    points : float64 (>= n, w)
        Per candidate, its contact point at columns ``col, col + 1, col + 2``.
    cval : float64 (>= n,)
        Per candidate, its distance (smaller is deeper).
    chosen : int64 (>= k_max,)
        Receives the picks, deepest first.
    dmin : float64 (>= n,)
        Scratch: squared distance to the nearest pick (-1 once picked).
    """
    if n == 0 or k_max <= 0:
        return 0
    first = 0
    for i in range(1, n):
        if cval[i] < cval[first]:
            first = i
    chosen[0] = first
    for i in range(n):
        dmin[i] = math.inf
    dmin[first] = -1.0
    m = 1
    while m < min(n, k_max):
        last = chosen[m - 1]
        lx = points[last, col]
        ly = points[last, col + 1]
        lz = points[last, col + 2]
        pick = -1
        for i in range(n):
            if dmin[i] < 0.0:
                continue
            x = points[i, col] - lx
            y = points[i, col + 1] - ly
            z = points[i, col + 2] - lz
            dmin[i] = min(dmin[i], x * x + y * y + z * z)
            if pick < 0 or dmin[i] > dmin[pick] or (dmin[i] == dmin[pick] and cval[i] < cval[pick]):
                pick = i
        if pick < 0:
            break
        chosen[m] = pick
        dmin[pick] = -1.0
        m += 1
    return m
