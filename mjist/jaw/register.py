"""Registration of two dental arches that ignores their given relative pose.

Arches come scanned separately (plaster models, intraoral scans without a bite scan, each
exported in its own frame), moved by a surgical plan, or in a bite known to be wrong. This
module puts the mandible in front of the maxilla from the arches' own shapes alone, so that the
occlusion search starts from the anatomy, not from wherever the files happened to lie:

1. **Each arch's frame** (``arch_axes``), from its vertices and normals only:

   * *left*: the normal of the arch's mirror plane (every arch is bilaterally symmetric),
     fitted by iterated closest-point matching of the arch against its own mirror image from
     each principal axis, keeping the best-matching plane;
   * *teeth direction*: the crowns carry most of the surface's sharp detail (cusps, fissures,
     embrasures), bone and cast bases are smooth or flat: the vertices whose normals vary most
     within ``DETAIL_RADIUS`` lie on a flat horseshoe whose normal, in the mirror plane, is the
     occlusal direction, signed by where those vertices' normals point (the occlusal surfaces
     face away from the arch);
   * *anterior*: the end of the arch where the horseshoe closes (it is narrower at the incisors
     than across the molars, rami or a cast's heels).

   Every step is computed from the vertices in their given order (no random sampling), so the
   frame moves exactly with the arch: the same arch given in any pose yields the same frame
   relative to it.

2. **Docking** (``register``): with the frames aligned (both mirror planes one plane, the
   mandible's teeth facing the maxilla's), the two occlusal surfaces are brought against each
   other along the occlusal direction (rays from each arch's occlusal points to the other
   arch: the first touch) and scored by the mean vertical gap left between them (capped at
   ``GAP_CAP``): interlocking cusps leave little gap over the whole dentition, a tipped or
   shifted arch leaves its far end open. A grid over the tilt in the mirror plane (the
   per-arch occlusal directions are rough) and the antero-posterior shift finds the basin;
   Powell's method (scipy) then refines tilt, shift, lateral shift, turn about the vertical and
   roll together.

The result is a rigid transform of the mandible (its file's frame, metres) into the maxilla's
file frame, at first touch, with the figures that say how it was found and how sure it is: the
docking score, the runner-up minimum at least ``RUNNER_UP_MM`` away and its score.

Only numpy, scipy (KD-trees, Powell) and the project's ray-casting BVH are used: Open3D's
FPFH global registration matches a surface to a copy of itself, whereas the two arches are
complementary surfaces (one's cusps sit in the other's fossae), which no feature
correspondence between them describes; the arches' symmetry and the docking do.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ranking import shift_mm

DETAIL_RADIUS = 1.0e-3  # m: neighbourhood over which a vertex's normal variation is measured (about a cusp's size)
DETAIL_POINTS = 30000  # vertices (evenly over the vertex list) where it is measured
DETAIL_SHARE = 0.2  # the share of vertices with the most normal variation taken as the crowns' detail
MIRROR_POINTS = 4000  # vertices (evenly over the vertex list) matched against their mirror image
MIRROR_ITERS = 30
FACING = 0.3  # cosine: an occlusal point's normal is this close to the teeth direction
ARCH_REACH = 0.060  # m: occlusal points lie within this of the arch's front (no condyles, fossae or heels)
OCCLUSAL_POINTS = 600  # per arch for the first docking, evenly over the occlusal points found (each costs a ray per pose)
MEET_POINTS = 1500  # per arch for the second docking
GAP_CAP = 3e-3  # m: a vertical gap is capped here (a region that does not meet says no more than that)
# the share of occlusal points allowed to pass through the other arch when scoring a docking: it smooths
# the landscape over cusps that collide before they interlock (the final placement is an exact first touch)
SOFT_TOUCH = 0.05
TILT_RANGE_DEG = 36.0  # the grid's tilt range about the aligned frames (the per-arch occlusal directions are rough)
TILT_STEP_DEG = 4.0
SHIFT_RANGE_MM = 26.0  # the grid's antero-posterior range about the aligned fronts
SHIFT_STEP_MM = 1.5
RUNNER_UP_MM = 1.0
REFINE_EVALS = 300  # Powell's evaluations per refined grid minimum: ~0.1 mm / 0.1°, well inside the search's range
REFINED = 2  # grid minima refined
# the second docking: only the points of either arch within MEET_REACH of the other at the first
# docking (the surfaces that meet), a stricter soft touch and a tighter cap
MEET_REACH = 3e-3
MEET_SOFT_TOUCH = 0.02
MEET_CAP = 1e-3
MEET_EVALS = 400  # a second docking minimum this far (largest tooth shift) from the best is reported beside it


@dataclass
class ArchAxes:
    """An arch's own frame in its file's coordinates (metres), from its shape alone."""

    left: np.ndarray  # unit: towards the patient's left
    teeth: np.ndarray  # unit: the way the crowns point (down for a maxilla, up for a mandible)
    anterior: np.ndarray  # unit: towards the incisors
    origin: np.ndarray  # on the mirror plane, at the front of the occlusal points, at their occlusal level
    mirror_mm: float  # median mismatch of the arch against its mirror image (how symmetric it is)

    def matrix(self, up: np.ndarray) -> np.ndarray:
        """Rows: left, up, anterior (a right-handed frame with ``up`` one of ±teeth)."""
        left = np.cross(up, self.anterior)
        return np.array([left / np.linalg.norm(left), up, self.anterior])

    def as_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}


@dataclass
class Registration:
    """The mandible placed against the maxilla from the arches' shapes (``register``)."""

    transform: np.ndarray  # (4, 4): mandible file (m) -> maxilla file (m), at first touch
    score_mm: float  # the second docking's score: mean gap of the surfaces that meet (mm, lower fits better)
    coarse_score_mm: float  # the first docking's score, which the runner-up's compares with
    runner_up_mm: float | None  # the first docking's best score at least RUNNER_UP_MM away (None: no other minimum)
    runner_up_shift_mm: float | None  # how far that minimum is (largest tooth-point shift)
    maxilla: ArchAxes
    mandible: ArchAxes
    seconds: float

    def as_dict(self) -> dict:
        return {"method": "arch frames (mirror plane, crown detail, arch form) then occlusal docking (rays, Powell)",
                "transform": self.transform.tolist(), "score_mm": self.score_mm, "coarse_score_mm": self.coarse_score_mm, "runner_up_mm": self.runner_up_mm,
                "runner_up_shift_mm": self.runner_up_shift_mm, "maxilla": self.maxilla.as_dict(),
                "mandible": self.mandible.as_dict(), "seconds": self.seconds}


