"""``mjist_narrowphase='surface'``: the IST finds the contact groups, the meshes give distance,
point and normal. Checked against exact geometry (flat tooth tips), coal and winding numbers on the
bundled jaws, rollout determinism, and the jaw closure's rest against the designed occlusion."""
import mujoco
import numpy as np
import pytest
import trimesh
from conftest import ROOT, load_script, shared_path, winding_numbers

from mjist.errors import ConfigError
from mjist.jaw import pair as jawmod
from mjist.mujoco import attach as A
from mjist.mujoco import config
from mjist.mujoco.scene import geom_pose, mesh_of

SCENE = ROOT / "models" / "jaw_closure.xml"
# docs/mujoco.md's measured bound on a separated pair's surface distance above coal's (metres):
# the descents stop in local minima of the meshes' distance
STATED_ERROR = 8e-5

COMB_XML = """
<mujoco>
  <option timestep="0.001" gravity="0 0 -9.81"/>
  <custom>
    <numeric name="mjist_max_error" data="0.0004"/>
    <text name="mjist_narrowphase" data="surface"/>
    {extra}
  </custom>
  <default><geom solref="0.003 1"/></default>
  <asset><mesh name="comb" file="{comb}"/></asset>
  <worldbody>
    <geom name="lower" type="mesh" mesh="comb"/>
    <body name="upper" euler="0 180 0">
      <freejoint/>
      <geom name="upper" type="mesh" mesh="comb"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def comb_file(tmp_path_factory):
    """Four 4 x 10 mm teeth, 12 mm tall, 6 mm apart, on a 6 mm base (metres, centred: base
    z -9..-3 mm, flat tips at +9, teeth at x ±(3..7) and ±(13..17) with 45° chamfered edges)."""
    occ = np.zeros((34 + 2, 12, 20), bool)
    occ[1:35, 1:11, 1:7] = True
    for i in range(4):
        occ[1 + 10 * i:5 + 10 * i, 1:11, 7:19] = True
    m = trimesh.voxel.VoxelGrid(occ).marching_cubes
    m.apply_scale(0.001)
    m.apply_translation(-m.bounds.mean(axis=0))
    p = tmp_path_factory.mktemp("comb") / "comb.obj"
    m.export(p)
    return str(p)


def _comb_model(comb_file, extra=""):
    return mujoco.MjModel.from_xml_string(COMB_XML.format(comb=comb_file, extra=extra))


def test_setting_is_checked_and_sets_its_defaults(comb_file, cache):
    m = _comb_model(comb_file)
    cfg = config.read_config(m)
    assert cfg.narrowphase == "surface" and cfg.surface_groups == 8 and cfg.candidates == 256
    with pytest.raises(ConfigError, match="mjist_surface_groups"):
        config.read_config(m, surface_groups=300)
    with pytest.raises(ConfigError, match="'spheres'.*'surface'"):
        A.attach(mujoco.MjModel.from_xml_string(
            COMB_XML.format(comb=comb_file, extra="").replace('data="surface"', 'data="triangles"')), cache_dir=cache)
    with pytest.raises(ConfigError, match="depths, not volumes"):
        A.attach(m, mode="penalty", penalty="volume", cache_dir=cache)
    assert config.read_config(m, mode="penalty").narrowphase == "surface"  # the contacts law takes surface depths


def test_flat_tips_give_the_exact_depth(comb_file, cache):
    """Tooth tips 0.5 mm into each other: every contact has the true depth and a vertical normal,
    where the spheres' depths are off by up to ε1+ε2 (0.8 mm here)."""
    m = _comb_model(comb_file)
    d = mujoco.MjData(m)
    with A.attach(m, cache_dir=cache) as h:
        assert h.surfaces and h.stats()["surface_groups"] == 0
        d.qpos[:3] = [0.0, 0.0, 0.0175]  # the flipped comb's tips at 8.5 mm, 0.5 mm into the lower's
        d.qpos[3:7] = [0, 0, 1, 0]
        mujoco.mj_forward(m, d)
        assert d.ncon > 0 and h.stats()["surface_groups"] > 0
        for c in d.contact[:d.ncon]:
            sign = 1 if c.geom[0] == 0 else -1  # as lower -> upper
            assert c.dist == pytest.approx(-0.0005, abs=1e-6)
            assert sign * c.frame[2] == pytest.approx(1.0, abs=1e-6)
            assert c.pos[2] == pytest.approx(0.00875, abs=1e-6)  # halfway between the tip faces
        assert h.stats()["failed"] == 0


