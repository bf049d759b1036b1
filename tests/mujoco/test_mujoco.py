"""The MuJoCo hook: IST contacts inside plain mj_step / mj_geomDistance / rollout, against coal."""
import warnings
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest
import trimesh
from conftest import ROOT
from numba import cfunc, types
from scipy.spatial.transform import Rotation

import mjist
from mjist.errors import ConfigError
from mjist.jaw import pair as jawmod
from mjist.mujoco import abi as mjabi
from mjist.mujoco import attach as A
from mjist.mujoco import config, registry
from mjist.mujoco.scene import geom_pose, mesh_of

PITCH = 0.001  # 1 mm voxels


def _comb(teeth=4, tooth=(4, 12), gap=6, base=6, depth=10):
    """A comb (metres) from a voxel occupancy, surfaced by marching cubes: watertight, non-convex."""
    w = teeth * tooth[0] + (teeth - 1) * gap
    occ = np.zeros((w + 2, depth + 2, base + tooth[1] + 2), bool)
    occ[1:w + 1, 1:depth + 1, 1:base + 1] = True
    for i in range(teeth):
        x = 1 + i * (tooth[0] + gap)
        occ[x:x + tooth[0], 1:depth + 1, base + 1:base + tooth[1] + 1] = True
    m = trimesh.voxel.VoxelGrid(occ).marching_cubes
    m.apply_scale(PITCH)
    m.apply_translation(-m.bounds.mean(axis=0))
    return m


