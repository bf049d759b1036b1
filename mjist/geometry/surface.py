"""A closed mesh's surface for the narrow phase: signed distance, closest point and outward
direction of any point, and the local distance between two posed surfaces (numba).

The sign comes from angle-weighted pseudo-normals (Bærentzen & Aanæs 2005): the normal of the
face, edge or vertex the closest point lies on, which tells inside from outside exactly on a
closed, consistently wound surface without self-intersections. Near a self-intersection (CBCT
fins) the sign can be wrong within the crossing region.

A surface is two flat arrays (``Surface.floats``, ``Surface.ints``) and three sizes, so the
MuJoCo hook can read it from addresses; ``unpack`` gives the views every kernel takes as one
tuple ``S``:

``NODE (m, 8)`` the triangle BVH (``bvh.build_bvh``), one 64-byte row per node: box ``lo``,
``hi``, then children ``left, right``, or for a leaf ``-count, first``; ``TRI (nf, 9)`` the
triangles' corners in the BVH's leaf order and ``ORDER (nf,)`` their face ids; ``F (nf, 3)``
faces, ``FN (nf, 3)`` unit face normals, ``VN (nv, 3)`` vertex pseudo-normals, ``ADJ (nf, 3)``
the face across edge ab, ac, bc (-1: none), ``POS (nf,)`` each face's row in ``TRI``. A query touches a node's row and its leaves'
corners only, one or two cache lines each (``bvh``'s build-time layout spreads a node over
six arrays): the narrow phase's queries are memory-bound.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from . import bvh, sdfgrid

STACK = bvh.STACK  # traversal stack words a query needs
NODE_W = 8


@dataclass
class Surface:
    """A surface packed for the kernels (``views()``: ``unpack(floats, ints, *sizes, *grid)``)."""

    floats: np.ndarray
    ints: np.ndarray
    sizes: tuple[int, int, int]  # vertices, faces, BVH nodes
    grid: tuple = field(default_factory=sdfgrid.empty)  # header, table, values (``add_grid``)
    grid_seconds: float = 0.0

    @property
    def nbytes(self) -> int:
        return int(self.floats.nbytes + self.ints.nbytes)

    @property
    def grid_nbytes(self) -> int:
        return int(sum(a.nbytes for a in self.grid))

    @property
    def grid_spacing(self) -> float:
        """The narrow-band grid's node spacing (0: no grid)."""
        return float(self.grid[0][3])

    def views(self):
        return unpack(self.floats, self.ints, *self.sizes, *self.grid)


def build_surface(V, F) -> Surface:
    """Pack a closed triangle mesh ``V (nv, 3)``, ``F (nf, 3)`` for the narrow-phase kernels."""
    V = np.ascontiguousarray(V, np.float64)
    F = np.ascontiguousarray(F, np.int64)
    nv, nf = V.shape[0], F.shape[0]
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    FN = n / np.where(area2 > 0, area2, 1.0)[:, None]
    # vertex pseudo-normals: face normals weighted by the face's angle at the vertex
    VN = np.zeros((nv, 3))
    for k in range(3):
        e1 = tri[:, (k + 1) % 3] - tri[:, k]
        e2 = tri[:, (k + 2) % 3] - tri[:, k]
        c = np.einsum("ij,ij->i", e1, e2)
        s = np.linalg.norm(np.cross(e1, e2), axis=1)
        np.add.at(VN, F[:, k], np.arctan2(s, c)[:, None] * FN)
    VN /= np.maximum(np.linalg.norm(VN, axis=1), 1e-300)[:, None]
    # the face across each edge (ab, ac, bc), matched through sorted vertex keys
    edges = np.concatenate([F[:, [0, 1]], F[:, [0, 2]], F[:, [1, 2]]])
    key = np.sort(edges, axis=1)
    key = key[:, 0] * nv + key[:, 1]
    owner = np.tile(np.arange(nf), 3)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    ADJ = np.full(3 * nf, -1, np.int64)
    same = ks[1:] == ks[:-1]
    single = same & np.r_[True, ~same[:-1]] & np.r_[~same[1:], True]  # exactly two faces share the edge
    i = np.nonzero(single)[0]
    ADJ[order[i]] = owner[order[i + 1]]
    ADJ[order[i + 1]] = owner[order[i]]
    ADJ = ADJ.reshape(3, nf).T.copy()
    lo, hi, left, right, start, count, border = bvh.build_bvh(tri.min(axis=1), tri.max(axis=1))
    m = lo.shape[0]
    leaf = left < 0
    node = np.empty((m, NODE_W))
    node[:, 0:3] = lo
    node[:, 3:6] = hi
    node[:, 6] = np.where(leaf, -count, left)
    node[:, 7] = np.where(leaf, start, right)
    floats = np.concatenate([node.ravel(), tri[border].ravel(), FN.ravel(), VN.ravel()])
    POS = np.empty(nf, np.int64)
    POS[border] = np.arange(nf)
    ints = np.concatenate([border, F.ravel(), ADJ.ravel(), POS]).astype(np.int64)
    return Surface(floats, ints, (nv, nf, m))


