"""The collision function MuJoCo calls for IST-managed geom pairs (numba cfuncs).

One cfunc per collision-table slot (mesh-mesh, mesh-sdf, sdf-sdf, and sphere, capsule,
cylinder, box against mesh: ``mjist.query.primitive``). MuJoCo's narrow phase
calls it as ``int f(const mjModel* m, mjData* d, mjPreContact* con, int g1, int g2,
mjtNum margin)``; no Python runs. It looks ``m`` up in the registry (``registry.py`` writes
it, ``layout.py`` declares its words), and for a managed pair:

1. poses of ``g1``, ``g2`` from ``d->geom_xpos/xmat`` (tree frame == MuJoCo's mesh frame);
2. the motion-bound skip: if last full distance query of this (MjData, pair) minus the
   relative motion since then still exceeds ``margin + offset``, no contact is possible;
3. multipoint traversal with threshold ``margin + offset``, seeded by last frame's groups;
4. the deepest then farthest-apart ``cap`` contacts into ``con`` — never more than the
   pair's ``mj_maxContact`` (more corrupts MuJoCo's heap);
5. when nothing is in contact and skipping is on, a backtracking distance query refreshes
   the skip reference.

With ``mjist_narrowphase='surface'`` the threshold of 3 is ``margin + ε1 + ε2`` (every leaf
pair whose surfaces can be within ``margin`` of each other lies in a group below it), and
the distance, point and normal of the deepest ``mjist_surface_groups`` groups come from the
meshes themselves (``query.narrow``: ``geometry.surface.local_distance`` started at the
group's deepest leaf pair) before 4. Those contacts are held: while B stays within
``mjist_surface_hold`` of the pose they were measured at, a call moves them with B instead of
measuring again (``_held_contacts``), so a resting pair keeps the same contacts with smoothly
changing depths and settles instead of flipping between descents' answers. The penalty forces (``forces.py``) call ``pair_contacts``
too, with ``soft``: every group's overlap depth at its blended point (``_surface_penalty``),
continuous in the pose where a descent's answer is not.

A distance request (``mj_geomDistance``, distance sensors: ``con`` is not in the MjData's
arena, see ``distance_request``) skips 2-5: its caller reads only the smallest distance, so it
gets one contact from a backtracking distance query, whatever ``margin`` (``distmax``) it passes.

Scratch memory comes from MuJoCo's own per-``mjData`` stack (``mj_stackAllocByte``), the
coherence state from a per-model table of (MjData, pair) slots claimed with an atomic
compare-and-swap, so several MjData on several threads never share anything writable.
The state only prunes work: every answer equals a fresh query's (up to exact ties), except
held surface contacts, which follow the MjData's own trajectory; either way rollouts are
deterministic whatever the threads. Nothing here raises; problems are counted.
"""
from __future__ import annotations

import math

import numpy as np
from numba import carray, cfunc, njit, types

from ..geometry import sdfgrid
from ..geometry import surface as sf
from ..query import narrow as nw
from ..query import primitive as cp
from ..query import traverse as tv
from ..query.select import spread
from . import abi
from .layout import (
    ENTRY_WORDS,
    F_D,
    F_FOK,
    F_FT0,
    F_FTHR,
    F_FXF,
    F_HC,
    F_HN,
    F_HOK,
    F_HXF,
    F_LOK,
    F_LXF,
    F_MARGIN,
    F_NPN,
    F_OK,
    F_PN,
    F_PT,
    F_REF,
    F_TIME,
    FW,
    H_B,
    H_DIST,
    H_NORMAL,
    H_POINT,
    H_WAY,
    HOLD_W,
    I_FRONT,
    I_NFRONT,
    I_NPREV,
    I_PAIR,
    I_PREV,
    IW,
    KP,
    MAX_MODELS,
    N_COUNT,
    NG,
    PAIR_GEOM_W,
    POSE_W,
    PRIM_F,
    ROOT_MODELS,
    ROOT_N,
    ROOT_ORIG,
    ROOT_WORDS,
    SLOTS,
    STACK_RESERVE,
    SURF_F,
    SURF_W,
    Count,
    Entry,
    pair_floats,
    pair_ints,
    pair_scratch_bytes,
    prim_floats,
    prim_ints,
    prim_scratch_bytes,
    slot_key,
)

SLACK_MIN, SLACK_MAX, SLACK_MOTION = 0.05, 0.5, 4.0  # front slack: fractions of ε1+ε2, x last step's motion


@njit(cache=True)
def model_entry(m):
    """Address of the registry entry of model ``m`` (0: not attached)."""
    root_addr = abi.registry_root()
    if root_addr == 0:
        return 0
    root = carray(abi.i64_ptr(root_addr), ROOT_WORDS)
    n = root[ROOT_N]
    for i in range(min(n, MAX_MODELS)):
        if root[ROOT_MODELS + 2 * i] == m:
            return root[ROOT_MODELS + 2 * i + 1]
    return 0


@njit(cache=True)
def geom_pose(xpos, xmat, g, P):
    """``P`` = 4x4 world pose of geom ``g`` from mjData's ``geom_xpos``/``geom_xmat`` arrays."""
    for i in range(3):
        for j in range(3):
            P[i, j] = xmat[9 * g + 3 * i + j]
        P[i, 3] = xpos[3 * g + i]
    P[3, 0] = 0.0
    P[3, 1] = 0.0
    P[3, 2] = 0.0
    P[3, 3] = 1.0


@njit(cache=True)
def claim_slot(E, d, p, nslot, other):
    """Index of the (d, pair) state slot (its second one if ``other``), claimed on first use;
    -1 when the table is full."""
    key = slot_key(d, p, other)
    keys_addr = E[Entry.KEYS]
    keys = carray(abi.i64_ptr(keys_addr), nslot)
    h = ((d >> 4) ^ (p * 2654435761) ^ (other * 40503)) % nslot
    for k in range(nslot):
        i = (h + k) % nslot
        cur = keys[i]
        if cur == key:
            return i, False
        if cur == 0:
            old = abi.cas_i64(keys_addr + 8 * i, 0, key)
            if old == 0:
                return i, True
            if old == key:  # pragma: no cover - only this thread uses this key
                return i, False
    return -1, False


@njit(cache=True)
def stack_room(E, d, need):
    """Whether MuJoCo's stack of ``d`` can give ``need`` bytes and keep STACK_RESERVE free.

    The arena fields read here describe the caller's stack only without a thread pool; with
    one, MuJoCo gives each thread its own stack and the check is left to it.
    """
    if abi.load_i64(d + E[Entry.POOL]) != 0:
        return True
    free = abi.load_i64(d + E[Entry.NARENA]) - abi.load_i64(d + E[Entry.PSTACK]) - abi.load_i64(d + E[Entry.PARENA])
    return free >= need + STACK_RESERVE


@njit(cache=True)
def pair_trees(E, g1, g2):
    """The packed trees ``(Na, Nb)`` of managed geoms ``g1``, ``g2``."""
    Na, Nb, _, _ = pair_arrays(E, g1, g2)
    return Na, Nb


@njit(cache=True)
def pair_exits(E, g1, g2):
    """The trees' exit directions ``(Xa, Xb)`` of managed geoms ``g1``, ``g2`` (``traverse.exit_directions``)."""
    _, _, Xa, Xb = pair_arrays(E, g1, g2)
    return Xa, Xb


