"""The bundled procedural jaws: regenerated here, closed, ~100k vertices, 14 crowns each, and
touching (not interpenetrating) in the stored ground-truth occlusion."""
import json

import numpy as np
import pytest
import trimesh
from conftest import ROOT

import mjist
from mjist.jaw import generator as jawmodel
from mjist.jaw import pair as jaw

MODELS = ROOT / "models"


@pytest.fixture(scope="module")
def generated():
    """The committed jaws (the slow test proves a regeneration gives them) and the design's data."""
    maxilla = trimesh.load(MODELS / "maxilla.obj", force="mesh")
    mandible = trimesh.load(MODELS / "mandible.obj", force="mesh")
    return maxilla, mandible, jawmodel.metadata()


def test_coarse_regeneration_is_closed_with_the_designed_shells():
    """The generator end to end at a coarse lattice (the full one is the slow test below)."""
    maxilla, mandible, meta = jawmodel.generate(spacing=1.5)
    for m, shells in ((maxilla, 3), (mandible, 1)):
        mesh = mjist.load_mesh((m.vertices, m.faces))  # raises unless closed, wound, non-degenerate
        assert mesh.shells == shells
        assert 5_000 <= len(mesh.vertices) <= 30_000
    stored = json.loads((MODELS / "occlusion.json").read_text())
    assert stored["hinge"] == pytest.approx(meta["hinge"])
    assert meta == jawmodel.metadata(1.5)


@pytest.mark.slow
def test_regenerated_models_are_closed_and_match_the_committed_files():
    maxilla, mandible, meta = jawmodel.generate()
    for name, m, shells in (("maxilla", maxilla, 3), ("mandible", mandible, 1)):
        mesh = mjist.load_mesh((m.vertices, m.faces))  # raises unless closed, wound, non-degenerate
        assert mesh.shells == shells  # maxilla: arch + two glenoid fossae
        assert 80_000 <= len(mesh.vertices) <= 140_000
        committed = mjist.load_mesh(MODELS / f"{name}.obj")
        assert len(committed.vertices) == len(mesh.vertices)
        assert abs(committed.volume - mesh.volume) <= 1e-6 * mesh.volume
        assert np.allclose(np.sort(committed.vertices, axis=0), np.sort(mesh.vertices, axis=0), atol=2e-9)
    stored = json.loads((MODELS / "occlusion.json").read_text())
    assert stored["hinge"] == pytest.approx(meta["hinge"])
    assert stored["vertices"] == {"maxilla": len(maxilla.vertices), "mandible": len(mandible.vertices)}


def _crowns(mesh, y):
    """Closed section loops at height y whose centre is on the dental arch (not the rami)."""
    sec = mesh.section(plane_origin=[0.0, y, 0.0], plane_normal=[0.0, 1.0, 0.0])
    return [p for p in sec.discrete if p[:, 2].mean() > -0.008]


def test_fourteen_crowns_per_jaw_of_plausible_size(generated):
    maxilla, mandible, _ = generated
    low = _crowns(mandible, -0.003)
    up = _crowns(maxilla, 0.003)
    assert len(low) == 14 and len(up) == 14
    for loops in (low, up):
        widths = [np.ptp(p[:, [0, 2]], axis=0).max() for p in loops]
        assert 0.004 <= min(widths) and max(widths) <= 0.013  # crowns ~5-11 mm
    arch = np.vstack(up)
    assert 0.045 <= np.ptp(arch[:, 0]) <= 0.070  # arch width ~50-60 mm


def test_ground_truth_pose_touches_and_one_millimetre_opening_separates(generated):
    maxilla, mandible, meta = generated
    bx = jaw.coal_bvh(maxilla.vertices, maxilla.faces)
    bd = jaw.coal_bvh(mandible.vertices, mandible.faces)
    I = np.eye(4)
    stored = json.loads((MODELS / "occlusion.json").read_text())
    P = np.array(stored["mandible_pose"])
    d = jaw.coal_distance(bx, I, bd, P)
    assert d <= 1e-5  # touching: within 10 µm
    assert not jaw.coal_collides(bx, I, bd, P) or _max_depth(bx, bd, P) <= 2e-5  # no deep overlap
    # 0.1 mm further closed they do interpenetrate: the contact is real, not a distant gap
    Q = P.copy()
    Q[1, 3] += 1e-4
    assert jaw.coal_collides(bx, I, bd, Q)
    # 1 mm of opening (straight down, or about the hinge at the incisors) separates them
    Q = P.copy()
    Q[1, 3] -= 1e-3
    assert jaw.coal_distance(bx, I, bd, Q) > 3e-4
    hinge = np.array(meta["hinge"])
    theta = 1e-3 / (0.040 - hinge[2])  # 1 mm at the incisors (z = 40 mm)
    assert jaw.coal_distance(bx, I, bd, jaw.hinge_pose(theta, hinge) @ P) > 1e-4
    # and the condyles stay clear of their fossae while the jaw opens 10 degrees
    assert jaw.coal_distance(bx, I, bd, jaw.hinge_pose(np.radians(10), hinge) @ P) > 1e-4


