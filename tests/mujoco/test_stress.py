"""Stress and fault injection: the quick ones run in CI; the long runs (thousands of attach
cycles, extreme mesh units, long chewing) are also marked ``slow`` (``-m slow``), and
``MJIST_STRESS=1`` makes every run its long version."""
import os
import resource

import mujoco
import numpy as np
import pytest
import trimesh
from conftest import ROOT, coal_depth

from mjist.jaw import pair as jawmod
from mjist.mujoco import attach as A
from mjist.mujoco import registry
from mjist.mujoco.scene import geom_pose, geom_pose_at, mesh_of

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
@pytest.mark.slow
def test_thousands_of_attach_detach_cycles(tmp_path, cache):
    """attach/detach again and again: the table comes back to MuJoCo's, memory stays flat."""
    m = mujoco.MjModel.from_xml_string(_box_scene(tmp_path))
    n = 3000 if FULL else 100
    h = A.attach(m, cache_dir=cache)
    h.detach()
    before = _rss_mb()
    d = mujoco.MjData(m)
    for _ in range(n):
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
        true = jawmod.coal_distance(jawmod.coal_bvh(*mesh_of(m2, 0)), geom_pose(d, 0), jawmod.coal_bvh(*mesh_of(m2, 1)), geom_pose(d, 1))
        assert true - 1e-9 <= max(dist, 0.0) <= true + h2.pairs[0].error_bound + 1e-9
        assert h2.trees["a"].num_leaves != n1



@pytest.mark.stress
@pytest.mark.slow
@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_extreme_mesh_units(tmp_path, cache, scale):
    """Millimetre-sized to kilometre-sized scenes: the distance interval holds against coal."""
    m = mujoco.MjModel.from_xml_string(_box_scene(tmp_path, scale))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(5)
    with A.attach(m, cache_dir=cache) as h:
        eps = h.pairs[0].error_bound
        assert eps <= 0.05 * scale
        ba, bb = (jawmod.coal_bvh(*mesh_of(m, g)) for g in (0, 1))
        for _ in range(20 if not FULL else 200):
            d.qpos[:3] = rng.uniform(-1, 1, 3) * scale * np.array([0.6, 0.6, 0.0]) + [0, 0, rng.uniform(0.85, 1.6) * scale]
            d.qpos[3:7] = [1, 0, 0, 0]
            mujoco.mj_forward(m, d)
            true = jawmod.coal_distance(ba, geom_pose(d, 0), bb, geom_pose(d, 1))
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


@pytest.fixture(scope="module")
def haptic_scene(cache):
    from mjist.jaw import haptic

    model, h = A.load_model(ROOT / "models" / "haptic_jaw.xml", cache_dir=cache)
    yield model, h, haptic
    h.detach()


def _straight_path(model, haptic, v, start=-4e-3, stop=2e-3, hold=300):
    """The handle moved straight up (jaw frame) at ``v`` m/s from ``start`` below the occlusion to
    ``stop`` past it, then held: the mandible hits the maxilla at up to ``v``."""
    from scipy.spatial.transform import Rotation

    p0, R0, _, _, R_jaw = haptic._occlusion(model)
    dt = float(model.opt.timestep)
    s = np.concatenate([np.arange(start, stop, v * dt), np.full(hold, stop)])
    x, y, z, w = Rotation.from_matrix(R0).as_quat()
    return haptic.DevicePath(f"straight {v} m/s", p0 + s[:, None] * R_jaw[:, 1], np.tile([w, x, y, z], (len(s), 1)), dt), p0, R_jaw[:, 1]


@pytest.mark.stress
@pytest.mark.parametrize("speed", [0.05, 0.2, 0.5])
def test_handle_speed_does_not_tunnel(haptic_scene, speed):
    """The handle slammed into the teeth at up to 0.5 m/s (0.5 mm per 1 ms step): the mandible stops
    on the maxilla's cusps, its true penetration (coal) stays within the IST depth + ε, then it settles."""
    model, h, haptic = haptic_scene
    path, p0, up = _straight_path(model, haptic, speed)
    log = haptic.run(model, h, path)
    assert haptic.summary(log)["finite"]
    off = (log["mandible_pos"] - p0) @ up  # how far past the designed occlusion, upwards
    assert off.max() < 1.0e-3, f"mandible {off.max() * 1e3:.2f} mm past the occlusion: through the cusps"
    v = np.linalg.norm(np.diff(log["mandible_pos"], axis=0), axis=1) / path.dt
    assert v.max() > 0.8 * speed  # the impact really was at that speed
    # the deepest step, against coal's exact meshes
    gmx, gmd = h.geoms["maxilla"], h.geoms["mandible"]
    bvh = [jawmod.coal_bvh(*mesh_of(model, g)) for g in (gmx, gmd)]
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    Pmx = geom_pose(d, gmx)
    i = int(np.argmax(log["depth"]))
    Pmd = geom_pose_at(model, gmd, log["mandible_pos"][i], log["mandible_quat"][i])
    depth = coal_depth(bvh, Pmx, Pmd)
    assert depth <= log["depth"][i] + h.pairs[0].error_bound and depth < 1.5e-3
    assert log["contacts"][-1] > 0 and v[-50:].max() < 0.05  # resting on the teeth, not bouncing off