@njit(cache=True)
def pair_arrays(E, g1, g2):
    """``(Na, Nb, Xa, Xb)``: the packed trees of managed geoms ``g1``, ``g2`` and their exit directions."""
    nman = E[Entry.NMAN]
    gslot = carray(abi.i64_ptr(E[Entry.GSLOT]), E[Entry.NGEOM])
    trees = carray(abi.i64_ptr(E[Entry.TREES]), 3 * nman)
    ka = gslot[g1]
    kb = gslot[g2]
    Na = carray(abi.f64_ptr(trees[3 * ka]), (trees[3 * ka + 1], 8))
    Nb = carray(abi.f64_ptr(trees[3 * kb]), (trees[3 * kb + 1], 8))
    Xa = carray(abi.f64_ptr(trees[3 * ka + 2]), (trees[3 * ka + 1], 4))
    Xb = carray(abi.f64_ptr(trees[3 * kb + 2]), (trees[3 * kb + 1], 4))
    return Na, Nb, Xa, Xb


@njit(cache=True)
def _pair_scratch(E, scratch, cap):
    """Views of a pair call's scratch (``layout.pair_floats``, ``layout.pair_ints``): float64
    poses, stack values, candidate values, dmin, geometry rows, a stateless slot, the blend
    accumulator; then int64 stack pairs, candidates, chosen, closest pair, a stateless slot."""
    ns = E[Entry.STACK]
    nc = E[Entry.NCAND]
    nf = pair_floats(ns, nc)
    f = carray(abi.f64_ptr(scratch), nf)
    Pa = f[0:16].reshape((4, 4))
    Pb = f[16:32].reshape((4, 4))
    xf = f[32:POSE_W]
    sv = f[POSE_W:POSE_W + ns]
    o = POSE_W + ns
    cval = f[o:o + nc]
    dmin = f[o + nc:o + 2 * nc]
    o += 2 * nc
    geom = f[o:o + PAIR_GEOM_W * nc].reshape((nc, PAIR_GEOM_W))
    o += PAIR_GEOM_W * nc
    fs_local = f[o:o + FW]
    bacc = f[o + FW:o + FW + tv.BLEND_W]
    iw = carray(abi.i64_ptr(scratch + 8 * nf), pair_ints(ns, nc, cap))
    st = iw[0:2 * ns].reshape((ns, 2))
    cand = iw[2 * ns:2 * ns + 4 * nc].reshape((nc, 4))
    chosen = iw[2 * ns + 4 * nc:2 * ns + 4 * nc + cap]
    q = 2 * ns + 4 * nc + cap
    pair = iw[q:q + 2]
    is_local = iw[q + 2:q + 2 + IW]
    return Pa, Pb, xf, sv, cval, dmin, geom, fs_local, bacc, st, cand, chosen, pair, is_local


@njit(cache=True)
def _posed(E, d, g1, g2, Pa, Pb, xf):
    """``Pa``, ``Pb`` ← the two geoms' world poses, ``xf`` ← B in A's frame; False for a bad pose."""
    xpos = abi.f64_ptr(abi.load_i64(d + E[Entry.XPOS]))
    xmat = abi.f64_ptr(abi.load_i64(d + E[Entry.XMAT]))
    geom_pose(xpos, xmat, g1, Pa)
    geom_pose(xpos, xmat, g2, Pb)
    return tv.relative_pose(Pa, Pb, xf)


@njit(cache=True)
def _write_row(row, dist, Pa, g):
    """A contact row of ``con``: ``dist``, then the point (``g[9:12]``) and normal (``g[0:3]``)
    of A's frame in world coordinates; the frame's other axes are MuJoCo's to complete."""
    _write_row_at(row, dist, Pa, g[9], g[10], g[11], g[0], g[1], g[2])


@njit(cache=True)
def _write_row_at(row, dist, Pa, px, py, pz, nx, ny, nz):
    """``_write_row`` with the point ``p`` and normal ``n`` (A's frame) given apart."""
    row[0] = dist
    for r in range(3):
        row[1 + r] = Pa[r, 0] * px + Pa[r, 1] * py + Pa[r, 2] * pz + Pa[r, 3]
        row[4 + r] = Pa[r, 0] * nx + Pa[r, 1] * ny + Pa[r, 2] * nz
        row[7 + r] = 0.0


@njit(cache=True)
def pair_contacts(E, m, d, con, g1, g2, margin, p, cap, scratch, soft):
    """Contacts of a managed pair into ``con``; returns the count (0..cap). ``soft``: rows for the
    penalty forces (with surfaces, ``_surface_penalty``'s)."""
    nman = E[Entry.NMAN]
    count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
    Na, Nb = pair_trees(E, g1, g2)
    offset = carray(abi.f64_ptr(E[Entry.OFFSET]), nman * nman)[p]
    eps = carray(abi.f64_ptr(E[Entry.EPS]), nman * nman)[p]
    surface = E[Entry.NARROW] != 0
    thr = margin + (eps if surface else offset)
    Pa, Pb, xf, sv, cval, dmin, geom, fs_local, bacc, st, cand, chosen, pair, is_local = _pair_scratch(E, scratch, cap)

    if not _posed(E, d, g1, g2, Pa, Pb, xf):
        count[Count.BAD_POSE] += 1
        return 0
    ist, fst = _slot_state(E, d, p, margin, Na.shape[0], Nb.shape[0], is_local, fs_local, count)

    # motion of B relative to A since the last call sizes the front's slack
    step = 0.0
    if fst[F_LOK] > 0.0:
        step = tv.motion_bound(fst[F_LXF:F_LXF + 12], xf, Nb[0, 0:3], Nb[0, 3])
    for k in range(12):
        fst[F_LXF + k] = xf[k]
    fst[F_LOK] = 1.0

    skip = E[Entry.SKIP] != 0
    if skip and fst[F_OK] > 0.0:
        mb = tv.motion_bound(fst[F_REF:F_REF + 12], xf, Nb[0, 0:3], Nb[0, 3])
        if fst[F_D] - mb >= thr:
            count[Count.SKIPPED] += 1
            fst[F_NPN] = 0.0
            return 0
    hold = carray(abi.f64_ptr(E[Entry.HOLD]), nman * nman)[p] if surface and not soft else 0.0
    if hold > 0.0 and fst[F_HOK] > 0.0 and tv.motion_bound(fst[F_HXF:F_HXF + 12], xf, Nb[0, 0:3], Nb[0, 3]) <= hold:
        count[Count.HELD_CALLS] += 1
        return _held_contacts(fst, xf, Pa, margin, con, cap)
    nheld = int(fst[F_HN]) if hold > 0.0 and fst[F_HOK] > 0.0 else 0  # measured again below
    fst[F_HOK] = 0.0
    n, code, use_front = _groups(E, Na, Nb, xf, ist, fst, thr, eps, step, skip, st, sv, cand, cval, pair, count)
    if code != tv.OK:
        ist[I_NPREV] = 0
        fst[F_FOK] = 0.0
        count[Count.FAILED] += 1
        return 0
    prev = ist[I_PREV:I_PREV + 4 * KP].reshape((KP, 4))
    keep = min(n, KP)
    for i in range(keep):
        for c in range(4):
            prev[i, c] = cand[i, c]
    ist[I_NPREV] = keep
    if n == 0:
        fst[F_NPN] = 0.0
        if skip and not use_front:
            _refresh_skip(Na, Nb, xf, ist, fst, st, sv, pair)
        return 0
    fst[F_OK] = 0.0
    if surface:
        if soft:
            k = _surface_penalty(E, Na, Nb, xf, Pa, g1, g2, cand, cval, n, margin, eps, geom, chosen, con, cap, scratch,
                                 count, st, sv, bacc, pair)
        else:
            k = _surface_contacts(E, Na, Nb, xf, Pa, g1, g2, cand, cval, n, margin, eps, geom, chosen, dmin, con, cap,
                                  scratch, count, fst, nheld, step)
            if hold > 0.0:
                _hold(fst, xf, Pa, con, k, geom, chosen)
        if k == 0:
            return 0
    else:
        k = tv.select_spread(Na, Nb, xf, cand, cval, n, cap, chosen, geom, dmin)
        Xa, Xb = pair_exits(E, g1, g2)
        _write_contacts(E, Na, Nb, Xa, Xb, xf, Pa, cand, cval, chosen, k, geom, thr, offset, st, sv, bacc, pair, con,
                        cap, count, fst, step)
    ist[I_PAIR] = cand[chosen[0], 2]
    ist[I_PAIR + 1] = cand[chosen[0], 3]
    count[Count.CONTACT_CALLS] += 1
    count[Count.CONTACTS] += k
    return k


