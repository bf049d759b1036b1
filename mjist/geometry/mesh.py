"""Load a triangle mesh and check it can be filled with inner spheres.

An Inner Sphere Tree needs a well-defined inside: the mesh must be closed (every edge
shared by exactly two faces), consistently wound with outward normals, finite and free of
degenerate faces. Several closed shells are fine (a maxilla has three, a dental arch of
separate teeth has sixteen).
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field

import numpy as np
import trimesh

from ..errors import MeshError


@dataclass
class Mesh:
    """A validated closed triangle mesh (float64 vertices, int64 faces)."""

    vertices: np.ndarray
    faces: np.ndarray
    volume: float
    area: float
    shells: int
    repairs: list = field(default_factory=list)
    closure: object = None  # geometry.repair.Closure when an open surface was closed

    @property
    def extents(self) -> np.ndarray:
        return self.vertices.max(axis=0) - self.vertices.min(axis=0)

    @property
    def content_hash(self) -> str:
        """SHA-256 of the vertex and face arrays (what a saved tree was built from)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.vertices, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.faces, dtype="<i8").tobytes())
        return h.hexdigest()

    def trimesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def _to_trimesh(mesh) -> trimesh.Trimesh:
    if isinstance(mesh, Mesh):
        return mesh.trimesh()
    if isinstance(mesh, trimesh.Trimesh):
        tm = mesh
    elif isinstance(mesh, (str, os.PathLike)):
        path = os.fspath(mesh)
        if not os.path.exists(path):
            raise MeshError(f"mesh file {path!r} does not exist: check the path")
        try:
            loaded = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types on unreadable files
            raise MeshError(
                f"could not read mesh file {path!r} ({type(exc).__name__}: {exc}); "
                "use a valid STL, OBJ or PLY file"
            ) from exc
        if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
            raise MeshError(f"mesh file {path!r} holds no triangles: export the surface as a triangle mesh")
        tm = loaded
    elif isinstance(mesh, tuple) and len(mesh) == 2:
        v = np.asarray(mesh[0], dtype=np.float64)
        f = np.asarray(mesh[1])
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise MeshError(
                f"(vertices, faces) must have shapes (n, 3) and (m, 3), got {v.shape} and {f.shape}"
            )
        if not np.issubdtype(f.dtype, np.integer):
            raise MeshError(f"faces must be integer vertex indices, got dtype {f.dtype}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise MeshError(
                f"faces index vertices outside 0..{len(v) - 1} (min {f.min()}, max {f.max()}): "
                "fix the face array"
            )
        tm = trimesh.Trimesh(v, f.astype(np.int64), process=False)
    else:
        raise MeshError(
            f"cannot use {type(mesh).__name__} as a mesh: pass a file path, a trimesh.Trimesh "
            "or a (vertices, faces) tuple"
        )
    return tm


def read_surface(mesh) -> trimesh.Trimesh:
    """``mesh`` (a path, a trimesh, ``(vertices, faces)`` or a ``Mesh``) as a trimesh, checked for
    emptiness and non-finite coordinates, coincident vertices merged; not yet validated as closed."""
    return _finite(_to_trimesh(mesh))


def _finite(tm) -> trimesh.Trimesh:
    """``tm`` checked for emptiness and non-finite coordinates, coincident vertices merged."""
    v = np.asarray(tm.vertices, dtype=np.float64)
    f = np.asarray(tm.faces, dtype=np.int64)
    if len(f) == 0 or len(v) == 0:
        raise MeshError("mesh is empty (no faces): pass a closed triangle surface")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise MeshError(
            f"mesh has {int(bad.sum())} vertices with NaN or infinite coordinates: "
            "fix the export or drop those vertices and their faces"
        )
    tm = trimesh.Trimesh(v, f, process=False)
    # geometric merge only (OBJ normals/uvs and STL soups split vertices)
    tm.merge_vertices(merge_tex=True, merge_norm=True, digits_vertex=_merge_digits(v))
    return tm


MERGE_RELATIVE = 1e-12  # vertices closer than this times the mesh size are one vertex (coincident copies)


def _merge_digits(V) -> int:
    """Decimal digits for merging coincident vertices: trimesh's default merges within 1e-8 in the
    file's units (10 nm in metres), which fuses two distinct vertices of a fine mesh in metres
    into zero-area faces; a tolerance relative to the mesh size keeps every distinct vertex and
    still joins the copies STL soups and OBJ normals make."""
    size = float(np.ptp(np.asarray(V, float), axis=0).max()) if len(V) else 1.0
    return int(np.clip(np.ceil(-np.log10(MERGE_RELATIVE * max(size, 1e-300))), 0, 300))


DEGENERATE = 1e-14  # a face whose doubled area is at most this times the mesh's size squared has zero area


