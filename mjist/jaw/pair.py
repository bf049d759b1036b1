"""Jaw-pair helpers: the hinge, the touching pose and a scripted chewing motion.

Frame convention (the shared CBCT pair and the bundled jaws): metres, +y superior
(up), +z anterior (towards the incisors), x left-right. The maxilla is fixed (identity
pose); the mandible moves.
"""
from __future__ import annotations

import numpy as np

from . import BUNDLED, arch, orient
from .exact import coal_bvh, coal_collides, coal_distance, coal_transform  # noqa: F401  (the pair's exact reference)

UP, ANTERIOR = 1, 2


CONDYLE_CAP = 5e-3  # m: the top of each condyle fitted; deeper reaches the neck, shallower is too flat to fit


def _condyle_centre(top: np.ndarray, highest: float) -> np.ndarray:
    """Centre of a condylar head from the vertices of its top cap: a circle fitted in the sagittal
    (up, anterior) plane, at the cap's mean lateral position; the cap's mean when the fit is not a
    condyle-sized circle below the top."""
    A = np.c_[2.0 * top[:, UP], 2.0 * top[:, ANTERIOR], np.ones(len(top))]
    (cy, cz, c), *_ = np.linalg.lstsq(A, (top[:, [UP, ANTERIOR]] ** 2).sum(axis=1), rcond=None)
    r = np.sqrt(max(c + cy * cy + cz * cz, 0.0))
    if len(top) < 10 or not (2e-3 <= r <= 15e-3) or not (0.0 < highest - cy <= r + 1e-3):
        return top.mean(axis=0)
    return np.array([top[:, 0].mean(), cy, cz])


def hinge_point(mandible_vertices) -> np.ndarray:
    """Centre of the condylar axis: midway between the centres of the two condylar heads (the
    highest parts of the posterior quarter of the mandible, ``_condyle_centre``).

    The mandible rotates about the left-right (x) axis through this point when it opens.
    """
    V = np.asarray(mandible_vertices, dtype=np.float64)
    z0, z1 = V[:, ANTERIOR].min(), V[:, ANTERIOR].max()
    post = V[V[:, ANTERIOR] < z0 + 0.25 * (z1 - z0)]
    mid = 0.5 * (V[:, 0].min() + V[:, 0].max())
    centres = []
    for side in (post[post[:, 0] < mid], post[post[:, 0] >= mid]):
        if len(side) == 0:
            raise ValueError("no condyles found: is the mandible in metres with +y up and +z anterior?")
        highest = side[:, UP].max()
        centres.append(_condyle_centre(side[side[:, UP] > highest - CONDYLE_CAP], highest))
    return 0.5 * (centres[0] + centres[1])


def hinge_pose(theta, hinge, lateral=0.0, protrusion=0.0, vertical=0.0) -> np.ndarray:
    """Mandible pose: opening rotation ``theta`` (rad, positive opens) about the x axis through
    ``hinge``, then a translation (lateral x, vertical y, protrusion z)."""
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    P = np.eye(4)
    P[:3, :3] = R
    P[:3, 3] = np.asarray(hinge) - R @ np.asarray(hinge) + [lateral, vertical, protrusion]
    return P


def hinge_touch(bvh_maxilla, bvh_mandible, hinge, reach_deg: float = 25.0, tol_deg: float = 1e-4) -> float:
    """Turn (rad, negative closes) about the jaw frame's x axis through ``hinge`` at which a mandible
    held apart at its file pose first touches the maxilla (coal). Raises ``ValueError`` when it
    touches already or not within ``reach_deg``."""
    def hit(deg):
        return coal_collides(bvh_maxilla, np.eye(4), bvh_mandible, hinge_pose(np.radians(deg), hinge))

    if hit(0.0):
        raise ValueError("the jaws already touch at the stored pose: nothing to close")
    apart, touching = 0.0, -reach_deg
    if not hit(touching):
        raise ValueError(f"the mandible does not reach the maxilla closing {reach_deg:g}° about its condyles")
    while apart - touching > tol_deg:
        mid = 0.5 * (apart + touching)
        if hit(mid):
            touching = mid
        else:
            apart = mid
    return float(np.radians(apart))


