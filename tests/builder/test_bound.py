"""The certificate's disk-cover test (``bound._balls_cover``): never claims a covered triangle
that has a point farther than t from every ball, and does certify the usual cases; given every
ball that reaches the triangle (``bound._cover_all``), its no is a true no."""
import numpy as np

from mjist.builder.bound import COVER_SHRINK, _balls_cover, _cover_all
from mjist.geometry.bvh import BVH, STACK


def _grid(a, b, c, n=80):
    """Barycentric grid of the triangle, edges and vertices included."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    u, v = i[keep] / n, j[keep] / n
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def _cover(tri, C, R, t):
    js = np.arange(len(R), dtype=np.int64)
    D = np.empty((max(len(R), 1), 3))
    return _balls_cover(*tri[0], *tri[1], *tri[2], js, len(R), np.ascontiguousarray(C, np.float64),
                        np.ascontiguousarray(R, np.float64), float(t), D)


def _max_gap(P, C, R):
    return (np.linalg.norm(P[:, None] - C[None], axis=2) - R[None]).min(axis=1).max()


def test_cover_never_certifies_an_uncovered_point():
    rng = np.random.default_rng(11)
    said_yes = 0
    truly_covered = 0
    found = 0
    for trial in range(3000):
        tri = rng.normal(scale=0.5, size=(3, 3))
        k = rng.integers(1, 7)
        # balls around points of the triangle, some off its plane (like spheres under a surface)
        w = rng.dirichlet(np.ones(3), size=k)
        C = w @ tri + rng.normal(scale=0.3, size=(k, 3))
        R = rng.uniform(0.05, 0.6, size=k)
        t = rng.uniform(0.0, 0.4)
        gap = _max_gap(_grid(*tri), C, R)
        yes = _cover(tri, C, R, t)
        if yes:
            said_yes += 1
            assert gap <= t + 1e-12, (trial, gap, t)
        if gap < 0.9 * t:
            truly_covered += 1
            found += yes
    # not vacuous: it certifies the triangles that are covered with some margin (all of them here)
    assert found >= 0.95 * truly_covered and truly_covered > 300 and said_yes >= truly_covered


def _random_case(rng):
    tri = rng.normal(scale=0.5, size=(3, 3))
    k = rng.integers(1, 7)
    w = rng.dirichlet(np.ones(3), size=k)
    C = w @ tri + rng.normal(scale=0.3, size=(k, 3))
    return tri, C, rng.uniform(0.05, 0.6, size=k), rng.uniform(0.0, 0.4)


def test_with_every_ball_a_no_is_a_true_no():
    """The builder treats a triangle that the complete test does not cover as open for certain
    (split no finer than bad_size): some point of it must then be farther than t from every ball."""
    rng = np.random.default_rng(12)
    nos = 0
    for trial in range(2000):
        tri, C, R, t = _random_case(rng)
        if _cover(tri, C, R, t):
            continue
        nos += 1
        n = 160
        spacing = max(np.linalg.norm(tri[i] - tri[j]) for i, j in ((0, 1), (1, 2), (2, 0))) / n
        gap = _max_gap(_grid(*tri, n=n), C, R)  # the grid is within `spacing` of every point
        assert gap > t - spacing, (trial, gap, t)
    assert nos > 300


def test_cover_all_gathers_every_ball_that_reaches_the_triangle():
    """``_cover_all`` (BVH range search + the disk test) answers as the test given every ball."""
    rng = np.random.default_rng(13)
    stack = np.empty(STACK, np.int64)
    js, D = np.empty(64, np.int64), np.empty((64, 3))
    answers = set()
    for trial in range(400):
        tri, C, R, t = _random_case(rng)
        far = rng.normal(size=(300, 3))
        far = tri.mean(0) + far / np.linalg.norm(far, axis=1)[:, None] * rng.uniform(2.5, 6.0, size=(300, 1))
        # and balls beyond the vertices that reach them only once grown by t
        m = tri.mean(0)
        out = (tri - m) / np.linalg.norm(tri - m, axis=1)[:, None]
        r_out = rng.uniform(0.05, 0.3, size=3)
        C_out = tri + out * (r_out + rng.uniform(0.0, 1.0, size=3) * t)[:, None]
        Call = np.ascontiguousarray(np.vstack([C, C_out, far]))
        Rall = np.ascontiguousarray(np.concatenate([R, r_out, rng.uniform(0.05, 0.6, size=300)]))
        bvh = BVH.of_spheres(Call, Rall)
        got = _cover_all(*tri[0], *tri[1], *tri[2], Call, Rall, *bvh.arrays, stack, t, js, D)
        assert got == int(_cover(tri, Call, Rall, t * (1.0 - COVER_SHRINK))), trial
        answers.add(got)
    assert answers == {0, 1}
    # more balls reach it than the buffer holds: undecided, not a no
    many = np.ascontiguousarray(tri.mean(0) + rng.normal(scale=0.05, size=(100, 3)))
    bvh = BVH.of_spheres(many, np.full(100, 0.01))
    assert _cover_all(*tri[0], *tri[1], *tri[2], many, np.full(100, 0.01), *bvh.arrays, stack, 0.3, js, D) == -1


def test_hole_between_three_balls_is_found():
    # three balls around the centroid leave a small hole there; a fourth ball over it closes it
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.9, 0.0]])
    C = tri.copy()
    mid = tri.mean(0)
    dist = np.linalg.norm(tri - mid, axis=1)
    R = dist - 0.01  # each ball stops 0.01 short of the centroid
    assert not _cover(tri, C, R, 0.0)
    assert _cover(tri, C, R, 0.02)
    assert _cover(tri, np.vstack([C, mid]), np.append(R, 0.05), 0.0)
    # a ball far off the plane does not reach it; a single big ball covers everything
    assert not _cover(tri, np.array([[0.5, 0.3, 5.0]]), np.array([1.0]), 0.1)
    assert _cover(tri, np.array([[0.5, 0.3, 0.2]]), np.array([1.5]), 0.0)


def test_slivers_and_empty_sets_are_not_certified():
    sliver = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1e-9, 0.0]])
    assert not _cover(sliver, np.array([[0.5, 0.0, 0.0]]), np.array([2.0]), 0.0)
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert not _cover(tri, np.empty((0, 3)), np.empty(0), 1.0)
