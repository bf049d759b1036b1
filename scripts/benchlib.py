"""What the benchmark scripts share: trees through mjist's own content-hashed cache.

The cache (``$MJIST_CACHE``, else ``~/.cache/mjist``; see ``mjist.cache``) keys a tree on the
mesh bytes, the build parameters and the builder and tree-format versions, so a benchmark never
times queries on a tree an older builder made, and a tree the CLI or a scene already built is
reused by every benchmark.
"""
from __future__ import annotations

from pathlib import Path

import mjist
from mjist.cache import cached_tree


def tree_for(path, *, progress: bool = False, **params):
    """The tree of the mesh at ``path`` built with ``params`` (``mjist.build`` keywords).

    Returns ``(tree, mesh, hit)``: ``mesh`` is the loaded ``mjist.Mesh``, ``hit`` whether the
    tree came from the cache. ``tree.timings["total"]`` is its build's own time either way.
    """
    mesh = mjist.load_mesh(path)
    tree, hit = cached_tree(mesh.vertices, mesh.faces, params, progress=progress, name=Path(path).name)
    if not hit:
        print(f"  built {Path(path).name} {params}: {tree.num_leaves} leaves, ε {tree.error_bound:.4g}", flush=True)
    return tree, mesh, hit
