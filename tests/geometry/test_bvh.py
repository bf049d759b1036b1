"""Triangle BVH queries against brute force: first ray hits and bounded distances."""
import numpy as np
import trimesh

from mjist.geometry.bvh import BVH


def _brute_hits(O, d, V, F):
    """Möller–Trumbore over every triangle: the nearest t ≥ 0 per ray (inf: none)."""
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e1, e2 = B - A, C - A
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    out = np.full(len(O), np.inf)
    for r, o in enumerate(O):
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ = o - A
            u = np.einsum("ij,ij->i", t_, p) / det
            q = np.cross(t_, e1)
            v = q @ d / det
            t = np.einsum("ij,ij->i", e2, q) / det
            ok = (det != 0) & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t >= 0)
        if ok.any():
            out[r] = t[ok].min()
    return out


def test_first_hits_match_brute_force_and_miss_where_nothing_lies():
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    rng = np.random.default_rng(0)
    O = np.column_stack([rng.uniform(-1.5, 1.5, 200), rng.uniform(-1.5, 1.5, 200), np.full(200, -3.0)])
    d = np.array([0.0, 0.0, 1.0])
    got = BVH.of_triangles(V, F).first_hits(O, d, V, F)
    want = _brute_hits(O, d, V, F)
    assert np.array_equal(np.isinf(got), np.isinf(want))
    assert np.isinf(got).any() and np.isfinite(got).any()  # some rays pass beside the sphere
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], rtol=0, atol=1e-12)
    # rays from inside meet the far side: the first hit, not the last
    inner = BVH.of_triangles(V, F).first_hits(np.zeros((1, 3)), d, V, F)
    assert 0.95 < inner[0] <= 1.0


def test_distance_within_bound_is_exact_inside_and_the_bound_beyond():
    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    P = np.array([[0.0, 0.0, 1.05], [0.0, 0.0, 1.5], [0.0, 3.0, 0.0]])
    b = BVH.of_triangles(V, F)
    full = b.distance(P, V, F)
    bounded = b.distance(P, V, F, within=0.2)
    assert np.isclose(bounded[0], full[0]) and full[0] < 0.2
    assert np.all(bounded[1:] == 0.2) and np.all(full[1:] > 0.2)