@njit(cache=True)
def _hold(fst, xf, Pa, con, k, geom, chosen):
    """Keep the ``k`` surface contacts just written to ``con`` (at most ``KP``) in A's frame, with
    B's surface point in B's frame, the way each was measured (``geom[chosen[j], narrow.WAY]``)
    and the pose ``xf`` they were measured at (``_held_contacts``)."""
    rows = carray(abi.f64_ptr(con), (max(k, 1), abi.PRECONTACT_DOUBLES))
    hc = fst[F_HC:F_HC + HOLD_W * KP].reshape((KP, HOLD_W))
    for j in range(k):
        row = rows[j]
        h = hc[j]
        h[H_DIST] = row[0]
        for r in range(3):  # world -> A's frame: Ra^T (x - ta)
            h[H_POINT + r] = (Pa[0, r] * (row[1] - Pa[0, 3]) + Pa[1, r] * (row[2] - Pa[1, 3])
                              + Pa[2, r] * (row[3] - Pa[2, 3]))
            h[H_NORMAL + r] = Pa[0, r] * row[4] + Pa[1, r] * row[5] + Pa[2, r] * row[6]
        # B's point: the contact point is midway between A's closest point and it, along the normal
        bx = h[H_POINT] + 0.5 * row[0] * h[H_NORMAL]
        by = h[H_POINT + 1] + 0.5 * row[0] * h[H_NORMAL + 1]
        bz = h[H_POINT + 2] + 0.5 * row[0] * h[H_NORMAL + 2]
        h[H_B], h[H_B + 1], h[H_B + 2] = sf.to_b(xf, bx, by, bz)
        h[H_WAY] = geom[chosen[j], nw.WAY]
    for r in range(12):
        fst[F_HXF + r] = xf[r]
    fst[F_HN] = k
    fst[F_HOK] = 1.0


@njit(cache=True)
def _held_contacts(fst, xf, Pa, margin, con, cap):
    """The held surface contacts moved with B to the pose ``xf``: each keeps its normal and B's
    surface point (moved with B), and its distance changes by that point's motion along the
    normal (exact for a plane of A; the error is second order in the motion); the contact point
    stays midway between B's point and A's plane. Those no longer within ``margin`` are left
    out. Returns the count written."""
    out = carray(abi.f64_ptr(con), (cap, abi.PRECONTACT_DOUBLES))
    hc = fst[F_HC:F_HC + HOLD_W * KP].reshape((KP, HOLD_W))
    k = 0
    for j in range(min(int(fst[F_HN]), cap)):
        h = hc[j]
        dist = h[H_DIST]
        nx, ny, nz = h[H_NORMAL], h[H_NORMAL + 1], h[H_NORMAL + 2]
        # B's point now (xf: A <- B) minus where it was, in A's frame
        bx, by, bz = sf.to_a(xf, h[H_B], h[H_B + 1], h[H_B + 2])
        mx = bx - (h[H_POINT] + 0.5 * dist * nx)
        my = by - (h[H_POINT + 1] + 0.5 * dist * ny)
        mz = bz - (h[H_POINT + 2] + 0.5 * dist * nz)
        mn = mx * nx + my * ny + mz * nz
        if not dist + mn < margin:
            continue
        _write_row_at(out[k], dist + mn, Pa, h[H_POINT] + mx - 0.5 * mn * nx, h[H_POINT + 1] + my - 0.5 * mn * ny,
                      h[H_POINT + 2] + mz - 0.5 * mn * nz, nx, ny, nz)
        k += 1
    return k


@njit(cache=True)
def distance_request(E, d, con, raw):
    """Whether MuJoCo asks for the distance only: ``mj_geomDistance`` (and the distance sensors
    that call it) passes a contact buffer on the caller's own C stack, while ``mj_collision``'s
    buffers come from the MjData's arena, where ``raw`` (our scratch, just taken from that
    arena's stack) also lies. A buffer within the arena's size of ``raw`` is treated as
    ``mj_collision``'s: a wrong guess that way only costs time, never contacts."""
    narena = abi.load_i64(d + E[Entry.NARENA])
    return not (raw - narena < con < raw + narena)


@njit(cache=True)
def pair_distance(E, d, con, g1, g2, margin, p, cap, scratch):
    """A distance request (see ``distance_request``): the caller reads only the smallest
    distance, so one contact from the pair's minimum leaf pair (backtracking from this slot's
    last answer) instead of the contact groups within ``margin`` (``distmax``, often far larger
    than a contact margin). Its distance equals the groups' deepest. With the surface narrow
    phase, the smallest of the surfaces' distances over the groups within ε1+ε2 of the IST's
    minimum, or that minimum when it is smaller and positive. Returns 0 or 1."""
    count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
    Na, Nb = pair_trees(E, g1, g2)
    offset = carray(abi.f64_ptr(E[Entry.OFFSET]), E[Entry.NMAN] * E[Entry.NMAN])[p]
    Pa, Pb, xf, sv, cval, _, geom, fs_local, _, st, cand, _, pair, is_local = _pair_scratch(E, scratch, cap)
    g = geom[0]

    if not _posed(E, d, g1, g2, Pa, Pb, xf):
        count[Count.BAD_POSE] += 1
        return 0
    ist, fst = _slot_state(E, d, p, margin, Na.shape[0], Nb.shape[0], is_local, fs_local, count)
    best, code, visits = _closest(Na, Nb, xf, ist, st, sv, pair)
    count[Count.VISITS] += visits
    if code != tv.OK:
        count[Count.FAILED] += 1
        return 0
    row = carray(abi.f64_ptr(con), abi.PRECONTACT_DOUBLES)
    if E[Entry.NARROW] != 0:
        eps = carray(abi.f64_ptr(E[Entry.EPS]), E[Entry.NMAN] * E[Entry.NMAN])[p]
        if not best - eps < margin:  # the surfaces are at least best - ε1 - ε2 apart
            return 0
        la, lb = pair[0], pair[1]
        j = _surface_distance(E, Na, Nb, xf, g1, g2, best, eps, ist, st, sv, cand, cval, geom, pair, cap, scratch,
                              count)
        sval = _surface_scratch(E, scratch, cap)[0]
        # both are upper bounds of a separated pair's distance (the spheres lie inside the
        # meshes): the spheres answer when the descents ended above them; a negative surface
        # value is a measured depth, which the spheres' overlap is not
        if j >= 0 and (sval[j] < 0.0 or not best < sval[j]):
            if not sval[j] < margin:
                return 0
            _write_row(row, sval[j], Pa, geom[j])
            return 1
        if j < 0:
            count[Count.FAILED] += 1
        pair[0], pair[1] = la, lb
        g = geom[0]
    if not best < margin + offset:
        return 0
    tv.leaf_geometry(Na, Nb, xf, pair[0], pair[1], g)
    Xa, Xb = pair_exits(E, g1, g2)
    tv.surface_normal(Na, Nb, Xa, Xb, xf, pair[0], pair[1], g)
    _write_row(row, best - offset, Pa, g)
    return 1


