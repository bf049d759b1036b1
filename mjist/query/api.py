"""Queries between two posed Inner Sphere Trees, with per-pair coherence state.

``q = Query(tree_a, tree_b)``; poses are rigid 4x4 transforms of each tree's mesh frame
in the world (mesh units). Every answer carries its error bound: because the leaf spheres
lie inside the meshes and every surface point is within ε of them,

    true distance ∈ [distance - (ε_A + ε_B), distance].

Given the meshes the trees were built from (``Query(a, b, meshes=(mesh_a, mesh_b))``),
``distance`` and ``contacts`` measure the IST's nearest contact groups on the meshes
themselves (``narrow``): distances, points and normals of the true surfaces, and a tighter
interval for the distance.

One numba entry point per call does everything (pose check, relative pose, motion-bound
skip, traversal, world-frame output) on arrays the ``Query`` owns, so a query allocates
nothing in the kernel and pays the Python dispatch once.
"""
from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from ..geometry import surface as sf
from ..tree import InnerSphereTree
from . import narrow as nw
from . import traverse as tv
from .select import spread

METHODS = {"distance": 0, "backtracking": 1, "multipoint": 2}
CANDIDATES = 256  # multipoint groups kept per query (the deepest, if more are found)
NARROWPHASES = ("spheres", "surface")

# ref (coherence) layout: xf at the last full distance query (12), its IST distance, valid
_REF_D = 12
_REF_OK = 13

# the records the contact kernels take (numba reads a namedtuple of arrays as one argument):
# the traversal's scratch (relative pose, pair stack and values)
_Traversal = namedtuple("_Traversal", "xf st sv")
# the contact groups (candidates, their values, last frame's groups and count), the selection
# (chosen, their geometry rows, spread distances)
_Groups = namedtuple("_Groups", "cand cval prev n_prev chosen geom dmin")
# the surface narrow phase's scratch: values, descent temporaries and answer, query stack
_Measure = namedtuple("_Measure", "sval tmp res sst")
# the contacts out (world frame): positions, normals, depths, leaf pairs and groups; count,
# candidates, visits
_Contacts = namedtuple("_Contacts", "pos nrm dep ids info")


@njit(cache=True)
def _world_point(P, x, y, z, out, o):
    for i in range(3):
        out[o + i] = P[i, 0] * x + P[i, 1] * y + P[i, 2] * z + P[i, 3]


@njit(cache=True)
def _world_vec(P, x, y, z, out, o):
    for i in range(3):
        out[o + i] = P[i, 0] * x + P[i, 1] * y + P[i, 2] * z


@njit(cache=True)
def _distance_kernel(Na, Nb, Pa, Pb, method, skip, tol, eps, xf, ref, st, sv, pair, geom, out):
    """out: distance, lower bound of the IST distance, point_a (3), point_b (3), visits."""
    if not tv.relative_pose(Pa, Pb, xf):
        return tv.BAD_POSE
    code = tv.OK
    have_pair = pair[0] >= 0
    if skip and have_pair and ref[_REF_OK] > 0.0 and ref[_REF_D] > eps:
        m = tv.motion_bound(ref[0:12], xf, Nb[0, 0:3], Nb[0, 3])
        if m < ref[_REF_D] - eps:
            # no mesh contact is possible: the IST distance moved by at most m
            v = tv.leaf_geometry(Na, Nb, xf, pair[0], pair[1], geom)
            out[0] = max(v, 0.0)
            out[1] = ref[_REF_D] - m
            out[8] = 0.0
            code = tv.SKIPPED
    if code != tv.SKIPPED:
        if method == 1 and have_pair:
            best, code, visits = tv.min_distance_backtrack(Na, Nb, xf, st, sv, tol, pair, 0.0)
        else:
            best, code, visits = tv.min_distance(Na, Nb, xf, st, sv, np.inf, tol, pair, 0.0)
        if code != tv.OK:
            pair[0] = -1
            pair[1] = -1
            ref[_REF_OK] = 0.0
            return code
        tv.leaf_geometry(Na, Nb, xf, pair[0], pair[1], geom)
        out[0] = max(best, 0.0)
        out[1] = max(best - tol, 0.0)  # the traversal's own tolerance
        out[8] = visits
        for k in range(12):
            ref[k] = xf[k]
        ref[_REF_D] = out[1]
        ref[_REF_OK] = 1.0
    _world_point(Pa, geom[3], geom[4], geom[5], out, 2)
    _world_point(Pa, geom[6], geom[7], geom[8], out, 5)
    return code


