"""Penalty forces and the haptic virtual coupling, applied inside ``mj_step``.

MuJoCo calls ``mjcb_passive(m, d)`` once per ``mj_forward``/``mj_step`` after the collision
phase and ``mj_comVel``, so positions and velocities are current. ``passive`` (a numba cfunc
installed there while a model with penalty pairs or a coupling is attached; a callback found
there first is called first) adds to ``qfrc_passive``:

* **penalty pairs** (``mjist_mode="penalty"``; their collision slot writes no MuJoCo contact):
  - ``contacts`` law: for each contact group (a pair of subtrees at ``split_depth``, Weller's
    multipoint), depth δ = offset − d_IST ≥ 0 of its deepest leaf pair, along the group's unit
    normal n (from geom1 to geom2) at its contact point p, force on geom2's body
    ``f = max(0, k δ − c δ v_n) n`` with v_n the normal relative velocity at p
    (Hunt–Crossley: the damping grows with the depth, so the force is continuous at first touch).
    n and p are the means over the group's leaf pairs at least half as deep as the deepest,
    weighted by how much deeper than that they are (``traverse.blend``): continuous in the pose,
    where the deepest pair's own normal jumps when another spot of the group becomes the deepest
    (that jump can sustain a chatter of a held mandible). With ``mjist_narrowphase='surface'``
    δ is the meshes' overlap thickness along n at p instead (``hook._surface_penalty``),
    positive only where the solids truly overlap and continuous too;
  - ``volume`` law: Weller & Zachmann's penetration volume V (all overlapping leaf pairs' lens
    volumes), force ``max(0, k_v V − c_v V v_n) n̂`` at the overlap centroid, n̂ the
    volume-weighted normal;
  equal and opposite on geom1's body when it can move.
* **virtual coupling** (``mjist_coupling="HANDLE BODY"``): a 6-DoF spring–damper between a mocap
  body (the haptic device's handle, standing for the body's frame) and a body:
  ``F = k_t (c_h − c_b) + c_t (v_h − v_b)`` between the body's centre of mass c_b and where
  the handle puts it, c_h (no lever arm), and ``τ = k_r θ + c_r (ω_h − ω_b)`` with θ the
  rotation vector from the body's to the handle's orientation; v_h, ω_h are finite
  differences of the mocap pose over one step. −F is what the device displays.

Per (MjData, pair or coupling) the last wrench, contact count, deepest δ and V are kept in an
output row (``Handle.haptic(d)`` reads it). Nothing here allocates outside MuJoCo's stack or
raises; problems are counted.
"""
from __future__ import annotations

import functools
import math

from numba import carray, cfunc, njit, types

from ..query import traverse as tv
from . import abi, hook
from .layout import (
    CPL_BODY,
    CPL_COM,
    CPL_CR,
    CPL_CT,
    CPL_KR,
    CPL_KT,
    CPL_MOCAP,
    CPL_W,
    ENTRY_WORDS,
    F_TIME,
    FW,
    N_COUNT,
    O_DEPTH,
    O_F,
    O_HOK,
    O_N,
    O_PH,
    O_QH,
    O_T,
    O_TIME,
    O_VH,
    O_VOL,
    O_WH,
    PEN_CAP,
    PEN_W,
    PO,
    POSE_W,
    ROOT_PASSIVE,
    ROOT_WORDS,
    SMALL,
    Count,
    Entry,
    Pen,
    forces_big_bytes,
    forces_scratch_bytes,
    forces_small_floats,
)

CONTACTS, VOLUME = 0, 1  # penalty laws
OBJ_BODY, OBJ_XBODY = 1, 2  # mjtObj: a body's inertial frame (centre of mass), its body frame
VMAX, WMAX = 2.0, 30.0  # m/s, rad/s: faster handle motion between two steps is a jump, not a velocity


@njit(cache=True)
def _cross_acc(a, b, out, s):
    out[0] += s * (a[1] * b[2] - a[2] * b[1])
    out[1] += s * (a[2] * b[0] - a[0] * b[2])
    out[2] += s * (a[0] * b[1] - a[1] * b[0])


@njit(cache=True)
def _point_velocity(vel, org, p, out):
    """Linear velocity at world point ``p`` of a body with ``vel = (ω, v at org)``."""
    rx = p[0] - org[0]
    ry = p[1] - org[1]
    rz = p[2] - org[2]
    out[0] = vel[3] + vel[1] * rz - vel[2] * ry
    out[1] = vel[4] + vel[2] * rx - vel[0] * rz
    out[2] = vel[5] + vel[0] * ry - vel[1] * rx


