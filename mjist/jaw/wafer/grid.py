"""The wafer's height-field grid: surfaces seen along up, and grey morphology by a ball.

A ``Grid`` lies in the maxillary arch's frame (u left, v anterior, w up). A surface seen along
up becomes a height field by dropping a ball on its samples (``Grid.drop``: the surface offset
by the ball's radius, as a ball rolled over it sees it); ``erode`` and ``dilate`` are grey
morphology by a ball (or a flat disk), the opening that makes the wafer printable.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

COARSE = 2.5e-4  # m: grid of the neighbourhood minima (``lowest_near``): coarser is faster, blurs cusp levels more


def basis(up, anterior) -> np.ndarray:
    """Rows u (left), v (anterior), w (up) of the arch frame from its up and anterior directions."""
    w = np.asarray(up, float) / np.linalg.norm(up)
    v = np.asarray(anterior, float) - (np.asarray(anterior, float) @ w) * w
    v /= np.linalg.norm(v)
    return np.stack([np.cross(w, v), v, w])


def surface_samples(V, F, spacing: float, keep=None) -> np.ndarray:
    """Points on the faces ``F[keep]`` no farther than ``spacing`` from each other along an edge:
    a barycentric grid per face, finer on longer faces."""
    V = np.asarray(V, float)
    F = np.asarray(F)[keep] if keep is not None else np.asarray(F)
    if len(F) == 0:
        return np.empty((0, 3))
    T = V[F]
    longest = np.max(np.linalg.norm(T - np.roll(T, 1, axis=1), axis=2), axis=1)
    n = np.maximum(1, np.ceil(longest / spacing).astype(np.int64))
    out = []
    for k in np.unique(n):
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        sel = i + j <= k
        a, b = i[sel] / k, j[sel] / k
        W = np.stack([1.0 - a - b, a, b], axis=1)  # (m, 3)
        out.append(np.einsum("mj,fjd->fmd", W, T[n == k]).reshape(-1, 3))
    return np.concatenate(out)


@njit(cache=True)
def _drop(pu, pv, pw, u0, v0, h, nu, nv, rho, sign, out):
    """Height field of a ball of radius ``rho`` resting on points from below (``sign`` -1) or
    from above (+1).

    ``out[i, j]`` at node ``(u0 + i h, v0 + j h)`` becomes ``min_p (w_p - s)`` (sign -1) or
    ``max_p (w_p + s)`` (+1) over points within ``rho`` horizontally, ``s = sqrt(rho² - d²)``:
    the surface offset by ``rho`` along the vertical, as a ball rolled over it sees it.
    """
    r2 = rho * rho
    for k in range(pu.shape[0]):
        fu = (pu[k] - u0) / h
        fv = (pv[k] - v0) / h
        i0 = max(int(np.ceil(fu - rho / h)), 0)
        i1 = min(int(np.floor(fu + rho / h)), nu - 1)
        j0 = max(int(np.ceil(fv - rho / h)), 0)
        j1 = min(int(np.floor(fv + rho / h)), nv - 1)
        for i in range(i0, i1 + 1):
            du = u0 + i * h - pu[k]
            for j in range(j0, j1 + 1):
                dv = v0 + j * h - pv[k]
                d2 = du * du + dv * dv
                if d2 > r2:
                    continue
                s = np.sqrt(r2 - d2)
                if sign < 0:
                    val = pw[k] - s
                    if val < out[i, j]:
                        out[i, j] = val
                else:
                    val = pw[k] + s
                    if val > out[i, j]:
                        out[i, j] = val


def _disk(h, radius):
    """A disk footprint of ``radius`` on a grid of spacing ``h`` and each offset's squared length."""
    k = int(np.floor(radius / h))
    a = np.arange(-k, k + 1) * h
    d2 = a[:, None] ** 2 + a[None, :] ** 2
    return d2 <= radius * radius, d2