def _drifted(path, haptic, amp=0.05):
    """The same device path with the handle quaternion's norm drifting by up to ``amp``
    (a device orientation integrated without renormalisation)."""
    n = path.steps
    k = 1.0 + amp * np.sin(np.linspace(0.0, 7.0, n))
    return haptic.DevicePath(path.name + " (drifting quaternion)", path.pos.copy(), path.quat * k[:, None], path.dt)


@pytest.mark.stress
def test_handle_quaternion_drift_changes_nothing(haptic_scene):
    """A handle quaternion off unit length (±5 %) gives the same coupling and motion as the unit one."""
    model, h, haptic = haptic_scene
    path = haptic.scripted(model, "chewing", 2.0)
    a = haptic.run(model, h, path)
    b = haptic.run(model, h, _drifted(path, haptic))
    # equal up to rounding (a drifted quaternion normalizes to within an ulp of the unit one)
    assert np.abs(a["coupling_force"] - b["coupling_force"]).max() < 1e-6  # N; the forces are ~1 N
    assert np.abs(a["mandible_pos"] - b["mandible_pos"]).max() < 1e-9  # m
    # a zero quaternion (a device glitch) is read as the identity, as MuJoCo does: finite, no raise
    z = haptic.DevicePath("zero quat", path.pos[:50].copy(), np.zeros((50, 4)), path.dt)
    assert haptic.summary(haptic.run(model, h, z))["finite"]


@pytest.mark.stress
@pytest.mark.slow
def test_long_haptic_chewing_has_no_energy_growth(haptic_scene):
    """10⁵ steps (100 s) of chewing cycles in contact with a drifting handle quaternion: finite,
    and the last cycles move and push no harder than the first ones (~6 s of wall time)."""
    model, h, haptic = haptic_scene
    secs = 100.0
    path = _drifted(haptic.scripted(model, "chewing", secs), haptic)
    log = haptic.run(model, h, path)
    s = haptic.summary(log)
    assert s["finite"] and np.all(np.isfinite(log["_data"].qpos)) and s["contact_steps"] > 0.1 * path.steps
    per = int(round(2.0 / path.dt))  # the chewing pattern repeats every 2 s (left, right)
    cycles = path.steps // per
    speed = np.linalg.norm(np.diff(log["mandible_pos"], axis=0), axis=1) / path.dt
    vmax = [speed[c * per:(c + 1) * per - 1].max() for c in range(cycles)]
    fmax = [np.linalg.norm(log["contact_force"][c * per:(c + 1) * per], axis=1).max() for c in range(cycles)]
    assert max(vmax[-3:]) <= 1.05 * max(vmax[1:4]), vmax
    assert max(fmax[-3:]) <= 1.2 * max(fmax[1:4]), fmax


def test_exit_directions_cache_is_content_keyed_and_survives_a_corrupt_file(tmp_path):
    """The leaves' exit directions are stored beside the trees: a second attach of the same tree
    and mesh reads them, a changed tree computes anew, and a damaged file is recomputed."""
    from mjist.cache import cached_exits

    N = np.arange(40, dtype=np.float64).reshape(5, 8)
    V, F = np.eye(3), np.array([[0, 1, 2]])
    calls = []

    def compute():
        calls.append(1)
        return np.full((5, 4), float(len(calls)))

    a = cached_exits(N, V, F, compute, folder=tmp_path)
    b = cached_exits(N, V, F, compute, folder=tmp_path)
    assert len(calls) == 1 and np.array_equal(a, b)
    cached_exits(N + 1.0, V, F, compute, folder=tmp_path)
    assert len(calls) == 2
    for f in tmp_path.glob("*.exits.npy"):
        f.write_bytes(b"not an array")
    c = cached_exits(N, V, F, compute, folder=tmp_path)
    assert len(calls) == 3 and (c == 3.0).all()


@pytest.mark.slow  # 200 processes of about 3 s each
@pytest.mark.stress
def test_two_hundred_fresh_processes_attach_without_a_refusal(tmp_path):
    """Each fresh process lays its heap out anew: the bundled closure scene attaches, steps and
    detaches in 200 of them (two at a time), with no ABI refusal and the same contacts in each."""
    import subprocess
    import sys
    from concurrent.futures import ThreadPoolExecutor

    code = ("import mujoco, mjist\n"
            "from mjist.jaw import BUNDLED\n"
            "m, h = mjist.load_model(str(BUNDLED / 'jaw_closure.xml'), progress=False)\n"
            "d = mujoco.MjData(m)\n"
            "for _ in range(5):\n    mujoco.mj_step(m, d)\n"
            "print('contacts', d.ncon, repr(float(d.qpos[0])))\n"
            "h.detach()\n")
    env = {**os.environ, "MJIST_CACHE": str(tmp_path / "cache")}

    def attach(_):
        p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
        return p.returncode, (p.stdout.strip().splitlines() or [""])[-1], p.stderr.strip()[-400:]

    with ThreadPoolExecutor(2) as pool:
        runs = list(pool.map(attach, range(200)))
    refused = [r for r in runs if r[0] != 0]
    assert not refused, f"{len(refused)} of 200 failed, e.g. {refused[0][2]}"
    assert len({r[1] for r in runs}) == 1, {r[1] for r in runs}  # the same contacts and pose in every process