COMB_XML = """
<mujoco>
  <option timestep="0.001"/>
  <custom>
    <text name="mjist_offset" data="none"/>
    <numeric name="mjist_max_error" data="0.0004"/>
    {extra}
  </custom>
  <default><geom solref="0.003 1"/></default>
  <asset>
    <mesh name="comb" file="{comb}"/>
  </asset>
  <worldbody>
    <geom name="lower" type="{gtype}" mesh="comb"/>
    <body name="upper" pos="0 0 0" euler="0 180 0">
      <freejoint/>
      <geom name="upper" type="{gtype}" mesh="comb"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def comb_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("comb") / "comb.obj"
    _comb().export(p)
    return str(p)


def _model(comb_file, gtype="mesh", extra=""):
    return mujoco.MjModel.from_xml_string(COMB_XML.format(comb=comb_file, gtype=gtype, extra=extra))


def _interlocked(m, d, gap_z=0.0, shift_x=0.0):
    """Upper comb flipped over the lower one, its teeth in the lower's gaps.

    Lower comb: base z -9..-3 mm, teeth -3..+9, teeth at x ±(3..7), ±(13..17). The flipped
    upper at height z0 has its teeth down to z0 - 9; shifted 5 mm in x they sit in the gaps
    with 1 mm on each side, and z0 = 7.5 mm leaves 1.5 mm above and below (gap_z adds to it).
    """
    d.qpos[:3] = [0.005 + shift_x, 0.0, 0.0075 + gap_z]
    d.qpos[3:7] = [0, 0, 1, 0]  # 180° about y (the body's own euler is composed on top)
    mujoco.mj_forward(m, d)



def _coal_pair(m, d):
    ba = jawmod.coal_bvh(*mesh_of(m, 0))
    bb = jawmod.coal_bvh(*mesh_of(m, 1))
    return jawmod.coal_distance(ba, geom_pose(d, 0), bb, geom_pose(d, 1)), jawmod.coal_collides(ba, geom_pose(d, 0), bb, geom_pose(d, 1))


def test_attach_detach_restores_the_table(comb_file, cache):
    m = _model(comb_file)
    assert registry.table_is_original()
    h = A.attach(m, cache_dir=cache)
    table = mjabi.collision_table()
    idx = mjabi.table_index(mjabi.GEOM_MESH, mjabi.GEOM_MESH)
    assert table[idx] == registry.hook.cfunc_address(*registry.SLOTS[0])
    assert h.attached and len(h.pairs) == 1 and h.pairs[0].cap == 4
    h.detach()
    assert registry.table_is_original() and not h.attached
    h.detach()  # idempotent


def test_nothing_installed_without_managed_pairs(comb_file, cache):
    xml = COMB_XML.format(comb=comb_file, gtype="mesh", extra="").replace('<freejoint/>', '')
    m = mujoco.MjModel.from_xml_string(xml)  # both combs static: they can never meet
    h = A.attach(m, cache_dir=cache)
    assert h.pairs == [] and h.trees == {} and registry.table_is_original()


def test_combs_true_gap_where_hulls_report_deep_contact(comb_file, cache):
    m = _model(comb_file)
    d = mujoco.MjData(m)
    _interlocked(m, d, gap_z=0.0)
    native = [c.dist for c in d.contact[:d.ncon]]
    true_d, hit = _coal_pair(m, d)
    assert not hit and true_d > 0.0007  # interlocked teeth, ~1 mm apart everywhere
    assert native and min(native) < -0.005  # hulls: centimetre-deep false contact
    with A.attach(m, cache_dir=cache) as h:
        mujoco.mj_forward(m, d)
        assert d.ncon == 0
        eps = h.pairs[0].error_bound
        dist = mujoco.mj_geomDistance(m, d, 0, 1, 0.05, None)
        assert true_d - 1e-9 <= dist <= true_d + eps + 1e-9
    mujoco.mj_forward(m, d)
    assert d.ncon > 0  # native again


def test_contacts_and_distance_against_coal(comb_file, cache):
    m = _model(comb_file)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(3)
    with A.attach(m, cache_dir=cache) as h:
        eps = h.pairs[0].error_bound
        ta, tb = h.trees["lower"], h.trees["upper"]
        q = mjist.Query(ta, tb)
        ba, bb = (jawmod.coal_bvh(*mesh_of(m, g)) for g in (0, 1))
        checked = 0
        for _ in range(60):
            _interlocked(m, d, gap_z=rng.uniform(-0.004, 0.003), shift_x=rng.uniform(-0.002, 0.002))
            d.qpos[3:7] = (Rotation.from_quat(d.qpos[[4, 5, 6, 3]]) * Rotation.from_rotvec(rng.normal(0, 0.05, 3))).as_quat()[[3, 0, 1, 2]]
            mujoco.mj_forward(m, d)
            Pa, Pb = geom_pose(d, 0), geom_pose(d, 1)
            true_d = jawmod.coal_distance(ba, Pa, bb, Pb)
            hit = jawmod.coal_collides(ba, Pa, bb, Pb)
            ref = q.distance(Pa, Pb)
            # a distance sensor's cutoff: groups farther than the deepest `candidates` cost nothing
            dist = mujoco.mj_geomDistance(m, d, 0, 1, 0.05, None)
            if ref.distance > 0:
                assert dist == pytest.approx(ref.distance, abs=1e-12)  # the slot answers distances too
                assert true_d - 1e-9 <= dist <= true_d + eps + 1e-9 or hit
            cons = [c for c in d.contact[:d.ncon]]
            assert len(cons) <= h.pairs[0].cap
            if cons:
                assert hit  # overlapping inner spheres ⇒ the meshes intersect
                for c in cons:
                    n = c.frame[:3]
                    assert abs(np.linalg.norm(n) - 1) < 1e-9 and c.dist <= 0
                    assert set(c.geom) == {0, 1}
                checked += 1
            else:
                # no sphere overlap: the meshes are closer than ε at most
                assert (not hit) or ref.distance <= eps
        assert checked > 5


def test_normal_points_from_geom1_to_geom2_for_either_order(comb_file, cache):
    out = []
    for swap in (False, True):
        xml = COMB_XML.format(comb=comb_file, gtype="mesh", extra="")
        if swap:  # declare the upper comb first: MuJoCo then passes the pair the other way round
            xml = xml.replace('<geom name="lower" type="mesh" mesh="comb"/>', "")
            xml = xml.replace("</body>", '</body>\n    <geom name="lower" type="mesh" mesh="comb"/>')
        m = mujoco.MjModel.from_xml_string(xml)
        d = mujoco.MjData(m)
        lower = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "lower")
        with A.attach(m, cache_dir=cache):
            d.qpos[:3] = [0.0, 0.0, 0.017]  # tooth tips on tooth tips, 0.5 mm into each other
            d.qpos[3:7] = [0, 0, 1, 0]
            mujoco.mj_forward(m, d)
            assert d.ncon > 0
            rows = []
            for c in d.contact[:d.ncon]:
                n = np.array(c.frame[:3]) * (1 if c.geom[0] == lower else -1)  # as lower → upper
                assert n[2] > 0.2  # the upper comb sits above: pushing it up separates
                rows.append([c.dist, *c.pos, *n])
            assert np.mean([r[6] for r in rows]) > 0.5
            out.append(np.array(sorted(rows)))
    assert np.allclose(out[0], out[1], atol=1e-12)


@pytest.mark.parametrize("gtype", ["mesh", "sdf"])
def test_contact_cap_never_exceeded(comb_file, cache, gtype):
    m = _model(comb_file, gtype=gtype, extra='<numeric name="mjist_contacts" data="50"/>')
    cap = min(mujoco.mj_maxContact(m, 0, 1, 0), mujoco.mj_maxContact(m, 0, 1, 1))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    most = 0
    with A.attach(m, cache_dir=cache) as h:
        assert h.pairs[0].cap == cap
        for _ in range(2000):
            d.qpos[:3] = rng.uniform(-0.015, 0.015, 3)
            d.qpos[3:7] = Rotation.random(random_state=rng).as_quat()[[3, 0, 1, 2]]
            mujoco.mj_forward(m, d)  # MuJoCo itself raises past the cap
            most = max(most, d.ncon)
            assert d.ncon <= cap
    assert most >= min(cap, 8)  # deep random overlaps do fill the buffer


def test_rollout_with_two_threads_is_bit_identical_to_serial(comb_file, cache):
    m = _model(comb_file)
    m.opt.gravity[:] = (0, 0, -9.81)
    d = mujoco.MjData(m)
    with A.attach(m, cache_dir=cache) as h:
        _interlocked(m, d, gap_z=0.006)
        states = []
        rng = np.random.default_rng(1)
        for _ in range(6):
            d.qpos[0] = 0.005 + rng.uniform(-0.0005, 0.0005)
            d.qpos[2] = 0.0075  # 1.5 mm above resting on the lower comb
            d.qvel[:] = rng.normal(0, 0.02, m.nv)
            s = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS))
            mujoco.mj_getState(m, d, s, mujoco.mjtState.mjSTATE_FULLPHYSICS)
            states.append(s)
        x0 = np.array(states)
        from mujoco import rollout

        serial, _ = rollout.rollout(m, mujoco.MjData(m), x0, nstep=300)
        par, _ = rollout.rollout(m, [mujoco.MjData(m), mujoco.MjData(m)], x0, nstep=300)
        again, _ = rollout.rollout(m, [mujoco.MjData(m), mujoco.MjData(m)], x0, nstep=300)
        # the upper comb fell and came to rest on the lower one (free fall would be 0.44 m)
        assert np.all(np.abs(serial[:, -1, 3] - 0.006) < 0.001)
        assert h.stats()["distance_calls"] == 0
    assert np.array_equal(serial, par) and np.array_equal(par, again)


def test_thread_pool_bound_to_mjdata_gives_identical_steps(comb_file, cache):
    """``mju_threadpool``: MuJoCo's per-thread stack shards and our CAS slots; same trajectory."""
    m = _model(comb_file)
    m.opt.gravity[:] = (0, 0, -9.81)
    with A.attach(m, cache_dir=cache) as h:
        runs = []
        for threads in (0, 2):
            d = mujoco.MjData(m)
            if threads:
                mujoco.mju_threadpool(d, threads)
            _interlocked(m, d, gap_z=0.006)
            d.qvel[:] = [0.01, 0.0, 0.0, 0.05, 0.02, 0.0]
            traj = []
            for _ in range(300):
                mujoco.mj_step(m, d)
                traj.append(np.concatenate([d.qpos, d.qvel, [d.ncon]]))
            runs.append(np.array(traj))
        assert h.stats()["no_stack"] == 0 and h.stats()["failed"] == 0
        assert h.stats()["distance_calls"] == 0  # the shards' contact buffers are the arena's
    assert runs[0][-1, -1] > 0 and np.array_equal(runs[0], runs[1])


