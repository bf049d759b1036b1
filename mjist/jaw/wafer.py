"""A surgical wafer (occlusal splint) between two arches at their occlusion.

The wafer is the space between the arches, opened about the hinge, over the dentition's
outline, with both arches' imprints offset by a clearance. It is made on a grid in the
maxillary arch's frame (u left, v anterior, w up) as two **height fields**:

* the **upper face** is the maxilla's surface seen from below, offset down by the clearance
  (a ball of that radius dropped from below onto surface samples: ``_drop``), the **lower face**
  the mandible's seen from above, offset up. A height field has no undercut along up, so the
  maxilla seats into the wafer and lifts off it straight; a boolean subtraction of the teeth
  would leave wafer material in the crowns' undercuts that locks the wafer or breaks off;
* faces are capped ``IMPRINT`` beyond the cusp tips (the wafer wraps the crowns that far) and
  kept inside the dentition's outline (where the arches face each other within ``REACH`` at
  the occlusion) widened by ``RIM``;
* the solid between the faces is **opened** by a ball of diameter ``thickness``: eroded, then
  dilated (grey morphology with a ball-shaped structure, ``_ball_min``), which removes every
  part a ball of that diameter cannot reach — fins between deep imprints, knife edges — and
  rounds the outer edges with that ball's radius. Every point of the wafer then lies in a ball
  of diameter ``thickness`` inside it, the printable minimum thickness;
* the mandible is opened about the hinge by the **smallest angle** at which such a ball fits
  between the offset faces everywhere over the dentition (bisection on coal's exact distance
  between the arches' occlusal parts, then checked on the grid);
* the mesh is built from the two fields: a top and a bottom triangle per grid half-square and
  a wall along the outline, so it is one closed, consistently wound shell by construction, and
  cannot self-intersect (the top field lies above the bottom one).

Everything here is in one Cartesian frame in metres (the search scene's world); ``make`` in
``waferjob`` turns it into the maxilla file's own frame and units.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

# the wafer wraps the crowns this far past the cusp tips (m): deep enough that a cusp's
# imprint holds sideways, shallow enough to stay off the gums and out of the undercuts
IMPRINT = 2.0e-3
# the outline: where the arches face each other within REACH at the occlusion (the occlusal
# table, m), its gaps between teeth closed over CLOSE, then widened by RIM so that the wafer
# covers the buccal and lingual cusps and their slopes
REACH = 3.0e-3
CLOSE = 1.5e-3
RIM = 2.5e-3
NEIGHBOURHOOD = 2.5e-3  # m: the cusp level the imprint depth counts from: the extreme within this radius
TIP = 1.5e-3  # m: a cusp tip is the extreme occlusal vertex within this radius (a molar's cusps are 2-3 mm apart)
GRID = 1.5e-4  # m: grid spacing; the faces between nodes err by about GRID**2 / (8 * the imprint's radius)
SAMPLE = 6.0e-5  # m: surface sample spacing (the ball drop between samples errs by about SAMPLE**2 / (4 * ball radius))
MAX_OPENING_DEG = 20.0


@dataclass
class WaferShape:
    """A wafer in the frame of the arches given to ``shape`` (metres)."""

    vertices: np.ndarray
    faces: np.ndarray
    opening_deg: float  # the mandible turned open about the hinge from the occlusion
    opening_source: str  # "smallest" (found) or "given"
    mandible_pose: np.ndarray  # 4x4: the occluded mandible's vertices -> where they seat on the wafer
    clearance: float
    thickness: float
    arch_gap: float  # coal's exact distance between the arches' occlusal parts at the opening
    grid: float
    cusps: dict = field(default_factory=dict)  # "maxilla", "mandible": (n, 3) cusp tips over the wafer (seated poses)
    timings: dict = field(default_factory=dict)


def _basis(up, anterior):
    w = np.asarray(up, float) / np.linalg.norm(up)
    v = np.asarray(anterior, float) - (np.asarray(anterior, float) @ w) * w
    v /= np.linalg.norm(v)
    return np.stack([np.cross(w, v), v, w])  # rows: u (left), v (anterior), w (up)


def hinge_turn(theta: float, hinge, axis) -> np.ndarray:
    """4x4 rotation by ``theta`` (rad) about ``axis`` through ``hinge``."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.asarray(axis, float) / np.linalg.norm(axis) * theta).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(hinge, float) - R @ np.asarray(hinge, float)
    return T


