"""The narrow-band grid of nearest faces (``geometry.sdfgrid``, ``surface.add_grid``): its answers
against the BVH's exact ones, its band, its cache; the both-way contact distance."""
import os

import numpy as np
import pytest
import trimesh
from numba import njit

from mjist import cache
from mjist.geometry import sdfgrid
from mjist.geometry import surface as sf


@njit  # not cached: numba would not see the mjist kernels change
def _both(S, P, grid, exact):
    stack = np.empty(sf.STACK, np.int64)
    row = np.empty(7)
    answered = 0
    for i in range(P.shape[0]):
        grid[i] = np.nan
        if sf._grid_closest(S, P[i, 0], P[i, 1], P[i, 2], row) >= 0:
            grid[i] = row
            answered += 1
        sf.signed_closest(S, P[i, 0], P[i, 1], P[i, 2], stack, np.inf, row)
        exact[i] = row
    return answered


def _torus():
    m = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=96, minor_sections=48)
    assert m.is_watertight
    return m


def _near_surface(m, n, spread, seed=0):
    rng = np.random.default_rng(seed)
    P, _ = trimesh.sample.sample_surface(m, n, seed=seed)
    return P + rng.normal(0.0, spread, P.shape)


def test_grid_answers_a_point_of_the_surface_and_mostly_the_closest():
    m = _torus()
    s = sf.add_grid(sf.build_surface(m.vertices, m.faces))
    h = s.grid_spacing
    edge = float(np.median(m.edges_unique_length))
    assert h == pytest.approx(sf.GRID_EDGE * edge, rel=0.05)
    P = _near_surface(m, 3000, 0.5 * h)
    grid, exact = np.empty((len(P), 7)), np.empty((len(P), 7))
    assert _both(s.views(), P, grid, exact) == len(P)  # every point within the band is answered
    # never nearer than the closest point, and a point of the surface (its own exact distance 0)
    assert np.all(np.abs(grid[:, 0]) >= np.abs(exact[:, 0]) - 1e-12)
    on = np.empty_like(grid)
    _both(s.views(), grid[:, 1:4].copy(), np.empty_like(grid), on)
    assert np.abs(on[:, 0]).max() < 1e-12
    same = np.abs(grid[:, 0] - exact[:, 0]) < 1e-12
    assert same.mean() > 0.8
    # where the faces agree, so do sign, point and direction
    assert np.allclose(grid[same], exact[same], atol=1e-9)
    # and where they do not, the answer is off by less than a cell
    assert np.abs(grid[:, 0] - exact[:, 0]).max() < h


def test_points_beyond_the_band_and_empty_grids_are_not_answered():
    m = _torus()
    s = sf.add_grid(sf.build_surface(m.vertices, m.faces))
    far = np.array([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0], [-9.0, 0.0, 0.0], [np.nan, 0.0, 0.0]])
    grid = np.empty((len(far), 7))
    assert _both(s.views(), far, grid, np.empty_like(grid)) == 0
    bare = sf.build_surface(m.vertices, m.faces)
    assert bare.grid_spacing == 0.0
    assert _both(bare.views(), _near_surface(m, 50, 0.01), np.empty((50, 7)), np.empty((50, 7))) == 0
    with pytest.raises(ValueError, match="spacing"):
        sf.add_grid(bare, spacing=0.0)
    with pytest.raises(ValueError, match="spacing"):
        sf.add_grid(bare, spacing=float("nan"))


def test_grid_memory_stays_bounded_for_a_coarse_mesh():
    m = trimesh.creation.box(extents=(1.0, 2.0, 3.0))  # edges of 1-3.6: the spacing is capped
    s = sf.add_grid(sf.build_surface(m.vertices, m.faces))
    assert s.grid_spacing <= 3.0 / 40 + 1e-12
    assert s.grid_nbytes < 20e6


def test_cached_grid_is_found_again_and_a_corrupt_one_rebuilt(tmp_path):
    m = _torus()
    calls = []

    def compute():
        calls.append(1)
        return sf.add_grid(sf.build_surface(m.vertices, m.faces)).grid

    g1 = cache.cached_grid(m.vertices, m.faces, compute, folder=tmp_path)
    g2 = cache.cached_grid(m.vertices, m.faces, compute, folder=tmp_path)
    assert len(calls) == 1 and all(np.array_equal(a, b) for a, b in zip(g1, g2))
    (path,) = [p for p in os.listdir(tmp_path) if p.endswith(".grid.npz")]
    bad = g1[2].copy()
    bad[0] = len(m.faces) + 7  # a face id no surface has: would read out of bounds
    np.savez(tmp_path / path, header=g1[0], table=g1[1], values=bad)
    g3 = cache.cached_grid(m.vertices, m.faces, compute, folder=tmp_path)
    assert len(calls) == 2 and np.array_equal(g3[2], g1[2])
    (tmp_path / path).write_bytes(b"not a zip")
    cache.cached_grid(m.vertices, m.faces, compute, folder=tmp_path)
    assert len(calls) == 3


@njit  # not cached
def _contact(SA, SB, xf, x, both):
    stack = np.empty(sf.STACK, np.int64)
    tmp = np.empty(sf.REFINE_W)
    out = np.full(7, np.nan)
    if both:
        ok = sf.contact_distance(SA, SB, xf, x[0], x[1], x[2], 30, 0.1, 1e-9, stack, tmp, out, sf.EITHER) == sf.REVERSE
    else:
        ok = sf.local_distance(SA, SB, xf, x[0], x[1], x[2], 30, 0.1, 1e-9, stack, tmp, out)
    return ok, out


@pytest.mark.parametrize("grids", [False, True])
def test_a_cusp_pressed_into_a_face_is_measured_from_its_tip(grids):
    """A sharp cone (A) pressed 0.1 into a box's face (B): B's points inside A lie at most 0.03
    deep, A's tip 0.1 deep in B. One way does not see the tip; both ways finds it, the normal
    pushing B off the tip."""
    cone = trimesh.creation.cone(radius=0.5, height=2.0, sections=64)  # tip at z = 2
    box = trimesh.creation.box(extents=(2.0, 2.0, 1.0))  # bottom face at z = -0.5 in its frame
    SA, SB = sf.build_surface(cone.vertices, cone.faces), sf.build_surface(box.vertices, box.faces)
    if grids:
        sf.add_grid(SA, spacing=0.02)
        sf.add_grid(SB, spacing=0.02)
    xf = np.r_[np.eye(3).ravel(), [0.0, 0.0, 2.0 - 0.1 + 0.5]]  # B's bottom face at z = 1.9
    start = np.array([0.01, 0.0, 1.93])
    ok, one = _contact(SA.views(), SB.views(), xf, start, False)
    assert ok and one[0] > -0.03
    ok, both = _contact(SA.views(), SB.views(), xf, start, True)
    assert ok and both[0] == pytest.approx(-0.1, abs=1e-9)
    assert np.allclose(both[4:7], [0.0, 0.0, 1.0], atol=1e-9)  # from A to B
    assert np.allclose(both[1:4], [0.0, 0.0, 1.95], atol=1e-9)  # midway between the tip and B's face


def test_layout_refuses_what_it_cannot_grid():
    with pytest.raises(ValueError, match="no faces"):
        sdfgrid.layout(np.zeros((0, 9)), 0.1, 0.2)
    with pytest.raises(ValueError, match="table entries"):
        sdfgrid.layout(np.array([[0, 0, 0, 1e6, 0, 0, 0, 1e6, 1e6]], float), 1e-3, 0.0)