def test_distance_queries_between_steps_leave_the_steps_alone(comb_file, cache):
    """mj_geomDistance on the stepped MjData has its own coherence slot: the steps' trajectory
    and their work (tree visits, front calls) are the same with or without the queries."""
    m = _model(comb_file)
    m.opt.gravity[:] = (0, 0, -9.81)
    with A.attach(m, cache_dir=cache) as h:
        runs = []
        for query in (False, True):
            h.reset_state()
            d = mujoco.MjData(m)
            _interlocked(m, d, gap_z=0.006)
            d.qvel[:] = [0.01, 0.0, 0.0, 0.05, 0.02, 0.0]
            traj, work = [], np.zeros(2, np.int64)
            for _ in range(200):
                s0 = h.stats()
                mujoco.mj_step(m, d)
                s1 = h.stats()
                work += [s1["visits"] - s0["visits"], s1["front_calls"] - s0["front_calls"]]
                traj.append(np.concatenate([d.qpos, d.qvel, [d.ncon]]))
                if query:
                    assert mujoco.mj_geomDistance(m, d, 0, 1, 0.003, None) < 0.003
            runs.append((np.array(traj), work))
        assert h.stats()["distance_calls"] == 200  # each query, and no step
    (ta, wa), (tb, wb) = runs
    assert ta[-1, -1] > 0 and wa[1] > 0  # resting in contact, the front in use
    assert np.array_equal(ta, tb) and np.array_equal(wa, wb)


def test_distance_request_answers_as_the_contact_path_would(comb_file, cache):
    """mj_geomDistance gets one contact from the pair's minimum instead of the contact groups
    within distmax: the same distance as mj_collision's contacts at that margin, and a step
    still gets its several contacts."""
    m = _model(comb_file)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(4)
    with A.attach(m, cache_dir=cache) as h:
        several = 0
        for _ in range(30):
            _interlocked(m, d, gap_z=rng.uniform(-0.002, 0.003), shift_x=rng.uniform(-0.002, 0.002))
            m.geom_margin[:] = 0.01
            mujoco.mj_forward(m, d)
            via_contacts = min([c.dist for c in d.contact[:d.ncon]], default=0.01)
            several += d.ncon > 1
            m.geom_margin[:] = 0.0
            calls = h.stats()["distance_calls"]
            assert mujoco.mj_geomDistance(m, d, 0, 1, 0.01, None) == pytest.approx(via_contacts, abs=1e-12)
            assert h.stats()["distance_calls"] == calls + 1
        assert several > 0 and h.stats()["failed"] == 0


