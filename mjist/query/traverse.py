"""Simultaneous traversal of two Inner Sphere Trees (numba kernels).

Every kernel works on the packed form of a tree (``pack``), one 64-byte row per node so a
node test touches one cache line (several times faster than separate arrays on large trees):

``N (n, 8) float64``: node sphere ``x, y, z, r`` (a leaf node holds its leaf sphere exactly),
then ``child_start, child_count, parent, depth`` (small integers, exact in float64).

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

from .select import spread

# return codes of the kernels
OK = 0
SKIPPED = 1  # motion-bound skip: no traversal ran
BAD_POSE = -1  # non-finite or non-rigid pose
STACK_FULL = -2  # cannot happen with stack_size(); reported rather than overrun

RIGID_TOL = 1e-6  # |R^T R - I| tolerance of a pose's rotation

# columns of a packed node row
CS, CC, PAR, DEP = 4, 5, 6, 7


def _aligned(shape, align=64):
    """Zeroed float64 array whose rows start on ``align``-byte boundaries."""
    n = int(np.prod(shape))
    buf = np.zeros(n + align // 8, np.float64)
    off = (-buf.ctypes.data % align) // 8
    return buf[off:off + n].reshape(shape)


def pack(tree):
    """Packed ``(n, 8)`` node rows of an ``InnerSphereTree`` for the kernels."""
    n = tree.num_nodes
    N = _aligned((n, 8))
    N[:, :3] = tree.centers
    N[:, 3] = tree.radii
    leaf = tree.child_count == 0
    # leaf nodes carry their leaf sphere bit for bit (the wrap of one ball is that ball)
    N[leaf, :3] = tree.leaf_centers[tree.leaf_start[leaf]]
    N[leaf, 3] = tree.leaf_radii[tree.leaf_start[leaf]]
    N[:, CS] = np.maximum(tree.child_start, 0)
    N[:, CC] = tree.child_count
    N[:, PAR] = tree.parent
    N[:, DEP] = tree.depth_of
    return N


def stack_size(*trees) -> int:
    """Stack capacity that a depth-first traversal of one packed tree, or of a pair of them,
    can never exceed.

    Each descent step pops one entry and pushes at most ``max children`` entries, and a path
    from the root(s) to a leaf (pair) has at most the sum of the trees' depths in steps.
    """
    bmax = int(max([N[:, CC].max() for N in trees if N.shape[0]] + [1]))
    depth = sum(int(N[:, DEP].max()) + 1 for N in trees if N.shape[0])
    return depth * bmax + 8


# --------------------------------------------------------------------------- pose helpers


@njit(cache=True)
def _rigid(P):
    """``P`` is finite and its rotation block orthonormal."""
    for i in range(3):
        for j in range(4):
            if not math.isfinite(P[i, j]):
                return False
    for i in range(3):
        for j in range(3):
            s = P[0, i] * P[0, j] + P[1, i] * P[1, j] + P[2, i] * P[2, j]
            if abs(s - (1.0 if i == j else 0.0)) > RIGID_TOL:
                return False
    return True


@njit(cache=True)
def relative_pose(Pa, Pb, xf):
    """``xf`` ← pose of B in A's frame, ``Pa^-1 Pb`` for rigid 4x4 ``Pa, Pb``.

    Returns False when either pose is non-finite or its rotation is not orthonormal.
    """
    if not (_rigid(Pa) and _rigid(Pb)):
        return False
    for i in range(3):
        for j in range(3):
            xf[3 * i + j] = Pa[0, i] * Pb[0, j] + Pa[1, i] * Pb[1, j] + Pa[2, i] * Pb[2, j]
        xf[9 + i] = (
            Pa[0, i] * (Pb[0, 3] - Pa[0, 3]) + Pa[1, i] * (Pb[1, 3] - Pa[1, 3]) + Pa[2, i] * (Pb[2, 3] - Pa[2, 3])
        )
    return True


@njit(cache=True)
def _to_a(xf, N, j):
    """Centre of B's node ``j`` in A's frame."""
    x = N[j, 0]
    y = N[j, 1]
    z = N[j, 2]
    return (
        xf[0] * x + xf[1] * y + xf[2] * z + xf[9],
        xf[3] * x + xf[4] * y + xf[5] * z + xf[10],
        xf[6] * x + xf[7] * y + xf[8] * z + xf[11],
    )


@njit(cache=True)
def _offset(Na, Nb, xf, a, b):
    """From A's node ``a`` to B's node ``b`` (A's frame): the centres' offset and its length."""
    bx, by, bz = _to_a(xf, Nb, b)
    dx = bx - Na[a, 0]
    dy = by - Na[a, 1]
    dz = bz - Na[a, 2]
    return dx, dy, dz, math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True)
def pair_value(Na, Nb, xf, a, b):
    """Signed sphere distance of A's node ``a`` and B's node ``b`` (a lower bound below them)."""
    _, _, _, d = _offset(Na, Nb, xf, a, b)
    return d - Na[a, 3] - Nb[b, 3]


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


@njit(cache=True)
def _push_children(Na, Nb, xf, a, b, split_a, thr, st, sv, sp):
    """Push the child pairs of ``(a, b)`` whose value is below ``thr``, nearest on top.

    The test is done on squared distances; the square root only for pairs kept.
    """
    base = sp
    if split_a:
        bx, by, bz = _to_a(xf, Nb, b)
        rb = Nb[b, 3]
        c0 = int(Na[a, CS])
        for c in range(c0, c0 + int(Na[a, CC])):
            dx = bx - Na[c, 0]
            dy = by - Na[c, 1]
            dz = bz - Na[c, 2]
            s = thr + Na[c, 3] + rb
            d2 = dx * dx + dy * dy + dz * dz
            if s > 0.0 and d2 < s * s:
                st[sp, 0] = c
                st[sp, 1] = b
                sv[sp] = math.sqrt(d2) - Na[c, 3] - rb
                sp += 1
    else:
        ax = Na[a, 0]
        ay = Na[a, 1]
        az = Na[a, 2]
        ra = Na[a, 3]
        c0 = int(Nb[b, CS])
        for c in range(c0, c0 + int(Nb[b, CC])):
            x, y, z = _to_a(xf, Nb, c)
            dx = x - ax
            dy = y - ay
            dz = z - az
            s = thr + ra + Nb[c, 3]
            d2 = dx * dx + dy * dy + dz * dz
            if s > 0.0 and d2 < s * s:
                st[sp, 0] = a
                st[sp, 1] = c
                sv[sp] = math.sqrt(d2) - ra - Nb[c, 3]
                sp += 1
    _sort_desc(st, sv, base, sp)
    return sp


@njit(cache=True)
def _sort_desc(st, sv, base, sp):
    """Insertion sort of stack entries ``base:sp`` by value, descending (smallest popped first)."""
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


MIN = 0  # descend mode: minimum signed leaf-pair distance
VOLUME = 1  # descend mode: accumulate lens volumes of all overlapping leaf pairs
BLEND = 2  # descend mode: accumulate weighted normals and points of the leaf pairs below ``best``


@njit(cache=True)
def descend(Na, Nb, xf, st, sv, base, sp, best, tol, pair, stop_at, visits, mode, acc):
    """Depth-first descent over the pairs on the stack ``st[base:sp]`` (the hot loop).

    ``mode == MIN``: minimum signed leaf-pair distance. ``best`` is an upper bound to beat
    (the answer is only recorded if below it) and ``pair[0:2]`` receives the arg-min leaf
    pair. Pairs whose lower bound is within ``tol`` of the best so far are pruned, so the
    answer exceeds the true minimum by at most ``tol`` (0 for the exact minimum); stops
    early once ``best <= stop_at`` (0 for a distance query: overlap is final).

    ``mode == VOLUME``: with ``best = 0, tol = 0``, visits every overlapping leaf pair and
    adds its lens to ``acc`` (see ``penetration``).

    ``mode == BLEND``: with ``tol = 0``, visits every leaf pair below ``best`` and adds its
    weighted normal and contact point to ``acc`` (see ``blend``).

    Returns ``(best, sp_after, visits)``; ``sp_after`` is ``-1`` if the stack would overflow
    (not possible with ``stack_size``). The child push is written out here rather than
    called: numba's inlining of a helper made this loop 2.4x slower.
    """
    cap = st.shape[0]
    while sp > base:
        sp -= 1
        if sv[sp] >= best - tol:
            continue
        a = st[sp, 0]
        b = st[sp, 1]
        visits += 1
        na = int(Na[a, CC])
        nb = int(Nb[b, CC])
        if na == 0 and nb == 0:
            if mode == VOLUME:
                _add_lens(Na, Nb, xf, a, b, acc)
                continue
            if mode == BLEND:
                _add_blend(Na, Nb, xf, a, b, best, acc)
                continue
            best = sv[sp]
            pair[0] = a
            pair[1] = b
            if best <= stop_at:
                return best, base, visits
            continue
        if sp + max(na, nb) > cap:
            return best, -1, visits
        thr = best - tol
        top = sp
        if na > 0 and (nb == 0 or Na[a, 3] >= Nb[b, 3]):
            x = Nb[b, 0]
            y = Nb[b, 1]
            z = Nb[b, 2]
            bx = xf[0] * x + xf[1] * y + xf[2] * z + xf[9]
            by = xf[3] * x + xf[4] * y + xf[5] * z + xf[10]
            bz = xf[6] * x + xf[7] * y + xf[8] * z + xf[11]
            rb = Nb[b, 3]
            c0 = int(Na[a, CS])
            for c in range(c0, c0 + na):
                dx = bx - Na[c, 0]
                dy = by - Na[c, 1]
                dz = bz - Na[c, 2]
                s = thr + Na[c, 3] + rb
                d2 = dx * dx + dy * dy + dz * dz
                if s > 0.0 and d2 < s * s:  # squared test; sqrt only for kept pairs
                    st[sp, 0] = c
                    st[sp, 1] = b
                    sv[sp] = math.sqrt(d2) - Na[c, 3] - rb
                    sp += 1
        else:
            ax = Na[a, 0]
            ay = Na[a, 1]
            az = Na[a, 2]
            ra = Na[a, 3]
            c0 = int(Nb[b, CS])
            for c in range(c0, c0 + nb):
                x = Nb[c, 0]
                y = Nb[c, 1]
                z = Nb[c, 2]
                dx = xf[0] * x + xf[1] * y + xf[2] * z + xf[9] - ax
                dy = xf[3] * x + xf[4] * y + xf[5] * z + xf[10] - ay
                dz = xf[6] * x + xf[7] * y + xf[8] * z + xf[11] - az
                s = thr + ra + Nb[c, 3]
                d2 = dx * dx + dy * dy + dz * dz
                if s > 0.0 and d2 < s * s:
                    st[sp, 0] = a
                    st[sp, 1] = c
                    sv[sp] = math.sqrt(d2) - ra - Nb[c, 3]
                    sp += 1
        _sort_desc(st, sv, top, sp)  # nearest pair popped first
    return best, base, visits


@njit(cache=True)
def descend_min(Na, Nb, xf, st, sv, base, sp, best, tol, pair, stop_at, visits):
    """``descend`` in ``MIN`` mode (which never touches ``acc``: ``sv`` stands in for it)."""
    return descend(Na, Nb, xf, st, sv, base, sp, best, tol, pair, stop_at, visits, MIN, sv)


@njit(cache=True)
def min_distance(Na, Nb, xf, st, sv, best, tol, pair, stop_at):
    """Plain traversal from the two roots (Weller's Algorithm 5.2). Returns ``(best, code, visits)``."""
    st[0, 0] = 0
    st[0, 1] = 0
    sv[0] = pair_value(Na, Nb, xf, 0, 0)
    best, spx, visits = descend_min(Na, Nb, xf, st, sv, 0, 1, best, tol, pair, stop_at, 0)
    return best, (OK if spx >= 0 else STACK_FULL), visits


@njit(cache=True)
def min_distance_backtrack(Na, Nb, xf, st, sv, tol, pair, stop_at):
    """Backtracking traversal (the seed's Algorithms 1-2).

    Starts from the leaf pair in ``pair`` (last frame's answer), whose current value is the
    first bound, and climbs towards the roots: at each step one side moves to its parent
    ``P`` and only ``P``'s other children are traversed against the other side, because the
    pair just left is already fully searched. At ``(root, root)`` everything is covered, so
    the answer equals the plain traversal's.
    """
    x = pair[0]
    y = pair[1]
    best = pair_value(Na, Nb, xf, x, y)
    visits = 1
    if best <= stop_at:
        return best, OK, visits
    cap = st.shape[0]
    while x != 0 or y != 0:
        # climb the side whose parent is smaller (keeps the pair balanced)
        climb_a = y == 0 or (x != 0 and Na[int(Na[x, PAR]), 3] <= Nb[int(Nb[y, PAR]), 3])
        N = Na if climb_a else Nb
        came = x if climb_a else y
        p = int(N[came, PAR])
        sp = 0
        c0 = int(N[p, CS])
        for c in range(c0, c0 + int(N[p, CC])):
            if c != came and sp < cap:
                a = c if climb_a else x
                b = y if climb_a else c
                v = pair_value(Na, Nb, xf, a, b)
                if v < best - tol:
                    st[sp, 0] = a
                    st[sp, 1] = b
                    sv[sp] = v
                    sp += 1
        if climb_a:
            x = p
        else:
            y = p
        _sort_desc(st, sv, 0, sp)  # visit the nearest sibling first
        best, spx, visits = descend_min(Na, Nb, xf, st, sv, 0, sp, best, tol, pair, stop_at, visits)
        if spx < 0:
            return best, STACK_FULL, visits
        if best <= stop_at:
            break
    return best, OK, visits


# --------------------------------------------------------------------------- leaf pair geometry


GEOM_W = 12  # leaf_geometry's row: normal, point on A's ball, point on B's ball, contact point


@njit(cache=True)
def leaf_geometry(Na, Nb, xf, a, b, out):
    """Normal (A→B), point on A's ball, point on B's ball, contact point, in A's frame, into ``out[0:12]``.

    Returns the signed distance. Coincident centres get the normal +z (any unit vector is a
    valid separating direction for two concentric balls).
    """
    bx, by, bz = _to_a(xf, Nb, b)
    dx = bx - Na[a, 0]
    dy = by - Na[a, 1]
    dz = bz - Na[a, 2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d > 1e-300:
        nx = dx / d
        ny = dy / d
        nz = dz / d
    else:
        nx = 0.0
        ny = 0.0
        nz = 1.0
    ra = Na[a, 3]
    rb = Nb[b, 3]
    # contact point: middle of the two balls' common chord on the centre line (clamped, so
    # it stays inside both balls even when one contains the other)
    lo = max(-ra, d - rb)
    hi = min(ra, d + rb)
    t = 0.5 * (lo + hi)
    out[9] = Na[a, 0] + t * nx
    out[10] = Na[a, 1] + t * ny
    out[11] = Na[a, 2] + t * nz
    out[0] = nx
    out[1] = ny
    out[2] = nz
    out[3] = Na[a, 0] + ra * nx
    out[4] = Na[a, 1] + ra * ny
    out[5] = Na[a, 2] + ra * nz
    out[6] = bx - rb * nx
    out[7] = by - rb * ny
    out[8] = bz - rb * nz
    return d - ra - rb


CROSS = 0.5  # a pair is "crossed" when its overlap exceeds this fraction of the smaller radius


@njit(cache=True)
def contact_normal(Na, Nb, xf, a, b, out, min_climb=0):
    """Unit contact normal (A→B, A's frame) of leaf pair ``(a, b)`` into ``out[0:3]``.

    The centre-to-centre direction of two balls that overlap by more than about their
    smaller radius can point backwards (the small ball of B has passed the small ball of
    A's centre): deep penetration of thin features. Then the direction is taken from the
    nearest ancestors whose overlap is shallow relative to their size: their centres lie
    deeper inside each object, so their direction keeps the larger-scale geometry.
    ``min_climb`` climbs at least that many levels anyway: sibling leaves share the normal,
    so it does not jump when the deepest pair moves to a neighbouring leaf (penalty forces).
    Returns the number of levels climbed.
    """
    climbed = 0
    while True:
        dx, dy, dz, d = _offset(Na, Nb, xf, a, b)
        ra = Na[a, 3]
        rb = Nb[b, 3]
        deep = ra + rb - d > CROSS * min(ra, rb)
        if (climbed >= min_climb and not deep or (a == 0 and b == 0)) and d > 1e-300:
            out[0] = dx / d
            out[1] = dy / d
            out[2] = dz / d
            return climbed
        if a == 0 and b == 0:  # concentric roots: any direction separates
            out[0] = 0.0
            out[1] = 0.0
            out[2] = 1.0
            return climbed
        if b == 0 or (a != 0 and ra <= rb):
            a = int(Na[a, PAR])
        else:
            b = int(Nb[b, PAR])
        climbed += 1


@njit(cache=True)
def _climb_inside(Na, Nb, Xa, Xb, xf, a, b, out):
    """``contact_normal``'s climb for a deep pair, through ancestors whose centres lie inside
    their solids only (``Xa[:, 3]``; a hollow object's inner nodes have theirs in its cavity):
    into ``out[0:3]`` the direction of the nearest pair that overlaps shallowly, or of the
    highest such ancestors when the climb would leave both solids first (centres deep inside
    each, so their direction keeps the larger-scale geometry). False for coincident centres."""
    while True:
        dx, dy, dz, d = _offset(Na, Nb, xf, a, b)
        ra = Na[a, 3]
        rb = Nb[b, 3]
        pa = int(Na[a, PAR]) if a != 0 else -1
        pb = int(Nb[b, PAR]) if b != 0 else -1
        oka = pa >= 0 and Xa[pa, 3] > 0.0
        okb = pb >= 0 and Xb[pb, 3] > 0.0
        if (not ra + rb - d > CROSS * min(ra, rb) or not (oka or okb)) and d > 1e-300:
            out[0] = dx / d
            out[1] = dy / d
            out[2] = dz / d
            return True
        if oka and (ra <= rb or not okb):
            a = pa
        elif okb:
            b = pb
        else:
            return False


@njit(cache=True)
def surface_normal(Na, Nb, Xa, Xb, xf, a, b, out):
    """Unit contact normal (A→B, A's frame) of leaf pair ``(a, b)`` into ``out[0:3]``: the
    centres' direction, turned round where the balls have crossed.

    Two small balls pressed past each other's centres (an object driven into a wall by a fast
    impact or MuJoCo's soft contacts) give a centre direction that points backwards. For a
    deep pair the nearest shallowly overlapping ancestors answer (as ``contact_normal``), but
    only through ancestors whose centres lie inside their solids (``_climb_inside``): in a
    hollow object they lie in its cavity (a cup's root is in its bowl). The meshes also say
    which side is out: ``Xa``, ``Xb``
    ``(n, 3)`` are the leaves' exit directions (``exit_directions``: from the centre towards
    the nearest point of the mesh, in the tree's frame, shorter where that is ambiguous), and
    ``Xa - R Xb`` (their first three columns) points from A into B for leaves of surfaces that meet, whatever their depth
    up to the middle of the thinner object. Only its sign is used, and only where it is
    clear: an exit direction is arbitrary at the medial axis (a ball's centre, a leaf filling
    a wall), the centres' direction is not. Then a deep pair's normal (overlap beyond ``DEEP``
    of the smaller radius) becomes the surfaces' own where
    their exits are trusted (``TRUSTED``): the mean of both when they agree (``FACES_COS``, two
    faces pressed together), the trusted one against a leaf without (a round object's centre),
    when within ``NEAR_COS`` of the centres' direction: a flat floor's normal instead of the
    tilt of two small balls' centres. Where the two disagree by less than
    ``CROSS_SIDE`` (past the middle of a wall the exits point the same way) the centres'
    direction stays; the hook then keeps the side of approach (``hook._side_of_approach``).
    With ``Xa`` empty it is the centres' direction. Returns the pair's overlap over the smaller
    radius (the hook's "deep").
    """
    dx, dy, dz, d = _offset(Na, Nb, xf, a, b)
    ra = Na[a, 3]
    rb = Nb[b, 3]
    if d > 1e-300:
        nx, ny, nz = dx / d, dy / d, dz / d
    else:
        nx, ny, nz = 0.0, 0.0, 1.0
    s = (ra + rb - d) / min(ra, rb)
    if Xa.shape[0] > a and Xb.shape[0] > b:
        ex = Xa[a, 0] - (xf[0] * Xb[b, 0] + xf[1] * Xb[b, 1] + xf[2] * Xb[b, 2])
        ey = Xa[a, 1] - (xf[3] * Xb[b, 0] + xf[4] * Xb[b, 1] + xf[5] * Xb[b, 2])
        ez = Xa[a, 2] - (xf[6] * Xb[b, 0] + xf[7] * Xb[b, 1] + xf[8] * Xb[b, 2])
        if s > CROSS and _climb_inside(Na, Nb, Xa, Xb, xf, a, b, out):
            nx, ny, nz = out[0], out[1], out[2]
        elif nx * ex + ny * ey + nz * ez < -CROSS_SIDE:
            nx, ny, nz = -nx, -ny, -nz
        # a deep pair takes the surfaces' own normal where they can be trusted (a shallow one keeps
        # its centres' direction): both exits when they agree (two faces pressed together), the
        # one trusted exit against a round object's centre leaf;
        # exits that disagree (an edge or a corner on a face) leave the centres' direction
        ux, uy, uz = Xa[a, 0], Xa[a, 1], Xa[a, 2]
        vx = -(xf[0] * Xb[b, 0] + xf[1] * Xb[b, 1] + xf[2] * Xb[b, 2])
        vy = -(xf[3] * Xb[b, 0] + xf[4] * Xb[b, 1] + xf[5] * Xb[b, 2])
        vz = -(xf[6] * Xb[b, 0] + xf[7] * Xb[b, 1] + xf[8] * Xb[b, 2])
        lu = math.sqrt(ux * ux + uy * uy + uz * uz)
        lv = math.sqrt(vx * vx + vy * vy + vz * vz)
        mx = my = mz = 0.0
        if lu > TRUSTED and lv > TRUSTED:
            if (ux * vx + uy * vy + uz * vz) / (lu * lv) > FACES_COS:
                mx, my, mz = ux / lu + vx / lv, uy / lu + vy / lv, uz / lu + vz / lv
        elif lu > TRUSTED:
            mx, my, mz = ux, uy, uz
        elif lv > TRUSTED:
            mx, my, mz = vx, vy, vz
        mm = math.sqrt(mx * mx + my * my + mz * mz)
        if s > DEEP and mm > 1e-9 and mx * nx + my * ny + mz * nz > NEAR_COS * mm:
            nx, ny, nz = mx / mm, my / mm, mz / mm
    out[0] = nx
    out[1] = ny
    out[2] = nz
    return s


# |Xa - R Xb| is 2 for surfaces that face each other: a centre direction this far against it
# (dot product) is taken as crossed. Larger leaves more tilted crossings alone; smaller turns
# round directions the exits do not really oppose (near a medial axis, where they are arbitrary)
CROSS_SIDE = 0.5
# an exit direction is trusted beyond this length (``exit_directions``: the leaf's far side is
# this fraction of its radius from the opposite surface); two trusted exits are one face pressed
# on another within this angle (cosine): looser takes edges for faces, tighter leaves curved
# faces to the bumpier centre directions (tilted by up to the leaves' size over their distance)
TRUSTED = 0.5
FACES_COS = 0.9
# ... and they replace the centres' direction only within this of it (cosine): two coplanar side
# faces at the corners of tooth tips pressed on tooth tips agree with each other, not with the
# centres, which lie one above the other; looser keeps more of the tilt at a patch's edge
NEAR_COS = 0.3
# overlap over the smaller radius beyond which the hook treats a contact as deep (its normal may
# then keep the side of approach)
DEEP = 0.25


def exit_directions(N, surface) -> np.ndarray:
    """``(n, 4)`` per node of packed tree ``N``: a leaf's exit direction (from its centre
    towards the nearest point of the mesh it fills, ``surface`` from ``geometry.surface``: the
    outward gradient of the mesh's distance there), scaled by how much it can be trusted, zero
    for inner nodes; then 1 where the node's centre lies inside the solid, else 0.

    A leaf that spans its wall (its far side touches the opposite surface too) or sits at a
    round object's centre lies on the medial axis, where the nearest point jumps between sides
    and the direction is arbitrary. The length is the far side's distance from the surface over
    the radius, clipped to 1: 1 for a leaf that touches one side only, 0 for one that fills the
    wall.
    """
    from ..geometry.surface import signed_distances

    X = np.zeros((N.shape[0], 4))
    if not N.shape[0]:
        return X
    X[:, 3] = signed_distances(surface, N[:, :3])[0] < 0.0
    leaf = np.flatnonzero(N[:, CC] == 0)
    if leaf.size:
        C, r = N[leaf, :3], N[leaf, 3]
        G = signed_distances(surface, C)[1]
        far = np.abs(signed_distances(surface, C - r[:, None] * G)[0])
        X[leaf, :3] = G * np.clip(far / np.maximum(r, 1e-300), 0.0, 1.0)[:, None]
        X[leaf, 3] = 1.0  # inner spheres lie inside by construction
    return X


BLEND_W = 21  # words of ``blend``'s accumulator


@njit(cache=True)
def _add_blend(Na, Nb, xf, a, b, cut, acc):
    """Add leaf pair ``(a, b)`` with weight ``cut - d`` (d its signed distance) to ``acc`` (see ``blend``)."""
    g = acc[9:21]
    w = cut - leaf_geometry(Na, Nb, xf, a, b, g)
    if not w > 0.0:
        return
    px = g[9]
    py = g[10]
    pz = g[11]
    contact_normal(Na, Nb, xf, a, b, g, int(acc[8]))
    acc[0] += w
    acc[1] += w * g[0]
    acc[2] += w * g[1]
    acc[3] += w * g[2]
    acc[4] += w * px
    acc[5] += w * py
    acc[6] += w * pz
    acc[7] += 1.0


@njit(cache=True)
def blend(Na, Nb, xf, st, sv, ga, gb, cut, climb, acc, pair):
    """Weighted mean normal and contact point of the leaf pairs under ``(ga, gb)`` below ``cut``.

    Each leaf pair at signed distance d < cut counts with weight ``cut - d`` (its normal from
    ``contact_normal`` climbing at least ``climb`` levels, its point the middle of the common
    chord). The weights are continuous in the pose and vanish as a pair leaves, so the means
    are continuous too, where the deepest pair alone jumps when another pair becomes deepest.
    With ``cut`` halfway between the deepest pair and the contact threshold, the means stay
    near the deepest spot yet pass smoothly from one spot to the next.

    ``acc`` (``BLEND_W``,) receives: total weight, ``Σ w n`` (A→B, 3), ``Σ w x`` (3, A's frame),
    number of pairs; the rest is scratch. Returns ``(code, visits)``.
    """
    for k in range(8):
        acc[k] = 0.0
    acc[8] = climb
    st[0, 0] = ga
    st[0, 1] = gb
    sv[0] = pair_value(Na, Nb, xf, ga, gb)
    _, spx, visits = descend(Na, Nb, xf, st, sv, 0, 1, cut, 0.0, pair, -np.inf, 0, BLEND, acc)
    return (OK if spx >= 0 else STACK_FULL), visits


# --------------------------------------------------------------------------- multipoint


@njit(cache=True)
def ancestor_at(N, n, depth):
    """Ancestor of node ``n`` at ``depth`` (``n`` itself if it is shallower)."""
    while N[n, DEP] > depth:
        n = int(N[n, PAR])
    return n


@njit(cache=True)
def _keep_candidate(cand, cval, n, a, b, pair, best):
    """Add group ``(a, b)``'s deepest pair; when full, replace the shallowest if this one is deeper."""
    cap_cand = cand.shape[0]
    if n < cap_cand:
        k = n
        n += 1
    else:
        k = 0
        for i in range(1, cap_cand):
            if cval[i] > cval[k]:
                k = i
        if best >= cval[k]:
            return n
    cand[k, 0] = a
    cand[k, 1] = b
    cand[k, 2] = pair[0]
    cand[k, 3] = pair[1]
    cval[k] = best
    return n


@njit(cache=True)
def multipoint(Na, Nb, xf, st, sv, split_depth, margin, prev, n_prev, cand, cval, pair):
    """Candidates for multipoint contacts: the deepest leaf pair of every group.

    Descends from the roots splitting only nodes above ``split_depth``. Each pair of
    subtrees rooted at ``split_depth`` (or at a shallower leaf) whose value is below
    ``margin`` is a group; its minimum signed leaf-pair distance is searched with the
    plain descent. The search is seeded with last frame's contact of the same group
    (rows of ``prev``: group a, group b, leaf a, leaf b), which prunes most of it.

    ``cand[k] = (group a, group b, leaf a, leaf b)``, ``cval[k]`` its signed distance
    (``< margin``). When more groups than ``len(cand)`` are found, the deepest are kept; once
    the list is full, the shallowest kept value replaces ``margin`` as the threshold, since a
    group can only enter by beating it. So a large margin (``mj_geomDistance``'s ``distmax``)
    costs about as much as the margin the deepest ``len(cand)`` groups need, and the result
    is the same. Returns ``(n_candidates, code, visits)``.
    """
    cap = st.shape[0]
    cap_cand = cand.shape[0]
    n = 0
    visits = 0
    thr = margin
    st[0, 0] = 0
    st[0, 1] = 0
    sv[0] = pair_value(Na, Nb, xf, 0, 0)
    sp = 1
    while sp > 0:
        sp -= 1
        if sv[sp] >= thr:
            continue
        a = st[sp, 0]
        b = st[sp, 1]
        visits += 1
        open_a = Na[a, CC] > 0 and Na[a, DEP] < split_depth
        open_b = Nb[b, CC] > 0 and Nb[b, DEP] < split_depth
        if open_a or open_b:
            split_a = open_a and ((not open_b) or Na[a, 3] >= Nb[b, 3])
            nk = (Na[a, CC] if split_a else Nb[b, CC])
            if sp + nk > cap:
                return n, STACK_FULL, visits
            sp = _push_children(Na, Nb, xf, a, b, split_a, thr, st, sv, sp)
            continue
        # a group: seed with last frame's contact of this group, if any
        best = thr
        pair[0] = -1
        pair[1] = -1
        for k in range(n_prev):
            if prev[k, 0] == a and prev[k, 1] == b:
                v = pair_value(Na, Nb, xf, prev[k, 2], prev[k, 3])
                if v < best:
                    best = v
                    pair[0] = prev[k, 2]
                    pair[1] = prev[k, 3]
                break
        # the group's own descent runs on the stack above the outer entries
        st[sp, 0] = a
        st[sp, 1] = b
        best, spx, visits = descend_min(Na, Nb, xf, st, sv, sp, sp + 1, best, 0.0, pair, -np.inf, visits)
        if spx < 0:
            return n, STACK_FULL, visits
        if pair[0] < 0:
            continue
        n = _keep_candidate(cand, cval, n, a, b, pair, best)
        if n == cap_cand:
            thr = cval[0]
            for i in range(1, cap_cand):
                thr = max(thr, cval[i])
    return n, OK, visits


@njit(cache=True)
def front_search(Na, Nb, xf, st, sv, front, nf, margin, cand, cval, pair):
    """``multipoint`` restricted to a list of groups (a *front*), seeded per group.

    ``front[k] = (group a, group b, leaf a, leaf b)``: groups known to hold every leaf pair
    that can now be below ``margin`` (see the hook's motion-bounded front). Each group's
    minimum below ``margin`` is searched exactly; a group's seed leaf pair is updated to its
    new minimum. Candidates as in ``multipoint``. Returns ``(n_candidates, code, visits)``.
    """
    n = 0
    visits = 0
    for k in range(nf):
        a = front[k, 0]
        b = front[k, 1]
        visits += 1
        root = pair_value(Na, Nb, xf, a, b)
        if root >= margin:
            continue
        best = margin
        pair[0] = -1
        pair[1] = -1
        v = pair_value(Na, Nb, xf, front[k, 2], front[k, 3])
        if v < best:
            best = v
            pair[0] = front[k, 2]
            pair[1] = front[k, 3]
        st[0, 0] = a
        st[0, 1] = b
        sv[0] = root
        best, spx, visits = descend_min(Na, Nb, xf, st, sv, 0, 1, best, 0.0, pair, -np.inf, visits)
        if spx < 0:
            return n, STACK_FULL, visits
        if pair[0] < 0:
            continue
        front[k, 2] = pair[0]
        front[k, 3] = pair[1]
        n = _keep_candidate(cand, cval, n, a, b, pair, best)
    return n, OK, visits


@njit(cache=True)
def select_spread(Na, Nb, xf, cand, cval, n, k_max, chosen, geom, dmin):
    """Pick up to ``k_max`` of ``n`` leaf-pair candidates (``select.spread``: the deepest
    first, then farthest-point over the contact points in A's frame).

    ``geom[i, 0:12]`` receives each candidate's normal, ball points and contact point. Returns the count.
    """
    if n == 0 or k_max <= 0:
        return 0
    for i in range(n):
        leaf_geometry(Na, Nb, xf, cand[i, 2], cand[i, 3], geom[i])
    return spread(geom, 9, cval, n, k_max, chosen, dmin)


# --------------------------------------------------------------------------- penetration volume


@njit(cache=True)
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
def _add_lens(Na, Nb, xf, a, b, acc):
    """Add the lens of leaf pair ``(a, b)`` to ``acc`` (see ``penetration``)."""
    dx, dy, dz, d = _offset(Na, Nb, xf, a, b)
    ra = Na[a, 3]
    rb = Nb[b, 3]
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
    acc[4] += v * (Na[a, 0] + t * nx)
    acc[5] += v * (Na[a, 1] + t * ny)
    acc[6] += v * (Na[a, 2] + t * nz)
    acc[7] += 1.0


@njit(cache=True)
def penetration(Na, Nb, xf, st, sv, acc, pair):
    """Sum of lens volumes of all overlapping leaf pairs (Weller & Zachmann).

    ``acc`` (8,) receives: volume, force vector ``Σ V n`` (A→B, 3), volume-weighted lens
    centre ``Σ V x`` (3, divide by volume), number of overlapping leaf pairs.
    Returns ``(code, visits)``.
    """
    for k in range(8):
        acc[k] = 0.0
    st[0, 0] = 0
    st[0, 1] = 0
    sv[0] = pair_value(Na, Nb, xf, 0, 0)
    _, spx, visits = descend(Na, Nb, xf, st, sv, 0, 1, 0.0, 0.0, pair, -np.inf, 0, VOLUME, acc)
    return (OK if spx >= 0 else STACK_FULL), visits
