"""Run a cohort: ``mjist.cohort.run`` and ``mjist cohort``.

A patient is done when its ``patients/<id>/result.json`` exists with the current key (its input
files' bytes, its options, the result-changing settings and mjist's version): the runner writes
that file last, atomically, after every other output of the patient, so a crash or Ctrl-C never
leaves a half-written patient taken as done, and a rerun skips exactly the finished ones. A
failed patient's record is kept too (an error row; ``retry_failed`` runs it again).
"""
from __future__ import annotations

import json
import os
import statistics
import time
from collections import deque
from pathlib import Path

from .. import __version__
from . import backends, report, stages, synthetic
from .manifest import Patient, discover, patient_key

RESULT = "result.json"
DEFAULTS = {"max_error": 3e-4, "starts": 64, "seconds": 0.4, "seed": 0, "threads": 1, "picture": True, "cache": None,
            "wafer": False}
# settings that change a patient's results; ``wafer`` only adds to them: a finished patient
# without one gets its wafer alone (prepare → wafer), its search kept
KEYED = ("max_error", "starts", "seconds", "seed")


def _write_json(path: Path, obj) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=str))
    os.replace(tmp, path)


def _load_result(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # missing, or unreadable: not done


def _progress_line(done, failed, inflight, remaining, rate) -> str:
    eta = f"{remaining / rate:.1f} min" if rate > 0 else "?"
    return f"done {done} · running {inflight} · failed {failed} · {rate:.2f} patients/min · ETA {eta}"


def make_synthetic(out: Path, n: int, seed: int, spacing: float, backend, progress: bool = True) -> Path:
    """Write synthetic patients 0..n-1 into ``out/input`` (those not yet written); return the folder."""
    folder = out / "input"
    todo = [(str(folder / synthetic.patient_name(i)), synthetic.anatomy(seed, i), spacing)
            for i in range(n) if not synthetic.generated(folder / synthetic.patient_name(i))]
    if todo:
        try:
            import skimage  # noqa: F401  (marching cubes, in the workers)
        except ImportError as exc:
            raise RuntimeError("synthetic patients need scikit-image: pip install 'mjist[cluster]'") from exc
        if progress:
            print(f"cohort: generating {len(todo)} synthetic patient(s) at {spacing} mm spacing")
        backend.map(synthetic.write_patient, todo)
    return folder


def run(input=None, out="out/cohort", *, synthetic_n: int = 0, seed: int = 0, spacing: float = 0.5, workers: int | None = None,
        address: str | None = None, serial: bool = False, retry_failed: bool = False, progress: bool = True, **settings) -> dict:
    """Run (or resume) a cohort; return its summary.

    Parameters
    ----------
    input : path
        A folder of patient folders or a manifest CSV (``manifest``). With ``synthetic_n`` it may be
        omitted: ``synthetic_n`` procedural patients (``synthetic``, seed ``seed``, ``spacing`` mm)
        are written into ``out/input`` and run.
    out : path
        Output folder: ``patients/<id>/`` (scene, search JSON and pictures, contact map,
        ``result.json``), ``cohort.csv``, ``cohort.png``, ``cohort.json``.
    workers, address, serial
        Local Ray with ``workers`` CPUs (default: all), a Ray cluster at ``address`` (or
        ``RAY_ADDRESS``), or no Ray (``serial``). Results do not depend on the choice.
    retry_failed : bool
        Run failed patients again (a rerun otherwise keeps their error rows).
    **settings
        ``max_error`` (m), ``starts``, ``seconds``, ``seed`` of the search, ``threads`` per search,
        ``picture``, ``cache`` (the tree cache folder; on a cluster, a shared one), ``wafer`` (make and
        prove a surgical wafer at each best occlusion, ``jaw.wafer``).

    Returns
    -------
    dict
        ``patients``, ``done``, ``failed``, ``skipped``, ``ran``, ``seconds``, ``csv``, ``figure``,
        ``backend``, ``slots``.
    """
    unknown = set(settings) - set(DEFAULTS)
    if unknown:
        raise TypeError(f"unknown cohort setting(s) {sorted(unknown)}: use {', '.join(DEFAULTS)}")
    cfg = {**DEFAULTS, **settings, "seed": seed}
    if cfg["cache"] is not None:
        cfg["cache"] = os.path.abspath(cfg["cache"])
    out = Path(out).resolve()
    (out / "patients").mkdir(parents=True, exist_ok=True)
    address = address or os.environ.get("RAY_ADDRESS") or None
    t0 = time.perf_counter()
    backend = backends.make("serial" if serial else "ray", str(out), cfg, workers=workers, address=address)
    try:
        _write_json(out / stages.SENTINEL, {"settings": cfg, "version": __version__, "input": str(input),
                                            "synthetic": synthetic_n, "spacing_mm": spacing})
        if synthetic_n:
            input = make_synthetic(out, synthetic_n, seed, spacing, backend, progress)
        if input is None:
            raise ValueError("give the cohort's INPUT folder or manifest (or --synthetic N)")
        patients = discover(input)
        return _run(patients, out, cfg, backend, retry_failed, progress, t0)
    finally:
        backend.close()


def _run(patients: list[Patient], out: Path, cfg: dict, backend, retry_failed: bool, progress: bool, t0: float) -> dict:
    keyed = {k: cfg[k] for k in KEYED}
    results, todo, keys, wafer_only = {}, deque(), {}, {}
    for p in patients:
        keys[p.id] = patient_key(p, keyed, __version__)
        r = _load_result(stages.patient_dir(out, p.id) / RESULT)
        if r is not None and r.get("key") == keys[p.id] and (r["status"] == "ok" or not retry_failed):
            if cfg["wafer"] and r["status"] == "ok" and "wafer_ok" not in r.get("row", {}):
                wafer_only[p.id] = r  # searched before without --wafer: its wafer alone
                todo.append(p)
            else:
                results[p.id] = r
        else:
            todo.append(p)
    skipped = len(results)
    bar = None
    if progress:
        from tqdm import tqdm

        print(f"cohort: {len(patients)} patients, {skipped} already done, {len(todo)} to run on {backend.name} "
              f"({backend.slots} CPU{'s' if backend.slots > 1 else ''}) → {out}")
        bar = tqdm(total=len(patients), initial=skipped, unit="patient", desc="cohort")
    inflight, ran, t_run = {}, 0, time.perf_counter()
    window = backend.slots + 1  # enough to keep every CPU busy across a patient's stages
    try:
        while todo or inflight:
            while todo and len(inflight) < window:
                p = todo.popleft()
                inflight[backend.submit(p, wafer_only.get(p.id))] = p
            for h, r in backend.wait(list(inflight), timeout=1.0):
                p = inflight.pop(h)
                r.update(patient=p.id, key=keys[p.id])
                pdir = stages.patient_dir(out, p.id)
                pdir.mkdir(parents=True, exist_ok=True)
                _write_json(pdir / RESULT, r)
                results[p.id] = r
                ran += 1
                report.write_csv(list(results.values()), out / "cohort.csv")
            if bar is not None:
                failed = sum(r["status"] != "ok" for r in results.values())
                rate = ran / max((time.perf_counter() - t_run) / 60.0, 1e-9)
                bar.n = len(results)
                bar.set_postfix_str(_progress_line(len(results) - failed, failed, len(inflight), len(todo) + len(inflight), rate))
                bar.refresh()
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        print(f"cohort: interrupted; {len(results)} of {len(patients)} patients are done and kept. "
              "Run the same command again to resume.")
        raise
    if bar is not None:
        bar.close()
    rows = [results[p.id] for p in patients]
    csv_path = report.write_csv(rows, out / "cohort.csv")
    fig = report.figure(rows, out / "cohort.png", stages.TARGET_MM)
    from ..report import write_cohort

    page = str(write_cohort(out))
    failed = [r["patient"] for r in rows if r["status"] != "ok"]
    summary = {"patients": len(patients), "done": len(rows) - len(failed), "failed": len(failed), "failed_patients": failed,
               "skipped": skipped, "ran": ran, "seconds": time.perf_counter() - t0, "run_seconds": time.perf_counter() - t_run,
               "csv": csv_path, "figure": fig, "page": page, "backend": backend.name, "slots": backend.slots}
    designed = [r["row"] for r in rows if r["status"] == "ok" and "within_target" in r.get("row", {})]
    if designed:
        summary["design"] = {"patients": len(designed), "within_target": sum(r["within_target"] == "yes" for r in designed),
                             "median_max_mm": float(statistics.median(r["design_max_mm"] for r in designed)),
                             "worst_max_mm": max(r["design_max_mm"] for r in designed),
                             "worst_rotation_deg": max(r["design_rotation_deg"] for r in designed)}
    _write_json(out / "summary.json", summary)
    return summary