def test_an_arena_too_small_for_the_scratch_says_how_large_to_make_it(comb_file, cache):
    xml = COMB_XML.format(comb=comb_file, gtype="mesh", extra="").replace("<mujoco>", '<mujoco>\n  <size memory="4K"/>')
    m = mujoco.MjModel.from_xml_string(xml)
    with pytest.raises(ConfigError, match=r"the model's arena \(\d+ bytes\) is too small for the IST scratch .* "
                                          r"raise it with <size memory=\"\d+M\"/>") as info:
        A.attach(m, cache_dir=cache)
    fix = info.value.args[0].split('memory="')[1].split('"')[0]
    m = mujoco.MjModel.from_xml_string(xml.replace('memory="4K"', f'memory="{fix}"'))  # the fix it names works
    A.attach(m, cache_dir=cache).detach()
    assert registry.table_is_original()


def test_more_models_than_the_registry_holds_are_refused_and_leave_it_usable(comb_file, cache):
    from mjist.mujoco.layout import MAX_MODELS

    handles = [A.attach(_model(comb_file), cache_dir=cache) for _ in range(MAX_MODELS)]
    try:
        extra = _model(comb_file)
        with pytest.raises(RuntimeError, match=f"at most {MAX_MODELS} models can be attached at once: detach some first"):
            A.attach(extra, cache_dir=cache)
        handles.pop().detach()
        handles.append(A.attach(extra, cache_dir=cache))  # the refusal left nothing behind
        d = mujoco.MjData(extra)
        _interlocked(extra, d, gap_z=-0.002)  # the teeth 0.5 mm into the other comb's base
        assert d.ncon > 0 and handles[-1].stats()["contacts"] > 0  # and the last model collides through mjist
    finally:
        for h in handles:
            h.detach()
    assert registry.table_is_original()


def test_bad_config_is_named(comb_file, cache):
    for extra, msg in [
        ('<text name="mjist_geomz" data="all"/>', "unknown mjist setting"),
        ('<text name="mjist_offset" data="lots"/>', "mjist_offset"),
        ('<text name="mjist_mode" data="springs"/>', "'constraint'"),
        ('<text name="mjist_penalty" data="spring"/>', "'contacts'"),
        ('<numeric name="mjist_stiffness" data="-5"/>', "≥ 0"),
        ('<text name="mjist_coupling" data="upper"/>', "two bodies"),
        ('<text name="mjist_coupling" data="upper lower"/>', "mocap body"),
        ('<numeric name="mjist_coupling_gains" data="1 2 3"/>', "4 numbers"),
        ('<numeric name="mjist_coupling_gains" data="1 2 -3 4"/>',
         r"mjist_coupling_gains=\[1.0, 2.0, -3.0, 4.0\] needs 4 numbers ≥ 0: k_t \(N/m\) c_t \(N·s/m\) k_r"),
        ('<numeric name="mjist_contacts" data="0"/>', "mjist_contacts"),
        ('<numeric name="mjist_max_error" data="-1"/>', "positive"),
        ('<text name="mjist_max_error" data="1"/>', "<numeric>"),
        ('<text name="mjist_skip" data="maybe"/>', "true or false"),
    ]:
        xml = COMB_XML.format(comb=comb_file, gtype="mesh", extra=extra)
        if "mjist_offset" in extra:
            xml = xml.replace('<text name="mjist_offset" data="none"/>', "")
        if "mjist_max_error" in extra:
            xml = xml.replace('<numeric name="mjist_max_error" data="0.0004"/>', "")
        m = mujoco.MjModel.from_xml_string(xml)
        with pytest.raises(ConfigError, match=msg):
            A.attach(m, cache_dir=cache)
    m = _model(comb_file)
    with pytest.raises(ConfigError, match="not a geom"):
        A.attach(m, geoms=["nope"], cache_dir=cache)
    assert registry.table_is_original()


def test_contact_groups_default_by_mode(comb_file):
    """Constraint contacts group at depth 5 (one contact per group: a deeper group cannot span both
    slopes of a cusp), penalty forces at depth 3 (their law sums over groups); a setting wins."""
    m = _model(comb_file)
    assert config.read_config(m).split_depth == 5
    assert config.read_config(m, mode="penalty").split_depth == 3
    assert config.read_config(m, split_depth=2).split_depth == 2
    xml = COMB_XML.format(comb=comb_file, gtype="mesh", extra='<numeric name="mjist_split_depth" data="4"/>')
    assert config.read_config(mujoco.MjModel.from_xml_string(xml), mode="penalty").split_depth == 4


def test_foreign_slot_function_is_refused(comb_file, cache):
    @cfunc(types.int32(types.voidptr, types.voidptr, types.voidptr, types.int32, types.int32, types.float64))
    def other(m, d, con, g1, g2, margin):
        return 0

    registry._record_originals()
    table = mjabi.collision_table()
    idx = mjabi.table_index(mjabi.GEOM_MESH, mjabi.GEOM_MESH)
    orig = table[idx]
    table[idx] = other.address
    try:
        with pytest.raises(RuntimeError, match="neither MuJoCo's nor mjist's"):
            A.attach(_model(comb_file), cache_dir=cache)
    finally:
        table[idx] = orig
    assert registry.table_is_original()