# a surface's default grid spacing, as a fraction of its median edge length: coarser cells miss
# a point's nearest face more often near edges and cusps (the query still answers a point of the
# surface, farther than the closest), finer ones cost quadratically more memory and build time
GRID_EDGE = 0.7
GRID_BAND = 2.0  # the band every stored cell lies within, in grid spacings


def add_grid(surface: Surface, spacing: float | None = None, band: float | None = None) -> Surface:
    """Gives ``surface`` its narrow-band grid of nearest faces (``sdfgrid``), which
    ``local_distance``'s steps query; returns it.

    Parameters
    ----------
    surface : Surface
        ``build_surface``'s result; its grid is replaced.
    spacing : float, optional
        Node spacing in the mesh's units; ``GRID_EDGE`` times the median edge length by default.
    band : float, optional
        Every point within ``band`` of the surface lies in a stored cell; ``GRID_BAND`` spacings
        by default.
    """
    import time

    t0 = time.perf_counter()
    TRI = surface.views()[1]
    if spacing is None:
        T = TRI.reshape(-1, 3, 3)
        edges = np.linalg.norm(T - np.roll(T, 1, axis=1), axis=2).ravel()
        spacing = GRID_EDGE * float(np.median(edges))
        ext = float(np.max(TRI.reshape(-1, 3).max(axis=0) - TRI.reshape(-1, 3).min(axis=0)))
        spacing = min(max(spacing, ext / 2000.0), ext / 40.0)  # bounded memory for any tessellation
    if band is None:
        band = GRID_BAND * spacing
    header, table, where = sdfgrid.layout(TRI, float(spacing), float(band))
    faces = np.empty(where.size * sdfgrid.NODES, np.int32)
    reach = band + 2.0 * math.sqrt(3.0) * spacing  # a node farther than this is no corner of a cell in the band
    _fill_grid(surface.views(), header, where, reach * reach, faces)
    surface.grid = (header, table, faces)
    surface.grid_seconds = time.perf_counter() - t0
    return surface


@njit(cache=True, parallel=True)
def _fill_grid(S, header, where, bound2, faces):
    """Each node of the bricks at ``where``: its nearest face, -1 beyond ``sqrt(bound2)``."""
    n = sdfgrid.NODES
    for b in prange(where.shape[0]):
        stack = np.empty(STACK, np.int64)
        row = np.empty(7)
        for k in range(n):
            px, py, pz = sdfgrid.node_point(header, where[b], k)
            faces[b * n + k] = _signed_closest_face(S, px, py, pz, stack, bound2, row)


@njit(cache=True)
def unpack(floats, ints, nv, nf, m, gheader, gtable, gvalues):
    """The kernels' views ``(NODE, TRI, ORDER, F, FN, VN, ADJ, POS, GH, GT, GV)`` of a packed
    surface (the last three: its narrow-band grid, ``sdfgrid``)."""
    o = NODE_W * m
    NODE = floats[0:o].reshape((m, NODE_W))
    TRI = floats[o:o + 9 * nf].reshape((nf, 9))
    o += 9 * nf
    FN = floats[o:o + 3 * nf].reshape((nf, 3))
    o += 3 * nf
    VN = floats[o:o + 3 * nv].reshape((nv, 3))
    ORDER = ints[0:nf]
    F = ints[nf:4 * nf].reshape((nf, 3))
    ADJ = ints[4 * nf:7 * nf].reshape((nf, 3))
    POS = ints[7 * nf:8 * nf]
    return NODE, TRI, ORDER, F, FN, VN, ADJ, POS, gheader, gtable, gvalues


@njit(cache=True)
def float_words(nv, nf, m):
    """Length of a packed surface's ``floats``."""
    return NODE_W * m + 12 * nf + 3 * nv


@njit(cache=True)
def int_words(nf):
    """Length of a packed surface's ``ints``."""
    return 8 * nf


