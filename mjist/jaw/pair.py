"""Jaw-pair helpers: the hinge, the touching pose and a scripted chewing motion.

Frame convention (the shared CBCT pair and the bundled jaws): metres, +y superior
(up), +z anterior (towards the incisors), x left-right. The maxilla is fixed (identity
pose); the mandible moves.
"""
from __future__ import annotations

import coal
import numpy as np

from . import BUNDLED

UP, ANTERIOR = 1, 2


def hinge_point(mandible_vertices) -> np.ndarray:
    """Centre of the two condyles: the highest points of the posterior quarter of the mandible.

    The mandible rotates about the left-right (x) axis through this point when it opens.
    """
    V = np.asarray(mandible_vertices, dtype=np.float64)
    z0, z1 = V[:, ANTERIOR].min(), V[:, ANTERIOR].max()
    post = V[V[:, ANTERIOR] < z0 + 0.25 * (z1 - z0)]
    top = post[post[:, UP] > post[:, UP].max() - 0.003]
    mid = 0.5 * (V[:, 0].min() + V[:, 0].max())
    left, right = top[top[:, 0] < mid], top[top[:, 0] >= mid]
    if len(left) == 0 or len(right) == 0:
        raise ValueError("no condyles found: is the mandible in metres with +y up and +z anterior?")
    return 0.5 * (left.mean(axis=0) + right.mean(axis=0))


def hinge_pose(theta, hinge, lateral=0.0, protrusion=0.0, vertical=0.0) -> np.ndarray:
    """Mandible pose: opening rotation ``theta`` (rad, positive opens) about the x axis through
    ``hinge``, then a translation (lateral x, vertical y, protrusion z)."""
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = np.asarray(hinge) - R @ np.asarray(hinge) + [lateral, vertical, protrusion]
    return P


def coal_bvh(vertices, faces) -> coal.BVHModelOBBRSS:
    """coal's OBBRSS BVH of a triangle mesh (the exact reference)."""
    b = coal.BVHModelOBBRSS()
    b.beginModel(len(faces), len(vertices))
    b.addVertices(np.ascontiguousarray(vertices, dtype=np.float64))
    b.addTriangles(np.ascontiguousarray(faces, dtype=np.int64))
    b.endModel()
    return b


def _tf(P):
    return coal.Transform3s(np.ascontiguousarray(P[:3, :3]), np.ascontiguousarray(P[:3, 3]))


def coal_distance(bvh_a, pose_a, bvh_b, pose_b) -> float:
    """Exact mesh distance (coal); ≤ 0 when the meshes intersect."""
    return coal.distance(bvh_a, _tf(pose_a), bvh_b, _tf(pose_b), coal.DistanceRequest(), coal.DistanceResult())


def coal_collides(bvh_a, pose_a, bvh_b, pose_b, tol: float | None = None) -> bool:
    """coal's collision test; ``tol`` sets its GJK tolerance (default 1e-6: meshes closer than
    about 1 µm count as touching)."""
    req = coal.CollisionRequest()
    if tol is not None:
        req.gjk_tolerance = tol
    res = coal.CollisionResult()
    coal.collide(bvh_a, _tf(pose_a), bvh_b, _tf(pose_b), req, res)
    return res.isCollision()


def touching_offset(bvh_maxilla, bvh_mandible, max_open=0.01, tol=1e-6) -> float:
    """Vertical mandible offset (m) at which the two meshes just touch, on the separated side.

    Bisection on coal's collision test within ``±max_open`` of the stored pose.
    """
    I = np.eye(4)
    P = np.eye(4)

    def hit(y):
        P[UP, 3] = y
        return coal_collides(bvh_maxilla, I, bvh_mandible, P)

    a, b = (0.0, -max_open) if hit(0.0) else (max_open, 0.0)  # a collides, b is separated
    if not hit(a) or hit(b):
        raise ValueError(f"the jaws do not go from contact to separation within {max_open} m along y")
    while abs(a - b) > tol:
        m = 0.5 * (a + b)
        if hit(m):
            a = m
        else:
            b = m
    return b