@njit(cache=True)
def _write_contacts(Pa, geom, val, cand, chosen, k, out):
    """The ``k`` contacts ``chosen`` (rows of ``geom``, ``cand``; distance ``val``, A's frame)
    into the world-frame outputs ``out`` (``_Contacts``)."""
    for j in range(k):
        i = chosen[j]
        g = geom[i]
        _world_point(Pa, g[9], g[10], g[11], out.pos[j], 0)
        _world_vec(Pa, g[0], g[1], g[2], out.nrm[j], 0)
        out.dep[j] = -val[i]
        out.ids[j, 0] = cand[i, 2]
        out.ids[j, 1] = cand[i, 3]
        out.ids[j, 2] = cand[i, 0]
        out.ids[j, 3] = cand[i, 1]


@njit(cache=True)
def _contacts_kernel(Na, Nb, Pa, Pb, method, split_depth, margin, k_max, tr, pair, G, out):
    """Contacts into ``out`` (``_Contacts``); ``tr``: ``_Traversal``, ``G``: ``_Groups``."""
    xf, st, sv = tr.xf, tr.st, tr.sv
    cand, cval = G.cand, G.cval
    if not tv.relative_pose(Pa, Pb, xf):
        return tv.BAD_POSE
    if method == 2:
        n, code, visits = tv.multipoint(Na, Nb, xf, st, sv, split_depth, margin, G.prev, G.n_prev[0], cand, cval, pair)
    else:
        if method == 1 and pair[0] >= 0:
            best, code, visits = tv.min_distance_backtrack(Na, Nb, xf, st, sv, 0.0, pair, -np.inf)
        else:
            best, code, visits = tv.min_distance(Na, Nb, xf, st, sv, np.inf, 0.0, pair, -np.inf)
        n = 0
        if code == tv.OK and best < margin:
            cand[0, 0] = tv.ancestor_at(Na, pair[0], split_depth)
            cand[0, 1] = tv.ancestor_at(Nb, pair[1], split_depth)
            cand[0, 2] = pair[0]
            cand[0, 3] = pair[1]
            cval[0] = best
            n = 1
    if code != tv.OK:
        G.n_prev[0] = 0
        pair[0] = -1
        pair[1] = -1
        return code
    m = tv.select_spread(Na, Nb, xf, cand, cval, n, k_max, G.chosen, G.geom, G.dmin)
    _write_contacts(Pa, G.geom, cval, cand, G.chosen, m, out)
    _keep_groups(G, n)
    out.info[0] = m
    out.info[1] = n
    out.info[2] = visits
    return tv.OK


@njit(cache=True)
def _keep_groups(G, n):
    """Coherence: every candidate group seeds next frame's search of that group."""
    for i in range(n):
        for c in range(4):
            G.prev[i, c] = G.cand[i, c]
    G.n_prev[0] = n


@njit(cache=True)
def _penetration_kernel(Na, Nb, Pa, Pb, xf, st, sv, acc, pair, out):
    """out: volume, force direction (3, unit, A→B, world), centre (3, world), pairs, visits."""
    if not tv.relative_pose(Pa, Pb, xf):
        return tv.BAD_POSE
    code, visits = tv.penetration(Na, Nb, xf, st, sv, acc, pair)
    if code != tv.OK:
        return code
    vol = acc[0]
    f = math.sqrt(acc[1] * acc[1] + acc[2] * acc[2] + acc[3] * acc[3])
    out[0] = vol
    if f > 0.0:
        _world_vec(Pa, acc[1] / f, acc[2] / f, acc[3] / f, out, 1)
    else:
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 0.0
    if vol > 0.0:
        _world_point(Pa, acc[4] / vol, acc[5] / vol, acc[6] / vol, out, 4)
    else:
        _world_point(Pa, Na[0, 0], Na[0, 1], Na[0, 2], out, 4)
    out[7] = acc[7]
    out[8] = visits
    out[9] = f
    return tv.OK


