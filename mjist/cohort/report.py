"""``cohort.csv`` (one row per patient) and ``cohort.png`` (the cohort's distributions)."""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path

# the columns of cohort.csv, in order; the *_s columns are times (they differ run to run)
COLUMNS = ["patient", "status", "error_stage", "error", "best_score", "best_starts", "regions", "n_regions", "both_sides",
           "interocclusal_mm", "contact_fraction", "settled", "ambiguous", "coal_gap_mm", "closest_maxilla_mm", "closest_mandible_mm", "contact_area_maxilla_mm2",
           "contact_area_mandible_mm2", "error_bound_mm", "midline_offset_mm", "design_max_mm", "design_rms_mm",
           "design_rotation_deg", "within_target", "wafer_ok", "wafer_opening_deg", "wafer_min_thickness_mm",
           "wafer_tip_gap_max_mm", "wafer_hold_max_mm", "units", "up", "hinge_source", "teeth_only",
           "prepare_s", "tree_maxilla_s", "tree_mandible_s", "search_s", "contact_map_s", "wafer_s", "work_s"]
TIME_COLUMNS = [c for c in COLUMNS if c.endswith("_s")]


def csv_row(result: dict) -> dict:
    """A patient's ``result.json`` as a ``cohort.csv`` row."""
    row = {"patient": result["patient"], "status": result["status"]}
    if result["status"] != "ok":
        row.update(error_stage=result.get("stage", ""), error=result.get("error", "").splitlines()[0][:300])
    row.update(result.get("row", {}))
    row.update({k: round(v, 2) for k, v in result.get("times", {}).items() if k in TIME_COLUMNS})
    return {k: row.get(k, "") for k in COLUMNS}


def write_csv(results: list[dict], path) -> str:
    """All rows, sorted by patient, written atomically."""
    path = Path(path)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, COLUMNS)
        w.writeheader()
        for r in sorted(results, key=lambda r: r["patient"]):
            w.writerow(csv_row(r))
    os.replace(tmp, path)
    return str(path)


def _floats(rows, key):
    out = []
    for r in rows:
        try:
            v = float(r.get(key, ""))
        except (TypeError, ValueError):
            continue
        if math.isfinite(v):
            out.append(v)
    return out


def figure(results: list[dict], path, target_mm: float = 0.2) -> str | None:
    """Distributions across the cohort: error against the design (when known), best score,
    closest distance, and the mean time per stage."""
    rows = [csv_row(r) for r in results if r["status"] == "ok"]
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    fig, ax = plt.subplots(2, 2, figsize=(11, 8))
    err = _floats(rows, "design_max_mm")
    if err:
        ax[0, 0].hist(err, bins=min(30, max(5, len(err))), color="tab:blue")
        ax[0, 0].axvline(target_mm, color="k", ls="--", label=f"target {target_mm} mm")
        ax[0, 0].legend()
        ax[0, 0].set_xlabel("best candidate: largest vertex shift from the designed occlusion (mm)")
    else:
        ax[0, 0].text(0.5, 0.5, "no designed occlusion to compare with", ha="center", va="center")
    ax[0, 0].set_title("accuracy against the design")
    ax[0, 1].hist(_floats(rows, "best_score"), bins=15, color="tab:green")
    ax[0, 1].set_xlabel("best candidate's score")
    ax[0, 1].set_title("occlusion score")
    for name, colour in (("maxilla", "tab:orange"), ("mandible", "tab:purple")):
        ax[1, 0].hist(_floats(rows, f"contact_area_{name}_mm2"), bins=15, color=colour, alpha=0.6, label=name)
    ax[1, 0].legend()
    ax[1, 0].set_xlabel("contact area at the best candidate: closer than 0.1 mm (mm²)")
    ax[1, 0].set_title("occlusal contact area")
    for a in (ax[0, 0], ax[0, 1], ax[1, 0]):
        a.yaxis.set_major_locator(MaxNLocator(integer=True))
        a.set_ylabel("patients")
    stages = ["prepare_s", "tree_maxilla_s", "tree_mandible_s", "search_s", "contact_map_s"]
    means = [sum(_floats(rows, s)) / max(len(_floats(rows, s)), 1) for s in stages]
    ax[1, 1].bar([s[:-2].replace("_", "\n") for s in stages], means, color="tab:gray")
    ax[1, 1].set_ylabel("mean seconds per patient")
    ax[1, 1].set_title(f"time per stage ({len(rows)} patients done, {len(results) - len(rows)} failed)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)