def test_held_contacts_follow_the_pose_exactly_on_flat_tips(comb_file, cache):
    """A pose within the hold moves the measured contacts with B instead of measuring again:
    on flat tips that is exact (depth and point), and ``mjist_surface_hold`` 0 measures instead."""
    with pytest.raises(ConfigError, match="mjist_surface_hold"):
        config.read_config(_comb_model(comb_file), surface_hold=-1e-6)
    answers = {}
    for hold in (None, 0.0):
        m = _comb_model(comb_file)
        d = mujoco.MjData(m)
        with A.attach(m, cache_dir=cache, surface_hold=hold) as h:
            d.qpos[3:7] = [0, 0, 1, 0]
            rows = []
            for dz in (0.0, 1e-6, 2.5e-6):  # 0.5 mm into the lower tips, then 1 and 2.5 µm deeper
                d.qpos[:3] = [0.0, 0.0, 0.0175 - dz]
                mujoco.mj_forward(m, d)
                rows.append(sorted((round(c.dist, 12), *np.round(c.pos, 12)) for c in d.contact[:d.ncon]))
            answers[hold] = rows, h.stats()["held_calls"]
    (held, nheld), (measured, nmeasured) = answers[None], answers[0.0]
    assert nheld == 2 and nmeasured == 0  # the hold here: 0.5 % of ε1+ε2 = 4 µm
    for a, b, dz in zip(held, measured, (0.0, 1e-6, 2.5e-6)):
        assert len(a) == len(b) > 0
        a, b = np.array(a), np.array(b)
        # depth and height exact; along the flat faces any point of the overlap is as deep, and a
        # measurement may end at another one than the held contact moved with B
        assert np.allclose(a[:, [0, 3]], b[:, [0, 3]], rtol=0, atol=1e-7)
        assert np.allclose(a[:, 1:3], b[:, 1:3], rtol=0, atol=1e-5)
        assert all(r[0] == pytest.approx(-0.0005 - dz, abs=1e-8) for r in a)  # the float32 mesh: nm


@pytest.mark.shared
def test_cbct_slide_at_mujocos_defaults_settles_on_the_true_surfaces():
    """The shared CBCT mandible pushed up a slide into its maxilla (``scripts/bench_slide.py``) at
    MuJoCo's default timestep, solref and solimp, default trees: surface contacts come to rest
    (below 0.1 mm/s) within 1.5 s, 0.016 mm past coal's first touch (the default soft contacts'
    sink under the push, most of it carried by one contact), where sphere contacts rest 0.29 mm
    short and MuJoCo's mesh-SDF 0.8 mm past; the surface contacts measured on every call (no hold)
    cost over 100× as much per step."""
    shared_path("jaw", "maxilla.obj")
    slide = load_script("scripts", "bench_slide.py")
    touch, coal = slide.first_touch(slide.SHARED)
    r = slide.run(slide.SHARED, "surface", None, 750, touch, coal, defaults=True)
    assert r["timestep_s"] == 0.002
    assert r["settled_s"] is not None and r["settled_s"] < 1.5
    assert abs(r["rest_past_first_touch_mm"]) < 0.02
    assert r["hook"]["held_calls"] > 500 and r["hook"]["failed"] == 0


def test_rollout_with_two_threads_is_bit_identical_to_serial(comb_file, cache):
    m = _comb_model(comb_file)
    with A.attach(m, cache_dir=cache) as h:
        d = mujoco.MjData(m)
        rng = np.random.default_rng(5)
        states = []
        for _ in range(4):
            # teeth in the gaps, 2.5 mm above resting on tips and base faces at z = 6 mm
            d.qpos[:3] = [0.005 + rng.uniform(-5e-4, 5e-4), 0.0, 0.0085]
            d.qpos[3:7] = [0, 0, 1, 0]
            d.qvel[:] = rng.normal(0, 0.02, m.nv)
            s = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS))
            mujoco.mj_getState(m, d, s, mujoco.mjtState.mjSTATE_FULLPHYSICS)
            states.append(s)
        from mujoco import rollout

        x0 = np.array(states)
        serial, _ = rollout.rollout(m, mujoco.MjData(m), x0, nstep=200)
        par, _ = rollout.rollout(m, [mujoco.MjData(m), mujoco.MjData(m)], x0, nstep=200)
        assert h.stats()["surface_groups"] > 0 and h.stats()["failed"] == 0
    assert np.array_equal(serial, par)
    assert np.all(np.abs(serial[:, -1, 3] - 0.006) < 0.0002)  # at rest on the true faces


