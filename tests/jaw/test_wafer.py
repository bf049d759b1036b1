"""Surgical wafers (``mjist wafer``): the three proofs checked from the written files alone.

Each check reads ``wafer.stl``, the pair's mesh files as stored and ``mandible_transform`` from
``wafer.json``, and measures with trimesh, coal and its own MuJoCo scene, not with the code that
made the wafer: closed and embedded (winding numbers), thick enough between its faces, no arch
inside it, every cusp tip the wafer covers at the clearance, and the mandible held under pushes.
"""
import json
from types import SimpleNamespace

import coal
import mujoco
import numpy as np
import pytest
import trimesh
from conftest import winding_numbers

from mjist.jaw import BUNDLED
from mjist.jaw.exact import coal_bvh
from mjist.jaw.wafer import holding as hold
from mjist.jaw.wafer import job, seating

CLEARANCE, THICKNESS = 0.1, 1.5  # mm, the defaults


def _read(path, scale=1.0):
    m = trimesh.load(path, force="mesh")
    m.apply_scale(scale)
    return m


def _check_printable(wafer: trimesh.Trimesh, up, thickness):
    """Closed, one body, positive volume, embedded; upper and lower faces a thickness apart."""
    assert wafer.is_watertight and wafer.is_winding_consistent and wafer.body_count == 1 and wafer.volume > 0
    rng = np.random.default_rng(0)
    f = rng.choice(len(wafer.faces), 60, replace=False)
    c, n = wafer.triangles_center[f], wafer.face_normals[f]
    eps = 1e-3 * thickness
    w = winding_numbers(np.vstack([c + eps * n, c - eps * n]), wafer.vertices, wafer.faces)
    assert np.allclose(w[:60], 0.0, atol=0.02) and np.allclose(w[60:], 1.0, atol=0.02)  # no part inside another
    cos = wafer.face_normals @ up
    wall = np.abs(cos) < 1e-6
    on_wall = np.zeros(len(wafer.vertices), bool)
    on_wall[wafer.faces[wall].ravel()] = True
    free = ~on_wall[wafer.faces].any(axis=1)
    upper, lower = wafer.faces[(cos > 0.3) & free], wafer.faces[(cos < -0.3) & free]
    d = coal.distance(coal_bvh(wafer.vertices, upper), coal.Transform3s(), coal_bvh(wafer.vertices, lower),
                      coal.Transform3s(), coal.DistanceRequest(), coal.DistanceResult())
    assert d >= thickness * (1 - 1e-6), f"upper and lower faces {d:.4f} apart"
    # the rim: each wall column (vertices sharing a place across up) is as tall as the thickness
    W = wafer.vertices[on_wall]
    flat = np.round((W - np.outer(W @ up, up)) / (1e-6 * thickness)).astype(np.int64)
    _, col = np.unique(flat, axis=0, return_inverse=True)
    h = W @ up
    heights = np.full(col.max() + 1, -np.inf)
    lows = np.full(col.max() + 1, np.inf)
    np.maximum.at(heights, col.ravel(), h)
    np.minimum.at(lows, col.ravel(), h)
    assert (heights - lows).min() >= thickness * (1 - 1e-6)


def _tips(arch: trimesh.Trimesh, wafer, facing, reach):
    """The arch's vertices turned towards the wafer (``facing``) within ``reach`` of it that are
    the nearest such vertex to it within three times ``reach`` across: its cusp tips over the wafer."""
    from scipy.spatial import cKDTree

    V = arch.vertices[arch.vertex_normals @ facing > 0.5]
    near = cKDTree(wafer.vertices).query(V, distance_upper_bound=2 * reach)[0] < np.inf  # coarse cut
    V = V[near]
    d = trimesh.proximity.closest_point(wafer, V)[1]
    keep = d < reach
    V, d = V[keep], d[keep]
    flat = V - np.outer(V @ facing, facing)
    tree = cKDTree(flat)
    tip = np.array([d[i] <= d[tree.query_ball_point(flat[i], 3.0 * reach)].min() for i in range(len(V))], bool)
    return V[tip], d[tip]


