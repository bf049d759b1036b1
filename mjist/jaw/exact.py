"""The exact reference for a jaw pair: coal's BVH distance and collision on the meshes."""
from __future__ import annotations

import coal
import numpy as np


def coal_bvh(vertices, faces) -> coal.BVHModelOBBRSS:
    """coal's OBBRSS BVH of a triangle mesh (the exact reference)."""
    b = coal.BVHModelOBBRSS()
    b.beginModel(len(faces), len(vertices))
    b.addVertices(np.ascontiguousarray(vertices, dtype=np.float64))
    b.addTriangles(np.ascontiguousarray(faces, dtype=np.int64))
    b.endModel()
    return b


def coal_transform(P) -> coal.Transform3s:
    """A 4x4 pose as coal's transform."""
    return coal.Transform3s(np.ascontiguousarray(P[:3, :3]), np.ascontiguousarray(P[:3, 3]))


def coal_distance(bvh_a, pose_a, bvh_b, pose_b) -> float:
    """Exact mesh distance (coal); ≤ 0 when the meshes intersect."""
    return coal.distance(bvh_a, coal_transform(pose_a), bvh_b, coal_transform(pose_b), coal.DistanceRequest(), coal.DistanceResult())


def coal_collides(bvh_a, pose_a, bvh_b, pose_b, tol: float | None = None) -> bool:
    """coal's collision test; ``tol`` sets its GJK tolerance (default 1e-6: meshes closer than
    about 1 µm count as touching)."""
    req = coal.CollisionRequest()
    if tol is not None:
        req.gjk_tolerance = tol
    res = coal.CollisionResult()
    coal.collide(bvh_a, coal_transform(pose_a), bvh_b, coal_transform(pose_b), req, res)
    return res.isCollision()


def coal_depth(bvh_a, pose_a, bvh_b, pose_b) -> float:
    """coal's deepest triangle-pair penetration of two meshes at their poses (0 when they do
    not touch): the exact reference for a contact's depth."""
    req = coal.CollisionRequest()
    req.enable_contact = True
    req.num_max_contacts = 1 << 20
    res = coal.CollisionResult()
    coal.collide(bvh_a, coal_transform(pose_a), bvh_b, coal_transform(pose_b), req, res)
    return max([0.0] + [-c.penetration_depth for c in res.getContacts()])


def near_faces(a, b, move: float) -> tuple[np.ndarray, np.ndarray]:
    """Which faces of meshes ``a`` and ``b`` (each ``(V, F)``, one frame) can meet while one moves
    by at most ``move`` (m, any point): those within ``move`` of the other mesh, plus their own
    size. coal's collision test on two surfaces that lie close over a large area (arches in
    occlusion) costs seconds at 300 k vertices; on these faces alone it costs milliseconds,
    with the same answer for every pose within that move."""
    from ..geometry.bvh import BVH

    keep = []
    for (W, F), (Wo, Fo) in ((a, b), (b, a)):
        W, Wo = np.asarray(W, float), np.asarray(Wo, float)
        C = W[F].mean(axis=1)
        size = np.linalg.norm(W[F] - C[:, None, :], axis=2).max(axis=1)
        d = BVH.of_triangles(Wo, Fo).distance(C, Wo, Fo, within=move + float(size.max()))
        keep.append(d <= move + size)
    return keep[0], keep[1]
