"""Stage 7: simultaneous traversal of two Inner Sphere Trees (numba kernels).

Every kernel works on the packed form of a tree (``pack``):

``S (n, 4) float64``  node sphere ``x, y, z, r`` (a leaf node holds its leaf sphere exactly)
``I (n, 4) int64``    ``child_start, child_count, parent, depth``

and on the pose of tree B in tree A's frame, a 12-vector ``xf`` (row-major rotation, then
translation). Traversals are depth first over a caller-owned pair stack; nothing is allocated
per query, nothing raises: problems are reported through the return code.

The quantity every traversal minimises is the signed sphere distance of a leaf pair,
``|c_a - c_b| - r_a - r_b``: negative when the spheres overlap. A node pair's value is a
lower bound of all its leaf pairs' values because node spheres enclose their leaves.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

# return codes of the kernels
OK = 0
SKIPPED = 1  # motion-bound skip: no traversal ran
BAD_POSE = -1  # non-finite or non-rigid pose
STACK_FULL = -2  # cannot happen with stack_size(); reported rather than overrun

RIGID_TOL = 1e-6  # |R^T R - I| tolerance of a pose's rotation


def pack(tree):
    """Packed ``(S, I)`` arrays of an ``InnerSphereTree`` for the kernels."""
    n = tree.num_nodes
    S = np.empty((n, 4))
    S[:, :3] = tree.centers
    S[:, 3] = tree.radii
    leaf = tree.child_count == 0
    # leaf nodes carry their leaf sphere bit for bit (the wrap of one ball is that ball)
    S[leaf, :3] = tree.leaf_centers[tree.leaf_start[leaf]]
    S[leaf, 3] = tree.leaf_radii[tree.leaf_start[leaf]]
    I = np.empty((n, 4), np.int64)
    I[:, 0] = tree.child_start
    I[:, 1] = tree.child_count
    I[:, 2] = tree.parent
    I[:, 3] = tree.depth_of
    return np.ascontiguousarray(S), np.ascontiguousarray(I)


def stack_size(Ia, Ib):
    """Pair-stack capacity that a depth-first traversal of the two trees can never exceed.

    Each descent step pops one pair and pushes at most ``max children`` pairs, and a path
    from (root, root) to a leaf pair has at most ``depth_a + depth_b`` steps.
    """
    bmax = max(int(Ia[:, 1].max()), int(Ib[:, 1].max()), 1)
    return (int(Ia[:, 3].max()) + int(Ib[:, 3].max()) + 2) * bmax + 8


# --------------------------------------------------------------------------- pose helpers


@njit(cache=True, inline="always")
def relative_pose(Pa, Pb, xf):
    """``xf`` ← pose of B in A's frame, ``Pa^-1 Pb`` for rigid 4x4 ``Pa, Pb``.

    Returns False when either pose is non-finite or its rotation is not orthonormal.
    """
    for P in (Pa, Pb):
        for i in range(3):
            for j in range(4):
                if not math.isfinite(P[i, j]):
                    return False
        for i in range(3):
            for j in range(3):
                s = P[0, i] * P[0, j] + P[1, i] * P[1, j] + P[2, i] * P[2, j]
                if abs(s - (1.0 if i == j else 0.0)) > RIGID_TOL:
                    return False
    for i in range(3):
        for j in range(3):
            xf[3 * i + j] = Pa[0, i] * Pb[0, j] + Pa[1, i] * Pb[1, j] + Pa[2, i] * Pb[2, j]
        xf[9 + i] = (
            Pa[0, i] * (Pb[0, 3] - Pa[0, 3]) + Pa[1, i] * (Pb[1, 3] - Pa[1, 3]) + Pa[2, i] * (Pb[2, 3] - Pa[2, 3])
        )
    return True


@njit(cache=True, inline="always")
def _to_a(xf, S, j):
    """Centre of B's node ``j`` in A's frame."""
    x = S[j, 0]
    y = S[j, 1]
    z = S[j, 2]
    return (
        xf[0] * x + xf[1] * y + xf[2] * z + xf[9],
        xf[3] * x + xf[4] * y + xf[5] * z + xf[10],
        xf[6] * x + xf[7] * y + xf[8] * z + xf[11],
    )


@njit(cache=True, inline="always")
def pair_value(Sa, Sb, xf, a, b):
    """Signed sphere distance of A's node ``a`` and B's node ``b`` (a lower bound below them)."""
    x, y, z = _to_a(xf, Sb, b)
    dx = x - Sa[a, 0]
    dy = y - Sa[a, 1]
    dz = z - Sa[a, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz) - Sa[a, 3] - Sb[b, 3]


@njit(cache=True)
def motion_bound(xf0, xf1, c, rho):
    """Largest displacement, between B-in-A poses ``xf0`` and ``xf1``, of a point within ``rho`` of ``c``.

    ``|(R1 - R0) p + t1 - t0| <= |(R1 - R0) c + t1 - t0| + ||R1 - R0||_2 rho`` and
    ``||R1 - R0||_2 = 2 sin(θ/2) = sqrt(3 - tr(R1 R0^T))`` for the angle θ between them.
    """
    tr = 0.0
    for k in range(9):
        tr += xf1[k] * xf0[k]
    rot = math.sqrt(max(0.0, 3.0 - tr))
    m2 = 0.0
    for i in range(3):
        v = xf1[9 + i] - xf0[9 + i]
        for j in range(3):
            v += (xf1[3 * i + j] - xf0[3 * i + j]) * c[j]
        m2 += v * v
    return math.sqrt(m2) + rot * rho


# --------------------------------------------------------------------------- core descent


@njit(cache=True, inline="always")
def _push_children(Sa, Ia, Sb, Ib, xf, a, b, split_a, best, st, sv, sp):
    """Push the child pairs of ``(a, b)`` whose value beats ``best``, nearest on top."""
    base = sp
    if split_a:
        bx, by, bz = _to_a(xf, Sb, b)
        rb = Sb[b, 3]
        c0 = Ia[a, 0]
        for c in range(c0, c0 + Ia[a, 1]):
            dx = bx - Sa[c, 0]
            dy = by - Sa[c, 1]
            dz = bz - Sa[c, 2]
            v = math.sqrt(dx * dx + dy * dy + dz * dz) - Sa[c, 3] - rb
            if v < best:
                st[sp, 0] = c
                st[sp, 1] = b
                sv[sp] = v
                sp += 1
    else:
        ax = Sa[a, 0]
        ay = Sa[a, 1]
        az = Sa[a, 2]
        ra = Sa[a, 3]
        c0 = Ib[b, 0]
        for c in range(c0, c0 + Ib[b, 1]):
            x, y, z = _to_a(xf, Sb, c)
            dx = x - ax
            dy = y - ay
            dz = z - az
            v = math.sqrt(dx * dx + dy * dy + dz * dz) - ra - Sb[c, 3]
            if v < best:
                st[sp, 0] = a
                st[sp, 1] = c
                sv[sp] = v
                sp += 1
    # insertion sort of the new entries, descending, so the smallest value is popped first
    for i in range(base + 1, sp):
        v = sv[i]
        p0 = st[i, 0]
        p1 = st[i, 1]
        j = i - 1
        while j >= base and sv[j] < v:
            sv[j + 1] = sv[j]
            st[j + 1, 0] = st[j, 0]
            st[j + 1, 1] = st[j, 1]
            j -= 1
        sv[j + 1] = v
        st[j + 1, 0] = p0
        st[j + 1, 1] = p1
    return sp


@njit(cache=True)
def descend_min(Sa, Ia, Sb, Ib, xf, st, sv, base, sp, best, tol, pair, stop_at, visits):
    """Minimum signed leaf-pair distance over the pairs on the stack ``st[base:sp]``.

    ``best`` is an upper bound to beat (the answer is only recorded if below it) and
    ``pair[0:2]`` receives the arg-min leaf pair. Pairs whose lower bound is within ``tol``
    of the best so far are pruned, so the answer exceeds the true minimum by at most ``tol``
    (0 for the exact minimum). Returns ``(best, sp_after, visits)``;
    stops early once ``best <= stop_at`` (0 for a distance query: overlap is final).
    ``sp_after`` is ``-1`` if the stack would overflow (not possible with ``stack_size``).
    """
    cap = st.shape[0]
    while sp > base:
        sp -= 1
        if sv[sp] >= best - tol:
            continue
        a = st[sp, 0]
        b = st[sp, 1]
        visits += 1
        leaf_a = Ia[a, 1] == 0
        leaf_b = Ib[b, 1] == 0
        if leaf_a and leaf_b:
            best = sv[sp]
            pair[0] = a
            pair[1] = b
            if best <= stop_at:
                return best, base, visits
            continue
        split_a = (not leaf_a) and (leaf_b or Sa[a, 3] >= Sb[b, 3])
        nk = Ia[a, 1] if split_a else Ib[b, 1]
        if sp + nk > cap:
            return best, -1, visits
        sp = _push_children(Sa, Ia, Sb, Ib, xf, a, b, split_a, best - tol, st, sv, sp)
    return best, base, visits


@njit(cache=True)
def min_distance(Sa, Ia, Sb, Ib, xf, st, sv, best, tol, pair, stop_at):
    """Plain traversal from the two roots (Weller's Algorithm 5.2). Returns ``(best, code, visits)``."""
    st[0, 0] = 0
    st[0, 1] = 0
    sv[0] = pair_value(Sa, Sb, xf, 0, 0)
    best, spx, visits = descend_min(Sa, Ia, Sb, Ib, xf, st, sv, 0, 1, best, tol, pair, stop_at, 0)
    return best, (OK if spx >= 0 else STACK_FULL), visits


@njit(cache=True)
def min_distance_backtrack(Sa, Ia, Sb, Ib, xf, st, sv, tol, pair, stop_at):
    """Backtracking traversal (the seed's Algorithms 1-2).

    Starts from the leaf pair in ``pair`` (last frame's answer), whose current value is the
    first bound, and climbs towards the roots: at each step one side moves to its parent
    ``P`` and only ``P``'s other children are traversed against the other side, because the
    pair just left is already fully searched. At ``(root, root)`` everything is covered, so
    the answer equals the plain traversal's.
    """
    x = pair[0]
    y = pair[1]
    best = pair_value(Sa, Sb, xf, x, y)
    visits = 1
    if best <= stop_at:
        return best, OK, visits
    cap = st.shape[0]
    while x != 0 or y != 0:
        if y == 0 or (x != 0 and Sa[Ia[x, 2], 3] <= Sb[Ib[y, 2], 3]):
            p = Ia[x, 2]
            sp = 0
            c0 = Ia[p, 0]
            for c in range(c0, c0 + Ia[p, 1]):
                if c != x and sp < cap:
                    v = pair_value(Sa, Sb, xf, c, y)
                    if v < best - tol:
                        st[sp, 0] = c
                        st[sp, 1] = y
                        sv[sp] = v
                        sp += 1
            x = p
        else:
            p = Ib[y, 2]
            sp = 0
            c0 = Ib[p, 0]
            for c in range(c0, c0 + Ib[p, 1]):
                if c != y and sp < cap:
                    v = pair_value(Sa, Sb, xf, x, c)
                    if v < best - tol:
                        st[sp, 0] = x
                        st[sp, 1] = c
                        sv[sp] = v
                        sp += 1
            y = p
        # visit the nearest sibling first: sort the (few) entries descending
        for i in range(1, sp):
            v = sv[i]
            p0 = st[i, 0]
            p1 = st[i, 1]
            j = i - 1
            while j >= 0 and sv[j] < v:
                sv[j + 1] = sv[j]
                st[j + 1, 0] = st[j, 0]
                st[j + 1, 1] = st[j, 1]
                j -= 1
            sv[j + 1] = v
            st[j + 1, 0] = p0
            st[j + 1, 1] = p1
        best, spx, visits = descend_min(Sa, Ia, Sb, Ib, xf, st, sv, 0, sp, best, tol, pair, stop_at, visits)
        if spx < 0:
            return best, STACK_FULL, visits
        if best <= stop_at:
            break
    return best, OK, visits


# --------------------------------------------------------------------------- leaf pair geometry


@njit(cache=True, inline="always")
def leaf_geometry(Sa, Sb, xf, a, b, out):
    """Normal (A→B), point on A's ball, point on B's ball, contact point, in A's frame, into ``out[0:12]``.

    Returns the signed distance. Coincident centres get the normal +z (any unit vector is a
    valid separating direction for two concentric balls).
    """
    bx, by, bz = _to_a(xf, Sb, b)
    dx = bx - Sa[a, 0]
    dy = by - Sa[a, 1]
    dz = bz - Sa[a, 2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d > 1e-300:
        nx = dx / d
        ny = dy / d
        nz = dz / d
    else:
        nx = 0.0
        ny = 0.0
        nz = 1.0
    ra = Sa[a, 3]
    rb = Sb[b, 3]
    # contact point: middle of the two balls' common chord on the centre line (clamped, so
    # it stays inside both balls even when one contains the other)
    lo = max(-ra, d - rb)
    hi = min(ra, d + rb)
    t = 0.5 * (lo + hi)
    out[9] = Sa[a, 0] + t * nx
    out[10] = Sa[a, 1] + t * ny
    out[11] = Sa[a, 2] + t * nz
    out[0] = nx
    out[1] = ny
    out[2] = nz
    out[3] = Sa[a, 0] + ra * nx
    out[4] = Sa[a, 1] + ra * ny
    out[5] = Sa[a, 2] + ra * nz
    out[6] = bx - rb * nx
    out[7] = by - rb * ny
    out[8] = bz - rb * nz
    return d - ra - rb


# --------------------------------------------------------------------------- multipoint


@njit(cache=True, inline="always")
def ancestor_at(I, n, depth):
    """Ancestor of node ``n`` at ``depth`` (``n`` itself if it is shallower)."""
    while I[n, 3] > depth:
        n = I[n, 2]
    return n


@njit(cache=True)
def multipoint(Sa, Ia, Sb, Ib, xf, st, sv, split_depth, margin, prev, n_prev, cand, cval, pair):
    """Candidates for multipoint contacts: the deepest leaf pair of every group.

    Descends from the roots splitting only nodes above ``split_depth``. Each pair of
    subtrees rooted at ``split_depth`` (or at a shallower leaf) whose value is below
    ``margin`` is a group; its minimum signed leaf-pair distance is searched with the
    plain descent. The search is seeded with last frame's contact of the same group
    (rows of ``prev``: group a, group b, leaf a, leaf b), which prunes most of it.

    ``cand[k] = (group a, group b, leaf a, leaf b)``, ``cval[k]`` its signed distance
    (``< margin``). When more groups than ``len(cand)`` are found, the deepest are kept.
    Returns ``(n_candidates, code, visits)``.
    """
    cap = st.shape[0]
    cap_cand = cand.shape[0]
    n = 0
    visits = 0
    st[0, 0] = 0
    st[0, 1] = 0
    sv[0] = pair_value(Sa, Sb, xf, 0, 0)
    sp = 1
    while sp > 0:
        sp -= 1
        if sv[sp] >= margin:
            continue
        a = st[sp, 0]
        b = st[sp, 1]
        visits += 1
        open_a = Ia[a, 1] > 0 and Ia[a, 3] < split_depth
        open_b = Ib[b, 1] > 0 and Ib[b, 3] < split_depth
        if open_a or open_b:
            split_a = open_a and ((not open_b) or Sa[a, 3] >= Sb[b, 3])
            nk = Ia[a, 1] if split_a else Ib[b, 1]
            if sp + nk > cap:
                return n, STACK_FULL, visits
            sp = _push_children(Sa, Ia, Sb, Ib, xf, a, b, split_a, margin, st, sv, sp)
            continue
        # a group: seed with last frame's contact of this group, if any
        best = margin
        pair[0] = -1
        pair[1] = -1
        for k in range(n_prev):
            if prev[k, 0] == a and prev[k, 1] == b:
                v = pair_value(Sa, Sb, xf, prev[k, 2], prev[k, 3])
                if v < best:
                    best = v
                    pair[0] = prev[k, 2]
                    pair[1] = prev[k, 3]
                break
        # the group's own descent runs on the stack above the outer entries
        st[sp, 0] = a
        st[sp, 1] = b
        best, spx, visits = descend_min(Sa, Ia, Sb, Ib, xf, st, sv, sp, sp + 1, best, 0.0, pair, -np.inf, visits)
        if spx < 0:
            return n, STACK_FULL, visits
        if pair[0] < 0:
            continue
        if n < cap_cand:
            k = n
            n += 1
        else:  # full: replace the shallowest candidate if this one is deeper
            k = 0
            for i in range(1, cap_cand):
                if cval[i] > cval[k]:
                    k = i
            if best >= cval[k]:
                continue
        cand[k, 0] = a
        cand[k, 1] = b
        cand[k, 2] = pair[0]
        cand[k, 3] = pair[1]
        cval[k] = best
    return n, OK, visits


@njit(cache=True)
def select_spread(Sa, Sb, xf, cand, cval, n, k_max, chosen, geom, dmin):
    """Pick up to ``k_max`` of ``n`` candidates: the deepest first, then farthest-point.

    Each next pick maximises its distance to the picks so far (contact points in A's frame),
    ties broken by depth then by index, so the choice is deterministic and spread out.
    ``geom[i, 0:12]`` receives each candidate's normal, ball points and contact point. Returns the count.
    """
    if n == 0 or k_max <= 0:
        return 0
    for i in range(n):
        leaf_geometry(Sa, Sb, xf, cand[i, 2], cand[i, 3], geom[i])
    first = 0
    for i in range(1, n):
        if cval[i] < cval[first]:
            first = i
    chosen[0] = first
    m = 1
    for i in range(n):
        dmin[i] = np.inf
    while m < min(n, k_max):
        last = chosen[m - 1]
        lx = geom[last, 9]
        ly = geom[last, 10]
        lz = geom[last, 11]
        pick = -1
        for i in range(n):
            if dmin[i] < 0.0:
                continue
            x = geom[i, 9] - lx
            y = geom[i, 10] - ly
            z = geom[i, 11] - lz
            dmin[i] = min(dmin[i], x * x + y * y + z * z)
        for j in range(m):
            dmin[chosen[j]] = -1.0
        for i in range(n):
            if dmin[i] < 0.0:
                continue
            if pick < 0 or dmin[i] > dmin[pick] or (dmin[i] == dmin[pick] and cval[i] < cval[pick]):
                pick = i
        if pick < 0:
            break
        chosen[m] = pick
        m += 1
    return m


# --------------------------------------------------------------------------- penetration volume


@njit(cache=True, inline="always")
def lens_volume(ra, rb, d):
    """Volume of the intersection of two balls of radii ``ra, rb`` whose centres are ``d`` apart."""
    s = ra + rb
    if d >= s:
        return 0.0
    if d <= abs(ra - rb):
        r = min(ra, rb)
        return 4.0 / 3.0 * math.pi * r * r * r
    h = s - d
    return math.pi * h * h * (d * d + 2.0 * d * s - 3.0 * (ra - rb) * (ra - rb)) / (12.0 * d)


@njit(cache=True)
def penetration(Sa, Ia, Sb, Ib, xf, st, sv, acc):
    """Sum of lens volumes of all overlapping leaf pairs (Weller & Zachmann).

    ``acc`` (8,) receives: volume, force vector ``Σ V n`` (A→B, 3), volume-weighted lens
    centre ``Σ V x`` (3, divide by volume), number of overlapping leaf pairs.
    Returns ``(code, visits)``.
    """
    for k in range(8):
        acc[k] = 0.0
    cap = st.shape[0]
    st[0, 0] = 0
    st[0, 1] = 0
    sv[0] = pair_value(Sa, Sb, xf, 0, 0)
    sp = 1
    visits = 0
    while sp > 0:
        sp -= 1
        if sv[sp] >= 0.0:
            continue
        a = st[sp, 0]
        b = st[sp, 1]
        visits += 1
        leaf_a = Ia[a, 1] == 0
        leaf_b = Ib[b, 1] == 0
        if leaf_a and leaf_b:
            bx, by, bz = _to_a(xf, Sb, b)
            dx = bx - Sa[a, 0]
            dy = by - Sa[a, 1]
            dz = bz - Sa[a, 2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            ra = Sa[a, 3]
            rb = Sb[b, 3]
            v = lens_volume(ra, rb, d)
            if d > 1e-300:
                nx = dx / d
                ny = dy / d
                nz = dz / d
                # lens centre: middle of the common chord on the centre line (the contained
                # ball's centre when one ball holds the other)
                t = 0.5 * (max(-ra, d - rb) + min(ra, d + rb))
            else:
                nx = 0.0
                ny = 0.0
                nz = 0.0
                t = 0.0
            acc[0] += v
            acc[1] += v * nx
            acc[2] += v * ny
            acc[3] += v * nz
            acc[4] += v * (Sa[a, 0] + t * nx)
            acc[5] += v * (Sa[a, 1] + t * ny)
            acc[6] += v * (Sa[a, 2] + t * nz)
            acc[7] += 1.0
            continue
        split_a = (not leaf_a) and (leaf_b or Sa[a, 3] >= Sb[b, 3])
        nk = Ia[a, 1] if split_a else Ib[b, 1]
        if sp + nk > cap:
            return STACK_FULL, visits
        sp = _push_children(Sa, Ia, Sb, Ib, xf, a, b, split_a, 0.0, st, sv, sp)
    return OK, visits