def _scatter(X) -> np.ndarray:
    """``Xᵀ X`` summed in a fixed order (einsum, not BLAS, whose sums depend on its thread count):
    the same arch gives the same frame with 1 thread or 8, in a Ray worker or not."""
    return np.einsum("ij,ik->jk", X, X)


def _even(n_total: int, n: int) -> np.ndarray:
    return np.linspace(0, n_total - 1, min(n, n_total)).astype(np.int64)


def _normals(V, F) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.Trimesh(V, F, process=False).vertex_normals)


def mirror_plane(V, start=None) -> tuple[np.ndarray, float, float]:
    """The plane an arch ``V (n, 3)`` is most symmetric about: ``(normal, offset, median mismatch)``
    with ``normal · x = offset`` on the plane (the normal's sign is arbitrary); ``start``
    (normal, offset) is matched from alone when given."""
    from scipy.spatial import cKDTree

    P = np.asarray(V, float)[_even(len(V), MIRROR_POINTS)]
    tree = cKDTree(P)
    c = P.mean(axis=0)
    _, vecs = np.linalg.eigh(_scatter(P - c))
    best = (np.inf, None, 0.0)
    # starts: the principal axes, their pairwise diagonals and the body diagonals, in the principal
    # frame (a set unchanged by the axes' sign flips, so the fit moves with the arch); an arch in
    # pieces (teeth and fossae) can have two equal principal extents, whose axes then say little
    dirs = [np.array(v, float) for v in np.ndindex(3, 3, 3)]
    dirs = [v - 1.0 for v in dirs]
    dirs = [v / np.linalg.norm(v) for v in dirs if v.any() and v[np.flatnonzero(v)[0]] > 0]
    starts = [(vecs @ v, float(c @ (vecs @ v))) for v in dirs] if start is None else [start]
    for n, d in starts:
        n = np.asarray(n, float)
        for _ in range(MIRROR_ITERS):
            M = P - 2.0 * (P @ n - d)[:, None] * n
            dist, j = tree.query(M)
            err = float(np.median(dist))
            if err < best[0]:  # every plane tried counts: the iteration is not a descent of this error
                best = (err, n.copy(), d)
            keep = dist <= np.quantile(dist, 0.8)  # the asymmetric fifth (a missing tooth, a cut) does not pull
            D = P[keep] - P[j[keep]]  # a point minus its mirror partner: along the normal
            n_new = np.linalg.eigh(_scatter(D))[1][:, 2]  # the direction the pairs differ along most
            n_new *= 1.0 if n_new @ n >= 0 else -1.0
            d = float(0.5 * (P[keep] + P[j[keep]]).mean(axis=0) @ n_new)
            moved = float(np.linalg.norm(n_new - n))
            n = n_new
            if moved < 1e-6:
                break
        M = P - 2.0 * (P @ n - d)[:, None] * n
        err = float(np.median(tree.query(M)[0]))
        if err < best[0]:
            best = (err, n, d)
    # the matching's update does not descend the median mismatch itself: polish the best plane on it
    from scipy.optimize import minimize

    err, n, d = best
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    scale = float(np.sqrt(np.linalg.eigvalsh(_scatter(P - c))[-1] / len(P)))  # tilts in units of the arch's size

    def plane(x):
        m = n + x[0] * u + x[1] * w
        m /= np.linalg.norm(m)
        return m, d + x[2] * scale

    def mismatch(x):
        m, e = plane(x)
        return float(np.median(tree.query(P - 2.0 * (P @ m - e)[:, None] * m)[0])) / scale

    r = minimize(mismatch, np.zeros(3), method="Nelder-Mead",
                 options={"initial_simplex": 0.02 * np.vstack([np.zeros(3), np.eye(3)]), "xatol": 1e-5, "fatol": 1e-7,
                          "maxfev": 300})
    if r.fun * scale < err:
        (n, d), err = plane(r.x), float(r.fun * scale)
    return n, d, err


