"""Queries between two trees, checked against coal's exact mesh distance and collision."""
import coal
import numpy as np
import pytest
import trimesh
from conftest import shared_path
from scipy.spatial.transform import Rotation

import mjist
from mjist.geometry.bvh import BVH
from mjist.query.api import Query
from mjist.query.traverse import lens_volume

TOL = 1e-9  # float tolerance only


def _torus():
    return trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=48, minor_sections=24)


def _box():
    return trimesh.creation.box(extents=(1.0, 2.0, 0.6))


def _bumpy():
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    v = m.vertices
    m.vertices = v * (1.0 + 0.08 * np.sin(5 * v[:, [0]]) * np.cos(4 * v[:, [1]]))
    return m


_SHAPES = {"torus": (_torus, 0.04), "box": (_box, 0.04), "bumpy": (_bumpy, 0.03)}
_cache = {}


def shape(name):
    """(mesh, tree, coal BVH) of a test shape, built once per session."""
    if name not in _cache:
        make, err = _SHAPES[name]
        m = make()
        t = mjist.build(m, max_error=err)
        b = coal.BVHModelOBBRSS()
        b.beginModel(len(m.faces), len(m.vertices))
        b.addVertices(np.asarray(m.vertices, dtype=np.float64))
        b.addTriangles(np.asarray(m.faces, dtype=np.int64))
        b.endModel()
        _cache[name] = (m, t, b)
    return _cache[name]


def _tf(P):
    return coal.Transform3s(P[:3, :3].copy(), P[:3, 3].copy())


def coal_distance(ba, Pa, bb, Pb):
    return coal.distance(ba, _tf(Pa), bb, _tf(Pb), coal.DistanceRequest(), coal.DistanceResult())


def coal_collides(ba, Pa, bb, Pb):
    res = coal.CollisionResult()
    coal.collide(ba, _tf(Pa), bb, _tf(Pb), coal.CollisionRequest(), res)
    return res.isCollision()


