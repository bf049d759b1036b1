"""The certified error bound ε of an inner sphere set.

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

* when neither is at or below the target t: if the balls ``(c_j, r_j + t)`` of the spheres
  nearest to T's vertices and to its parent's vertices cover T, then ``max_T g <= t``. Their
  cuts with T's plane are disks; T lies in the union of disks if every vertex of T, every
  crossing of a circle with an edge of T and every crossing of two circles inside T lies
  strictly inside another disk (a point of T outside all disks would lie in an uncovered
  region, whose boundary has such a corner point that no disk's interior holds). This
  certifies a sub-triangle that a hole between a few spheres spans, where the two bounds
  above only get there by splitting down to a fraction of the hole (several times fewer
  sub-triangles on a segmented jaw). When those six do not cover T, the test
  runs again with every sphere whose grown ball reaches T (``_cover_all``); then it decides:
  either T is covered, or a point of T lies farther than t from every sphere, so T is open
  for certain, like a sub-triangle with a vertex gap above t.

The smallest of these is T's bound ``UB(T)``; a sub-triangle is split again until
``UB(T) <= target`` or it is smaller than ``min_size`` (or than ``bad_size`` once a vertex
gap above the target or the complete cover test proves it open: splitting it further would
only place its seeds finer). Across the builder's lattice
levels (same target, more spheres, smaller ``min_size``) each triangle's split is the same
fixed quadtree, so a level walks only the sub-triangles that were still above the target at
the previous one: the rest was certified then, and gaps only shrink as spheres are added
(``certify_faces(prev=)``). ε is the maximum ``UB`` over
the final sub-triangles, and ``max_i g(v_i)`` over all evaluated vertices is a lower
bound of the true Hausdorff distance (reported so the bound's tightness is visible).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..geometry.bvh import BVH, STACK, ball_gap, face_normal, sphere_gap, sphere_gap_xyz, spheres_near

SUB_STACK = 256
# Bad sub-triangle centroids kept per triangle in the first pass: at least SEED_BUF, and SEED_GROWTH
# times its bad sub-triangles of the previous level (an open-for-certain one of bad_size splits into
# at most four of the next, half as large), within SEED_BUDGET entries in all (32 bytes each; only
# the written ones are touched). Only triangles with more are walked again, so a fine level (over a
# hundred seeds per triangle) is walked once, not twice. A larger budget costs memory, a smaller
# one walks more triangles twice; BENCHMARKS.md has the figures.
SEED_BUF = 32
SEED_GROWTH = 4.0
SEED_BUDGET = 12_000_000
COVER_SPHERES = 6  # spheres tried by the disk-cover test: nearest to the vertices and to the parent's
# The cover test runs with the target shrunk by this (relative): rounding in the planar frame
# (~1e-16 of the coordinates) can then never turn an uncovered point into a covered one.
COVER_SHRINK = 1e-7
COVER_MIN_SHAPE = 1e-6  # slivers (2 * area below this times the longest edge squared) are not tested
# When that fails, the test runs again with every sphere whose grown ball reaches the sub-triangle
# (up to COVER_ALL of them): then it decides, and a failure proves a point of T uncovered, so T is
# open for certain and is split no finer than bad_size, instead of down to min_size: a faster
# certification and fewer leaves placed where the gap was already closed, for the same ε.
COVER_ALL = 64
# A sub-triangle's place in its triangle's fixed midpoint quadtree, as a key: two bits per level
# from the top, left-aligned to PATH_DEPTH levels, shifted left by DEPTH_BITS to hold the depth.
# A sub-triangle's descendants are the keys in [path, path + 4**(PATH_DEPTH - depth)) << DEPTH_BITS;
# (path, depth) itself names it exactly. Deeper leaves are recorded by their ancestor at
# PATH_DEPTH (conservative: everything below it is walked again).
PATH_DEPTH = 28
DEPTH_BITS = 5


@njit(cache=True)
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


@njit(cache=True)
def _in_other_disk(px, py, D, k, m, n):
    """Is (px, py) strictly inside one of the disks ``D[:k]`` other than ``m`` and ``n``?"""
    for q in range(k):
        if q != m and q != n and (px - D[q, 0]) ** 2 + (py - D[q, 1]) ** 2 < D[q, 2] * (1.0 - 1e-9):
            return True
    return False


@njit(cache=True)
def _balls_cover(ax, ay, az, bx, by, bz, cx, cy, cz, js, nj, C, R, t, D):
    """Is the triangle (a, b, c) inside the union of the balls ``(C[j], R[j] + t)``, j in ``js[:nj]``?

    A sufficient test (False when unsure): the balls cut the triangle's plane in disks, and the
    triangle is covered if each of its vertices, each crossing of a circle with one of its edges
    and each crossing of two circles inside it lies strictly inside some other disk. ``D`` is
    scratch space, ``(nj, 3)``: disk centre (x, y) in the triangle's frame and radius squared.
    """
    e1x, e1y, e1z = bx - ax, by - ay, bz - az
    e2x, e2y, e2z = cx - ax, cy - ay, cz - az
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    l1 = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    longest = max(e1x * e1x + e1y * e1y + e1z * e1z, e2x * e2x + e2y * e2y + e2z * e2z,
                  (cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2)
    if nn <= COVER_MIN_SHAPE * longest or l1 == 0.0:
        return False
    # orthonormal frame (u along ab, v in the plane, n normal); a = (0, 0), b = (l1, 0), c = (x2, y2)
    ux, uy, uz = e1x / l1, e1y / l1, e1z / l1
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    vx, vy, vz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux
    x2 = e2x * ux + e2y * uy + e2z * uz
    y2 = e2x * vx + e2y * vy + e2z * vz
    # the triangle's box in the plane, a little wider: disks that miss it hold no point of the
    # triangle and no crossing the test looks at, so they are left out (the test is cubic in them)
    pad = 1e-6 * l1
    x_lo, x_hi, y_hi = min(0.0, x2) - pad, max(l1, x2) + pad, y2 + pad
    k = 0
    for q in range(nj):
        j = js[q]
        dx, dy, dz = C[j, 0] - ax, C[j, 1] - ay, C[j, 2] - az
        off = dx * nx + dy * ny + dz * nz
        rr = (R[j] + t) ** 2 - off * off
        if rr > 0.0:
            px = dx * ux + dy * uy + dz * uz
            py = dx * vx + dy * vy + dz * vz
            ex = max(x_lo - px, 0.0, px - x_hi)
            ey = max(-pad - py, 0.0, py - y_hi)
            if ex * ex + ey * ey >= rr:
                continue
            D[k, 0] = px
            D[k, 1] = py
            D[k, 2] = rr
            k += 1
    if k == 0:
        return False
    if not (_in_other_disk(0.0, 0.0, D, k, -1, -1) and _in_other_disk(l1, 0.0, D, k, -1, -1)
            and _in_other_disk(x2, y2, D, k, -1, -1)):
        return False
    for m in range(k):  # circle-edge crossings
        for e in range(3):
            if e == 0:
                px, py, qx, qy = 0.0, 0.0, l1, 0.0
            elif e == 1:
                px, py, qx, qy = l1, 0.0, x2, y2
            else:
                px, py, qx, qy = x2, y2, 0.0, 0.0
            dx, dy = qx - px, qy - py
            fx, fy = px - D[m, 0], py - D[m, 1]
            qa = dx * dx + dy * dy
            qb = fx * dx + fy * dy
            disc = qb * qb - qa * (fx * fx + fy * fy - D[m, 2])
            if disc < 0.0:
                continue
            sq = np.sqrt(disc)
            for s in ((-qb - sq) / qa, (-qb + sq) / qa):
                if 0.0 <= s <= 1.0 and not _in_other_disk(px + s * dx, py + s * dy, D, k, m, -1):
                    return False
    det = l1 * y2
    for m in range(k):  # circle-circle crossings inside the triangle (or just outside it)
        for n in range(m + 1, k):
            dx, dy = D[n, 0] - D[m, 0], D[n, 1] - D[m, 1]
            d2 = dx * dx + dy * dy
            if d2 == 0.0:
                continue
            d = np.sqrt(d2)
            rm, rn = np.sqrt(D[m, 2]), np.sqrt(D[n, 2])
            if d >= rm + rn or d <= abs(rm - rn):
                continue
            along = (D[m, 2] - D[n, 2] + d2) / (2.0 * d)
            half = np.sqrt(max(D[m, 2] - along * along, 0.0))
            mx, my = D[m, 0] + along * dx / d, D[m, 1] + along * dy / d
            for sg in (-1.0, 1.0):
                px = mx - sg * half * dy / d
                py = my + sg * half * dx / d
                wb = (px * y2 - py * x2) / det  # barycentric weights of b and c
                wc = l1 * py / det
                if wb < -1e-9 or wc < -1e-9 or wb + wc > 1.0 + 1e-9:
                    continue
                if not _in_other_disk(px, py, D, k, m, n):
                    return False
    return True


@njit(cache=True)
def _gap_at(x, y, z, C, R, lo, hi, left, right, start, count, order, stack):
    return sphere_gap_xyz(x, y, z, C, R, lo, hi, left, right, start, count, order, stack, np.inf)


@njit(cache=True)
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


@njit(cache=True)
def _sphere_ub(P, sp, C, R, j):
    """max over the triangle's vertices of the gap to sphere j (convex: its max over T)."""
    m = 0.0
    for w in range(3):
        m = max(m, ball_gap(P[sp, w, 0], P[sp, w, 1], P[sp, w, 2], C, R, j))
    return m


