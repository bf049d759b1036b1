"""One Inner Sphere Tree against a MuJoCo primitive (sphere, capsule, cylinder, box).

MuJoCo collides a mesh with a primitive as the mesh's convex hull, which is wrong wherever
the primitive reaches into a concavity (a probe between two teeth). Here the tree's leaf
spheres meet the primitive instead. Every primitive has an exact signed distance ``sd`` (negative
inside) with a unit gradient; ``sd`` is 1-Lipschitz, so for a node sphere (c, r) the value
``sd(c) - r`` is a lower bound of every leaf sphere's below it, and a single depth-first
traversal prunes with it exactly as the tree-pair traversals do.

A leaf ball's value ``sd(c) - r`` is its signed distance to the primitive; the smallest over the
leaves, d_IST, satisfies true distance ∈ [d_IST - ε, d_IST] with ε the tree's bound (the
primitive is exact). Contacts are the deepest leaf of each subtree at ``split_depth`` below
the threshold, then the deepest and farthest-apart ``cap`` of those.

Everything is in the primitive's frame: ``xf`` (12 floats, row-major rotation then
translation) maps tree-frame points into it. Nothing allocates, nothing raises.
"""
from __future__ import annotations

import math

from numba import njit

from .traverse import CC, CS, OK, STACK_FULL, ancestor_at

SPHERE, CAPSULE, CYLINDER, BOX = 2, 3, 5, 6  # mjtGeom values
TYPES = (SPHERE, CAPSULE, CYLINDER, BOX)
GEOM_W = 7  # per candidate: normal (3, primitive → tree), contact point (3), leaf value


@njit(cache=True)
def _sgn(v):
    return 1.0 if v >= 0.0 else -1.0


@njit(cache=True)
def signed_distance(ptype, s0, s1, s2, x, y, z, g):
    """Signed distance of point (x, y, z) to the primitive (MuJoCo ``geom_size`` convention).

    ``g`` receives the unit outward gradient (never zero). Sphere: radius ``s0``; capsule:
    radius ``s0``, half-length ``s1`` along z; cylinder: radius ``s0``, half-height ``s1``;
    box: half-sizes ``s0, s1, s2``.
    """
    if ptype == BOX:
        dx = abs(x) - s0
        dy = abs(y) - s1
        dz = abs(z) - s2
        if dx <= 0.0 and dy <= 0.0 and dz <= 0.0:
            g[0] = 0.0
            g[1] = 0.0
            g[2] = 0.0
            if dx >= dy and dx >= dz:
                g[0] = _sgn(x)
                return dx
            if dy >= dz:
                g[1] = _sgn(y)
                return dy
            g[2] = _sgn(z)
            return dz
        ox = max(dx, 0.0)
        oy = max(dy, 0.0)
        oz = max(dz, 0.0)
        L = math.sqrt(ox * ox + oy * oy + oz * oz)
        g[0] = _sgn(x) * ox / L
        g[1] = _sgn(y) * oy / L
        g[2] = _sgn(z) * oz / L
        return L
    if ptype == CYLINDER:
        rho = math.sqrt(x * x + y * y)
        ux = x / rho if rho > 0.0 else 1.0
        uy = y / rho if rho > 0.0 else 0.0
        dr = rho - s0
        dz = abs(z) - s1
        if dr <= 0.0 and dz <= 0.0:
            if dr >= dz:
                g[0] = ux
                g[1] = uy
                g[2] = 0.0
                return dr
            g[0] = 0.0
            g[1] = 0.0
            g[2] = _sgn(z)
            return dz
        orr = max(dr, 0.0)
        oz = max(dz, 0.0)
        L = math.sqrt(orr * orr + oz * oz)
        g[0] = ux * orr / L
        g[1] = uy * orr / L
        g[2] = _sgn(z) * oz / L
        return L
    # sphere, capsule: distance to a point / a segment along z, minus the radius
    vz = z
    if ptype == CAPSULE:
        vz = z - min(max(z, -s1), s1)
    L = math.sqrt(x * x + y * y + vz * vz)
    if L > 0.0:
        g[0] = x / L
        g[1] = y / L
        g[2] = vz / L
    else:
        g[0] = 1.0
        g[1] = 0.0
        g[2] = 0.0
    return L - s0


