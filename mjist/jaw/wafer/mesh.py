"""The wafer's mesh from its two height fields: one closed, consistently wound shell by
construction (a top and a bottom triangle pair per grid square, a vertical wall along the
squares' outline), which cannot self-intersect where the top field lies above the bottom one."""
from __future__ import annotations

import numpy as np


def _squares(valid) -> np.ndarray:
    """The grid squares whose four nodes are ``valid``, as the largest edge-connected set with no
    two squares meeting only at a corner (that would make a non-manifold vertex)."""
    from scipy import ndimage

    sq = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
    for _ in range(100):  # two squares meeting only at a corner: drop one
        a, b, c, d = sq[:-1, :-1], sq[1:, :-1], sq[:-1, 1:], sq[1:, 1:]
        diag = (a & d & ~b & ~c)
        anti = (b & c & ~a & ~d)
        if not (diag.any() or anti.any()):
            break
        sq[:-1, :-1] &= ~diag
        sq[1:, :-1] &= ~anti
    lab, n = ndimage.label(sq)  # 4-connected
    if n == 0:
        raise ValueError("the wafer is empty: the arches leave no room for it over the dentition")
    sizes = ndimage.sum(sq, lab, index=np.arange(1, n + 1))
    return lab == 1 + int(np.argmax(sizes))


def _halves(h, corners, up: bool) -> np.ndarray:
    """Two triangles per square (node indices ``corners`` = a, b, c, d; heights ``h`` per node),
    split along its shorter diagonal in 3D: a steep slope split the other way folds into a
    sawtooth of creases. Counter-clockwise in (u, v) when ``up``."""
    a, b, c, d = corners
    ad = np.abs(h[a] - h[d]) <= np.abs(h[b] - h[c])
    t1 = np.where(ad[:, None], np.stack([a, b, d], 1), np.stack([a, b, c], 1))
    t2 = np.where(ad[:, None], np.stack([a, d, c], 1), np.stack([b, d, c], 1))
    T = np.concatenate([t1, t2])
    return T if up else T[:, ::-1]


def _walls(sq, idx, ni) -> list:
    """Wall quads along the outline of the squares ``sq``: an edge p -> q (counter-clockwise
    around the squares) gets p_top, p_bot, q_bot, q_top facing outwards (bottom nodes are the top
    ones + ``ni``)."""
    walls = []
    pad = np.pad(sq, 1)
    for (oi, oj), (p, q) in (((0, -1), ((0, 0), (1, 0))), ((1, 0), ((1, 0), (1, 1))),
                             ((0, 1), ((1, 1), (0, 1))), ((-1, 0), ((0, 1), (0, 0)))):
        out = sq & ~pad[1 + oi:1 + oi + sq.shape[0], 1 + oj:1 + oj + sq.shape[1]]
        ei, ej = np.nonzero(out)
        P = idx[ei + p[0], ej + p[1]]
        Q = idx[ei + q[0], ej + q[1]]
        walls += [np.stack([P, P + ni, Q + ni], 1), np.stack([P, Q + ni, Q], 1)]
    return walls


def closed_mesh(top, bottom, valid, grid) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh (world vertices, faces) from the height fields ``top`` and
    ``bottom`` over the squares of ``valid`` nodes (``_squares``)."""
    sq = _squares(valid)
    used = np.zeros(valid.shape, bool)
    for di in (0, 1):
        for dj in (0, 1):
            used[di:di + sq.shape[0], dj:dj + sq.shape[1]] |= sq
    idx = -np.ones(valid.shape, np.int64)
    ni = int(used.sum())
    idx[used] = np.arange(ni)
    U, W = grid.nodes()
    top_v = np.stack([U[used], W[used], top[used]], axis=1)
    bot_v = np.stack([U[used], W[used], bottom[used]], axis=1)
    V = grid.world(np.vstack([top_v, bot_v]))
    si, sj = np.nonzero(sq)
    corners = (idx[si, sj], idx[si + 1, sj], idx[si, sj + 1], idx[si + 1, sj + 1])
    # counter-clockwise in (u, v) faces +w: up on the top face, down on the bottom one
    top_f = _halves(top[used], corners, True)
    bot_f = _halves(bottom[used], corners, False) + ni
    # (u left, v anterior, w up) is left-handed: the windings above face inwards, so reverse them
    F = np.concatenate([top_f, bot_f, *_walls(sq, idx, ni)])[:, ::-1]
    return V, np.ascontiguousarray(F)