@njit(cache=True)
def _surface_distance_kernel(Na, Nb, SA, SB, Pa, best, eps, split_depth, k_groups, tr, pair, G, M, out):
    """The surfaces' distance near the IST's minimum ``best`` (``tr.xf`` already posed): the
    deepest ``k_groups`` groups within ``best + eps`` (where the surfaces' closest points lie)
    measured on the meshes. out: smallest value, point on A (3), point on B (3), normal A→B
    (3), all world; returns the number of groups measured (0: none, ``out`` untouched) or an
    error code. ``G``: ``_Groups`` (its coherence fields unused), ``M``: ``_Measure``."""
    xf = tr.xf
    n, code, _ = tv.multipoint(Na, Nb, xf, tr.st, tr.sv, split_depth, best + eps, G.cand, 0, G.cand, G.cval, pair)
    if code != tv.OK:
        return code
    n = nw.deepest(G.cand, G.cval, n, k_groups)
    m, _ = nw.measure(SA, SB, Na, Nb, xf, G.cand, n, np.inf, eps, G.geom, M.sval, M.tmp, M.res, M.sst, sf.EITHER)
    j = nw.smallest(M.sval, m)
    if j < 0:
        return 0
    g = G.geom[j]
    v = M.sval[j]
    h = 0.5 * v  # the point is midway between A's point and B's, along the normal
    out[0] = v
    _world_point(Pa, g[9] - h * g[0], g[10] - h * g[1], g[11] - h * g[2], out, 1)
    _world_point(Pa, g[9] + h * g[0], g[10] + h * g[1], g[11] + h * g[2], out, 4)
    _world_vec(Pa, g[0], g[1], g[2], out, 7)
    return m


@njit(cache=True)
def _surface_contacts_kernel(Na, Nb, SA, SB, Pa, Pb, split_depth, margin, eps, k_groups, k_max, tr, pair, G, M, out):
    """Surface contacts into ``out`` (``_Contacts``): the groups below ``margin + eps`` by the
    IST, the deepest ``k_groups`` by the surfaces (``narrow.screen``) measured on the meshes,
    those below ``margin`` kept (deepest, then spread, one per point)."""
    xf = tr.xf
    if not tv.relative_pose(Pa, Pb, xf):
        return tv.BAD_POSE
    n, code, visits = tv.multipoint(Na, Nb, xf, tr.st, tr.sv, split_depth, margin + eps, G.prev, G.n_prev[0], G.cand,
                                    G.cval, pair)
    if code != tv.OK:
        G.n_prev[0] = 0
        return code
    _keep_groups(G, n)
    out.info[1] = n
    out.info[2] = visits
    k = nw.screen(SA, SB, Na, Nb, xf, G.cand, G.cval, n, k_groups, G.geom, M.tmp, M.sst)
    m, _ = nw.measure(SA, SB, Na, Nb, xf, G.cand, k, margin, eps, G.geom, M.sval, M.tmp, M.res, M.sst, sf.EITHER)
    k = nw.distinct(G.geom, G.chosen, spread(G.geom, 9, M.sval, m, k_max, G.chosen, G.dmin), eps)
    _write_contacts(Pa, G.geom, M.sval, G.cand, G.chosen, k, out)
    out.info[0] = k
    return tv.OK


@njit(cache=True)
def _distance_batch(Na, Nb, Pa, Pb, method, skip, tol, eps, xf, ref, st, sv, pair, geom, out, res):
    """Replay frames ``k``: ``res[k] = distance, lower bound, visits, code`` (no Python per frame)."""
    for k in range(Pa.shape[0]):
        code = _distance_kernel(Na, Nb, Pa[k], Pb[k], method, skip, tol, eps, xf, ref, st, sv, pair, geom, out)
        res[k, 0] = out[0]
        res[k, 1] = out[1]
        res[k, 2] = out[8]
        res[k, 3] = code