def _check_seating(maxilla, mandible, wafer, up, clearance):
    """coal: neither arch overlaps the wafer; the cusp tips the wafer covers lie at the clearance
    and at heights over a millimetre apart (imprints, not a flat plate)."""
    bw = coal_bvh(wafer.vertices, wafer.faces)
    for arch in (maxilla, mandible):
        req, res = coal.CollisionRequest(), coal.CollisionResult()
        coal.collide(coal_bvh(arch.vertices, arch.faces), coal.Transform3s(), bw, coal.Transform3s(), req, res)
        assert not res.isCollision()
    reach = 5.0 * clearance  # tips within this of the wafer: the ones it covers
    for arch, facing in ((maxilla, -up), (mandible, up)):
        P, d = _tips(arch, wafer, facing, reach)
        assert len(P) >= 6, f"only {len(P)} cusp tips over the wafer"
        assert d.min() > 0.0 and d.max() <= clearance + seating.TIP_SLACK_MM, d.max()
        assert np.ptp(P @ up) > 10 * clearance  # the tips' heights differ by over a millimetre


def _hold(files, mandible_transform, scale, up, forward, left, cache, whole_mandible=False):
    """The mandible (its file at ``mandible_transform``) closed onto the wafer with 50 N and pushed
    with 20 N each way, in a scene of the three files made here (slides and a ball joint damped as
    soft tissue): the largest drift of its teeth from the planned pose (mm). ``whole_mandible``:
    a teeth-only file gets a whole mandible's mass (110 g) at its middle."""
    body = 'density="1900"'
    if whole_mandible:
        c = _read(files["mandible"], scale).bounds.mean(axis=0)
        body = f'mass="0" density="0"/>\n      <inertial pos="{c[0]} {c[1]} {c[2]}" mass="0.11" diaginertia="8e-5 1.6e-4 1.3e-4"'

    xml = f"""<mujoco>
  <option timestep="{hold.TIMESTEP}" gravity="0 0 0"/>
  <default><geom solref="{hold.SOLREF[0]} {hold.SOLREF[1]}" friction="0.1"/></default>
  <asset>
    <mesh name="maxilla" file="{files['maxilla']}" scale="{scale} {scale} {scale}"/>
    <mesh name="wafer" file="{files['wafer']}" scale="{scale} {scale} {scale}"/>
    <mesh name="mandible" file="{files['mandible']}" scale="{scale} {scale} {scale}"/>
  </asset>
  <worldbody>
    <geom name="maxilla" type="mesh" mesh="maxilla"/>
    <geom name="wafer" type="mesh" mesh="wafer"/>
    <body name="mandible">
      <joint type="slide" axis="1 0 0" damping="3"/><joint type="slide" axis="0 1 0" damping="3"/>
      <joint type="slide" axis="0 0 1" damping="3"/><joint type="ball" damping="0.003"/>
      <geom name="mandible" type="mesh" mesh="mandible" {body}/>
    </body>
  </worldbody>
</mujoco>"""
    import mjist

    model = mujoco.MjModel.from_xml_string(xml)
    handle = mjist.attach(model, narrowphase="surface", contacts=hold.CONTACTS, max_error=3e-4,
                          surface_groups=hold.SURFACE_GROUPS, cache_dir=cache)
    try:
        d = mujoco.MjData(model)
        T = np.asarray(mandible_transform, float)
        T[:3, 3] *= scale
        from scipy.spatial.transform import Rotation

        x, y, z, w = Rotation.from_matrix(T[:3, :3] / np.cbrt(np.linalg.det(T[:3, :3]))).as_quat()
        d.qpos[:7] = [*T[:3, 3], w, x, y, z]  # three slides, then the ball joint's quaternion
        mujoco.mj_forward(model, d)
        b = model.body("mandible").id
        m = model.mesh("mandible").id
        V = model.mesh_vert[model.mesh_vertadr[m]:model.mesh_vertadr[m] + model.mesh_vertnum[m]].astype(float)
        g, gw = model.geom("mandible").id, model.geom("wafer").id
        centre = d.geom_xpos[gw].copy()

        def points():
            return d.geom_xpos[g] + V @ d.geom_xmat[g].reshape(3, 3).T

        wm = model.mesh("wafer").id
        W = model.mesh_vert[model.mesh_vertadr[wm]:model.mesh_vertadr[wm] + model.mesh_vertnum[wm]].astype(float)
        W = d.geom_xpos[gw] + W @ d.geom_xmat[gw].reshape(3, 3).T
        lo, hi = W.min(axis=0) - 1e-3, W.max(axis=0) + 1e-3
        start = points()
        teeth = np.all((start >= lo) & (start <= hi), axis=1)  # the mandible's teeth about the wafer
        V, start = V[teeth], start[teeth]
        worst = 0.0
        steps = int(0.15 / model.opt.timestep)  # a push ramps over 0.15 s, holds 0.075 s, then rests
        for F in (0.0 * up, forward, -forward, left, -left):
            for k in range(2 * steps):
                push = 20.0 * F * min(1.0, k / steps) if k < steps * 1.5 else 0.0 * F
                f = 50.0 * up + push
                d.xfrc_applied[b, :3] = f
                d.xfrc_applied[b, 3:] = np.cross(centre - d.xipos[b], f)
                mujoco.mj_step(model, d)
                if k % 20 == 0:
                    worst = max(worst, float(np.linalg.norm(points() - start, axis=1).max()) * 1e3)
        return worst
    finally:
        handle.detach()


