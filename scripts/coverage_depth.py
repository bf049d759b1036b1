"""Where a tree's uncovered volume lies: coverage by depth below the surface (a diagnostic).

    python scripts/coverage_depth.py ../shared/data/jaw/mandible.obj --max-error 5e-5 --out out/coverage_mandible.json
    python scripts/coverage_depth.py MESH --tree saved_tree.npz

Samples points uniformly in the mesh's bounding box (fixed seed), keeps those inside, and bins
them by their distance to the surface; a point is covered when it lies in a leaf sphere. Prints
and writes (JSON) each depth band's share of the volume, its coverage and its share of the
uncovered volume: whether the volume the leaves miss is a surface layer (the ε band) or the
residual between packed spheres at every depth.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
from numba import njit, prange

import mjist
from mjist.builder.voxelize import Voxelizer
from mjist.geometry.bvh import BVH, STACK, sphere_within_xyz
from mjist.geometry.mesh import load_mesh

EDGES_MM = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0, 4.0, np.inf)


@njit(cache=True, parallel=True)
def _covered(P, C, R, lo, hi, left, right, start, count, order, tol):
    out = np.empty(P.shape[0], np.bool_)
    for i in prange(P.shape[0]):
        stack = np.empty(STACK, np.int64)
        out[i] = sphere_within_xyz(P[i, 0], P[i, 1], P[i, 2], C, R, lo, hi, left, right, start, count, order, stack, tol) >= 0
    return out


def coverage_by_depth(mesh, centers, radii, samples: int = 3_000_000, seed: int = 0, edges=None) -> dict:
    """Monte Carlo coverage of the solid by the spheres, per depth band (``edges`` in mesh units).

    Returns ``{"coverage", "inside_samples", "bands": [{lo, hi, volume_share, coverage, uncovered_share}]}``.
    """
    m = load_mesh(mesh)
    vox = Voxelizer(m.vertices, m.faces, float(np.max(m.vertices.max(0) - m.vertices.min(0))))
    rng = np.random.default_rng(seed)
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    P = lo + rng.random((int(samples), 3)) * (hi - lo)
    depth = vox.signed_distance(P)
    inside = depth > 0
    P, depth = np.ascontiguousarray(P[inside]), depth[inside]
    C = np.ascontiguousarray(centers, dtype=np.float64)
    R = np.ascontiguousarray(radii, dtype=np.float64)
    tol = 1e-12 * float(np.linalg.norm(hi - lo))  # inside a sphere, up to rounding
    cov = _covered(P, C, R, *BVH.of_spheres(C, R).arrays, tol)
    edges = np.asarray(edges if edges is not None else EDGES_MM, dtype=np.float64)
    miss = max(int((~cov).sum()), 1)
    bands = []
    for a, b in zip(edges[:-1], edges[1:]):
        s = (depth >= a) & (depth < b)
        if s.any():
            bands.append({"lo": float(a), "hi": float(b), "volume_share": float(s.mean()), "coverage": float(cov[s].mean()),
                          "uncovered_share": float((s & ~cov).sum() / miss)})
    return {"coverage": float(cov.mean()), "inside_samples": int(len(P)), "bands": bands}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mesh")
    ap.add_argument("--max-error", type=float, help="build the tree (mesh units)")
    ap.add_argument("--tree", help="a saved tree of this mesh instead of a build")
    ap.add_argument("--samples", type=int, default=3_000_000, help="points in the bounding box")
    ap.add_argument("--unit", type=float, default=1e-3, help="depth bands in this many mesh units (default mm of a mesh in m)")
    ap.add_argument("--out", help="JSON file to write")
    a = ap.parse_args()
    if (a.tree is None) == (a.max_error is None):
        ap.error("give either --max-error (build) or --tree (load)")
    t = time.perf_counter()
    tree = mjist.load_tree(a.tree) if a.tree else mjist.build(a.mesh, max_error=a.max_error)
    built = time.perf_counter() - t
    r = coverage_by_depth(a.mesh, tree.leaf_centers, tree.leaf_radii, samples=a.samples,
                          edges=np.asarray(EDGES_MM) * a.unit)
    r.update(mesh=a.mesh, max_error=a.max_error, tree=a.tree, leaves=int(tree.num_leaves), tree_coverage=float(tree.coverage),
             error_bound=float(tree.error_bound), build_s=built if a.max_error else None)
    print(f"{a.mesh}: {tree.num_leaves} leaves, coverage {tree.coverage:.1%} (sampled {r['coverage']:.1%} of "
          f"{r['inside_samples']} inside points)")
    print(f"{'depth':>16s} {'volume':>8s} {'covered':>8s} {'of the gap':>11s}")
    for b in r["bands"]:
        print(f"{b['lo'] / a.unit:6.2f}-{b['hi'] / a.unit:<8.2f} {b['volume_share']:8.1%} {b['coverage']:8.1%} {b['uncovered_share']:11.1%}")
    if a.out:
        with open(a.out, "w") as fh:
            json.dump(r, fh, indent=2)
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
