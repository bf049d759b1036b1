"""What happens to one patient, stage by stage; each stage is a plain function a worker runs.

``prepare`` (load, validate, write the occlusion-search scene) → ``tree`` for the maxilla and for
the mandible (independent: built in parallel, into the content-hashed tree cache) → ``search``
(the occlusion search, which finds both trees in the cache, its outputs, the contact map, the
error against a designed occlusion, the summary row) → ``wafer`` when asked (a surgical wafer at
the best occlusion, proved). A stage never raises for a patient's
problem: it returns ``{"status": "error", "stage": ..., "error": ...}`` and the later stages
pass that on, so a bad patient becomes an error row and the cohort goes on.
"""
from __future__ import annotations

import json
import os
import time
import traceback
import warnings
from pathlib import Path

import numpy as np

from .manifest import Patient

SENTINEL = "cohort.json"  # in the output folder: a worker that cannot see it is on another filesystem
TARGET_MM, TARGET_DEG = 0.2, 1.0  # a search within this of the designed occlusion finds it


def patient_dir(out_dir, patient_id: str) -> Path:
    return Path(out_dir) / "patients" / patient_id


def _failure(stage: str, exc: BaseException) -> dict:
    msg = str(exc).strip() or type(exc).__name__
    return {"status": "error", "stage": stage, "error": f"{type(exc).__name__}: {msg}",
            "traceback": traceback.format_exc(limit=6)}


def prepare(patient: Patient, out_dir: str, settings: dict) -> dict:
    """Load and validate the pair, write its occlusion-search scene into the patient's folder."""
    t0 = time.perf_counter()
    try:
        if not (Path(out_dir) / SENTINEL).exists():
            raise RuntimeError(f"this worker cannot see the cohort folder {out_dir}: on a cluster the output (and input) "
                               "folders must be on a filesystem every node mounts at the same path")
        from ..jaw.scenes import pair_scene

        pdir = patient_dir(out_dir, patient.id)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the notes carry what the warnings say
            # registered from the arches' shapes, as ``mjist occlusion`` does: the search starts from
            # the anatomy, not from wherever each patient's files put the mandible
            scene = pair_scene(patient.folder, pdir, "occlusion", **{"register": True, **patient.pair_options()},
                               max_error=settings["max_error"], progress=False)
        pair = json.loads((pdir / "pair.json").read_text())
    except Exception as exc:  # a bad patient: an error row, the cohort goes on
        return _failure("load", exc)
    return {"status": "ok", "scene": str(scene), "pair": pair, "seconds": time.perf_counter() - t0}


def tree(prep: dict, geom: str, settings: dict) -> dict:
    """Build (or find) the tree of one jaw of the prepared scene in the shared tree cache."""
    if prep["status"] != "ok":
        return prep
    t0 = time.perf_counter()
    try:
        import mujoco

        from ..mujoco.attach import geom_tree

        model = mujoco.MjModel.from_xml_path(prep["scene"])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t, hit = geom_tree(model, geom, cache_dir=settings.get("cache"))
    except Exception as exc:
        return _failure(f"tree ({geom})", exc)
    return {"status": "ok", "seconds": time.perf_counter() - t0, "cache_hit": bool(hit),
            "error_bound_mm": float(t.error_bound * 1e3), "leaves": int(len(t.leaf_radii))}


def _design_pose(prep: dict, design_path: Path) -> np.ndarray:
    """The designed mandible pose in the jaw frame (``design.json`` is in the files' coordinates)."""
    o = prep["pair"]["orientation"]
    S = np.eye(4)
    S[:3, :3] = o["scales"][0] * np.asarray(o["rotation"])
    return S @ np.asarray(json.loads(design_path.read_text())["mandible_pose"]) @ np.linalg.inv(S)