def touching_offset(bvh_maxilla, bvh_mandible, max_open=0.01, tol=1e-6) -> float:
    """Vertical mandible offset (m) at which the two meshes just touch, on the separated side:
    ``orient.touch_offset`` along the jaw frame's +y, within ``±max_open`` of the stored pose."""
    return orient.touch_offset(bvh_maxilla, bvh_mandible, np.eye(3)[UP], reach=max_open, tol=tol)


def chewing_motion(n, hinge, *, contact_offset=0.0, open_deg=8.0, excursion=0.003, protrusion=0.003,
                   guidance_deg=1.0) -> np.ndarray:
    """A smooth mandible motion (the paper's hand-recorded motion, scripted): ``(n, 4, 4)`` poses.

    Phases (fractions of ``n``): close from ``open_deg`` to contact (0-0.2), rest (0.2-0.25),
    lateral excursion right and left by ``excursion`` (0.25-0.45), protrusion by
    ``protrusion`` and back (0.45-0.65), re-open (0.65-1). During excursion and protrusion the
    jaw opens by up to ``guidance_deg`` as cusps and incisors guide it. ``contact_offset`` is
    the vertical offset that makes the closed jaws touch (see ``touching_offset``).
    """
    t = np.linspace(0.0, 1.0, n)
    op = np.radians(open_deg)
    theta = np.where(t < 0.2, op * 0.5 * (1 + np.cos(np.pi * np.clip(t / 0.2, 0, 1))), 0.0)
    theta = np.where(t > 0.65, op * 0.5 * (1 - np.cos(np.pi * np.clip((t - 0.65) / 0.35, 0, 1))), theta)
    x = np.where((t > 0.25) & (t < 0.45), excursion * np.sin(2 * np.pi * (t - 0.25) / 0.2), 0.0)
    z = np.where((t > 0.45) & (t < 0.65), protrusion * np.sin(np.pi * (t - 0.45) / 0.2), 0.0)
    guide = np.radians(guidance_deg) * (np.abs(x) / max(excursion, 1e-12) + z / max(protrusion, 1e-12))
    theta = theta + np.where(t <= 0.65, guide, 0.0)
    return np.stack([hinge_pose(a, hinge, lateral=b, protrusion=c, vertical=contact_offset) for a, b, c in zip(theta, x, z)])




MUJOCO_STL_FACES = 200_000  # MuJoCo's binary STL importer refuses more faces


def _find(folder, maxilla, mandible) -> dict:
    from pathlib import Path

    if maxilla is not None or mandible is not None:
        if maxilla is None or mandible is None:
            raise ValueError("pass both maxilla and mandible mesh files (or a folder holding them)")
        paths = {"maxilla": Path(maxilla), "mandible": Path(mandible)}
        for name, p in paths.items():
            if not p.exists():
                raise FileNotFoundError(f"{name} mesh {p} does not exist: check the path")
        return paths
    folder = Path(folder) if folder is not None else BUNDLED
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder} is not a folder: pass the folder of a jaw pair (or --maxilla FILE --mandible FILE)")
    meshes = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    paths = {}
    for name in ("maxilla", "mandible"):
        exact = [p for p in meshes if p.stem.lower() == name]  # maxilla.obj wins over any other name
        found = exact or [p for p in meshes if arch_of(p.name) == name]
        if len(found) > 1:
            raise ValueError(f"several {name} meshes in {folder}: {', '.join(p.name for p in found)}; keep one, or name "
                             "them outright with --maxilla FILE --mandible FILE")
        if not found:
            saw = ", ".join(p.name for p in meshes) or "no STL/OBJ/PLY file"
            raise FileNotFoundError(f"no {name} mesh in {folder} (saw: {saw}): name the arches upper/lower, maxilla/mandible, "
                                    "maxillary/mandibular or UpperJaw/LowerJaw, or pass --maxilla FILE --mandible FILE")
        paths[name] = found[0]
    return paths


