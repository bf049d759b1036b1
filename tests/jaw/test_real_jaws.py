"""The shared CBCT pair as users bring it: millimetres, +z up, cropped to the teeth.

The closure of a teeth-only pair must rest in its stored occlusion (the condylar guidance holds
the condyles in their seat), and its scene and pair.json say where the hinge came from and how
sure it is. Skipped when ../shared/data is absent.
"""
import json

import mujoco
import numpy as np
import pytest
from conftest import shared_path


def test_teeth_only_closure_rests_in_its_stored_occlusion(teeth_only, cache, tmp_path):
    """MuJoCo's closing muscles drive a free teeth-only mandible back along the cusp inclines
    (2.4 mm without the condylar stop); with it the jaw rests within 0.3 mm of the stored
    occlusion, at rest."""
    from mjist.jaw.demo import run_closure
    from mjist.jaw.scenes import pair_scene
    from mjist.mujoco.attach import load_model

    scene = pair_scene(teeth_only, tmp_path, "closure", progress=False)
    meta = json.loads((tmp_path / "pair.json").read_text())
    assert meta["teeth_only"] and meta["hinge_source"] == "Bonwill estimate" and meta["hinge_uncertainty_mm"] == 10.0
    assert "hinge: Bonwill estimate" in scene.read_text() and "uncertain by about 10 mm" in scene.read_text()
    model, handle = load_model(scene, cache_dir=cache)
    try:
        res = run_closure(model, seconds=0.6, handle=handle)
    finally:
        handle.detach()
    print({k: res[k] for k in ("final_hinge_deg", "final_protrusion_mm", "final_lateral_mm", "drift_mm_s", "settled")})
    assert abs(res["final_protrusion_mm"]) < 0.3 and abs(res["final_lateral_mm"]) < 0.3
    assert res["settled"] and res["true_distance_mm"] > -0.05  # resting on the teeth, not sunk into them


@pytest.mark.slow  # the finding behind the stop; the default set keeps the test with the stop
def test_without_the_condylar_stop_the_teeth_drive_it_back(teeth_only, cache, tmp_path):
    """The finding the guidance answers: the same scene with the plain ±3 mm slide ends far behind."""
    from mjist.jaw.demo import run_closure
    from mjist.jaw.scenes import pair_scene
    from mjist.mujoco.attach import load_model

    scene = pair_scene(teeth_only, tmp_path, "closure", progress=False, condylar_stop=False)
    model, handle = load_model(scene, cache_dir=cache)
    try:
        res = run_closure(model, seconds=0.6, handle=handle)
    finally:
        handle.detach()
    assert res["final_protrusion_mm"] < -1.0
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "protrusion") >= 0


@pytest.mark.shared
def test_pair_given_open_is_closed_about_its_condyles(tmp_path):
    """The stored mandible turned 8° open about its condyles and moved 1 mm forward: moving it up
    first meets the condyles in their fossae (not an arch), so the pair is closed about the
    condyles to where the teeth first touch, and the scene carries that turned pose and leaves the
    condyles' seat to the search."""
    import trimesh

    from mjist.jaw.exact import coal_bvh, coal_distance
    from mjist.jaw.pair import hinge_point, load_pair
    from mjist.jaw.scenes import pair_scene

    src = shared_path("jaw")
    mx = trimesh.load(src / "maxilla.obj", process=False)
    md = trimesh.load(src / "mandible.obj", process=False)
    md.merge_vertices()
    h = hinge_point(md.vertices)
    a = np.radians(8.0)
    O = np.eye(4)
    O[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
    O[:3, 3] = h - O[:3, :3] @ h + (0.0, 0.0, 1e-3)
    md.apply_transform(O)
    mx.export(tmp_path / "maxilla.obj")
    md.export(tmp_path / "mandible.obj")
    Mx, Md, info = load_pair(tmp_path)
    assert info["source"] == "coal first touch closing about the condyles"
    turn = np.degrees(np.arctan2(info["mandible_pose"][2, 1], info["mandible_pose"][1, 1]))
    assert -8.0 < turn < -6.0  # closed most of the 8°: the 1 mm forward shift stops the teeth a little early
    assert info["arches"]["maxilla"].depth > 0.035 and info["arches"]["maxilla"].anterior[2] > 0.99
    gap = coal_distance(coal_bvh(Mx.vertices, Mx.faces), np.eye(4), coal_bvh(Md.vertices, Md.faces), info["mandible_pose"])
    assert abs(gap) < 1e-5  # the teeth touch
    scene = pair_scene(tmp_path, tmp_path / "scene", "occlusion", progress=False)
    model = mujoco.MjModel.from_xml_path(str(scene))  # the turned occlusion is baked into the exported mandible
    assert (tmp_path / "scene" / "mandible.jaw.obj").exists() and model.nmesh == 2
    # given open, the pose says where the condyles were, not where they seat: the search samples it
    assert info["seat_uncertainty"] > 0 and json.loads((tmp_path / "scene" / "pair.json").read_text())["seat_uncertainty_mm"] > 0


@pytest.mark.shared
def test_touch_offset_from_vertex_rays_agrees_with_plain_bisection():
    """The stored CBCT pair moved along +y: the touch found from rays along up through every
    vertex (then a short bisection) is the plain bisection's within its tolerance, apart by
    coal's test there and touching 2 µm further up."""
    import trimesh

    from mjist.jaw import orient
    from mjist.jaw.exact import coal_bvh, coal_collides

    meshes = []
    for name in ("maxilla", "mandible"):
        m = trimesh.load(shared_path("jaw", f"{name}.obj"), force="mesh", process=False)
        m.merge_vertices()
        meshes.append((np.asarray(m.vertices, float), np.asarray(m.faces)))
    bx, bd = coal_bvh(*meshes[0]), coal_bvh(*meshes[1])
    u = np.array([0.0, 1.0, 0.0])
    tol = 1e-6
    rays = orient.touch_offset(bx, bd, u, tol=tol, meshes=meshes)
    plain = orient.touch_offset(bx, bd, u, tol=tol)
    assert abs(rays - plain) <= 2 * tol, (rays, plain)

    def at(t):
        P = np.eye(4)
        P[:3, 3] = t * u
        return coal_collides(bx, np.eye(4), bd, P)

    assert not at(rays) and at(rays + 2 * tol)
