"""Cohort throughput and accuracy: a synthetic cohort with 1 and 2 local Ray workers.

    python scripts/bench_cohort.py [--patients 8] [--workers 1,2] [--spacing 0.5] [--starts 64]

Generates the synthetic cohort once (``mjist.cohort.synthetic``: known occlusions), then runs it
with each worker count from scratch: a fresh output folder and a fresh tree cache, so every run
builds every tree. Reports patients per minute (wall time of the run, Ray's start included), the
per-stage time split (CPU-seconds per patient), whether the runs' ``cohort.csv`` agree apart from
times, the accuracy of each patient's best candidate against its designed occlusion (median and
worst), and from these figures the time for 1,000 patients on k machines like this one. Writes
``<out>/bench_cohort.{json,md,png}``.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import time
from pathlib import Path

from mjist.cohort import backends, report, run
from mjist.cohort.runner import make_synthetic

ROOT = Path(__file__).resolve().parent.parent

def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _same(a, b) -> bool:
    strip = lambda rows: [{k: v for k, v in r.items() if k not in report.TIME_COLUMNS} for r in rows]
    return strip(a) == strip(b)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--patients", type=int, default=8)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--spacing", type=float, default=0.5, help="mm")
    ap.add_argument("--starts", type=int, default=64)
    ap.add_argument("--max-error", type=float, default=3e-4, help="m")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_cohort"))
    a = ap.parse_args(argv)
    prefix = Path(a.out)
    work = prefix.parent / (prefix.name + "_runs")
    t = time.perf_counter()
    make_synthetic(work, a.patients, a.seed, a.spacing, backends.Serial(str(work), {}), progress=False)
    gen_s = time.perf_counter() - t
    print(f"{a.patients} synthetic patients generated in {gen_s:.0f} s", flush=True)
    runs = []
    for w in [int(x) for x in a.workers.split(",")]:
        out, cache = work / f"workers{w}", work / f"trees{w}"
        for p in (out, cache):
            shutil.rmtree(p, ignore_errors=True)
        s = run(work / "input", out, workers=w, progress=False, cache=str(cache), seed=a.seed,
                starts=a.starts, max_error=a.max_error, picture=False)
        rows = _rows(out / "cohort.csv")
        ok = [r for r in rows if r["status"] == "ok"]
        stage = {k: statistics.median(float(r[k]) for r in ok) for k in report.TIME_COLUMNS if ok}
        runs.append({"workers": w, "seconds": s["run_seconds"], "patients": s["patients"], "failed": s["failed"],
                     "patients_per_min": s["patients"] / s["run_seconds"] * 60.0, "stage_median_s": stage,
                     "design": s.get("design"), "rows": rows})
        d = s.get("design") or {}
        print(f"{w} worker(s): {s['patients']} patients in {s['run_seconds']:.0f} s ({runs[-1]['patients_per_min']:.2f}/min), "
              f"{s['failed']} failed; design: {d.get('within_target')}/{d.get('patients')} within target, median "
              f"{d.get('median_max_mm', float('nan')):.3f} mm, worst {d.get('worst_max_mm', float('nan')):.3f} mm", flush=True)
    agree = all(_same(runs[0]["rows"], r["rows"]) for r in runs[1:])
    best = max(runs, key=lambda r: r["patients_per_min"])
    per_machine = best["patients_per_min"]
    projection = {k: 1000.0 / (per_machine * k) / 60.0 for k in (1, 2, 4, 8, 16, 32)}  # hours
    ok = [r for r in runs[0]["rows"] if r["status"] == "ok"]
    errs = sorted(float(r["design_max_mm"]) for r in ok if r["design_max_mm"])
    rots = sorted(float(r["design_rotation_deg"]) for r in ok if r["design_rotation_deg"])
    res = {"patients": a.patients, "spacing_mm": a.spacing, "starts": a.starts, "max_error_m": a.max_error,
           "generate_s": gen_s, "runs": [{k: v for k, v in r.items() if k != "rows"} for r in runs],
           "csv_identical_apart_from_times": agree, "hours_for_1000_patients_on_k_machines": projection,
           "accuracy": {"median_max_mm": statistics.median(errs) if errs else None, "worst_max_mm": max(errs, default=None),
                        "worst_rotation_deg": max(rots, default=None),
                        "within_target": sum(r["within_target"] == "yes" for r in ok), "of": len(ok),
                        "misses": {r["patient"]: r["within_target"] for r in ok if r["within_target"] != "yes"}}}
    os.makedirs(prefix.parent, exist_ok=True)
    prefix.with_suffix(".json").write_text(json.dumps(res, indent=1))
    md = ["| local Ray workers | patients | wall s | patients/min | median s per patient: prepare / trees (max+mand) / search / contact map | failed |",
          "|---|---|---|---|---|---|"]
    for r in runs:
        st = r["stage_median_s"]
        md.append(f"| {r['workers']} | {r['patients']} | {r['seconds']:.0f} | {r['patients_per_min']:.2f} | "
                  f"{st.get('prepare_s', 0):.1f} / {st.get('tree_maxilla_s', 0):.1f}+{st.get('tree_mandible_s', 0):.1f} / "
                  f"{st.get('search_s', 0):.1f} / {st.get('contact_map_s', 0):.1f} | {r['failed']} |")
    acc = res["accuracy"]
    md += ["", f"cohort.csv identical apart from times across worker counts: {'yes' if agree else 'NO'}.",
           f"Accuracy against the designed occlusions ({a.patients} patients, {a.spacing} mm polygonisation, ε {a.max_error * 1e3:g} mm "
           f"trees, {a.starts} starts): {acc['within_target']}/{acc['of']} best candidates within 0.2 mm and 1°; largest vertex "
           f"shift median {acc['median_max_mm']:.3f} mm, worst {acc['worst_max_mm']:.3f} mm / {acc['worst_rotation_deg']:.3f}°.",
           "", "1,000 patients at this machine's best rate, k such machines (hours): "
           + ", ".join(f"k={k}: {h:.1f}" for k, h in projection.items()) + "."]
    if acc["misses"]:
        md += ["", "Misses: " + "; ".join(f"{k}: {v}" for k, v in acc["misses"].items())]
    prefix.with_suffix(".md").write_text("\n".join(md) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].bar([str(r["workers"]) for r in runs], [r["patients_per_min"] for r in runs])
    ax[0].set_xlabel("local Ray workers")
    ax[0].set_ylabel("patients per minute")
    ax[0].set_title("cohort throughput (trees built from scratch)")
    ax[1].bar(range(len(errs)), errs)
    ax[1].axhline(0.2, color="k", ls="--", label="target 0.2 mm")
    ax[1].set_xlabel("patient (sorted)")
    ax[1].set_ylabel("best candidate vs design: largest shift (mm)")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(prefix.with_suffix(".png"), dpi=100)
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