def apply_pose(T, V) -> np.ndarray:
    """The points ``V (n, 3)`` moved by the 4x4 pose ``T``."""
    return np.asarray(V, float) @ T[:3, :3].T + T[:3, 3]


def surface_samples(V, F, spacing: float, keep=None) -> np.ndarray:
    """Points on the faces ``F[keep]`` no farther than ``spacing`` from each other along an edge:
    a barycentric grid per face, finer on longer faces."""
    V = np.asarray(V, float)
    F = np.asarray(F)[keep] if keep is not None else np.asarray(F)
    if len(F) == 0:
        return np.empty((0, 3))
    T = V[F]
    longest = np.max(np.linalg.norm(T - np.roll(T, 1, axis=1), axis=2), axis=1)
    n = np.maximum(1, np.ceil(longest / spacing).astype(np.int64))
    out = []
    for k in np.unique(n):
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        sel = i + j <= k
        a, b = i[sel] / k, j[sel] / k
        W = np.stack([1.0 - a - b, a, b], axis=1)  # (m, 3)
        Tk = T[n == k]
        out.append(np.einsum("mj,fjd->fmd", W, Tk).reshape(-1, 3))
    return np.concatenate(out)


@njit(cache=True)
def _drop(pu, pv, pw, u0, v0, h, nu, nv, rho, sign, out):
    """Height field of a ball of radius ``rho`` resting on points: from below (``sign`` -1: the
    lowest the ball's top can reach under the points, minus nothing) or from above (+1).

    ``out[i, j]`` at node ``(u0 + i h, v0 + j h)`` becomes ``min_p (w_p - s)`` (sign -1) or
    ``max_p (w_p + s)`` (+1) over points within ``rho`` horizontally, ``s = sqrt(rho² - d²)``:
    the surface offset by ``rho`` along the vertical, as a ball rolled over it sees it.
    """
    r2 = rho * rho
    for k in range(pu.shape[0]):
        fu = (pu[k] - u0) / h
        fv = (pv[k] - v0) / h
        i0 = max(int(np.ceil(fu - rho / h)), 0)
        i1 = min(int(np.floor(fu + rho / h)), nu - 1)
        j0 = max(int(np.ceil(fv - rho / h)), 0)
        j1 = min(int(np.floor(fv + rho / h)), nv - 1)
        for i in range(i0, i1 + 1):
            du = u0 + i * h - pu[k]
            for j in range(j0, j1 + 1):
                dv = v0 + j * h - pv[k]
                d2 = du * du + dv * dv
                if d2 > r2:
                    continue
                s = np.sqrt(r2 - d2)
                if sign < 0:
                    val = pw[k] - s
                    if val < out[i, j]:
                        out[i, j] = val
                else:
                    val = pw[k] + s
                    if val > out[i, j]:
                        out[i, j] = val


def _disk(h, radius):
    """A disk footprint of ``radius`` on a grid of spacing ``h`` and each offset's squared length."""
    k = int(np.floor(radius / h))
    a = np.arange(-k, k + 1) * h
    d2 = a[:, None] ** 2 + a[None, :] ** 2
    return d2 <= radius * radius, d2


