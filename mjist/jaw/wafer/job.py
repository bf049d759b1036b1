"""``mjist wafer``: a surgical wafer made at a pair's occlusion, proved, and written in the
maxilla file's own frame and units.

The occlusion comes from the pair as stored (``occlusion.json`` of a pair folder, else where
coal says the teeth first touch), from an ``mjist occlusion`` result (``--pose``) or from a
fresh search (``--search``). Everything is computed in the occlusion scene's world (metres,
+z up) and turned back into the maxilla file's frame once, at the end:

* ``A_x`` maps the maxilla file into the world (the orientation ``pair.json`` records, then the
  scene's 90° turn about x); ``A_d`` maps the mandible file to its reference occlusion in the
  world;
* the wafer's mandible pose is ``X = open · P_c · P_ref⁻¹`` (the candidate's geom pose against
  the reference, then the opening about the hinge), so the mandible file's vertices seat on the
  wafer at ``mandible_transform = A_x⁻¹ · X · A_d`` in the maxilla file's frame.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from ..scenepair import apply_pose, file_maps
from . import outline
from .holding import HOLD_DEG, HOLD_MM, holding
from .printable import printable
from .seating import PENETRATION_MM, TIP_SLACK_MM, seating
from .shape import shape


def _candidate_pose(jp, pose_file) -> tuple[np.ndarray, str]:
    """The mandible geom's world pose of an ``mjist occlusion`` result's best candidate."""
    try:
        res = json.loads(Path(pose_file).read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"--pose {pose_file}: no such file (an occlusion.json written by mjist occlusion)") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"--pose {pose_file} is not JSON ({exc}): pass the occlusion.json mjist occlusion wrote") from None
    if not res.get("candidates"):
        raise ValueError(f"--pose {pose_file} has no candidates: the search found no occlusion; rerun it (mjist occlusion) "
                         "or use --search")
    ref = np.asarray(res.get("reference_pos", [np.nan] * 3), float)
    hinge = np.asarray(res.get("hinge", [np.nan] * 3), float)
    if not (np.allclose(ref, jp.reference_pos, atol=1e-6) and np.allclose(hinge, jp.hinge, atol=1e-6)):
        raise ValueError(f"--pose {pose_file} was made for another pair or scene (its reference occlusion or hinge differs): "
                         "run mjist occlusion on this pair with the same options, or use --search")
    best = res["candidates"][0]
    return jp.pose(best["pos"], best["quat"]), f"{pose_file} (candidate #1)"


def make(folder=None, *, output="out/wafer/wafer.stl", pose=None, search: bool = False, opening_deg=None,
         clearance_mm: float = 0.1, thickness_mm: float = 1.5, pair: dict | None = None, hold: bool = True,
         picture: bool = True, starts: int = 64, seed: int = 0, threads=None, progress: bool = True, cache_dir=None,
         scene=None) -> dict:
    """Make, prove and write a wafer for the jaw pair in ``folder`` (default the bundled pair).

    Parameters
    ----------
    scene : path, optional
        The pair's occlusion-search scene with its ``pair.json`` (``scenes.pair_scene``), when
        it exists already (a cohort's patient); else it is written beside ``output``.
    pose : path, optional
        An ``occlusion.json`` from ``mjist occlusion`` on the same pair: its best candidate.
    search : bool
        Search the occlusion first (``occlusion.search``; ``starts``, ``seed``, ``threads``).
        Without ``pose`` or ``search`` the pair's own occlusion is used.
    opening_deg : float, optional
        The mandible's opening about the hinge; default the smallest that leaves ``thickness_mm``.
    clearance_mm, thickness_mm : float
        Gap between each arch and its imprint; the wafer's minimum thickness.
    pair : dict, optional
        ``load_pair`` options (units, up, hinge, repair, max_deviation_mm, maxilla, mandible).
    hold : bool
        Run the holding proof in MuJoCo.

    Returns
    -------
    dict
        What ``wafer.json`` holds: inputs, opening, ``mandible_transform``, volume, bounding
        box, minimum thickness, the three proofs, timings and the files written.
    """
    from ..scenepair import HINGE_AXIS
    from ..scenes import pair_scene

    if pose is not None and search:
        raise ValueError("pass either --pose occlusion.json or --search, not both")
    if folder is not None and (pair or {}).get("maxilla"):
        raise ValueError("pass either the pair's FOLDER or --maxilla FILE --mandible FILE, not both")
    if not clearance_mm >= 0 or not thickness_mm > 0:
        raise ValueError(f"--clearance {clearance_mm} and --thickness {thickness_mm}: the clearance must be ≥ 0 mm and the "
                         "thickness > 0 mm")
    t0 = time.perf_counter()
    output = Path(output)
    work = output.parent / f"{output.stem}_work"
    os.makedirs(work, exist_ok=True)
    if scene is None:
        scene = pair_scene(folder, work, "occlusion", progress=progress, **dict(pair or {}))
    scene = Path(scene)
    meta = json.loads((scene.parent / "pair.json").read_text())
    timings = {"scene_s": time.perf_counter() - t0}
    jp, Pc, source, res = _occlusion(scene, meta, pose, search, starts, seed, threads, progress, cache_dir, timings)
    fx = jp.frames["maxilla"]
    t2 = time.perf_counter()
    (Vx, Fx), (Vd, Fd) = jp.maxilla, jp.mandible
    w = shape((apply_pose(jp.maxilla_pose, Vx), Fx), (apply_pose(Pc, Vd), Fd), fx.up, fx.anterior, jp.hinge, HINGE_AXIS,
              clearance=clearance_mm * 1e-3, thickness=thickness_mm * 1e-3, opening_deg=opening_deg)
    timings["shape_s"] = time.perf_counter() - t2
    X = w.mandible_pose @ Pc @ np.linalg.inv(jp.reference)  # world: reference occlusion -> seated on the wafer
    in_file = _FileFrame(meta, X)
    proofs, world_file = _proofs(w, in_file, jp, meta, work, timings)
    planned = jp.body(X @ jp.reference)  # the mandible body seated on the wafer
    if hold:
        t5 = time.perf_counter()
        centre = 0.5 * (w.vertices.min(axis=0) + w.vertices.max(axis=0))
        proofs["holding"] = holding(scene, world_file, planned, w.cusps["mandible"], centre,
                                    {"up": fx.up, "forward": fx.anterior, "left": fx.left},
                                    cache_dir=cache_dir, progress=progress, threads=threads)
        timings["holding_s"] = time.perf_counter() - t5
    out = _record(w, in_file, meta, output, source, proofs, res, clearance_mm, thickness_mm, opening_deg)
    files = [str(output)]
    if picture:
        from .picture import render

        try:
            files.append(render(scene, world_file, planned, output.with_suffix(".png")))
        except Exception as exc:  # no GL: the proofs still stand
            print(f"picture skipped ({type(exc).__name__}: {exc}); set MUJOCO_GL=egl or osmesa")
    timings["total_s"] = time.perf_counter() - t0
    out["timings"] = timings
    out["files"] = files + [str(output.with_suffix(".json"))]
    output.with_suffix(".json").write_text(json.dumps(out, indent=1))
    return out


def _occlusion(scene, meta, pose, search, starts, seed, threads, progress, cache_dir, timings):
    """The resolved pair, the mandible geom's world pose at the occlusion the wafer is made for,
    where it came from, and the search's result (``--search``) or None."""
    from ...mujoco.attach import load_model
    from ..occlusion import search as occlusion_search
    from ..scenepair import resolve

    res = None
    t1 = time.perf_counter()
    if search:
        res = occlusion_search(scene, starts=starts, seed=seed, threads=threads, progress=progress, cache_dir=cache_dir)
        model, handle, jp = res["_model"], res["_handle"], res["_pair"]
    else:
        model, handle = load_model(scene, progress=progress, cache_dir=cache_dir)
        jp = resolve(model, handle)
    handle.detach()
    timings["occlusion_s" if search else "trees_s"] = time.perf_counter() - t1
    if search:
        if not res["candidates"]:
            raise ValueError("the search found no occlusion (no start settled): check the pair (mjist occlusion) or pass --pose")
        best = res["candidates"][0]
        return jp, jp.pose(best["pos"], best["quat"]), "search (candidate #1)", res
    if pose is not None:
        return (jp, *_candidate_pose(jp, pose), None)
    return jp, jp.reference, f"the pair's occlusion ({meta['occlusion_source']})", None


class _FileFrame:
    """The maxilla file's frame and units: ``to_file`` (world -> file), the mandible file's seated
    pose ``M`` there (``X``: world, reference occlusion -> seated), and the file's scale ``sx``."""

    def __init__(self, meta, X):
        A_x, A_d, self.sx = file_maps(meta)
        self.to_file = np.linalg.inv(A_x)
        self.M = self.to_file @ X @ A_d

    def points(self, V) -> np.ndarray:
        """World points in the maxilla file's frame (its units: ``sx`` turns them back into metres)."""
        return apply_pose(self.to_file, V)


def _proofs(w, f: _FileFrame, jp, meta, work, timings) -> tuple[dict, Path]:
    """The printable and seating proofs, on the pair's files as stored (the mandible at ``f.M``),
    and the wafer written in the world frame for the holding proof."""
    import trimesh

    from ...geometry.mesh import read_surface

    t3 = time.perf_counter()
    proofs = {"printable": printable(w.vertices, w.faces, w.thickness, jp.frames["maxilla"].up)}
    timings["printable_s"] = time.perf_counter() - t3
    t4 = time.perf_counter()
    sx = f.sx
    stored = {k: read_surface(meta_paths(meta)[k]) for k in ("maxilla", "mandible")}
    mx = (np.asarray(stored["maxilla"].vertices) * sx, stored["maxilla"].faces)
    md = (apply_pose(f.M, stored["mandible"].vertices) * sx, stored["mandible"].faces)
    tips = {k: f.points(v) * sx for k, v in w.cusps.items()}
    proofs["seating"] = seating(mx, md, (f.points(w.vertices) * sx, w.faces), w.clearance, tips)
    timings["seating_s"] = time.perf_counter() - t4
    world_file = work / "wafer.world.obj"
    trimesh.Trimesh(w.vertices, w.faces, process=False).export(world_file, digits=17)
    return proofs, world_file


def _record(w, f: _FileFrame, meta, output, source, proofs, res, clearance_mm, thickness_mm, opening_deg) -> dict:
    """``wafer.stl`` written in the maxilla file's frame and units, and what ``wafer.json`` holds of it."""
    import trimesh

    sx = f.sx
    V_file = f.points(w.vertices)
    os.makedirs(output.parent, exist_ok=True)
    trimesh.Trimesh(V_file, w.faces, process=False).export(output)
    lo, hi = V_file.min(axis=0), V_file.max(axis=0)
    unit = "m" if sx == 1.0 else "mm" if sx == 1e-3 else f"{sx:g} m"
    out = {
        "wafer": str(output), "units": unit, "frame": "the maxilla file's own coordinates",
        "inputs": {"maxilla": meta_paths(meta)["maxilla"], "mandible": meta_paths(meta)["mandible"],
                   "occlusion": source, "clearance_mm": clearance_mm, "thickness_mm": thickness_mm,
                   "opening": "given" if opening_deg is not None else "smallest", "grid_mm": w.grid * 1e3,
                   "imprint_mm": outline.IMPRINT * 1e3, "rim_mm": outline.RIM * 1e3},
        "opening_deg": w.opening_deg, "arch_gap_mm": w.arch_gap * 1e3,
        "mandible_transform": f.M.tolist(),
        "volume_mm3": proofs["printable"]["volume_mm3"],
        "bounding_box": {"min": lo.tolist(), "max": hi.tolist()},
        "min_thickness_mm": proofs["printable"]["min_thickness_mm"],
        "hinge_source": meta.get("hinge_source"), "hinge_uncertainty_mm": meta.get("hinge_uncertainty_mm"),
        "proofs": proofs,
        "ok": all(p["ok"] for p in proofs.values()),
    }
    if res is not None:
        c = res["candidates"][0]
        out["search"] = {"interocclusal_mm": c["interocclusal_mm"], "ambiguous": res["confidence"].get("ambiguous"),
                         "error_vs_reference_mm": c["error"]["max_mm"], "starts": res["starts"]}
    return out


def meta_paths(meta: dict) -> dict:
    """The pair's mesh files as the user gave them (``pair.json``)."""
    return meta.get("given") or meta["meshes"]


def main(folder=None, output="out/wafer/wafer.stl", progress=True, **kwargs) -> int:
    res = make(folder, output=output, progress=progress, **kwargs)
    p = res["proofs"]
    pr, se = p["printable"], p["seating"]
    print(f"wafer         {res['wafer']} ({res['units']}, {res['frame']}): {pr['faces']} faces, "
          f"{res['volume_mm3']:.0f} mm³, opened {res['opening_deg']:.2f}° about the hinge ({res['hinge_source']}), "
          f"occlusion: {res['inputs']['occlusion']}")
    print(f"printable     {'PASS' if pr['ok'] else 'FAIL'}: watertight {pr['watertight']}, {pr['shells']} shell(s), "
          f"{'embedded' if pr['winding']['ok'] else str(pr['winding']['faces_not_0_1']) + ' faces beside a crossing'}, "
          f"minimum thickness {pr['min_thickness_mm']:.3f} mm (between the faces {pr['between_faces_mm']:.3f}, rim "
          f"{pr['rim_height_mm']:.3f}; asked {res['inputs']['thickness_mm']:g})")
    for k in ("maxilla", "mandible"):
        s = se[k]
        print(f"seating       {'PASS' if s['ok'] else 'FAIL'} {k}: coal distance {s['coal_distance_mm']:.4f} mm, deepest "
              f"overlap {s['penetration_mm']:.4f} mm (≤ {PENETRATION_MM}), {s['cusp_tips']} cusp tips "
              f"{s['tip_distance_median_mm']:.3f} mm median / {s['tip_distance_max_mm']:.3f} mm max from the wafer "
              f"(clearance {res['inputs']['clearance_mm']:g} + {TIP_SLACK_MM})")
    if "holding" in p:
        h = p["holding"]
        pushes = ", ".join(f"{r['push']} {r['max_drift_mm']:.3f} mm/{r['max_rotation_deg']:.2f}° (back to "
                           f"{r['after_mm']:.3f} mm)" for r in h["pushes"])
        print(f"holding       {'PASS' if h['ok'] else 'FAIL'}: closed with {h['closing_force_n']:g} N, "
              f"{h['seated_drift_mm']:.3f} mm / {h['seated_rotation_deg']:.2f}° from the plan; {h['push_n']:g} N pushes: "
              f"{pushes} (limits {HOLD_MM} mm / {HOLD_DEG}°)")
    print(f"time          {res['timings']['total_s']:.1f} s")
    from ... import report

    for f in res["files"] + [report.build_or_say(Path(res["wafer"]).parent)]:
        print(f"written       {f}")
    return 0 if res["ok"] else 2