def chewing_motion(n, hinge, *, contact_offset=0.0, open_deg=8.0, excursion=0.003, protrusion=0.003,
                   guidance_deg=1.0) -> np.ndarray:
    """A smooth mandible motion (the paper's hand-recorded motion, scripted): ``(n, 4, 4)`` poses.

    Phases (fractions of ``n``): close from ``open_deg`` to contact (0-0.2), rest (0.2-0.25),
    lateral excursion right and left by ``excursion`` (0.25-0.45), protrusion by
    ``protrusion`` and back (0.45-0.65), re-open (0.65-1). During excursion and protrusion the
    jaw opens by up to ``guidance_deg`` as cusps and incisors guide it. ``contact_offset`` is
    the vertical offset that makes the closed jaws touch (see ``touching_offset``).
    """
    t = np.linspace(0.0, 1.0, n)
    op = np.radians(open_deg)
    theta = np.where(t < 0.2, op * 0.5 * (1 + np.cos(np.pi * np.clip(t / 0.2, 0, 1))), 0.0)
    theta = np.where(t > 0.65, op * 0.5 * (1 - np.cos(np.pi * np.clip((t - 0.65) / 0.35, 0, 1))), theta)
    x = np.where((t > 0.25) & (t < 0.45), excursion * np.sin(2 * np.pi * (t - 0.25) / 0.2), 0.0)
    z = np.where((t > 0.45) & (t < 0.65), protrusion * np.sin(np.pi * (t - 0.45) / 0.2), 0.0)
    guide = np.radians(guidance_deg) * (np.abs(x) / max(excursion, 1e-12) + z / max(protrusion, 1e-12))
    theta = theta + np.where(t <= 0.65, guide, 0.0)
    return np.stack([hinge_pose(a, hinge, lateral=b, protrusion=c, vertical=contact_offset) for a, b, c in zip(theta, x, z)])




def load_pair(folder=None):
    """A jaw pair and its occlusion: the bundled models (default) or any folder holding
    ``maxilla`` and ``mandible`` meshes (``.obj``/``.stl``/``.ply``), e.g. ``../shared/data/jaw``.

    Returns
    -------
    maxilla, mandible : mjist.Mesh
    info : dict
        ``mandible_pose`` (4x4, ground-truth occlusion: from ``occlusion.json`` when the folder
        has one, else the pose where coal says the meshes first touch, moving the mandible
        vertically from the stored pose) and ``hinge`` (condyle centre, for the opening axis).
    """
    import json
    from pathlib import Path

    from ..geometry.mesh import load_mesh

    folder = Path(folder) if folder is not None else BUNDLED
    paths = {}
    for name in ("maxilla", "mandible"):
        found = [folder / f"{name}{ext}" for ext in (".obj", ".stl", ".ply") if (folder / f"{name}{ext}").exists()]
        if not found:
            raise FileNotFoundError(f"no {name}.obj/.stl/.ply in {folder}: pass the folder of a jaw pair")
        paths[name] = found[0]
    mx = load_mesh(paths["maxilla"])
    md = load_mesh(paths["mandible"])
    meta = folder / "occlusion.json"
    if meta.exists():
        j = json.loads(meta.read_text())
        info = {"mandible_pose": np.array(j["mandible_pose"]), "hinge": np.array(j["hinge"]), "source": str(meta)}
    else:
        touch = touching_offset(coal_bvh(mx.vertices, mx.faces), coal_bvh(md.vertices, md.faces))
        P = np.eye(4)
        P[UP, 3] = touch
        info = {"mandible_pose": P, "hinge": hinge_point(md.vertices), "source": "coal first touch"}
    info["paths"] = {k: str(v) for k, v in paths.items()}
    return mx, md, info