def _max_depth(bx, bd, P):
    import coal

    req = coal.CollisionRequest()
    req.enable_contact = True
    req.num_max_contacts = 1000
    res = coal.CollisionResult()
    coal.collide(bx, jaw.coal_transform(np.eye(4)), bd, jaw.coal_transform(P), req, res)
    return max(res.getContact(i).penetration_depth for i in range(res.numContacts()))


def test_designed_contacts_lie_on_both_jaws(generated):
    maxilla, mandible, meta = generated
    C = np.array(meta["designed_contacts"])
    assert len(C) >= 20
    for m in (maxilla, mandible):
        _, dist, _ = trimesh.proximity.closest_point(m, C)
        assert np.median(dist) <= 1e-4 and dist.max() <= 3e-4


def test_load_pair_from_a_folder_without_pose_finds_first_touch(tmp_path):
    d = jaw.BUNDLED
    for name in ("maxilla", "mandible"):
        (tmp_path / f"{name}.obj").write_bytes((d / f"{name}.obj").read_bytes())
    _, _, info = jaw.load_pair(tmp_path)
    assert info["source"] == "coal first touch"
    assert abs(info["mandible_pose"][1, 3]) <= 2e-5  # the design pose already touches
    assert info["hinge"][1] > 0.02  # condyles found above the occlusal plane
    with pytest.raises(FileNotFoundError, match="maxilla"):
        jaw.load_pair(tmp_path / "nowhere")


@pytest.mark.parametrize("anatomy", [
    jawmodel.Anatomy(arch_width=1.08, arch_depth=0.92, tooth_size=1.06, class_shift=3.0),
    jawmodel.Anatomy(arch_width=0.92, tooth_size=0.94, crowding=1.2, class_shift=-3.0, crossbite="left",
                     missing=(("mandible", "right", 5),)),
], ids=["wide-class-II", "narrow-class-III-crossbite-missing"])
def test_other_patients_touch_in_their_design_pose(anatomy):
    """Every anatomy keeps the design's guarantee: closed jaws that touch on both sides and do not
    overlap in the design pose (up to the lattice's discretisation, ~0.1 mm at 1 mm spacing)."""
    maxilla, mandible, meta = jawmodel.generate(spacing=1.0, anatomy=anatomy)
    for m in (maxilla, mandible):
        mjist.load_mesh((m.vertices, m.faces))
    bx = jaw.coal_bvh(maxilla.vertices, maxilla.faces)
    bd = jaw.coal_bvh(mandible.vertices, mandible.faces)
    assert abs(jaw.touching_offset(bx, bd)) <= 1.5e-4
    P = np.eye(4)
    P[1, 3] = -1e-3
    assert jaw.coal_distance(bx, np.eye(4), bd, P) > 3e-4
    C = np.array(meta["designed_contacts"])
    assert (C[:, 0] > 0).sum() >= 6 and (C[:, 0] < 0).sum() >= 6
    for m in (maxilla, mandible):
        _, dist, _ = trimesh.proximity.closest_point(m, C)
        assert np.median(dist) <= 2e-4
    ivl, _ = jawmodel.tooth_layout(anatomy)
    top = mandible.vertices[mandible.vertices[:, 1] > -0.003]  # crowns above the gingiva
    for t in range(len(jawmodel.KINDS)):  # a crown stands at each tooth's place, except a missing one
        x, z = jawmodel.arch_point(ivl[t].mean(), 0.0, anatomy) * 1e-3
        for side, sign in (("left", 1.0), ("right", -1.0)):
            near = np.hypot(top[:, 0] - sign * x, top[:, 2] - z) < 2e-3
            assert near.any() != (("mandible", side, t) in anatomy.missing), (side, t)
    if anatomy.crossbite == "left":  # the lower buccal cusps stand outside the upper crowns on that side only
        def outermost(V, lo, hi, side):  # largest outward offset from the arch line of second-premolar crown points (mm)
            V = V[(V[:, 1] > lo) & (V[:, 1] < hi) & (np.sign(V[:, 0]) == side)] * 1e3
            s_, v_ = jawmodel.arch_coordinates(V[:, 0], V[:, 2], anatomy)
            return v_[(s_ > ivl[4, 0] + 1) & (s_ < ivl[4, 1] - 1)].max()

        for side, crossed in ((1.0, True), (-1.0, False)):
            upper, lower = outermost(maxilla.vertices, 0.0005, 0.004, side), outermost(mandible.vertices, -0.004, 0.0005, side)
            assert (lower > upper) == crossed, (side, upper, lower)
    with pytest.raises(ValueError, match="crossbite"):
        jawmodel.Anatomy(crossbite="both")
