"""Close an open or many-piece surface into a solid, and say how far it moved and what it added.

Real anatomy arrives open: an intraoral scan is crowns and a strip of gingiva with one long rim
and small holes; a CT segmentation is cut at the scan's edge, split into teeth and bone, and
strewn with loose fragments. An Inner Sphere Tree needs an inside, so ``close_surface`` closes
the surface, in one of two ways:

``meshfix``
    Every connected piece on its own with MeshFix (``pymeshfix``): its hole filling first
    (every input face stays), its full repair only when holes remain; the closed pieces stay
    separate shells. Right for a scan with holes and an open rim, and for pieces that are
    whole objects (teeth segmented apart from bone, specks): the input surface is kept exactly.
    Pieces it cannot close (loose triangles, slivers) are left out, and their vertices count in
    the deviation. Wrong for pieces of one surface (a bone split along seams): each closes into
    a dome of its own, which ``_solid_mismatch`` tells from the input's winding number.
``winding``
    The generalized winding number (libigl's fast winding number, after Jacobson et al. 2013 and
    Barill et al. 2018) decides inside and outside of the whole input at once, whatever its
    pieces and openings: a point is inside where the input winds about it more than half a
    turn. Signed by it, the distance to the input is sampled on an adaptive grid that refines
    only where the surface passes, and contoured by libigl's sparse marching cubes. Near the
    input the nearest face's side is used instead, which keeps thin walls near an opening. Right for
    surfaces open by design (a bone cut at the scan's edge) and split into many pieces. It
    rounds features finer than its cells (``WINDING_CELL`` of the deviation allowed).

``"auto"`` tries MeshFix, then the winding number. Either way the result is measured against
the input: the Hausdorff and mean distance of the input's vertices to the closed surface (the
deviation), and the area, centre and extent of the faces that lie off the input (what was
added). A closing that moves the input further than ``max_deviation`` is refused with what to
try, never used silently. The tree's certified ε holds for the closed surface; against the
input, add the deviation.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import trimesh

from ..errors import MeshError

# the deviation allowed when the caller gives none, relative to the mesh's largest extent:
# 0.2 mm on a 100 mm jaw (``jaw.pair`` passes 0.2 mm in the file's units)
MAX_DEVIATION_RELATIVE = 2e-3
# the winding-number grid's finest cell, relative to the deviation allowed: marching cubes moves a
# smooth surface by a small fraction of a cell and cuts a sharp crest by up to about 2/3 of one;
# smaller cells keep crests but cost the inverse square in time and vertices
WINDING_CELL = 0.75
# the most grid cells the winding number's contour may need (about 1 GB and a few minutes): a finer
# deviation over a large surface is refused rather than left to run out of memory
MAX_CELLS = 2e7
# top level of the winding-number grid: about this many nodes, then halved where the surface passes
COARSE_NODES = 60_000
# within this many cells of the input the side comes from the nearest face, farther from the
# winding number: more keeps thicker walls near an opening whole, but trusts faces further
# from them (a face seen through an opening is the wrong side's)
NEAR = 2.0
# the winding number's contour (tens of times the input's faces at a fine cell) is simplified to
# the first of these multiples of the input's faces that stays closed and meets the deviation
# allowed (the fewest faces the tree and MuJoCo then carry); the simplifier's aggression trades
# its speed for how closely it keeps the shape
DECIMATE_FACES = (2, 4, 8)
DECIMATE_AGGRESSION = 5.0
# MeshFix's closing is taken when its solid and the input's winding-number solid differ by at most
# this fraction of the volume (``_solid_mismatch``, from this many random points): more accepts
# pieces closed on their own that belong to one surface, less sends ordinary scans to the
# winding number (which rounds their crests)
SOLID_MISMATCH = 0.05
SOLID_SAMPLES = 200_000
# pieces MeshFix cannot close (loose triangles and slivers, which enclose nothing) may be left out
# up to this fraction of the input's area, reported; more sends the surface to the winding number
LEFT_OUT_AREA = 0.01
METHODS = ("auto", "meshfix", "winding")


@dataclass
class Closure:
    """What closing an open surface did, in the mesh's units."""

    method: str  # "meshfix" or "winding"
    pieces: int  # connected pieces of the input
    boundary_edges: int  # open edges of the input
    hausdorff: float  # largest distance of an outer input vertex to the closed surface
    mean_deviation: float  # mean distance of the outer input vertices to the closed surface
    max_deviation: float  # the deviation allowed
    kept_fraction: float  # input vertices on the output surface (within 1e-5 of the size)
    added_area: float  # area of the faces off the input surface
    added_centre: np.ndarray
    added_extent: np.ndarray
    left_out: int = 0  # pieces that enclose nothing (loose triangles MeshFix cannot close), left out
    left_out_area: float = 0.0
    left_out_distance: float = 0.0  # their farthest vertex from the closed surface (not in ``hausdorff``)
    inner: int = 0  # input vertices inside the input's own solid (overlapping pieces), not counted

    def describe(self, unit: str = "") -> str:
        u = f" {unit}" if unit else ""
        c = ", ".join(f"{a:.4g}" for a in self.added_centre)
        e = " x ".join(f"{a:.3g}" for a in self.added_extent)
        how = {"meshfix": "MeshFix", "winding": "the winding number"}[self.method]
        out = (f"; left out {self.left_out} loose piece(s) that enclose nothing ({self.left_out_area:.3g}{u}², up to "
               f"{self.left_out_distance:.3g}{u} from the closed surface)" if self.left_out else "")
        if self.inner:
            out += f"; {self.inner} input vertices lie inside the solid (overlapping pieces)"
        return (f"closed {self.boundary_edges} open edges in {self.pieces} piece(s) with {how}: input moved by at most "
                f"{self.hausdorff:.3g}{u} (mean {self.mean_deviation:.3g}{u}, allowed {self.max_deviation:.3g}{u}); added "
                f"{self.added_area:.4g}{u}² of surface around ({c}), spanning {e}{u}{out}")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["added_centre"] = [float(a) for a in self.added_centre]
        d["added_extent"] = [float(a) for a in self.added_extent]
        return d


