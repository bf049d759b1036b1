"""Property tests (issue 7's stress suite): every query against coal on random shapes and poses,
from exactly touching through deeply nested to far apart, and awkward geometry (thin walls,
needle-like teeth, sliver triangles). Hypothesis drives the poses; ``MJIST_STRESS=1`` runs
ten times as many examples."""
import os

import coal
import numpy as np
import pytest
import trimesh
from conftest import gaps_to_union
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import mjist
from mjist.query.api import Query

FULL = os.environ.get("MJIST_STRESS") == "1"
TOL = 1e-9
pytestmark = pytest.mark.stress


# --- random shapes: a fixed, seeded pool (trees are built once), drawn from by hypothesis ----------
def _bumpy(rng):
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    a, b = rng.uniform(2, 6, size=2)
    v = m.vertices
    m.vertices = v * (1.0 + 0.12 * np.sin(a * v[:, [0]]) * np.cos(b * v[:, [1]]))
    return m


def _two_shells(rng):
    s = rng.uniform(0.2, 0.4)
    a = trimesh.creation.box(extents=(s, s, 2 * s))
    b = trimesh.creation.icosphere(subdivisions=2, radius=s)
    b.apply_translation([s + 0.3, 0.0, 0.0])
    return trimesh.util.concatenate([a, b])


def _pool():
    rng = np.random.default_rng(2026)
    out = [
        ("box", trimesh.creation.box(extents=rng.uniform(0.3, 1.2, size=3))),
        ("ellipsoid", trimesh.creation.icosphere(3, radius=1.0).apply_scale(rng.uniform(0.2, 0.6, size=3))),
        ("torus", trimesh.creation.torus(major_radius=rng.uniform(0.4, 0.6), minor_radius=rng.uniform(0.1, 0.2),
                                         major_sections=40, minor_sections=16)),
        ("capsule", trimesh.creation.capsule(height=rng.uniform(0.4, 1.0), radius=rng.uniform(0.1, 0.3))),
        ("bumpy", _bumpy(rng)),
        ("two shells", _two_shells(rng)),
    ]
    return out


POOL = _pool()
_BUILT = {}


def _shape(i):
    """(name, mesh, tree, coal BVH, bounding radius) of pool shape ``i``."""
    if i not in _BUILT:
        name, m = POOL[i]
        size = float(np.min(m.extents))
        t = mjist.build(m, max_error=0.08 * size)
        _BUILT[i] = (name, m, t, _bvh(m), float(np.linalg.norm(m.vertices, axis=1).max()))
    return _BUILT[i]


def _bvh(mesh):
    b = coal.BVHModelOBBRSS()
    b.beginModel(len(mesh.faces), len(mesh.vertices))
    b.addVertices(np.asarray(mesh.vertices, dtype=np.float64))
    b.addTriangles(np.asarray(mesh.faces, dtype=np.int64))
    b.endModel()
    return b


def _tf(P):
    return coal.Transform3s(P[:3, :3].copy(), P[:3, 3].copy())


def _coal(ba, Pa, bb, Pb):
    d = coal.distance(ba, _tf(Pa), bb, _tf(Pb), coal.DistanceRequest(), coal.DistanceResult())
    res = coal.CollisionResult()
    coal.collide(ba, _tf(Pa), bb, _tf(Pb), coal.CollisionRequest(), res)
    return d, res.isCollision()


def _touching_offset(ba, Pa, bb, Pb, u, far):
    """Offset along ``u`` where coal goes from collision to separation (within 1e-10)."""
    lo, hi = 0.0, far
    P = Pb.copy()
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        P[:3, 3] = Pa[:3, 3] + mid * u
        if _coal(ba, Pa, bb, P)[1]:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-10:
            break
    return hi


seed = st.integers(0, 2**32 - 1)  # random rotations / directions from a drawn seed (uniform, shrinkable)
relation = st.sampled_from(["touching", "near", "penetrating", "nested", "far"])


def _rot(s):
    return Rotation.random(random_state=np.random.default_rng(s)).as_matrix()


def _unit(s):
    u = np.random.default_rng(s).normal(size=3)
    return u / np.linalg.norm(u)


def _pose_pair(sa, sb, qa, qb, u, rel, frac):
    _, _, ta, ba, ra = sa
    _, _, tb, bb, rb = sb
    Pa = np.eye(4)
    Pa[:3, :3] = _rot(qa)
    Pa[:3, 3] = [0.1, -0.2, 0.3]
    Pb = np.eye(4)
    Pb[:3, :3] = _rot(qb)
    u = _unit(u)
    if rel == "nested":  # B's frame at a random point well inside A's bounding ball
        Pb[:3, 3] = Pa[:3, 3] + frac * 0.3 * ra * u
        return Pa, Pb
    t0 = _touching_offset(ba, Pa, bb, Pb, u, 2.0 * (ra + rb) + 1.0)
    eps = ta.error_bound + tb.error_bound
    off = {"touching": 0.0, "near": frac * 2 * eps, "penetrating": -frac * 0.5 * min(ra, rb), "far": 5.0 * (ra + rb) * (1 + frac)}[rel]
    Pb[:3, 3] = Pa[:3, 3] + (t0 + off) * u
    return Pa, Pb