@njit(cache=True)
def _box2(px, py, pz, NODE, i):
    """Squared distance from a point to node ``i``'s box."""
    d2 = 0.0
    for k, p in ((0, px), (1, py), (2, pz)):
        v = NODE[i, k] - p
        if v > 0.0:
            d2 += v * v
        else:
            v = p - NODE[i, 3 + k]
            if v > 0.0:
                d2 += v * v
    return d2


@njit(cache=True)
def _closest(S, px, py, pz, stack, best):
    """Squared distance to the surface, closest point, its triangle's position in ``TRI`` and
    its feature (``bvh.closest_on_triangle``); triangle -1 when nothing is closer than ``best``."""
    NODE, TRI = S[0], S[1]
    qx = qy = qz = 0.0
    bt = -1
    feature = bvh.INTERIOR
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        i = stack[sp]
        if _box2(px, py, pz, NODE, i) >= best:
            continue
        c = NODE[i, 6]
        if c < 0.0:
            t0 = int(NODE[i, 7])
            for t in range(t0, t0 - int(c)):
                T = TRI[t]
                x, y, z, feat = bvh.closest_on_triangle_xyz(px, py, pz, T[0], T[1], T[2], T[3], T[4], T[5],
                                                            T[6], T[7], T[8])
                d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
                if d2 < best:
                    best = d2
                    qx, qy, qz = x, y, z
                    bt = t
                    feature = feat
            continue
        l = int(c)
        r = int(NODE[i, 7])
        # the nearer child is popped next
        if _box2(px, py, pz, NODE, l) < _box2(px, py, pz, NODE, r):
            stack[sp] = r
            stack[sp + 1] = l
        else:
            stack[sp] = l
            stack[sp + 1] = r
        sp += 2
    return best, qx, qy, qz, bt, feature


@njit(cache=True)
def _pseudo_normal(S, f, feature):
    """Unnormalized pseudo-normal of ``feature`` (``bvh.VERT_A`` ...) of face ``f``."""
    F, FN, VN, ADJ = S[3], S[4], S[5], S[6]
    if feature <= bvh.VERT_C:
        v = F[f, feature]
        return VN[v, 0], VN[v, 1], VN[v, 2]
    if feature <= bvh.EDGE_BC:
        g = ADJ[f, feature - bvh.EDGE_AB]
        if g >= 0:
            return FN[f, 0] + FN[g, 0], FN[f, 1] + FN[g, 1], FN[f, 2] + FN[g, 2]
    return FN[f, 0], FN[f, 1], FN[f, 2]


@njit(cache=True)
def _signed(S, f, feature, d2, qx, qy, qz, px, py, pz, out):
    """``signed_closest``'s ``out`` from the closest point ``q`` on ``feature`` of face ``f``."""
    nx, ny, nz = _pseudo_normal(S, f, feature)
    dx, dy, dz = px - qx, py - qy, pz - qz
    d = math.sqrt(d2)
    side = dx * nx + dy * ny + dz * nz
    sign = -1.0 if side < 0.0 else 1.0
    if d > 1e-12 * (1.0 + abs(qx) + abs(qy) + abs(qz)):
        gx, gy, gz = sign * dx / d, sign * dy / d, sign * dz / d
    else:
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        gx, gy, gz = nx / nn, ny / nn, nz / nn
    out[0] = sign * d
    out[1] = qx
    out[2] = qy
    out[3] = qz
    out[4] = gx
    out[5] = gy
    out[6] = gz


@njit(cache=True)
def signed_closest(S, px, py, pz, stack, bound2, out):
    """Signed distance of ``p`` to the surface ``S`` (negative inside), its closest point and the
    outward direction (the distance's gradient) into ``out[0:7]``.

    ``bound2``: a squared distance the closest point is known to lie within (``np.inf``
    without one). Returns False when the surface has no point within it (``out`` untouched).
    """
    return _signed_closest_face(S, px, py, pz, stack, bound2, out) >= 0


@njit(cache=True)
def _signed_closest_face(S, px, py, pz, stack, bound2, out):
    """``signed_closest`` returning the closest point's face (-1: none within the bound)."""
    d2, qx, qy, qz, t, feature = _closest(S, px, py, pz, stack, bound2)
    if t < 0:
        return -1
    f = S[2][t]
    _signed(S, f, feature, d2, qx, qy, qz, px, py, pz, out)
    return f


ONE_WAY_W = 21  # float64 words of local_distance's temporaries
REFINE_W = ONE_WAY_W + 19  # ... and of contact_distance's
WALK_STEPS = 64  # faces a walk moves through at most (it stops earlier at a local closest point)
RING_MAX = 64  # faces around one vertex a walk looks at, at most