@pytest.fixture(scope="module")
def bundled(tmp_path_factory, cache):
    out = tmp_path_factory.mktemp("wafer") / "wafer.stl"
    res = job.make(None, output=out, picture=False, progress=False, cache_dir=cache)
    return out, res


@pytest.mark.slow
def test_bundled_wafer_prints_seats_and_holds(bundled, cache):
    out, res = bundled
    meta = json.loads(out.with_suffix(".json").read_text())
    up = np.array([0.0, 1.0, 0.0])  # the bundled files: metres, +y up
    wafer = _read(out, 1e3)  # checked in mm
    _check_printable(wafer, up, THICKNESS)
    maxilla = _read(BUNDLED / "maxilla.obj", 1e3)
    mandible = _read(BUNDLED / "mandible.obj")
    mandible.apply_transform(meta["mandible_transform"])
    mandible.apply_scale(1e3)
    _check_seating(maxilla, mandible, wafer, up, CLEARANCE)
    assert res["ok"] and meta["opening_deg"] > 0 and meta["units"] == "m"
    obj = out.with_suffix(".obj")  # MuJoCo's STL reader takes at most 200 k faces
    _read(out).export(obj)
    drift = _hold({"maxilla": BUNDLED / "maxilla.obj", "mandible": BUNDLED / "mandible.obj", "wafer": obj},
                  meta["mandible_transform"], 1.0, up, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), cache)
    assert 0.5 * CLEARANCE <= drift <= hold.HOLD_MM, drift  # closes through the clearance, then holds


def _slab(centre):
    """A 60 x 10 x 50 mm box with vertices every 1-2 mm (the wafer reads arches by their vertices)."""
    b = trimesh.creation.box((0.06, 0.01, 0.05))
    for _ in range(5):
        b = b.subdivide()
    b.apply_translation(centre)
    return b


def test_too_thin_an_opening_is_refused_with_the_fix():
    from mjist.jaw.wafer.shape import shape

    upper = _slab((0.0, 0.0055, 0.0))  # 0.5 mm above the lower one
    lower = _slab((0.0, -0.005, 0.0))
    args = ((upper.vertices, upper.faces), (lower.vertices, lower.faces), (0, 1, 0), (0, 0, 1), (0, 0.03, -0.08), (1, 0, 0))
    with pytest.raises(ValueError, match="leave --opening out"):
        shape(*args, opening_deg=0.2)
    w = shape(*args)  # the smallest opening that fits: the faces a thickness apart, flat
    assert w.opening_source == "smallest" and w.opening_deg > 0.2


