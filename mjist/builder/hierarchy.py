"""The sphere hierarchy, top-down by Batch Neural Gas.

Each inner node's leaf spheres are clustered into ``B`` groups by Batch Neural Gas
(Cottrell, Hammer, Hasenfuß, Villmann 2006): prototypes ``w_j`` are set to the
weighted mean ``sum_i h_λ(k_ij) v_i x_i / sum_i h_λ(k_ij) v_i`` where ``k_ij`` is the
rank of prototype j by distance to sphere i, ``h_λ(k) = exp(-k/λ)``, ``v_i`` the
sphere's volume and λ decays geometrically from B/2 to 0.01 per iteration. It stops at
``max_iter`` or when no prototype moves more than ``tol`` times the node size. Each
sphere joins its nearest prototype; each group becomes a child, recursively.

Every node sphere encloses all leaf spheres below it (a wrapped hierarchy): its centre is
refined by the Bădoiu–Clarkson iteration for the minimal ball enclosing balls, and its
radius is then set to ``max |c - c_i| + r_i`` over its leaves, so enclosure holds exactly
whatever the iteration did. A node of two leaves (a third of them) gets the minimal ball in
closed form instead (``_two_balls``).

Nodes are numbered breadth first, so each node's children are contiguous
(``child_start``, ``child_count``); leaves are reordered so each node's leaves are a
contiguous range (``leaf_start``, ``leaf_end``).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

BNG_MAX_ITER = 24
BNG_TOL = 1e-4
MEB_ITER = 64
CORE_MAX = 16  # larger nodes wrap through a core set of at most this many balls
BNG_SAMPLE = 1024  # larger nodes cluster a stride subsample, then assign all


@njit(cache=True)
def _mix(x):
    """splitmix64 finaliser: a deterministic, thread-independent pseudo-random hash."""
    x = (x + np.uint64(0x9E3779B97F4A7C15)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    x = ((x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    x = ((x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    return x ^ (x >> np.uint64(31))


@njit(cache=True)
def _bng(X, w, k, max_iter, tol, key):
    """Batch Neural Gas prototypes ``(k, 3)`` of points ``X`` with weights ``w``.

    Initial prototypes are distinct points picked by hashing ``key`` (seed and node id), so
    the result does not depend on thread scheduling.
    """
    n = X.shape[0]
    lo = np.empty(3)
    hi_ = np.empty(3)
    for d in range(3):
        lo[d] = X[:, d].min()
        hi_[d] = X[:, d].max()
    size = np.sqrt(((hi_ - lo) ** 2).sum())
    # deterministic distinct initial prototypes (global RNG seeded by the caller)
    W = np.empty((k, 3))
    picked = np.full(k, -1, np.int64)
    h = np.uint64(key)
    for j in range(k):
        while True:
            h = _mix(h)
            cand = int(h % np.uint64(n))
            ok = True
            for q in range(j):
                if picked[q] == cand:
                    ok = False
            if ok:
                break
        picked[j] = cand
        W[j] = X[cand]
    lam0 = k / 2.0
    lamf = 0.01
    dist = np.empty(k)
    num = np.empty((k, 3))
    den = np.empty(k)
    hk = np.empty(k)
    for t in range(max_iter):
        lam = lam0 * (lamf / lam0) ** (t / max(1, max_iter - 1))
        for j in range(k):
            hk[j] = np.exp(-j / lam)
        num[:] = 0.0
        den[:] = 0.0
        # scalar arithmetic throughout: array expressions here would allocate per point
        for i in range(n):
            x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
            for j in range(k):
                dist[j] = (x0 - W[j, 0]) ** 2 + (x1 - W[j, 1]) ** 2 + (x2 - W[j, 2]) ** 2
            # ranks by counting (k is small)
            for j in range(k):
                r = 0
                dj = dist[j]
                for q in range(k):
                    if dist[q] < dj or (dist[q] == dj and q < j):
                        r += 1
                hw = hk[r] * w[i]
                den[j] += hw
                num[j, 0] += hw * x0
                num[j, 1] += hw * x1
                num[j, 2] += hw * x2
        move = 0.0
        for j in range(k):
            if den[j] > 0:
                n0, n1, n2 = num[j, 0] / den[j], num[j, 1] / den[j], num[j, 2] / den[j]
                move = max(move, np.sqrt((n0 - W[j, 0]) ** 2 + (n1 - W[j, 1]) ** 2 + (n2 - W[j, 2]) ** 2))
                W[j, 0], W[j, 1], W[j, 2] = n0, n1, n2
        if move <= tol * size:
            break
    return W


@njit(cache=True)
def _assign(X, W, labels):
    for i in range(X.shape[0]):
        best = np.inf
        for j in range(W.shape[0]):
            dd = (X[i, 0] - W[j, 0]) ** 2 + (X[i, 1] - W[j, 1]) ** 2 + (X[i, 2] - W[j, 2]) ** 2
            if dd < best:
                best = dd
                labels[i] = j


@njit(cache=True)
def _farthest(C, R, idx, m, c0, c1, c2):
    """Farthest ball surface ``max |c - C_i| + R_i`` over ``idx[:m]`` and where it is."""
    far = -1.0
    fi = 0
    for q in range(m):  # scalar form: this loop runs over every leaf of a node per pass
        i = idx[q]
        dd = np.sqrt((C[i, 0] - c0) ** 2 + (C[i, 1] - c1) ** 2 + (C[i, 2] - c2) ** 2) + R[i]
        if dd > far:
            far = dd
            fi = i
    return far, fi


@njit(cache=True)
def _badoiu_clarkson(C, R, idx, m, c0, c1, c2):
    """Bădoiu–Clarkson for the balls ``idx[:m]`` from ``c``: the best centre seen and its radius."""
    b0, b1, b2 = c0, c1, c2
    best_r = np.inf
    for t in range(MEB_ITER):
        far, fi = _farthest(C, R, idx, m, c0, c1, c2)
        if far < best_r:
            best_r = far
            b0, b1, b2 = c0, c1, c2
        v0, v1, v2 = C[fi, 0] - c0, C[fi, 1] - c1, C[fi, 2] - c2
        nv = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if nv > 0:
            s = R[fi] / nv
            q0, q1, q2 = C[fi, 0] + s * v0, C[fi, 1] + s * v1, C[fi, 2] + s * v2
        else:
            q0, q1, q2 = C[fi, 0] + R[fi], C[fi, 1], C[fi, 2]
        step = 1.0 / (t + 2.0)
        c0 += (q0 - c0) * step
        c1 += (q1 - c1) * step
        c2 += (q2 - c2) * step
    return b0, b1, b2, best_r


@njit(cache=True)
def _enclosing(C, R, idx, c0):
    """Ball enclosing the balls ``C[idx], R[idx]`` (Bădoiu–Clarkson from ``c0``, exact final radius).

    A node with more than ``CORE_MAX`` balls runs the iteration on a core set instead: the
    balls that were farthest from a centre so far, grown one per pass over all balls until the
    farthest ball is one of them (Bădoiu–Clarkson's core sets). A few passes over the leaves
    instead of ``MEB_ITER`` over every ball, which would dominate the hierarchy's time.
    """
    m = idx.shape[0]
    if m <= CORE_MAX:
        b0, b1, b2, _ = _badoiu_clarkson(C, R, idx, m, c0[0], c0[1], c0[2])
    else:
        core = np.empty(CORE_MAX, np.int64)
        nc = 0
        x0, x1, x2 = c0[0], c0[1], c0[2]
        b0, b1, b2 = x0, x1, x2
        best_r = np.inf
        for _ in range(CORE_MAX):
            far, fi = _farthest(C, R, idx, m, x0, x1, x2)
            if far < best_r:
                best_r = far
                b0, b1, b2 = x0, x1, x2
            known = False
            for q in range(nc):
                if core[q] == fi:
                    known = True
            if known:
                break
            core[nc] = fi
            nc += 1
            x0, x1, x2, _ = _badoiu_clarkson(C, R, core, nc, b0, b1, b2)
    # exact radius for the chosen centre (enclosure holds by construction)
    r, _ = _farthest(C, R, idx, m, b0, b1, b2)
    best_c = np.empty(3)
    best_c[0], best_c[1], best_c[2] = b0, b1, b2
    return best_c, r * (1.0 + 1e-12)


@njit(cache=True)
def _two_balls(C, R, i, j):
    """The minimal ball enclosing balls ``i`` and ``j``: exact, where two runs of
    Bădoiu–Clarkson (``MEB_ITER`` steps each) came within 5e-5 of it."""
    v0, v1, v2 = C[j, 0] - C[i, 0], C[j, 1] - C[i, 1], C[j, 2] - C[i, 2]
    d = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    c = np.empty(3)
    if d + R[j] <= R[i]:  # j lies inside i
        c[0], c[1], c[2] = C[i, 0], C[i, 1], C[i, 2]
        return c, R[i]
    if d + R[i] <= R[j]:
        c[0], c[1], c[2] = C[j, 0], C[j, 1], C[j, 2]
        return c, R[j]
    s = (0.5 * (d + R[i] + R[j]) - R[i]) / d  # on the line of centres, touching both far sides
    c[0], c[1], c[2] = C[i, 0] + s * v0, C[i, 1] + s * v1, C[i, 2] + s * v2
    # the radius for that centre as computed (rounding), as _enclosing does
    r = max(np.sqrt((c[0] - C[i, 0]) ** 2 + (c[1] - C[i, 1]) ** 2 + (c[2] - C[i, 2]) ** 2) + R[i],
            np.sqrt((c[0] - C[j, 0]) ** 2 + (c[1] - C[j, 1]) ** 2 + (c[2] - C[j, 2]) ** 2) + R[j])
    return c, r * (1.0 + 1e-12)


@njit(cache=True)
def _split(C, vol, seg, B, key, lab):
    """Labels (0..k-1) of the spheres ``seg`` of one node: its children's groups."""
    cnt = seg.shape[0]
    k = min(B, cnt)
    if cnt <= B:
        for i in range(cnt):
            lab[i] = i
        return
    X = np.empty((cnt, 3))
    wv = np.empty(cnt)
    for i in range(cnt):
        X[i] = C[seg[i]]
        wv[i] = vol[seg[i]]
    if cnt > BNG_SAMPLE:
        # prototypes from a deterministic stride subsample; every sphere is then assigned
        stride = cnt // BNG_SAMPLE
        ns = cnt // stride
        Xs = np.empty((ns, 3))
        ws = np.empty(ns)
        for q in range(ns):
            Xs[q] = X[q * stride]
            ws[q] = wv[q * stride]
        W = _bng(Xs, ws, k, BNG_MAX_ITER, BNG_TOL, key)
    else:
        W = _bng(X, wv, k, BNG_MAX_ITER, BNG_TOL, key)
    _assign(X, W, lab)
    seen = np.zeros(k, np.bool_)
    for i in range(cnt):
        seen[lab[i]] = True
    if seen.sum() < 2:
        # all centres coincide with one prototype (degenerate): split along the longest axis
        ext = np.empty(3)
        for d in range(3):
            ext[d] = X[:, d].max() - X[:, d].min()
        ax = np.argmax(ext)
        o = np.argsort(X[:, ax], kind="mergesort")
        for q in range(cnt):
            lab[o[q]] = (q * k) // cnt


@njit(cache=True, parallel=True)
def _split_frontier(C, vol, perm, frontier, leaf_start, leaf_end, B, seed, lab):
    for t in prange(frontier.shape[0]):
        nd = frontier[t]
        a = leaf_start[nd]
        b = leaf_end[nd]
        key = (np.uint64(seed) << np.uint64(32)) ^ np.uint64(nd)
        _split(C, vol, perm[a:b], B, key, lab[a:b])


@njit(cache=True, parallel=True)
def _wrap_level(C, R, perm, lo_node, hi_node, child_start, child_count, leaf_start, leaf_end, centers, radii):
    for nd in prange(lo_node, hi_node):
        a = leaf_start[nd]
        b = leaf_end[nd]
        if b - a == 1:
            centers[nd] = C[perm[a]]
            radii[nd] = R[perm[a]]
            continue
        if b - a == 2:  # two leaves (a third of the nodes): the minimal ball in closed form
            c, r = _two_balls(C, R, perm[a], perm[a + 1])
            centers[nd] = c
            radii[nd] = r
            continue
        # start from the ball around the children's (already enclosing) spheres, refine on the leaves
        kids = np.arange(child_start[nd], child_start[nd] + child_count[nd])
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for q in kids:
            for d in range(3):
                lo[d] = min(lo[d], centers[q, d] - radii[q])
                hi[d] = max(hi[d], centers[q, d] + radii[q])
        c0, _ = _enclosing(centers, radii, kids, 0.5 * (lo + hi))
        c, r = _enclosing(C, R, perm[a:b], c0)
        centers[nd] = c
        radii[nd] = r


@njit(cache=True)
def build_hierarchy(C, R, B, seed):
    """Top-down BNG hierarchy over leaf spheres ``(C, R)`` with branching factor ``B``.

    Nodes of one depth are split in parallel (labels only); children are then numbered
    sequentially, so the tree is the same for any number of threads.
    Returns the node arrays and the leaf permutation (``leaf_order``): leaf ``i`` of the
    tree is input sphere ``leaf_order[i]``.
    """
    n = R.shape[0]
    m_max = 2 * n + 1
    leaf_start = np.zeros(m_max, np.int64)
    leaf_end = np.zeros(m_max, np.int64)
    child_start = np.full(m_max, -1, np.int64)
    child_count = np.zeros(m_max, np.int64)
    parent = np.full(m_max, -1, np.int64)
    depth = np.zeros(m_max, np.int64)
    perm = np.arange(n)
    vol = R ** 3
    lab = np.empty(n, np.int64)
    leaf_start[0] = 0
    leaf_end[0] = n
    m = 1
    level_lo = 0
    level_hi = 1
    bounds = [0]
    while level_lo < level_hi:
        cand = np.arange(level_lo, level_hi)
        frontier = cand[(leaf_end[cand] - leaf_start[cand]) > 1]
        _split_frontier(C, vol, perm, frontier, leaf_start, leaf_end, B, seed, lab)
        for nd in frontier:
            a = leaf_start[nd]
            b = leaf_end[nd]
            seg = perm[a:b].copy()
            lseg = lab[a:b]
            k = lseg.max() + 1
            cs = m
            pos = a
            for j in range(k):
                first = pos
                for i in range(b - a):
                    if lseg[i] == j:
                        perm[pos] = seg[i]
                        pos += 1
                if pos > first:
                    leaf_start[m] = first
                    leaf_end[m] = pos
                    parent[m] = nd
                    depth[m] = depth[nd] + 1
                    m += 1
            child_start[nd] = cs
            child_count[nd] = m - cs
        bounds.append(level_hi)
        level_lo = level_hi
        level_hi = m
    centers = np.empty((m, 3))
    radii = np.empty(m)
    # bottom-up, one depth at a time (BFS numbering: each depth is a contiguous range)
    for q in range(len(bounds) - 1, 0, -1):
        _wrap_level(C, R, perm, bounds[q - 1], bounds[q], child_start, child_count, leaf_start, leaf_end, centers, radii)
    return (
        centers, radii, child_start[:m].copy(), child_count[:m].copy(), parent[:m].copy(),
        depth[:m].copy(), leaf_start[:m].copy(), leaf_end[:m].copy(), perm,
    )