@njit(cache=True)
def _certify_triangle(V, F, f, C, R, lo, hi, left, right, start, count, order, target, min_size, bad_size, stack, seeds,
                      inset, prev, paths):
    """Bound for triangle ``F[f]``. Returns (ub, lb, n_bad); writes the first ``len(seeds)`` bad
    centroids to ``seeds``, moved ``inset`` into the solid along the face normal, and their
    quadtree keys to ``paths``.

    ``prev``: the sorted keys of this triangle's bad sub-triangles from an earlier walk with the
    same target and fewer spheres (empty: walk everything). A sub-triangle that neither holds
    one of them nor lies inside one was covered by that walk's good sub-triangles, every part at
    or below the target then; gaps only shrink as spheres are added, so it is not walked again
    and counts as ``target`` in the returned bound. Inside a bad one everything is walked.

    Stack entries carry their vertices, the gaps and nearest spheres there, and the parent's
    bound (a sub-triangle's bound never exceeds its parent's: it lies inside it). Everything
    is scalar or in the preallocated stack: this runs on millions of sub-triangles.
    """
    P = np.empty((SUB_STACK, 3, 3))
    G = np.empty((SUB_STACK, 3))
    J = np.empty((SUB_STACK, 3), np.int64)
    UBP = np.empty(SUB_STACK)
    KEY = np.empty(SUB_STACK, np.int64)
    DEP = np.empty(SUB_STACK, np.int64)
    ALL = np.empty(SUB_STACK, np.bool_)  # inside an earlier bad sub-triangle: walk everything
    PJ = np.full((SUB_STACK, 3), -1, np.int64)  # the parent's nearest spheres (for the cover test)
    js = np.empty(COVER_SPHERES, np.int64)
    D = np.empty((COVER_SPHERES, 3))
    js_all = np.empty(COVER_ALL, np.int64)
    D_all = np.empty((COVER_ALL, 3))
    KEY[0] = 0
    DEP[0] = 0
    n_prev = prev.shape[0]
    ALL[0] = n_prev == 0
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
        key, dep, walk_all = KEY[sp], DEP[sp], ALL[sp]
        code = (key << DEPTH_BITS) | dep
        if not walk_all:
            j = np.searchsorted(prev, code)
            if j == n_prev or prev[j] >= (key + (np.int64(1) << (2 * (PATH_DEPTH - dep)))) << DEPTH_BITS:
                ub_max = max(ub_max, target)  # certified at or below target by the earlier walk
                continue
            walk_all = prev[j] == code  # an earlier bad leaf itself: all of it again
        ax, ay, az = P[sp, 0, 0], P[sp, 0, 1], P[sp, 0, 2]
        bx, by, bz = P[sp, 1, 0], P[sp, 1, 1], P[sp, 1, 2]
        cx, cy, cz = P[sp, 2, 0], P[sp, 2, 1], P[sp, 2, 2]
        g0, g1, g2 = G[sp, 0], G[sp, 1], G[sp, 2]
        j0, j1, j2 = J[sp, 0], J[sp, 1], J[sp, 2]
        cov = _cov(ax, ay, az, bx, by, bz, cx, cy, cz)
        lb_max = max(lb_max, g0, g1, g2)
        ub = _sub_ub(P, G, J, sp, cov, UBP[sp], C, R)
        is_open = max(g0, g1, g2) > target  # a vertex gap above the target: open for certain
        if ub > target and not is_open:
            if _cover_test(P, J, PJ, sp, js, C, R, target, D):
                ub = target
            else:
                n_all = _cover_all(ax, ay, az, bx, by, bz, cx, cy, cz, C, R, lo, hi, left, right, start, count, order,
                                   stack, target, js_all, D_all)
                if n_all == 1:
                    ub = target
                elif n_all == 0:
                    is_open = True
        # an open sub-triangle is split only down to bad_size (finer splits would only place its seeds
        # finer); the uncertain ones (bound above the target, not proven open) go on to min_size
        if ub <= target or cov <= min_size or (cov <= bad_size and is_open) or sp + 4 > SUB_STACK:
            ub_max = max(ub_max, ub)
            if ub > target:
                if nbad < seeds.shape[0]:
                    seeds[nbad, 0] = (ax + bx + cx) / 3.0 + nx
                    seeds[nbad, 1] = (ay + by + cy) / 3.0 + ny
                    seeds[nbad, 2] = (az + bz + cz) / 3.0 + nz
                    paths[nbad] = code
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
            PJ[sp + q, 0], PJ[sp + q, 1], PJ[sp + q, 2] = j0, j1, j2
            ALL[sp + q] = walk_all
            if dep < PATH_DEPTH:
                KEY[sp + q] = key + (np.int64(q) << (2 * (PATH_DEPTH - dep - 1)))
                DEP[sp + q] = dep + 1
            else:  # past the key's resolution: children share the ancestor's key
                KEY[sp + q] = key
                DEP[sp + q] = dep
        sp += 4
    return ub_max, lb_max, nbad