def _detail(V, N, at) -> np.ndarray:
    """The normal variation within ``DETAIL_RADIUS`` (1 − length of the mean normal) at the vertices ``at``."""
    from scipy.spatial import cKDTree

    nb = cKDTree(V).query_ball_point(V[at], DETAIL_RADIUS)
    return np.array([1.0 - np.linalg.norm(N[i].mean(axis=0)) for i in nb])


def arch_axes(V, F) -> ArchAxes:
    """The frame of one arch (``ArchAxes``) from its mesh ``(V, F)`` in metres, any pose."""
    V = np.asarray(V, float)
    N = _normals(V, F)
    left, offset, mirror = mirror_plane(V)
    sub = _even(len(V), DETAIL_POINTS)
    detail = _detail(V, N, sub)
    sharp = sub[detail >= np.quantile(detail, 1.0 - DETAIL_SHARE)]
    T, NT = V[sharp], N[sharp]
    _, vecs = np.linalg.eigh(_scatter(T - T.mean(axis=0)))
    teeth = vecs[:, 0] - (vecs[:, 0] @ left) * left  # the horseshoe's normal, in the mirror plane
    teeth /= np.linalg.norm(teeth)
    if NT.sum(axis=0) @ teeth < 0:
        teeth = -teeth
    ant = np.cross(left, teeth)
    # the horseshoe is narrower at its front than at its back (incisors against molars, rami, heels)
    a, s = T @ ant, T @ left - offset
    lo, hi = np.quantile(a, [0.2, 0.8])
    if np.ptp(s[a > hi]) > np.ptp(s[a < lo]):
        ant = -ant
    facing = (N @ teeth > FACING) & (V @ ant > (V @ ant).max() - ARCH_REACH)
    P = V[facing]
    front = float((P @ ant).max())
    level = float(np.quantile(P @ teeth, 0.9))
    origin = left * offset
    origin = origin + ant * (front - origin @ ant) + teeth * (level - origin @ teeth)
    return ArchAxes(left=left, teeth=teeth, anterior=ant, origin=origin, mirror_mm=mirror * 1e3)