MESH_SUFFIXES = (".obj", ".stl", ".ply")
# how scanners, labs and segmentation tools name the arches (any case, any prefix or suffix)
ARCH_WORDS = {"maxilla": ("maxilla", "maxillary", "upper", "oberkiefer"),
              "mandible": ("mandible", "mandibular", "lower", "unterkiefer")}


def arch_of(filename: str) -> str | None:
    """"maxilla", "mandible" or None for a mesh file name (``Case12_UpperJaw.stl`` → "maxilla").

    A name naming both arches (or neither) is None; mjist's own exports (``*.jaw.obj``) are skipped.
    """
    stem = filename.lower()
    if stem.endswith(".jaw.obj"):
        return None
    hits = {arch for arch, words in ARCH_WORDS.items() if any(w in stem for w in words)}
    return hits.pop() if len(hits) == 1 else None


# how far closing an open scan may move it (mm): a segmentation's voxel, well under a cusp's height
MAX_DEVIATION_MM = 0.2


def _load(path, name: str, repair: str, unit: str = "auto", max_deviation_mm: float | None = None):
    """A jaw mesh validated; an open surface closed (``geometry.repair``) when ``repair`` is "auto"
    or "on", moving it by at most ``max_deviation_mm`` (``MAX_DEVIATION_MM``) in the file's
    ``unit`` (detected from its size when "auto")."""
    from ..errors import MeshError
    from ..geometry.mesh import load_mesh, read_surface

    if repair not in ("auto", "on", "off", True, False):
        raise ValueError(f"repair={repair!r}: use auto (close open scans), on or off")
    try:
        return load_mesh(path, repair=False)
    except MeshError as exc:
        if repair in ("off", False) or (repair == "auto" and "not closed" not in str(exc)):
            raise MeshError(f"{name} ({path}): {exc}") from exc
    tm = read_surface(path)
    if unit == "auto":
        unit = orient.unit_of(float(np.ptp(tm.vertices, axis=0).max())) or "mm"
    limit = (MAX_DEVIATION_MM if max_deviation_mm is None else float(max_deviation_mm)) * 1e-3 / orient.UNITS[unit]
    try:
        return load_mesh(tm, repair=True, max_deviation=limit)
    except MeshError as exc:
        raise MeshError(f"{name} ({path}): {exc} (--max-deviation takes millimetres)") from exc


def _closure_notes(raw: dict, o, notes: list) -> None:
    """Warn, in millimetres of the jaw frame, what closing an open scan added."""
    import warnings

    for i, (name, mesh) in enumerate(raw.items()):
        for r in mesh.repairs:
            if "internal walls" in r:  # shells glued together (crowns on gingiva): said, though nothing moved
                notes.append(f"{name}: {r}")
        c = mesh.closure
        if c is None:
            continue
        s = o.scales[i] * 1e3  # file units -> mm
        where = ", ".join(f"{a:.1f}" for a in o.apply(c.added_centre[None], name)[0] * 1e3)
        how = {"meshfix": "MeshFix", "winding": "the winding number"}[c.method]
        left = (f"; left out {c.left_out} loose piece(s) enclosing nothing ({c.left_out_area * s * s:.2f} mm²)"
                if c.left_out else "")
        msg = (f"{name} is an open surface ({c.boundary_edges} open edges in {c.pieces} piece(s)): closed with {how}, which "
               f"moved the scan by at most {c.hausdorff * s:.3f} mm (mean {c.mean_deviation * s:.4f} mm) and added "
               f"{c.added_area * s * s:.1f} mm² around ({where}) mm in the jaw frame{left}. The tree's certified error holds "
               "for the closed surface (add the deviation against the scan); the added faces are not anatomy, so contacts "
               "on them are not real")
        warnings.warn(msg, stacklevel=3)
        notes.append(msg)


def _in_jaw_frame(mesh, o, jaw: str):
    from ..geometry.mesh import Mesh

    s = o.scales[0 if jaw == "maxilla" else 1]
    if o.identity:
        return mesh
    return Mesh(vertices=np.ascontiguousarray(o.apply(mesh.vertices, jaw)), faces=mesh.faces, volume=mesh.volume * s ** 3,
                area=mesh.area * s ** 2, shells=mesh.shells, repairs=mesh.repairs, closure=mesh.closure)