def _edges(tm) -> tuple[np.ndarray, np.ndarray]:
    return np.unique(np.sort(tm.edges, axis=1), axis=0, return_counts=True)


def _meshfix(piece: trimesh.Trimesh) -> trimesh.Trimesh:
    """One piece closed by MeshFix: its hole filling first (keeps every input face), its full
    repair (which also removes self-intersecting parts) only when holes remain."""
    import pymeshfix

    v, f = np.asarray(piece.vertices, np.float64), np.asarray(piece.faces, np.int32)
    fix = pymeshfix.MeshFix(v, f)
    fix.fill_holes(0, refine=True)  # 0: every hole
    out = trimesh.Trimesh(np.asarray(fix.points, np.float64), np.asarray(fix.faces, np.int64), process=False)
    if out.is_watertight:
        return out
    fix = pymeshfix.MeshFix(v, f)
    fix.repair(joincomp=False, remove_smallest_components=False)
    return trimesh.Trimesh(np.asarray(fix.points, np.float64), np.asarray(fix.faces, np.int64), process=False)


def close_meshfix(tm: trimesh.Trimesh) -> tuple[trimesh.Trimesh, np.ndarray]:
    """``tm`` closed piece by piece with MeshFix; returns it and a mask of ``tm``'s faces left out
    (pieces MeshFix closed to nothing or left open: a loose triangle encloses nothing). Closed
    pieces stay separate shells, even where they overlap: the tree builder takes the inside as
    the nonzero winding number, and an exact union would round the input (manifold3d works in
    single precision and collapses a crest's slivers).

    Raises
    ------
    MeshError
        No piece could be closed.
    """
    closed = []
    left_out = np.zeros(len(tm.faces), bool)
    labels = trimesh.graph.connected_component_labels(tm.face_adjacency, node_count=len(tm.faces))
    for k in range(labels.max() + 1 if len(labels) else 0):
        faces = np.flatnonzero(labels == k)
        p = tm.submesh([faces], append=True, repair=False)
        c = p if p.is_watertight else _meshfix(p)
        if len(c.faces) and c.is_watertight and c.volume != 0:
            if c.volume < 0:  # a loose patch's faces say nothing of its outside: MeshFix may close it inside out
                c.invert()
            closed.append(c)
        else:
            left_out[faces] = True
    if not closed:
        raise MeshError("MeshFix could not close any piece of the surface")
    return trimesh.util.concatenate(closed), left_out


def _solid_mismatch(tm: trimesh.Trimesh, out: trimesh.Trimesh, samples: int = SOLID_SAMPLES) -> float:
    """How much the solid of ``out`` differs from the input's own (its winding number above 1/2):
    the volume in one and not the other over the input's, from random points in the bounds (a
    fixed seed). Closing the pieces of one surface each on its own makes domes and pancakes
    that fit the input's faces but not its inside."""
    import igl

    rng = np.random.default_rng(0)
    lo, hi = tm.bounds
    P = lo + rng.random((samples, 3)) * (hi - lo)
    w_in = igl.fast_winding_number(np.ascontiguousarray(tm.vertices, np.float64), np.ascontiguousarray(tm.faces, np.int64), P)
    w_out = igl.fast_winding_number(np.ascontiguousarray(out.vertices, np.float64),
                                    np.ascontiguousarray(out.faces, np.int64), P)
    a, b = w_in > 0.5, w_out > 0.5
    return float((a != b).sum() / max(a.sum(), 1))