def random_pose(rng, spread):
    P = np.eye(4)
    P[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    P[:3, 3] = rng.normal(size=3) * spread
    return P


def poses_near_contact(rng, ba, bb, n):
    """Pairs of poses from deep penetration through near touching to well apart.

    B starts at a random pose and slides along a random direction; the offsets are chosen
    around the coal contact offset, so many samples are within 1e-3..1e-1 of touching.
    """
    out = []
    while len(out) < n:
        Pa = random_pose(rng, 0.1)
        Pb = random_pose(rng, 0.0)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        # bisection on the offset where coal starts to separate
        lo, hi = 0.0, 5.0
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            Pb[:3, 3] = Pa[:3, 3] + mid * u
            if coal_collides(ba, Pa, bb, Pb):
                lo = mid
            else:
                hi = mid
        for off in (-0.3, -0.05, 0.0, 1e-3, 1e-2, 0.03, 0.1, 0.5):
            P = Pb.copy()
            P[:3, 3] = Pa[:3, 3] + (hi + off) * u
            out.append((Pa, P))
    return out[:n]


PAIRS = [("torus", "torus"), ("torus", "box"), ("bumpy", "box")]


@pytest.mark.parametrize("na,nb", PAIRS)
@pytest.mark.parametrize("method", ["distance", "backtracking"])
def test_distance_is_sound_against_coal(na, nb, method):
    _, ta, ba = shape(na)
    _, tb, bb = shape(nb)
    q = Query(ta, tb)
    rng = np.random.default_rng(7)
    poses = poses_near_contact(rng, ba, bb, 96) + [(random_pose(rng, 0.5), random_pose(rng, 2.0)) for _ in range(40)]
    n_coll = 0
    for Pa, Pb in poses:
        r = q.distance(Pa, Pb, method=method)
        dc = max(coal_distance(ba, Pa, bb, Pb), 0.0)
        assert r.error_bound == pytest.approx(ta.error_bound + tb.error_bound)
        # inner spheres: never below the truth; certified ε: never above truth + ε_A + ε_B
        assert dc <= r.distance + TOL
        assert r.distance <= dc + r.error_bound + TOL
        if r.colliding:
            n_coll += 1
            assert coal_collides(ba, Pa, bb, Pb)
        # the witness points are on the reported leaf spheres, at the reported distance
        if not r.colliding:
            assert np.linalg.norm(r.point_b - r.point_a) == pytest.approx(r.distance, abs=1e-9)
    assert n_coll > 10  # the sample does exercise penetration


@pytest.mark.parametrize("na,nb", PAIRS)
def test_backtracking_and_plain_agree_along_a_motion(na, nb):
    _, ta, _ = shape(na)
    _, tb, _ = shape(nb)
    q_plain, q_bt = Query(ta, tb), Query(ta, tb)
    Pa = np.eye(4)
    rot = Rotation.from_rotvec([0.0, 0.0, 0.0])
    for k in range(300):
        s = k / 299
        rot = Rotation.from_rotvec([0.7 * s, 1.1 * s, 0.2])
        Pb = np.eye(4)
        Pb[:3, :3] = rot.as_matrix()
        Pb[:3, 3] = [2.6 - 2.4 * np.sin(np.pi * s), 0.3 * s, 0.1]
        a = q_plain.distance(Pa, Pb, method="distance")
        b = q_bt.distance(Pa, Pb, method="backtracking")
        assert a.distance == b.distance
        assert a.colliding == b.colliding


def test_tolerance_widens_the_bound_honestly():
    _, ta, ba = shape("torus")
    _, tb, bb = shape("bumpy")
    q, q0 = Query(ta, tb), Query(ta, tb)
    rng = np.random.default_rng(3)
    tol = 0.05
    for Pa, Pb in poses_near_contact(rng, ba, bb, 48):
        exact = q0.distance(Pa, Pb, method="distance").distance
        r = q.distance(Pa, Pb, method="distance", tolerance=tol)
        assert exact - TOL <= r.distance <= exact + tol + TOL
        dc = max(coal_distance(ba, Pa, bb, Pb), 0.0)
        assert r.distance - r.error_bound - TOL <= dc <= r.distance + TOL
        assert r.error_bound <= q.error_bound + tol + TOL


def test_motion_bound_skip_never_hides_a_collision():
    _, ta, ba = shape("torus")
    _, tb, bb = shape("box")
    q = Query(ta, tb)
    ref = Query(ta, tb)
    Pa = np.eye(4)
    skipped = 0
    for k in range(400):
        s = k / 399
        Pb = np.eye(4)
        Pb[:3, :3] = Rotation.from_rotvec([0.3 * s, 0.8 * s, 0.0]).as_matrix()
        Pb[:3, 3] = [2.8 - 2.0 * s, 0.05, 0.3 * np.sin(6 * s)]
        r = q.distance(Pa, Pb, skip=True)
        dc = coal_distance(ba, Pa, bb, Pb)
        if r.skipped:
            skipped += 1
            assert not coal_collides(ba, Pa, bb, Pb)
            assert not r.colliding
        # the interval stays true whether or not the traversal ran
        assert max(dc, 0.0) <= r.distance + TOL
        assert r.distance - r.error_bound <= max(dc, 0.0) + TOL
        exact = ref.distance(Pa, Pb, method="distance").distance
        assert r.distance - r.error_bound - TOL <= exact <= r.distance + TOL
    assert 50 < skipped < 400


def _sign_dist_inside(mesh, P, pts):
    m = mesh.copy()
    m.apply_transform(P)
    return trimesh.proximity.signed_distance(m, pts)  # > 0 inside


@pytest.mark.parametrize("method", ["multipoint", "distance", "backtracking"])
def test_contacts_lie_in_both_meshes_with_unit_normals(method):
    ma, ta, ba = shape("torus")
    mb, tb, bb = shape("bumpy")
    q = Query(ta, tb, max_contacts=8)
    rng = np.random.default_rng(11)
    seen = 0
    for Pa, Pb in poses_near_contact(rng, ba, bb, 64):
        c = q.contacts(Pa, Pb, split_depth=2, method=method)
        d = q.distance(Pa, Pb)
        assert (c.count > 0) == d.colliding
        if c.count == 0:
            continue
        seen += 1
        assert c.count <= (8 if method == "multipoint" else 1)
        assert c.positions.shape == (c.count, 3) and c.normals.shape == (c.count, 3)
        assert np.allclose(np.linalg.norm(c.normals, axis=1), 1.0)
        assert (c.depths >= 0).all()
        assert c.depths[0] == c.depths.max()  # deepest first
        # inside both meshes, up to each mesh's own ε
        assert (_sign_dist_inside(ma, Pa, c.positions) >= -ta.error_bound - TOL).all()
        assert (_sign_dist_inside(mb, Pb, c.positions) >= -tb.error_bound - TOL).all()
        # depths are those of the reported leaf pairs, normals point from A's leaf to B's
        for (la, lb), n, dep in zip(c.leaf_pairs, c.normals, c.depths):
            ca = Pa[:3, :3] @ ta.centers[la] + Pa[:3, 3]
            cb = Pb[:3, :3] @ tb.centers[lb] + Pb[:3, 3]
            assert dep == pytest.approx(ta.radii[la] + tb.radii[lb] - np.linalg.norm(cb - ca), abs=1e-12)
            assert np.allclose(n, (cb - ca) / np.linalg.norm(cb - ca))
        if method == "multipoint":
            groups = {tuple(g) for g in c.groups}
            assert len(groups) == c.count  # one contact per pair of depth-2 subtrees
            for (la, lb), (ga, gb) in zip(c.leaf_pairs, c.groups):
                assert _ancestor(ta, la, 2) == ga and _ancestor(tb, lb, 2) == gb
            # the deepest contact overall is the single-point answer
            single = Query(ta, tb).contacts(Pa, Pb, method="distance")
            assert c.depths[0] == pytest.approx(single.depths[0], abs=1e-12)
    assert seen >= 12


def _ancestor(tree, n, depth):
    while tree.depth_of[n] > depth:
        n = tree.parent[n]
    return n


def test_multipoint_reuse_matches_a_fresh_query_and_is_deterministic():
    _, ta, _ = shape("torus")
    _, tb, _ = shape("bumpy")
    warm = Query(ta, tb, max_contacts=6)
    Pa = np.eye(4)
    for k in range(60):
        Pb = np.eye(4)
        Pb[:3, :3] = Rotation.from_rotvec([0.02 * k, 0.01 * k, 0.0]).as_matrix()
        Pb[:3, 3] = [1.2 - 0.005 * k, 0.0, 0.2]
        a = warm.contacts(Pa, Pb, split_depth=3)
        b = Query(ta, tb, max_contacts=6).contacts(Pa, Pb, split_depth=3)
        assert a.count == b.count and a.candidates == b.candidates
        assert np.array_equal(a.leaf_pairs, b.leaf_pairs)
        assert np.array_equal(a.positions, b.positions)


@pytest.mark.parametrize("margin", [0.05, 0.5, 10.0])
def test_multipoint_full_pool_keeps_exactly_the_deepest_groups(margin):
    """Once the candidate list is full its shallowest value becomes the threshold (what makes a
    large margin, e.g. mj_geomDistance's distmax, cheap): the groups kept must be exactly the
    deepest of all the groups a list without limit finds."""
    from mjist.query import traverse as tv

    _, ta, _ = shape("torus")
    _, tb, _ = shape("bumpy")
    q = Query(ta, tb)
    rng = np.random.default_rng(5)
    for _ in range(12):
        xf = np.zeros(12)
        assert tv.relative_pose(np.eye(4), random_pose(rng, 0.6), xf)
        found = []
        for size in (1 << 16, 6):
            st = np.zeros((tv.stack_size(q.Na, q.Nb), 2), np.int64)
            sv = np.zeros(len(st))
            cand, cval = np.zeros((size, 4), np.int64), np.zeros(size)
            n, code, visits = tv.multipoint(q.Na, q.Nb, xf, st, sv, 3, margin, np.zeros((1, 4), np.int64), 0, cand, cval,
                                            np.zeros(2, np.int64))
            assert code == tv.OK and n < 1 << 16
            order = np.argsort(cval[:n], kind="stable")
            found.append((cand[:n][order], cval[:n][order], visits))
        (c_all, v_all, visits_all), (c_six, v_six, visits_six) = found
        assert np.array_equal(c_six, c_all[:6]) and np.array_equal(v_six, v_all[:6])
        assert visits_six <= visits_all


def test_penetration_volume_is_exact_for_two_spheres_and_continuous():
    a = mjist.sphere_tree([[0.0, 0.0, 0.0]], [1.0])
    b = mjist.sphere_tree([[0.0, 0.0, 0.0]], [0.6])
    q = Query(a, b)
    I = np.eye(4)
    for d in (0.0, 0.2, 0.4, 0.7, 1.2, 1.59, 1.6, 2.0):
        P = np.eye(4)
        P[:3, 3] = [0.0, d, 0.0]
        r = q.penetration_volume(I, P)
        if d >= 1.6:
            assert r.volume == 0.0 and r.pairs == 0
            assert np.array_equal(r.force_direction, np.zeros(3))
        elif d <= 0.4:
            assert r.volume == pytest.approx(4 / 3 * np.pi * 0.6**3)
        else:
            # independent value: integrate the lens cross-sections numerically
            x = np.linspace(-1.0, 1.0, 200001)
            ra2 = np.maximum(1.0 - x**2, 0)
            rb2 = np.maximum(0.36 - (x - d) ** 2, 0)
            assert r.volume == pytest.approx(np.trapezoid(np.pi * np.minimum(ra2, rb2), x), rel=1e-6)
            assert np.allclose(r.force_direction, [0.0, 1.0, 0.0])
    assert lens_volume(1.0, 0.6, 0.4) == pytest.approx(4 / 3 * np.pi * 0.6**3)  # continuous at containment


def test_blended_contact_normal_turns_continuously_where_the_deepest_pair_jumps():
    """Penalty groups use ``traverse.blend``: a ball rolling over two balls turns its normal smoothly."""
    from mjist.query import traverse as tv

    a = mjist.sphere_tree([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [1.0, 1.0])
    b = mjist.sphere_tree([[0.0, 0.0, 0.0]], [1.0])
    Na, Nb = tv.pack(a), tv.pack(b)
    ns = tv.stack_size(Na, Nb)
    st, sv = np.zeros((ns, 2), np.int64), np.zeros(ns)
    acc, pair, g = np.zeros(tv.BLEND_W), np.zeros(2, np.int64), np.zeros(12)
    xs = np.linspace(-0.5, 0.5, 1001)  # B's centre at (x, 0, 1.6): both pairs overlap, the deepest switches at 0
    deepest, blended = [], []
    for x in xs:
        xf = np.array([1.0, 0, 0, 0, 1, 0, 0, 0, 1, x, 0.0, 1.6])
        d = [tv.leaf_geometry(Na, Nb, xf, i, 0, g) for i in (1, 2)]  # the two leaves of A (nodes 1, 2)
        tv.leaf_geometry(Na, Nb, xf, 1 + int(np.argmin(d)), 0, g)
        deepest.append(g[:3].copy())
        code, _ = tv.blend(Na, Nb, xf, st, sv, 0, 0, 0.5 * min(d), 0, acc, pair)
        assert code == tv.OK and acc[7] >= 1
        blended.append(acc[1:4] / np.linalg.norm(acc[1:4]))
    step = lambda n: np.linalg.norm(np.diff(np.array(n), axis=0), axis=1).max()
    assert step(deepest) > 0.5  # the deepest pair's normal flips from one ball to the other
    assert step(blended) < 0.01  # the blend turns by about the step (1e-3) times its slope
    assert np.allclose(blended[500], [0.0, 0.0, 1.0])  # symmetric: straight up above the middle
    assert np.allclose(blended[0], deepest[0])  # one pair alone in the window: its own normal


@pytest.mark.slow  # 50 s of volume sweeps
def test_penetration_volume_is_zero_apart_continuous_and_below_the_true_overlap():
    ma, ta, ba = shape("torus")
    mb, tb, bb = shape("bumpy")
    q = Query(ta, tb)
    I = np.eye(4)
    vols = []
    xs = np.linspace(3.0, 0.0, 241)
    for x in xs:
        P = np.eye(4)
        P[:3, 3] = [x, 0.1, 0.05]
        r = q.penetration_volume(I, P)
        vols.append(r.volume)
        if not coal_collides(ba, I, bb, P):
            assert r.volume == 0.0
        if r.volume > 0:
            assert np.isclose(np.linalg.norm(r.force_direction), 1.0)
    vols = np.array(vols)
    assert vols[-1] > 0.1
    # continuity: no step larger than the sum of all lens cross-sections allows; halving the
    # step roughly halves the largest jump
    jumps = np.abs(np.diff(vols))
    coarse = np.abs(np.diff(vols[::2])).max()
    assert jumps.max() < 0.75 * coarse
    # lenses of disjoint leaves are disjoint and lie in A ∩ B: the sum is at most the overlap
    P = np.eye(4)
    P[:3, 3] = [1.0, 0.1, 0.05]
    v = q.penetration_volume(I, P).volume
    b = mb.copy()
    b.apply_transform(P)
    pts = trimesh.sample.volume_mesh(ma, 200000)
    V, F = np.asarray(b.vertices, float), np.asarray(b.faces, np.int64)
    inside_b = BVH.of_triangles(V, F).contains(pts, V, F)  # ray-cast winding number (trimesh's contains: same, 500× slower)
    overlap = ma.volume * inside_b.mean()  # Monte Carlo estimate of vol(A ∩ B)
    assert 0 < v <= overlap * 1.05


def test_bad_input_is_named():
    _, ta, _ = shape("torus")
    q = Query(ta, ta)
    I = np.eye(4)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="rigid"):
        q.distance(I, bad)
    with pytest.raises(ValueError, match="rigid"):
        q.contacts(2.0 * I, I)
    with pytest.raises(ValueError, match="4x4"):
        q.penetration_volume(np.eye(3), I)
    with pytest.raises(ValueError, match="method"):
        q.distance(I, I, method="multipoint")
    with pytest.raises(ValueError, match="max_contacts"):
        q.contacts(I, I, max_contacts=0)
    with pytest.raises(ValueError, match="margin"):
        q.contacts(I, I, margin=-1.0)
    with pytest.raises(TypeError, match="InnerSphereTree"):
        Query(ta, "not a tree")
    # after a rejected pose the state is still usable
    assert q.distance(I, I).colliding


@pytest.mark.parametrize("na,nb", PAIRS)
def test_surface_distance_is_sound_and_tighter_than_the_spheres(na, nb):
    ma, ta, ba = shape(na)
    mb, tb, bb = shape(nb)
    q = Query(ta, tb, meshes=(ma, mb))
    qs = Query(ta, tb)
    eps = q.error_bound
    rng = np.random.default_rng(7)
    poses = poses_near_contact(rng, ba, bb, 64) + [(random_pose(rng, 0.5), random_pose(rng, 2.0)) for _ in range(16)]
    bounds, errors, n_coll, n_coll_spheres = [], [], 0, 0
    for Pa, Pb in poses:
        r = q.distance(Pa, Pb)
        s = qs.distance(Pa, Pb)
        assert r.narrowphase == "surface" and s.narrowphase == "spheres" and np.isnan(s.depth)
        dc = max(coal_distance(ba, Pa, bb, Pb), 0.0)
        # a distance between two surface points is never below the truth; the lower end is the IST's
        assert dc <= r.distance + TOL
        assert r.distance - r.error_bound <= dc + TOL
        assert r.distance <= s.distance and r.error_bound <= s.error_bound + TOL
        n_coll += r.colliding
        n_coll_spheres += s.colliding
        if r.colliding:
            assert coal_collides(ba, Pa, bb, Pb) and r.distance == 0.0 and r.depth > 0.0
        else:
            assert r.depth == 0.0
            assert np.linalg.norm(r.point_b - r.point_a) == pytest.approx(r.distance, abs=1e-9)
            bounds.append(r.error_bound)
            errors.append(r.distance - dc)
    assert n_coll >= n_coll_spheres > 5
    # measured: the surfaces' distance is coal's to within 0.1 % of ε (the spheres': tens of %),
    # and the interval, whose lower end stays the IST's, about halves
    assert np.median(errors) < 0.01 * eps
    assert np.median(bounds) < 0.8 * eps


def test_surface_contacts_are_exact_at_their_points():
    ma, ta, ba = shape("torus")
    mb, tb, bb = shape("bumpy")
    q = Query(ta, tb, meshes=(ma, mb), max_contacts=8)
    rng = np.random.default_rng(11)
    n_coll = 0
    for i, (Pa, Pb) in enumerate(poses_near_contact(rng, ba, bb, 48)):
        margin = 0.0 if i % 2 else 0.02
        c = q.contacts(Pa, Pb, margin=margin)
        assert c.narrowphase == "surface" and c.error_bound == q.error_bound
        collides = coal_collides(ba, Pa, bb, Pb)
        n_coll += collides
        if collides:
            assert c.count > 0  # measured on this sample, not certified (docs/mujoco.md)
        if c.count == 0:
            continue
        assert np.allclose(np.linalg.norm(c.normals, axis=1), 1.0)
        assert (c.depths >= -margin).all() and c.depths[0] == c.depths.max()
        if margin == 0.0:
            assert collides
        # behind each contact a point of one surface inside the other by exactly the depth: B's
        # (measured into A) or A's (measured into B), half the depth from the contact point (trimesh's
        # distances carry about 1e-9 of rounding)
        yb = c.positions - 0.5 * c.depths[:, None] * c.normals
        ya = c.positions + 0.5 * c.depths[:, None] * c.normals
        b_in_a = (np.abs(_sign_dist_inside(mb, Pb, yb)) < 1e-9) & np.isclose(_sign_dist_inside(ma, Pa, yb), c.depths, atol=2e-9)
        a_in_b = (np.abs(_sign_dist_inside(ma, Pa, ya)) < 1e-9) & np.isclose(_sign_dist_inside(mb, Pb, ya), c.depths, atol=2e-9)
        assert np.all(b_in_a | a_in_b)
        p = np.round(c.positions, 9)
        assert len({tuple(x) for x in p}) == c.count  # one contact per point
    assert n_coll > 5


def test_surface_narrow_phase_input_is_named():
    ma, ta, _ = shape("torus")
    mb, tb, _ = shape("box")
    I = np.eye(4)
    with pytest.raises(ValueError, match="mesh_b is not the mesh tree_b was built from"):
        Query(ta, tb, meshes=(ma, ma))
    with pytest.raises(ValueError, match="pair"):
        Query(ta, tb, meshes=ma)
    with pytest.raises(ValueError, match="sphere set"):
        Query(ta, mjist.sphere_tree([[0, 0, 0]], [0.1]), meshes=(ma, mb))
    with pytest.raises(ValueError, match="surface_groups"):
        Query(ta, tb, meshes=(ma, mb), surface_groups=0)
    with pytest.raises(ValueError, match="needs the meshes"):
        Query(ta, tb).distance(I, I, narrowphase="surface")
    q = Query(ta, tb, meshes=(ma, mb))
    with pytest.raises(ValueError, match="method='multipoint'"):
        q.contacts(I, I, method="distance")
    with pytest.raises(ValueError, match="narrowphase"):
        q.distance(I, I, narrowphase="triangles")
    assert q.contacts(I, I, method="distance", narrowphase="spheres").narrowphase == "spheres"


@pytest.mark.shared
def test_jaw_pair_distance_is_sound(tmp_path):
    jaw = shared_path("jaw")
    ma = mjist.load_mesh(jaw / "maxilla.obj")
    mb = mjist.load_mesh(jaw / "mandible.obj")
    ta = mjist.build(ma.trimesh(), max_error=1e-3)
    tb = mjist.build(mb.trimesh(), max_error=1e-3)
    bvh = []
    for m in (ma, mb):
        b = coal.BVHModelOBBRSS()
        b.beginModel(len(m.faces), len(m.vertices))
        b.addVertices(m.vertices)
        b.addTriangles(m.faces.astype(np.int64))
        b.endModel()
        bvh.append(b)
    q = Query(ta, tb)
    qs = Query(ta, tb, meshes=(ma, mb))
    I = np.eye(4)
    hits = 0
    for dy in np.linspace(0.0, -0.004, 41):  # from the stored (interpenetrating) pose to 3.4 mm open
        P = np.eye(4)
        P[1, 3] = dy
        dc = max(coal_distance(bvh[0], I, bvh[1], P), 0.0)
        for r in (q.distance(I, P), qs.distance(I, P)):
            assert dc <= r.distance + TOL
            assert r.distance - r.error_bound <= dc + TOL
            hits += r.colliding
    assert hits > 0


def test_distance_batch_brackets_coal_and_equals_single_queries():
    """``distance_batch`` over a sweep of frames: each frame's separation distance brackets coal's
    exact distance within the certified band, and equals the one-frame ``distance`` there."""
    ma, ta, ba = shape("torus")
    mb, tb, bb = shape("bumpy")
    q = Query(ta, tb)
    rng = np.random.default_rng(11)
    Pa = random_pose(rng, 0.0)
    Pbs = []
    for s in np.linspace(3.0, 1.6, 12):  # from well apart towards touching, turning as it comes
        P = random_pose(rng, 0.0)
        P[:3, 3] = Pa[:3, 3] + [s, 0.2, 0.1]
        Pbs.append(P)
    Pbs = np.array(Pbs)
    out = q.distance_batch(Pa, Pbs)
    assert out["distance"].shape == (12,) and np.all(out["visits"] > 0)
    for i, P in enumerate(Pbs):
        exact = coal_distance(ba, Pa, bb, P)
        d = out["distance"][i]
        if exact > 0:
            assert exact <= d + TOL and d - ta.error_bound - tb.error_bound <= exact + TOL, (i, d, exact)
        assert d == pytest.approx(q.distance(Pa, P).distance, abs=1e-12)
    with pytest.raises(ValueError, match="method must be 'distance' or 'backtracking', got 'nearest'"):
        q.distance_batch(Pa, Pbs, method="nearest")
    with pytest.raises(ValueError, match="tolerance must be finite and ≥ 0, got nan"):
        q.distance_batch(Pa, Pbs, tolerance=float("nan"))
