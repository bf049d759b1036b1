"""Arch files as labs name them, named outright, and conversions that keep a valid mesh valid."""
import numpy as np
import pytest
import trimesh

from mjist import cli
from mjist.geometry.mesh import load_mesh
from mjist.jaw.pair import _find, arch_of, load_pair


@pytest.mark.parametrize("name,arch", [
    ("Case12_UpperJaw.stl", "maxilla"), ("Case12_LowerJaw.stl", "mandible"), ("upper.ply", "maxilla"),
    ("LOWER.PLY", "mandible"), ("p7-Maxillary.obj", "maxilla"), ("scan_mandibular_arch.stl", "mandible"),
    ("maxilla.obj", "maxilla"), ("Oberkiefer.stl", "maxilla"), ("notes.stl", None), ("upper_and_lower.stl", None),
    ("mandible.jaw.obj", None),
])
def test_arch_names(name, arch):
    assert arch_of(name) == arch


def test_folder_of_lab_names_and_ambiguous_or_missing_ones(tmp_path):
    for f in ("Case12_UpperJaw.stl", "Case12_LowerJaw.stl", "Case12_notes.txt"):
        (tmp_path / f).write_text("x")
    found = _find(tmp_path, None, None)
    assert found["maxilla"].name == "Case12_UpperJaw.stl" and found["mandible"].name == "Case12_LowerJaw.stl"
    (tmp_path / "Case13_UpperJaw.stl").write_text("x")
    with pytest.raises(ValueError, match="several maxilla meshes.*Case12_UpperJaw.stl, Case13_UpperJaw.stl.*--maxilla FILE"):
        _find(tmp_path, None, None)
    (tmp_path / "Case13_UpperJaw.stl").unlink()
    (tmp_path / "Case12_LowerJaw.stl").unlink()
    with pytest.raises(FileNotFoundError, match=r"no mandible mesh .*saw: .*Case12_UpperJaw.stl.*upper/lower"):
        _find(tmp_path, None, None)


def test_lab_named_pair_goes_through_the_occlusion_search(tmp_path, cache, monkeypatch):
    """`mjist occlusion --data` on a folder of Case12_UpperJaw.obj / Case12_LowerJaw.obj, no flags
    (but no picture: no GL here); --maxilla/--mandible name the same files outright."""
    import json

    from mjist.jaw import generator

    folder = tmp_path / "case12"
    folder.mkdir()
    maxilla, mandible, meta = generator.generate(1.0)  # the designed jaws at 1 mm spacing: quick trees
    maxilla.export(folder / "Case12_UpperJaw.obj")
    mandible.export(folder / "Case12_LowerJaw.obj")
    (folder / "occlusion.json").write_text(json.dumps({"mandible_pose": np.eye(4).tolist(), "hinge": list(meta["hinge"])}))
    monkeypatch.setenv("MJIST_CACHE", cache)
    out = tmp_path / "occ"
    assert cli.main(["occlusion", "--data", str(folder), "--starts", "4", "--out-dir", str(out), "-q", "--no-contact-map",
                     "--no-picture"]) == 0
    # the answer, judged here: the designed pose at coal's first touch along +y (``_reference``)
    import _reference as ref

    res = json.loads((out / "occlusion.json").read_text())
    a, Vd = (maxilla.vertices, maxilla.faces), np.asarray(mandible.vertices)
    V0 = Vd + [0.0, ref.first_touch(a, (Vd, mandible.faces), [0.0, 1.0, 0.0], reach=3e-3), 0.0]
    idx = ref.near_vertices(V0, a, 3e-3, every=3)
    M = np.asarray(res["mandible_transform"][0])
    Vc = Vd[idx] @ M[:3, :3].T + M[:3, 3]
    shift, turn = ref.largest_shift(Vc, V0[idx]) * 1e3, ref.rotation_between_deg(Vc, V0[idx])
    print("lab-named pair vs design:", shift, "mm", turn, "deg")
    assert shift <= 0.3 and turn <= 1.0  # the bundled design's target (0.2 mm with 64 starts and finer trees)
    # named outright: the same pair options reach the same search (pair_scene(None, maxilla=..., mandible=...))
    args = cli.build_parser().parse_args(["occlusion", "--maxilla", "a.stl", "--mandible", "b.stl"])
    assert cli._pair_options(args)["maxilla"] == "a.stl" and cli._pair_options(args)["mandible"] == "b.stl"
    args = cli.build_parser().parse_args(["occlusion", "--data", str(folder), "--maxilla", "a.stl", "--mandible", "b.stl"])
    with pytest.raises(ValueError, match="either --data FOLDER or --maxilla"):
        cli._pair_options(args)
    assert cli.main(["occlusion", "--maxilla", str(folder / "Case12_UpperJaw.obj"), "-q"]) == 1  # both or neither


def test_conversion_keeps_two_close_vertices_apart(tmp_path):
    """A watertight mandible (mm, +z up) with one edge split 1e-8 of the jaw's size from its end:
    valid as given, and still valid (no zero-area face) after mjist converts it to metres."""
    from mjist.jaw.scenes import pair_scene

    S = np.diag([1000.0, 1000.0, 1000.0, 1.0])
    S[:3, :3] = 1000.0 * np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # jaw frame (m) -> mm, +z up
    from mjist.jaw import generator

    mx, md, _ = generator.generate(1.0)  # the designed jaws at 1 mm spacing (metres, jaw frame)
    for m in (mx, md):
        m.apply_transform(S)
    V, F = np.asarray(md.vertices), np.asarray(md.faces)
    a, b = F[0, 0], F[0, 1]  # split edge ab (both faces on it) by a vertex 1e-8 of the size from a
    size = float(np.ptp(V, axis=0).max())
    c = len(V)
    V = np.vstack([V, V[a] + (V[b] - V[a]) / np.linalg.norm(V[b] - V[a]) * 1e-8 * size])
    faces = []
    for f in F:
        i = [int(x) for x in f]
        k = next((j for j in range(3) if {i[j], i[(j + 1) % 3]} == {a, b}), None)
        if k is None:
            faces.append(i)
            continue
        p, q, r = i[k], i[(k + 1) % 3], i[(k + 2) % 3]
        faces += [[p, c, r], [c, q, r]]
    split = trimesh.Trimesh(V, np.array(faces), process=False)
    assert split.is_watertight and len(split.faces) == len(F) + 2
    folder = tmp_path / "pair"
    folder.mkdir()
    mx.export(folder / "maxilla.obj")
    split.export(folder / "mandible.obj", digits=10)  # OBJ text keeps it (float32 PLY/STL could not)
    load_mesh(folder / "mandible.obj")  # valid as given
    _, _, info = load_pair(folder)
    assert info["orientation"].units == "mm"
    scene = pair_scene(folder, tmp_path / "scene", "closure", progress=False)
    exported = load_mesh(tmp_path / "scene" / "mandible.jaw.obj")  # raises on a zero-area face
    assert len(split.faces) - 2 <= len(exported.faces) <= len(split.faces)  # at most the sliver pair MuJoCo could not hold
    import mujoco

    from mjist.mujoco.scene import mesh_of

    model = mujoco.MjModel.from_xml_path(str(scene))  # what the scene's tree is built from: MuJoCo's float32 vertices
    load_mesh(mesh_of(model, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "mandible")))