def test_tree_cache_hit_and_corrupt_entry_rebuilt(comb_file, tmp_path):
    m = _model(comb_file)
    h = A.attach(m, cache_dir=tmp_path)
    h.detach()
    assert h.cache_hits == 0
    files = sorted(tmp_path.glob("*.ist.npz"))
    assert len(files) == 1  # the two geoms share one mesh: one tree
    h = A.attach(m, cache_dir=tmp_path)
    h.detach()
    assert h.cache_hits == 1
    files[0].write_bytes(b"not a tree")
    with pytest.warns(RuntimeWarning, match="rebuilding cached tree"):
        h = A.attach(m, cache_dir=tmp_path)
    h.detach()
    assert mjist.load_tree(files[0]).num_leaves > 0


def test_prebuilt_trees_are_found_read_only(comb_file, tmp_path, monkeypatch):
    from mjist import cache as tree_cache

    m = _model(comb_file)
    shipped, fresh = tmp_path / "shipped", tmp_path / "fresh"
    A.attach(m, cache_dir=shipped).detach()
    monkeypatch.setattr(tree_cache, "PREBUILT", [str(shipped)])
    h = A.attach(m, cache_dir=fresh)
    h.detach()
    assert h.cache_hits == 1 and not fresh.exists()  # loaded from the prebuilt folder, nothing built or written
    tree = next(shipped.glob("*.ist.npz"))
    tree.write_bytes(b"not a tree")
    with pytest.warns(RuntimeWarning, match="rebuilding cached tree"):
        h = A.attach(m, cache_dir=fresh)
    h.detach()
    assert h.cache_hits == 0 and (fresh / tree.name).exists() and tree.read_bytes() == b"not a tree"


def test_bundled_closure_scene_ships_its_trees(tmp_path):
    """The wheel carries the closure scene's trees (models/trees), so a first ``mjist demo`` builds none."""
    from mjist.jaw import BUNDLED

    h = A.attach(mujoco.MjModel.from_xml_path(str(BUNDLED / "jaw_closure.xml")), cache_dir=tmp_path,
                 narrowphase="surface")
    h.detach()
    assert h.cache_hits == 2, "models/trees no longer matches the meshes or the builder: run python scripts/make_jaws.py --trees"
    # the exit directions and the surface grids were shipped too
    assert not any(tmp_path.iterdir()), "models/trees lacks exits or grids: run python scripts/make_jaws.py --trees"


def test_state_changes_speed_not_answers(comb_file, cache):
    """Coherence state only prunes: the same poses give the same contacts with or without it."""
    rng = np.random.default_rng(7)
    poses = [(rng.uniform(-0.006, 0.0), rng.uniform(-0.001, 0.001)) for _ in range(40)]
    runs = []
    for skip in ("true", "false"):
        mm = _model(comb_file, extra=f'<text name="mjist_skip" data="{skip}"/>')
        dd = mujoco.MjData(mm)
        with A.attach(mm, cache_dir=cache):
            out = []
            for i, (z, x) in enumerate(poses):
                dd.time = 0.001 * i
                _interlocked(mm, dd, gap_z=z, shift_x=x)
                out.append(np.array([[c.dist, *c.pos, *c.frame[:3]] for c in dd.contact[:dd.ncon]]))
            runs.append(out)
    for a, b in zip(*runs):
        assert a.shape == b.shape and np.allclose(a, b, atol=1e-12)


def test_jaw_closure_scene_reaches_occlusion(cache):
    """The bundled scene: the muscles close the jaw onto the teeth near the ground-truth pose."""
    from mjist.jaw.demo import run_closure

    model, h = A.load_model(ROOT / "models" / "jaw_closure.xml", cache_dir=cache)
    try:
        assert [p.geom1 for p in h.pairs] == ["maxilla"] and h.pairs[0].cap == 4
        res = run_closure(model, seconds=0.3, handle=h)
    finally:
        h.detach()
    assert res["final_contacts"] >= 1
    assert abs(res["final_hinge_deg"]) < 1.0  # teeth stop the closure near the occlusion
    eps = res["error_bound_mm"]
    assert -eps <= res["true_distance_mm"] <= eps
    assert res["hook"]["failed"] == 0 and res["hook"]["no_stack"] == 0


def test_scene_file_is_the_generator_output():
    import json

    from mjist.jaw.scenes import jaw_closure_xml

    j = json.loads((ROOT / "models" / "occlusion.json").read_text())
    xml = jaw_closure_xml("maxilla.obj", "mandible.obj", j["hinge"], np.array(j["mandible_pose"])[:3, 3],
                          half_width=abs(j["condyles"][0][0]))
    assert (ROOT / "models" / "jaw_closure.xml").read_text() == xml


