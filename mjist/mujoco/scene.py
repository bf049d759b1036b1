"""What a MuJoCo model holds for the IST: which geoms it manages, which pairs can meet, their meshes and poses."""
from __future__ import annotations

import warnings

import mujoco
import numpy as np

from ..errors import ConfigError
from ..query import primitive as cp
from . import abi
from .config import Config


def _is_ist_geom(model, g: int) -> bool:
    """A geom the IST can stand in for: a mesh, or an sdf geom with a mesh (a plugin's too)."""
    t = model.geom_type[g]
    return t == abi.GEOM_MESH or (t == abi.GEOM_SDF and model.geom_dataid[g] >= 0)


def _is_plugin_sdf(model, g: int) -> bool:
    """An sdf geom whose distance a plugin computes (e.g. ``mujoco.sdf.torus``): exact already."""
    return model.geom_type[g] == abi.GEOM_SDF and model.geom_plugin[g] >= 0


def geom_name(model, g: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom #{g}"


def managed_geoms(model, cfg: Config) -> list[int]:
    """Geom ids the configuration asks for (validated).

    ``"all"`` is every mesh geom and every mesh-backed sdf geom except those of an SDF plugin:
    a plugin's signed distance is exact, and its mesh is only what the viewer draws, so those
    keep MuJoCo's own collision unless ``mjist_geoms`` names them.
    """
    if cfg.geoms == "all":
        return [g for g in range(model.ngeom) if _is_ist_geom(model, g) and not _is_plugin_sdf(model, g)]
    out = []
    for name in cfg.geoms:
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if g < 0:
            raise ConfigError(f"mjist_geoms names {name!r}, which is not a geom of this model: check the name or use 'all'")
        if not _is_ist_geom(model, g):
            raise ConfigError(
                f"mjist_geoms names {name!r}, a {mujoco.mjtGeom(model.geom_type[g]).name} geom: only mesh geoms "
                "(type='mesh', or type='sdf' with a mesh) can get an Inner Sphere Tree"
            )
        out.append(g)
    return out


def can_collide(model, g1: int, g2: int) -> bool:
    """Whether MuJoCo's broad phase can ever pass the pair ``(g1, g2)`` to the narrow phase."""
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return False
    for i in range(model.npair):
        if {model.pair_geom1[i], model.pair_geom2[i]} == {g1, g2}:
            return True
    b1, b2 = model.geom_bodyid[g1], model.geom_bodyid[g2]
    w1, w2 = model.body_weldid[b1], model.body_weldid[b2]
    if w1 == w2:
        return False  # same rigid body (or both static)
    if not (model.geom_contype[g1] & model.geom_conaffinity[g2] or model.geom_contype[g2] & model.geom_conaffinity[g1]):
        return False
    if not (model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT):
        p1, p2 = model.body_weldid[model.body_parentid[w1]], model.body_weldid[model.body_parentid[w2]]
        if w1 != 0 and w2 != 0 and (p1 == w2 or p2 == w1):
            return False
    sig = (min(b1, b2) << 16) + max(b1, b2)
    return sig not in set(int(s) for s in model.exclude_signature)


def mesh_of(model, g: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of geom ``g``'s mesh in the geom frame (as MuJoCo compiled them)."""
    mid = model.geom_dataid[g]
    va, vn = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
    fa, fn = model.mesh_faceadr[mid], model.mesh_facenum[mid]
    V = np.array(model.mesh_vert[va:va + vn], dtype=np.float64)
    F = np.array(model.mesh_face[fa:fa + fn], dtype=np.int64)
    return V, F


def geom_pose(data, g: int) -> np.ndarray:
    """4x4 world pose of geom ``g`` in ``data`` (after ``mj_forward``/``mj_step``)."""
    P = np.eye(4)
    P[:3, :3] = data.geom_xmat[g].reshape(3, 3)
    P[:3, 3] = data.geom_xpos[g]
    return P


def geom_pose_at(model, g: int, body_pos, body_quat) -> np.ndarray:
    """4x4 world pose of geom ``g`` when its body stands at ``body_pos``, ``body_quat`` (w first),
    e.g. a body pose logged during a run."""
    from scipy.spatial.transform import Rotation

    Rb = Rotation.from_quat(np.asarray(body_quat)[[1, 2, 3, 0]])
    Rg = Rotation.from_quat(model.geom_quat[g][[1, 2, 3, 0]])
    P = np.eye(4)
    P[:3, :3] = (Rb * Rg).as_matrix()
    P[:3, 3] = np.asarray(body_pos) + Rb.apply(model.geom_pos[g])
    return P


def warn_primitive_pairs(model, wanted: list[int], ist: bool) -> None:
    """Say which IST geom ↔ primitive pairs keep MuJoCo's convex-hull contacts."""
    prim = (abi.GEOM_SPHERE, abi.GEOM_CAPSULE, abi.GEOM_BOX, int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_ELLIPSOID))
    hits = []
    for a in wanted:
        for b in range(model.ngeom):
            t = model.geom_type[b]
            if t not in prim or not can_collide(model, a, b):
                continue
            if ist and t in cp.TYPES and model.geom_type[a] == abi.GEOM_MESH:
                continue  # answered by the leaf spheres
            hits.append(f"{geom_name(model, a)} ↔ {geom_name(model, b)}")
    if hits:
        why = ("ellipsoids and sdf-type geoms keep MuJoCo's native contacts" if ist
               else "mjist_primitives='native'")
        warnings.warn(
            f"these pairs use MuJoCo's native contacts, which treat the mesh as its convex hull ({why}; exact only "
            "where the primitive meets the hull's surface; planes and height fields are exact): " + ", ".join(hits[:8])
            + (" ..." if len(hits) > 8 else ""), RuntimeWarning, stacklevel=3)