@njit(cache=True)
def _slot_state(E, d, p, margin, na, nb, is_local, fs_local, count):
    """The (int, float) coherence state of this (MjData, pair), claimed or reset as needed.

    The state is only valid along one trajectory (time never decreases), so a reset or a new
    MjData at a recycled address starts fresh. It serves one margin: mj_collision passes the
    pair's, mj_geomDistance its distmax, and a distance query between two steps would otherwise
    reset the steps' front and seeds (the answers stay the same, the work does not): calls with
    another margin get a second slot. A full table gives the scratch's stateless slot.
    """
    nslot = E[Entry.NSLOT]
    now = abi.load_f64(d + E[Entry.TIME])
    s, fresh = claim_slot(E, d, p, nslot, 0)
    if s >= 0:
        fst = carray(abi.f64_ptr(E[Entry.FSTATE] + 8 * FW * s), FW)
        if not fresh and not (fst[F_TIME] <= now):
            fresh = True
        if not fresh and fst[F_MARGIN] != margin:
            s, fresh = claim_slot(E, d, p, nslot, 1)
            if s >= 0:
                fst = carray(abi.f64_ptr(E[Entry.FSTATE] + 8 * FW * s), FW)
                if not fresh and not (fst[F_TIME] <= now):
                    fresh = True
    if s >= 0:
        ist = carray(abi.i64_ptr(E[Entry.ISTATE] + 8 * IW * s), IW)
    else:
        count[Count.STATELESS] += 1
        ist = is_local
        fst = fs_local
        fresh = True
    if fresh:
        ist[I_PAIR] = -1
        ist[I_PAIR + 1] = -1
        ist[I_NPREV] = 0
        ist[I_NFRONT] = 0
        fst[F_OK] = 0.0
        fst[F_FOK] = 0.0
        fst[F_LOK] = 0.0
        fst[F_NPN] = 0.0
        fst[F_HOK] = 0.0
        fst[F_MARGIN] = margin
    fst[F_TIME] = now
    if ist[I_PAIR] < 0 or ist[I_PAIR] >= na or ist[I_PAIR + 1] < 0 or ist[I_PAIR + 1] >= nb:
        ist[I_PAIR] = -1
        ist[I_PAIR + 1] = -1
    return ist, fst


@njit(cache=True)
def _groups(E, Na, Nb, xf, ist, fst, thr, eps, step, skip, st, sv, cand, cval, pair, count):
    """The contact groups below ``thr`` into ``cand``/``cval``: ``(n, code, use_front)``.

    From the front when the motion since its refresh keeps it valid (at the refresh pose every
    leaf pair below T0 lay in one of its groups; a pair below thr now moved by at most mb, so it
    was below thr + mb < T0 then); else a multipoint traversal seeded by last frame's groups,
    with a slack that refreshes the front.
    """
    na = Na.shape[0]
    nb = Nb.shape[0]
    n_prev = min(max(ist[I_NPREV], 0), KP)
    prev = ist[I_PREV:I_PREV + 4 * KP].reshape((KP, 4))
    front = ist[I_FRONT:I_FRONT + 4 * NG].reshape((NG, 4))
    use_front = False
    if skip and fst[F_FOK] > 0.0 and fst[F_FTHR] == thr:
        mb = tv.motion_bound(fst[F_FXF:F_FXF + 12], xf, Nb[0, 0:3], Nb[0, 3])
        use_front = mb < fst[F_FT0] - thr
    if use_front:
        count[Count.FRONT_CALLS] += 1
        n, code, visits = tv.front_search(Na, Nb, xf, st, sv, front, ist[I_NFRONT], thr, cand, cval, pair)
    else:
        for k in range(n_prev):
            if not (0 <= prev[k, 0] < na and 0 <= prev[k, 1] < nb and 0 <= prev[k, 2] < na and 0 <= prev[k, 3] < nb):
                n_prev = 0
                break
        slack = min(max(SLACK_MOTION * step, SLACK_MIN * eps), SLACK_MAX * eps) if skip else 0.0
        t0 = thr + slack
        n, code, visits = tv.multipoint(Na, Nb, xf, st, sv, E[Entry.SPLIT], t0, prev, n_prev, cand, cval, pair)
        fst[F_FOK] = 0.0
        if code == tv.OK and skip and n < min(NG, cand.shape[0]):
            count[Count.FRONT_REFRESHES] += 1
            for i in range(n):
                for c in range(4):
                    front[i, c] = cand[i, c]
            ist[I_NFRONT] = n
            for k in range(12):
                fst[F_FXF + k] = xf[k]
            fst[F_FT0] = t0
            fst[F_FTHR] = thr
            fst[F_FOK] = 1.0
        # keep only the contacts (below thr) among the front's groups
        m = 0
        for i in range(n):
            if cval[i] < thr:
                for c in range(4):
                    cand[m, c] = cand[i, c]
                cval[m] = cval[i]
                m += 1
        n = m
    count[Count.VISITS] += visits
    count[Count.FRONT_GROUPS] += ist[I_NFRONT]
    return n, code, use_front


@njit(cache=True)
def _closest(Na, Nb, xf, ist, st, sv, pair):
    """The pair's minimum leaf pair into ``pair``, backtracking from the slot's last one (plain
    from the roots without one); the slot keeps it. Returns ``(best, code, visits)``."""
    if ist[I_PAIR] >= 0:
        pair[0] = ist[I_PAIR]
        pair[1] = ist[I_PAIR + 1]
        best, code, visits = tv.min_distance_backtrack(Na, Nb, xf, st, sv, 0.0, pair, -np.inf)
    else:
        best, code, visits = tv.min_distance(Na, Nb, xf, st, sv, np.inf, 0.0, pair, -np.inf)
    if code == tv.OK:
        ist[I_PAIR] = pair[0]
        ist[I_PAIR + 1] = pair[1]
    else:
        ist[I_PAIR] = -1
        ist[I_PAIR + 1] = -1
    return best, code, visits


@njit(cache=True)
def _refresh_skip(Na, Nb, xf, ist, fst, st, sv, pair):
    """Nothing in contact: the far-skip reference becomes the true IST distance (backtracking
    from last frame's closest pair)."""
    best, code, _ = _closest(Na, Nb, xf, ist, st, sv, pair)
    if code == tv.OK:
        for k in range(12):
            fst[F_REF + k] = xf[k]
        fst[F_D] = best
        fst[F_OK] = 1.0