class _Grid:
    """The node grid in the arch frame: ``B`` rows u, v, w; origin; spacing; shape."""

    def __init__(self, B, origin, lo, hi, h):
        self.B, self.origin, self.h = B, np.asarray(origin, float), float(h)
        self.u0, self.v0 = float(lo[0]), float(lo[1])
        self.shape = (int(np.ceil((hi[0] - lo[0]) / h)) + 1, int(np.ceil((hi[1] - lo[1]) / h)) + 1)

    def local(self, P):
        return (np.asarray(P, float) - self.origin) @ self.B.T

    def world(self, U):
        return self.origin + np.asarray(U, float) @ self.B

    def index(self, L):
        """The node nearest each point of local coordinates ``L (n, 3)``: ``i, j`` and whether it is on the grid."""
        i = np.rint((L[:, 0] - self.u0) / self.h).astype(np.int64)
        j = np.rint((L[:, 1] - self.v0) / self.h).astype(np.int64)
        return i, j, (i >= 0) & (i < self.shape[0]) & (j >= 0) & (j < self.shape[1])

    def nodes(self):
        i, j = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return self.u0 + i * self.h, self.v0 + j * self.h

    def disk(self, radius):
        return _disk(self.h, radius)

    def drop(self, P, rho, sign):
        return self.drop_local(self.local(P), rho, sign)

    def drop_local(self, L, rho, sign):
        out = np.full(self.shape, np.inf if sign < 0 else -np.inf)
        _drop(np.ascontiguousarray(L[:, 0]), np.ascontiguousarray(L[:, 1]), np.ascontiguousarray(L[:, 2]),
              self.u0, self.v0, self.h, self.shape[0], self.shape[1], float(rho), int(sign), out)
        return out


@njit(cache=True, parallel=True)
def _ball_min(H, di, dj, s, out):
    """``out[i, j] = min_k H[i + di[k], j + dj[k]] - s[k]`` (offsets off the grid count as +inf)."""
    ni, nj = H.shape
    for i in prange(ni):
        for j in range(nj):
            best = np.inf
            for k in range(di.shape[0]):
                a = i + di[k]
                b = j + dj[k]
                if a < 0 or a >= ni or b < 0 or b >= nj:
                    continue
                val = H[a, b] - s[k]
                if val < best:
                    best = val
            out[i, j] = best


def _erode(H, grid, radius, flat: bool = False):
    """Grey erosion by a ball from above, ``min_q (H(q) - sqrt(r² - |p - q|²))`` over ``|p - q| ≤ r``
    (``flat``: by a disk, ``min_q H(q)``); ``grid`` is a ``_Grid`` or a spacing."""
    foot, d2 = _disk(getattr(grid, "h", grid), radius)
    di, dj = np.nonzero(foot)
    k = foot.shape[0] // 2
    s = np.zeros(len(di)) if flat else np.sqrt(np.maximum(radius * radius - d2[di, dj], 0.0))
    out = np.empty(H.shape)
    _ball_min(np.ascontiguousarray(H, dtype=np.float64), (di - k).astype(np.int64), (dj - k).astype(np.int64), s, out)
    return out


def _dilate(H, grid, radius, flat: bool = False):
    """Grey dilation by a ball from below: ``max_q (H(q) + sqrt(r² - |p - q|²))``."""
    return -_erode(-np.asarray(H, float), grid, radius, flat)


def _outline(gap, grid) -> np.ndarray:
    """The dentition's outline on the grid: the largest region where the arches face each other
    within ``REACH`` (gaps between teeth closed over ``CLOSE``), widened by ``RIM``."""
    from scipy import ndimage

    facing = np.isfinite(gap) & (gap <= REACH)
    m = ~_dilate_mask(~_dilate_mask(facing, grid, CLOSE), grid, CLOSE)  # closing
    m = ndimage.binary_fill_holes(m)
    lab, n = ndimage.label(m)
    if n == 0:
        raise ValueError(f"the arches do not face each other within {REACH * 1e3:g} mm anywhere at the given occlusion: "
                         "pass the pose where the teeth meet (--pose occlusion.json or --search)")
    sizes = ndimage.sum(m, lab, index=np.arange(1, n + 1))
    m = lab == 1 + int(np.argmax(sizes))
    return _dilate_mask(m, grid, RIM)