def _occlusal(V, F, axes: ArchAxes) -> np.ndarray:
    """Occlusal points of an arch: vertices facing its teeth direction within ``ARCH_REACH`` of its front."""
    N = _normals(V, F)
    keep = (N @ axes.teeth > FACING) & (V @ axes.anterior > axes.origin @ axes.anterior - ARCH_REACH)
    P = V[keep]
    return P[_even(len(P), OCCLUSAL_POINTS)]


def _rot(axis, angle) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(angle * np.asarray(axis, float)).as_matrix()


class _Dock:
    """The docking objective: the mandible moved by (tilt, shift, lateral, turn, roll) from the
    aligned frames, brought up to first touch; the mean capped vertical gap that leaves."""

    soft, cap = SOFT_TOUCH, GAP_CAP

    def __init__(self, maxilla, mandible, ax: ArchAxes, ad: ArchAxes):
        from ..geometry.bvh import BVH

        (self.Vx, self.Fx), (self.Vd, self.Fd) = maxilla, mandible
        self.bx, self.bd = BVH.of_triangles(self.Vx, self.Fx), BVH.of_triangles(self.Vd, self.Fd)
        self.up = -ax.teeth  # maxilla file frame: from the mandible towards the maxilla
        Fx, Fd = ax.matrix(self.up), ad.matrix(ad.teeth)
        self.A = np.eye(4)  # the aligned start: mandible frame onto maxilla frame, fronts together, 50 mm apart
        self.A[:3, :3] = Fx.T @ Fd
        self.A[:3, 3] = ax.origin - self.A[:3, :3] @ ad.origin - 0.050 * self.up
        self.left, self.ant = Fx[0], Fx[2]
        self.px = _occlusal(self.Vx, self.Fx, ax)
        self.pd = _occlusal(self.Vd, self.Fd, ad)  # mandible file frame
        self.pivot = ax.origin - 0.5 * ARCH_REACH * self.ant  # about the middle of the arch
        self.front = float(ax.origin @ self.ant)

    def pose(self, x) -> np.ndarray:
        """The mandible's pose (before touch) for parameters ``x``: tilt, shift, lateral, turn, roll
        (degrees and millimetres: one scale for the optimiser's steps)."""
        tilt, shift, lat, turn, roll = np.radians(x[0]), x[1] * 1e-3, x[2] * 1e-3, np.radians(x[3]), np.radians(x[4])
        R = _rot(self.up, turn) @ _rot(self.ant, roll) @ _rot(self.left, tilt)
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = self.pivot - R @ self.pivot + shift * self.ant + lat * self.left
        return M @ self.A

    def gaps(self, P) -> np.ndarray:
        """How far each occlusal point of both arches runs along up (the mandible's rising, the
        maxilla's falling) before it meets the other arch, with the mandible at ``P``; inf: never."""
        Wd = self.pd @ P[:3, :3].T + P[:3, 3]
        up_gap = self.bx.first_hits(Wd, self.up, self.Vx, self.Fx)
        Rt = P[:3, :3].T  # the maxilla's points seen from the mandible's file frame, moving down
        down_gap = self.bd.first_hits((self.px - P[:3, 3]) @ Rt.T, -Rt @ self.up, self.Vd, self.Fd)
        return np.r_[up_gap, down_gap]

    def touch(self, P) -> np.ndarray:
        """The pose ``P`` moved along up to first touch (an occlusal vertex against the other arch)."""
        g = self.gaps(P)
        Q = P.copy()
        if np.isfinite(g).any():
            Q[:3, 3] += float(g.min()) * self.up
        return Q

    def score(self, x) -> float:
        """Mean distance of the occlusal points' gaps from the ``SOFT_TOUCH`` quantile of them,
        capped at ``GAP_CAP``: how evenly the occlusal surfaces meet once brought together,
        forgiving the few cusps that would hold them apart before interlocking."""
        g = self.gaps(self.pose(x))
        meets = np.isfinite(g)  # a point whose ray misses the other arch counts as a capped gap
        if meets.sum() < self.soft * len(g) * 4:
            return self.cap
        t = np.quantile(g[meets], self.soft * len(g) / meets.sum())
        return float(np.where(meets, np.minimum(np.abs(g - t), self.cap), self.cap).mean())

    def meet(self, P) -> None:
        """Score from now on only the points that meet the other arch with the mandible at ``P``
        (within ``MEET_REACH``, inside the arch's reach), around ``P`` (moved down 5 mm)."""
        Wd = self.Vd @ P[:3, :3].T + P[:3, 3]
        from ..geometry.bvh import BVH

        near_x = BVH.of_triangles(Wd, self.Fd).distance(self.Vx, Wd, self.Fd, within=MEET_REACH) < MEET_REACH
        near_d = self.bx.distance(Wd, self.Vx, self.Fx, within=MEET_REACH) < MEET_REACH
        front = self.front - ARCH_REACH
        px, pd = self.Vx[near_x & (self.Vx @ self.ant > front)], self.Vd[near_d & (Wd @ self.ant > front)]
        if min(len(px), len(pd)) < 50:
            return
        self.px, self.pd = px[_even(len(px), MEET_POINTS)], pd[_even(len(pd), MEET_POINTS)]
        self.A = P.copy()
        self.A[:3, 3] -= 0.005 * self.up
        self.soft, self.cap = MEET_SOFT_TOUCH, MEET_CAP


