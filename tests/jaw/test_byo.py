"""Other people's jaws: units, up axis, the arch's own frame, teeth-only and open scans, scenes.

The procedural jaws (the bundled pair's design, polygonised coarsely to keep this quick),
converted as a user's scan would come (``scripts/byo_jaws.py``: millimetres, +z superior,
anterior along -y; cropped to the teeth; holes cut into the gingiva), must give back the same
pair in the jaw frame, and bad pairs must be refused with the flag that fixes them.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from mjist.errors import MeshError
from mjist.jaw import arch, contact_map, generator, orient
from mjist.jaw.pair import load_pair
from tests.conftest import load_script

byo = load_script("scripts", "byo_jaws.py")


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """The designed jaws at 1 mm spacing (~25 k vertices each), with their designed occlusion."""
    folder = tmp_path_factory.mktemp("design")
    maxilla, mandible, meta = generator.generate(1.0)
    maxilla.export(folder / "maxilla.obj")
    mandible.export(folder / "mandible.obj")
    (folder / "occlusion.json").write_text(json.dumps({"mandible_pose": np.eye(4).tolist(), "hinge": list(meta["hinge"])}))
    return folder


@pytest.fixture(scope="module")
def pairs(source, tmp_path_factory):
    return byo.variants(source, tmp_path_factory.mktemp("byo"))


@pytest.fixture(scope="module")
def bundled(source):
    return load_pair(source)


def _write(folder, maxilla, mandible):
    folder.mkdir(parents=True, exist_ok=True)
    maxilla.export(folder / "maxilla.stl")
    mandible.export(folder / "mandible.stl")
    return folder


def _files(folder):
    return (trimesh.load(folder / "maxilla.stl", process=False), trimesh.load(folder / "mandible.stl", process=False))


def test_millimetres_z_up_come_back_as_the_bundled_pair(pairs, bundled):
    mx0, md0, info0 = bundled
    assert info0["orientation"].identity and info0["hinge_source"] == "occlusion.json"
    folder, S = pairs["mm_z"]
    mx, md, info = load_pair(folder)
    o = info["orientation"]
    assert (o.units, o.up) == ("mm", "+z") and "units" in o.detected and "up" in o.detected
    np.testing.assert_allclose(o.R, S[:3, :3].T / 1000.0, atol=1e-12)  # anterior snapped to -y exactly
    np.testing.assert_allclose(np.sort(mx.vertices, axis=0), np.sort(mx0.vertices, axis=0), atol=1e-7)
    # the designed occlusion: the files store the mandible there, so first touch is (almost) no move
    assert abs(info["mandible_pose"][1, 3]) < 5e-5
    assert info["hinge_source"] == "condyles" and not info["teeth_only"]
    # condyle detection fits the condylar heads' tops (at 1 mm spacing); the designed axis runs through their centres
    np.testing.assert_allclose(info["hinge"] + info["mandible_pose"][:3, 3], info0["hinge"] + info0["mandible_pose"][:3, 3],
                               atol=1.5e-3)
    # the same with the flags given
    _, _, given = load_pair(folder, units="mm", up="+z")
    np.testing.assert_allclose(given["orientation"].R, o.R)
    assert given["orientation"].detected.keys() == {"anterior"}


def test_arch_frame_and_regions_follow_the_arch_not_the_world(bundled):
    mx, md, info = bundled
    shift = np.array([0.054, 0.0, 0.0])  # the arch at x = 16-92 mm, like a scan in its scanner's frame
    P = info["mandible_pose"]
    Vd = md.vertices @ P[:3, :3].T + P[:3, 3]
    f0 = info["arches"]["maxilla"]
    f = arch.arch_frame(arch.occlusal_points(mx.vertices + shift, Vd + shift, md.faces), (0.0, 1.0, 0.0))
    np.testing.assert_allclose(f.origin - f0.origin, shift, atol=5e-4)
    np.testing.assert_allclose(f.anterior, [0.0, 0.0, 1.0], atol=0.02)
    np.testing.assert_allclose(f.left, [1.0, 0.0, 0.0], atol=0.02)
    pts = np.array([[0.02, 0.0, 0.0], [-0.02, 0.0, 0.0], [0.005, 0.0, f0.origin[2] - 0.002], [-0.02, 0.0, f0.origin[2] - 0.04]])
    assert f.regions(pts + shift) == f0.regions(pts)
    assert f0.regions(pts)[2] == "left-anterior" and f0.regions(pts)[3] == "right-molar"
    assert 40 < f0.width * 1e3 < 80 and f0.symmetry_mm < 0.5


def test_teeth_only_pair_gets_bonwill_hinge_and_a_jaws_mass(pairs, bundled):
    _, _, info0 = bundled
    mx, md, info = load_pair(pairs["mm_z_teeth"][0])
    assert info["teeth_only"] and info["hinge_source"] == "Bonwill estimate"
    hinge = info["hinge"] + info["mandible_pose"][:3, 3]
    true = info0["hinge"] + info0["mandible_pose"][:3, 3]
    assert np.linalg.norm(hinge - true) < 0.012  # Bonwill's triangle against this pair's condyles
    assert info["inertial"]["mass"] == arch.MANDIBLE_MASS
    _, _, given = load_pair(pairs["mm_z_teeth"][0], hinge=(0.0, -35.0, 30.0))  # file coordinates, mm
    assert given["hinge_source"] == "given"
    np.testing.assert_allclose(given["hinge"] + given["mandible_pose"][:3, 3], [0.0, 0.030, 0.035], atol=1e-9)


def test_open_scan_is_closed_and_reported(pairs):
    folder = pairs["mm_z_teeth_holes"][0]
    with pytest.raises(MeshError, match="not closed.*--repair"):
        load_pair(folder, repair="off")
    with pytest.warns(UserWarning, match="open surface.*MeshFix.*not anatomy"):
        mx, md, info = load_pair(folder)
    assert mx.closure is not None and mx.closure.kept_fraction > 0.99 and mx.closure.added_area > 0
    assert info["export"] and any("open surface" in n for n in info["notes"])


def test_mismatched_units_swapped_jaws_and_apart_are_refused(pairs, tmp_path):
    a, b = _files(pairs["mm_z"][0])
    metres = b.copy()
    metres.apply_scale(1e-3)
    with pytest.raises(ValueError, match="different units.*--units"):
        load_pair(_write(tmp_path / "units", a, metres))
    _, _, info = load_pair(tmp_path / "units", units="mm,m")
    assert info["orientation"].scales == (1e-3, 1.0)
    with pytest.raises(ValueError, match="swapped.*up=-z"):
        load_pair(_write(tmp_path / "swapped", b, a), up="+z")
    with pytest.raises(ValueError, match="swapped"):  # up detected: the rami give the mandible away
        load_pair(tmp_path / "swapped")
    apart = b.copy()
    apart.apply_translation((0.0, 0.0, -40.0))  # 40 mm below: never meet
    with pytest.raises(ValueError, match="cannot tell which way is up|do not face"):
        load_pair(_write(tmp_path / "apart", a, apart))
    huge = a.copy()
    huge.apply_scale(10.0)
    with pytest.raises(ValueError, match="cannot tell the units.*--units"):
        load_pair(_write(tmp_path / "huge", huge, b))
    with pytest.raises(ValueError, match="units="):
        orient.parse_units("inch")


def test_scene_command_writes_a_loadable_scene(pairs, tmp_path, monkeypatch, capsys):
    import mujoco

    from mjist import cli
    from mjist.jaw import pair

    monkeypatch.setattr(pair, "MUJOCO_STL_FACES", 1000)  # as if the STL were beyond MuJoCo's importer
    folder = pairs["mm_z_teeth"][0]
    out = tmp_path / "s" / "scene.xml"
    assert cli.main(["scene", str(folder / "maxilla.stl"), str(folder / "mandible.stl"), "--kind", "haptic", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "units mm (detected), up +z (detected)" in text and "teeth-only" in text
    xml = out.read_text()
    assert "maxilla.jaw.obj" in xml and 'mass="0.11"' in xml
    m = mujoco.MjModel.from_xml_path(str(out))
    assert m.body_mass[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "mandible")] == pytest.approx(0.11)
    assert cli.main(["scene", str(folder / "maxilla.stl"), str(folder / "nothing.stl")]) == 1
    assert "does not exist" in capsys.readouterr().err


def _map_within_exact_distances(model, cmap, qpos, n=150):
    """Each arch's map is drawn on that arch where MuJoCo puts it at ``qpos``, and at sampled
    vertices near the other arch the exact distance to it (coal, computed here) lies in the map's
    certified interval (the lower end where the vertex is outside the other arch, as the map
    states)."""
    import _reference as ref
    from conftest import winding_numbers

    world = {g: (ref.geom_world_vertices(model, qpos, g), ref.geom_faces(model, g)) for g in ("maxilla", "mandible")}
    rng = np.random.default_rng(0)
    for name, other in (("maxilla", "mandible"), ("mandible", "maxilla")):
        m = cmap[name]
        assert np.allclose(m.vertices, world[name][0], atol=1e-9)
        near = np.flatnonzero(m.upper < 1e-3)
        assert near.size > 0
        pick = np.sort(rng.choice(near, min(n, near.size), replace=False))
        dist = ref.point_distances(m.vertices[pick], world[other])
        outside = winding_numbers(m.vertices[pick], *world[other]) < 0.5  # exact for a closed surface
        assert np.all(np.where(outside, dist, 0.0) <= m.upper[pick] + 1e-9), name
        assert np.all(dist[outside] >= m.lower[pick][outside] - 1e-9), name


def test_teeth_only_open_scan_runs_end_to_end(pairs, tmp_path):
    """The most common dental data (teeth only, open, millimetres, +z up): search, contact map, haptics."""
    import warnings

    from mjist.jaw import contactmap, haptic, occlusion

    folder = pairs["mm_z_teeth_holes"][0]
    opts = {"max_error": 1e-3}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the open-surface warning, tested above
        res = occlusion.search(data=folder, out_dir=tmp_path / "occ", starts=6, top=2, polish=1, progress=False, pair=opts)
    try:
        best = res["candidates"][0]
        assert {r.split("-")[0] for r in best["regions"]} == {"left", "right"}  # a bilateral occlusion
        # against the design, computed here: the files store it; coal brings it to first touch along +z (mm)
        import _reference as ref

        mx, md = (trimesh.load(folder / f"{n}.stl", process=False) for n in ("maxilla", "mandible"))
        a, Vd = (mx.vertices, mx.faces), np.asarray(md.vertices)
        V0 = Vd + [0.0, 0.0, ref.first_touch(a, (Vd, md.faces), [0.0, 0.0, 1.0], reach=3.0, tol=1e-4)]
        idx = ref.near_vertices(V0, a, 3.0, every=3)
        M = np.asarray(res["mandible_transform"][0])
        Vc = Vd[idx] @ M[:3, :3].T + M[:3, 3]
        shift, turn = ref.largest_shift(Vc, V0[idx]), ref.rotation_between_deg(Vc, V0[idx])
        print("teeth-only open scan vs design:", shift, "mm", turn, "deg; reported", best["error"])
        assert shift < 0.5 and turn < 1.0  # coarse trees (ε 1 mm)
        assert res["arches"]["maxilla"]["width_mm"] > 40
        cmap = contact_map(res["_model"], res["_handle"], best["pos"], best["quat"], sample=100)
        _map_within_exact_distances(res["_model"], cmap, np.r_[best["pos"], best["quat"]])
        for name in ("maxilla", "mandible"):
            assert any(r["closest_mm"] < 0.05 for r in cmap[name].regions)
        written = contactmap.write(cmap, res["_pair"].frames,
                                   tmp_path / "map")
        assert len(written) == 5 and trimesh.load(written[0]).visual.vertex_colors.shape[1] == 4
    finally:
        res["_handle"].detach()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        assert haptic.main(data=folder, trajectory="close", seconds=0.2, out=tmp_path / "hap", progress=False, pair=opts) == 0
