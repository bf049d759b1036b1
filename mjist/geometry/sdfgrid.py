"""A sparse narrow-band grid over a closed surface: each node knows its nearest triangle, so a
point near the surface finds its closest point among its cell's eight corners' triangles, in
O(1) instead of a BVH descent (numba).

The grid's nodes lie ``h`` apart; nodes are stored in bricks of ``BRICK``³ cells
(``(BRICK + 1)``³ nodes each, the shared faces repeated so that a cell's eight corners are in one
brick) and only for the bricks within ``band`` of the surface. A dense table over the surface's
box holds each brick's row (-1: no brick). Each node holds the face nearest to it (-1: none
within the band's reach). The closest point of a point ``p`` lies on the face nearest to one of
its cell's corners whenever the cells are small against the faces (a face nearest to ``p`` is
within a cell diagonal of being nearest to the corner next to it); when it does not, the
corners' faces still give a point of the surface, so the distance found is never below the true
one. The narrow phase steps on these answers and takes its final one from the BVH.

A grid is three flat arrays, so the MuJoCo hook can read it from addresses: ``header``
(float64: origin, ``h``, the brick table's dims), ``table`` (int32, one entry per brick position,
C order ``(nz, ny, nx)``) and ``faces`` (int32, ``NODES`` per brick, x fastest). ``layout`` says
which bricks a surface needs and where their nodes are (``node_point``); the faces come from the
surface's own closest-point query (``geometry.surface.add_grid``).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

BRICK = 4  # cells per brick side: larger bricks store more nodes far from the surface, smaller ones repeat more shared faces
NB = BRICK + 1  # nodes per brick side
NODES = NB ** 3
HDR_W = 7  # header words: origin (3), h, table dims (3)


@njit(cache=True)
def _mark(TRI, lo, inv, dims, pad, mark):
    """Marks every brick position within ``pad`` (grid units) of a triangle's box."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    b0 = np.empty(3, np.int64)
    b1 = np.empty(3, np.int64)
    for t in range(TRI.shape[0]):
        T = TRI[t]
        for k in range(3):
            a = min(T[k], T[3 + k], T[6 + k])
            c = max(T[k], T[3 + k], T[6 + k])
            b0[k] = max(0, int(math.floor(((a - lo[k]) * inv - pad) / BRICK)))
            b1[k] = min(dims[k] - 1, int(math.floor(((c - lo[k]) * inv + pad) / BRICK)))
        for z in range(b0[2], b1[2] + 1):
            for y in range(b0[1], b1[1] + 1):
                for x in range(b0[0], b1[0] + 1):
                    mark[(z * ny + y) * nx + x] = 1
    return nx * ny * nz


@njit(cache=True)
def node_point(header, pos, k):
    """Position of node ``k`` (0 ≤ k < ``NODES``, x fastest) of the brick at table position ``pos``."""
    nx, ny = int(header[4]), int(header[5])
    h = header[3]
    bx = pos % nx
    by = (pos // nx) % ny
    bz = pos // (nx * ny)
    k0 = k % NB
    k1 = (k // NB) % NB
    k2 = k // (NB * NB)
    return (header[0] + (bx * BRICK + k0) * h, header[1] + (by * BRICK + k1) * h,
            header[2] + (bz * BRICK + k2) * h)


def layout(TRI, h: float, band: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bricks a grid of spacing ``h`` needs to hold every point within ``band`` of the
    triangles ``TRI (nf, 9)`` (corners a, b, c).

    Returns
    -------
    header : (HDR_W,) float64
        Origin, ``h``, the brick table's dims.
    table : (nz * ny * nx,) int32
        Each brick position's row in the faces (-1: none).
    where : (nbricks,) int64
        Each brick's table position, in row order.
    """
    if not (h > 0 and math.isfinite(h)) or not (band >= 0 and math.isfinite(band)):
        raise ValueError(f"grid spacing {h!r} and band {band!r} must be finite, spacing > 0")
    TRI = np.ascontiguousarray(TRI, np.float64).reshape(-1, 9)
    if TRI.shape[0] == 0:
        raise ValueError("the surface has no faces: nothing to grid")
    pad = band / h + 1.0  # grid units: the band, and one cell so that a point's cell lies wholly inside
    lo = TRI.reshape(-1, 3).min(axis=0) - (pad + 1.0) * h
    hi = TRI.reshape(-1, 3).max(axis=0) + (pad + 1.0) * h
    dims = np.maximum(np.ceil((hi - lo) / (BRICK * h)).astype(np.int64), 1)
    count = math.prod(int(d) for d in dims)
    if count > 2 ** 31 - 1:
        raise ValueError(f"a grid of spacing {h:g} over a box of {hi - lo} needs {count} table entries: "
                         "use a coarser spacing")
    mark = np.zeros(count, np.uint8)
    _mark(TRI, lo, 1.0 / h, dims, pad, mark)
    where = np.flatnonzero(mark).astype(np.int64)
    table = np.full(count, -1, np.int32)
    table[where] = np.arange(where.size, dtype=np.int32)
    header = np.array([lo[0], lo[1], lo[2], h, dims[0], dims[1], dims[2]], np.float64)
    return header, table, where


def empty() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grid with no bricks (``cell`` always answers -1): header, table, faces."""
    return np.zeros(HDR_W), np.zeros(0, np.int32), np.zeros(0, np.int32)


@njit(cache=True)
def cell(header, table, x, y, z):
    """Index in ``faces`` of the first corner of the cell holding ``(x, y, z)`` (its other
    corners at ``+ CORNER``), or -1 when the cell's brick is not stored."""
    h = header[3]
    if not h > 0.0:
        return -1
    u = (x - header[0]) / h
    v = (y - header[1]) / h
    w = (z - header[2]) / h
    if not (u >= 0.0 and v >= 0.0 and w >= 0.0):
        return -1
    i, j, k = int(u), int(v), int(w)
    nx, ny, nz = int(header[4]), int(header[5]), int(header[6])
    bi, bj, bk = i // BRICK, j // BRICK, k // BRICK
    if bi >= nx or bj >= ny or bk >= nz:
        return -1
    b = table[(bk * ny + bj) * nx + bi]
    if b < 0:
        return -1
    return b * NODES + ((k - bk * BRICK) * NB + (j - bj * BRICK)) * NB + (i - bi * BRICK)


CORNER = (0, 1, NB, NB + 1, NB * NB, NB * NB + 1, NB * NB + NB, NB * NB + NB + 1)  # a cell's corners from its first