def degenerate_faces(V, F, scale: float | None = None) -> np.ndarray:
    """Which faces have zero area: a repeated vertex, or a doubled area of at most ``DEGENERATE``
    times ``scale`` squared (default: the mesh's bounding-box diagonal)."""
    V, F = np.asarray(V, float), np.asarray(F)
    if scale is None:
        scale = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) if len(V) else 1.0
    tri = V[F]
    dbl_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    repeated = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    return repeated | (dbl_area <= DEGENERATE * scale * scale)


def _drop_degenerate(tm, scale: float, repair: bool, repairs: list) -> None:
    """Refuse zero-area faces, or remove them with ``repair``."""
    degenerate = degenerate_faces(tm.vertices, tm.faces, scale)
    if not degenerate.any():
        return
    if not repair:
        raise MeshError(
            f"mesh has {int(degenerate.sum())} degenerate (zero-area) faces: "
            "pass repair=True (or --repair) to remove them, or clean the mesh"
        )
    tm.update_faces(~degenerate)
    tm.remove_unreferenced_vertices()
    repairs.append(f"removed {int(degenerate.sum())} degenerate faces")
    tm.merge_vertices(merge_tex=True, merge_norm=True, digits_vertex=_merge_digits(tm.vertices))


def _edge_defects(tm) -> tuple[int, int]:
    """Boundary edges (one face) and non-manifold edges (more than two faces)."""
    _, counts = np.unique(np.sort(tm.edges, axis=1), axis=0, return_counts=True)
    return int((counts == 1).sum()), int((counts > 2).sum())


