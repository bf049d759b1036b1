"""Command outputs as a report: the meshes to draw (``Layer``), the poses to switch between
(``View``) and the tables, read from the files the command wrote and nothing else.

Every length is in millimetres; display meshes are simplified to ``DISPLAY_FACES`` faces each
(the figures in the tables come from the full meshes, as the command measured them).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# faces per arch drawn in the browser: ~60 k faces turn smoothly in a software-rendered WebGL
# canvas and keep a 220 k-vertex pair's page under 15 MB; more shows finer facets, costs frame rate
DISPLAY_FACES = 60_000
IVORY, BLUE, GREEN = (0.93, 0.87, 0.76), (0.62, 0.74, 0.90), (0.35, 0.75, 0.45)


@dataclass
class Layer:
    """A mesh drawn in the page: vertices (mm, the report's frame), faces, colour and, for a
    contact map, each vertex's band (index into ``Report.legend``)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    colour: tuple = IVORY
    band: np.ndarray | None = None
    opacity: float = 1.0


@dataclass
class View:
    """One pose of the layers: a 4x4 (mm) per moved layer, the hidden ones, and what it shows."""

    label: str
    transforms: dict = field(default_factory=dict)
    hidden: tuple = ()
    note: str = ""


@dataclass
class Report:
    title: str
    kind: str
    summary: list
    layers: list
    views: list
    tables: list  # (title, header, rows)
    legend: list | None = None  # (rgb, label)
    eye: tuple = (0.0, -2.0, 0.7)  # the camera: from the patient's front, a little above


def read_output(out_dir) -> Report:
    """The report of a command's output folder (``occlusion.json``, a wafer's JSON (``wafer.json``
    beside ``wafer.stl``) or ``closure_ist.json`` in ``out_dir``)."""
    out_dir = Path(out_dir)
    wafers = sorted((p for p in out_dir.glob("*.json") if _is_wafer(p)), key=lambda p: p.name != "wafer.json")
    if wafers:  # a wafer's folder may hold the search it was made from: the wafer is what it shows
        return _wafer(out_dir, wafers[0])
    if (out_dir / "occlusion.json").exists():
        return _occlusion(out_dir)
    if (out_dir / "closure_ist.json").exists():
        return _closure(out_dir)
    raise FileNotFoundError(f"{out_dir} holds no occlusion.json, wafer.json or closure_ist.json: give the output folder "
                            "of mjist occlusion, mjist wafer or mjist demo --data")


def _is_wafer(path: Path) -> bool:
    """A wafer's JSON (``mjist wafer`` writes it beside its STL, named after it)."""
    try:
        j = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(j, dict) and {"wafer", "proofs", "mandible_transform", "inputs"} <= j.keys()


# ---- geometry ---------------------------------------------------------------------------


def display_mesh(V, F, band=None, faces: int = DISPLAY_FACES):
    """``V, F`` simplified to about ``faces`` faces (quadric edge collapses, fast-simplification);
    each kept vertex takes the band of the nearest input vertex."""
    V, F = np.asarray(V, float), np.asarray(F, np.int64)
    if len(F) > faces:
        import fast_simplification
        from scipy.spatial import cKDTree

        Vs, Fs = fast_simplification.simplify(V.astype(np.float32), F.astype(np.int32), 1.0 - faces / len(F))
        if band is not None:
            band = band[cKDTree(V).query(Vs)[1]]
        V, F = np.asarray(Vs, float), np.asarray(Fs, np.int64)
    return V, F, band


def _scene_path(out_dir: Path, recorded: str) -> Path:
    p = Path(recorded)
    for cand in (p, out_dir / p.name, out_dir / p):
        if cand.exists():
            return cand
    raise FileNotFoundError(f"the scene {recorded} the command used is gone (nor is {p.name} in {out_dir}): "
                            "rerun the command, or rebuild the report where its scene is")


def _scene_geoms(scene: Path, qpos) -> dict:
    """World vertices (mm), faces and 4x4 pose (mm) of the scene's maxilla and mandible mesh
    geoms at ``qpos`` (MuJoCo's own kinematics; the scene is loaded as plain MuJoCo, nothing
    attached), and the model."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(scene))
    d = mujoco.MjData(m)
    d.qpos[:] = qpos if qpos is not None else m.qpos0
    mujoco.mj_kinematics(m, d)
    out = {}
    for name in ("maxilla", "mandible"):
        g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)
        k = int(m.geom_dataid[g])
        V = m.mesh_vert[m.mesh_vertadr[k]:m.mesh_vertadr[k] + m.mesh_vertnum[k]].astype(float)
        F = m.mesh_face[m.mesh_faceadr[k]:m.mesh_faceadr[k] + m.mesh_facenum[k]].astype(np.int64)
        P = np.eye(4)
        P[:3, :3], P[:3, 3] = d.geom_xmat[g].reshape(3, 3), 1e3 * d.geom_xpos[g]
        out[name] = (V @ (1e3 * P[:3, :3]).T + P[:3, 3], F, P)
    return out, m


def _pose(pos, quat) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    P = np.eye(4)
    P[:3, :3] = Rotation.from_quat(np.asarray(quat, float)[[1, 2, 3, 0]]).as_matrix()
    P[:3, 3] = np.asarray(pos, float) * 1e3
    return P


def _open_book(layers: dict, lateral=(1.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> dict:
    """Transforms that open the arches like a book about the left-right axis: each occlusal
    surface turned a quarter towards the viewer (anterior: ``up × lateral``), the maxilla above."""
    from scipy.spatial.transform import Rotation

    lateral, up = np.asarray(lateral, float), np.asarray(up, float)
    out = {}
    height = max(float(np.ptp(V @ np.cross(up, lateral))) for V, _ in layers.values())
    for name, sign in (("maxilla", 1.0), ("mandible", -1.0)):
        V = layers[name][0]
        c = V.mean(axis=0)
        R = Rotation.from_rotvec(-sign * np.pi / 2 * lateral).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c - R @ c + sign * 0.35 * height * up
        out[name] = T
    return out


# ---- readers ----------------------------------------------------------------------------


def _bands_from_colours(rgb: np.ndarray) -> np.ndarray:
    from ..jaw.contactmap import COLOURS

    d = np.linalg.norm(rgb[:, None, :3] / 255.0 - COLOURS[None], axis=2)
    return np.argmin(d, axis=1).astype(np.int8)


def _legend():
    from ..jaw.contactmap import COLOURS, LABELS

    return [(tuple(c), lab) for c, lab in zip(COLOURS, LABELS)]


def _occlusion(out_dir: Path) -> Report:
    import trimesh

    occ = json.loads((out_dir / "occlusion.json").read_text())
    cands = occ["candidates"]
    if not cands:
        raise ValueError(f"{out_dir / 'occlusion.json'} lists no candidate: nothing to show")
    scene = _scene_path(out_dir, occ["scene"])
    best = cands[0]
    geoms, _ = _scene_geoms(scene, np.r_[best["pos"], best["quat"]])
    bands, legend = {}, None
    cmap = out_dir / "contact_map.json"
    if cmap.exists() and all((out_dir / f"contact_map_{n}.ply").exists() for n in geoms):
        legend = _legend()
        for n in geoms:
            ply = trimesh.load(out_dir / f"contact_map_{n}.ply", process=False)
            if len(ply.vertices) == len(geoms[n][0]):  # the map of these meshes at the best pose
                bands[n] = _bands_from_colours(np.asarray(ply.visual.vertex_colors))
    layers = []
    for n, colour in (("maxilla", IVORY), ("mandible", BLUE)):
        V, F, b = display_mesh(*geoms[n][:2], bands.get(n))
        layers.append(Layer(n, V, F, colour, b))
    Pb = _pose(best["pos"], best["quat"])
    views = []
    amb = occ.get("confidence", {}).get("ambiguous")
    for c in cands:
        T = _pose(c["pos"], c["quat"]) @ np.linalg.inv(Pb)
        e = c.get("error", {})
        note = (f"score {c['score']:.3f}, interocclusal {c['interocclusal_mm']:.3f} mm, {c['starts']} start(s)"
                + (f", {e['max_mm']:.3f} mm / {e['rotation_deg']:.2f}° from the reference" if e else ""))
        label = f"#{c['rank']}" + (" (other basin)" if amb and c["rank"] == 2 else "")
        views.append(View(label, {"mandible": T}, note=note))
    views.append(View("opened", _open_book({L.name: (L.vertices, L.faces) for L in layers}),
                      note="both occlusal surfaces, turned towards you"))
    tables = [_candidate_table(cands), _confidence_table(occ)]
    if cmap.exists():
        tables.append(_map_table(json.loads(cmap.read_text())))
    if occ.get("registration"):
        tables.append(_registration_table(occ))
    summary = [f"{len(cands)} candidate(s) from {occ['starts']} starts ({occ['settled']} settled), "
               f"ε of the trees {occ['error_bound_mm']:.2f} mm: true distances lie in [d − ε, d]",
               "ambiguous: two basins score within the margin" if amb else "clear: the best basin wins by the margin"]
    return Report(f"Occlusion: {out_dir.name}", "occlusion", summary, layers, views, tables, legend)


def _candidate_table(cands):
    rows = []
    for c in cands:
        e = c.get("error", {})
        rows.append([f"#{c['rank']}", f"{c['score']:.3f}", f"{c['interocclusal_mm']:.3f}", f"{100 * c['contact_fraction']:.1f} %",
                     ", ".join(c["regions"]) or "none", str(c["starts"]), "yes" if c["settled"] else "no",
                     f"{e['max_mm']:.3f} / {e['rotation_deg']:.2f}°" if e else "",
                     f"{c['coal_distance_mm']:.4f}" if c.get("coal_distance_mm") is not None else ""])
    return ("Candidates", ["rank", "score", "interocclusal mm", "points in contact", "regions in contact", "starts",
                           "settled", "from reference (mm / °)", "coal distance mm"], rows)


def _confidence_table(occ):
    c = occ.get("confidence", {})
    rows = [[k.replace("_", " "), json.dumps(v) if isinstance(v, (list, dict)) else str(v)] for k, v in c.items()]
    rows += [["trees' ε (mm)", f"{occ['error_bound_mm']:.3f}"], ["seat uncertainty (mm)", str(occ.get("seat_uncertainty_mm"))],
             ["search time (s)", f"{occ['total_s']:.1f}"]]
    return ("Confidence", ["figure", "value"], rows)


def _map_table(cm):
    rows = []
    for n in ("maxilla", "mandible"):
        for r in cm[n]["regions"]:
            lo, hi = r["closest_interval_mm"]
            rows.append([n, r["region"], f"{r['contact_area_mm2']:.2f}", f"{r['certain_contact_area_mm2']:.2f}",
                         f"{r['closest_mm']:.3f}", f"[{lo:.3f}, {hi:.3f}]"])
    return ("Contact map (certified intervals)", ["arch", "region", "contact area mm²", "certain contact mm²", "closest mm",
                                                  "closest, certified mm"], rows)


def _registration_table(occ):
    r, g = occ["registration"], occ.get("given", {})
    rows = [["registration used", str(r.get("used"))], ["docking score (mm)", f"{r.get('score_mm', float('nan')):.3f}"],
            ["runner-up (mm)", str(r.get("runner_up_mm"))], ["seconds", f"{r.get('seconds', 0):.1f}"]]
    if g:
        rows.append(["given touching", str(g.get("touching"))])
        b = g.get("best_from_given")
        if b:
            rows.append(["best from the given pose", f"{b['max_mm']:.2f} mm / {b['rotation_deg']:.2f}°"])
    return ("Registration", ["figure", "value"], rows)


def _wafer(out_dir: Path, path: Path) -> Report:
    from ..geometry.mesh import read_surface

    w = json.loads(path.read_text())
    scale = {"m": 1e3, "mm": 1.0}.get(w["units"], 1.0)
    M = np.asarray(w["mandible_transform"], float)
    mx = read_surface(w["inputs"]["maxilla"])
    md = read_surface(w["inputs"]["mandible"])
    wafer_file = Path(w["wafer"])
    wafer_file = wafer_file if wafer_file.exists() else out_dir / wafer_file.name
    wf = read_surface(wafer_file)
    Vd = np.asarray(md.vertices) @ M[:3, :3].T + M[:3, 3]
    layers = [Layer("maxilla", *display_mesh(np.asarray(mx.vertices) * scale, mx.faces)[:2], IVORY),
              Layer("mandible", *display_mesh(Vd * scale, md.faces)[:2], BLUE),
              Layer("wafer", *display_mesh(np.asarray(wf.vertices) * scale, wf.faces)[:2], GREEN, opacity=0.75)]
    views = [View("seated on the wafer", note=f"opening {w['opening_deg']:.2f}°"),
             View("wafer alone", hidden=("maxilla", "mandible"), note="its imprints face up and down"),
             View("arches only", hidden=("wafer",), note="the mandible where the wafer holds it")]
    p = w["proofs"]
    rows = [["printable", str(p["printable"]["ok"]), f"min thickness {p['printable']['min_thickness_mm']:.3f} mm, "
             f"volume {p['printable']['volume_mm3']:.0f} mm³"]]
    for k, v in p.get("seating", {}).items():
        if isinstance(v, dict):
            rows.append([f"seating: {k}", str(v.get("ok", "")), ", ".join(f"{a} {b:.4g}" for a, b in v.items()
                                                                         if isinstance(b, (int, float)) and not isinstance(b, bool))])
    if "holding" in p:
        h = p["holding"]
        rows.append(["holding", str(h.get("ok")), ", ".join(f"{a} {b:.4g}" for a, b in h.items()
                                                            if isinstance(b, (int, float)) and not isinstance(b, bool))])
    figures = [["opening (°)", f"{w['opening_deg']:.3f}"], ["arch gap (mm)", f"{w['arch_gap_mm']:.3f}"],
               ["clearance (mm)", str(w["inputs"]["clearance_mm"])], ["thickness (mm)", str(w["inputs"]["thickness_mm"])],
               ["all proofs", str(w["ok"])]]
    summary = [f"wafer {wafer_file.name}: {'every proof holds' if w['ok'] else 'a proof FAILS'} (frame: {w['frame']}, {w['units']})"]
    return Report(f"Wafer: {out_dir.name}", "wafer", summary, layers, views,
                  [("Proofs", ["proof", "ok", "figures"], rows), ("Wafer", ["figure", "value"], figures)], eye=(1.6, 1.6, 0.9))


def _closure(out_dir: Path) -> Report:
    res = json.loads((out_dir / "closure_ist.json").read_text())
    if "scene" not in res or "final_qpos" not in res:
        raise ValueError(f"{out_dir / 'closure_ist.json'} records no scene and final pose (written by an older mjist): "
                         "rerun mjist demo --data to get a report")
    scene = _scene_path(out_dir, res["scene"])
    geoms, m = _scene_geoms(scene, np.asarray(res["final_qpos"]))
    layers = [Layer(n, *display_mesh(*geoms[n][:2])[:2], c) for n, c in (("maxilla", IVORY), ("mandible", BLUE))]
    views = [View("closed", note=f"after {res['steps']} steps of {res['timestep'] * 1e3:g} ms")]
    import mujoco

    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "occlusion")
    if k >= 0:
        ref, _ = _scene_geoms(scene, m.key_qpos[k])
        T = ref["mandible"][2] @ np.linalg.inv(geoms["mandible"][2])  # the mandible from rest to the keyframe
        views.append(View("reference occlusion", {"mandible": T}, note="the pair's given occlusion (keyframe)"))
    views.append(View("opened", _open_book({L.name: (L.vertices, L.faces) for L in layers})))
    keys = ("steps", "step_us_median_closed", "final_contacts", "final_hinge_deg", "settled", "true_distance_mm",
            "true_collision", "error_bound_mm")
    rows = [[k.replace("_", " "), f"{res[k]:.4g}" if isinstance(res[k], float) else str(res[k])] for k in keys if k in res]
    summary = [f"jaw closure with {res['contacts']} contacts: {'settled' if res.get('settled') else 'not settled'}, "
               f"coal's distance at rest {res['true_distance_mm']:.4f} mm (ε {res.get('error_bound_mm') or 0:.2f} mm)"]
    return Report(f"Jaw closure: {out_dir.name}", "closure", summary, layers, views, [("Closure", ["figure", "value"], rows)])

