"""What the benchmark scripts share: trees through mjist's own content-hashed cache, and the
Markdown tables they write.

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


def write_table(path, header, rows) -> str:
    """Write a Markdown table (``header`` cells, then one line of cells per row) to ``path``,
    print it and return its text."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    text = "\n".join(lines) + "\n"
    Path(path).write_text(text)
    print(text, end="")
    return text