@njit(cache=True)
def _ray_box(ox, oy, oz, ix, iy, iz, NODE, i, tmax):
    """Whether the ray ``o + t d`` (``i``: 1/d per axis) meets node ``i``'s box for some
    0 ≤ t < ``tmax``."""
    t0 = 0.0
    t1 = tmax
    for k, o, inv in ((0, ox, ix), (1, oy, iy), (2, oz, iz)):
        a = (NODE[i, k] - o) * inv
        b = (NODE[i, 3 + k] - o) * inv
        if a > b:
            a, b = b, a
        t0 = max(t0, a)
        t1 = min(t1, b)
        if t0 > t1:
            return False
    return True


@njit(cache=True)
def ray_exit(S, ox, oy, oz, dx, dy, dz, stack):
    """Distance along the unit direction ``d`` from ``o`` to the first triangle of ``S`` the ray
    crosses (t > 0; ``np.inf``: none), over the BVH. From a point inside a closed surface, how
    far the point must move along ``d`` to leave it there."""
    NODE, TRI = S[0], S[1]
    ix = 1.0 / dx if dx != 0.0 else 1e300
    iy = 1.0 / dy if dy != 0.0 else 1e300
    iz = 1.0 / dz if dz != 0.0 else 1e300
    best = np.inf
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        i = stack[sp]
        if not _ray_box(ox, oy, oz, ix, iy, iz, NODE, i, best):
            continue
        c = NODE[i, 6]
        if c >= 0.0:
            stack[sp] = int(c)
            stack[sp + 1] = int(NODE[i, 7])
            sp += 2
            continue
        t0 = int(NODE[i, 7])
        for t in range(t0, t0 - int(c)):
            T = TRI[t]
            det, u, v, h, _, _ = bvh.ray_triangle_xyz(ox, oy, oz, dx, dy, dz, T[0], T[1], T[2], T[3], T[4], T[5],
                                                      T[6], T[7], T[8])
            if det != 0.0 and 0.0 <= u and 0.0 <= v and u + v <= 1.0 and 0.0 < h < best:
                best = h
    return best


