"""The Inner Sphere Tree container, flat structure of arrays, and its file format."""
from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field

import numpy as np

from .errors import TreeFileError

FORMAT_VERSION = 1
_ARRAYS = (
    "centers", "radii", "child_start", "child_count", "parent", "depth",
    "leaf_start", "leaf_end", "leaf_centers", "leaf_radii", "leaf_node",
)


@dataclass
class InnerSphereTree:
    """An Inner Sphere Tree: non-overlapping leaf spheres inside a mesh, wrapped by a hierarchy.

    Nodes are numbered breadth first (node 0 is the root); node ``i``'s children are
    ``child_start[i] : child_start[i] + child_count[i]`` and its leaves are
    ``leaf_start[i] : leaf_end[i]`` of ``leaf_centers``/``leaf_radii``. Every node sphere
    encloses the leaf spheres below it. Leaf nodes have ``child_count == 0``.

    ``error_bound`` (ε) is a certified upper bound of the distance from any point of the
    mesh surface to the union of the leaf spheres, in mesh units (see ``mjist.bound``).
    """

    centers: np.ndarray
    radii: np.ndarray
    child_start: np.ndarray
    child_count: np.ndarray
    parent: np.ndarray
    depth_of: np.ndarray
    leaf_start: np.ndarray
    leaf_end: np.ndarray
    leaf_centers: np.ndarray
    leaf_radii: np.ndarray
    leaf_node: np.ndarray
    error_bound: float
    error_lower: float
    mesh_volume: float
    mesh_hash: str
    params: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @property
    def num_leaves(self) -> int:
        return int(self.leaf_radii.shape[0])

    @property
    def num_nodes(self) -> int:
        return int(self.radii.shape[0])

    @property
    def depth(self) -> int:
        """Depth of the deepest leaf (the root has depth 0)."""
        return int(self.depth_of.max()) if self.num_nodes else 0

    @property
    def coverage(self) -> float:
        """Leaf sphere volume over mesh volume (leaves do not overlap, so this is the union's)."""
        return float((4.0 / 3.0) * np.pi * np.sum(self.leaf_radii**3) / self.mesh_volume)

    def stats(self) -> dict:
        """Summary figures: leaves, nodes, depth, ε and its lower bound, coverage, timings."""
        return {
            "leaves": self.num_leaves,
            "nodes": self.num_nodes,
            "depth": self.depth,
            "error_bound": self.error_bound,
            "error_lower": self.error_lower,
            "coverage": self.coverage,
            "min_leaf_radius": float(self.leaf_radii.min()),
            "max_leaf_radius": float(self.leaf_radii.max()),
            "root_radius": float(self.radii[0]),
            "params": dict(self.params),
            "timings": dict(self.timings),
            **{k: v for k, v in self.info.items()},
        }

    def save(self, path) -> str:
        """Write the tree to ``path`` (``.npz``: arrays plus a JSON header with format version)."""
        path = os.fspath(path)
        meta = {
            "format": "mjist-ist",
            "format_version": FORMAT_VERSION,
            "error_bound": self.error_bound,
            "error_lower": self.error_lower,
            "mesh_volume": self.mesh_volume,
            "mesh_hash": self.mesh_hash,
            "params": self.params,
            "timings": self.timings,
            "info": self.info,
        }
        arrays = {name: getattr(self, "depth_of" if name == "depth" else name) for name in _ARRAYS}
        tmp = f"{path}.{os.getpid()}.tmp"  # per process: two workers may store the same cached tree
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, meta=np.array(json.dumps(meta)), **arrays)
        os.replace(tmp, path)  # atomic: a crash never leaves a half-written tree
        return path


def load_tree(path, *, expect_hash: str | None = None) -> InnerSphereTree:
    """Load a tree written by ``InnerSphereTree.save``.

    Raises
    ------
    TreeFileError
        Missing, unreadable or corrupt file, another format version, inconsistent arrays,
        or (with ``expect_hash``) a tree built from a different mesh.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise TreeFileError(f"tree file {path!r} does not exist: build it with mjist.build(...).save(path)")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {name: np.array(z[name]) for name in _ARRAYS}
    except (zipfile.BadZipFile, KeyError, ValueError, OSError, EOFError, json.JSONDecodeError) as exc:
        raise TreeFileError(
            f"tree file {path!r} is corrupt or not an mjist tree ({type(exc).__name__}: {exc}): "
            "delete it and rebuild"
        ) from exc
    if meta.get("format") != "mjist-ist":
        raise TreeFileError(f"{path!r} is not an mjist tree file: rebuild it with mjist.build")
    ver = meta.get("format_version")
    if ver != FORMAT_VERSION:
        raise TreeFileError(
            f"tree file {path!r} has format version {ver}, this mjist reads version {FORMAT_VERSION}: rebuild it"
        )
    n_nodes = arrays["radii"].shape[0]
    n_leaves = arrays["leaf_radii"].shape[0]
    ok = (
        n_nodes > 0
        and n_leaves > 0
        and arrays["centers"].shape == (n_nodes, 3)
        and arrays["leaf_centers"].shape == (n_leaves, 3)
        and all(arrays[k].shape == (n_nodes,) for k in ("child_start", "child_count", "parent", "depth", "leaf_start", "leaf_end"))
        and arrays["leaf_node"].shape == (n_leaves,)
        and np.isfinite(arrays["centers"]).all()
        and np.isfinite(arrays["radii"]).all()
        and np.isfinite(arrays["leaf_centers"]).all()
        and (arrays["leaf_radii"] > 0).all()
        and int(arrays["leaf_end"].max()) <= n_leaves
        and int((arrays["child_start"] + arrays["child_count"]).max()) <= n_nodes
        and int(arrays["leaf_node"].max()) < n_nodes
    )
    if not ok:
        raise TreeFileError(f"tree file {path!r} has inconsistent arrays (corrupt): delete it and rebuild")
    if expect_hash is not None and meta.get("mesh_hash") != expect_hash:
        raise TreeFileError(
            f"tree file {path!r} was built from another mesh (content hash differs): rebuild it"
        )
    return InnerSphereTree(
        centers=arrays["centers"].astype(np.float64),
        radii=arrays["radii"].astype(np.float64),
        child_start=arrays["child_start"].astype(np.int64),
        child_count=arrays["child_count"].astype(np.int64),
        parent=arrays["parent"].astype(np.int64),
        depth_of=arrays["depth"].astype(np.int64),
        leaf_start=arrays["leaf_start"].astype(np.int64),
        leaf_end=arrays["leaf_end"].astype(np.int64),
        leaf_centers=arrays["leaf_centers"].astype(np.float64),
        leaf_radii=arrays["leaf_radii"].astype(np.float64),
        leaf_node=arrays["leaf_node"].astype(np.int64),
        error_bound=float(meta["error_bound"]),
        error_lower=float(meta.get("error_lower", 0.0)),
        mesh_volume=float(meta["mesh_volume"]),
        mesh_hash=str(meta["mesh_hash"]),
        params=dict(meta.get("params", {})),
        timings=dict(meta.get("timings", {})),
        info=dict(meta.get("info", {})),
    )
