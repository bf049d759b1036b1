"""Surgical wafers: `mjist wafer FOLDER --search` on real and bundled arches, timed and proved.

    python scripts/bench_wafer.py [--variants bundled,stored,teeth,dense] [--out out/bench_wafer]

Variants (the shared CBCT pair, ``../shared/data/jaw``, stored in occlusion, as users bring it):

* ``bundled``: the bundled procedural pair (about 100 k vertices each, designed occlusion);
* ``stored``: the CBCT pair as stored (metres, +y up, with condyles and fossae, 21 k vertices);
* ``teeth``: converted to millimetres with +z up, cropped 9 mm either side of the occlusal level;
* ``dense``: the stored pair refined (one Loop, one midpoint subdivision) to 335-345 k vertices
  per arch, the size of a dense intraoral scan; its occlusion is its own first touch.

Each runs ``wafer.make(FOLDER, search=True)`` (the occlusion search with default settings,
then the wafer and its three proofs) twice: first with an empty tree cache (what a user's
first run costs), then with the trees cached. Per run: the time of each step, the search's
error against the stored occlusion (largest tooth-point shift and rotation), the opening, the
minimum thickness, the seating figures and the holding drifts. Writes ``OUT/bench_wafer.json``
and ``OUT/bench_wafer.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import write_table  # noqa: E402

SHARED = ROOT.parent / "shared" / "data" / "jaw"


def _teeth(out: Path) -> Path:
    from byo_jaws import TO_FILE, _crop, _load

    from mjist.jaw.pair import load_pair

    mx, md = _load(SHARED / "maxilla.obj"), _load(SHARED / "mandible.obj")
    _, _, info = load_pair(SHARED)
    md.apply_transform(info["mandible_pose"])
    y0 = float(info["arches"]["mandible"].origin[1])
    S = np.eye(4)
    S[:3, :3] = 1000.0 * TO_FILE
    folder = out / "teeth"
    folder.mkdir(parents=True, exist_ok=True)
    for name, m in (("maxilla", mx), ("mandible", md)):
        c = _crop(m, y0 + 9e-3, y0 - 9e-3, -1.0)
        c.apply_transform(S)
        c.export(folder / f"{name}.stl")
    return folder


def _dense(out: Path) -> Path:
    """The stored pair refined to about 340 k vertices per arch: one Loop subdivision
    (which also rounds off the slivers that MuJoCo's float32 copy would flatten to zero area),
    then one midpoint subdivision."""
    import trimesh

    folder = out / "dense"
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("maxilla", "mandible"):
        m = trimesh.load(SHARED / f"{name}.obj", force="mesh", process=False)
        m.merge_vertices()
        V, F = trimesh.remesh.subdivide_loop(m.vertices, m.faces, iterations=1)
        V, F = trimesh.remesh.subdivide(V, F)
        trimesh.Trimesh(V, F, process=False).export(folder / f"{name}.obj", digits=12)
    return folder


def _summary(res: dict, seconds: float, cached: bool) -> dict:
    p = res["proofs"]
    h = p.get("holding", {})
    s = res.get("search", {})
    return {
        "trees_cached": cached, "seconds": seconds, "timings": res["timings"],
        "search_error_mm": s.get("error_vs_reference_mm"), "ambiguous": s.get("ambiguous"),
        "opening_deg": res["opening_deg"], "min_thickness_mm": res["min_thickness_mm"],
        "faces": p["printable"]["faces"], "volume_mm3": res["volume_mm3"],
        "printable": p["printable"]["ok"], "seating": p["seating"]["ok"], "holding": h.get("ok"),
        "tip_max_mm": max(p["seating"][k]["tip_distance_max_mm"] for k in ("maxilla", "mandible")),
        "cusp_tips": [p["seating"][k]["cusp_tips"] for k in ("maxilla", "mandible")],
        "overlap_mm": max(p["seating"][k]["penetration_mm"] for k in ("maxilla", "mandible")),
        "seated_mm": h.get("seated_drift_mm"), "push_max_mm": max((r["max_drift_mm"] for r in h.get("pushes", [])), default=None),
        "push_max_deg": max((r["max_rotation_deg"] for r in h.get("pushes", [])), default=None),
        "return_max_mm": max((r["after_mm"] for r in h.get("pushes", [])), default=None),
        "push_max_any_step_mm": max((r["max_drift_any_step_mm"] for r in h.get("pushes", [])), default=None),
        "rattle_mm_per_step": h.get("rattle_mm_per_step"),
        "ok": res["ok"],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="bundled,stored,teeth,dense")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_wafer"))
    args = ap.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from mjist.jaw import wafer

    folders = {"bundled": None}
    names = args.variants.split(",")
    if any(n != "bundled" for n in names) and not SHARED.exists():
        print(f"{SHARED} is absent: only the bundled pair")
        names = ["bundled"]
    if "stored" in names:
        folders["stored"] = SHARED
    if "teeth" in names:
        folders["teeth"] = _teeth(out / "input")
    if "dense" in names:
        folders["dense"] = _dense(out / "input")
    rows = {}
    for name in names:
        rows[name] = []
        cache = out / "trees" / name
        shutil.rmtree(cache, ignore_errors=True)
        for run in range(2):
            t0 = time.perf_counter()
            res = wafer.make(folders[name], output=out / name / "wafer.stl", search=True, picture=run == 1,
                                progress=False, cache_dir=str(cache))
            rows[name].append(_summary(res, time.perf_counter() - t0, cached=run == 1))
            (out / name / "rows.json").write_text(json.dumps(rows[name], indent=1))
            r = rows[name][-1]
            print(f"{name:8s} {'cached' if run else 'first ':6s} {r['seconds']:6.1f} s  search {r['search_error_mm']:.3f} mm from "
                  f"stored  opening {r['opening_deg']:.2f}°  thickness {r['min_thickness_mm']:.3f}  tips ≤ {r['tip_max_mm']:.3f}  "
                  f"pushes ≤ {r['push_max_mm']:.3f} mm  proofs {'PASS' if r['ok'] else 'FAIL'}", flush=True)
    (out / "bench_wafer.json").write_text(json.dumps(rows, indent=1))
    header = ["pair", "trees", "time (s)", "search vs stored (mm)", "opening (°)", "min thickness (mm)",
              "tips from wafer, max (mm)", "seated / pushed / back (mm)", "pushed, any step (mm)", "printable", "seating",
              "holding"]
    write_table(out / "bench_wafer.md", header, [
        [name, "cached" if r["trees_cached"] else "built", f"{r['seconds']:.0f}", f"{r['search_error_mm']:.3f}",
         f"{r['opening_deg']:.2f}", f"{r['min_thickness_mm']:.3f}", f"{r['tip_max_mm']:.3f}",
         f"{r['seated_mm']:.3f} / {r['push_max_mm']:.3f} / {r['return_max_mm']:.3f}", f"{r['push_max_any_step_mm']:.3f}",
         "pass" if r["printable"] else "FAIL", "pass" if r["seating"] else "FAIL", "pass" if r["holding"] else "FAIL"]
        for name, rs in rows.items() for r in rs])
    return 0


if __name__ == "__main__":
    sys.exit(main())