def _orientation(mx, md, units, up, notes: list):
    """Units, up and anterior of the pair (``orient``, ``arch``) and the touching offset along up."""

    unit, ev_u = orient.detect_units(mx.vertices, md.vertices, units)
    sx, sd = orient.scales(unit)
    Vx, Vd = mx.vertices * sx, md.vertices * sd
    bx, bd = coal_bvh(Vx, mx.faces), coal_bvh(Vd, md.faces)
    up_axis, ev_up = orient.detect_up(bx, bd, up)
    u = np.asarray(orient.AXES[up_axis])
    touch = orient.touch_offset(bx, bd, u, meshes=((Vx, mx.faces), (Vd, md.faces)))
    pts = arch.occlusal_points(Vx, Vd + touch * u, md.faces, up=u)
    fx = arch.arch_frame(pts, u)
    if fx.depth < arch.ARCH_MIN_DEPTH:  # they first meet outside the teeth (condyles in their fossae, a pair given open)
        fx = arch.arch_frame(arch.facing_band(Vx, mx.faces, -u), u)
        notes.append("the jaws first meet outside the teeth moving the mandible up (given open?): the arch's front "
                     "comes from the maxilla's occlusal surface")
    anterior = orient.snap(fx.anterior, up_axis)
    detected = {}
    if str(units) == "auto":
        detected["units"] = {"value": unit, "largest_extent_file_units": ev_u["extent"]}
    if up == "auto":
        detected["up"] = {"value": up_axis, **ev_up}
    detected["anterior"] = {"value": [round(float(a), 4) for a in fx.anterior], "snapped": [float(a) for a in anterior]}
    o = orient.Orientation(unit, up_axis, anterior, orient.frame_matrix(up_axis, anterior), (sx, sd), detected)
    ant = next((k for k, v in orient.AXES.items() if np.allclose(v, anterior)), np.round(anterior, 3).tolist())
    notes.append(f"units {unit}{' (detected)' if 'units' in detected else ''}, up {up_axis}"
                 f"{' (detected)' if 'up' in detected else ''}, anterior {ant} (from the arch's shape)")
    return o, touch


def _closed_about_condyles(mx, md, pose, notes: list, info: dict) -> np.ndarray:
    """The occlusion of a pair whose first contact moving the mandible up is not at the teeth (the
    condyles meet their fossae first: a pair given open): the mandible turned closed about its
    condyles from its stored pose to coal's first touch. Other pairs keep ``pose``."""

    Vd = md.vertices @ pose[:3, :3].T + pose[:3, 3]
    up_j = np.array([0.0, 1.0, 0.0])
    if arch.arch_frame(arch.occlusal_points(mx.vertices, Vd, md.faces, up=up_j), up_j).depth >= arch.ARCH_MIN_DEPTH:
        return pose
    fx = arch.arch_frame(arch.facing_band(mx.vertices, mx.faces, -up_j), up_j)
    if not arch.has_rami(md.vertices, fx):
        raise ValueError("the jaws meet outside the teeth when the mandible moves up and the mandible has no condyles "
                         "to close it about: place the arches in occlusion (or pass --hinge)")
    h = hinge_point(md.vertices)
    turn = hinge_touch(coal_bvh(mx.vertices, mx.faces), coal_bvh(md.vertices, md.faces), h)
    notes.append(f"the jaws first meet outside the teeth moving the mandible up: closed {-np.degrees(turn):.2f}° about "
                 "its condyles to where the teeth first touch (coal)")
    info["source"] = "coal first touch closing about the condyles"
    info["seat_uncertainty"] = arch.SEAT_UNCERTAINTY
    return hinge_pose(turn, h)


GIVEN_TOUCHING = 5e-5  # m: arches given within this of each other (coal) are "given touching"
SEPARATE_STEP, SEPARATE_REACH = 5e-4, 0.03  # m: how a registered mandible that overlaps elsewhere is dropped
GIVEN_NEAR_MM = 3.0  # ... and the registration within this of it: the files' pose is an occlusion, searched around
REGISTERED_UP_DEG = 35.0  # a registration's occlusal direction within this of a file axis makes that axis up
GIVEN_OVERLAP = 1e-3  # m: ... unless they still overlap with the mandible this much further down (given through each other)


