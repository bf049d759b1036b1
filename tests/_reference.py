"""Independent references for the jaw application's tests.

Everything here is computed with MuJoCo's own kinematics, coal's exact mesh distance, trimesh
and numpy, never with ``mjist``: a test judges what a command found (a pose, a map, a wafer) by
these figures, not by the figures the command reports about itself.
"""
from __future__ import annotations

import coal
import numpy as np
from scipy.spatial.transform import Rotation


def _bvh(V, F) -> coal.BVHModelOBBRSS:
    b = coal.BVHModelOBBRSS()
    b.beginModel(len(F), len(V))
    b.addVertices(np.ascontiguousarray(V, dtype=np.float64))
    b.addTriangles(np.ascontiguousarray(F, dtype=np.int64))
    b.endModel()
    return b


def exact_distance(a, b, offset=(0.0, 0.0, 0.0)) -> float:
    """coal's distance between meshes ``a`` and ``b`` (each ``(V, F)``, one frame), ``b`` moved by
    ``offset``; ≤ 0 when they intersect."""
    I, t = np.eye(3), np.asarray(offset, float)
    return coal.distance(_bvh(*a), coal.Transform3s(I, np.zeros(3)), _bvh(*b), coal.Transform3s(I, t),
                         coal.DistanceRequest(), coal.DistanceResult())


def point_distances(points, mesh) -> np.ndarray:
    """Exact unsigned distance from each point to the triangles of ``mesh`` ``(V, F)`` (coal, a
    point as a sphere of zero radius; trimesh's ``closest_point`` can miss the nearest triangle)."""
    b = _bvh(*mesh)
    I, dot = coal.Transform3s(np.eye(3), np.zeros(3)), coal.Sphere(1e-12)
    return np.array([coal.distance(dot, coal.Transform3s(np.eye(3), np.asarray(p, float)), b, I, coal.DistanceRequest(),
                                   coal.DistanceResult()) for p in np.asarray(points, float)])


def first_touch(a, b, up, reach: float, tol: float = 1e-7) -> float:
    """How far (along the unit ``up``, within ±``reach``) mesh ``b`` moves until it first
    touches ``a``: bisection on coal's exact distance (apart above, intersecting below)."""
    up = np.asarray(up, float)
    ba, bb = _bvh(*a), _bvh(*b)
    I = coal.Transform3s(np.eye(3), np.zeros(3))

    def gap(s):
        return coal.distance(ba, I, bb, coal.Transform3s(np.eye(3), s * up), coal.DistanceRequest(), coal.DistanceResult())

    lo, hi = -reach, reach  # b moved by lo is apart, by hi it overlaps
    if gap(lo) <= 0.0 or gap(hi) > 0.0:
        raise ValueError(f"the meshes do not go from apart to touching within ±{reach} along {up}")
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if gap(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return lo


def geom_world_vertices(model, qpos, geom: str) -> np.ndarray:
    """The world vertices of mesh geom ``geom`` at ``qpos`` (MuJoCo's own kinematics)."""
    import mujoco

    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(model, d)
    g = model.geom(geom)
    m = int(model.geom_dataid[g.id])
    V = model.mesh_vert[model.mesh_vertadr[m]:model.mesh_vertadr[m] + model.mesh_vertnum[m]].astype(float)
    return V @ d.geom_xmat[g.id].reshape(3, 3).T + d.geom_xpos[g.id]


def geom_faces(model, geom: str) -> np.ndarray:
    m = int(model.geom_dataid[model.geom(geom).id])
    return model.mesh_face[model.mesh_faceadr[m]:model.mesh_faceadr[m] + model.mesh_facenum[m]].astype(np.int64)


def near_vertices(V, other, reach: float, every: int = 1) -> np.ndarray:
    """Indices of the vertices ``V[::every]`` within ``reach`` of the surface ``other`` ``(V, F)``
    (coal's exact point distances), as indices into ``V``."""
    idx = np.arange(0, len(V), every)
    return idx[point_distances(np.asarray(V)[idx], other) < reach]


def largest_shift(A, B) -> float:
    """Largest distance between corresponding points of two copies ``A``, ``B`` ``(n, 3)``."""
    return float(np.linalg.norm(np.asarray(A) - np.asarray(B), axis=1).max())


def rotation_between_deg(A, B) -> float:
    """The angle (degrees) of the rotation taking point set ``B`` to ``A`` (Kabsch; rigid copies)."""
    a, b = np.asarray(A) - np.mean(A, axis=0), np.asarray(B) - np.mean(B, axis=0)
    U, _, Wt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Wt))])
    return float(np.degrees(Rotation.from_matrix((U @ D @ Wt).T).magnitude()))