@njit(cache=True)
def _write_contacts(E, Na, Nb, Xa, Xb, xf, Pa, cand, cval, chosen, k, geom, thr, offset, st, sv, bacc, pair, con, cap,
                    count, fst, step):
    """The ``k`` chosen candidates as MuJoCo contacts (world frame) into ``con``.

    Their normals turn to the meshes' own as they get deep (``traverse.surface_normal``); a deep
    contact whose normal turns more than 60° from last step's contact nearest to it (within its depth
    and size, the pair having moved less than that) keeps last step's: an object pressed past
    the middle of a wall is pushed back out the side it came from (the side of approach).
    Penalty rows keep the ancestors' normals, blended over the group (smooth forces).
    """
    out = carray(abi.f64_ptr(con), (cap, abi.PRECONTACT_DOUBLES))
    mem = fst[F_PN:F_PN + 6 * KP].reshape((KP, 6))
    nmem = int(fst[F_NPN])
    for j in range(k):
        i = chosen[j]
        g = geom[i]
        if E[Entry.NUP] > 0:
            tv.contact_normal(Na, Nb, xf, cand[i, 2], cand[i, 3], g, E[Entry.NUP])
        else:
            s = tv.surface_normal(Na, Nb, Xa, Xb, xf, cand[i, 2], cand[i, 3], g)
            reach = 2.0 * (abs(cval[i]) + Na[cand[i, 2], 3] + Nb[cand[i, 3], 3])
            if s > tv.DEEP and nmem > 0 and step < reach:
                _side_of_approach(mem, nmem, g, reach)
        if E[Entry.NUP] > 0 and cval[i] < thr:
            count[Count.VISITS] += _blend_group(Na, Nb, xf, st, sv, cand[i, 0], cand[i, 1], 0.5 * (thr + cval[i]), E[Entry.NUP],
                                            bacc, pair, g)
        _write_row(out[j], cval[i] - offset, Pa, g)
    _remember(fst, geom, chosen, k)


# a deep contact's normal may turn this far from last step's (cosine) before it is taken for a
# flip: more keeps true turns of a fast-rotating pair, less catches the flips that are not reversals
TURN_COS = 0.5


@njit(cache=True)
def _side_of_approach(mem, nmem, g, reach):
    """Turn normal ``g[0:3]`` back to the side it came from: the normal of the remembered contact
    nearest to point ``g[9:12]`` when that one lies within ``reach`` and is more than 60° away."""
    best = _nearest_remembered(mem, nmem, g, reach)
    if best >= 0 and mem[best, 3] * g[0] + mem[best, 4] * g[1] + mem[best, 5] * g[2] < TURN_COS:
        for r in range(3):
            g[r] = mem[best, 3 + r]


@njit(cache=True)
def _nearest_remembered(mem, nmem, g, reach):
    """The row of ``mem[:nmem]`` (last call's contacts: point, normal) whose point is nearest
    to ``g[9:12]``, within ``reach`` (-1: none)."""
    best = -1
    bd = reach * reach
    for m in range(nmem):
        d2 = (mem[m, 0] - g[9]) ** 2 + (mem[m, 1] - g[10]) ** 2 + (mem[m, 2] - g[11]) ** 2
        if d2 < bd:
            bd = d2
            best = m
    return best


@njit(cache=True)
def _remember(fst, geom, chosen, k):
    """Keeps the contacts ``chosen[:k]`` (at most ``KP``; point and normal of their ``geom``
    rows, A's frame) and the time, for the next call's side of approach."""
    mem = fst[F_PN:F_PN + 6 * KP].reshape((KP, 6))
    keep = min(k, KP)
    for j in range(keep):
        g = geom[chosen[j]]
        for r in range(3):
            mem[j, r] = g[9 + r]
            mem[j, 3 + r] = g[r]
    fst[F_NPN] = keep
    fst[F_PT] = fst[F_TIME]


@njit(cache=True)
def _blend_group(Na, Nb, xf, st, sv, ga, gb, cut, climb, acc, pair, g):
    """Penalty mode: the group's normal and point (``g[0:3]``, ``g[9:12]``) become the means of
    its leaf pairs below ``cut`` (``traverse.blend``), so its force turns continuously when
    another spot of the group becomes the deepest. Left as they are if the means degenerate.
    Returns the node pairs visited."""
    code, visits = tv.blend(Na, Nb, xf, st, sv, ga, gb, cut, climb, acc, pair)
    if code != tv.OK or not acc[0] > 0.0:
        return visits
    nn = math.sqrt(acc[1] * acc[1] + acc[2] * acc[2] + acc[3] * acc[3])
    if not nn > 1e-9 * acc[0]:  # opposite normals cancel: keep the deepest pair's
        return visits
    for r in range(3):
        g[r] = acc[1 + r] / nn
        g[9 + r] = acc[4 + r] / acc[0]
    return visits


@njit(cache=True)
def _surface(E, g):
    """The packed surface (``geometry.surface.unpack``) of managed geom ``g``, with its grid."""
    k = carray(abi.i64_ptr(E[Entry.GSLOT]), E[Entry.NGEOM])[g]
    tab = carray(abi.i64_ptr(E[Entry.SURF]), SURF_W * E[Entry.NMAN])[SURF_W * k:SURF_W * k + SURF_W]
    nv = tab[2]
    nf = tab[3]
    m = tab[4]
    fl = carray(abi.f64_ptr(tab[0]), sf.float_words(nv, nf, m))
    it = carray(abi.i64_ptr(tab[1]), sf.int_words(nf))
    gh = carray(abi.f64_ptr(tab[5]), sdfgrid.HDR_W)
    gt = carray(abi.i32_ptr(tab[6]), int(gh[4]) * int(gh[5]) * int(gh[6]))
    gv = carray(abi.i32_ptr(tab[7]), tab[8] * sdfgrid.NODES)
    return sf.unpack(fl, it, nv, nf, m, gh, gt, gv)


@njit(cache=True)
def _surface_scratch(E, scratch, cap):
    """The surface narrow phase's part of a pair call's scratch (the tails of
    ``layout.pair_floats`` and ``layout.pair_ints``): candidate values, ``local_distance``'s
    temporaries and answer, the surface queries' stack."""
    ns = E[Entry.STACK]
    nc = E[Entry.NCAND]
    nf = pair_floats(ns, nc)
    f = carray(abi.f64_ptr(scratch), nf)
    o = nf - nc - SURF_F
    sval = f[o:o + nc]
    tmp = f[o + nc:o + nc + sf.REFINE_W]
    res = f[o + nc + sf.REFINE_W:o + nc + sf.REFINE_W + 7]
    ni = pair_ints(ns, nc, cap)
    sst = carray(abi.i64_ptr(scratch + 8 * nf), ni)[ni - sf.STACK:ni]
    return sval, tmp, res, sst


@njit(cache=True)
def _measure(E, SA, SB, Na, Nb, xf, cand, n, below, eps, geom, sval, tmp, res, sst, count, ways):
    """``narrow.measure`` with the hook's counters."""
    m, failed = nw.measure(SA, SB, Na, Nb, xf, cand, n, below, eps, geom, sval, tmp, res, sst, ways)
    count[Count.SURFACE_GROUPS] += n
    count[Count.FAILED] += failed
    return m


