"""IST contacts in scenes that are not jaws: a non-convex container, SDF plugin geoms."""
import mujoco
import numpy as np
from conftest import load_script

import mjist


def _container():
    return load_script("examples", "container.py")


def test_objects_dropped_into_a_cup_at_mujocos_defaults_rest_on_its_floor(tmp_path, cache, monkeypatch):
    """The README's container example, with MuJoCo's default timestep, solref and solimp: a ball,
    a capsule and a box fall 5-9 cm into a round cup (6 mm walls, 10 mm floor). The soft
    default contacts let each sink millimetres into the floor on impact, past the middle of
    thinner walls; IST contacts, on the spheres and on the surfaces, still push every one back
    out the side it came in and it rests on the floor within 0.5 mm of the height MuJoCo's
    mesh-SDF gives it. MuJoCo's convex hull of the cup is a closed cylinder: the objects stay on
    its lid."""
    monkeypatch.setenv("MJIST_CACHE", cache)
    res = _container().run(tmp_path)
    sdf = res["native mesh-SDF"]["objects"]
    assert {o["where"] for o in sdf.values()} == {"in the cup"}
    assert {o["where"] for o in res["native hull"]["objects"].values()} == {"on the lid"}
    for mode in ("ist", "ist surface"):
        ist = res[mode]["objects"]
        print(mode, {k: (round(o["height_from_sdf_mm"], 3), round(o["from_sdf_mm"], 2), round(o["sank_mm"], 1),
                         round(o["speed_m_s"] * 1e3, 2)) for k, o in ist.items()})
        for name, o in ist.items():
            assert o["where"] == "in the cup", (mode, name, o)
            assert abs(o["height_from_sdf_mm"]) < 0.5, (mode, name, o)
        assert max(o["sank_mm"] for o in ist.values()) > 3.0  # the impacts really were deep
    # sphere contacts settle every object; on the surfaces the ball rolls on (docs/mujoco.md)
    assert all(o["speed_m_s"] < 1e-3 for o in res["ist"]["objects"].values())
    assert res["ist surface"]["objects"]["box"]["speed_m_s"] < 1e-3


TORUS = """<mujoco>
  <extension><plugin plugin="mujoco.sdf.torus"><instance name="torus">
    <config key="radius1" value="0.35"/><config key="radius2" value="0.15"/></instance></plugin></extension>
  <option sdf_iterations="10" sdf_initpoints="40"/>
  <asset>
    <mesh name="torus"><plugin instance="torus"/></mesh>
    <mesh name="ball" file="{ball}"/>
  </asset>
  <worldbody>
    <geom type="sdf" name="torus" mesh="torus"><plugin instance="torus"/></geom>
    <body name="a" pos="0.35 0 0.4"><freejoint/><geom name="a" type="mesh" mesh="ball"/></body>
    <body name="b" pos="-0.35 0 0.6"><freejoint/><geom name="b" type="mesh" mesh="ball"/></body>
  </worldbody>
</mujoco>"""


def _torus_scene(tmp_path, extra=""):
    import trimesh

    trimesh.creation.icosphere(2, radius=0.08).export(tmp_path / "ball.obj")
    xml = TORUS.format(ball=tmp_path / "ball.obj").replace("<worldbody>", f"<custom>{extra}</custom>\n  <worldbody>")
    path = tmp_path / "torus.xml"
    path.write_text(xml)
    return path


def test_sdf_plugin_geoms_keep_mujocos_collision_unless_named(tmp_path, cache):
    """Two mesh balls fall onto an analytic torus (``mujoco.sdf.torus``): the balls get a tree
    (their pair is the IST's), the torus keeps its exact plugin SDF, so each ball's fall onto it
    and roll off it is MuJoCo's own to the bit."""
    path = _torus_scene(tmp_path)
    native = mujoco.MjModel.from_xml_path(str(path))
    dn = mujoco.MjData(native)
    model, h = mjist.load_model(path, cache_dir=cache)
    try:
        assert set(h.trees) == {"a", "b"}  # the plugin's visual mesh gets no tree
        assert [(p.geom1, p.geom2) for p in h.pairs] == [("a", "b")]
        d = mujoco.MjData(model)
        torus = model.geom("torus").id
        touched = 0
        for _ in range(500):
            mujoco.mj_step(model, d)
            mujoco.mj_step(native, dn)
            touched += sum(torus in (c.geom1, c.geom2) for c in d.contact[:d.ncon])
        assert touched > 0
        for ball in ("a", "b"):  # they roll off the tube's top and settle on its side
            assert np.array_equal(d.body(ball).xpos, dn.body(ball).xpos)
            assert np.array_equal(d.body(ball).xquat, dn.body(ball).xquat)
    finally:
        h.detach()


def test_sdf_plugin_geom_named_in_mjist_geoms_gets_a_tree(tmp_path, cache):
    path = _torus_scene(tmp_path, '<text name="mjist_geoms" data="torus a"/>')
    model, h = mjist.load_model(path, cache_dir=cache, max_error=0.01)
    try:
        assert set(h.trees) == {"torus", "a"}
    finally:
        h.detach()
