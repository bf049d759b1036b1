"""The narrow-phase surface: signed distances against independent references, local distances
between posed surfaces against coal."""
import numpy as np
import pytest
import trimesh
from conftest import winding_numbers
from numba import njit

from mjist.geometry import surface as sf


@njit  # not cached: numba would not see the mjist kernels change
def _signed_all(S, P, out):
    stack = np.empty(sf.STACK, np.int64)
    row = np.empty(7)
    for i in range(P.shape[0]):
        row[:] = np.nan
        sf.signed_closest(S, P[i, 0], P[i, 1], P[i, 2], stack, np.inf, row)
        out[i] = row


def signed(surf, P):
    out = np.empty((len(P), 7))
    _signed_all(surf.views(), np.ascontiguousarray(P, float), out)
    return out


@njit  # not cached: numba would not see the mjist kernels change
def _local(SA, SB, xf, x, iters, step0):
    stack = np.empty(sf.STACK, np.int64)
    tmp = np.empty(sf.REFINE_W)
    out = np.full(7, np.nan)
    ok = sf.local_distance(SA, SB, xf, x[0], x[1], x[2], iters, step0, 1e-12, stack, tmp, out)
    return ok, out


def xf_of(P):
    return np.r_[P[:3, :3].ravel(), P[:3, 3]]


def test_signed_distance_of_a_box_matches_the_exact_one_and_the_winding_number():
    m = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    s = sf.build_surface(m.vertices, m.faces)
    rng = np.random.default_rng(0)
    P = rng.uniform(-1.5, 1.5, size=(400, 3)) * [1, 1.5, 2]
    # corners, edges and faces of the box are closest points: every feature's pseudo-normal is used
    P = np.r_[P, [[0.9, 1.4, 1.9], [0.9, 1.4, 0.0], [0.6, 0.0, 0.0], [-0.49, 0.99, 1.49]]]
    r = signed(s, P)
    h = np.array([0.5, 1.0, 1.5])
    q = np.abs(P) - h
    exact = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    assert np.allclose(r[:, 0], exact, atol=1e-12)
    inside = winding_numbers(P, m.vertices, m.faces) > 0.5
    assert np.array_equal(r[:, 0] < 0, inside)
    # the closest point is on the box, at |d| from the query, and the direction is unit
    assert np.allclose(np.abs(np.abs(r[:, 1:4]) - h).min(axis=1), 0, atol=1e-12)
    assert np.allclose(np.linalg.norm(r[:, 1:4] - P, axis=1), np.abs(r[:, 0]), atol=1e-12)
    assert np.allclose(np.linalg.norm(r[:, 4:7], axis=1), 1.0)


def test_signed_distance_of_a_sphere_mesh_has_the_right_sign_at_vertices_and_edges():
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    s = sf.build_surface(m.vertices, m.faces)
    # just outside and inside every vertex and edge midpoint, where the closest feature is not a face
    mids = m.vertices[m.edges_unique].mean(axis=1)
    base = np.r_[m.vertices, mids]
    n = base / np.linalg.norm(base, axis=1)[:, None]
    for delta in (1e-3, -1e-3):
        r = signed(s, base + delta * n)
        assert np.all(np.sign(r[:, 0]) == np.sign(delta))
        assert np.all(np.einsum("ij,ij->i", r[:, 4:7], n) > 0.9)  # outward
    ref = trimesh.proximity.signed_distance(m, base[:50] + 0.05 * n[:50])  # trimesh: positive inside
    assert np.allclose(signed(s, base[:50] + 0.05 * n[:50])[:, 0], -ref, atol=1e-9)


@njit  # not cached: numba would not see the mjist kernels change
def _overlap(SA, SB, xf, P, n, within):
    stack = np.empty(sf.STACK, np.int64)
    out = np.empty(7)
    res = np.empty(len(P))
    for i in range(len(P)):
        res[i] = sf.overlap_depth(SA, SB, xf, P[i, 0], P[i, 1], P[i, 2], n[0], n[1], n[2], within, stack, out)
    return res


def test_overlap_depth_is_the_thickness_between_two_boxes_and_negative_outside():
    """Box B 1.8 above box A (both 2 wide): their overlap is the slab 0.8 < z < 1, 0.2 thick.
    From any point of the slab's column the balanced point gives 0.2; a point whose balanced
    point lies outside either box (or within ``within`` of it) gives a negative value."""
    A = sf.build_surface(*_box_arrays())
    xf = np.r_[np.eye(3).ravel(), 0.0, 0.0, 1.8]
    P = np.array([[0, 0, 0.9], [0.3, -0.2, 0.85], [0, 0, 0.99], [0.5, 0.5, 0.7], [0, 0, -0.5], [0, 0, 2.5]], float)
    d = _overlap(A.views(), A.views(), xf, P, np.array([0.0, 0.0, 1.0]), 0.5)
    assert np.allclose(d[:4], 0.2, atol=1e-12)
    assert (d[4:] < 0).all()
    # continuous along a line through the overlap's edge (x = 1): no jump at the corner
    line = np.c_[np.linspace(0.9, 1.1, 201), np.zeros(201), np.full(201, 0.9)]
    d = _overlap(A.views(), A.views(), xf, line, np.array([0.0, 0.0, 1.0]), 0.5)
    assert np.abs(np.diff(d)).max() <= 2 * 0.001 + 1e-12  # 2-Lipschitz in the point
    assert d[0] == pytest.approx(0.2) and d[-1] < 0


def _box_arrays():
    m = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


@njit  # not cached: numba would not see the mjist kernels change
def _walk_from(S, starts, P, out):
    for i in range(P.shape[0]):
        sf._walk(S, starts[i], P[i, 0], P[i, 1], P[i, 2], out[i])