def design_errors(model, gmd, ref_pos, ref_quat, P_touch, P_design, candidates) -> list[dict]:
    """Each candidate's distance from the designed occlusion: the largest and RMS displacement of
    a mandible vertex (mm) and the rotation (degrees).

    The scene's reference keyframe holds the mandible at first touch ``P_touch`` (jaw frame); the
    design ``P_design`` differs from it by ``P_design P_touch⁻¹`` in the jaw frame, which the
    scene turns into the world by a fixed rotation (``scenes.jaw_to_world``).
    """
    from scipy.spatial.transform import Rotation

    from ..jaw.scenes import jaw_to_world
    from ..mujoco.scene import geom_pose_at, mesh_of

    Rx = jaw_to_world(np.eye(3), np.zeros(3))[0]
    V, _ = mesh_of(model, gmd)
    Gt = geom_pose_at(model, gmd, ref_pos, ref_quat)
    D = np.asarray(P_design) @ np.linalg.inv(P_touch)
    Wt = V @ Gt[:3, :3].T + Gt[:3, 3]
    Wd = (Wt @ Rx @ D[:3, :3].T + D[:3, 3]) @ Rx.T  # world -> jaw, design move, jaw -> world
    Rd = Rx @ D[:3, :3] @ Rx.T @ Gt[:3, :3]
    out = []
    for c in candidates:
        G = geom_pose_at(model, gmd, c["pos"], c["quat"])
        dv = np.linalg.norm(V @ G[:3, :3].T + G[:3, 3] - Wd, axis=1)
        ang = Rotation.from_matrix(G[:3, :3] @ Rd.T).magnitude()
        out.append({"max_mm": float(dv.max() * 1e3), "rms_mm": float(np.sqrt(np.mean(dv ** 2)) * 1e3),
                    "rotation_deg": float(np.degrees(ang))})
    return out


def _verdict(errors: list[dict], candidates: list[dict]) -> str:
    """"yes" when the best candidate finds the design, else why not."""
    ok = [e["max_mm"] <= TARGET_MM and e["rotation_deg"] <= TARGET_DEG for e in errors]
    if ok and ok[0]:
        return "yes"
    e = errors[0] if errors else None
    if e is None:
        return "no: no candidate"
    what = f"no: best candidate {e['max_mm']:.2f} mm / {e['rotation_deg']:.2f}° from the design"
    if any(ok):
        k = ok.index(True)
        return (f"{what}; #{k + 1} (score {candidates[k]['score']:.2f} vs {candidates[0]['score']:.2f}, "
                f"{candidates[k]['starts']} starts) is within {TARGET_MM} mm / {TARGET_DEG}°")
    k = int(np.argmin([x["max_mm"] for x in errors]))
    return f"{what}; no candidate within target (closest #{k + 1} at {errors[k]['max_mm']:.2f} mm)"


def search(patient: Patient, prep: dict, tree_maxilla: dict, tree_mandible: dict, out_dir: str, settings: dict) -> dict:
    """Occlusion search, its outputs and the contact map in the patient's folder; the patient's row."""
    t0 = time.perf_counter()
    for r in (prep, tree_maxilla, tree_mandible):
        if r["status"] != "ok":
            return r
    try:
        from ..jaw import occlusion

        pdir = patient_dir(out_dir, patient.id)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = occlusion.search(prep["scene"], starts=settings["starts"], seconds=settings["seconds"], seed=settings["seed"],
                                   threads=settings["threads"], progress=False, cache_dir=settings.get("cache"))
        try:
            t1 = time.perf_counter()
            design = patient.design()
            if design is not None and res["candidates"]:
                model, handle = res["_model"], res["_handle"]
                errs = design_errors(model, handle.geoms["mandible"], np.asarray(res["reference_pos"]),
                                     np.asarray(res["reference_quat"]), np.asarray(prep["pair"]["mandible_pose"]),
                                     _design_pose(prep, design), res["candidates"])
                for c, e in zip(res["candidates"], errs):
                    c["design_error"] = e
                res["design"] = {"file": str(design), "target_mm": TARGET_MM, "target_deg": TARGET_DEG,
                                 "verdict": _verdict(errs, res["candidates"])}
            occlusion.write_outputs(res, pdir, picture=settings["picture"])
            t2 = time.perf_counter()
            cmap = None
            if res["candidates"]:
                cmap, _ = occlusion.write_contact_map(res, pdir)
                from .. import report

                report.build_or_say(pdir)  # the patient's report.html (cohort.html links it)
            t3 = time.perf_counter()
        finally:
            res["_handle"].detach()
    except Exception as exc:
        return _failure("search", exc)
    return {"status": "ok", "row": _row(prep, res, cmap),
            "seconds": {"search": res["total_s"], "outputs": t2 - t1, "contact_map": t3 - t2, "stage": time.perf_counter() - t0}}