def _point_distance(bvh, pose, x):
    """coal's exact distance from a world point to a posed mesh (trimesh's closest point
    misses the nearest face on these meshes by up to 20 µm)."""
    import coal

    tf = coal.Transform3s()
    tf.setTranslation(pose[:3, :3].T @ (np.asarray(x, float) - pose[:3, 3]))
    return coal.distance(bvh, coal.Transform3s(), coal.Sphere(1e-12), tf, coal.DistanceRequest(),
                         coal.DistanceResult()) + 1e-12


def _exact_behind(bvh, P, on, into, y, dist):
    """``y`` lies on geom ``on`` and inside geom ``into`` by exactly ``-dist`` (coal)."""
    return (_point_distance(bvh[on], P[on], y) < 1e-9
            and abs(_point_distance(bvh[into], P[into], y) + dist) < 1e-9)


def _check_poses(cache, n, seed):
    """Bundled jaws, default trees, ``n`` poses around the occlusion: separated ⇒ no contact and
    the distance within the stated error above coal's; colliding ⇒ a contact; every contact's
    point of the second mesh lies on it, inside the first by exactly the contact's depth (coal's
    point distances; winding numbers for the side of the deepest). A colliding pose without a
    contact is a graze the descents missed: its distance must be within the stated error of 0.
    Returns (touching, separated, missed)."""
    model, h = A.load_model(SCENE, cache_dir=cache, narrowphase="surface")
    try:
        gmx, gmd = h.geoms["maxilla"], h.geoms["mandible"]
        meshes = {g: mesh_of(model, g) for g in (gmx, gmd)}
        bvh = {g: jawmod.coal_bvh(*mesh_of(model, g)) for g in (gmx, gmd)}
        d = mujoco.MjData(model)
        occ = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "occlusion")
        rng = np.random.default_rng(seed)
        touching = separated = missed = 0
        for _ in range(n):
            mujoco.mj_resetDataKeyframe(model, d, occ)
            d.qpos[:3] += [np.radians(rng.uniform(-0.3, 0.6)), rng.uniform(-3e-4, 3e-4), rng.uniform(-3e-4, 3e-4)]
            mujoco.mj_forward(model, d)
            P = {gmx: geom_pose(d, gmx), gmd: geom_pose(d, gmd)}
            true_d = jawmod.coal_distance(bvh[gmx], P[gmx], bvh[gmd], P[gmd])
            hit = jawmod.coal_collides(bvh[gmx], P[gmx], bvh[gmd], P[gmd])
            cons = [c for c in d.contact[:d.ncon] if {int(c.geom1), int(c.geom2)} == {gmx, gmd}]
            assert len(cons) <= h.pairs[0].cap
            if not hit:
                separated += 1
                assert not cons
                dist = mujoco.mj_geomDistance(model, d, gmx, gmd, 0.05, None)
                assert true_d - 1e-9 <= dist <= true_d + STATED_ERROR
                continue
            touching += 1
            if not cons:
                missed += 1
                assert mujoco.mj_geomDistance(model, d, gmx, gmd, 0.05, None) <= STATED_ERROR
            for j, c in enumerate(cons):
                ga, gb = int(c.geom[0]), int(c.geom[1])
                # a point of one surface inside the other by exactly the depth: geom2's point
                # (measured into geom1) or geom1's (measured into geom2), half the depth from pos
                yb = np.array(c.pos) + 0.5 * c.dist * np.array(c.frame[:3])
                ya = np.array(c.pos) - 0.5 * c.dist * np.array(c.frame[:3])
                on, into, y = (gb, ga, yb) if _exact_behind(bvh, P, gb, ga, yb, c.dist) else (ga, gb, ya)
                assert _exact_behind(bvh, P, on, into, y, c.dist)
                if j == 0:
                    la = P[into][:3, :3].T @ (y - P[into][:3, 3])
                    assert winding_numbers(la[None], *meshes[into])[0] > 0.5  # inside the other mesh
        assert h.stats()["failed"] == 0
        return touching, separated, missed
    finally:
        h.detach()