@njit(cache=True)
def _rotate(q, x, y, z, out):
    """``out`` = unit quaternion ``q`` (w, x, y, z) applied to (x, y, z)."""
    w, a, b, c = q[0], q[1], q[2], q[3]
    tx = 2.0 * (b * z - c * y)
    ty = 2.0 * (c * x - a * z)
    tz = 2.0 * (a * y - b * x)
    out[0] = x + w * tx + (b * tz - c * ty)
    out[1] = y + w * ty + (c * tx - a * tz)
    out[2] = z + w * tz + (a * ty - b * tx)


@njit(cache=True)
def _unit_quat(q, out):
    """``out`` = ``q`` / |q|; the identity for a (near) zero quaternion, as ``mju_normalize4``."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not n > 1e-14:  # also NaN
        out[0], out[1], out[2], out[3] = 1.0, 0.0, 0.0, 0.0
        return
    for r in range(4):
        out[r] = q[r] / n


@njit(cache=True)
def quat_error(qh, qb, out):
    """Rotation vector θ of ``qh ⊗ conj(qb)`` (shortest way from the body's to the handle's orientation)."""
    w = qh[0] * qb[0] + qh[1] * qb[1] + qh[2] * qb[2] + qh[3] * qb[3]
    x = -qh[0] * qb[1] + qh[1] * qb[0] - qh[2] * qb[3] + qh[3] * qb[2]
    y = -qh[0] * qb[2] + qh[1] * qb[3] + qh[2] * qb[0] - qh[3] * qb[1]
    z = -qh[0] * qb[3] - qh[1] * qb[2] + qh[2] * qb[1] + qh[3] * qb[0]
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        out[0] = 2.0 * x
        out[1] = 2.0 * y
        out[2] = 2.0 * z
        return
    a = 2.0 * math.atan2(s, w) / s
    out[0] = a * x
    out[1] = a * y
    out[2] = a * z


@njit(cache=True)
def _penalty_pair(E, m, d, row, con, small, big, out):
    """Wrench of one penalty pair on body 2 (world force, torque about body 2's COM) into ``out``; applied.

    The contact groups come from the hook's own path (``hook.pair_contacts``: motion-bound skip,
    the front of groups, backtracking, robust normals) with MuJoCo's contact layout written
    into ``con`` instead of ``mjData.contact``; the volume law runs only when they show overlap.
    """
    b1 = int(row[Pen.B1])
    b2 = int(row[Pen.B2])
    for i in range(O_TIME):
        out[i] = 0.0
    n = hook.pair_contacts(E, m, d, con.ctypes.data, int(row[Pen.G1]), int(row[Pen.G2]), 0.0, int(row[Pen.PAIR]),
                           int(row[Pen.GROUPS]), big.ctypes.data, True)
    if n == 0:
        return
    v1 = small[0:6]
    v2 = small[6:12]
    bx = carray(abi.f64_ptr(abi.load_i64(d + E[Entry.BXPOS])), 3 * E[Entry.NBODY])
    bi = carray(abi.f64_ptr(abi.load_i64(d + E[Entry.BXIPOS])), 3 * E[Entry.NBODY])
    for i in range(6):
        v1[i] = 0.0
    if b1 >= 0:
        abi.call_object_velocity(E[Entry.OBJVEL], m, d, OBJ_XBODY, b1, v1.ctypes.data, 0)
    abi.call_object_velocity(E[Entry.OBJVEL], m, d, OBJ_XBODY, b2, v2.ctypes.data, 0)
    com = bi[3 * b2:3 * b2 + 3]
    o1 = bx[3 * max(b1, 0):3 * max(b1, 0) + 3]
    o2 = bx[3 * b2:3 * b2 + 3]
    rows = con.reshape((con.shape[0] // abi.PRECONTACT_DOUBLES, abi.PRECONTACT_DOUBLES))
    if int(row[Pen.LAW]) == CONTACTS:
        _contacts_law(E, row, rows, n, o1, o2, com, small, out)
    else:
        if not _volume_law(E, d, row, o1, o2, com, small, big, out):
            return
        out[O_DEPTH] = -rows[0, 0]
    _apply(E, m, d, b1, b2, com, small, out)


@njit(cache=True)
def _add_force(amount, k, c, v1, o1, v2, o2, com, pnt, nrm, tmp, out):
    """Hunt–Crossley force ``max(0, k a − c a v_n)`` of amount ``a`` (depth or volume) along
    ``nrm`` at ``pnt`` added to ``out`` (force, torque about ``com``); v_n is the normal speed of
    body 2 against body 1 there (velocities ``v1``, ``v2`` at origins ``o1``, ``o2``)."""
    va = tmp[0:3]
    vb = tmp[3:6]
    r3 = tmp[6:9]
    _point_velocity(v1, o1, pnt, va)
    _point_velocity(v2, o2, pnt, vb)
    vn = (vb[0] - va[0]) * nrm[0] + (vb[1] - va[1]) * nrm[1] + (vb[2] - va[2]) * nrm[2]
    mag = max(0.0, k * amount - c * amount * vn)
    for r in range(3):
        out[O_F + r] += mag * nrm[r]
        r3[r] = pnt[r] - com[r]
    _cross_acc(r3, nrm, out[O_T:O_T + 3], mag)


@njit(cache=True)
def _contacts_law(E, row, rows, n, o1, o2, com, small, out):
    """Hunt–Crossley force of each contact group in ``rows[:n]`` summed into ``out``."""
    k = row[Pen.K]
    c = row[Pen.C]
    v1, v2, pnt, nrm, tmp = small[0:6], small[6:12], small[12:15], small[15:18], small[18:27]
    # stability: each group adds ~k of stiffness along its normal; an explicit step stays
    # stable while the sum is below 4 m_eff/dt² (= 4 K_max): count the steps past it
    groups = 0
    for i in range(n):
        if -rows[i, 0] > 0.0:
            groups += 1
    if k * groups > 4.0 * row[Pen.KMAX]:
        count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
        count[Count.OVER_STIFFNESS_BUDGET] += 1
    for i in range(n):
        depth = -rows[i, 0]
        if depth <= 0.0:
            continue
        for r in range(3):
            pnt[r] = rows[i, 1 + r]
            nrm[r] = rows[i, 4 + r]
        _add_force(depth, k, c, v1, o1, v2, o2, com, pnt, nrm, tmp, out)
        out[O_N] += 1.0
        out[O_DEPTH] = max(out[O_DEPTH], depth)


@njit(cache=True)
def _volume_law(E, d, row, o1, o2, com, small, big, out):
    """Weller & Zachmann's penetration volume of all overlapping leaf pairs: its force into ``out``.

    Returns False when there is no force to apply (bad pose, failed traversal, no overlap).
    """
    k = row[Pen.K]
    c = row[Pen.C]
    g1 = int(row[Pen.G1])
    g2 = int(row[Pen.G2])
    count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
    v1, v2, pnt, nrm, tmp = small[0:6], small[6:12], small[12:15], small[15:18], small[18:27]
    acc = small[40:48]
    Na, Nb = hook.pair_trees(E, g1, g2)
    ns = E[Entry.STACK]
    Pa = big[0:16].reshape((4, 4))
    Pb = big[16:32].reshape((4, 4))
    xf = big[32:44]
    sv = big[POSE_W:POSE_W + ns]
    iw = carray(abi.i64_ptr(big.ctypes.data + 8 * (POSE_W + ns)), 2 * ns + 2)
    st = iw[0:2 * ns].reshape((ns, 2))
    pair = iw[2 * ns:2 * ns + 2]
    xpos = abi.f64_ptr(abi.load_i64(d + E[Entry.XPOS]))
    xmat = abi.f64_ptr(abi.load_i64(d + E[Entry.XMAT]))
    hook.geom_pose(xpos, xmat, g1, Pa)
    hook.geom_pose(xpos, xmat, g2, Pb)
    if not tv.relative_pose(Pa, Pb, xf):
        count[Count.BAD_POSE] += 1
        return False
    code, visits = tv.penetration(Na, Nb, xf, st, sv, acc, pair)
    count[Count.VISITS] += visits
    if code != tv.OK:
        count[Count.FAILED] += 1
        return False
    V = acc[0]
    out[O_VOL] = V
    out[O_N] = acc[7]
    L = math.sqrt(acc[1] * acc[1] + acc[2] * acc[2] + acc[3] * acc[3])
    if not (V > 0.0 and L > 0.0):
        return False
    for r in range(3):
        nrm[r] = (Pa[r, 0] * acc[1] + Pa[r, 1] * acc[2] + Pa[r, 2] * acc[3]) / L
        pnt[r] = Pa[r, 0] * acc[4] / V + Pa[r, 1] * acc[5] / V + Pa[r, 2] * acc[6] / V + Pa[r, 3]
    _add_force(V, k, c, v1, o1, v2, o2, com, pnt, nrm, tmp, out)  # onto the zeroed row
    return True


@njit(cache=True)
def _apply(E, m, d, b1, b2, com, small, out):
    """The wrench in ``out`` on body 2 at its COM, the opposite one on body 1 (same line of action)."""
    pnt = small[12:15]
    F = small[27:30]
    T = small[30:33]
    qfrc = abi.load_i64(d + E[Entry.QFRCP])
    for r in range(3):
        F[r] = out[O_F + r]
        T[r] = out[O_T + r]
        pnt[r] = com[r]
    if F[0] != 0.0 or F[1] != 0.0 or F[2] != 0.0:
        abi.call_apply_ft(E[Entry.APPLYFT], m, d, F.ctypes.data, T.ctypes.data, pnt.ctypes.data, b2, qfrc)
        if b1 >= 0:
            for r in range(3):
                F[r] = -F[r]
                T[r] = -T[r]
            abi.call_apply_ft(E[Entry.APPLYFT], m, d, F.ctypes.data, T.ctypes.data, pnt.ctypes.data, b1, qfrc)


@njit(cache=True)
def _coupling(E, m, d, row, f, out, now, fresh):
    """Virtual coupling wrench on the body (world force at its origin, torque) into ``out``; applied."""
    mid = int(row[CPL_MOCAP])
    b = int(row[CPL_BODY])
    kt = row[CPL_KT]
    ct = row[CPL_CT]
    kr = row[CPL_KR]
    cr = row[CPL_CR]
    nb = E[Entry.NBODY]
    mp = carray(abi.f64_ptr(abi.load_i64(d + E[Entry.MOCPOS])), 3 * E[Entry.NMOCAP])
    mq = carray(abi.f64_ptr(abi.load_i64(d + E[Entry.MOCQUAT])), 4 * E[Entry.NMOCAP])
    bq = carray(abi.f64_ptr(abi.load_i64(d + E[Entry.BXQUAT])), 4 * nb)
    ph = mp[3 * mid:3 * mid + 3]
    # the handle's quaternion as MuJoCo reads it: normalized (a device's integrated orientation
    # drifts off unit length; MuJoCo normalizes mocap_quat for the kinematics but not in place)
    qh = f[29:33]
    _unit_quat(mq[4 * mid:4 * mid + 4], qh)
    # handle velocity: finite difference over one step of simulated time; none after a jump
    # (a reset, a teleported handle, or state inherited by an MjData at a freed one's address:
    # Handle.forget(data) clears it)
    if fresh or out[O_HOK] == 0.0:
        for r in range(3):
            out[O_VH + r] = 0.0
            out[O_WH + r] = 0.0
    elif now > out[O_TIME]:
        dt = now - out[O_TIME]
        th = f[0:3]
        qp = f[3:7]
        for r in range(4):
            qp[r] = out[O_QH + r]
        quat_error(qh, qp, th)
        v2 = 0.0
        w2 = 0.0
        for r in range(3):
            out[O_VH + r] = (ph[r] - out[O_PH + r]) / dt
            out[O_WH + r] = th[r] / dt
            v2 += out[O_VH + r] ** 2
            w2 += out[O_WH + r] ** 2
        if dt > 1.5 * E[Entry.DT_NS] * 1e-9 or v2 > VMAX * VMAX or w2 > WMAX * WMAX:
            for r in range(3):
                out[O_VH + r] = 0.0
                out[O_WH + r] = 0.0
    if fresh or out[O_HOK] == 0.0 or now > out[O_TIME]:
        for r in range(3):
            out[O_PH + r] = ph[r]
        for r in range(4):
            out[O_QH + r] = qh[r]
        out[O_HOK] = 1.0
    # the spring acts between the body's centre of mass and where the handle puts it, so it
    # has no lever arm (a body origin far from the mass would make the coupling unstable)
    vel = f[8:14]
    abi.call_object_velocity(E[Entry.OBJVEL], m, d, OBJ_BODY, b, vel.ctypes.data, 0)
    bi = carray(abi.f64_ptr(abi.load_i64(d + E[Entry.BXIPOS])), 3 * nb)
    th = f[14:17]
    quat_error(qh, bq[4 * b:4 * b + 4], th)
    F = f[17:20]
    T = f[20:23]
    pt = f[23:26]
    hc = f[26:29]
    _rotate(qh, row[CPL_COM], row[CPL_COM + 1], row[CPL_COM + 2], hc)  # the COM's offset, turned by the handle
    for r in range(3):
        pt[r] = bi[3 * b + r]
    for r in range(3):
        wxr = out[O_WH + (r + 1) % 3] * hc[(r + 2) % 3] - out[O_WH + (r + 2) % 3] * hc[(r + 1) % 3]
        F[r] = kt * (ph[r] + hc[r] - pt[r]) + ct * (out[O_VH + r] + wxr - vel[3 + r])
        T[r] = kr * th[r] + cr * (out[O_WH + r] - vel[r])
        out[O_F + r] = F[r]
        out[O_T + r] = T[r]
    qfrc = abi.load_i64(d + E[Entry.QFRCP])
    abi.call_apply_ft(E[Entry.APPLYFT], m, d, F.ctypes.data, T.ctypes.data, pt.ctypes.data, b, qfrc)



@njit(cache=True)
def apply(E, m, d):
    """All penalty pairs and couplings of one model entry, for one MjData."""
    npen = E[Entry.NPEN]
    ncpl = E[Entry.NCPL]
    count = carray(abi.i64_ptr(E[Entry.COUNT]), N_COUNT)
    ns = E[Entry.STACK]
    nc = E[Entry.NCAND]
    need = forces_scratch_bytes(ns, nc)
    if not hook.stack_room(E, d, need):
        count[Count.NO_STACK] += 1
        return
    nslot = E[Entry.NSLOT]
    now = abi.load_f64(d + E[Entry.TIME])
    nman = E[Entry.NMAN]
    abi.call_with_data(E[Entry.MARK], d)
    raw = abi.call_stack_alloc(E[Entry.ALLOC], d, need, 64)
    nsmall = forces_small_floats()
    f = carray(abi.f64_ptr(raw), nsmall)
    con = f[0:PEN_CAP * abi.PRECONTACT_DOUBLES]
    small = f[PEN_CAP * abi.PRECONTACT_DOUBLES:PEN_CAP * abi.PRECONTACT_DOUBLES + SMALL]
    spare = f[nsmall - PO:nsmall]  # stands in for the output row when the slot table is full
    big_addr = raw + ((8 * nsmall + 63) // 64) * 64
    big = carray(abi.f64_ptr(big_addr), forces_big_bytes(ns, nc) // 8)
    pen = carray(abi.f64_ptr(E[Entry.PEN]), (max(npen, 1), PEN_W))
    cpl = carray(abi.f64_ptr(E[Entry.CPL]), (max(ncpl, 1), CPL_W))
    pout = carray(abi.f64_ptr(E[Entry.POUT]), (nslot, PO))
    for i in range(npen):
        row = pen[i]
        count[Count.CALLS] += 1
        s, _ = hook.claim_slot(E, d, int(row[Pen.PAIR]), nslot, 0)  # the hook's own slot: its state is managed there
        out = pout[s] if s >= 0 else spare
        _penalty_pair(E, m, d, row, con, small, big, out)
        out[O_TIME] = now
    for i in range(ncpl):
        row = cpl[i]
        s, fresh = hook.claim_slot(E, d, nman * nman + i, nslot, 0)
        if s >= 0:
            out = pout[s]
            fst = carray(abi.f64_ptr(E[Entry.FSTATE] + 8 * FW * s), FW)
            if not fresh and not (fst[F_TIME] <= now):
                fresh = True  # a reset or a new MjData at a recycled address
            fst[F_TIME] = now
        else:
            out = spare
            fresh = True
        _coupling(E, m, d, row, small, out, now, fresh)
        out[O_TIME] = now
    abi.call_with_data(E[Entry.FREE], d)


def _passive(m, d):
    """``mjcb_passive``: the previous callback, then this model's penalty forces and couplings."""
    root_addr = abi.registry_root()
    if root_addr == 0:
        return
    root = carray(abi.i64_ptr(root_addr), ROOT_WORDS)
    prev = root[ROOT_PASSIVE]
    if prev != 0:
        abi.call_generic(prev, m, d)
    e = hook.model_entry(m)
    if e == 0:
        return
    E = carray(abi.i64_ptr(e), ENTRY_WORDS)
    if E[Entry.NPEN] > 0 or E[Entry.NCPL] > 0:
        apply(E, m, d)


@functools.cache
def passive():
    """The ``mjcb_passive`` cfunc, compiled (or loaded from numba's cache) on first use, so a
    scene without penalty pairs or couplings never compiles the force laws."""
    return cfunc(types.void(types.int64, types.int64), cache=True)(_passive)