def _registered(raw: dict, units, notes: list) -> tuple[dict, dict]:
    """The mandible moved onto the maxilla by ``register.register`` from the arches' shapes alone
    (its file's own pose ignored), and what that did: the registration's figures, the transform
    (metres, maxilla file axes) and whether the arches were given touching."""
    import dataclasses

    from .register import register

    unit, _ = orient.detect_units(raw["maxilla"].vertices, raw["mandible"].vertices, units)
    sx, sd = orient.scales(unit)
    mx, md = raw["maxilla"], raw["mandible"]
    reg = register((mx.vertices * sx, mx.faces), (md.vertices * sd, md.faces))
    T = reg.transform
    # given touching: within GIVEN_TOUCHING of each other, and apart once the mandible drops by
    # GIVEN_OVERLAP (two arches given through each other, in unrelated frames, are not touching)
    bx, bd = coal_bvh(mx.vertices * sx, mx.faces), coal_bvh(md.vertices * sd, md.faces)
    drop = np.eye(4)
    drop[:3, 3] = GIVEN_OVERLAP * reg.maxilla.teeth
    touching = (coal_distance(bx, np.eye(4), bd, np.eye(4)) <= GIVEN_TOUCHING
                and not coal_collides(bx, np.eye(4), bd, drop))
    # the docking touched the occlusal surfaces; elsewhere (condyles in their fossae, a coronoid) a
    # registration a few degrees off can overlap: drop the mandible until the whole arches are apart
    down = np.eye(4)
    for _ in range(int(SEPARATE_REACH / SEPARATE_STEP)):
        if not coal_collides(bx, np.eye(4), bd, down @ T):
            break
        down[:3, 3] += SEPARATE_STEP * reg.maxilla.teeth
    T = down @ T
    # how far the registration puts the mandible's arch from where the files have it
    Vm = md.vertices * sd
    arch_pts = Vm[Vm @ reg.mandible.anterior > reg.mandible.origin @ reg.mandible.anterior - 0.06]
    apart_mm = float(np.linalg.norm(arch_pts @ (T[:3, :3] - np.eye(3)).T + T[:3, 3], axis=1).max() * 1e3)
    # given in occlusion: touching where the teeth fit (the registration lands near the given pose;
    # a pair given apart can still touch elsewhere, a condyle against its fossa)
    in_occlusion = bool(touching and apart_mm <= GIVEN_NEAR_MM)
    out = {**reg.as_dict(), "transform": T.tolist(), "given_touching": bool(touching), "used": not in_occlusion,
           "dropped_mm": float(down[:3, 3] @ reg.maxilla.teeth * 1e3), "from_given_mm": apart_mm}
    head = (f"registered the arches from their shapes in {reg.seconds:.1f} s (docking score {reg.score_mm:.3f} mm"
            + (f", runner-up {reg.runner_up_mm:.3f} mm at {reg.runner_up_shift_mm:.1f} mm" if reg.runner_up_mm else "")
            + f"), {apart_mm:.1f} mm from where the files put the mandible")
    if in_occlusion:
        # a pair given in occlusion: its pose (and the condyles' seat with it) is better evidence than
        # the teeth alone, which leave a teeth-only jaw's seat open by a millimetre (BENCHMARKS.md)
        notes.append(head + "; the arches were given in occlusion (touching there): the search starts from that pose")
        return raw, out
    notes.append(head + "; the arches were given " + ("touching elsewhere" if touching else "apart")
                 + ": the search starts from the registration")
    moved = dataclasses.replace(md, vertices=np.ascontiguousarray((md.vertices * sd @ T[:3, :3].T + T[:3, 3]) / sd))
    return {**raw, "mandible": moved}, out


