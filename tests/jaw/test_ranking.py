"""The ranking principle on constructed arches whose answer is known from geometry alone.

Two slabs stand in for the arches: the maxilla's lower face and the mandible's upper face are
the same height field, so the aligned pose interlocks everywhere at zero gap. The judge must
rank, whatever its constants: the aligned pose before a tipped, one-sided one; an interlocked
pose before the same cusps resting on each other; and bring a penetrating pose back to exactly
zero penetration about the hinge.
"""
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from mjist.jaw import ranking
from mjist.jaw.arch import ArchFrame

MM = 1e-3
HINGE = np.array([0.0, 60 * MM, 35 * MM])  # behind (+y) and above the teeth; world +z up, anterior -y
HALF_W, DEPTH, AMP, WAVE = 20 * MM, 40 * MM, 0.5 * MM, 4 * MM


def _heightfield(f, top: bool, n: int = 81) -> trimesh.Trimesh:
    """A closed slab over x in ±HALF_W, y in [-DEPTH, 0]: one face is z = f(x, y), the other flat
    5 mm beyond it (above for the maxilla, ``top=False``; below for the mandible)."""
    x, y = np.meshgrid(np.linspace(-HALF_W, HALF_W, n), np.linspace(-DEPTH, 0.0, n), indexing="ij")
    z = f(x, y)
    far = np.full_like(z, (z.max() + 5 * MM) if not top else (z.min() - 5 * MM))
    V = np.concatenate([np.c_[x.ravel(), y.ravel(), z.ravel()], np.c_[x.ravel(), y.ravel(), far.ravel()]])
    idx = np.arange(n * n).reshape(n, n)
    F = []
    for off in (0, n * n):
        a, b, c, d = idx[:-1, :-1] + off, idx[1:, :-1] + off, idx[1:, 1:] + off, idx[:-1, 1:] + off
        F += [np.c_[a.ravel(), b.ravel(), c.ravel()], np.c_[a.ravel(), c.ravel(), d.ravel()]]
    ring = np.r_[idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]]
    for i in range(len(ring)):
        a, b = ring[i], ring[(i + 1) % len(ring)]
        F += [[[a, b, b + n * n]], [[a, b + n * n, a + n * n]]]
    m = trimesh.Trimesh(V, np.concatenate(F), process=True)
    m.fix_normals()
    assert m.is_watertight and m.volume > 0
    return m


def _surface(x, y):
    return AMP * np.sin(2 * np.pi * x / WAVE)


@pytest.fixture(scope="module")
def sample():
    upper = _heightfield(_surface, top=False)
    lower = _heightfield(_surface, top=True)
    frame = ArchFrame(origin=np.array([0.0, -DEPTH, 0.0]), left=np.array([1.0, 0, 0]), up=np.array([0, 0, 1.0]),
                      anterior=np.array([0, -1.0, 0]), depth=DEPTH, width=2 * HALF_W, plane_tilt_deg=0.0, symmetry_mm=0.0,
                      incisal=np.array([0.0, -DEPTH, 0.0]))
    I = np.eye(4)
    s = ranking.occlusal_sample((upper.vertices, upper.faces), (lower.vertices, lower.faces), I, I, frame, HINGE)
    assert set(s.regions) == set(range(6))
    return s


def _moved(R=np.eye(3), t=(0.0, 0.0, 0.0), about=np.zeros(3)):
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = np.asarray(about) - R @ np.asarray(about) + np.asarray(t)
    return P


def _opened(P, deg=0.5):
    """``P`` turned open about the hinge (touch closes it along the same path)."""
    return _moved(Rotation.from_rotvec(np.radians(deg) * np.array([1.0, 0, 0])).as_matrix(), about=HINGE) @ P


def test_bilateral_beats_tipped_one_sided(sample):
    """Rolled 1° about the arch's long axis, one side touches and the other stays open: it must rank
    below the aligned pose, both brought to touch about the same hinge."""
    aligned = ranking.judge(sample, _opened(np.eye(4)))
    tipped = ranking.judge(sample, _opened(_moved(Rotation.from_rotvec(np.radians(1.0) * np.array([0, 1.0, 0])).as_matrix(),
                                                  about=(0, -DEPTH / 2, 0))))
    assert aligned.interocclusal_mm < 0.01 and aligned.score > tipped.score
    assert tipped.interocclusal_mm > 0.1  # the open side: up to 0.7 mm across 40 mm
    left, right = tipped.region_mm["left-molar"], tipped.region_mm["right-molar"]
    assert max(left, right) > 2 * min(left, right)  # one side open, the other touching
    assert aligned.balance > 0.9


def test_interlocked_beats_cusp_on_cusp(sample):
    """Shifted half a wave sideways the cusps stand on each other and hold the arches 2·AMP apart."""
    inter = ranking.judge(sample, _opened(np.eye(4)))
    cusp = ranking.judge(sample, _opened(_moved(t=(WAVE / 2, 0, 0))))
    assert inter.score > cusp.score
    assert cusp.interocclusal_mm > 0.5 and inter.interocclusal_mm < 0.01


def test_touch_removes_known_penetration_about_the_hinge(sample):
    """Pushed 0.3 mm up into the maxilla, the pose is turned open to exactly zero penetration; apart
    by 1 mm it is turned closed to exactly touching; the turn matches the hinge geometry."""
    for lift in (0.3 * MM, -1.0 * MM):
        P, turn = ranking.touch(sample, _moved(t=(0, 0, lift)))
        a, _, b, _ = ranking.distances(sample, P)
        assert abs(min(a.min(), b.min())) < 1e-8  # 10 nm
        assert np.sign(turn) == np.sign(lift)  # penetrating: opens (positive turn); apart: closes
        # a tooth point rises by its horizontal distance from the hinge times the turn: the lift is
        # taken up between the back of the arch (nearest the hinge) and its front
        assert abs(lift) / (HINGE[1] + DEPTH) * 0.99 < abs(turn) < abs(lift) / HINGE[1] * 1.01
