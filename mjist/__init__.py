"""mjist: Inner Sphere Tree collision detection for MuJoCo.

Build: ``tree = mjist.build("jaw.stl", max_error=5e-5)`` fills a closed mesh with
non-overlapping inner spheres, wraps them in a Batch-Neural-Gas hierarchy and certifies
the error bound ε (every surface point lies within ε of a sphere).

Query: ``q = mjist.Query(tree_a, tree_b)``; ``q.distance(pose_a, pose_b)``,
``q.contacts(...)``, ``q.penetration_volume(...)`` with 4x4 poses, each answer with its
error bound (true distance ∈ [distance - error_bound, distance]).

MuJoCo: ``model, handle = mjist.load_model("scene.xml")`` (or ``mjist.attach(model)``) makes
plain ``mujoco.mj_step`` use IST contacts for the model's mesh geom pairs.
"""
from . import jitcache

jitcache.check()  # before any kernel loads: a cache built from other sources is stale

from .builder.pipeline import build, sphere_tree  # noqa: E402
from .errors import ConfigError, MeshError, TreeFileError  # noqa: E402
from .geometry.mesh import Mesh, load_mesh  # noqa: E402
from .query.api import ContactResult, DistanceResult, PenetrationResult, Query  # noqa: E402
from .tree import FORMAT_VERSION, InnerSphereTree, load_tree  # noqa: E402

__all__ = [
    "attach",
    "load_model",
    "Handle",
    "ConfigError",
    "build",
    "sphere_tree",
    "Query",
    "DistanceResult",
    "ContactResult",
    "PenetrationResult",
    "load_tree",
    "load_mesh",
    "Mesh",
    "InnerSphereTree",
    "MeshError",
    "TreeFileError",
    "FORMAT_VERSION",
]
__version__ = "0.4.0"

_MUJOCO_NAMES = {"attach": "attach", "load_model": "attach", "Handle": "handle"}


def __getattr__(name):
    # the MuJoCo layer is imported on first use, so `mjist render`/`demo` can pick the GL
    # backend (MUJOCO_GL) before `import mujoco` reads it
    if name in _MUJOCO_NAMES:
        import importlib

        return getattr(importlib.import_module(f".mujoco.{_MUJOCO_NAMES[name]}", __name__), name)
    raise AttributeError(f"module 'mjist' has no attribute {name!r}")