def test_arches_apart_are_refused_with_the_fix():
    from mjist.jaw.wafer.shape import shape

    box = _slab((0.0, 0.0, 0.0))
    low = _slab((0.0, -0.04, 0.0))
    with pytest.raises(ValueError, match="apart at the given occlusion.*--search"):
        shape((box.vertices, box.faces), (low.vertices, low.faces), (0, 1, 0), (0, 0, 1), (0, 0.05, -0.05), (1, 0, 0))


def test_a_pose_file_of_another_pair_is_refused(tmp_path):
    jp = SimpleNamespace(reference_pos=np.zeros(3), hinge=np.array([0.0, 0.03, -0.04]))
    f = tmp_path / "occlusion.json"
    f.write_text(json.dumps({"reference_pos": [0.001, 0, 0], "hinge": [0.0, 0.03, -0.04],
                             "candidates": [{"pos": [0, 0, 0], "quat": [1, 0, 0, 0]}]}))
    with pytest.raises(ValueError, match="another pair"):
        job._candidate_pose(jp, f)
    f.write_text(json.dumps({"reference_pos": [0, 0, 0], "hinge": [0, 0.03, -0.04], "candidates": []}))
    with pytest.raises(ValueError, match="no candidates"):
        job._candidate_pose(jp, f)


def test_cli_names_open_meshes_and_conflicting_sources(tmp_path, capsys):
    from mjist.cli import main

    sphere = trimesh.creation.icosphere(3, radius=0.02)
    open_ = trimesh.Trimesh(sphere.vertices, sphere.faces[:-20])
    for name in ("maxilla", "mandible"):
        open_.export(tmp_path / f"{name}.stl")
    assert main(["wafer", str(tmp_path), "--repair", "off", "--no-picture", "-o", str(tmp_path / "w.stl")]) == 1
    err = capsys.readouterr().err
    assert "maxilla" in err and "not closed" in err
    with pytest.raises(SystemExit):
        main(["wafer", "--pose", "x.json", "--search"])


def test_real_teeth_in_mm_z_get_a_wafer_that_prints_seats_and_holds(teeth_only, tmp_path, cache):
    """The stored occlusion of the real pair, brought as mm/+z teeth: the wafer comes out in mm
    with +z up, lies between the files as they are, prints, seats, and holds the mandible in a
    scene made here of the three files."""
    out = tmp_path / "wafer.stl"
    job.make(teeth_only, output=out, hold=False, picture=False, progress=False, cache_dir=cache)  # held below
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["units"] == "mm"
    up = np.array([0.0, 0.0, 1.0])
    wafer = _read(out)
    _check_printable(wafer, up, THICKNESS)
    maxilla = _read(teeth_only / "maxilla.stl")
    mandible = _read(teeth_only / "mandible.stl")
    mandible.apply_transform(meta["mandible_transform"])
    _check_seating(maxilla, mandible, wafer, up, CLEARANCE)
    # between the arches: the wafer's heights lie between the maxilla's lowest and the mandible's highest teeth
    z = wafer.vertices[:, 2]
    assert mandible.vertices[:, 2].max() > z.min() and maxilla.vertices[:, 2].min() < z.max()
    assert 1.0 < meta["opening_deg"] < 8.0
    obj = out.with_suffix(".obj")  # MuJoCo's STL reader takes at most 200 k faces
    wafer.export(obj)
    # the converted files: x left, y posterior, z up
    drift = _hold({"maxilla": teeth_only / "maxilla.stl", "mandible": teeth_only / "mandible.stl", "wafer": obj},
                  meta["mandible_transform"], 1e-3, up, np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0]), cache,
                  whole_mandible=True)
    assert 0.5 * CLEARANCE <= drift <= hold.HOLD_MM, drift  # closes through the clearance, then holds
