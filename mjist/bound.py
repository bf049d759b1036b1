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

from .bvh import BVH, STACK, ball_gap, face_normal, sphere_gap, sphere_gap_xyz

SUB_STACK = 256
SEED_BUF = 32  # bad sub-triangle centroids kept per triangle in the first pass


@njit(cache=True, inline="always")
def _cov(ax, ay, az, bx, by, bz, cx, cy, cz):
    """Covering radius of a triangle by its vertices (scalar form: no temporaries)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    la = (cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2
    lb = acx * acx + acy * acy + acz * acz
    lc = abx * abx + aby * aby + abz * abz
    longest = max(la, lb, lc)
    if 2.0 * longest >= la + lb + lc:  # right or obtuse: farthest point is the long edge's midpoint
        return 0.5 * np.sqrt(longest)
    nx = aby * acz - abz * acy
    ny = abz * acx - abx * acz
    nz = abx * acy - aby * acx
    area2 = nx * nx + ny * ny + nz * nz
    return np.sqrt(la * lb * lc / (4.0 * area2))


@njit(cache=True, inline="always")
def _gap_at(x, y, z, C, R, lo, hi, left, right, start, count, order, stack):
    return sphere_gap_xyz(x, y, z, C, R, lo, hi, left, right, start, count, order, stack, np.inf)


@njit(cache=True, inline="always")
def _gap_near(x, y, z, ja, jb, C, R, lo, hi, left, right, start, count, order, stack):
    """``_gap_at`` warm-started by the nearest spheres of the edge's two ends (prunes the search)."""
    bound = np.inf
    jc = -1
    for j in (ja, jb):
        if j >= 0:
            g = ball_gap(x, y, z, C, R, j)
            if g < bound:
                bound = g
                jc = j
    if bound <= 0.0:
        return 0.0, jc
    g, j = sphere_gap_xyz(x, y, z, C, R, lo, hi, left, right, start, count, order, stack, bound)
    if j < 0:  # nothing closer than the warm start
        return bound, jc
    return g, j


@njit(cache=True, inline="always")
def _sphere_ub(P, sp, C, R, j):
    """max over the triangle's vertices of the gap to sphere j (convex: its max over T)."""
    m = 0.0
    for w in range(3):
        m = max(m, ball_gap(P[sp, w, 0], P[sp, w, 1], P[sp, w, 2], C, R, j))
    return m


@njit(cache=True)
def _certify_triangle(V, F, f, C, R, lo, hi, left, right, start, count, order, target, min_size, stack, seeds, inset):
    """Bound for triangle ``F[f]``. Returns (ub, lb, n_bad); writes the first ``len(seeds)`` bad
    centroids to ``seeds``, moved ``inset`` into the solid along the face normal.

    Stack entries carry their vertices, the gaps and nearest spheres there, and the parent's
    bound (a sub-triangle's bound never exceeds its parent's: it lies inside it). Everything
    is scalar or in the preallocated stack: this runs on millions of sub-triangles.
    """
    P = np.empty((SUB_STACK, 3, 3))
    G = np.empty((SUB_STACK, 3))
    J = np.empty((SUB_STACK, 3), np.int64)
    UBP = np.empty(SUB_STACK)
    for v in range(3):
        for d in range(3):
            P[0, v, d] = V[F[f, v], d]
        G[0, v], J[0, v] = _gap_at(P[0, v, 0], P[0, v, 1], P[0, v, 2], C, R, lo, hi, left, right, start, count, order, stack)
    UBP[0] = np.inf
    sp = 1
    nx, ny, nz = face_normal(V, F, f)  # outward: the seeds go -inset along it
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    s_in = -inset / nn if nn > 0 else 0.0
    nx, ny, nz = nx * s_in, ny * s_in, nz * s_in
    ub_max = 0.0
    lb_max = 0.0
    nbad = 0
    while sp > 0:
        sp -= 1
        ax, ay, az = P[sp, 0, 0], P[sp, 0, 1], P[sp, 0, 2]
        bx, by, bz = P[sp, 1, 0], P[sp, 1, 1], P[sp, 1, 2]
        cx, cy, cz = P[sp, 2, 0], P[sp, 2, 1], P[sp, 2, 2]
        g0, g1, g2 = G[sp, 0], G[sp, 1], G[sp, 2]
        j0, j1, j2 = J[sp, 0], J[sp, 1], J[sp, 2]
        cov = _cov(ax, ay, az, bx, by, bz, cx, cy, cz)
        lb_max = max(lb_max, g0, g1, g2)
        ub = _sub_ub(P, G, J, sp, cov, UBP[sp], C, R)
        if ub <= target or cov <= min_size or sp + 4 > SUB_STACK:
            ub_max = max(ub_max, ub)
            if ub > target:
                if nbad < seeds.shape[0]:
                    seeds[nbad, 0] = (ax + bx + cx) / 3.0 + nx
                    seeds[nbad, 1] = (ay + by + cy) / 3.0 + ny
                    seeds[nbad, 2] = (az + bz + cz) / 3.0 + nz
                nbad += 1
            continue
        abx, aby, abz = 0.5 * (ax + bx), 0.5 * (ay + by), 0.5 * (az + bz)
        bcx, bcy, bcz = 0.5 * (bx + cx), 0.5 * (by + cy), 0.5 * (bz + cz)
        cax, cay, caz = 0.5 * (cx + ax), 0.5 * (cy + ay), 0.5 * (cz + az)
        gab, jab = _gap_near(abx, aby, abz, j0, j1, C, R, lo, hi, left, right, start, count, order, stack)
        gbc, jbc = _gap_near(bcx, bcy, bcz, j1, j2, C, R, lo, hi, left, right, start, count, order, stack)
        gca, jca = _gap_near(cax, cay, caz, j2, j0, C, R, lo, hi, left, right, start, count, order, stack)
        # children: (a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca); entry sp still holds a, b, c
        _put(P, G, J, sp + 3, abx, aby, abz, gab, jab, bcx, bcy, bcz, gbc, jbc, cax, cay, caz, gca, jca)
        _put(P, G, J, sp + 2, cax, cay, caz, gca, jca, bcx, bcy, bcz, gbc, jbc, cx, cy, cz, g2, j2)
        _put(P, G, J, sp + 1, abx, aby, abz, gab, jab, bx, by, bz, g1, j1, bcx, bcy, bcz, gbc, jbc)
        _put(P, G, J, sp, ax, ay, az, g0, j0, abx, aby, abz, gab, jab, cax, cay, caz, gca, jca)
        for q in range(4):
            UBP[sp + q] = ub
        sp += 4
    return ub_max, lb_max, nbad