def load_pair(folder=None, *, maxilla=None, mandible=None, units="auto", up="auto", hinge=None, repair="auto",
              max_deviation_mm=None, register: bool = False):
    """A jaw pair in the jaw frame (metres, +y up, +z anterior) and its occlusion.

    Parameters
    ----------
    folder : path, optional
        A folder holding ``maxilla`` and ``mandible`` meshes (``.obj``/``.stl``/``.ply``), e.g.
        ``../shared/data/jaw``; default the bundled jaws. Or give ``maxilla`` and ``mandible`` files.
    units : "auto", "mm", "m" or "mm,m"
        The files' length unit (per jaw when they differ); detected from the jaws' size.
    up : "auto", "+x", "-x", "+y", "-y", "+z" or "-z"
        The file axis pointing superior; detected from how the pair opens (``orient``).
    hinge : (3,), optional
        Centre of the condylar axis, in the maxilla file's coordinates and units. Default: the
        condyles when the mandible has them, else Bonwill's estimate from the incisal point.
    repair : "auto", "on" or "off"
        "auto" closes an open or many-piece surface (a scan, a segmentation; ``geometry.repair``)
        and warns; "on" also fixes winding, inversion and degenerate faces; "off" refuses them.
    max_deviation_mm : float, optional
        The farthest closing may move a scan's vertex (default ``MAX_DEVIATION_MM``).
    register : bool
        Place the mandible against the maxilla from the arches' own shapes
        (``register.register``) unless the files give the arches touching: arches scanned
        separately, in unrelated frames, given open or apart. The returned mandible is then the
        registered one, and ``info["given"]`` (4x4, jaw frame) maps it back to where the files
        put it; ``info["registration"]`` holds how (``used``: whether it placed the mandible).

    Returns
    -------
    maxilla, mandible : mjist.Mesh
        In the jaw frame.
    info : dict
        ``mandible_pose`` (4x4, the occlusion: from ``occlusion.json`` when the folder has one,
        else where coal says the jaws first touch moving the mandible along up), ``hinge``
        (mandible mesh coordinates), ``hinge_source`` and ``hinge_uncertainty`` (m, how far the
        true condylar axis may be: about 10 mm for Bonwill's estimate), ``seat_uncertainty`` (m, how far
        forward or back the condyles may seat in occlusion: ``arch.SEAT_UNCERTAINTY`` for a pair given
        open, else 0), ``orientation``, ``arches`` (each
        arch's frame, ``arch.ArchFrame``), ``teeth_only`` and ``inertial`` (anatomical mass
        properties for a teeth-only mandible), ``paths``, ``notes`` (what was detected or repaired).

    Raises
    ------
    ValueError, MeshError, FileNotFoundError
        Missing files, bad meshes, units or axes that cannot be told or contradict the
        geometry, arches that do not face each other; the message names the flag that fixes it.
    """
    import json


    paths = _find(folder, maxilla, mandible)
    notes: list[str] = []

    given = dict(zip(("maxilla", "mandible"), orient.parse_units(units)))
    raw = {name: _load(p, name, repair, given[name], max_deviation_mm) for name, p in paths.items()}
    registration, up_used = None, up
    if register:
        raw, registration = _registered(raw, units, notes)
        if registration["used"] and up == "auto":
            # the maxilla keeps its file's frame: its up is the file axis nearest the registration's
            # (coal's probe, which reads it from how the pair opens, can be unclear at a registered pose)
            w = -np.asarray(registration["maxilla"]["teeth"])
            k = max(orient.AXES, key=lambda a: float(np.dot(orient.AXES[a], w)))
            if float(np.dot(orient.AXES[k], w)) > np.cos(np.radians(REGISTERED_UP_DEG)):
                up_used = k
    o, touch = _orientation(raw["maxilla"], raw["mandible"], units, up_used, notes)
    _closure_notes(raw, o, notes)
    mx, md = _in_jaw_frame(raw["maxilla"], o, "maxilla"), _in_jaw_frame(raw["mandible"], o, "mandible")
    P = np.eye(4)
    P[UP, 3] = touch
    info = {"mandible_pose": P, "source": "coal first touch", "seat_uncertainty": 0.0}
    meta = paths["maxilla"].parent / "occlusion.json"
    if maxilla is None and not register:  # a pair folder may carry its designed occlusion
        if meta.exists():
            j = json.loads(meta.read_text())
            S = np.eye(4)
            S[:3, :3] = o.scales[0] * o.R
            info = {"mandible_pose": S @ np.array(j["mandible_pose"]) @ np.linalg.inv(S), "source": str(meta), "seat_uncertainty": 0.0,
                    "hinge": o.apply(np.array(j["hinge"])[None], "mandible")[0]}
    pose = info["mandible_pose"]
    up_j = (0.0, 1.0, 0.0)
    if info["source"] == "coal first touch":
        pose = info["mandible_pose"] = _closed_about_condyles(mx, md, pose, notes, info)
    Vd_occ = md.vertices @ pose[:3, :3].T + pose[:3, 3]
    frames = {"maxilla": arch.arch_frame(arch.occlusal_points(mx.vertices, Vd_occ, md.faces, up=up_j), up_j),
              "mandible": arch.arch_frame(arch.occlusal_points(Vd_occ, mx.vertices, mx.faces, up=up_j), up_j)}
    if up == "auto":  # the file names say which jaw is upper; a maxilla with rami is a mandible
        fx = frames["maxilla"]
        below = -float(np.min((mx.vertices - fx.origin) @ fx.up))
        if below > arch.RAMUS_HEIGHT:
            raise ValueError(
                f"the maxilla reaches {below * 1e3:.0f} mm below the occlusal plane, as a mandible's rami do: upper and "
                f"lower jaws swapped? swap the two files, or pass up={o.up} (--up) if the maxilla really is this shape")
    teeth_only = not arch.has_rami(Vd_occ, frames["mandible"])
    to_mesh = np.linalg.inv(pose)  # occlusion -> mandible mesh coordinates
    if hinge is not None:
        h = o.apply(np.asarray(hinge, float)[None], "maxilla")[0]
        info["hinge"], info["hinge_source"] = to_mesh[:3, :3] @ h + to_mesh[:3, 3], "given"
        info["hinge_uncertainty"] = 0.0
    elif "hinge" in info:
        info["hinge_source"], info["hinge_uncertainty"] = "occlusion.json", 0.0
    elif teeth_only:
        h = arch.bonwill_hinge(frames["mandible"])
        info["hinge"], info["hinge_source"] = to_mesh[:3, :3] @ h + to_mesh[:3, 3], "Bonwill estimate"
        info["hinge_uncertainty"] = arch.BONWILL_UNCERTAINTY
    else:
        info["hinge"], info["hinge_source"] = hinge_point(md.vertices), "condyles"
        info["hinge_uncertainty"] = arch.CONDYLE_UNCERTAINTY
    if teeth_only:
        inertial = arch.anatomical_inertia(frames["mandible"])
        inertial["pos"] = to_mesh[:3, :3] @ inertial["pos"] + to_mesh[:3, 3]
        info["inertial"] = inertial
        notes.append(f"teeth-only mandible: hinge from {info['hinge_source']}, mass and inertia of a whole "
                     f"mandible ({arch.MANDIBLE_MASS * 1e3:.0f} g)")
    if registration is not None and registration["used"]:
        # the registered mandible (jaw frame) back to where its file put it: G⁻¹ with G = R T R⁻¹
        R4 = np.eye(4)
        R4[:3, :3] = o.R
        G = R4 @ np.asarray(registration["transform"]) @ R4.T
        info["registration"], info["given"] = registration, np.linalg.inv(G)
        info["seat_uncertainty"] = arch.SEAT_UNCERTAINTY  # the condyles' seat comes from the registration, not the files
    elif registration is not None:
        info["registration"] = registration  # given touching: reported beside the given pose, not used
    info.update(orientation=o, arches=frames, teeth_only=teeth_only, notes=notes,
                paths={k: str(v) for k, v in paths.items()},
                export=bool(registration and registration["used"]) or not o.identity or any(m.closure is not None or m.repairs for m in raw.values())
                or any(p.suffix.lower() == ".stl" and len(m.faces) > MUJOCO_STL_FACES for p, m in zip(paths.values(), raw.values())))
    return mx, md, info