@njit(cache=True)
def _to_prim(xf, N, i, q):
    x = N[i, 0]
    y = N[i, 1]
    z = N[i, 2]
    q[0] = xf[0] * x + xf[1] * y + xf[2] * z + xf[9]
    q[1] = xf[3] * x + xf[4] * y + xf[5] * z + xf[10]
    q[2] = xf[6] * x + xf[7] * y + xf[8] * z + xf[11]


@njit(cache=True)
def tree_contacts(N, ptype, s0, s1, s2, xf, thr, split_depth, st, cand, cval, geom, q):
    """Deepest leaf per ``split_depth`` subtree with ``sd(c) - r < thr``.

    ``st`` (int64) is the traversal stack, ``cand[i] = (group, leaf)``, ``cval[i]`` its value,
    ``geom[i]`` normal and contact point (primitive frame), ``q`` 6 floats of scratch.
    Returns ``(n, code, visits)``; when more groups than ``cand`` rows qualify, the deepest are kept.
    """
    nc = cand.shape[0]
    cap_st = st.shape[0]
    n = 0
    visits = 0
    sp = 0
    st[0] = 0
    sp = 1
    g = q[3:6]
    while sp > 0:
        sp -= 1
        i = st[sp]
        visits += 1
        _to_prim(xf, N, i, q)
        r = N[i, 3]
        sd = signed_distance(ptype, s0, s1, s2, q[0], q[1], q[2], g)
        v = sd - r
        if v >= thr:
            continue
        cc = int(N[i, CC])
        if cc == 0:
            grp = ancestor_at(N, i, split_depth)
            k = -1
            for j in range(n):
                if cand[j, 0] == grp:
                    k = j
                    break
            if k >= 0:
                if v >= cval[k]:
                    continue
            elif n < nc:
                k = n
                n += 1
            else:
                k = 0
                for j in range(1, nc):
                    if cval[j] > cval[k]:
                        k = j
                if v >= cval[k]:
                    continue
            cand[k, 0] = grp
            cand[k, 1] = i
            cval[k] = v
            h = 0.5 * (sd + r)  # midway between the primitive's surface and the ball's
            for c in range(3):
                geom[k, c] = g[c]
                geom[k, 3 + c] = q[c] - h * g[c]
            geom[k, 6] = v
            continue
        if sp + cc > cap_st:
            return n, STACK_FULL, visits
        cs = int(N[i, CS])
        for c in range(cc - 1, -1, -1):
            st[sp] = cs + c
            sp += 1
    return n, OK, visits


@njit(cache=True)
def min_distance(N, ptype, s0, s1, s2, xf, st, g):
    """Smallest ``sd(c) - r`` over the leaves: the signed distance from the primitive to the
    union of leaf spheres (negative: overlap depth), depth first with the node bound
    ``sd(c) - r`` pruning against the best so far. ``st`` (int64) is the stack, ``g`` 3 floats
    of scratch. Returns ``(value, leaf node, code)``."""
    best = math.inf
    best_leaf = -1
    cap_st = st.shape[0]
    st[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        i = st[sp]
        x = N[i, 0]
        y = N[i, 1]
        z = N[i, 2]
        v = signed_distance(ptype, s0, s1, s2, xf[0] * x + xf[1] * y + xf[2] * z + xf[9],
                            xf[3] * x + xf[4] * y + xf[5] * z + xf[10],
                            xf[6] * x + xf[7] * y + xf[8] * z + xf[11], g) - N[i, 3]
        if v >= best:
            continue
        cc = int(N[i, CC])
        if cc == 0:
            best = v
            best_leaf = i
            continue
        if sp + cc > cap_st:
            return best, best_leaf, STACK_FULL
        cs = int(N[i, CS])
        for c in range(cc - 1, -1, -1):
            st[sp] = cs + c
            sp += 1
    return best, best_leaf, OK


@njit(cache=True)
def points_distance(N, P, xf_rows, st, g, out):
    """Distance from each point ``P[k]`` (tree frame after ``xf_rows``: point k is
    ``R p + t`` with the 12-vector xf) to the union of leaf spheres: ``out[k]`` (negative inside)."""
    for k in range(P.shape[0]):
        x = P[k, 0]
        y = P[k, 1]
        z = P[k, 2]
        # a point is a sphere of radius 0: put it at the origin of a primitive frame
        xf_rows[9] = -x
        xf_rows[10] = -y
        xf_rows[11] = -z
        v, _, code = min_distance(N, SPHERE, 0.0, 0.0, 0.0, xf_rows, st, g)
        out[k] = v if code == OK else math.nan