def wafer(patient: Patient, prep: dict, res: dict, out_dir: str, settings: dict) -> dict:
    """A surgical wafer at the patient's best occlusion (``jaw.wafer``: made, proved, written
    as ``wafer.stl``/``.json``/``.png`` in the patient's folder); its figures join the row. A
    wafer whose proofs fail is a figure of the row (``wafer_ok``), not an error."""
    if res["status"] != "ok":
        return res
    t0 = time.perf_counter()
    try:
        from ..jaw import wafer

        pdir = patient_dir(out_dir, patient.id)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w = wafer.make(scene=prep["scene"], pose=pdir / "occlusion.json", output=pdir / "wafer.stl",
                              picture=settings["picture"], progress=False, cache_dir=settings.get("cache"))
    except Exception as exc:
        f = _failure("wafer", exc)
        return {**res, "status": "error", "stage": f["stage"], "error": f["error"], "traceback": f["traceback"]}
    p = w["proofs"]
    res["row"].update(wafer_ok=w["ok"], wafer_opening_deg=round(w["opening_deg"], 3),
                      wafer_min_thickness_mm=round(w["min_thickness_mm"], 3),
                      wafer_tip_gap_max_mm=round(max(p["seating"][k]["tip_distance_max_mm"] for k in ("maxilla", "mandible")), 4),
                      wafer_hold_max_mm=round(max(r["max_drift_mm"] for r in p["holding"]["pushes"]), 4))
    res["times"]["wafer_s"] = time.perf_counter() - t0
    res["times"]["work_s"] += res["times"]["wafer_s"]
    return res


def _row(prep: dict, res: dict, cmap) -> dict:
    """The figures of one patient that go into ``cohort.csv`` (no times: those are added by the runner)."""
    pair = prep["pair"]
    row = {"units": pair["orientation"]["units"], "up": pair["orientation"]["up"], "hinge_source": pair["hinge_source"],
           "teeth_only": pair["teeth_only"], "error_bound_mm": round(res["error_bound_mm"], 4),
           "midline_offset_mm": round(res["midline_offset_mm"], 3)}
    if not res["candidates"]:
        return {**row, "best_score": None}
    b = res["candidates"][0]
    sides = {r.split("-")[0] for r in b["regions"]}
    row.update(best_score=round(b["score"], 4), best_starts=b["starts"], regions=";".join(b["regions"]), n_regions=len(b["regions"]),
               both_sides=sides == {"left", "right"}, interocclusal_mm=round(b["interocclusal_mm"], 4),
               contact_fraction=round(b["contact_fraction"], 4), settled=b["settled"], ambiguous=res["confidence"]["ambiguous"],
               coal_gap_mm=None if b["coal_distance_mm"] is None else round(b["coal_distance_mm"], 5))
    for name in ("maxilla", "mandible"):
        regs = cmap[name].regions if cmap else []
        row[f"closest_{name}_mm"] = round(min((r["closest_mm"] for r in regs), default=float("nan")), 4)
        row[f"contact_area_{name}_mm2"] = round(sum(r["contact_area_mm2"] for r in regs), 2)
    if "design" in res:
        e = b["design_error"]
        row.update(design_max_mm=round(e["max_mm"], 4), design_rms_mm=round(e["rms_mm"], 4),
                   design_rotation_deg=round(e["rotation_deg"], 4), within_target=res["design"]["verdict"])
    return row


def crash_point(patient_id: str, stage: str) -> None:
    """Fault injection for the cohort's tests: with ``MJIST_COHORT_CRASH_ONCE`` naming a folder that
    holds ``<patient>.<stage>``, the worker running that stage deletes the file and kills itself
    (SIGKILL, as the OOM killer would), once. Only the Ray backend calls this."""
    folder = os.environ.get("MJIST_COHORT_CRASH_ONCE")
    if not folder:
        return
    flag = Path(folder) / f"{patient_id}.{stage}"
    try:
        flag.unlink()
    except OSError:
        return
    import signal

    os.kill(os.getpid(), signal.SIGKILL)