class Grid:
    """The node grid in the arch frame: ``B`` rows u, v, w; origin; spacing; shape."""

    def __init__(self, B, origin, lo, hi, h):
        self.B, self.origin, self.h = B, np.asarray(origin, float), float(h)
        self.u0, self.v0 = float(lo[0]), float(lo[1])
        self.shape = (int(np.ceil((hi[0] - lo[0]) / h)) + 1, int(np.ceil((hi[1] - lo[1]) / h)) + 1)

    def local(self, P):
        return (np.asarray(P, float) - self.origin) @ self.B.T

    def world(self, U):
        return self.origin + np.asarray(U, float) @ self.B

    def to_grid(self) -> np.ndarray:
        """4x4: world -> the grid's frame."""
        G = np.eye(4)
        G[:3, :3], G[:3, 3] = self.B, -self.B @ self.origin
        return G

    def index(self, L):
        """The node nearest each point of local coordinates ``L (n, 3)``: ``i, j`` and whether it is on the grid."""
        i = np.rint((L[:, 0] - self.u0) / self.h).astype(np.int64)
        j = np.rint((L[:, 1] - self.v0) / self.h).astype(np.int64)
        return i, j, (i >= 0) & (i < self.shape[0]) & (j >= 0) & (j < self.shape[1])

    def over(self, P, mask) -> np.ndarray:
        """Which points ``P`` (world) lie over ``mask``."""
        i, j, ok = self.index(self.local(P))
        ok[ok] = mask[i[ok], j[ok]]
        return ok

    def nodes(self):
        i, j = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return self.u0 + i * self.h, self.v0 + j * self.h

    def drop(self, P, rho, sign):
        """``_drop`` of a ball of radius ``rho`` on the world points ``P``."""
        return self.drop_local(self.local(P), rho, sign)

    def drop_local(self, L, rho, sign):
        out = np.full(self.shape, np.inf if sign < 0 else -np.inf)
        _drop(np.ascontiguousarray(L[:, 0]), np.ascontiguousarray(L[:, 1]), np.ascontiguousarray(L[:, 2]),
              self.u0, self.v0, self.h, self.shape[0], self.shape[1], float(rho), int(sign), out)
        return out


@njit(cache=True, parallel=True)
def _ball_min(H, di, dj, s, out):
    """``out[i, j] = min_k H[i + di[k], j + dj[k]] - s[k]`` (offsets off the grid count as +inf)."""
    ni, nj = H.shape
    for i in prange(ni):
        for j in range(nj):
            best = np.inf
            for k in range(di.shape[0]):
                a = i + di[k]
                b = j + dj[k]
                if a < 0 or a >= ni or b < 0 or b >= nj:
                    continue
                val = H[a, b] - s[k]
                if val < best:
                    best = val
            out[i, j] = best


def erode(H, grid, radius, flat: bool = False):
    """Grey erosion by a ball from above, ``min_q (H(q) - sqrt(r² - |p - q|²))`` over ``|p - q| ≤ r``
    (``flat``: by a disk, ``min_q H(q)``); ``grid`` is a ``Grid`` or a spacing."""
    foot, d2 = _disk(getattr(grid, "h", grid), radius)
    di, dj = np.nonzero(foot)
    k = foot.shape[0] // 2
    s = np.zeros(len(di)) if flat else np.sqrt(np.maximum(radius * radius - d2[di, dj], 0.0))
    out = np.empty(H.shape)
    _ball_min(np.ascontiguousarray(H, dtype=np.float64), (di - k).astype(np.int64), (dj - k).astype(np.int64), s, out)
    return out


def dilate(H, grid, radius, flat: bool = False):
    """Grey dilation by a ball from below: ``max_q (H(q) + sqrt(r² - |p - q|²))``."""
    return -erode(-np.asarray(H, float), grid, radius, flat)


def dilate_mask(mask, grid, radius):
    """Nodes within ``radius`` of ``mask`` (an exact Euclidean distance transform)."""
    from scipy import ndimage

    return ndimage.distance_transform_edt(~mask, sampling=grid.h) <= radius + 1e-12


def erode_mask(mask, grid, radius):
    """Nodes of ``mask`` farther than ``radius`` from outside it (the grid's edge counts as outside)."""
    from scipy import ndimage

    return ndimage.distance_transform_edt(np.pad(mask, 1), sampling=grid.h)[1:-1, 1:-1] > radius + 1e-12


def lowest_near(H, grid, radius):
    """``min H`` within about ``radius`` of each node: on blocks of ``COARSE``, then back on the grid."""
    f = max(1, int(round(COARSE / grid.h)))
    ni, nj = H.shape
    P = np.full((-(-ni // f) * f, -(-nj // f) * f), np.inf)
    P[:ni, :nj] = H
    Hc = P.reshape(P.shape[0] // f, f, P.shape[1] // f, f).min(axis=(1, 3))
    Ec = erode(Hc, grid.h * f, radius, flat=True)
    return np.repeat(np.repeat(Ec, f, axis=0), f, axis=1)[:ni, :nj]