def _crop(V, F, grid, inside, band):
    """Faces of ``(V, F)`` whose centroid lies over ``inside`` (grid mask) within ``band`` of w = 0."""
    C = grid.local(V[F].mean(axis=1))
    i, j, ok = grid.index(C)
    ok &= np.abs(C[:, 2]) < band
    ok[ok] = inside[i[ok], j[ok]]
    return ok


def _mesh(top, bottom, valid, grid) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh from two height fields over the grid squares whose four nodes are
    ``valid``: top and bottom faces and a vertical wall along the squares' outline (the largest
    edge-connected set of squares; squares touching others only at a corner are dropped so that
    every vertex is manifold)."""
    from scipy import ndimage

    sq = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
    for _ in range(100):  # two squares meeting only at a corner make a non-manifold vertex: drop one
        a, b, c, d = sq[:-1, :-1], sq[1:, :-1], sq[:-1, 1:], sq[1:, 1:]
        diag = (a & d & ~b & ~c)
        anti = (b & c & ~a & ~d)
        if not (diag.any() or anti.any()):
            break
        sq[:-1, :-1] &= ~diag
        sq[1:, :-1] &= ~anti
    lab, n = ndimage.label(sq)  # 4-connected
    if n == 0:
        raise ValueError("the wafer is empty: the arches leave no room for it over the dentition")
    sizes = ndimage.sum(sq, lab, index=np.arange(1, n + 1))
    sq = lab == 1 + int(np.argmax(sizes))
    used = np.zeros(valid.shape, bool)
    for di in (0, 1):
        for dj in (0, 1):
            used[di:di + sq.shape[0], dj:dj + sq.shape[1]] |= sq
    idx = -np.ones(valid.shape, np.int64)
    ni = int(used.sum())
    idx[used] = np.arange(ni)
    U, W = grid.nodes()
    top_v = np.stack([U[used], W[used], top[used]], axis=1)
    bot_v = np.stack([U[used], W[used], bottom[used]], axis=1)
    V = grid.world(np.vstack([top_v, bot_v]))
    si, sj = np.nonzero(sq)
    a, b, c, d = idx[si, sj], idx[si + 1, sj], idx[si, sj + 1], idx[si + 1, sj + 1]

    def halves(H, up: bool):
        # each square split along its shorter diagonal in 3D: a steep slope split the other way
        # folds into a sawtooth of creases
        h = H[used]
        ad = np.abs(h[a] - h[d]) <= np.abs(h[b] - h[c])
        t1 = np.where(ad[:, None], np.stack([a, b, d], 1), np.stack([a, b, c], 1))
        t2 = np.where(ad[:, None], np.stack([a, d, c], 1), np.stack([b, d, c], 1))
        T = np.concatenate([t1, t2])
        return T if up else T[:, ::-1]

    # counter-clockwise in (u, v) faces +w: up on the top face, down on the bottom one
    top_f = halves(top, True)
    bot_f = halves(bottom, False) + ni
    walls = []
    pad = np.pad(sq, 1)
    # an edge of the outline between nodes p -> q (counter-clockwise around the squares) gets a
    # wall quad p_top, p_bot, q_bot, q_top facing outwards
    for (oi, oj), (p, q) in (((0, -1), ((0, 0), (1, 0))), ((1, 0), ((1, 0), (1, 1))),
                             ((0, 1), ((1, 1), (0, 1))), ((-1, 0), ((0, 1), (0, 0)))):
        out = sq & ~pad[1 + oi:1 + oi + sq.shape[0], 1 + oj:1 + oj + sq.shape[1]]
        ei, ej = np.nonzero(out)
        P = idx[ei + p[0], ej + p[1]]
        Q = idx[ei + q[0], ej + q[1]]
        walls += [np.stack([P, P + ni, Q + ni], 1), np.stack([P, Q + ni, Q], 1)]
    # (u left, v anterior, w up) is left-handed: the windings above face inwards, so reverse them
    F = np.concatenate([top_f, bot_f, *walls])[:, ::-1]
    return V, np.ascontiguousarray(F)


def shape(maxilla, mandible, up, anterior, hinge, hinge_axis, *, clearance: float = 1e-4, thickness: float = 1.5e-3,
          opening_deg: float | None = None, grid: float = GRID) -> WaferShape:
    """The wafer between ``maxilla`` and ``mandible`` (each ``(V, F)``, the mandible at its
    occlusion), in their frame (metres).

    Parameters
    ----------
    up, anterior : (3,)
        The maxillary arch's up and anterior directions (``arch.ArchFrame``).
    hinge, hinge_axis : (3,)
        The condylar axis; a positive turn about ``hinge_axis`` opens the mandible.
    clearance : float
        Gap between each arch and its imprint (m).
    thickness : float
        Minimum thickness of the wafer (m): a ball of this diameter fits at every point.
    opening_deg : float, optional
        The mandible's opening about the hinge; default the smallest that leaves room for
        ``thickness`` between the offset arches everywhere over the dentition.
    """
    import time

    from .exact import coal_bvh, coal_distance

    t0 = time.perf_counter()
    (Vx, Fx), (Vd, Fd) = [(np.asarray(V, float), np.asarray(F, np.int64)) for V, F in (maxilla, mandible)]
    if clearance < 0 or thickness <= 0:
        raise ValueError(f"clearance {clearance * 1e3:g} mm and thickness {thickness * 1e3:g} mm: the clearance must be ≥ 0 "
                         "and the thickness > 0")
    from .arch import occlusal_points

    B = _basis(up, anterior)
    P = occlusal_points(Vx, Vd, Fd, reach=REACH)
    if len(P) < 20:
        raise ValueError(f"the arches are more than {REACH * 1e3:g} mm apart at the given occlusion (only {len(P)} maxillary "
                         "points within reach): pass the pose where the teeth meet (--pose occlusion.json or --search)")
    L = (P - P.mean(axis=0)) @ B.T
    origin = P.mean(axis=0)
    margin = RIM + CLOSE + IMPRINT
    g = _Grid(B, origin, L[:, :2].min(axis=0) - margin, L[:, :2].max(axis=0) + margin, grid)
    band = float(np.ptp(L[:, 2])) + 4 * IMPRINT + 2 * thickness
    rho = max(clearance, 1.5 * grid)  # the ball dropped; shifted back to the clearance below
    nx = _normals(Vx, Fx) @ B[2]
    everywhere = np.ones(g.shape, bool)
    sx = surface_samples(Vx, Fx, SAMPLE, (nx < 0.3) & _crop(Vx, Fx, g, everywhere, band))
    Hx = g.drop(sx, rho, -1) + (rho - clearance)
    nd = _normals(Vd, Fd) @ B[2]
    sd = surface_samples(Vd, Fd, SAMPLE, (nd > -0.5) & _crop(Vd, Fd, g, everywhere, band))
    Hd0 = g.drop(sd, rho, +1) - (rho - clearance)
    inside = _outline(Hx - Hd0 - 2 * clearance, g)
    # the mandible's samples over the outline (and a margin for the opening's shift), in the grid's frame
    sd = sd[_over(g, sd, _dilate_mask(inside, g, 2 * IMPRINT))]
    Ld = g.local(sd)
    t_samples = time.perf_counter()
    # the occlusal parts of the arches, for coal's exact distance as the mandible opens
    bx = coal_bvh(Vx, Fx[_crop(Vx, Fx, g, inside, band)])
    cd = _crop(Vd, Fd, g, inside, band)
    bd = coal_bvh(Vd, Fd[cd])
    I4 = np.eye(4)
    r = 0.5 * thickness + 0.5 * grid  # the opening ball: half the thickness and half a grid step of margin
    core = _erode_mask(inside, g, r)
    top = np.minimum(Hx, _cap(Hx, inside, g, -1))
    hi_c = _erode(np.where(inside, top, np.inf), g, r)  # the highest ball centres under the fixed upper face
    G = np.eye(4)  # world -> grid frame
    G[:3, :3], G[:3, 3] = B, -B @ origin

    def fits(theta) -> tuple[bool, np.ndarray]:
        T = G @ hinge_turn(theta, hinge, hinge_axis) @ np.linalg.inv(G)
        Hd = g.drop_local(apply_pose(T, Ld), rho, +1) - (rho - clearance)
        bottom = np.maximum(Hd, _cap(Hd, inside, g, +1))
        lo_c = _dilate(np.where(inside, bottom, -np.inf), g, r)
        return bool(np.all(hi_c[core] >= lo_c[core])), bottom

    need = 2 * r + 2 * clearance  # the ball and the clearances: coal's distance where the grid's test should pass
    if opening_deg is None:
        lo_t, hi_t = 0.0, np.radians(MAX_OPENING_DEG)
        if coal_distance(bx, I4, bd, hinge_turn(hi_t, hinge, hinge_axis)) < need:
            raise ValueError(f"even opened {MAX_OPENING_DEG:g}° about the hinge the arches stay closer than "
                             f"{need * 1e3:.2f} mm over the dentition: check the hinge (--hinge) and the occlusion")
        if coal_distance(bx, I4, bd, I4) >= need:
            hi_t = 0.0
        for _ in range(40):  # bisection on the exact distance between the occlusal parts
            if hi_t - lo_t < np.radians(1e-3):
                break
            mid = 0.5 * (lo_t + hi_t)
            if coal_distance(bx, I4, bd, hinge_turn(mid, hinge, hinge_axis)) >= need:
                hi_t = mid
            else:
                lo_t = mid
        theta = hi_t
        ok, bottom = fits(theta)
        step = np.radians(0.05)
        while not ok and theta < np.radians(MAX_OPENING_DEG):  # the grid's ball test has the last word
            theta += step
            ok, bottom = fits(theta)
        source = "smallest"
    else:
        theta = np.radians(float(opening_deg))
        ok, bottom = fits(theta)
        source = "given"
    if not ok:
        raise ValueError(f"opened {np.degrees(theta):.2f}° about the hinge, the arches leave less than {thickness * 1e3:g} mm "
                         f"(+ {clearance * 1e3:g} mm clearance each side) over part of the dentition: open more (--opening) "
                         "or leave --opening out for the smallest opening that fits")
    t_open = time.perf_counter()
    T = hinge_turn(theta, hinge, hinge_axis)
    gap = coal_distance(bx, I4, bd, T)
    # open the solid by the ball: centres where the ball fits, then the union of the balls
    lo_c = _dilate(np.where(inside, bottom, -np.inf), g, r)
    centre = core & (hi_c >= lo_c) & np.isfinite(hi_c) & np.isfinite(lo_c)
    top_o = _dilate(np.where(centre, hi_c, -np.inf), g, r)
    bot_o = _erode(np.where(centre, lo_c, np.inf), g, r)
    # the rim's columns: the balls' union thins to nothing at their equators, which a grid cannot
    # facet (the last square would be a knife edge); the outline is cut where the wafer is still
    # the thickness tall, leaving a wall there with the balls' rounded fillets above and below
    valid = np.isfinite(top_o) & np.isfinite(bot_o) & (top_o - bot_o >= thickness)
    V, F = _mesh(top_o, bot_o, valid, g)
    t_mesh = time.perf_counter()
    seat = _erode_mask(centre, g, TIP)  # cusps with the wafer all round them
    cusps = {"maxilla": cusp_tips(Vx, Fx, g, seat, band, -1, other=(Vd, Fd)),
             "mandible": apply_pose(T, cusp_tips(Vd, Fd, g, seat, band, +1, other=(Vx, Fx)))}
    return WaferShape(V, F, float(np.degrees(theta)), source, T, clearance, thickness, float(gap), grid, cusps,
                      {"samples_s": t_samples - t0, "opening_s": t_open - t_samples, "mesh_s": t_mesh - t_open})


def _normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _over(grid, P, mask) -> np.ndarray:
    """Which points ``P`` (world) lie over ``mask``."""
    i, j, ok = grid.index(grid.local(P))
    ok[ok] = mask[i[ok], j[ok]]
    return ok


def _dilate_mask(mask, grid, radius):
    """Nodes within ``radius`` of ``mask`` (an exact Euclidean distance transform)."""
    from scipy import ndimage

    return ndimage.distance_transform_edt(~mask, sampling=grid.h) <= radius + 1e-12


def _erode_mask(mask, grid, radius):
    """Nodes of ``mask`` farther than ``radius`` from outside it (the grid's edge counts as outside)."""
    from scipy import ndimage

    return ndimage.distance_transform_edt(np.pad(mask, 1), sampling=grid.h)[1:-1, 1:-1] > radius + 1e-12


COARSE = 2.5e-4  # m: grid of the neighbourhood minima (cusp levels): a tenth of NEIGHBOURHOOD


def _lowest_near(H, grid, radius):
    """``min H`` within about ``radius`` of each node: on blocks of ``COARSE``, then back on the grid."""
    f = max(1, int(round(COARSE / grid.h)))
    ni, nj = H.shape
    P = np.full((-(-ni // f) * f, -(-nj // f) * f), np.inf)
    P[:ni, :nj] = H
    Hc = P.reshape(P.shape[0] // f, f, P.shape[1] // f, f).min(axis=(1, 3))
    Ec = _erode(Hc, grid.h * f, radius, flat=True)
    return np.repeat(np.repeat(Ec, f, axis=0), f, axis=1)[:ni, :nj]


def _cap(H, inside, grid, sign):
    """How far the wafer may wrap the crowns: ``IMPRINT`` past the extreme cusp within
    ``NEIGHBOURHOOD`` (above it for the maxilla, ``sign`` -1; below for the mandible, +1)."""
    if sign < 0:
        return _lowest_near(np.where(inside, H, np.inf), grid, NEIGHBOURHOOD) + IMPRINT
    return -_lowest_near(np.where(inside, -H, np.inf), grid, NEIGHBOURHOOD) - IMPRINT


def cusp_tips(V, F, grid, over, band, sign, other=None) -> np.ndarray:
    """Cusp tips of an arch over the grid mask ``over``: its occlusal vertices (facing the other
    arch: down for the maxilla, ``sign`` -1, up for the mandible, +1; within ``REACH`` of
    ``other`` = (V, F) of the other arch at the occlusion, when given) that are the extreme
    occlusal vertex within ``TIP``."""
    n = np.zeros_like(V)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    facing = (n @ grid.B[2]) * sign > 0.5 * np.linalg.norm(n, axis=1)
    L = grid.local(V)
    i, j, ok = grid.index(L)
    ok &= facing & (np.abs(L[:, 2]) < band)
    if other is not None:
        from ..geometry.bvh import BVH

        k = np.flatnonzero(ok)
        Vo, Fo = other
        ok[k] = BVH.of_triangles(Vo, Fo).distance(np.ascontiguousarray(V[k]), Vo, Fo, within=REACH) < REACH
    H = np.full(grid.shape, np.inf)
    np.minimum.at(H, (i[ok], j[ok]), -sign * L[ok, 2])  # the extreme (lowest for the maxilla) per node
    local = _lowest_near(H, grid, TIP)
    ok[ok] = over[i[ok], j[ok]]
    k = np.flatnonzero(ok)
    tip = -sign * L[k, 2] <= local[i[k], j[k]] + 1e-12
    return V[k[tip]]