def test_jaw_contacts_against_coal_at_poses(cache):
    touching, separated, missed = _check_poses(cache, 12, seed=11)
    assert touching >= 3 and separated >= 3 and missed == 0


@pytest.mark.slow
def test_jaw_contacts_against_coal_at_many_poses(cache):
    touching, separated, missed = _check_poses(cache, 80, seed=12)
    assert touching >= 20 and separated >= 20 and missed <= touching // 10


def test_jaw_closure_rests_on_the_true_surfaces(cache):
    """Default trees (ε1+ε2 = 1 mm): the muscles close the jaw onto the teeth within 0.02 mm of
    the true surfaces and 0.05° of the designed hinge angle (spheres: +0.35°, 0.19 mm gap), and
    it comes to rest within 1 s: held contacts, measured again from their own points (each its
    own way) when the pose leaves the hold (measured on every call it wanders by 0.05°,
    docs/mujoco.md)."""
    from mjist.jaw.demo import run_closure

    model, h = A.load_model(SCENE, cache_dir=cache, narrowphase="surface")
    try:
        res = run_closure(model, seconds=1.0, handle=h)
    finally:
        h.detach()
    assert res["error_bound_mm"] == pytest.approx(1.0, rel=0.01)
    assert abs(res["final_hinge_deg"]) < 0.05 and res["settled"]
    assert res["final_contacts"] >= 1 and max(res["final_contact_depths_mm"]) < 0.02
    assert res["hook"]["held_calls"] > res["steps"] // 3  # at rest the contacts are held, not measured
    assert res["true_distance_mm"] < 0.02
    assert res["hook"]["failed"] == 0


SLAB_XML = """
<mujoco>
  <custom><text name="mjist_narrowphase" data="surface"/></custom>
  <asset><mesh name="slab" file="{slab}"/><mesh name="ball" file="{ball}"/></asset>
  <worldbody>
    <geom name="slab" type="mesh" mesh="slab"/>
    <body name="ball"><freejoint/><geom name="ball" type="mesh" mesh="ball"/></body>
  </worldbody>
</mujoco>
"""


def test_a_ball_pressed_past_a_walls_middle_is_pushed_back_the_way_it_came(tmp_path, cache):
    """A 10 mm ball pressed into a 6 mm slab from above, 2 mm deep, then step by step to 4.5 mm
    (its lowest point past the slab's middle, nearer the underside): the contacts keep pushing
    it up, as deep as its lowest point is below the top face, spread over where it overlaps.
    B's points' own signed distances level off at the slab's middle (3 mm) there, and the
    lowest point's says 1.5 mm, downwards."""
    trimesh.creation.box((0.06, 0.06, 0.006)).export(tmp_path / "slab.obj")  # top face z = 3 mm
    trimesh.creation.icosphere(4, radius=0.005).export(tmp_path / "ball.obj")
    xml = SLAB_XML.format(slab=tmp_path / "slab.obj", ball=tmp_path / "ball.obj")
    m = mujoco.MjModel.from_xml_string(xml)
    with A.attach(m, cache_dir=cache):
        d = mujoco.MjData(m)
        for depth in (0.002, 0.003, 0.0035, 0.004, 0.0045):
            d.time += 0.002  # steps of a trajectory: a pose set by hand at the same time has no side
            d.qpos[:3] = [0.0, 0.0, 0.003 + 0.005 - depth]
            d.qpos[3:7] = [1, 0, 0, 0]
            mujoco.mj_forward(m, d)
            rows = [(c.dist, c.frame[2], *c.pos) for c in d.contact[:d.ncon]]
            assert rows and all(nz > 0.99 for _, nz, *_ in rows), (depth, rows)
            assert min(r[0] for r in rows) == pytest.approx(-depth, abs=5e-5), (depth, rows)
    spread = np.ptp(np.array([r[2:4] for r in rows]), axis=0)
    assert len(rows) > 1 and spread.max() > 0.002  # not all at the lowest point
