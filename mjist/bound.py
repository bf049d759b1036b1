"""Stage 5: the certified error bound ε of an inner sphere set.

ε is an upper bound of the one-sided Hausdorff distance from the mesh surface to the
union U of the leaf spheres: every surface point is within ε of some sphere. With both
objects' spheres inside their meshes, the true distance between two meshes then lies in
``[d_IST - ε_A - ε_B, d_IST]``.

How it is computed (a rigorous bound, not an estimate). Let ``g(x) = dist(x, U)``.
Every triangle is split recursively into four; for a sub-triangle T with vertices v_i:

* ``g`` is 1-Lipschitz, so ``max_T g <= max_i g(v_i) + cov(T)``, where ``cov(T)`` is
  the covering radius of T by its vertices (circumradius if acute, half the longest
  edge otherwise);
* for any single sphere (c, r), ``|x - c| - r`` is convex, so its maximum over T is
  attained at a vertex: ``max_T g <= min_j max_i (|v_i - c_j| - r_j)`` over the spheres
  nearest to the vertices.

The smaller of the two is T's bound ``UB(T)``; a sub-triangle is split again until
``UB(T) <= target`` or it is smaller than ``min_size``. ε is the maximum ``UB`` over
the final sub-triangles, and ``max_i g(v_i)`` over all evaluated vertices is a lower
bound of the true Hausdorff distance (reported so the bound's tightness is visible).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .bvh import BVH, STACK, sphere_gap

SUB_STACK = 256


@njit(cache=True, inline="always")
def _cov(a, b, c):
    ab = b - a
    ac = c - a
    bc = c - b
    la = bc @ bc
    lb = ac @ ac
    lc = ab @ ab
    longest = max(la, lb, lc)
    if 2.0 * longest >= la + lb + lc:  # right or obtuse: farthest point is the long edge's midpoint
        return 0.5 * np.sqrt(longest)
    cr = np.cross(ab, ac)
    area2 = cr @ cr
    return np.sqrt(la * lb * lc / (4.0 * area2))


@njit(cache=True, inline="always")
def _gap_at(p, C, R, lo, hi, left, right, start, count, order, stack):
    return sphere_gap(p, C, R, lo, hi, left, right, start, count, order, stack, np.inf)


@njit(cache=True)
def _certify_triangle(a0, b0, c0, C, R, lo, hi, left, right, start, count, order, target, min_size, stack, seeds, emit):
    """Bound for one triangle. Returns (ub, lb, n_bad); writes bad centroids to seeds if emit.

    Stack entries carry their vertices, the gaps and nearest spheres there, and the parent's
    bound (a sub-triangle's bound never exceeds its parent's: it lies inside it).
    """
    P = np.empty((SUB_STACK, 3, 3))
    G = np.empty((SUB_STACK, 3))
    J = np.empty((SUB_STACK, 3), np.int64)
    UBP = np.empty(SUB_STACK)
    P[0, 0] = a0
    P[0, 1] = b0
    P[0, 2] = c0
    for v in range(3):
        G[0, v], J[0, v] = _gap_at(P[0, v], C, R, lo, hi, left, right, start, count, order, stack)
    UBP[0] = np.inf
    sp = 1
    ub_max = 0.0
    lb_max = 0.0
    nbad = 0
    mid = np.empty((3, 3))
    gm = np.empty(3)
    jm = np.empty(3, np.int64)
    while sp > 0:
        sp -= 1
        a = P[sp, 0].copy()
        b = P[sp, 1].copy()
        c = P[sp, 2].copy()
        g0, g1, g2 = G[sp, 0], G[sp, 1], G[sp, 2]
        j0, j1, j2 = J[sp, 0], J[sp, 1], J[sp, 2]
        cov = _cov(a, b, c)
        gmax = max(g0, g1, g2)
        lb_max = max(lb_max, gmax)
        ub = min(gmax + cov, UBP[sp])
        for v in range(3):
            j = j0 if v == 0 else (j1 if v == 1 else j2)
            if j < 0:
                continue
            m = 0.0
            for w in range(3):
                p = a if w == 0 else (b if w == 1 else c)
                d = np.sqrt((p[0] - C[j, 0]) ** 2 + (p[1] - C[j, 1]) ** 2 + (p[2] - C[j, 2]) ** 2) - R[j]
                m = max(m, d)
            ub = min(ub, m)
        if ub <= target or cov <= min_size or sp + 4 > SUB_STACK:
            ub_max = max(ub_max, ub)
            if ub > target:
                if emit:
                    seeds[nbad] = (a + b + c) / 3.0
                nbad += 1
            continue
        mid[0] = 0.5 * (a + b)
        mid[1] = 0.5 * (b + c)
        mid[2] = 0.5 * (c + a)
        for v in range(3):
            gm[v], jm[v] = _gap_at(mid[v], C, R, lo, hi, left, right, start, count, order, stack)
        # children: (a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)
        P[sp, 0] = a
        P[sp, 1] = mid[0]
        P[sp, 2] = mid[2]
        G[sp, 0], G[sp, 1], G[sp, 2] = g0, gm[0], gm[2]
        J[sp, 0], J[sp, 1], J[sp, 2] = j0, jm[0], jm[2]
        P[sp + 1, 0] = mid[0]
        P[sp + 1, 1] = b
        P[sp + 1, 2] = mid[1]
        G[sp + 1, 0], G[sp + 1, 1], G[sp + 1, 2] = gm[0], g1, gm[1]
        J[sp + 1, 0], J[sp + 1, 1], J[sp + 1, 2] = jm[0], j1, jm[1]
        P[sp + 2, 0] = mid[2]
        P[sp + 2, 1] = mid[1]
        P[sp + 2, 2] = c
        G[sp + 2, 0], G[sp + 2, 1], G[sp + 2, 2] = gm[2], gm[1], g2
        J[sp + 2, 0], J[sp + 2, 1], J[sp + 2, 2] = jm[2], jm[1], j2
        P[sp + 3, 0] = mid[0]
        P[sp + 3, 1] = mid[1]
        P[sp + 3, 2] = mid[2]
        G[sp + 3, 0], G[sp + 3, 1], G[sp + 3, 2] = gm[0], gm[1], gm[2]
        J[sp + 3, 0], J[sp + 3, 1], J[sp + 3, 2] = jm[0], jm[1], jm[2]
        for q in range(4):
            UBP[sp + q] = ub
        sp += 4
    return ub_max, lb_max, nbad


@njit(cache=True, parallel=True)
def _certify_all(V, F, faces, C, R, lo, hi, left, right, start, count, order, target, min_size):
    nf = faces.shape[0]
    ub = np.empty(nf)
    lb = np.empty(nf)
    nbad = np.empty(nf, np.int64)
    dummy = np.empty((0, 3))
    for t in prange(nf):
        f = faces[t]
        stack = np.empty(STACK, np.int64)
        ub[t], lb[t], nbad[t] = _certify_triangle(
            V[F[f, 0]], V[F[f, 1]], V[F[f, 2]], C, R, lo, hi, left, right, start, count, order,
            target, min_size, stack, dummy, False,
        )
    return ub, lb, nbad


@njit(cache=True, parallel=True)
def _emit_bad(V, F, faces, offsets, C, R, lo, hi, left, right, start, count, order, target, min_size, seeds):
    for t in prange(faces.shape[0]):
        f = faces[t]
        stack = np.empty(STACK, np.int64)
        _certify_triangle(
            V[F[f, 0]], V[F[f, 1]], V[F[f, 2]], C, R, lo, hi, left, right, start, count, order,
            target, min_size, stack, seeds[offsets[t]:offsets[t + 1]], True,
        )


def certify(V, F, C, R, target: float, min_size: float, want_seeds: bool = False, bvh: BVH | None = None):
    """Certified upper bound of the surface-to-spheres gap.

    Parameters
    ----------
    V, F : mesh vertices and faces.
    C, R : sphere centres and radii.
    target : stop refining a sub-triangle once its bound is below this.
    min_size : never refine a sub-triangle whose covering radius is below this.
    want_seeds : also return the centroids of sub-triangles whose bound exceeds ``target``.

    Returns
    -------
    ub : float, the certified bound ε (max over sub-triangles).
    lb : float, a lower bound of the true one-sided Hausdorff distance.
    seeds : (k, 3) centroids of the regions still above ``target`` (empty unless asked).
    """
    ub, lb, seeds = certify_faces(V, F, np.arange(len(F), dtype=np.int64), C, R, target, min_size, want_seeds, bvh)
    return float(ub.max()), float(lb.max()), seeds


def certify_faces(V, F, faces, C, R, target: float, min_size: float, want_seeds: bool = False, bvh: BVH | None = None):
    """``certify`` on the triangles ``faces`` only, per triangle.

    Adding spheres only shrinks gaps, so a triangle certified below ``target`` stays so: the
    builder re-certifies only the triangles still open at the previous lattice level.

    Returns
    -------
    ub, lb : (len(faces),) per-triangle bound and lower bound.
    seeds : (k, 3) centroids of the sub-triangles still above ``target`` (empty unless asked).
    """
    if len(R) == 0:
        raise ValueError("no spheres to certify")
    if bvh is None:
        bvh = BVH.of_spheres(C, R)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    ub, lb, nbad = _certify_all(V, F, faces, C, R, *bvh.arrays, float(target), float(min_size))
    seeds = np.empty((0, 3))
    if want_seeds and nbad.sum() > 0:
        bad = np.flatnonzero(nbad)
        offsets = np.concatenate([[0], np.cumsum(nbad[bad])]).astype(np.int64)
        seeds = np.empty((offsets[-1], 3))
        _emit_bad(V, F, faces[bad], offsets, C, R, *bvh.arrays, float(target), float(min_size), seeds)
    return ub, lb, seeds


def tight_bound(V, F, C, R, rel_tol: float = 0.05, bvh: BVH | None = None, known: float = np.inf):
    """The certified ε, refined until it is within ``rel_tol`` of its own lower bound.

    ``known`` is a bound certified earlier for a subset of these spheres (still valid:
    adding spheres only shrinks gaps); every certificate is an upper bound, so the
    smallest one is returned. Returns ``(eps, lower)``: ``lower <= true gap <= eps``.
    """
    if bvh is None:
        bvh = BVH.of_spheres(C, R)
    scale = float(np.linalg.norm(V.max(0) - V.min(0)))
    ub, lb, _ = certify(V, F, C, R, target=np.inf, min_size=np.inf, bvh=bvh)
    best = min(ub, known)
    for _ in range(6):
        target = max(lb * (1.0 + rel_tol), 1e-9 * scale)
        ub, lb2, _ = certify(V, F, C, R, target=target, min_size=target * rel_tol * 0.5, bvh=bvh)
        lb = max(lb, lb2)
        best = min(best, ub)
        if best <= lb * (1.0 + rel_tol) + 1e-12 * scale:
            break
    return best, lb


@njit(cache=True, parallel=True)
def _gaps(P, C, R, lo, hi, left, right, start, count, order):
    out = np.empty(P.shape[0])
    for i in prange(P.shape[0]):
        stack = np.empty(STACK, np.int64)
        out[i], _ = sphere_gap(P[i], C, R, lo, hi, left, right, start, count, order, stack, np.inf)
    return out


def surface_gaps(V, F, C, R, samples: int = 20000, seed: int = 0, bvh: BVH | None = None) -> np.ndarray:
    """Gap from area-uniform random surface points to the sphere union (each ≤ ε).

    Their mean is the *typical* amount by which the spheres sit inside the surface, the
    offset that makes IST contact start at the true surface on average.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    rng = np.random.default_rng(seed)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    face = rng.choice(len(F), size=int(samples), p=area / area.sum())
    u, v = rng.random(samples), rng.random(samples)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    P = a[face] + u[:, None] * (b[face] - a[face]) + v[:, None] * (c[face] - a[face])
    if bvh is None:
        bvh = BVH.of_spheres(C, R)
    return _gaps(np.ascontiguousarray(P), C, R, *bvh.arrays)