# corners of a grid cell (libigl's sparse marching cubes expects this order)
_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.int64)
# each face of a cell: its four corners (rows of _CORNERS) and the neighbour across it
_FACES = (((0, 3, 4, 7), (-1, 0, 0)), ((1, 2, 5, 6), (1, 0, 0)), ((0, 1, 4, 5), (0, -1, 0)),
          ((2, 3, 6, 7), (0, 1, 0)), ((0, 1, 2, 3), (0, 0, -1)), ((4, 5, 6, 7), (0, 0, 1)))


class _Grid:
    """Signed distance to the input (negative inside: winding number above 1/2) at the nodes of a
    grid of spacing ``h``, evaluated on demand and kept by node key."""

    def __init__(self, V, F, h, nodes):
        import igl

        self._igl = igl
        self.V, self.F, self.h = V, F, h
        self.lo = V.min(0) - 2 * h
        self.n = nodes  # nodes per axis
        self.keys = np.empty(0, np.int64)
        self.vals = np.empty(0)

    def key(self, q):
        return (q[:, 0] * self.n[1] + q[:, 1]) * self.n[2] + q[:, 2]

    def point(self, k):
        n1, n2 = self.n[1], self.n[2]
        return self.lo + np.stack([k // (n1 * n2), (k // n2) % n1, k % n2], 1) * self.h

    def values(self, k):
        """Field at node keys ``k`` (any shape), evaluating those not seen yet."""
        flat = k.ravel()
        u, inv = np.unique(flat, return_inverse=True)
        new = u[~np.isin(u, self.keys)]
        if len(new):
            s = self._signed(self.point(new))
            s[s == 0.0] = 1e-12 * self.h  # a node exactly on the surface would give a zero-area face
            self.keys = np.concatenate([self.keys, new])
            self.vals = np.concatenate([self.vals, s])
            o = np.argsort(self.keys, kind="stable")
            self.keys, self.vals = self.keys[o], self.vals[o]
        return self.vals[np.searchsorted(self.keys, u)][inv].reshape(k.shape)

    def _signed(self, P):
        """Distance to the input, negative inside. Within ``NEAR`` cells of the input the side is
        the nearest face's (its angle-weighted pseudonormal): exact beside a face, and it keeps a
        thin wall near an opening whole, where the winding number falls below 1/2; beyond an
        opening's rim it continues the rim's faces by at most ``NEAR`` cells. Farther away the
        winding number says."""
        igl = self._igl
        S, *_ = igl.signed_distance(P, self.V, self.F, igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
        far = np.abs(S) > NEAR * self.h
        if far.any():
            w = igl.fast_winding_number(self.V, self.F, P[far])
            S[far] = np.where(w > 0.5, -np.abs(S[far]), np.abs(S[far]))
        return S

    def corners(self, cells, step=1):
        return self.values(self.key((cells[:, None, :] + _CORNERS[None] * step).reshape(-1, 3))).reshape(-1, 8)


def close_winding(tm: trimesh.Trimesh, cell: float) -> trimesh.Trimesh:
    """The solid where ``tm``'s generalized winding number exceeds 1/2, its surface contoured on
    cells of size ``cell`` (the module's docstring).

    Raises
    ------
    MeshError
        Nothing of the input encloses a volume at this cell size.
    """
    import igl

    V = np.ascontiguousarray(tm.vertices, np.float64)
    F = np.ascontiguousarray(tm.faces, np.int64)
    need = 2.0 * tm.area / cell ** 2  # about the cells the contour passes through
    if need > MAX_CELLS:
        raise MeshError(f"a {cell:.3g} grid over this surface needs about {need:.3g} cells (at most {MAX_CELLS:.0e})")
    ext = np.ptp(V, axis=0) + 4 * cell
    levels = 0
    while np.prod(np.ceil(ext / (cell * 2 ** levels)) + 1) > COARSE_NODES:
        levels += 1
    top = np.ceil(ext / (cell * 2 ** levels)).astype(np.int64)
    g = _Grid(V, F, cell, top * 2 ** levels + 1)
    step = 2 ** levels
    cells = np.stack(np.meshgrid(*[np.arange(c) for c in top], indexing="ij"), -1).reshape(-1, 3) * step
    while True:
        S = g.corners(cells, step)
        change = (S.min(1) < 0) & (S.max(1) >= 0)
        if step == 1:
            cells = cells[change]
            break
        # a cell the surface passes through has every corner within its diagonal of the surface
        # and one within half of it; a sign change without that is where the winding number
        # closes an opening, away from the input
        diag = step * cell * np.sqrt(3.0)
        A = np.abs(S)
        keep = ((A.max(1) <= diag) & (A.min(1) <= diag / 2)) | change
        step //= 2
        cells = (cells[keep][:, None, :] + _CORNERS[None] * step).reshape(-1, 3)
    cells = _closed_set(g, cells)
    if not len(cells):
        raise MeshError("the input encloses no volume its winding number can find (a flat patch or a few loose pieces)")
    corner = g.key((cells[:, None, :] + _CORNERS[None]).reshape(-1, 3))
    u, inv = np.unique(corner, return_inverse=True)
    Vm, Fm, _ = igl.marching_cubes(g.values(u), g.point(u), inv.reshape(-1, 8).astype(np.int64), 0.0)
    out = trimesh.Trimesh(Vm, Fm, process=False)
    out.merge_vertices(digits_vertex=int(np.ceil(-np.log10(1e-9 * cell))))
    # marching cubes leaves specks where a single node changes sign; a cell's volume is the least kept
    shells = [s for s in out.split(only_watertight=False) if abs(s.volume) > cell ** 3]
    if not shells:
        raise MeshError("the input encloses no volume its winding number can find (a flat patch or a few loose pieces)")
    return trimesh.util.concatenate(shells)


def _decimate(out: trimesh.Trimesh, faces: int) -> trimesh.Trimesh | None:
    """The contour simplified to about ``faces`` faces by quadric edge collapses
    (``fast_simplification``), or ``None`` when it has fewer already or the result is not closed."""
    import fast_simplification

    if len(out.faces) <= faces:
        return None
    V, F = fast_simplification.simplify(np.asarray(out.vertices, np.float64), np.asarray(out.faces, np.int32),
                                        target_count=int(faces), agg=DECIMATE_AGGRESSION)
    small = trimesh.Trimesh(V, F, process=False)
    small.remove_unreferenced_vertices()
    return small if small.is_watertight and small.is_winding_consistent and small.volume > 0 else None


def _closed_set(g: _Grid, cells: np.ndarray) -> np.ndarray:
    """``cells`` grown until every face with a sign change among its corners has its cells on both
    sides (a sign change missed on a coarser level would leave the contour open there)."""
    have = set(g.key(cells).tolist())
    todo = cells
    while len(todo):
        S = g.corners(todo)
        add = []
        for corners, d in _FACES:
            f = S[:, corners]
            cross = (f.min(1) < 0) & (f.max(1) >= 0)
            nb = todo[cross] + np.asarray(d)
            nb = nb[(nb >= 0).all(1) & (nb < g.n - 1).all(1)]
            add.append(nb)
        nb = np.unique(np.concatenate(add), axis=0) if add else np.empty((0, 3), np.int64)
        k = g.key(nb)
        fresh = np.array([x not in have for x in k.tolist()], bool) if len(k) else np.zeros(0, bool)
        todo = nb[fresh]
        have.update(k[fresh].tolist())
        cells = np.concatenate([cells, todo])
    return cells


def _outer(tm: trimesh.Trimesh, offset: float) -> np.ndarray:
    """Input vertices on the solid's outer surface: the input's own winding number just outside
    them (``offset`` along the vertex normal) is below 1/2. The others lie inside the input's
    solid (a tooth's root inside bone where the segmentation overlaps them), which any closing
    covers."""
    import igl

    V = np.ascontiguousarray(tm.vertices, np.float64)
    F = np.ascontiguousarray(tm.faces, np.int64)
    return igl.fast_winding_number(V, F, V + offset * np.asarray(tm.vertex_normals)) < 0.5


def _measure(tm, out, method, pieces, boundary, max_deviation, left_out=None) -> Closure:
    """The deviation of ``tm``'s outer vertices from ``out`` (but those only on ``left_out``
    faces) and the faces ``out`` adds."""
    from .bvh import BVH

    tol = 1e-5 * float(np.linalg.norm(np.ptp(tm.vertices, axis=0)))
    Vo, Fo = np.asarray(out.vertices, np.float64), np.asarray(out.faces, np.int64)
    Vi, Fi = np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64)
    dev = BVH.of_triangles(Vo, Fo).distance(Vi, Vo, Fo)
    outer = _outer(tm, max_deviation / 4)
    counted = outer.copy()
    lost = np.zeros(len(Vi), bool)
    if left_out is not None and left_out.any():
        lost[Fi[left_out].ravel()] = True
        lost[Fi[~left_out].ravel()] = False
    counted &= ~lost
    if not counted.any():
        counted = ~lost
    # a face is added where its centre lies off the input by more than the closing's own rounding
    rounding = max_deviation / 2 if method == "winding" else tol
    off = BVH.of_triangles(Vi, Fi).distance(out.triangles_center, Vi, Fi) > max(tol, rounding)
    area = out.area_faces[off]
    centre = (out.triangles_center[off] * area[:, None]).sum(0) / area.sum() if off.any() else np.zeros(3)
    extent = np.ptp(out.triangles_center[off], axis=0) if off.any() else np.zeros(3)
    n_left = 0 if left_out is None else int(len(np.unique(trimesh.graph.connected_component_labels(
        tm.face_adjacency, node_count=len(Fi))[left_out])))
    return Closure(method, pieces, boundary, float(dev[counted].max()) if counted.any() else 0.0,
                   float(dev[counted].mean()) if counted.any() else 0.0, float(max_deviation),
                   float((dev < tol).mean()), float(area.sum()), centre, extent, n_left,
                   float(tm.area_faces[left_out].sum()) if n_left else 0.0,
                   float(dev[lost].max()) if lost.any() else 0.0, int((~outer).sum()))


def close_surface(tm: trimesh.Trimesh, max_deviation: float | None = None,
                  method: str = "auto") -> tuple[trimesh.Trimesh, Closure]:
    """The open surface ``tm`` closed into a solid, with a report of what that moved and added.

    Parameters
    ----------
    tm : trimesh.Trimesh
        The open surface, any number of pieces.
    max_deviation : float, optional
        The largest distance an input vertex may end up from the closed surface, in the mesh's
        units (default ``MAX_DEVIATION_RELATIVE`` of its largest extent).
    method : {"auto", "meshfix", "winding"}
        "auto" takes MeshFix's closing when it is within ``max_deviation``, else the winding
        number's.

    Raises
    ------
    MeshError
        No method closes the surface within ``max_deviation``; the message gives each method's
        deviation and what to try.
    """
    if method not in METHODS:
        raise ValueError(f"method={method!r}: use one of {', '.join(METHODS)}")
    size = float(np.ptp(tm.vertices, axis=0).max())
    if max_deviation is None:
        max_deviation = MAX_DEVIATION_RELATIVE * size
    if not max_deviation > 0:
        raise ValueError(f"max_deviation={max_deviation!r}: pass a positive length in the mesh's units")
    _, counts = _edges(tm)
    boundary = int((counts == 1).sum())
    pieces = len(tm.split(only_watertight=False))
    tried = []
    for how in (("meshfix", "winding") if method == "auto" else (method,)):
        try:
            if how == "meshfix":
                out, left_out = close_meshfix(tm)
                if tm.area_faces[left_out].sum() > LEFT_OUT_AREA * tm.area:
                    tried.append(f"meshfix: could not close {100 * tm.area_faces[left_out].sum() / tm.area:.1f}% of the "
                                 "surface's area")
                    continue
                mismatch = _solid_mismatch(tm, out)
                if method == "auto" and mismatch > SOLID_MISMATCH:
                    tried.append(f"meshfix: its solid differs from the input's winding number by {100 * mismatch:.0f}% of "
                                 "the volume (pieces of one surface closed on their own)")
                    continue
            else:
                out, left_out = close_winding(tm, WINDING_CELL * max_deviation), None
        except MeshError as exc:
            tried.append(f"{how}: {exc}")
            continue
        if how == "winding":
            for times in DECIMATE_FACES:  # the fewest faces that stay closed and within the deviation
                small = _decimate(out, max(times * len(tm.faces), 1000))
                if small is not None:
                    small_report = _measure(tm, small, how, pieces, boundary, max_deviation, left_out)
                    if small_report.hausdorff <= max_deviation:
                        return small, small_report
        report = _measure(tm, out, how, pieces, boundary, max_deviation, left_out)
        if report.hausdorff <= max_deviation:
            return out, report
        tried.append(f"{how}: moved the input by up to {report.hausdorff:.3g} (mean {report.mean_deviation:.3g})")
    raise MeshError(
        f"could not close the open surface ({boundary} open edges, {pieces} piece(s)) within {max_deviation:.3g} of the "
        f"input ({'; '.join(tried)}): allow more (max_deviation, --max-deviation), remove loose fragments and "
        "self-intersections, or close it in a mesh editor")