class DistanceResult:
    """Answer of ``Query.distance``.

    Attributes
    ----------
    distance : float
        IST distance (≥ 0, 0 when spheres overlap); never below the true mesh distance. With
        ``narrowphase='surface'``, the smaller of it and the surfaces' measured distance (a
        distance between two surface points, so never below the true one either).
    error_bound : float
        The true distance lies in ``[distance - error_bound, distance]``.
    point_a, point_b : ndarray (3,)
        World points on the two closest (or overlapping) leaf spheres; on the two meshes when
        the surface measurement gave the distance.
    colliding : bool
        Leaf spheres overlap, or (``'surface'``) a point of B's surface lies inside A: the
        meshes intersect.
    depth : float
        ``'surface'``: how deep B's deepest point found lies inside A when colliding, else 0
        (measured, not certified: a deeper point can exist). NaN with ``'spheres'``.
    narrowphase : str
        ``'spheres'`` or ``'surface'``: what the answer was measured on.
    skipped : bool
        Motion-bound skip: no traversal ran; ``distance`` is the last frame's closest pair
        re-evaluated, and ``error_bound`` widened by the motion so the interval stays true.
    visits : int
        Node pairs visited by the traversal (0 when skipped).
    """

    __slots__ = ("distance", "error_bound", "point_a", "point_b", "colliding", "depth", "narrowphase", "skipped", "visits",
                 "leaf_pair")

    def __repr__(self):
        return (
            f"DistanceResult(distance={self.distance:.6g}, error_bound={self.error_bound:.3g}, "
            f"colliding={self.colliding}, skipped={self.skipped}, visits={self.visits})"
        )


class ContactResult:
    """Answer of ``Query.contacts``: ``count`` contacts, deepest first then spread out.

    Attributes
    ----------
    positions : ndarray (k, 3)
        World contact points: middle of the two leaf balls' common chord on their centre line
        (inside both balls when they overlap). ``'surface'``: midway between a point of B's
        surface and its closest point on A.
    normals : ndarray (k, 3)
        Unit normals from A to B (centre of A's leaf to centre of B's leaf; ``'surface'``: A's
        outward direction at the contact).
    depths : ndarray (k,)
        Leaf sphere overlap depths (≥ 0; down to ``-margin`` when a margin was asked).
        ``'surface'``: the depth of that point of B inside A (negative: its distance outside).
    leaf_pairs : ndarray (k, 2)
        Node ids of the two leaves; ``groups (k, 2)`` their ancestors at ``split_depth``.
    error_bound : float
        ε_A + ε_B: a sphere contact's depth is within it of the meshes' local penetration. A
        surface contact's depth is exact at its point; ``error_bound`` is then the margin the
        group search adds so that no place closer than ``margin`` is missed.
    candidates : int
        Separate groups below the threshold before selection (≥ count).
    narrowphase : str
        ``'spheres'`` or ``'surface'``.
    """

    __slots__ = ("positions", "normals", "depths", "leaf_pairs", "groups", "count", "candidates", "error_bound", "visits",
                 "narrowphase")

    def __repr__(self):
        return f"ContactResult(count={self.count}, candidates={self.candidates}, visits={self.visits})"


class PenetrationResult:
    """Answer of ``Query.penetration_volume`` (Weller & Zachmann's penetration volume).

    Attributes
    ----------
    volume : float
        Σ of lens volumes of overlapping leaf-sphere pairs (mesh units³); continuous in the pose.
    force_direction : ndarray (3,)
        Unit ``Σ V_ij n_ij`` with ``n_ij`` from A's to B's leaf centre: the direction to push
        B out of A (zero vector when not penetrating).
    force_magnitude : float
        ``|Σ V_ij n_ij|`` before normalising (≤ volume).
    center : ndarray (3,)
        Volume-weighted centre of the lenses (world).
    pairs : int
        Overlapping leaf pairs.
    """

    __slots__ = ("volume", "force_direction", "force_magnitude", "center", "pairs", "visits")

    def __repr__(self):
        return f"PenetrationResult(volume={self.volume:.6g}, pairs={self.pairs}, visits={self.visits})"


