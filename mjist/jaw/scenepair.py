"""A jaw pair as an occlusion-search scene holds it, resolved once.

``resolve`` reads from a loaded scene everything the search, the ranking and the contact map
need — both meshes in their geom frames, the maxilla's pose, where the mandible's geom sits in
its body, the reference occlusion (the ``occlusion`` keyframe), the hinge, both arches'
frames and the meshes packed for exact distances — so no later step reads the model again.
World frame: +z up (from the mandible towards the maxilla), as the scenes write it.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry.surface import build_surface
from ..mujoco.scene import geom_pose, geom_pose_at, mesh_of
from .arch import arch_frame, occlusal_points

UP = np.array([0.0, 0.0, 1.0])  # world: from the mandible towards the maxilla (the jaw frame's +y)
JAW_TO_WORLD = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # jaw frame (x left, y up, z anterior) -> world
HINGE_AXIS = np.array([1.0, 0.0, 0.0])  # world; a positive turn about it opens the mandible


def file_maps(meta: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """``A_x`` (maxilla file -> world) and ``A_d`` (mandible file -> world at the reference
    occlusion) from a scene's ``pair.json``, and the maxilla file's metres per unit."""
    o = meta["orientation"]
    R = np.asarray(o["rotation"], float)
    sx, sd = (float(s) for s in o["scales"])
    Sx, Sd, W = np.eye(4), np.eye(4), np.eye(4)
    Sx[:3, :3], Sd[:3, :3], W[:3, :3] = sx * R, sd * R, JAW_TO_WORLD
    return W @ Sx, W @ np.asarray(meta["mandible_pose"], float) @ Sd, sx


def apply_pose(T, V) -> np.ndarray:
    """The points ``V (n, 3)`` moved by the 4x4 pose ``T``."""
    return np.asarray(V, float) @ T[:3, :3].T + T[:3, 3]


def file_transform(meta: dict, pose, reference) -> np.ndarray:
    """The mandible file's pose in the maxilla file's frame and units (4x4) when the mandible geom
    stands at the world pose ``pose`` instead of its ``reference`` (``pair.json`` as ``meta``)."""
    A_x, A_d, sx = file_maps(meta)
    M = np.linalg.inv(A_x) @ np.asarray(pose, float) @ np.linalg.inv(np.asarray(reference, float)) @ A_d
    return M


@dataclass
class ScenePair:
    """The jaw pair of an occlusion scene: meshes (geom frames), poses (world 4x4), frames, hinge."""

    model: object
    handle: object
    maxilla_geom: int
    mandible_geom: int
    maxilla: tuple  # (V, F) in the maxilla geom's frame
    mandible: tuple  # (V, F) in the mandible geom's frame
    maxilla_pose: np.ndarray
    geom_in_body: np.ndarray  # the mandible geom's pose in its body frame
    reference_pos: np.ndarray  # mandible body at the reference occlusion
    reference_quat: np.ndarray  # w, x, y, z
    hinge: np.ndarray  # world centre of the condylar axis
    frames: dict  # "maxilla", "mandible": arch.ArchFrame (world, at the reference)
    surfaces: tuple  # (Surface, Surface): the meshes packed for exact distances
    sample: object = None  # ranking.OcclusalSample: the occlusal points the ranking measures

    def pose(self, pos, quat) -> np.ndarray:
        """World pose of the mandible geom when its body stands at ``pos``, ``quat`` (w first)."""
        B = np.eye(4)
        B[:3, :3] = Rotation.from_quat(np.asarray(quat, float)[[1, 2, 3, 0]]).as_matrix()
        B[:3, 3] = pos
        return B @ self.geom_in_body

    def body(self, P) -> tuple[np.ndarray, np.ndarray]:
        """Mandible body ``(pos, quat)`` (w first) whose geom stands at the world pose ``P``."""
        B = np.asarray(P, float) @ np.linalg.inv(self.geom_in_body)
        x, y, z, w = Rotation.from_matrix(B[:3, :3]).as_quat()
        q = np.array([w, x, y, z])
        return B[:3, 3].copy(), q if w >= 0 else -q

    @property
    def reference(self) -> np.ndarray:
        """World pose of the mandible geom at the reference occlusion."""
        return self.pose(self.reference_pos, self.reference_quat)


def reference_pose(model):
    """The mandible body at the scene's ``occlusion`` keyframe and the hinge site (world)."""
    from .scenes import reference_pose as ref

    pos, quat, _, hinge, _ = ref(model)
    return pos, quat, hinge


def frames_at(maxilla, mandible, maxilla_pose, mandible_pose) -> dict:
    """Both arches' frames (world) with the mandible geom at ``mandible_pose`` (``arch.arch_frame``)."""
    (Vx, Fx), (Vd, Fd) = maxilla, mandible
    Wx = Vx @ maxilla_pose[:3, :3].T + maxilla_pose[:3, 3]
    Wd = Vd @ mandible_pose[:3, :3].T + mandible_pose[:3, 3]
    return {"maxilla": arch_frame(occlusal_points(Wx, Wd, Fd, up=UP), UP),
            "mandible": arch_frame(occlusal_points(Wd, Wx, Fx, up=UP), UP)}


def arch_frames(model, gmx, gmd) -> dict:
    """Both arches' frames (world) at a scene's reference occlusion."""
    pos, quat, _ = reference_pose(model)
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    return frames_at(mesh_of(model, gmx), mesh_of(model, gmd), geom_pose(d, gmx), geom_pose_at(model, gmd, pos, quat))


def resolve(model, handle) -> ScenePair:
    """The pair of an occlusion scene loaded with ``mjist.load_model`` (geoms named maxilla, mandible)."""
    gmx, gmd = handle.geoms["maxilla"], handle.geoms["mandible"]
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    Px = geom_pose(d, gmx)
    pos, quat, hinge = reference_pose(model)
    G = np.eye(4)
    G[:3, :3] = Rotation.from_quat(model.geom_quat[gmd][[1, 2, 3, 0]]).as_matrix()
    G[:3, 3] = model.geom_pos[gmd]
    mx, md = mesh_of(model, gmx), mesh_of(model, gmd)
    pair = ScenePair(model, handle, gmx, gmd, mx, md, Px, G, pos, quat, hinge, {},
                     (build_surface(*mx), build_surface(*md)))
    pair.frames = frames_at(mx, md, Px, pair.reference)
    return pair