def register(maxilla, mandible) -> Registration:
    """Place the mandible against the maxilla from the arches' shapes, ignoring their given poses.

    Parameters
    ----------
    maxilla, mandible : (V, F)
        Each arch in its own file's frame, in metres.

    Returns
    -------
    Registration
        ``transform`` maps the mandible's file coordinates into the maxilla's at first touch.
    """
    import time

    from scipy.optimize import minimize

    t0 = time.perf_counter()
    maxilla = (np.asarray(maxilla[0], float), np.asarray(maxilla[1], np.int64))
    mandible = (np.asarray(mandible[0], float), np.asarray(mandible[1], np.int64))
    ax, ad = arch_axes(*maxilla), arch_axes(*mandible)
    dock = _Dock(maxilla, mandible, ax, ad)
    tilts = np.arange(-TILT_RANGE_DEG, TILT_RANGE_DEG + 1e-9, TILT_STEP_DEG)
    shifts = np.arange(-SHIFT_RANGE_MM, SHIFT_RANGE_MM + 1e-9, SHIFT_STEP_MM)
    grid = np.array([[dock.score((a, s, 0.0, 0.0, 0.0)) for s in shifts] for a in tilts])
    # local minima of the grid, best first: each refined, the best refined one kept
    order = np.argsort(grid, axis=None, kind="stable")
    seeds = []
    for k in order:
        i, j = np.unravel_index(k, grid.shape)
        if not np.isfinite(grid[i, j]):
            break
        if all(abs(i - a) > 2 or abs(j - b) > 3 for a, b in seeds):
            seeds.append((i, j))
        if len(seeds) == REFINED:
            break
    if not seeds:
        raise ValueError("the arches never meet when brought together along their occlusal directions: are these a "
                         "maxilla and a mandible (each a dental arch with its teeth)?")
    refined = []
    for i, j in seeds:
        r = minimize(dock.score, np.array([tilts[i], shifts[j], 0.0, 0.0, 0.0]), method="Powell",
                     options={"xtol": 0.02, "ftol": 1e-6, "maxfev": REFINE_EVALS})
        refined.append((float(r.fun), r.x))
    refined.sort(key=lambda z: z[0])
    poses = [dock.touch(dock.pose(x)) for _, x in refined]
    runner = None
    for (f, _), P in zip(refined[1:], poses[1:]):
        shift = shift_mm(P, poses[0], dock.pd)
        if shift >= RUNNER_UP_MM:
            runner = (f * 1e3, shift)
            break
    first = refined[0][0]
    dock.meet(poses[0])  # then the surfaces that meet, more strictly
    r = minimize(dock.score, np.zeros(5), method="Powell", options={"xtol": 0.01, "ftol": 1e-7, "maxfev": MEET_EVALS})
    best, score = dock.touch(dock.pose(r.x)), float(r.fun)
    return Registration(transform=best, score_mm=score * 1e3, coarse_score_mm=first * 1e3,
                        runner_up_mm=None if runner is None else runner[0],
                        runner_up_shift_mm=None if runner is None else runner[1], maxilla=ax, mandible=ad,
                        seconds=time.perf_counter() - t0)