def _pose(P, name):
    if not (isinstance(P, np.ndarray) and P.dtype == np.float64 and P.shape == (4, 4) and P.flags.c_contiguous):
        try:
            P = np.ascontiguousarray(P, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a 4x4 rigid transform (numpy array): {exc}") from None
        if P.shape != (4, 4):
            raise ValueError(f"{name} must be a 4x4 rigid transform, got shape {P.shape}")
    return P


class Query:
    """Queries between two Inner Sphere Trees, with the coherence state of this pair.

    Parameters
    ----------
    tree_a, tree_b : InnerSphereTree
        Trees in the same length unit (their poses' translations use it too).
    max_contacts : int
        Capacity of ``contacts`` (default 4: MuJoCo's mesh-mesh cap).
    meshes : (mesh_a, mesh_b), optional
        The meshes the trees were built from (anything ``mjist.build`` takes: path, trimesh,
        ``(vertices, faces)``, ``mjist.Mesh``), checked against the trees' content hashes.
        With them ``distance`` and ``contacts`` default to ``narrowphase='surface'``:
        the IST finds where the surfaces can be close, the meshes say how far.
    surface_groups : int
        Contact groups measured on the meshes per call, the deepest by the IST first; each
        costs tens of µs on a 200 k-face pair (docs/mujoco.md).

    Notes
    -----
    The state remembers last frame's closest leaf pair (``method='backtracking'``), last
    frame's contact groups (``method='multipoint'``) and the pose of the last full distance
    query (``skip=True``). Use one ``Query`` per pair of objects; it is not thread safe.
    """

    def __init__(self, tree_a: InnerSphereTree, tree_b: InnerSphereTree, *, max_contacts: int = 4, meshes=None,
                 surface_groups: int = 8):
        for name, t in (("tree_a", tree_a), ("tree_b", tree_b)):
            if not isinstance(t, InnerSphereTree):
                raise TypeError(f"{name} must be an mjist.InnerSphereTree (from mjist.build or mjist.load_tree), got {type(t).__name__}")
        if not 1 <= int(surface_groups) <= CANDIDATES:
            raise ValueError(f"surface_groups={surface_groups} must be between 1 and {CANDIDATES}")
        self.surface_groups = int(surface_groups)
        self._packed = None if meshes is None else _surfaces(meshes, (tree_a, tree_b))
        self.surfaces = None if meshes is None else tuple(p.views() for p in self._packed)
        self.tree_a = tree_a
        self.tree_b = tree_b
        self.error_bound = float(tree_a.error_bound + tree_b.error_bound)
        self.Na = tv.pack(tree_a)
        self.Nb = tv.pack(tree_b)
        cap = tv.stack_size(self.Na, self.Nb)
        self._st = np.zeros((cap, 2), np.int64)
        self._sv = np.zeros(cap)
        self._xf = np.zeros(12)
        self._ref = np.zeros(14)
        self._pair = np.full(2, -1, np.int64)  # distance coherence
        self._cpair = np.full(2, -1, np.int64)  # single-point contact coherence
        self._ppair = np.full(2, -1, np.int64)  # scratch of the volume traversal
        self._mpair = np.full(2, -1, np.int64)  # scratch of the surface distance's group search
        self._geom = np.zeros((CANDIDATES, nw.GEOM_W))
        self._dout = np.zeros(9)
        self._cand = np.zeros((CANDIDATES, 4), np.int64)
        self._cval = np.zeros(CANDIDATES)
        self._prev = np.zeros((CANDIDATES, 4), np.int64)
        self._n_prev = np.zeros(1, np.int64)
        self._dmin = np.zeros(CANDIDATES)
        self._info = np.zeros(3, np.int64)
        self._acc = np.zeros(8)
        self._pout = np.zeros(10)
        self._sval = np.zeros(CANDIDATES)
        self._stmp = np.zeros(sf.REFINE_W)
        self._sres = np.zeros(7)
        self._sst = np.zeros(sf.STACK, np.int64)
        self._sout = np.zeros(10)
        self._tr = _Traversal(self._xf, self._st, self._sv)
        self._measure = _Measure(self._sval, self._stmp, self._sres, self._sst)
        self._resize_contacts(max_contacts)

    def _narrow(self, narrowphase):
        if narrowphase is None:
            return "spheres" if self.surfaces is None else "surface"
        if narrowphase not in NARROWPHASES:
            raise ValueError(f"narrowphase must be 'spheres' or 'surface', got {narrowphase!r}")
        if narrowphase == "surface" and self.surfaces is None:
            raise ValueError("narrowphase='surface' needs the meshes: Query(tree_a, tree_b, meshes=(mesh_a, mesh_b))")
        return narrowphase

    def _resize_contacts(self, k):
        self._k = k
        self._chosen = np.zeros(k, np.int64)
        self._groups = _Groups(self._cand, self._cval, self._prev, self._n_prev, self._chosen, self._geom, self._dmin)
        self._out = _Contacts(np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k), np.zeros((k, 4), np.int64), self._info)

    def reset(self):
        """Forget the coherence state (next queries start from the roots)."""
        self._pair[:] = -1
        self._cpair[:] = -1
        self._ref[:] = 0.0
        self._n_prev[0] = 0

    @staticmethod
    def _check(code):
        if code == tv.BAD_POSE:
            raise ValueError("pose_a and pose_b must be finite rigid 4x4 transforms (orthonormal rotation, no scale)")
        if code == tv.STACK_FULL:  # pragma: no cover - excluded by stack_size
            raise RuntimeError("IST traversal stack overflow: the trees' depth arrays are inconsistent")

    def distance(self, pose_a, pose_b, *, method: str = "backtracking", skip: bool = False,
                 tolerance: float = 0.0, narrowphase: str | None = None) -> DistanceResult:
        """Distance between the two trees' sphere unions at the given poses.

        Parameters
        ----------
        method : {'backtracking', 'distance'}
            'distance' traverses from the roots; 'backtracking' starts from last call's
            closest leaf pair and climbs only as far as needed. Both give the same answer.
        skip : bool
            Motion-bound skip: if the relative motion since the last full query is smaller
            than its distance minus the error bound, no contact is possible and no traversal
            runs (``result.skipped``); the returned interval stays true.
        tolerance : float
            Approximate traversal: prune pairs that cannot beat the best so far by more than
            ``tolerance`` (mesh units). ``error_bound`` grows by at most ``tolerance``; a
            fraction of ε costs little accuracy and saves much of the traversal.
        narrowphase : {'spheres', 'surface'}, optional
            'surface' (the default when the ``Query`` has the meshes) measures the groups of
            leaf pairs within ε_A + ε_B of the IST's minimum on the meshes (the surfaces'
            closest points lie in one of them) and answers the smallest distance found when
            it is below the IST's. The interval keeps the IST's certified lower end and gets
            this measured upper end, so it narrows by how far the surfaces lie outside the
            spheres; when B's surface is found inside A the meshes intersect: distance 0,
            error bound 0, ``depth`` the depth found. A motion-bound skip (``skip=True``)
            answers on the spheres.
        """
        if not (math.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f"tolerance must be finite and ≥ 0, got {tolerance}")
        narrow = self._narrow(narrowphase)
        m = METHODS.get(method, -1)
        if m not in (0, 1):
            raise ValueError(f"method must be 'distance' or 'backtracking', got {method!r}")
        out = self._dout
        code = _distance_kernel(
            self.Na, self.Nb, _pose(pose_a, "pose_a"), _pose(pose_b, "pose_b"),
            m, bool(skip), float(tolerance), self.error_bound, self._xf, self._ref, self._st, self._sv, self._pair, self._geom[0], out,
        )
        self._check(code)
        r = DistanceResult()
        r.distance = float(out[0])
        r.error_bound = float(out[0] - out[1]) + self.error_bound
        r.point_a = out[2:5].copy()
        r.point_b = out[5:8].copy()
        r.skipped = code == tv.SKIPPED
        r.colliding = (not r.skipped) and out[0] == 0.0
        r.visits = int(out[8])
        r.leaf_pair = (int(self._pair[0]), int(self._pair[1]))
        r.narrowphase = "spheres"
        r.depth = math.nan
        if narrow == "surface" and not r.skipped:
            self._surface_distance(r, _pose(pose_a, "pose_a"), float(out[1]))
        return r

    def _surface_distance(self, r, Pa, lower):
        """Refines ``r`` on the meshes; ``lower``: the IST distance's certified lower end."""
        SA, SB = self.surfaces
        o = self._sout
        code = _surface_distance_kernel(
            self.Na, self.Nb, SA, SB, Pa, r.distance, self.error_bound, 3, self.surface_groups, self._tr, self._mpair,
            self._groups, self._measure, o,
        )
        self._check(code)
        r.narrowphase = "surface"
        r.depth = 0.0
        if code == 0:  # no surface query answered: the spheres' answer stands
            return
        if o[0] < 0.0:
            r.distance = 0.0
            r.error_bound = 0.0
            r.colliding = True
            r.depth = float(-o[0])
        elif o[0] < r.distance:
            r.distance = float(o[0])
            r.error_bound = r.distance - max(lower - self.error_bound, 0.0)
        else:
            return
        r.point_a = o[1:4].copy()
        r.point_b = o[4:7].copy()

    def distance_batch(self, poses_a, poses_b, *, method: str = "backtracking", skip: bool = False,
                       tolerance: float = 0.0) -> dict:
        """``distance`` over a sequence of frames in one kernel call (coherence carries over), on
        the spheres.

        Parameters
        ----------
        poses_a, poses_b : array (n, 4, 4)
            One pose per frame, or one (4, 4) pose for all frames.

        Returns
        -------
        dict
            ``distance``, ``error_bound`` (per frame, same meaning as ``distance()``),
            ``visits`` and ``skipped`` arrays.
        """
        m = METHODS.get(method, -1)
        if m not in (0, 1):
            raise ValueError(f"method must be 'distance' or 'backtracking', got {method!r}")
        if not (math.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f"tolerance must be finite and ≥ 0, got {tolerance}")
        Pa = np.asarray(poses_a, dtype=np.float64)
        Pb = np.asarray(poses_b, dtype=np.float64)
        n = max(Pa.shape[0] if Pa.ndim == 3 else 1, Pb.shape[0] if Pb.ndim == 3 else 1)
        Pa = np.broadcast_to(Pa, (n, 4, 4)).copy() if Pa.shape[-2:] == (4, 4) else Pa
        Pb = np.broadcast_to(Pb, (n, 4, 4)).copy() if Pb.shape[-2:] == (4, 4) else Pb
        if Pa.shape != (n, 4, 4) or Pb.shape != (n, 4, 4):
            raise ValueError(f"poses must be (n, 4, 4) or (4, 4) arrays, got {np.shape(poses_a)} and {np.shape(poses_b)}")
        res = np.zeros((n, 4))
        _distance_batch(
            self.Na, self.Nb, Pa, Pb, m, bool(skip), float(tolerance), self.error_bound,
            self._xf, self._ref, self._st, self._sv, self._pair, self._geom[0], self._dout, res,
        )
        code = res[:, 3].astype(np.int64)
        bad = np.flatnonzero(code < 0)
        if len(bad):
            self._check(int(code[bad[0]]))
        return {
            "distance": res[:, 0].copy(),
            "error_bound": res[:, 0] - res[:, 1] + self.error_bound,
            "visits": res[:, 2].astype(np.int64),
            "skipped": code == tv.SKIPPED,
        }

    def contacts(self, pose_a, pose_b, *, max_contacts: int | None = None, split_depth: int = 3,
                 margin: float = 0.0, method: str = "multipoint", narrowphase: str | None = None) -> ContactResult:
        """Contacts between the two trees: leaf-sphere pairs closer than ``margin`` (default: overlapping).

        Parameters
        ----------
        max_contacts : int, optional
            At most this many contacts (default: the ``Query``'s ``max_contacts``).
        split_depth : int
            'multipoint' returns at most one contact per pair of subtrees rooted at this
            depth, so contacts are spread out; the deepest come first, then the farthest
            from those already chosen.
        margin : float
            Report pairs whose sphere distance is below ``margin`` (≥ 0, mesh units).
        method : {'multipoint', 'backtracking', 'distance'}
            'multipoint' reuses last frame's contact groups to seed this frame's search;
            the other two return the single deepest pair.
        narrowphase : {'spheres', 'surface'}, optional
            'surface' (the default when the ``Query`` has the meshes; 'multipoint' only)
            searches the groups within ``margin + ε_A + ε_B`` (so no place where the surfaces
            are within ``margin`` is missed), measures the ``surface_groups`` deepest on the
            meshes and returns those closer than ``margin``: depth, point and normal of the
            true surfaces.
        """
        m = METHODS.get(method, -1)
        if m < 0:
            raise ValueError(f"method must be 'multipoint', 'backtracking' or 'distance', got {method!r}")
        narrow = self._narrow(narrowphase)
        if narrow == "surface" and m != 2:
            raise ValueError(f"narrowphase='surface' measures the contact groups of method='multipoint', got {method!r}: "
                             "use method='multipoint' or narrowphase='spheres'")
        k = self._k if max_contacts is None else int(max_contacts)
        if k < 1:
            raise ValueError(f"max_contacts must be ≥ 1, got {max_contacts}")
        if int(split_depth) < 0:
            raise ValueError(f"split_depth must be ≥ 0, got {split_depth}")
        if not (math.isfinite(margin) and margin >= 0):
            raise ValueError(f"margin must be finite and ≥ 0, got {margin}")
        if k != self._k:
            self._resize_contacts(k)
        if narrow == "surface":
            SA, SB = self.surfaces
            code = _surface_contacts_kernel(
                self.Na, self.Nb, SA, SB, _pose(pose_a, "pose_a"), _pose(pose_b, "pose_b"), int(split_depth),
                float(margin), self.error_bound, self.surface_groups, k, self._tr, self._cpair, self._groups,
                self._measure, self._out,
            )
        else:
            code = _contacts_kernel(
                self.Na, self.Nb, _pose(pose_a, "pose_a"), _pose(pose_b, "pose_b"), m, int(split_depth),
                float(margin), k, self._tr, self._cpair, self._groups, self._out,
            )
        self._check(code)
        o = self._out
        n = int(o.info[0])
        r = ContactResult()
        r.count = n
        r.positions = o.pos[:n].copy()
        r.normals = o.nrm[:n].copy()
        r.depths = o.dep[:n].copy()
        r.leaf_pairs = o.ids[:n, 0:2].copy()
        r.groups = o.ids[:n, 2:4].copy()
        r.candidates = int(o.info[1])
        r.visits = int(o.info[2])
        r.error_bound = self.error_bound
        r.narrowphase = narrow
        return r

    def penetration_volume(self, pose_a, pose_b) -> PenetrationResult:
        """Penetration volume: Σ of lens volumes of all overlapping leaf-sphere pairs."""
        out = self._pout
        code = _penetration_kernel(
            self.Na, self.Nb, _pose(pose_a, "pose_a"), _pose(pose_b, "pose_b"),
            self._xf, self._st, self._sv, self._acc, self._ppair, out,
        )
        self._check(code)
        r = PenetrationResult()
        r.volume = float(out[0])
        r.force_direction = out[1:4].copy()
        r.center = out[4:7].copy()
        r.pairs = int(out[7])
        r.visits = int(out[8])
        r.force_magnitude = float(out[9])
        return r