def test_jaw_contacts_against_coal_at_many_poses(cache):
    """Bundled jaws, 40 poses around the occlusion: distances, overlaps and contact points vs coal."""
    model, h = A.load_model(ROOT / "models" / "jaw_closure.xml", cache_dir=cache, offset="none")
    try:
        gmx, gmd = h.geoms["maxilla"], h.geoms["mandible"]
        eps = h.pairs[0].error_bound
        meshes = {g: trimesh.Trimesh(*mesh_of(model, g), process=False) for g in (gmx, gmd)}
        bvh = {g: jawmod.coal_bvh(*mesh_of(model, g)) for g in (gmx, gmd)}
        d = mujoco.MjData(model)
        occ = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "occlusion")
        rng = np.random.default_rng(11)
        touching = separated = 0
        for _ in range(40):
            mujoco.mj_resetDataKeyframe(model, d, occ)
            d.qpos[:3] += [np.radians(rng.uniform(-0.4, 2.0)), rng.uniform(-5e-4, 5e-4), rng.uniform(-5e-4, 5e-4)]
            mujoco.mj_forward(model, d)
            Pa, Pb = geom_pose(d, gmx), geom_pose(d, gmd)
            true_d = jawmod.coal_distance(bvh[gmx], Pa, bvh[gmd], Pb)
            hit = jawmod.coal_collides(bvh[gmx], Pa, bvh[gmd], Pb)
            dist = mujoco.mj_geomDistance(model, d, gmx, gmd, 0.05, None)
            cons = [c for c in d.contact[:d.ncon] if {int(c.geom1), int(c.geom2)} == {gmx, gmd}]
            assert len(cons) <= h.pairs[0].cap
            if dist > 0:
                separated += 1
                assert true_d - 1e-9 <= dist <= true_d + eps + 1e-9
                assert not cons
            if cons:
                touching += 1
                assert hit  # inner spheres overlap ⇒ the meshes intersect
                for c in cons:
                    assert c.dist <= 0 and abs(np.linalg.norm(c.frame[:3]) - 1) < 1e-9
                    # the contact point lies in both solids, up to the bound
                    for g, P in ((gmx, Pa), (gmd, Pb)):
                        local = P[:3, :3].T @ (np.array(c.pos) - P[:3, 3])
                        assert trimesh.proximity.signed_distance(meshes[g], local[None])[0] >= -eps
            elif hit:
                assert true_d == 0.0 and dist <= eps + 1e-9  # a graze thinner than ε
        assert touching >= 10 and separated >= 10
    finally:
        h.detach()


def test_overlay_draws_tree_layers_and_contacts(cache):
    """``mjist view``/``render --spheres``: layer cuts cover each leaf once; the scene never overflows."""
    from mjist.mujoco.view import layer, overlay

    model, h = A.load_model(ROOT / "models" / "jaw_closure.xml", cache_dir=cache)
    try:
        d = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, d, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "occlusion"))
        mujoco.mj_forward(model, d)
        for t in h.trees.values():
            for depth in (0, 2, t.depth):
                idx = layer(t, depth)
                covered = np.concatenate([np.arange(t.leaf_start[i], t.leaf_end[i]) for i in idx])
                assert np.array_equal(np.sort(covered), np.arange(t.num_leaves))
        scn = mujoco.MjvScene(model, maxgeom=4000)
        for g in scn.geoms:  # what an earlier frame may leave in the slots (a mesh geom's ids)
            g.dataid, g.matid, g.texid, g.objtype = 7, 3, 2, int(mujoco.mjtObj.mjOBJ_GEOM)
        got = overlay(scn, model, d, h, depth=3)
        expect = sum(layer(t, 3).size for t in h.trees.values())
        ist = [c for c in d.contact[:d.ncon] if frozenset((c.geom1, c.geom2)) == frozenset(h.pairs[0].ids)]
        assert got == {"spheres": expect, "spheres_skipped": 0, "contacts": len(ist)} and len(ist) > 0
        assert scn.ngeom == expect + 2 * len(ist)
        c = scn.geoms[scn.ngeom - 1]  # the last arrow starts at the last contact point
        assert np.linalg.norm(np.array(c.pos) - ist[-1].pos) <= 0.03 * float(model.geom_rbound.max())
        # every drawn geom is fully initialised: no stale mesh, material or texture id for the
        # renderer to follow (an arrow set by mjv_connector alone kept them: mjr_render segfaulted)
        for g in list(scn.geoms)[:scn.ngeom]:
            assert (g.dataid, g.matid, g.texid) == (-1, -1, -1), (g.type, g.dataid, g.matid, g.texid)
        small = mujoco.MjvScene(model, maxgeom=50)
        got = overlay(small, model, d, h, depth=h.trees["mandible"].depth)
        assert small.ngeom <= 50 and got["spheres"] == 50 and got["spheres_skipped"] > 0
    finally:
        h.detach()


PRIM_XML = """
<mujoco>
  <option timestep="0.001" gravity="0 0 0"/>
  <custom><text name="mjist_offset" data="none"/><numeric name="mjist_max_error" data="0.0004"/></custom>
  <default><geom solref="0.002 1"/></default>
  <asset><mesh name="comb" file="{comb}"/></asset>
  <worldbody>
    <geom name="comb" type="mesh" mesh="comb"/>
    <body name="probe"><freejoint/><geom name="probe" type="{ptype}" size="{size}"/></body>
  </worldbody>
</mujoco>
"""
PRIMS = {  # MuJoCo size -> coal shape
    "sphere": ("0.0015", lambda s: __import__("coal").Sphere(s[0])),
    "capsule": ("0.001 0.003", lambda s: __import__("coal").Capsule(s[0], 2 * s[1])),
    "cylinder": ("0.0012 0.003", lambda s: __import__("coal").Cylinder(s[0], 2 * s[1])),
    "box": ("0.001 0.0015 0.004", lambda s: __import__("coal").Box(2 * s[0], 2 * s[1], 2 * s[2])),
}