def _drop_internal_walls(tm, repairs: list) -> bool:
    """Remove the faces that closed shells share (a crown's base on the gingiva, teeth on bone):
    every face whose three vertices another face also uses, with that face. Such a wall lies
    inside the union of the shells, so the outer surface keeps every face it had; what is left
    is that surface, closed when the shells met only there. Returns whether any were removed."""
    key = np.sort(np.asarray(tm.faces), axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    shared = counts[inverse.ravel()] > 1
    if not shared.any():
        return False
    tm.update_faces(~shared)
    tm.remove_unreferenced_vertices()
    repairs.append(f"removed {int(shared.sum())} faces of internal walls where closed shells met (the outer surface keeps "
                   "every face)")
    return True


def _check_closed(tm, repair: bool, repairs: list, max_deviation=None):
    """Refuse an open or non-manifold surface, or close it (``geometry.repair``) when ``repair``,
    moving the input by at most ``max_deviation``. Returns the closed mesh and the closure report
    (``None`` when closed already)."""
    if tm.is_watertight:
        return tm, None
    if repair and _drop_internal_walls(tm, repairs) and tm.is_watertight:
        return tm, None
    if repair:
        from .repair import close_surface

        tm, closure = close_surface(tm, max_deviation)
        repairs.append(closure.describe())
        return tm, closure
    boundary, nonmanifold = _edge_defects(tm)
    what = []
    if boundary:
        what.append(f"{boundary} open (boundary) edges")
    if nonmanifold:
        what.append(f"{nonmanifold} non-manifold edges shared by more than two faces")
    raise MeshError(f"mesh is not closed: {', '.join(what)}. An inner sphere tree needs a watertight surface: "
                    "pass repair=True (--repair) to close it (MeshFix or the winding number; how far that moves the "
                    "surface and what it adds are reported), or close it in a mesh editor")


def _check_winding(tm, repair: bool, repairs: list) -> None:
    """Refuse inconsistent face winding, or make it consistent with ``repair``."""
    if tm.is_winding_consistent:
        return
    if not repair:
        raise MeshError(
            "mesh faces are not consistently wound (some normals point in, some out): "
            "pass repair=True to fix the winding"
        )
    trimesh.repair.fix_winding(tm)
    repairs.append("made face winding consistent")
    if not tm.is_winding_consistent:
        raise MeshError("could not make the face winding consistent: check the mesh for self-overlaps")


def _outward_volume(tm, scale: float, repair: bool, repairs: list) -> float:
    """The enclosed volume, refusing a flat surface and an inside-out one (flipped with ``repair``)."""
    volume = float(tm.volume)
    if abs(volume) <= 1e-12 * scale**3:
        raise MeshError("mesh encloses no volume (flat or collapsed): pass a solid, closed surface")
    if volume < 0:
        if not repair:
            raise MeshError(
                "mesh is inside out (faces wound so normals point inward, negative volume): "
                "pass repair=True to flip it, or invert the faces"
            )
        tm.invert()
        repairs.append("flipped inverted faces (normals now point outward)")
        volume = float(tm.volume)
    return volume


def load_mesh(mesh, *, repair: bool = False, max_deviation: float | None = None) -> Mesh:
    """Load and validate a closed triangle mesh.

    Parameters
    ----------
    mesh : str, path, trimesh.Trimesh, or (vertices, faces)
        The surface. Files are read with trimesh (STL, OBJ, PLY, ...). Coincident vertices
        are merged (STL and OBJ files with normals store them split); nothing else changes.
    repair : bool
        Drop degenerate faces, fix winding and inversion (trimesh), and close an open or
        many-piece surface (``geometry.repair.close_surface``: MeshFix, else the generalized
        winding number). What was changed is listed in ``Mesh.repairs`` (and ``Mesh.closure``:
        how far the input moved, the area added).
    max_deviation : float, optional
        With ``repair``: the farthest an input vertex may end up from the closed surface, in
        the mesh's units (default ``geometry.repair.MAX_DEVIATION_RELATIVE`` of its size).

    Raises
    ------
    MeshError
        Empty, non-finite, degenerate, open, non-manifold, inconsistently wound, inverted
        or zero-volume meshes; the message names the defect and the fix.
    """
    tm = read_surface(mesh)
    repairs: list[str] = []
    scale = float(np.linalg.norm(tm.vertices.max(0) - tm.vertices.min(0)))
    if scale == 0.0:
        raise MeshError("mesh is degenerate: all vertices coincide")
    _drop_degenerate(tm, scale, repair, repairs)
    tm, closure = _check_closed(tm, repair, repairs, max_deviation)
    _check_winding(tm, repair, repairs)
    volume = _outward_volume(tm, scale, repair, repairs)
    shells = len(trimesh.graph.connected_components(tm.face_adjacency, nodes=np.arange(len(tm.faces))))
    return Mesh(
        vertices=np.ascontiguousarray(tm.vertices, dtype=np.float64),
        faces=np.ascontiguousarray(tm.faces, dtype=np.int64),
        volume=volume,
        area=float(tm.area),
        shells=shells,
        repairs=repairs,
        closure=closure,
    )


def single_precision(V, F) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The mesh as a float32 reader (MuJoCo's compiler) will see it, cleaned of what that rounding
    makes: vertices that round to one float32 point become one vertex, and the zero-area faces
    this leaves are removed (each is a sliver between two such vertices, so the surface stays
    closed); a sliver whose three corners rounding puts on one line is flipped away
    (``_split_slivers``). Returns ``(V, F, faces removed, slivers flipped)``; ``V`` holds
    float32-exact coordinates.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    V32 = V.astype(np.float32)
    _, first, inverse = np.unique(V32, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    removed = 0
    if len(first) == len(V):
        W = V32.astype(np.float64)
    else:
        G = inverse[F]
        keep = (G[:, 0] != G[:, 1]) & (G[:, 1] != G[:, 2]) & (G[:, 0] != G[:, 2])
        W, F, removed = V32[first].astype(np.float64), G[keep], int((~keep).sum())
    F, flipped = _split_slivers(W, F)
    return W, F, removed, flipped


SLIVER_PASSES = 8  # rounds of flips at most (a flip can leave a new sliver where a neighbour is on the line too)


def _split_slivers(V, F) -> tuple[np.ndarray, int]:
    """Zero-area faces with three distinct corners on one line, flipped away: the face ``a b m``
    (``m`` on the edge ``a b``) goes, and the face across ``a b``, ``b a s``, becomes ``b m s``
    and ``m a s``. The surface stays closed and consistently wound, and keeps its face count.
    Returns the faces and the number of flips; slivers without a neighbour to flip with stay
    (the tree build names them)."""
    F = np.array(F, np.int64)
    nv = len(V)
    flips = 0
    for _ in range(SLIVER_PASSES):
        bad = np.flatnonzero(degenerate_faces(V, F))
        if bad.size == 0:
            break
        key = np.concatenate([F[:, 0] * nv + F[:, 1], F[:, 1] * nv + F[:, 2], F[:, 2] * nv + F[:, 0]])
        owner = np.tile(np.arange(len(F)), 3)
        order = np.argsort(key, kind="stable")
        key, owner = key[order], owner[order]
        used = np.zeros(len(F), bool)
        out = []
        for f in bad:
            c = F[f]
            if used[f] or len(set(c.tolist())) < 3:
                continue
            P = V[c]
            k = int(np.argmax([np.sum((P[(i + 1) % 3] - P[i]) ** 2) for i in range(3)]))  # the longest edge c[k] -> c[k+1]
            a, b, m = c[k], c[(k + 1) % 3], c[(k + 2) % 3]
            j = np.searchsorted(key, b * nv + a)
            if j >= len(key) or key[j] != b * nv + a or used[owner[j]]:
                continue
            g = owner[j]
            G = F[g]
            s = int(G[(list(G).index(a) + 1) % 3])  # g runs b -> a -> s
            used[f] = used[g] = True
            out.append((f, g, (b, m, s), (m, a, s)))
        if not out:
            break
        drop = np.zeros(len(F), bool)
        new = []
        for f, g, t1, t2 in out:
            drop[f] = drop[g] = True
            new += [t1, t2]
        F = np.concatenate([F[~drop], np.array(new, np.int64)])
        flips += len(out)
    return F, flips
