"""Stress and fault injection (issue 7, first part): a quick subset runs in CI; ``MJIST_STRESS=1``
(or ``-m stress`` with it) runs the long versions."""
import os
import resource

import mujoco
import numpy as np
import pytest
import trimesh

from mjist import collision_driver as A
from mjist import jaw as jawmod
from mjist import registry

from conftest import ROOT

FULL = os.environ.get("MJIST_STRESS") == "1"
BOX_XML = """
<mujoco>
  <custom><numeric name="mjist_max_error" data="{eps}"/><text name="mjist_offset" data="none"/></custom>
  <asset><mesh name="a" file="{a}"/><mesh name="b" file="{b}"/></asset>
  <worldbody>
    <geom name="a" type="mesh" mesh="a"/>
    <body name="b" pos="0 0 {z}"><freejoint/><geom name="b" type="mesh" mesh="b"/></body>
  </worldbody>
</mujoco>
"""


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _box_scene(tmp_path, scale=1.0, eps=None, shape=(1.0, 1.0, 1.0)):
    a = tmp_path / f"a{scale:g}.obj"
    b = tmp_path / f"b{scale:g}.obj"
    trimesh.creation.box(extents=np.array(shape) * scale).export(a)
    trimesh.creation.icosphere(subdivisions=3, radius=0.4 * scale).export(b)
    return BOX_XML.format(a=a, b=b, z=1.2 * scale, eps=eps if eps is not None else 0.02 * scale)


@pytest.mark.stress
def test_thousands_of_attach_detach_cycles(tmp_path, cache):
    """attach/detach again and again: the table comes back to MuJoCo's, memory stays flat."""
    m = mujoco.MjModel.from_xml_string(_box_scene(tmp_path))
    n = 3000 if FULL else 300
    h = A.attach(m, cache_dir=cache)
    h.detach()
    before = _rss_mb()
    d = mujoco.MjData(m)
    for i in range(n):
        h = A.attach(m, cache_dir=cache)
        mujoco.mj_step(m, d)
        h.detach()
        assert registry.table_is_original() and not registry._ENTRIES
    grown = _rss_mb() - before
    assert grown < 50, f"RSS grew by {grown:.1f} MB over {n} cycles"
    mujoco.mj_step(m, d)  # MuJoCo's own functions again: no crash


@pytest.mark.stress
def test_mesh_changed_since_the_cache_is_rebuilt(tmp_path, cache):
    """A cached tree belongs to its mesh bytes: change the mesh, get a new tree, right distances."""
    xml = _box_scene(tmp_path)
    m1 = mujoco.MjModel.from_xml_string(xml)
    with A.attach(m1, cache_dir=cache) as h1:
        n1 = h1.trees["a"].num_leaves
    # other content under the same file name (in another folder: MuJoCo caches mesh assets by
    # path within a process): a taller box
    (tmp_path / "v2").mkdir()
    trimesh.creation.box(extents=(1.0, 1.0, 1.6)).export(tmp_path / "v2" / "a1.obj")
    m2 = mujoco.MjModel.from_xml_string(xml.replace(str(tmp_path / "a1.obj"), str(tmp_path / "v2" / "a1.obj")))
    with A.attach(m2, cache_dir=cache) as h2:
        assert h2.cache_hits == 1  # the sphere's tree is reused, the box's is rebuilt
        d = mujoco.MjData(m2)
        mujoco.mj_forward(m2, d)
        dist = mujoco.mj_geomDistance(m2, d, 0, 1, 1.0, None)
        # taller box: top at 0.8, ball (radius 0.4) centred at 1.2 -> true gap 0
        true = jawmod.coal_distance(jawmod.coal_bvh(*A.mesh_of(m2, 0)), _pose(d, 0), jawmod.coal_bvh(*A.mesh_of(m2, 1)), _pose(d, 1))
        assert true - 1e-9 <= max(dist, 0.0) <= true + h2.pairs[0].error_bound + 1e-9
        assert h2.trees["a"].num_leaves != n1


def _pose(d, g):
    P = np.eye(4)
    P[:3, :3] = d.geom_xmat[g].reshape(3, 3)
    P[:3, 3] = d.geom_xpos[g]
    return P


@pytest.mark.stress
@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_extreme_mesh_units(tmp_path, cache, scale):
    """Millimetre-sized to kilometre-sized scenes: the distance interval holds against coal."""
    m = mujoco.MjModel.from_xml_string(_box_scene(tmp_path, scale))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(5)
    with A.attach(m, cache_dir=cache) as h:
        eps = h.pairs[0].error_bound
        assert eps <= 0.05 * scale
        ba, bb = (jawmod.coal_bvh(*A.mesh_of(m, g)) for g in (0, 1))
        for _ in range(20 if not FULL else 200):
            d.qpos[:3] = rng.uniform(-1, 1, 3) * scale * np.array([0.6, 0.6, 0.0]) + [0, 0, rng.uniform(0.85, 1.6) * scale]
            d.qpos[3:7] = [1, 0, 0, 0]
            mujoco.mj_forward(m, d)
            true = jawmod.coal_distance(ba, _pose(d, 0), bb, _pose(d, 1))
            dist = mujoco.mj_geomDistance(m, d, 0, 1, 10 * scale, None)
            if dist > 0:
                assert true - 1e-9 * scale <= dist <= true + eps + 1e-9 * scale
            else:
                assert true <= eps + 1e-9 * scale


@pytest.mark.stress
def test_long_jaw_closure_stays_finite_and_shut(cache):
    """Jaw closure for 10 s (CI) / 100 s (MJIST_STRESS=1) of 1 ms steps: no NaN, no drift, no tunnelling."""
    model, h = A.load_model(ROOT / "models" / "jaw_closure.xml", cache_dir=cache)
    try:
        d = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, d, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "open"))
        d.ctrl[:] = 1.0
        n = 100_000 if FULL else 10_000
        hinge = np.empty(n)
        for i in range(n):
            mujoco.mj_step(model, d)
            hinge[i] = d.qpos[0]
        assert np.all(np.isfinite(hinge)) and np.all(np.isfinite(d.qvel))
        tail = np.degrees(hinge[n // 2:])
        assert np.ptp(tail) < 0.05  # clenched and still: no creep, no oscillation
        assert -1.0 < tail[-1] < 1.0  # on the teeth, not through them
        assert h.stats()["failed"] == 0 and h.stats()["bad_pose"] == 0
    finally:
        h.detach()