@njit(cache=True)
def _on_face(S, g, px, py, pz):
    """Squared distance from p to face ``g``, the closest point and its feature."""
    T = S[1][S[7][g]]
    x, y, z, feat = bvh.closest_on_triangle_xyz(px, py, pz, T[0], T[1], T[2], T[3], T[4], T[5], T[6], T[7], T[8])
    return (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2, x, y, z, feat


@njit(cache=True)
def _ring_edge(corner, side):
    """The edge of a face's ``corner`` (0, 1, 2) its ring around that vertex leaves by first
    (``side`` 0) or second: a (ab, ac), b (ab, bc), c (ac, bc), as ``ADJ``'s columns."""
    if side == 0:
        return 0 if corner < 2 else 1
    return 1 if corner == 0 else 2


@njit(cache=True)
def _ring_next(F, ADJ, v, prev, cur):
    """The face after ``cur`` around vertex ``v``, walking away from ``prev`` (-1: a border)."""
    k = 0 if F[cur, 0] == v else (1 if F[cur, 1] == v else 2)
    nxt = ADJ[cur, _ring_edge(k, 0)]
    if nxt == prev:
        nxt = ADJ[cur, _ring_edge(k, 1)]
    return nxt


@njit(cache=True)
def _corner(S, f, k):
    """The position of corner ``k`` of face ``f``."""
    T = S[1][S[7][f]]
    return T[3 * k], T[3 * k + 1], T[3 * k + 2]


@njit(cache=True)
def lowest_inside(SB, f, SA, xf, dx, dy, dz, stack, tmp):
    """The vertex of ``SB`` lowest along the direction ``d`` (B's frame) that a walk from face
    ``f`` over B's vertex rings reaches while staying inside ``SA`` (``xf``: B's pose in A's
    frame): B's local extreme point in ``d`` within the overlap. Returns it in A's frame and
    whether one of ``f``'s corners lies inside A at all. ``tmp``: 7 floats."""
    F, ADJ = SB[3], SB[6]
    bf, bk = -1, 0
    best = np.inf
    for k in range(3):
        x, y, z = _corner(SB, f, k)
        h = x * dx + y * dy + z * dz
        if h < best:
            ax, ay, az = to_a(xf, x, y, z)
            if _query(SA, ax, ay, az, -1, np.inf, stack, tmp)[0] >= 0 and tmp[0] < 0.0:
                bf, bk, best = f, k, h
    if bf < 0:
        return 0.0, 0.0, 0.0, False
    for _ in range(WALK_STEPS):
        v = F[bf, bk]
        nf, nk = -1, 0
        nb = best
        for side in range(2):
            prev = bf
            cur = ADJ[bf, _ring_edge(bk, side)]
            n = 0
            while cur >= 0 and cur != bf and n < RING_MAX:
                n += 1
                for k in range(3):
                    if F[cur, k] != v:
                        x, y, z = _corner(SB, cur, k)
                        h = x * dx + y * dy + z * dz
                        if h < nb:
                            ax, ay, az = to_a(xf, x, y, z)
                            if _query(SA, ax, ay, az, -1, np.inf, stack, tmp)[0] >= 0 and tmp[0] < 0.0:
                                nf, nk, nb = cur, k, h
                prev, cur = cur, _ring_next(F, ADJ, v, prev, cur)
            if cur == bf:
                break
        if nf < 0:
            break
        bf, bk, best = nf, nk, nb
    x, y, z = _corner(SB, bf, bk)
    ax, ay, az = to_a(xf, x, y, z)
    return ax, ay, az, True


@njit(cache=True)
def _walk(S, f, px, py, pz, out):
    """A local closest point of the surface to p, walked to from face ``f`` over the edge
    adjacency, as ``signed_closest`` writes it into ``out``; returns its face.

    While the closest point lies on an edge or a vertex, the faces sharing it (the face across
    the edge, every face around the vertex) are tried and the walk moves to the closest that is
    strictly closer. No BVH: each step reads a few neighbouring faces. The point it stops at is
    closest among its neighbours, not necessarily globally (a walk does not cross to another
    sheet of the surface); ``signed_closest`` answers globally."""
    F, ADJ = S[3], S[6]
    d2, qx, qy, qz, feat = _on_face(S, f, px, py, pz)
    for _ in range(WALK_STEPS):
        if feat >= bvh.FACE:
            break
        bg = -1
        bd2, bx, by, bz, bfeat = d2, 0.0, 0.0, 0.0, 0
        if feat >= bvh.EDGE_AB:
            g = ADJ[f, feat - bvh.EDGE_AB]
            if g >= 0:
                e2, x, y, z, ft = _on_face(S, g, px, py, pz)
                if e2 < bd2:
                    bg, bd2, bx, by, bz, bfeat = g, e2, x, y, z, ft
        else:
            v = F[f, feat]
            # around the vertex both ways from f (the second only when the first meets a border)
            for side in range(2):
                prev = f
                cur = ADJ[f, _ring_edge(feat, side)]
                n = 0
                while cur >= 0 and cur != f and n < RING_MAX:
                    n += 1
                    e2, x, y, z, ft = _on_face(S, cur, px, py, pz)
                    if e2 < bd2:
                        bg, bd2, bx, by, bz, bfeat = cur, e2, x, y, z, ft
                    prev, cur = cur, _ring_next(F, ADJ, v, prev, cur)
                if cur == f:
                    break
        if bg < 0:
            break
        f, d2, qx, qy, qz, feat = bg, bd2, bx, by, bz, bfeat
    _signed(S, f, feat, d2, qx, qy, qz, px, py, pz, out)
    return f


@njit(cache=True)
def to_a(xf, x, y, z):
    """A point of B's frame in A's frame: R p + t (``xf``: B's pose in A's frame, rotation
    row-major then translation)."""
    return (xf[0] * x + xf[1] * y + xf[2] * z + xf[9], xf[3] * x + xf[4] * y + xf[5] * z + xf[10],
            xf[6] * x + xf[7] * y + xf[8] * z + xf[11])


@njit(cache=True)
def to_b(xf, x, y, z):
    """A point of A's frame in B's frame: R^T (p - t)."""
    px, py, pz = x - xf[9], y - xf[10], z - xf[11]
    return (xf[0] * px + xf[3] * py + xf[6] * pz, xf[1] * px + xf[4] * py + xf[7] * pz,
            xf[2] * px + xf[5] * py + xf[8] * pz)


@njit(cache=True)
def _near(S, x, y, z, stack, within, out):
    """``signed_closest`` looking first within ``within`` of the point (a bound that prunes the
    tree), then everywhere when rounding left the bound too tight; returns the face (-1: the
    surface is empty)."""
    if within < np.inf:
        f = _signed_closest_face(S, x, y, z, stack, (within * (1.0 + 1e-9) + 1e-300) ** 2, out)
        if f >= 0:
            return f
    return _signed_closest_face(S, x, y, z, stack, np.inf, out)


@njit(cache=True)
def closest_face(S, x, y, z, stack, out):
    """The face of ``S`` nearest the point (``_query``: from the grid when it holds the point,
    else the BVH; ``out`` gets ``signed_closest``'s answer); -1 for an empty surface."""
    return _query(S, x, y, z, -1, np.inf, stack, out)[0]


@njit(cache=True)
def _grid_closest(S, px, py, pz, out):
    """``signed_closest`` over the faces nearest to the corners of p's grid cell (``sdfgrid``);
    returns the face, -1 (``out`` untouched) when the cell is not stored."""
    F = S[10]
    o = sdfgrid.cell(S[8], S[9], px, py, pz)
    if o < 0:
        return -1
    best = np.inf
    bf = -1
    qx = qy = qz = 0.0
    feature = 0
    for c in range(8):
        f = F[o + sdfgrid.CORNER[c]]
        if f < 0:
            return -1  # a corner beyond the band
        seen = False
        for cc in range(c):
            if F[o + sdfgrid.CORNER[cc]] == f:
                seen = True
                break
        if seen:
            continue
        d2, x, y, z, feat = _on_face(S, f, px, py, pz)
        if d2 < best:
            best, bf, qx, qy, qz, feature = d2, f, x, y, z, feat
    _signed(S, bf, feature, best, qx, qy, qz, px, py, pz, out)
    return bf


@njit(cache=True)
def _query(S, x, y, z, f, within, stack, out):
    """``signed_closest`` of the point on ``S`` into ``out``: from the grid's cell when the grid
    holds it (``_grid_closest``), else by a walk from face ``f`` when ``f`` ≥ 0, else from the
    BVH (the closest point known within ``within``). Returns the face (-1: the surface is
    empty) and whether the answer is the BVH's (the true closest point) rather than a local
    one."""
    g = _grid_closest(S, x, y, z, out)
    if g >= 0:
        return g, False
    if f >= 0:
        return _walk(S, f, x, y, z, out), False
    return _near(S, x, y, z, stack, within, out), True


@njit(cache=True)
def _on_b(SB, xf, x, y, z, stack, within, b, f):
    """``b`` ← B's closest point to ``(x, y, z)`` (``_query``: from B's grid; else walked to
    from B's face ``f`` when ``f`` ≥ 0, else from the BVH, known within ``within``) and B's
    outward direction there, in A's frame. Returns the face (-1: a query failed)."""
    bx, by, bz = to_b(xf, x, y, z)
    f = _query(SB, bx, by, bz, f, within, stack, b)[0]
    if f < 0:
        return f
    cx, cy, cz = b[1], b[2], b[3]
    gx, gy, gz = b[4], b[5], b[6]
    b[1] = xf[0] * cx + xf[1] * cy + xf[2] * cz + xf[9]
    b[2] = xf[3] * cx + xf[4] * cy + xf[5] * cz + xf[10]
    b[3] = xf[6] * cx + xf[7] * cy + xf[8] * cz + xf[11]
    b[4] = xf[0] * gx + xf[1] * gy + xf[2] * gz
    b[5] = xf[3] * gx + xf[4] * gy + xf[5] * gz
    b[6] = xf[6] * gx + xf[7] * gy + xf[8] * gz
    return f


@njit(cache=True)
def _depths(SA, SB, xf, x, y, z, within, stack, out):
    """The point's depths inside A and inside B (negative outside; NaN when a query fails)."""
    if _near(SA, x, y, z, stack, within, out) < 0:
        return np.nan, np.nan
    da = -out[0]
    bx, by, bz = to_b(xf, x, y, z)
    if _near(SB, bx, by, bz, stack, within, out) < 0:
        return np.nan, np.nan
    return da, -out[0]


@njit(cache=True)
def overlap_depth(SA, SB, xf, x, y, z, nx, ny, nz, within, stack, out):
    """How thick the two solids' overlap is at the point ``(x, y, z)`` along the unit direction
    ``n`` from A to B (A's frame; ``xf`` is B's pose in A's frame): the point moves along ``n``
    to where its depths in A and in B would be equal if both surfaces were planes across ``n``
    (by at most ``within``), and the answer is twice the smaller of its depths there. Negative
    when that point is outside either solid, positive only where the solids truly overlap (the
    point is inside both); equal to the overlap's thickness between two planes across ``n``.
    Continuous in the point, ``n`` and B's pose. NaN when a surface query fails. ``within``: a
    distance both surfaces are expected within (it prunes the searches). ``out``: 7 floats."""
    da, db = _depths(SA, SB, xf, x, y, z, within, stack, out)
    t = max(-within, min(within, 0.5 * (da - db)))  # deeper in A than in B: towards B
    da, db = _depths(SA, SB, xf, x + t * nx, y + t * ny, z + t * nz, within, stack, out)
    return 2.0 * min(da, db)


@njit(cache=True)
def _answer(a, x, y, z, out):
    """``local_distance``'s answer for B's point ``(x, y, z)`` and A's query there, ``a``."""
    out[0] = a[0]
    out[1] = 0.5 * (x + a[1])
    out[2] = 0.5 * (y + a[2])
    out[3] = 0.5 * (z + a[3])
    out[4] = a[4]
    out[5] = a[5]
    out[6] = a[6]


@njit(cache=True)
def local_distance(SA, SB, xf, x, y, z, iters, step0, tol, stack, tmp, out):
    """Distance between surfaces ``SA`` and ``SB`` near the point ``(x, y, z)`` (A's frame; ``xf``
    is B's pose in A's frame, rotation row-major then translation), into ``out[0:7]``: signed
    distance, contact point, unit normal from A to B, all in A's frame.

    Minimizes A's signed distance over B's surface, from B's point closest to the start: steps
    against A's gradient along B's tangent plane, each projected back onto B, with
    Barzilai–Borwein lengths (the first ``step0`` times the gradient); a step that does not
    lower the distance is retried a quarter as long. ``iters`` surface queries of A at most, or
    until a step would be shorter than ``tol``. Each query asks the surface's grid first
    (``add_grid``: the faces nearest to the point's cell corners, O(1)); beyond the grid's band
    the first projection and query use the BVH and the later ones walk the edge adjacency from
    the best point's faces (``_walk``). The best point's value is then taken from the BVH again,
    so the answer is a true signed distance however the steps ended. It is the smallest value met: for
    separated surfaces a true distance between two surface points (an upper bound of the
    surfaces' distance, equal to it at a local minimum), for overlapping ones minus the depth
    of B's deepest point met inside A. The point is the middle of that point of B and its
    closest point on A; the normal, A's outward direction there. ``tmp``: ``ONE_WAY_W`` floats.
    Returns False when a surface query fails.
    """
    a = tmp[0:7]  # A at the trial point
    b = tmp[7:14]  # B's trial point and normal
    yb = tmp[14:17]  # best point of B
    tb = tmp[17:20]  # A's tangential gradient there
    fb = _on_b(SB, xf, x, y, z, stack, np.inf, b, -1)
    if fb < 0:
        return False
    fa = -1
    fyb = fya = 0  # the best point's faces on B and A: the walks start there
    walked = False
    best = np.inf
    alpha = step0
    tn = 0.0
    for it in range(max(iters, 1)):
        fa, exact = _query(SA, b[1], b[2], b[3], fya if fa >= 0 else -1, np.inf, stack, a)
        if fa < 0:
            return False
        walked |= not exact
        gn = a[4] * b[4] + a[5] * b[5] + a[6] * b[6]
        tx, ty, tz = a[4] - gn * b[4], a[5] - gn * b[5], a[6] - gn * b[6]
        if a[0] < best:
            if it > 0:  # Barzilai–Borwein length from the accepted step
                sx, sy, sz = b[1] - yb[0], b[2] - yb[1], b[3] - yb[2]
                sg = sx * (tx - tb[0]) + sy * (ty - tb[1]) + sz * (tz - tb[2])
                if sg > 0.0:
                    alpha = min((sx * sx + sy * sy + sz * sz) / sg, 100.0 * step0)
            best = a[0]
            _answer(a, b[1], b[2], b[3], out)
            yb[0], yb[1], yb[2] = b[1], b[2], b[3]
            fyb, fya = fb, fa
            tb[0], tb[1], tb[2] = tx, ty, tz
            tn = math.sqrt(tx * tx + ty * ty + tz * tz)
        else:
            alpha *= 0.25
        if alpha * tn < tol or it == iters - 1:
            break
        fb = _on_b(SB, xf, yb[0] - alpha * tb[0], yb[1] - alpha * tb[1], yb[2] - alpha * tb[2], stack,
                   alpha * tn, b, fyb)
    if walked:
        # the grid and the walks found local closest points: the best point's value from the whole of A
        if _near(SA, yb[0], yb[1], yb[2], stack, abs(best), a) < 0:
            return False
        _answer(a, yb[0], yb[1], yb[2], out)
    return True


@njit(cache=True)
def start_distance(SA, SB, xf, x, y, z, stack, tmp):
    """The surfaces' signed distance near the point ``(x, y, z)`` (A's frame) without a descent:
    A's signed distance at B's point closest to it, or B's at A's closest point, whichever is
    smaller (two queries each, from the grids when they hold the points, else from the BVHs).
    Every value is a signed distance of a surface point, so an upper bound of the minimum
    ``contact_distance`` finds from there, for ranking where to descend. ``tmp``: 14 floats;
    ``np.inf`` when a query fails."""
    a = tmp[0:7]
    b = tmp[7:14]
    if _on_b(SB, xf, x, y, z, stack, np.inf, b, -1) < 0 or _query(SA, b[1], b[2], b[3], -1, np.inf, stack, a)[0] < 0:
        return np.inf
    v = a[0]
    if _query(SA, x, y, z, -1, np.inf, stack, a)[0] < 0:
        return v
    bx, by, bz = to_b(xf, a[1], a[2], a[3])
    if _query(SB, bx, by, bz, -1, np.inf, stack, b)[0] < 0:
        return v
    return min(v, b[0])


FORWARD, REVERSE = 1, 2  # contact_distance's ways: B's point in A, A's point in B
EITHER = FORWARD | REVERSE


@njit(cache=True)
def contact_distance(SA, SB, xf, x, y, z, iters, step0, tol, stack, tmp, out, ways):
    """``local_distance`` both ways: the deepest point of B in A met from the start
    (``FORWARD``), and the deepest point of A in B (``REVERSE``: ``local_distance`` of B over A's
    surface), whichever is deeper (or, apart, nearer), into ``out`` as ``local_distance`` writes
    it (A's frame, normal from A to B). A cusp of A pressed into a face of B leaves B's points only
    shallowly inside A, and its own tip deep in B: one way alone misses it. ``ways``: the ways to
    try (``EITHER``, or one of them: a contact measured again keeps its way, so that two ways
    that nearly tie cannot trade places from one measurement to the next). Returns the way of
    the answer, 0 when a surface query failed. ``tmp``: ``REFINE_W`` floats."""
    best = 0
    if ways & FORWARD:
        if not local_distance(SA, SB, xf, x, y, z, iters, step0, tol, stack, tmp, out):
            return 0
        best = FORWARD
    if not ways & REVERSE:
        return best
    inv = tmp[ONE_WAY_W:ONE_WAY_W + 12]
    o2 = tmp[ONE_WAY_W + 12:ONE_WAY_W + 19]
    for r in range(3):  # A's pose in B's frame: R^T, -R^T t
        for c in range(3):
            inv[3 * r + c] = xf[3 * c + r]
    for r in range(3):
        inv[9 + r] = -(inv[3 * r] * xf[9] + inv[3 * r + 1] * xf[10] + inv[3 * r + 2] * xf[11])
    bx, by, bz = to_b(xf, x, y, z)
    if not local_distance(SB, SA, inv, bx, by, bz, iters, step0, tol, stack, tmp, o2):
        return 0
    if best == 0 or o2[0] < out[0]:
        out[0] = o2[0]
        out[1], out[2], out[3] = to_a(xf, o2[1], o2[2], o2[3])
        for r in range(3):  # B's outward direction, turned into A's frame and reversed: from A to B
            out[4 + r] = -(xf[3 * r] * o2[4] + xf[3 * r + 1] * o2[5] + xf[3 * r + 2] * o2[6])
        best = REVERSE
    return best


@njit(cache=True, parallel=True)
def _signed_many(floats, ints, nv, nf, m, P, out):
    S = unpack(floats, ints, nv, nf, m, np.zeros(sdfgrid.HDR_W), np.zeros(0, np.int32), np.zeros(0, np.int32))
    for i in prange(P.shape[0]):
        stack = np.empty(STACK, np.int64)
        row = np.empty(7)
        signed_closest(S, P[i, 0], P[i, 1], P[i, 2], stack, np.inf, row)
        for k in range(4):
            out[i, k] = row[k] if k == 0 else row[k + 3]


def signed_distances(surface: Surface, P) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of points ``P (n, 3)`` to ``surface`` (negative inside) and its gradient.

    Returns
    -------
    distance : (n,) float
        Exact distance to the nearest triangle, negative for points inside the closed surface
        (sign from the nearest feature's angle-weighted pseudo-normal).
    gradient : (n, 3) float
        The outward unit direction of steepest increase of the distance at each point.
    """
    P = np.ascontiguousarray(P, np.float64).reshape(-1, 3)
    out = np.empty((len(P), 4))
    _signed_many(surface.floats, surface.ints, *surface.sizes, P, out)
    return out[:, 0], out[:, 1:]