def test_walk_reaches_the_closest_point_of_a_sphere_mesh_from_a_nearby_face():
    """Points 0.02–0.2 outside or 0.02–0.05 inside a unit sphere mesh, each walk started on the
    face closest to the point turned 10° away: outside, the walk ends at the exact closest
    point (the BVH's); inside, within 1e-3 of the exact depth (inside a convex mesh each face
    holds a local closest point, slightly deeper than the global one)."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    S = sf.build_surface(m.vertices, m.faces)
    rng = np.random.default_rng(3)
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    r = np.r_[rng.uniform(1.02, 1.2, 200), rng.uniform(0.95, 0.98, 200)]
    P = u * r[:, None]
    turned = P @ trimesh.transformations.rotation_matrix(np.radians(10), [0, 0, 1])[:3, :3].T
    exact = signed(S, P)
    start_rows = signed(S, turned)
    # the face of each turned point's closest point: the BVH's, found by matching closest points
    tri = m.triangles
    starts = np.array([np.argmin(np.linalg.norm(tri.mean(axis=1) - q, axis=1)) for q in start_rows[:, 1:4]])
    out = np.full((len(P), 7), np.nan)
    _walk_from(S.views(), starts, P, out)
    assert np.allclose(out[:200, 0], exact[:200, 0], atol=1e-12)
    assert np.allclose(out[:200, 1:4], exact[:200, 1:4], atol=1e-12)
    assert (out[200:, 0] < 0).all() and np.abs(out[200:, 0] - exact[200:, 0]).max() < 1e-3


def test_local_distance_between_two_spheres():
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    s = sf.build_surface(m.vertices, m.faces)
    SA = SB = s.views()
    for gap in (0.3, 0.01, -0.05):
        P = np.eye(4)
        P[:3, 3] = [2.0 + gap, 0.0, 0.0]
        # start well off the line of centres: the descent has to slide along the surface
        ok, out = _local(SA, SB, xf_of(P), np.array([1.0, 0.4, 0.3]), 30, 0.1)
        assert ok
        # a polyhedral sphere: its surface lies between 0.999 and 1 of the radius at this refinement
        assert out[0] == pytest.approx(gap, abs=3e-3)
        assert out[4] == pytest.approx(1.0, abs=1e-2)  # normal from A to B
        assert out[1] == pytest.approx(1.0 + 0.5 * gap, abs=1e-2) and abs(out[2]) < 0.05 and abs(out[3]) < 0.05


def test_local_distance_is_a_true_distance_near_the_jaws_occlusion():
    """Separated poses of the bundled jaws: started 0.1 mm from coal's closest points, the local
    distance is a distance between two surface points (never below coal's), never above its
    first value, and reaches coal's."""
    import coal

    from mjist.jaw import pair as jaw

    mx, md, info = jaw.load_pair(jaw.BUNDLED)
    SA = sf.build_surface(mx.vertices, mx.faces).views()
    SB = sf.build_surface(md.vertices, md.faces).views()
    bx, bd = jaw.coal_bvh(mx.vertices, mx.faces), jaw.coal_bvh(md.vertices, md.faces)
    touch = float(info["mandible_pose"][1, 3])
    rng = np.random.default_rng(3)
    for gap in (2e-4, 5e-5):
        P = jaw.hinge_pose(np.radians(0.1), info["hinge"], vertical=touch - gap)
        res = coal.DistanceResult()
        d = coal.distance(bx, coal.Transform3s(), bd, coal.Transform3s(P[:3, :3], P[:3, 3]), coal.DistanceRequest(), res)
        assert d > 0
        mid = 0.5 * (np.asarray(res.getNearestPoint1()) + np.asarray(res.getNearestPoint2()))
        for _ in range(5):
            off = rng.normal(size=3)
            x = mid + 1e-4 * off / np.linalg.norm(off)
            first = _local(SA, SB, xf_of(P), x, 1, 1e-4)[1][0]
            ok, out = _local(SA, SB, xf_of(P), x, 30, 1e-4)
            assert ok and d - 1e-9 <= out[0] <= first
            assert out[0] <= d + 2e-6


@njit  # not cached: numba would not see the mjist kernels change
def _rays(S, O, D, out):
    stack = np.empty(sf.STACK, np.int64)
    for i in range(O.shape[0]):
        out[i] = sf.ray_exit(S, O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2], stack)


def test_ray_exit_is_the_first_crossing_trimesh_finds():
    """From points inside and outside a sphere mesh, in random directions: the distance to the
    first triangle crossed equals trimesh's ray test, and a ray that misses gives inf."""
    m = trimesh.creation.icosphere(3, radius=1.0)
    surf = sf.build_surface(m.vertices, m.faces)
    rng = np.random.default_rng(0)
    O = rng.uniform(-1.5, 1.5, (300, 3))
    D = rng.normal(size=(300, 3))
    D /= np.linalg.norm(D, axis=1)[:, None]
    out = np.empty(300)
    _rays(surf.views(), O, D, out)
    loc, ray, _ = m.ray.intersects_location(O, D, multiple_hits=True)
    for i in range(300):
        hits = np.linalg.norm(loc[ray == i] - O[i], axis=1)
        hits = hits[hits > 1e-12]
        if len(hits):
            assert out[i] == pytest.approx(hits.min(), abs=1e-9), i
        else:
            assert out[i] == np.inf, i
    inside = np.linalg.norm(O, axis=1) < 0.95
    assert inside.sum() > 20 and np.isfinite(out[inside]).all()  # from inside a closed surface every ray leaves