def _nested(ma, Pa, mb, Pb):
    """Does a shell of one solid lie inside the other (no surface crossing needed)?"""
    A = ma.copy().apply_transform(Pa)
    B = mb.copy().apply_transform(Pb)
    return bool(A.contains(B.vertices).any() or B.contains(A.vertices).any())


def _inside(mesh, P, pts):
    m = mesh.copy()
    m.apply_transform(P)
    return trimesh.proximity.signed_distance(m, pts)  # > 0 inside


@settings(max_examples=400 if FULL else 40, deadline=None, derandomize=not FULL,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(ia=st.integers(0, len(POOL) - 1), ib=st.integers(0, len(POOL) - 1), qa=seed, qb=seed, u=seed, rel=relation,
       frac=st.floats(0.05, 1.0, allow_nan=False), warm=seed)
def test_every_query_against_coal(ia, ib, qa, qb, u, rel, frac, warm):
    sa, sb = _shape(ia), _shape(ib)
    _, ma, ta, ba, _ = sa
    _, mb, tb, bb, _ = sb
    Pa, Pb = _pose_pair(sa, sb, qa, qb, u, rel, frac)
    dc, coll = _coal(ba, Pa, bb, Pb)
    # coal collides surfaces: a shell wholly inside the other solid is "apart" for it, yet the
    # solids overlap (true distance 0), which is what inner spheres see
    if not coll and _nested(ma, Pa, mb, Pb):
        dc, coll = 0.0, True
        event("nested without surface contact (solids overlap, coal's surfaces apart)")
    truth = max(dc, 0.0)
    scale = 1.0  # the pool's shapes are unit-sized: float tolerance in absolute terms
    q = Query(ta, tb, max_contacts=6)
    # distance: plain from the roots, and backtracking from another pose's leaf pair
    r = q.distance(Pa, Pb, method="distance")
    Pw = Pb.copy()
    Pw[:3, :3] = _rot(warm)
    q.distance(Pa, Pw, method="backtracking")
    rb = q.distance(Pa, Pb, method="backtracking")
    assert rb.distance == pytest.approx(r.distance, abs=1e-12)
    event(f"{rel}: {'overlap' if r.colliding else 'apart'}, coal {'collides' if coll else 'apart'}")
    assert truth <= r.distance + TOL * scale, f"{rel}: IST {r.distance} below coal {truth}"
    assert r.distance <= truth + r.error_bound + TOL * scale, f"{rel}: IST {r.distance} above coal {truth} + ε {r.error_bound}"
    if r.colliding:
        assert coll or truth <= TOL * scale, f"{rel}: spheres overlap but coal sees {truth}"
    else:
        assert np.linalg.norm(r.point_b - r.point_a) == pytest.approx(r.distance, abs=1e-9)
    # motion-bound skip, coming from a far pose: never hides a collision; its interval stays true
    qs = Query(ta, tb)
    Pf = Pb.copy()
    Pf[:3, 3] += 10.0 * _unit(u)
    qs.distance(Pa, Pf, skip=True)
    rs = qs.distance(Pa, Pb, skip=True)
    if rs.skipped:
        assert not coll
    assert truth <= rs.distance + TOL and rs.distance - rs.error_bound <= truth + TOL
    # contacts: exactly when the spheres overlap; inside both meshes up to each ε; unit normals
    c = q.contacts(Pa, Pb, split_depth=2)
    assert (c.count > 0) == r.colliding
    if c.count:
        assert np.allclose(np.linalg.norm(c.normals, axis=1), 1.0)
        assert (c.depths >= 0).all() and c.depths[0] == pytest.approx(c.depths.max())
        assert (_inside(ma, Pa, c.positions) >= -ta.error_bound - TOL).all()
        assert (_inside(mb, Pb, c.positions) >= -tb.error_bound - TOL).all()
        assert len({tuple(g) for g in c.groups}) == c.count  # spread: one per subtree pair
    # penetration volume: zero apart, positive only with overlap, never above the smaller solid
    v = q.penetration_volume(Pa, Pb)
    assert (v.volume > 0) == r.colliding
    assert v.volume <= min(ma.volume, mb.volume) * (1 + 1e-9)
    if v.volume > 0:
        assert np.linalg.norm(v.force_direction) == pytest.approx(1.0)


# --- awkward geometry: thin walls, needle-like teeth, sliver triangles --------------------------------
def _slivers(m, t=1e-7):
    """Split every face by a point ``t`` (relative) from its first corner: two slivers per face."""
    V = np.asarray(m.vertices, float)
    F = np.asarray(m.faces)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    p = a + t * (b - a) + t * (c - a)
    k = len(V) + np.arange(len(F))
    faces = np.concatenate([np.stack([F[:, 0], F[:, 1], k], 1), np.stack([F[:, 1], F[:, 2], k], 1),
                            np.stack([F[:, 2], F[:, 0], k], 1)])
    return trimesh.Trimesh(np.concatenate([V, p]), faces, process=False)


AWKWARD = {
    # a 1 mm wall of a 50 mm part (mesh units mm)
    "thin wall": (lambda: trimesh.creation.box(extents=(50.0, 30.0, 1.0)), 0.3),
    # a needle-like tooth: 10 mm long, 0.8 mm across, rounded tip
    "needle tooth": (lambda: trimesh.creation.capsule(height=10.0, radius=0.4, count=[24, 24]), 0.1),
    # a conical canine with a sharp tip (1:6)
    "sharp cusp": (lambda: trimesh.creation.cone(radius=1.0, height=6.0, sections=32), 0.2),
    # every triangle split into two slivers of relative width 1e-7
    "sliver triangles": (lambda: _slivers(trimesh.creation.icosphere(2, radius=5.0)), 0.3),
}


@pytest.mark.parametrize("name", list(AWKWARD))
def test_awkward_geometry_builds_a_sound_tree(name):
    make, err = AWKWARD[name]
    m = make()
    if name == "sliver triangles":
        assert m.area_faces.min() < 1e-9 * m.area  # the slivers are really there
    t = mjist.build(m, max_error=err)
    assert t.error_bound <= err * (1 + 1e-9)
    # every leaf inside the mesh
    sd = trimesh.proximity.signed_distance(m, t.leaf_centers)
    assert (sd >= t.leaf_radii - 1e-9 * float(m.scale)).all()
    # ε holds on random surface points (brute-force distance to the union)
    pts, _ = trimesh.sample.sample_surface(m, 3000, seed=1)
    assert gaps_to_union(pts, t.leaf_centers, t.leaf_radii).max() <= t.error_bound + 1e-9
    # a probe sphere brought to the part from several sides: interval vs coal
    probe = trimesh.creation.icosphere(2, radius=0.5 * float(np.min(m.extents)) + 0.5)
    tp = mjist.build(probe, max_error=0.1 * float(np.min(probe.extents)))
    bm, bp = _bvh(m), _bvh(probe)
    q = Query(t, tp)
    rng = np.random.default_rng(3)
    I = np.eye(4)
    hits = 0
    for _ in range(24):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        P = np.eye(4)
        t0 = _touching_offset(bm, I, bp, P, u, float(np.linalg.norm(m.extents)) * 2)
        for off in (-0.2, 0.0, 0.05, 0.5):
            P[:3, 3] = (t0 + off * t.error_bound * 4) * u
            dc, coll = _coal(bm, I, bp, P)
            r = q.distance(I, P)
            assert max(dc, 0.0) <= r.distance + 1e-9 and r.distance <= max(dc, 0.0) + r.error_bound + 1e-9
            if r.colliding:
                hits += 1
                assert coll
    assert hits > 0


def test_a_solid_wholly_inside_another_overlaps():
    """Deeply nested: a ball wholly inside a box. coal's mesh distance measures the surfaces (apart),
    the inner spheres measure the solids: overlap, contacts, and a penetration volume close to the
    ball's covered volume."""
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    ball = trimesh.creation.icosphere(3, radius=0.3)
    ta, tb = mjist.build(box, max_error=0.05), mjist.build(ball, max_error=0.02)
    q = Query(ta, tb)
    I = np.eye(4)
    P = np.eye(4)
    P[:3, 3] = [0.2, -0.1, 0.3]
    bb, bx = _bvh(ball), _bvh(box)
    d, coll = _coal(bx, I, bb, P)
    assert d > 0.3 and not coll  # coal: the surfaces are apart
    assert _nested(box, I, ball, P)
    r = q.distance(I, P)
    assert r.colliding and r.distance == 0.0
    assert q.contacts(I, P).count > 0
    v = q.penetration_volume(I, P).volume
    # the box's largest leaf (its inscribed ball, radius ~1) holds the whole ball: every ball leaf's
    # lens with it is the leaf itself, so the volume is the ball's covered volume
    assert ta.leaf_radii.max() > np.linalg.norm(P[:3, 3]) + 0.3
    assert v == pytest.approx(tb.coverage * ball.volume, rel=1e-9)