@njit(cache=True)
def _surface_contacts(E, Na, Nb, xf, Pa, g1, g2, cand, cval, n, margin, eps, geom, chosen, dmin, con, cap, scratch,
                      count, fst, nheld, step):
    """Surface narrow phase: the distances on the meshes of the deepest of the ``n`` groups by
    the IST (``narrow.deepest``), and of the ``nheld`` contacts held until this call, and those
    within ``margin`` as contacts into ``con`` (the deepest, then the most spread, one per point),
    each pushing out the side it came in by (``_surface_approach``; ``step``: how far the pair
    moved since the last call). Returns the count; ``chosen[0]`` indexes the deepest in ``cand``."""
    sval, tmp, res, sst = _surface_scratch(E, scratch, cap)
    SA = _surface(E, g1)
    SB = _surface(E, g2)
    out = carray(abi.f64_ptr(con), (cap, abi.PRECONTACT_DOUBLES))
    n = nw.screen(SA, SB, Na, Nb, xf, cand, cval, n, E[Entry.NARROW], geom, tmp, sst)
    # beside held contacts (a pair that was at rest) the groups one way only: a second way that
    # nearly ties with the held contacts' trades places with them and kicks the pair
    ways = sf.FORWARD if nheld > 0 else sf.EITHER
    m = _measure(E, SA, SB, Na, Nb, xf, cand, n, margin, eps, geom, sval, tmp, res, sst, count, ways)
    m = _remeasure_held(fst, nheld, SA, SB, xf, margin, eps, cand, geom, sval, m, E[Entry.NCAND], tmp, res, sst, count)
    k = spread(geom, 9, sval, m, cap, chosen, dmin)
    kk = nw.distinct(geom, chosen, k, eps)  # groups whose descents ended at one point give one contact
    _surface_approach(fst, SA, SB, xf, geom, sval, chosen, kk, step, eps, sst, res)
    for j in range(kk):
        _write_row(out[j], sval[chosen[j]], Pa, geom[chosen[j]])
    return kk


# how far from a surface contact, in its depths, last call's contacts are looked for to tell its
# side of approach: farther finds one for every point of a wide face pressed past a wall's middle
# (last call's contacts are few and spread out), nearer keeps apart opposite contacts of a thin
# part squeezed between two faces
APPROACH_REACH = 4.0
# a surface contact deeper than this multiple of ε1 + ε2 takes its depth along its side of
# approach when that is deeper (``surface.lowest_inside``, no longer a signed distance): lower
# extends that to shallower contacts (a walk over B's vertices each), higher leaves deeper ones
# levelled off at a wall's middle
APPROACH_DEEP = 1.0


@njit(cache=True)
def _surface_approach(fst, SA, SB, xf, geom, sval, chosen, k, step, eps, stack, tmp):
    """The side of approach for surface contacts (``chosen[:k]``, rows of ``geom`` and
    ``sval``), which are then remembered for the next call.

    A point pressed past the middle of a wall is nearer the far side: its signed distance gives
    the depth to there and a normal that pushes it on through. A penetrating contact whose
    normal turns more than 60° (``TURN_COS``) from last call's contact nearest to it (within
    ``APPROACH_REACH`` times its depth, the pair having moved less than the depth since, and
    the MjData's time having advanced: a pose set by hand is no step) has crossed that middle: it
    takes last call's normal. Its depth, and a deep contact's (``APPROACH_DEEP``)
    when that is larger, is then measured along that side: how far B's lowest point inside A
    near the contact (``surface.lowest_inside``; for a contact measured the reverse way, A's
    point inside B) must move along the normal to leave the solid it is in
    (``surface.ray_exit``), so the contact pushes it back the way it came, the deeper the
    harder, and does not level off at the wall's middle. ``tmp``: 7 floats."""
    mem = fst[F_PN:F_PN + 6 * KP].reshape((KP, 6))
    nmem = int(fst[F_NPN]) if fst[F_PT] < fst[F_TIME] else 0
    for j in range(k):
        i = chosen[j]
        v = sval[i]
        reach = -APPROACH_REACH * v
        if not (v < 0.0 and nmem > 0 and step < -v):
            continue
        g = geom[i]
        best = _nearest_remembered(mem, nmem, g, reach)
        if best < 0:
            continue
        flipped = mem[best, 3] * g[0] + mem[best, 4] * g[1] + mem[best, 5] * g[2] < TURN_COS
        if not (flipped or -v > APPROACH_DEEP * eps):
            continue
        nx, ny, nz = (mem[best, 3], mem[best, 4], mem[best, 5]) if flipped else (g[0], g[1], g[2])
        if int(g[nw.WAY]) == sf.REVERSE:
            # A's point inside B leaves B along -n as B moves along n
            px, py, pz = g[9] - 0.5 * v * g[0], g[10] - 0.5 * v * g[1], g[11] - 0.5 * v * g[2]
            bx, by, bz = sf.to_b(xf, px, py, pz)
            dx = -(xf[0] * nx + xf[3] * ny + xf[6] * nz)  # -n in B's frame: -R^T n
            dy = -(xf[1] * nx + xf[4] * ny + xf[7] * nz)
            dz = -(xf[2] * nx + xf[5] * ny + xf[8] * nz)
            t = sf.ray_exit(SB, bx, by, bz, dx, dy, dz, stack)
            h = -0.5
        else:
            # B's point inside A, then B's lowest point along -n inside A near it, leaves A along n
            px, py, pz = g[9] + 0.5 * v * g[0], g[10] + 0.5 * v * g[1], g[11] + 0.5 * v * g[2]
            bx, by, bz = sf.to_b(xf, px, py, pz)
            f = sf.closest_face(SB, bx, by, bz, stack, tmp)
            t = np.inf
            if f >= 0:  # lowest along n: n in B's frame, R^T n
                dx = xf[0] * nx + xf[3] * ny + xf[6] * nz
                dy = xf[1] * nx + xf[4] * ny + xf[7] * nz
                dz = xf[2] * nx + xf[5] * ny + xf[8] * nz
                lx, ly, lz, ok = sf.lowest_inside(SB, f, SA, xf, dx, dy, dz, stack, tmp)
                if ok:
                    # its depth, at the contact's own place (contacts of a face pressed flat stay spread)
                    t = sf.ray_exit(SA, lx, ly, lz, nx, ny, nz, stack)
                    lo = (lx - px) * nx + (ly - py) * ny + (lz - pz) * nz
                    px, py, pz = px + lo * nx, py + lo * ny, pz + lo * nz
            if not t < np.inf:
                t = sf.ray_exit(SA, px, py, pz, nx, ny, nz, stack)
            h = 0.5
        if not t < np.inf or not (flipped or t > -v):
            continue
        g[0], g[1], g[2] = nx, ny, nz
        g[9], g[10], g[11] = px + h * t * nx, py + h * t * ny, pz + h * t * nz
        sval[i] = -t
    _remember(fst, geom, chosen, k)


