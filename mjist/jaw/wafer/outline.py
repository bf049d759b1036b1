"""Where the wafer lies and how far it wraps the crowns: the dentition's outline on the grid,
the imprint depth, and the cusp tips the seating proof checks."""
from __future__ import annotations

import numpy as np

from .grid import dilate_mask, lowest_near

# the wafer wraps the crowns this far past the cusp tips (m): deep enough that a cusp's
# imprint holds sideways, shallow enough to stay off the gums and out of the undercuts
IMPRINT = 2.0e-3
# the outline: where the arches face each other within REACH at the occlusion (the occlusal
# table, m), its gaps between teeth closed over CLOSE, then widened by RIM so that the wafer
# covers the buccal and lingual cusps and their slopes
REACH = 3.0e-3
CLOSE = 1.5e-3
RIM = 2.5e-3
NEIGHBOURHOOD = 2.5e-3  # m: the cusp level the imprint depth counts from: the extreme within this radius
TIP = 1.5e-3  # m: a cusp tip is the extreme occlusal vertex within this radius (a molar's cusps are 2-3 mm apart)


def outline(gap, grid) -> np.ndarray:
    """The dentition's outline on the grid: the largest region where the arches face each other
    within ``REACH`` (``gap``: the vertical gap per node; gaps between teeth closed over
    ``CLOSE``), widened by ``RIM``."""
    from scipy import ndimage

    facing = np.isfinite(gap) & (gap <= REACH)
    m = ~dilate_mask(~dilate_mask(facing, grid, CLOSE), grid, CLOSE)  # closing
    m = ndimage.binary_fill_holes(m)
    lab, n = ndimage.label(m)
    if n == 0:
        raise ValueError(f"the arches do not face each other within {REACH * 1e3:g} mm anywhere at the given occlusion: "
                         "pass the pose where the teeth meet (--pose occlusion.json or --search)")
    sizes = ndimage.sum(m, lab, index=np.arange(1, n + 1))
    m = lab == 1 + int(np.argmax(sizes))
    return dilate_mask(m, grid, RIM)


def crop(V, F, grid, inside, band) -> np.ndarray:
    """Faces of ``(V, F)`` whose centroid lies over ``inside`` (grid mask) within ``band`` of w = 0."""
    C = grid.local(V[F].mean(axis=1))
    i, j, ok = grid.index(C)
    ok &= np.abs(C[:, 2]) < band
    ok[ok] = inside[i[ok], j[ok]]
    return ok


def cap(H, inside, grid, sign) -> np.ndarray:
    """How far the wafer may wrap the crowns: ``IMPRINT`` past the extreme cusp within
    ``NEIGHBOURHOOD`` (above it for the maxilla, ``sign`` -1; below for the mandible, +1)."""
    if sign < 0:
        return lowest_near(np.where(inside, H, np.inf), grid, NEIGHBOURHOOD) + IMPRINT
    return -lowest_near(np.where(inside, -H, np.inf), grid, NEIGHBOURHOOD) - IMPRINT


def cusp_tips(V, F, grid, over, band, sign, other=None) -> np.ndarray:
    """Cusp tips of an arch over the grid mask ``over``: its occlusal vertices (facing the other
    arch: down for the maxilla, ``sign`` -1, up for the mandible, +1; within ``REACH`` of
    ``other`` = (V, F) of the other arch at the occlusion, when given) that are the extreme
    occlusal vertex within ``TIP``."""
    n = np.zeros_like(V)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    facing = (n @ grid.B[2]) * sign > 0.5 * np.linalg.norm(n, axis=1)
    L = grid.local(V)
    i, j, ok = grid.index(L)
    ok &= facing & (np.abs(L[:, 2]) < band)
    if other is not None:
        from ...geometry.bvh import BVH

        k = np.flatnonzero(ok)
        Vo, Fo = other
        ok[k] = BVH.of_triangles(Vo, Fo).distance(np.ascontiguousarray(V[k]), Vo, Fo, within=REACH) < REACH
    H = np.full(grid.shape, np.inf)
    np.minimum.at(H, (i[ok], j[ok]), -sign * L[ok, 2])  # the extreme (lowest for the maxilla) per node
    local = lowest_near(H, grid, TIP)
    ok[ok] = over[i[ok], j[ok]]
    k = np.flatnonzero(ok)
    tip = -sign * L[k, 2] <= local[i[k], j[k]] + 1e-12
    return V[k[tip]]