@pytest.mark.parametrize("ptype", sorted(PRIMS))
def test_primitive_probe_between_teeth_against_coal(comb_file, cache, ptype):
    """A primitive probing the comb's gaps: leaf-sphere contacts, distances inside the bound, normals out of the comb."""
    size, shape = PRIMS[ptype]
    m = mujoco.MjModel.from_xml_string(PRIM_XML.format(comb=comb_file, ptype=ptype, size=size))
    d = mujoco.MjData(m)
    hull_false = 0
    native = mujoco.MjData(m)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no hull-fallback warning for these primitives
        h = A.attach(m, cache_dir=cache)
    with h:
        assert [(p.geom1, p.geom2) for p in h.primitive_pairs] == [("probe", "comb")] and not h.pairs
        eps = h.primitive_pairs[0].error_bound
        cap = h.primitive_pairs[0].cap
        bvh = jawmod.coal_bvh(*mesh_of(m, 0))
        comb = trimesh.Trimesh(*mesh_of(m, 0), process=False)
        geo = shape(m.geom_size[1])
        rng = np.random.default_rng(7)
        touching = separated = 0
        for _ in range(120):
            # the gap between teeth at x = ±10 mm (teeth x ±(3..7), ±(13..17)), tooth tops at z = 9 mm
            x = rng.choice([-10e-3, 10e-3, -5e-3, 5e-3]) + rng.uniform(-2.5e-3, 2.5e-3)
            d.qpos[:3] = [x, rng.uniform(-3e-3, 3e-3), rng.uniform(0.0, 12e-3)]
            d.qpos[3:7] = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_quat()[[3, 0, 1, 2]]
            mujoco.mj_forward(m, d)
            Pm, Pp = geom_pose(d, 0), geom_pose(d, 1)
            true_d = jawmod.coal_distance(bvh, Pm, geo, Pp)
            hit = jawmod.coal_collides(bvh, Pm, geo, Pp)
            dist = mujoco.mj_geomDistance(m, d, 1, 0, 0.05, None)
            cons = list(d.contact[:d.ncon])
            assert len(cons) <= cap
            if comb.contains((Pm[:3, :3].T @ (Pp[:3, 3] - Pm[:3, 3]))[None])[0]:
                # the probe's centre is inside the solid comb: coal's triangle-soup distance is
                # no solid distance there, but the inner spheres see the penetration
                assert cons and dist < 0
                continue
            if dist > 0:
                separated += 1
                # coal meets these shapes by GJK (1e-6 tolerance): allow a micrometre
                assert true_d - 1e-6 <= dist <= true_d + eps + 1e-6
                assert not cons
            for c in cons:
                assert hit and c.dist <= 0  # leaf spheres are inside the comb
                n = np.array(c.frame[:3])
                assert abs(np.linalg.norm(n) - 1) < 1e-9
                # normal from geom1 to geom2 (MuJoCo passes the primitive first): out of the convex
                # probe; pos lies half the depth inside the probe's surface along it
                sign = 1.0 if c.geom1 == 1 else -1.0
                assert sign * float(n @ (np.array(c.pos) - d.geom_xpos[1])) >= 0.5 * c.dist - 1e-12
                touching += 1
        assert touching >= 5 and separated >= 20
    # MuJoCo's own function sees the comb as its hull: a probe inside a gap is a (false) contact
    for x in (-10e-3, 10e-3):
        native.qpos[:3] = [x, 0.0, 2e-3]
        native.qpos[3:7] = [1, 0, 0, 0]
        mujoco.mj_forward(m, native)
        hull_false += native.ncon > 0
    Pm, Pp = geom_pose(native, 0), geom_pose(native, 1)
    assert jawmod.coal_distance(bvh, Pm, geo, Pp) > 0.5e-3 and hull_false == 2
    with A.attach(m, cache_dir=cache):
        mujoco.mj_forward(m, native)
        assert native.ncon == 0  # the IST sees the gap


