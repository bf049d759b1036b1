"""Every bad input raises MeshError naming the defect and the fix."""
import numpy as np
import pytest
import trimesh

import mjist
from mjist import MeshError, load_mesh


def box():
    return trimesh.creation.box(extents=(1.0, 2.0, 3.0))


def test_valid_box_and_multiple_shells():
    m = load_mesh(box())
    assert m.shells == 1 and m.volume == pytest.approx(6.0)
    a = box()
    b = box()
    b.apply_translation([5, 0, 0])
    m2 = load_mesh(trimesh.util.concatenate([a, b]))
    assert m2.shells == 2 and m2.volume == pytest.approx(12.0)


def test_tuple_input_and_split_vertices_are_merged():
    b = box()
    soup = b.vertices[b.faces].reshape(-1, 3)  # STL-like triangle soup
    m = load_mesh((soup, np.arange(len(soup)).reshape(-1, 3)))
    assert len(m.vertices) == 8 and m.volume == pytest.approx(6.0)


def test_empty():
    with pytest.raises(MeshError, match="empty"):
        load_mesh((np.zeros((0, 3)), np.zeros((0, 3), int)))


def test_nan():
    b = box()
    v = b.vertices.copy()
    v[2, 1] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        load_mesh((v, b.faces))


def test_bad_shapes_and_indices():
    with pytest.raises(MeshError, match="shapes"):
        load_mesh((np.zeros((4, 2)), np.zeros((1, 3), int)))
    with pytest.raises(MeshError, match="outside"):
        load_mesh((np.zeros((3, 3)), np.array([[0, 1, 5]])))
    with pytest.raises(MeshError, match="integer"):
        load_mesh((np.zeros((3, 3)), np.zeros((1, 3))))
    with pytest.raises(MeshError, match="cannot use"):
        load_mesh(42)


def test_open_mesh_and_repair():
    b = box()
    hole = b.area_faces[0]
    b.update_faces(np.arange(1, len(b.faces)))  # drop one triangle: a hole
    with pytest.raises(MeshError, match="not closed.*open .boundary. edges.*repair=True"):
        load_mesh(b)
    fixed = load_mesh(b, repair=True)
    assert fixed.volume == pytest.approx(6.0)
    assert any("closed 3 open edges" in r for r in fixed.repairs)
    assert fixed.closure.added_area == pytest.approx(hole, rel=1e-6)


def test_non_manifold():
    a = box()
    # a third face on an existing edge: the edge is shared by more than two faces
    v = np.vstack([a.vertices, [[5.0, 5.0, 5.0]]])
    f = np.vstack([a.faces, [[a.faces[0, 0], a.faces[0, 1], len(a.vertices)]]])
    with pytest.raises(MeshError, match="non-manifold"):
        load_mesh((v, f))


def test_inconsistent_winding_and_repair():
    b = box()
    f = b.faces.copy()
    f[0] = f[0, ::-1]
    with pytest.raises(MeshError, match="consistently wound"):
        load_mesh((b.vertices, f))
    fixed = load_mesh((b.vertices, f), repair=True)
    assert fixed.volume == pytest.approx(6.0)


def test_inside_out_and_repair():
    b = box()
    with pytest.raises(MeshError, match="inside out"):
        load_mesh((b.vertices, b.faces[:, ::-1]))
    assert load_mesh((b.vertices, b.faces[:, ::-1]), repair=True).volume == pytest.approx(6.0)


def test_degenerate_faces_and_repair():
    b = box()
    v = np.vstack([b.vertices, b.vertices[b.faces[0]].mean(0)])
    # split face 0 into three, one of which is a sliver of zero area on an edge
    f0 = b.faces[0]
    c = len(b.vertices)
    f = np.vstack([b.faces[1:], [[f0[0], f0[1], c], [f0[1], f0[2], c], [f0[2], f0[0], c], [f0[0], f0[0], f0[1]]]])
    with pytest.raises(MeshError, match="degenerate"):
        load_mesh((v, f))
    fixed = load_mesh((v, f), repair=True)
    assert fixed.volume == pytest.approx(6.0)


def test_flat_mesh():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2], [2, 1, 0], [2, 3, 1]])
    with pytest.raises(MeshError):
        load_mesh((v, f))


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(MeshError, match="does not exist"):
        load_mesh(tmp_path / "nope.stl")
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    with pytest.raises(MeshError):
        load_mesh(bad)


def test_build_rejects_units_mismatch():
    with pytest.raises(ValueError, match="units"):
        mjist.build(box(), max_error=5.0)
    with pytest.raises(ValueError, match="units"):
        mjist.build(box(), max_error=1e-9)
    with pytest.raises(ValueError, match="positive"):
        mjist.build(box(), max_error=-1.0)
    with pytest.raises(ValueError, match="branching"):
        mjist.build(box(), branching=1)


def test_slivers_float32_flattens_are_flipped_away_and_the_surface_stays_closed():
    """A closed mesh with a sliver whose middle corner lies 1e-9 m off its long edge: float32
    rounding puts the three corners on one line (zero area, which the tree build refuses);
    single_precision flips it away with its neighbour, keeping the surface closed and wound."""
    import trimesh

    from mjist.geometry.mesh import degenerate_faces, single_precision

    tet = trimesh.Trimesh([[0.05, 0.05, 0.05], [0.0500001, 0.05, 0.05], [0.05, 0.06, 0.05], [0.05, 0.05, 0.06]],
                          [[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]], process=False)
    tet.fix_normals()
    V = np.vstack([tet.vertices, [0.05000005, 0.05 + 1e-9, 0.05]])  # m: on edge 0-1 in float32, not in float64
    F = [list(f) for f in tet.faces]
    f = next(i for i, t in enumerate(F) if {0, 1} <= set(t) and 2 in t)
    a, b, c = F[f]
    while {a, b} != {0, 1}:
        a, b, c = b, c, a  # rotate so that a -> b is the edge 0-1 in the face's winding
    F[f:f + 1] = [[a, 4, c], [4, b, c], [a, b, 4]]  # the face split at m, with the sliver a b m
    F = np.array(F)
    assert not degenerate_faces(V, F).any()  # fine in float64
    assert degenerate_faces(V.astype(np.float32).astype(float), F).sum() == 1  # flat in float32
    W, G, removed, flipped = single_precision(V, F)
    assert (removed, flipped) == (0, 1) and len(G) == len(F)
    assert not degenerate_faces(W, G).any()
    m = trimesh.Trimesh(W, G, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