def _surfaces(meshes, trees):
    """The two meshes packed for the surface narrow phase, each checked against its tree."""
    from ..errors import MeshError
    from ..geometry.mesh import load_mesh

    try:
        mesh_a, mesh_b = meshes
    except (TypeError, ValueError):
        raise ValueError("meshes must be a pair (mesh_a, mesh_b): the meshes the two trees were built from") from None
    out = []
    for name, mesh, tree in (("a", mesh_a, trees[0]), ("b", mesh_b, trees[1])):
        if tree.params.get("spheres"):
            raise ValueError(f"tree_{name} is a sphere set (mjist.sphere_tree), not a mesh's tree: it has no surface to "
                             "measure; leave meshes unset")
        try:
            m = load_mesh(mesh, repair=bool(tree.params.get("repair", False)), max_deviation=tree.params.get("max_deviation"))
        except MeshError as exc:
            raise MeshError(f"mesh_{name}: {exc}") from None
        if m.content_hash != tree.mesh_hash:
            raise ValueError(f"mesh_{name} is not the mesh tree_{name} was built from (content hashes differ): pass the "
                             "mesh given to mjist.build, in the same units and frame")
        s = sf.build_surface(m.vertices, m.faces)
        from ..cache import cached_grid

        s.grid = cached_grid(m.vertices, m.faces, lambda s=s: sf.add_grid(s).grid)
        out.append(s)
    return out