@njit(cache=True)
def _remeasure_held(fst, nheld, SA, SB, xf, margin, eps, cand, geom, sval, m, nc, tmp, res, sst, count):
    """The ``nheld`` contacts held until this call, measured again from their points of B (moved
    with B), each its own way only (``surface.contact_distance``), and appended after the ``m``
    measured groups, so that a measurement continues the
    contacts it held (the descents from one spot end at one point, and ``narrow.distinct`` keeps
    one of them) instead of trading them for another set at a pose a micrometre away. Returns
    the new count."""
    hc = fst[F_HC:F_HC + HOLD_W * KP].reshape((KP, HOLD_W))
    for j in range(nheld):
        if m >= nc:
            break
        h = hc[j]
        x, y, z = sf.to_a(xf, h[H_B], h[H_B + 1], h[H_B + 2])
        count[Count.SURFACE_GROUPS] += 1
        # no leaf pair of its own: the first group's keeps the bookkeeping valid
        m, ok = nw.measure_from(SA, SB, xf, x, y, z, margin, eps, 0, cand, geom, sval, m, tmp, res, sst,
                                int(h[H_WAY]) & sf.EITHER or sf.EITHER)  # its own way
        count[Count.FAILED] += not ok
    return m


@njit(cache=True)
def _surface_penalty(E, Na, Nb, xf, Pa, g1, g2, cand, cval, n, margin, eps, geom, chosen, con, cap, scratch, count, st,
                     sv, bacc, pair):
    """The penalty forces' rows on the surfaces: each group (``cap`` at most, the deepest by the
    IST) at the point and normal its leaf pairs blend to (``_blend_group``), with the overlap
    thickness of the meshes there along that normal (``surface.overlap_depth``) as its depth.
    All three are continuous in the pose and the depth is positive only where the solids truly
    overlap; every group deeper than ``-margin`` is a row (no selection, no merging), so the
    summed force is continuous. Returns the count; ``chosen[0]`` indexes the deepest."""
    sval, tmp, res, sst = _surface_scratch(E, scratch, cap)
    SA = _surface(E, g1)
    SB = _surface(E, g2)
    out = carray(abi.f64_ptr(con), (cap, abi.PRECONTACT_DOUBLES))
    n = nw.deepest(cand, cval, n, cap) if n > cap else n
    thr = margin + eps
    m = 0
    for i in range(n):
        g = geom[i]
        tv.leaf_geometry(Na, Nb, xf, cand[i, 2], cand[i, 3], g)
        count[Count.VISITS] += _blend_group(Na, Nb, xf, st, sv, cand[i, 0], cand[i, 1], 0.5 * (thr + cval[i]), E[Entry.NUP],
                                        bacc, pair, g)
        depth = sf.overlap_depth(SA, SB, xf, g[9], g[10], g[11], g[0], g[1], g[2], eps, sst, res)
        count[Count.SURFACE_GROUPS] += 1
        if not depth == depth:  # a surface query failed
            count[Count.FAILED] += 1
        elif depth > -margin:
            if m == 0 or depth > -sval[chosen[0]]:
                chosen[0] = i
            sval[i] = -depth
            _write_row(out[m], -depth, Pa, g)
            m += 1
    return m


@njit(cache=True)
def _surface_distance(E, Na, Nb, xf, g1, g2, best, eps, ist, st, sv, cand, cval, geom, pair, cap, scratch, count):
    """A distance request on the surfaces: of the groups whose leaf pairs are within ε1+ε2 of the
    IST's minimum ``best`` (the surfaces' closest points lie in one of them), the deepest
    (``narrow.deepest``) measured on the meshes. Returns the index in ``cand``/``geom`` of the smallest (-1: none), its distance in
    the first word of the surface scratch's values."""
    sval, tmp, res, sst = _surface_scratch(E, scratch, cap)
    prev = ist[I_PREV:I_PREV + 4 * KP].reshape((KP, 4))
    n, code, visits = tv.multipoint(Na, Nb, xf, st, sv, E[Entry.SPLIT], best + eps, prev, 0, cand, cval, pair)
    count[Count.VISITS] += visits
    if code != tv.OK:
        return -1
    n = nw.deepest(cand, cval, n, E[Entry.NARROW])
    m = _measure(E, _surface(E, g1), _surface(E, g2), Na, Nb, xf, cand, n, np.inf, eps, geom, sval, tmp, res, sst,
                 count, sf.EITHER)
    return nw.smallest(sval, m)


@njit(cache=True)
def _managed_prim(E, d, con, gm, gp, mesh_first, k, pi, cap, margin, scratch):
    """Contacts of tree ``k`` (geom ``gm``) against primitive ``pi`` (geom ``gp``); returns the count.

    ``mesh_first``: MuJoCo passed the mesh as geom1, so the normal (primitive → mesh) flips.
    """
    count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
    nman = E[Entry.NMAN]
    trees = carray(abi.i64_ptr(E[Entry.TREES]), 3 * nman)
    N = carray(abi.f64_ptr(trees[3 * k]), (trees[3 * k + 1], 8))
    prim = carray(abi.f64_ptr(E[Entry.PRIM]), (E[Entry.NPRIM], 4))
    offset = carray(abi.f64_ptr(E[Entry.POFF]), E[Entry.NPRIM] * nman)[pi * nman + k]
    ns = E[Entry.STACK]
    nc = E[Entry.NCAND]
    # scratch (float64): Pm, Pp (16 each), xf (12), q (6), values, dmin, geometry rows;
    # then int64: stack, candidates (group, leaf), chosen
    nf = prim_floats(nc)
    f = carray(abi.f64_ptr(scratch), nf)
    Pm = f[0:16].reshape((4, 4))
    Pp = f[16:32].reshape((4, 4))
    xf = f[32:44]
    q = f[44:50]
    cval = f[PRIM_F:PRIM_F + nc]
    dmin = f[PRIM_F + nc:PRIM_F + 2 * nc]
    geom = f[PRIM_F + 2 * nc:nf].reshape((nc, cp.GEOM_W))
    iw = carray(abi.i64_ptr(scratch + 8 * nf), prim_ints(ns, nc, cap))
    st = iw[0:ns]
    cand = iw[ns:ns + 2 * nc].reshape((nc, 2))
    chosen = iw[ns + 2 * nc:ns + 2 * nc + cap]
    xpos = abi.f64_ptr(abi.load_i64(d + E[Entry.XPOS]))
    xmat = abi.f64_ptr(abi.load_i64(d + E[Entry.XMAT]))
    geom_pose(xpos, xmat, gm, Pm)
    geom_pose(xpos, xmat, gp, Pp)
    if not tv.relative_pose(Pp, Pm, xf):  # tree frame -> primitive frame
        count[Count.BAD_POSE] += 1
        return 0
    n, code, visits = cp.tree_contacts(N, int(prim[pi, 0]), prim[pi, 1], prim[pi, 2], prim[pi, 3], xf,
                                       margin + offset, E[Entry.SPLIT], st, cand, cval, geom, q)
    count[Count.VISITS] += visits
    if code != tv.OK:
        count[Count.FAILED] += 1
        return 0
    if n == 0:
        return 0
    k_out = spread(geom, 3, cval, n, cap, chosen, dmin)  # contact points at columns 3..5
    out = carray(abi.f64_ptr(con), (cap, abi.PRECONTACT_DOUBLES))
    sign = -1.0 if mesh_first else 1.0
    for j in range(k_out):
        i = chosen[j]
        row = out[j]
        row[0] = cval[i] - offset
        for r in range(3):
            row[1 + r] = Pp[r, 0] * geom[i, 3] + Pp[r, 1] * geom[i, 4] + Pp[r, 2] * geom[i, 5] + Pp[r, 3]
            row[4 + r] = sign * (Pp[r, 0] * geom[i, 0] + Pp[r, 1] * geom[i, 1] + Pp[r, 2] * geom[i, 2])
            row[7 + r] = 0.0
    count[Count.PRIMITIVE_CONTACTS] += k_out
    return k_out