@njit(cache=True)
def _cover_test(P, J, PJ, sp, js, C, R, target, D):
    """``_balls_cover`` of sub-triangle ``sp`` by its vertices' and its parent's nearest spheres."""
    nj = 0
    for q in range(6):
        j = J[sp, q] if q < 3 else PJ[sp, q - 3]
        if j < 0:
            continue
        new = True
        for q2 in range(nj):
            if js[q2] == j:
                new = False
        if new:
            js[nj] = j
            nj += 1
    return _balls_cover(P[sp, 0, 0], P[sp, 0, 1], P[sp, 0, 2], P[sp, 1, 0], P[sp, 1, 1], P[sp, 1, 2],
                        P[sp, 2, 0], P[sp, 2, 1], P[sp, 2, 2], js, nj, C, R, target * (1.0 - COVER_SHRINK), D)


@njit(cache=True)
def _cover_all(ax, ay, az, bx, by, bz, cx, cy, cz, C, R, lo, hi, left, right, start, count, order, stack, target, js, D):
    """``_balls_cover`` of the triangle by every sphere whose ball grown by ``target`` reaches it.

    Returns 1 if covered, 0 if not (then some point of the triangle is farther than ``target``
    from every sphere, up to the test's rounding margins), -1 if undecided (more spheres than
    ``js`` holds, or a sliver, which ``_balls_cover`` does not test). The spheres are those within ``target`` of the ball around the centroid
    through the farthest vertex, a superset of those whose grown balls meet the triangle.
    """
    e1x, e1y, e1z, e2x, e2y, e2z = bx - ax, by - ay, bz - az, cx - ax, cy - ay, cz - az
    nn = np.sqrt((e1y * e2z - e1z * e2y) ** 2 + (e1z * e2x - e1x * e2z) ** 2 + (e1x * e2y - e1y * e2x) ** 2)
    if nn <= COVER_MIN_SHAPE * max(e1x * e1x + e1y * e1y + e1z * e1z, e2x * e2x + e2y * e2y + e2z * e2z,
                                   (cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2):
        return -1  # a sliver: _balls_cover does not test it
    mx, my, mz = (ax + bx + cx) / 3.0, (ay + by + cy) / 3.0, (az + bz + cz) / 3.0
    rho = np.sqrt(max((ax - mx) ** 2 + (ay - my) ** 2 + (az - mz) ** 2, (bx - mx) ** 2 + (by - my) ** 2 + (bz - mz) ** 2,
                      (cx - mx) ** 2 + (cy - my) ** 2 + (cz - mz) ** 2))
    n = spheres_near(mx, my, mz, C, R, lo, hi, left, right, start, count, order, stack, rho + target, js)
    if n < 0:
        return -1
    if n > 0 and _balls_cover(ax, ay, az, bx, by, bz, cx, cy, cz, js, n, C, R, target * (1.0 - COVER_SHRINK), D):
        return 1
    return 0


@njit(cache=True)
def _put(P, G, J, s, x0, y0, z0, g0, j0, x1, y1, z1, g1, j1, x2, y2, z2, g2, j2):
    P[s, 0, 0], P[s, 0, 1], P[s, 0, 2] = x0, y0, z0
    P[s, 1, 0], P[s, 1, 1], P[s, 1, 2] = x1, y1, z1
    P[s, 2, 0], P[s, 2, 1], P[s, 2, 2] = x2, y2, z2
    G[s, 0], G[s, 1], G[s, 2] = g0, g1, g2
    J[s, 0], J[s, 1], J[s, 2] = j0, j1, j2


@njit(cache=True)
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
def _certify_all(V, F, faces, C, R, lo, hi, left, right, start, count, order, target, min_size, bad_size, buf, buf_off, inset,
                 prev, prev_off, pbuf):
    """Every triangle's bound; its first bad centroids go to ``buf[buf_off[t]:buf_off[t + 1]]``,
    their keys to ``pbuf`` likewise; ``prev[prev_off[t]:prev_off[t + 1]]`` are its earlier bad keys."""
    nf = faces.shape[0]
    ub = np.empty(nf)
    lb = np.empty(nf)
    nbad = np.empty(nf, np.int64)
    for t in prange(nf):
        stack = np.empty(STACK, np.int64)
        ub[t], lb[t], nbad[t] = _certify_triangle(
            V, F, faces[t], C, R, lo, hi, left, right, start, count, order, target, min_size, bad_size, stack,
            buf[buf_off[t]:buf_off[t + 1]], inset, prev[prev_off[t]:prev_off[t + 1]], pbuf[buf_off[t]:buf_off[t + 1]],
        )
    return ub, lb, nbad


@njit(cache=True, parallel=True)
def _pack_seeds(buf, pbuf, buf_off, nbad, off, seeds, keys):
    """Copy each triangle's first-pass seeds and keys (those that fit its buffer) to their places."""
    for t in prange(nbad.shape[0]):
        if nbad[t] > buf_off[t + 1] - buf_off[t]:
            continue  # walked again (_emit_bad)
        for q in range(nbad[t]):
            for d in range(3):
                seeds[off[t] + q, d] = buf[buf_off[t] + q, d]
            keys[off[t] + q] = pbuf[buf_off[t] + q]


@njit(cache=True, parallel=True)
def _emit_bad(V, F, faces, offsets, C, R, lo, hi, left, right, start, count, order, target, min_size, bad_size, seeds,
              inset, prev, prev_off, paths):
    for t in prange(faces.shape[0]):
        stack = np.empty(STACK, np.int64)
        _certify_triangle(
            V, F, faces[t], C, R, lo, hi, left, right, start, count, order,
            target, min_size, bad_size, stack, seeds[offsets[t]:offsets[t + 1]], inset,
            prev[prev_off[t]:prev_off[t + 1]], paths[offsets[t]:offsets[t + 1]],
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
    ub, lb, seeds, _ = certify_faces(V, F, np.arange(len(F), dtype=np.int64), C, R, target, min_size, want_seeds, bvh)
    return float(ub.max()), float(lb.max()), seeds


def certify_faces(
    V, F, faces, C, R, target: float, min_size: float, want_seeds: bool = False, bvh: BVH | None = None,
    seed_inset: float = 0.0, prev=None, bad_size: float | None = None,
):
    """``certify`` on the triangles ``faces`` only, per triangle.

    Adding spheres only shrinks gaps, so a triangle certified below ``target`` stays so: the
    builder re-certifies only the triangles still open at the previous lattice level, and
    inside them only the sub-triangles that were still open (``prev``).

    Parameters
    ----------
    bad_size : float, optional
        Split a sub-triangle with a vertex gap above ``target`` (open for certain) only down
        to this covering radius; the uncertain ones go on to ``min_size``. Default ``min_size``.
    prev : (keys, offsets), optional
        Per triangle of ``faces``, the sorted quadtree keys of its sub-triangles above
        ``target`` in an earlier call with the same ``target`` and ``min_size`` no smaller
        than this one's, and a subset of these spheres (the ``paths`` it returned, restricted
        to these triangles); the rest of each triangle is not walked again.

    Returns
    -------
    ub, lb : (len(faces),) per-triangle bound and lower bound.
    seeds : (k, 3) centroids of the sub-triangles still above ``target`` (empty unless asked),
        moved ``seed_inset`` into the solid along their face's normal (where new spheres go);
        per triangle, in the segments of ``paths``' offsets.
    paths : (keys, offsets) the quadtree keys of those sub-triangles per triangle, sorted
        (empty unless asked); ``restrict_paths`` selects triangles for the next call.
    """
    if len(R) == 0:
        raise ValueError("no spheres to certify")
    if bvh is None:
        bvh = BVH.of_spheres(C, R)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if prev is None:
        prev = (np.empty(0, np.int64), np.zeros(len(faces) + 1, np.int64))
    pk, po = prev
    if len(po) != len(faces) + 1:
        raise ValueError(f"prev holds {len(po) - 1} triangles, faces {len(faces)}")
    # one pass keeps the seeds of each triangle that fit its share of the buffer (see SEED_GROWTH);
    # only triangles with more are walked again
    if want_seeds:
        grow = SEED_GROWTH if SEED_GROWTH * len(pk) <= SEED_BUDGET else max(1.0, SEED_BUDGET / max(len(pk), 1))
        cap = np.maximum(SEED_BUF, np.ceil(grow * np.diff(po))).astype(np.int64)
    else:
        cap = np.zeros(len(faces), np.int64)
    buf_off = np.concatenate([[0], np.cumsum(cap)]).astype(np.int64)
    buf = np.empty((buf_off[-1], 3))
    pbuf = np.empty(buf_off[-1], np.int64)
    bad_size = float(min_size if bad_size is None else max(bad_size, min_size))
    ub, lb, nbad = _certify_all(V, F, faces, C, R, *bvh.arrays, float(target), float(min_size), bad_size, buf, buf_off,
                                float(seed_inset), pk, po, pbuf)
    seeds = np.empty((0, 3))
    paths = (np.empty(0, np.int64), np.zeros(len(faces) + 1, np.int64))
    if want_seeds and nbad.sum() > 0:
        off = np.concatenate([[0], np.cumsum(nbad)]).astype(np.int64)
        keys = np.empty(off[-1], np.int64)
        seeds = np.empty((off[-1], 3))
        _pack_seeds(buf, pbuf, buf_off, nbad, off, seeds, keys)
        del buf, pbuf
        more = np.flatnonzero(nbad > cap)
        if len(more):
            offsets = np.concatenate([[0], np.cumsum(nbad[more])]).astype(np.int64)
            rest = np.empty((offsets[-1], 3))
            rest_keys = np.empty(offsets[-1], np.int64)
            _emit_bad(V, F, faces[more], offsets, C, R, *bvh.arrays, float(target), float(min_size), bad_size, rest, float(seed_inset),
                      *restrict_paths((pk, po), more), rest_keys)
            seeds[np.repeat(off[more] - offsets[:-1], nbad[more]) + np.arange(offsets[-1])] = rest
            _copy_segments(rest_keys, offsets[:-1], keys, off[more], nbad[more])
        _sort_segments(keys, off)
        paths = (keys, off)
    return ub, lb, seeds, paths


@njit(cache=True, parallel=True)
def _sort_segments(keys, off):
    """Sort ``keys[off[t]:off[t + 1]]`` for every t, in place (no temporaries of the whole array)."""
    for t in prange(off.shape[0] - 1):
        keys[off[t]:off[t + 1]].sort()


def restrict_paths(paths, keep):
    """``paths`` (keys, offsets) of ``certify_faces`` for the triangles at indices ``keep`` only."""
    keys, off = paths
    keep = np.asarray(keep, np.int64)
    new_off = np.concatenate([[0], np.cumsum(off[keep + 1] - off[keep])]).astype(np.int64)
    out = np.empty(new_off[-1], np.int64)
    _copy_segments(keys, off[keep], out, new_off[:-1], np.diff(new_off))
    return out, new_off


@njit(cache=True)
def _copy_segments(src, src_start, dst, dst_start, length):
    """``dst[dst_start[i]:dst_start[i] + length[i]] = src[src_start[i]:...]`` for every i."""
    for i in range(length.shape[0]):
        for k in range(length[i]):
            dst[dst_start[i] + k] = src[src_start[i] + k]


def tight_bound(V, F, C, R, rel_tol: float = 0.05, bvh: BVH | None = None, known: float = np.inf, face_ub=None):
    """The certified ε, refined until it is within ``rel_tol`` of its own lower bound.

    ``known`` is a bound certified earlier for a subset of these spheres (still valid:
    adding spheres only shrinks gaps); every certificate is an upper bound, so the
    smallest one is returned. ``face_ub`` (one per triangle), likewise certified earlier:
    a refinement walks only the triangles whose bound is above its target (the builder's
    levels leave all but the open ones at or below ``max_error``). Returns ``(eps, lower)``:
    ``lower <= true gap <= eps``.
    """
    if bvh is None:
        bvh = BVH.of_spheres(C, R)
    scale = float(np.linalg.norm(V.max(0) - V.min(0)))
    ub_f, lb_f, _, _ = certify_faces(V, F, np.arange(len(F), dtype=np.int64), C, R, np.inf, np.inf, bvh=bvh)
    if face_ub is not None:
        ub_f = np.minimum(ub_f, face_ub)
    lb = float(lb_f.max())
    best = min(float(ub_f.max()), known)
    for _ in range(6):
        if best <= lb * (1.0 + rel_tol) + 1e-12 * scale:  # already tight (often: the vertices' own gaps)
            break
        target = max(lb * (1.0 + rel_tol), 1e-9 * scale)
        walk = np.flatnonzero(ub_f > target)  # the others are certified at or below it already
        ub_w, lb_w, _, _ = certify_faces(V, F, walk, C, R, target, target * rel_tol * 0.5, bvh=bvh)
        ub_f[walk] = np.minimum(ub_f[walk], ub_w)
        lb = max(lb, float(lb_w.max()))
        best = min(best, float(ub_f.max()))
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
