"""mjist: Inner Sphere Tree collision detection for MuJoCo.

Build: ``tree = mjist.build("jaw.stl", max_error=5e-5)`` fills a closed mesh with
non-overlapping inner spheres, wraps them in a Batch-Neural-Gas hierarchy and certifies
the error bound ε (every surface point lies within ε of a sphere).
"""
from .build import build
from .errors import MeshError, TreeFileError
from .mesh import Mesh, load_mesh
from .tree import FORMAT_VERSION, InnerSphereTree, load_tree

__all__ = [
    "build",
    "load_tree",
    "load_mesh",
    "Mesh",
    "InnerSphereTree",
    "MeshError",
    "TreeFileError",
    "FORMAT_VERSION",
]
__version__ = "0.1.0"