@njit(cache=True)
def _collide_prim(E, d, con, g1, g2, ka, kb, margin):
    """The primitive path of ``collide``; -1 when the pair is not ours."""
    ngeom = E[Entry.NGEOM]
    gprim = carray(abi.i64_ptr(E[Entry.GPRIM]), ngeom)
    if ka >= 0 and gprim[g2] >= 0:
        gm, gp, k, pi, mesh_first = g1, g2, ka, gprim[g2], True
    elif kb >= 0 and gprim[g1] >= 0:
        gm, gp, k, pi, mesh_first = g2, g1, kb, gprim[g1], False
    else:
        return -1
    nman = E[Entry.NMAN]
    cap = carray(abi.i64_ptr(E[Entry.PCAP]), E[Entry.NPRIM] * nman)[pi * nman + k]
    if cap <= 0:
        return -1
    count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
    count[Count.PRIMITIVE_CALLS] += 1
    need = prim_scratch_bytes(E[Entry.STACK], E[Entry.NCAND], cap)
    if not stack_room(E, d, need):
        count[Count.NO_STACK] += 1
        return 0
    abi.call_with_data(E[Entry.MARK], d)
    raw = abi.call_stack_alloc(E[Entry.ALLOC], d, need, 64)
    n = _managed_prim(E, d, con, gm, gp, mesh_first, k, pi, cap, margin, raw)
    abi.call_with_data(E[Entry.FREE], d)
    return n


@njit(cache=True)
def collide(slot, m, d, con, g1, g2, margin):
    """The body of every slot's cfunc (``slot`` picks the original function to fall back on)."""
    e = model_entry(m)
    root_addr = abi.registry_root()
    if e != 0:
        E = carray(abi.i64_ptr(e), ENTRY_WORDS)
        ngeom = E[Entry.NGEOM]
        if 0 <= g1 < ngeom and 0 <= g2 < ngeom:
            gslot = carray(abi.i64_ptr(E[Entry.GSLOT]), ngeom)
            ka = gslot[g1]
            kb = gslot[g2]
            if ka >= 0 and kb >= 0:
                nman = E[Entry.NMAN]
                p = ka * nman + kb
                cap = carray(abi.i64_ptr(E[Entry.CAP]), nman * nman)[p]
                if cap < 0:
                    return 0  # a penalty pair: forces.py applies its forces, no MuJoCo contact
                if cap > 0:
                    count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
                    count[Count.CALLS] += 1
                    need = pair_scratch_bytes(E[Entry.STACK], E[Entry.NCAND], cap)
                    if not stack_room(E, d, need):
                        count[Count.NO_STACK] += 1
                        return 0
                    abi.call_with_data(E[Entry.MARK], d)
                    raw = abi.call_stack_alloc(E[Entry.ALLOC], d, need, 64)
                    if distance_request(E, d, con, raw):
                        count[Count.DISTANCE_CALLS] += 1
                        k = pair_distance(E, d, con, g1, g2, margin, p, cap, raw)
                    else:
                        k = pair_contacts(E, m, d, con, g1, g2, margin, p, cap, raw, False)
                    abi.call_with_data(E[Entry.FREE], d)
                    return k
            elif E[Entry.NPRIM] > 0:
                k = _collide_prim(E, d, con, g1, g2, ka, kb, margin)
                if k >= 0:
                    return k
    root = carray(abi.i64_ptr(root_addr), ROOT_WORDS)
    return abi.call_collision(root[ROOT_ORIG + slot], m, d, con, g1, g2, margin)


_SIG = types.int32(types.int64, types.int64, types.int64, types.int32, types.int32, types.float64)

# One body per slot of ``layout.SLOTS``; the constant is the slot's index there, which picks the
# original function ``collide`` falls back on. numba caches each body's cfunc by its own name.
_MESH_MESH, _MESH_SDF, _SDF_SDF, _SPHERE_MESH, _CAPSULE_MESH, _CYLINDER_MESH, _BOX_MESH = (
    SLOTS.index(k) for k in ((abi.GEOM_MESH, abi.GEOM_MESH), (abi.GEOM_MESH, abi.GEOM_SDF), (abi.GEOM_SDF, abi.GEOM_SDF),
                             (cp.SPHERE, abi.GEOM_MESH), (cp.CAPSULE, abi.GEOM_MESH), (cp.CYLINDER, abi.GEOM_MESH),
                             (cp.BOX, abi.GEOM_MESH)))


def _mesh_mesh(m, d, con, g1, g2, margin):
    return collide(_MESH_MESH, m, d, con, g1, g2, margin)


def _mesh_sdf(m, d, con, g1, g2, margin):
    return collide(_MESH_SDF, m, d, con, g1, g2, margin)


def _sdf_sdf(m, d, con, g1, g2, margin):
    return collide(_SDF_SDF, m, d, con, g1, g2, margin)


def _sphere_mesh(m, d, con, g1, g2, margin):
    return collide(_SPHERE_MESH, m, d, con, g1, g2, margin)


def _capsule_mesh(m, d, con, g1, g2, margin):
    return collide(_CAPSULE_MESH, m, d, con, g1, g2, margin)


def _cylinder_mesh(m, d, con, g1, g2, margin):
    return collide(_CYLINDER_MESH, m, d, con, g1, g2, margin)


def _box_mesh(m, d, con, g1, g2, margin):
    return collide(_BOX_MESH, m, d, con, g1, g2, margin)


COLLISION_TABLE = {  # collision-table slot (geom types, lower first) -> the body of its cfunc
    SLOTS[_MESH_MESH]: _mesh_mesh,
    SLOTS[_MESH_SDF]: _mesh_sdf,
    SLOTS[_SDF_SDF]: _sdf_sdf,
    SLOTS[_SPHERE_MESH]: _sphere_mesh,
    SLOTS[_CAPSULE_MESH]: _capsule_mesh,
    SLOTS[_CYLINDER_MESH]: _cylinder_mesh,
    SLOTS[_BOX_MESH]: _box_mesh,
}
_CFUNCS: dict = {}


def cfunc_address(t1: int, t2: int) -> int:
    """Address of the collision cfunc for geom types ``t1``, ``t2`` (a key of ``COLLISION_TABLE``),
    compiled (or loaded from numba's cache) on first use, so a scene pays only for its slots."""
    key = (min(t1, t2), max(t1, t2))
    if key not in _CFUNCS:
        from . import prewarm

        prewarm.compile_split(COLLISION_TABLE[key], _SIG)  # a first run: its kernels on two cores
        _CFUNCS[key] = cfunc(_SIG, cache=True)(COLLISION_TABLE[key])
    return _CFUNCS[key].address


def compiled_address(t1: int, t2: int) -> int:
    """``cfunc_address`` if that cfunc exists in this process, else 0 (then it is in no table)."""
    c = _CFUNCS.get((min(t1, t2), max(t1, t2)))
    return c.address if c is not None else 0