@njit(cache=True, inline="always")
def _put(P, G, J, s, x0, y0, z0, g0, j0, x1, y1, z1, g1, j1, x2, y2, z2, g2, j2):
    P[s, 0, 0], P[s, 0, 1], P[s, 0, 2] = x0, y0, z0
    P[s, 1, 0], P[s, 1, 1], P[s, 1, 2] = x1, y1, z1
    P[s, 2, 0], P[s, 2, 1], P[s, 2, 2] = x2, y2, z2
    G[s, 0], G[s, 1], G[s, 2] = g0, g1, g2
    J[s, 0], J[s, 1], J[s, 2] = j0, j1, j2


@njit(cache=True, inline="always")
def _sub_ub(P, G, J, sp, cov, ub_parent, C, R):
    """Bound of sub-triangle ``sp`` from its vertex gaps and the spheres nearest to its vertices."""
    ub = min(max(G[sp, 0], G[sp, 1], G[sp, 2]) + cov, ub_parent)
    j0, j1, j2 = J[sp, 0], J[sp, 1], J[sp, 2]
    if j0 >= 0:
        ub = min(ub, _sphere_ub(P, sp, C, R, j0))
    if j1 >= 0 and j1 != j0:
        ub = min(ub, _sphere_ub(P, sp, C, R, j1))
    if j2 >= 0 and j2 != j0 and j2 != j1:
        ub = min(ub, _sphere_ub(P, sp, C, R, j2))
    return ub


@njit(cache=True, parallel=True)
def _certify_all(V, F, faces, C, R, lo, hi, left, right, start, count, order, target, min_size, buf, inset):
    """Every triangle's bound; its first ``buf.shape[1]`` bad centroids go to ``buf[t]``."""
    nf = faces.shape[0]
    ub = np.empty(nf)
    lb = np.empty(nf)
    nbad = np.empty(nf, np.int64)
    for t in prange(nf):
        stack = np.empty(STACK, np.int64)
        ub[t], lb[t], nbad[t] = _certify_triangle(
            V, F, faces[t], C, R, lo, hi, left, right, start, count, order,
            target, min_size, stack, buf[t], inset,
        )
    return ub, lb, nbad


@njit(cache=True, parallel=True)
def _emit_bad(V, F, faces, offsets, C, R, lo, hi, left, right, start, count, order, target, min_size, seeds, inset):
    for t in prange(faces.shape[0]):
        stack = np.empty(STACK, np.int64)
        _certify_triangle(
            V, F, faces[t], C, R, lo, hi, left, right, start, count, order,
            target, min_size, stack, seeds[offsets[t]:offsets[t + 1]], inset,
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


def certify_faces(
    V, F, faces, C, R, target: float, min_size: float, want_seeds: bool = False, bvh: BVH | None = None, seed_inset: float = 0.0
):
    """``certify`` on the triangles ``faces`` only, per triangle.

    Adding spheres only shrinks gaps, so a triangle certified below ``target`` stays so: the
    builder re-certifies only the triangles still open at the previous lattice level.

    Returns
    -------
    ub, lb : (len(faces),) per-triangle bound and lower bound.
    seeds : (k, 3) centroids of the sub-triangles still above ``target`` (empty unless asked),
        moved ``seed_inset`` into the solid along their face's normal (where new spheres go).
    """
    if len(R) == 0:
        raise ValueError("no spheres to certify")
    if bvh is None:
        bvh = BVH.of_spheres(C, R)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    # one pass keeps up to SEED_BUF seeds per triangle; only triangles with more are walked again
    buf = np.empty((len(faces), SEED_BUF if want_seeds else 0, 3))
    ub, lb, nbad = _certify_all(V, F, faces, C, R, *bvh.arrays, float(target), float(min_size), buf, float(seed_inset))
    seeds = np.empty((0, 3))
    if want_seeds and nbad.sum() > 0:
        fits = (nbad > 0) & (nbad <= SEED_BUF)
        kept = buf[fits][np.arange(SEED_BUF)[None, :] < nbad[fits][:, None]]  # (k, 3), triangle order
        more = np.flatnonzero(nbad > SEED_BUF)
        seeds = kept
        if len(more):
            offsets = np.concatenate([[0], np.cumsum(nbad[more])]).astype(np.int64)
            rest = np.empty((offsets[-1], 3))
            _emit_bad(V, F, faces[more], offsets, C, R, *bvh.arrays, float(target), float(min_size), rest, float(seed_inset))
            seeds = np.concatenate([kept, rest])
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