def test_sphere_falls_into_the_gap_between_teeth(comb_file, cache):
    """Dynamics: a ball dropped over a gap reaches the gap's floor with the IST, rests on the hull natively."""
    xml = PRIM_XML.format(comb=comb_file, ptype="sphere", size="0.0015").replace('gravity="0 0 0"', 'gravity="0 0 -9.81"')
    m = mujoco.MjModel.from_xml_string(xml)
    rest = {}
    for mode in ("native", "ist"):
        d = mujoco.MjData(m)
        d.qpos[:3] = [0.010, 0.0, 0.013]
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            h = A.attach(m, cache_dir=cache, primitives=mode)
        assert any("convex hull" in str(x.message) for x in w) == (mode == "native")  # the fallback is announced
        q = np.empty((400, 3))
        with h:
            for i in range(400):
                mujoco.mj_step(m, d)
                q[i] = d.qpos[:3]
        # height at rest: the median after landing (step ~55) while the ball is still over the
        # comb. A ball on the IST floor rolls: a sphere-mesh pair holds ONE contact in MuJoCo, so it
        # lands on one leaf sphere (a bump, not a pocket), is kicked sideways along the gap at
        # tens of mm/s and may leave the 10 mm deep comb within ~80 steps.
        over = (np.arange(400) >= 60) & (np.abs(q[:, 1]) < 0.005 - 0.0015)
        assert over.sum() >= 30, mode
        rest[mode] = float(np.median(q[over, 2]))
    eps = 0.0004
    assert rest["native"] > 0.0095  # on the hull's lid over the tooth tips (9 mm + radius)
    assert -0.0015 - 1e-4 <= rest["ist"] <= -0.0015 + eps + 1e-4  # on the gap's floor (-3 mm + radius), within ε


def test_passive_callback_chains_and_is_restored(cache):
    """A callback already in mjcb_passive keeps running under ours; detach puts it back."""
    hits = np.zeros(1, np.int64)
    addr = hits.ctypes.data

    @cfunc(types.void(types.int64, types.int64))
    def count(m, d):
        p = mjabi.i64_ptr(addr)
        p[0] += 1

    cb = mjabi.passive_callback()
    before = cb.value
    cb.value = count.address
    try:
        model, h = A.load_model(ROOT / "models" / "haptic_jaw.xml", cache_dir=cache)
        assert registry.passive_is_ours()
        d = mujoco.MjData(model)
        h0 = int(hits[0])  # count only these steps
        for _ in range(5):
            mujoco.mj_step(model, d)
        assert hits[0] == h0 + 5 and h.haptic(d)["coupling"] is not None  # theirs ran, and ours
        h.detach()
        assert cb.value == count.address  # theirs is back alone
        # replaced after attach (mujoco.set_mjcb_passive does that): a new attach chains it again
        model, h = A.load_model(ROOT / "models" / "haptic_jaw.xml", cache_dir=cache)
        cb.value = count.address
        assert not registry.passive_is_ours()
        model2, h2 = A.load_model(ROOT / "models" / "haptic_jaw.xml", cache_dir=cache)
        assert registry.passive_is_ours()
        h0 = int(hits[0])
        mujoco.mj_step(model2, mujoco.MjData(model2))
        assert hits[0] == h0 + 1
        h2.detach()
        h.detach()
        assert cb.value == count.address
    finally:
        cb.value = before


def test_data_offsets_come_from_the_declaration_and_match_every_array():
    """mjData's layout computed from its declaration (introspected field order and types, C
    rules) puts every pointer field of a live MjData, not only the probed ones, where the
    wrapper's arrays live, and its counters and time where their values are; reads stop at the
    struct's end, so copies of the pointer block in the memory beyond it change nothing."""
    from mujoco.introspect import ast_nodes

    from mjist.mujoco import abi

    layout, size, _ = abi.struct_layout("mjData")
    m = mujoco.MjModel.from_xml_string(abi._PROBE_XML)
    d = mujoco.MjData(m)
    mujoco.mj_step(m, d)
    words = abi._words(d._address, size // 8)
    checked = 0
    for f in abi._mj_structs.STRUCTS["mjData"].fields:
        arr = getattr(d, f.name, None)
        word = int(words[layout[f.name] // 8])
        # a NULL word is an arena array this step did not allocate (the wrapper shows a placeholder)
        if isinstance(f.type, ast_nodes.PointerType) and isinstance(arr, np.ndarray) and arr.size and word:
            assert word == arr.ctypes.data, f.name
            checked += 1
    assert checked >= 50
    assert words[layout["time"] // 8] == np.array([d.time]).view(np.uint64)[0]
    off = abi.data_offsets()
    assert all(off[k] == layout[k] for k in abi._POINTER_FIELDS) and off["sizeof"] == size
    # copies of the whole pointer block planted beyond the struct: nothing there is read
    beyond = np.concatenate([words, np.tile(words[layout["mocap_pos"] // 8:layout["qfrc_passive"] // 8 + 1], 3)])
    abi._check(beyond[: size // 8], d, off)
    abi.verify_offsets(d, off)


def test_a_field_where_the_declaration_does_not_put_it_is_refused_by_name():
    from mjist.mujoco import abi

    m = mujoco.MjModel.from_xml_string(abi._PROBE_XML)
    d = mujoco.MjData(m)
    off = abi.data_offsets()
    words = abi._words(d._address, off["sizeof"] // 8)
    for field in ("geom_xmat", "time", "pstack"):
        bad = words.copy()
        bad[off[field] // 8] ^= np.uint64(8)
        with pytest.raises(abi.MuJoCoABIError, match=rf"mjData\.{field} is not at byte {off[field]}.*MuJoCo 4\.0"):
            abi._check(bad, d, off)
    with pytest.raises(abi.MuJoCoABIError, match="mjData declares a field of type .* use MuJoCo 4.0"):
        abi._type_layout(SimpleNamespace())  # a type the layout does not know
