"""The benchmark suite in one command: ``mjist bench [--quick]``.

Runs the benchmark scripts of ``scripts/`` one after the other, each in its own process (so
each stage's timings and peak memory are its own): tree builds (``bench_build``), queries
against coal (``bench_query``), the seed paper's Figs. 6-9 with backtracking / multipoint
speedups in and out of contact (``bench_paper``), scaling with mesh size 10k → 200k
vertices (``bench_scaling``), MuJoCo step time against native hull / mesh-SDF / CoACD
(``bench_mujoco``), a jaw pushed into occlusion on a slide (``bench_slide``), the haptic loop (``bench_haptic``), the occlusion search
(``bench_occlusion``), cohorts on Ray (``bench_cohort``), surgical wafers (``bench_wafer``) and stability under stress
(``bench_stress``). Then writes into the output
folder ``BENCHMARKS.generated.md`` (the exact command, machine, versions, wall time per stage and every stage's table) and
``pareto.png``: run time against error for the IST at each ε against coal's exact distance
(queries) and for each MuJoCo contact mode against the ground-truth occlusion (jaw closure).
``--quick`` (the stages of ``QUICK``, small sizes, a few minutes; it names what it skips) is
what CI-sized machines can afford; the full run states its time. The repository's BENCHMARKS.md is a full run's report (with
``pareto.png`` as ``docs/pareto.png``): see docs/architecture.md.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = ROOT / "scripts"

# stage -> (script, extra args for --quick, extra args for the full run, how its outputs are named)
STAGES = {
    "build": ("bench_build.py", ["--quick"], [], "dir"),
    "query": ("bench_query.py", ["--quick", "--pairs", "bundled"], [], "dir"),
    "paper": ("bench_paper.py", ["--quick"], [], "dir"),
    "scaling": ("bench_scaling.py", ["--quick"], [], "dir"),
    "mujoco": ("bench_mujoco.py", ["--quick", "--pairs", "bundled"], [], "prefix"),
    "slide": ("bench_slide.py", ["--max-errors", "default", "--steps", "400"], [], "prefix"),
    "haptic": ("bench_haptic.py", ["--quick"], [], "prefix"),
    "occlusion": ("bench_occlusion.py", ["--starts", "32"], [], "prefix"),
    "real_occlusion": ("bench_real_occlusion.py", ["--seeds", "1", "--variants", "stored,bundled"], [], "prefix"),
    "any_start": ("bench_any_start.py", ["--pairs", "orthocast", "--starts", "stored,apart", "--seeds", "1"], [], "prefix"),
    "cohort": ("bench_cohort.py", ["--patients", "2", "--spacing", "1.0", "--starts", "16", "--max-error", "0.001"], [], "prefix"),
    "wafer": ("bench_wafer.py", ["--variants", "bundled"], [], "dir"),
    "stress": ("bench_stress.py", ["--quick"], [], "dir"),
}

# the stages ``--quick`` runs: the bundled models only, prebuilt trees, a few minutes on a fresh
# install of a 2-core machine. The others search real pairs, run cohorts or stress runs (tens of
# minutes); ``--only`` runs any of them with its quick arguments
QUICK = ("build", "query", "mujoco", "haptic")

# stage -> (section title, what it measures: a paragraph above the stage's table)
NOTES = {
    "build": ("Tree builds", "Each build in its own process (peak memory its own): leaves, certified ε and the "
              "lower bound found on the surface, coverage of the volume, the pipeline's stage times. Reference: "
              "coal's OBBRSS BVH build of the same mesh in the same run (a preprocessing reference, not the same "
              "product: coal's BVH certifies nothing)."),
    "query": ("Distance, contact and volume queries", "One chewing motion of the mandible replayed against the "
              "maxilla, every traversal timed per frame (Python call included; kernel-only in its column). "
              "References on the same frames: coal's exact distance, MuJoCo's convex hull and mesh-SDF through "
              "mj_geomDistance; the IST's answers checked against coal's interval on every frame."),
    "paper": ("The seed paper's figures", "Speed against the number of leaves and the tree depth, error against "
              "leaves, and the speed-ups of backtracking and multipoint in and out of contact (Figs. 6–9)."),
    "scaling": ("Scaling with mesh size", "The same motion on remeshed jaws of 10 k to 200 k vertices: IST "
                "queries against coal."),
    "mujoco": ("MuJoCo: jaw closure", "The jaw-closure scene with each contact mode: IST (sphere and surface "
               "contacts; mesh and sdf geoms), MuJoCo's convex hull, mesh-SDF and CoACD pieces; step time, where the "
               "jaw comes to rest against the designed occlusion and coal's distance there, and the IST's distances "
               "checked against coal's (bound violations)."),
    "slide": ("MuJoCo: a jaw pushed into occlusion", "The CBCT mandible pushed straight up on a slide joint "
              "against the maxilla: sphere and surface contacts at each tree error and MuJoCo's mesh-SDF; step "
              "time, and where it rests against coal's first touch along the slide (the exact answer)."),
    "haptic": ("Haptic loop", "Every scripted device path with both penalty laws: loop time (mocap update → "
               "mj_step → force readout), forces, the largest force change per step, and the IST's depth "
               "against coal's deepest triangle-pair penetration."),
    "occlusion": ("Occlusion search", "Starts closed in mujoco.rollout threads, the whole search's time, and "
                  "the best candidate's distance from the designed occlusion."),
    "real_occlusion": ("Real occlusions", "The default occlusion search on the shared CBCT pair as stored, "
                       "cropped to its teeth in mm/+z and given open (8° about its hinge, 1 mm forward), and on the "
                       "bundled pair, one search per seed: the best candidate's largest tooth-point shift and rotation "
                       "from the stored occlusion, the rank of the right basin, the rank correlation of score and "
                       "error over the settled starts, how often the search called itself ambiguous, its time."),
    "any_start": ("Any start: automated articulation", "`mjist occlusion --data` with default settings on the "
                  "shared casts and CBCT pair handed over as stored, open, apart and in an unrelated frame: the best "
                  "candidate's largest occlusal-point shift and rotation from the stored occlusion at first touch "
                  "(measured on the mandible file's reported transform), the spread between starts, the ambiguity "
                  "flag and the time."),
    "cohort": ("Cohorts", "A synthetic cohort (known occlusions) run by `mjist cohort` on local Ray with 1 and 2 "
               "workers, each run from an empty tree cache: patients per minute, the median time per stage, whether "
               "cohort.csv agrees across worker counts, each search's distance from its patient's design, and the "
               "time for 1,000 patients on k such machines."),
    "wafer": ("Surgical wafers", "`mjist wafer FOLDER --search` on the bundled pair and the shared CBCT pair (as "
              "stored, cropped to its teeth in mm/+z, refined to 340 k vertices), with an empty and a filled tree "
              "cache: time per step, the searched occlusion against the stored one, the opening, the minimum "
              "thickness, the cusp tips' distance to the wafer and the holding proof's drifts."),
    "stress": ("Stability under stress", "The bundled jaws clenched for 100 s, closed at 0.5 to 10 ms steps, slammed "
               "into the teeth through the haptic handle at up to 2 m/s, chewed for 100 s with a drifting device "
               "quaternion, and attached and detached 1,000 times: finite, where they rest against coal's exact "
               "meshes, energy growth, memory."),
}


def machine() -> dict:
    """CPU, cores, memory and library versions of this machine."""
    import coal  # noqa: F401
    import mujoco
    import numba
    import numpy
    import trimesh

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = round(int(line.split()[1]) / 2**20, 1)
                break
    except OSError:
        pass
    from importlib.metadata import version

    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gb": mem, "python": platform.python_version(),
            "mujoco": mujoco.__version__, "numba": numba.__version__, "numpy": numpy.__version__,
            "trimesh": trimesh.__version__, "coal": version("coal"), "platform": platform.platform()}


def _outputs(stage: str, out: Path) -> tuple[list[str], Path]:
    """Arguments that point a stage's script at ``out``, and its Markdown table's path."""
    script, _, _, kind = STAGES[stage]
    name = script[:-3]
    if kind == "dir":
        return ["--out", str(out)], out / f"{name}.md"
    return ["--out", str(out / name)], out / f"{name}.md"


def pareto(out: Path) -> str | None:
    """Run time against error from the query and MuJoCo stages' JSON (whatever exists)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    q = out / "bench_query.json"
    m = out / "bench_mujoco.json"
    if not q.exists() and not m.exists():
        return None
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    if q.exists():
        res = json.loads(q.read_text())["results"]
        for pair, r in res.items():
            ax[0].scatter([r["coal"]["median_us"]], [0.0], marker="*", s=120, label=f"coal exact ({pair})")
            for name, x in r.get("references", {}).items():  # MuJoCo's convex hull / CoACD pieces, same frames
                ax[0].scatter([x["median_us"]], [x["err_max"] * 1e3], marker="x", s=70,
                              label=f"{name}, {x['pieces'][0]}+{x['pieces'][1]} pieces: {x['false_contacts']} false contacts ({pair})")
            for lv in r["levels"]:
                for meth in ("distance", "backtracking", "backtracking+skip"):
                    s = lv["methods"][meth]
                    ax[0].errorbar([s["median_us"]], [s["err_max"] * 1e3], yerr=[[0], [lv["error_bound"] * 1e3 - s["err_max"] * 1e3]],
                                   fmt="o", capsize=3, label=f"IST {meth}, ε1+ε2 {lv['error_bound'] * 1e3:.2f} mm ({pair})")
        ax[0].set_xscale("log")
        ax[0].set_xlabel("median time per query (µs)")
        ax[0].set_ylabel("max |d − coal| (mm); bar: up to the IST's certified ε1+ε2")
        ax[0].set_title("distance queries along the chewing motion")
        ax[0].legend(fontsize=6)
    if not q.exists():
        ax[0].set_axis_off()
    if not m.exists():
        ax[1].set_axis_off()
    else:
        res = json.loads(m.read_text())["cases"]
        for pair, modes in res.items():
            for mode, r in modes.items():
                ax[1].scatter([r["step_us_median"]], [abs(r["final_hinge_deg"])], s=40)
                ax[1].annotate(f"{mode} ({pair})", (r["step_us_median"], abs(r["final_hinge_deg"])), fontsize=7)
        ax[1].set_xscale("log")
        ax[1].set_yscale("symlog", linthresh=0.1)
        ax[1].set_ylim(bottom=0)
        ax[1].set_xlabel("median mj_step time (µs)")
        ax[1].set_ylabel("|final hinge − ground truth| (°)")
        ax[1].set_title("jaw closure in MuJoCo: cost against occlusion error")
    fig.tight_layout()
    path = out / "pareto.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def run(quick: bool = False, out="out/bench", only: list[str] | None = None, echo=print) -> dict:
    """Run the stages; write ``BENCHMARKS.generated.md`` and ``pareto.png``; return the summary."""
    if not SCRIPTS.exists():
        raise FileNotFoundError(f"{SCRIPTS} is missing: `mjist bench` runs the repository's scripts; "
                                "install from a clone with `pip install -e .`")
    out = Path(out).resolve()
    os.makedirs(out, exist_ok=True)
    stages = only or list(STAGES)
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        raise ValueError(f"unknown stage(s) {unknown}: choose from {', '.join(STAGES)}")
    skipped = [s for s in stages if quick and not only and s not in QUICK]
    stages = [s for s in stages if s not in skipped]
    if skipped:
        echo(f"--quick runs {', '.join(stages)}; skipped (run without --quick, or --only STAGE): {', '.join(skipped)}")
    command = "mjist bench" + (" --quick" if quick else "") + (f" --only {','.join(stages)}" if only else "")
    t_all = time.perf_counter()
    done = {}
    for st in stages:
        script, qargs, fargs, _ = STAGES[st]
        args, md = _outputs(st, out)
        cmd = [sys.executable, str(SCRIPTS / script), *(qargs if quick else fargs), *args]
        echo(f"[{st}] {' '.join(cmd[1:])}")
        t = time.perf_counter()
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        sec = time.perf_counter() - t
        done[st] = {"seconds": sec, "returncode": p.returncode, "table": md.read_text() if md.exists() else None}
        if p.returncode != 0:
            done[st]["error"] = (p.stderr or p.stdout)[-2000:]
            echo(f"[{st}] FAILED after {sec:.0f} s:\n{done[st]['error']}")
        else:
            echo(f"[{st}] {sec:.0f} s")
    total = time.perf_counter() - t_all
    mach = machine()
    lines = [
        "# Benchmarks", "",
        f"Today's figures, written by `{command}` (from the project root; {time.strftime('%Y-%m-%d')}, "
        f"{total / 60:.1f} min). Each stage runs its script in its own process; its command is given "
        "with its table, and every reference (coal, MuJoCo's own contacts) is measured in the same run. "
        "This machine is shared and noisy: compare medians and ratios, not single figures.", "",
        "Machine: " + ", ".join(f"{k} {v}" for k, v in mach.items()), "",
        "| stage | script | seconds | status |", "|---|---|---|---|",
    ]
    for st, r in done.items():
        lines.append(f"| {st} | scripts/{STAGES[st][0]} | {r['seconds']:.0f} | {'ok' if r['returncode'] == 0 else 'failed'} |")
    for st in skipped:
        lines.append(f"| {st} | scripts/{STAGES[st][0]} | | skipped by --quick |")
    for st, r in done.items():
        script, qargs, fargs = STAGES[st][:3]
        title, note = NOTES.get(st, (st, ""))
        cmd = " ".join(["python", f"scripts/{script}", *(qargs if quick else fargs)])
        lines += ["", f"## {title}", "", f"`{cmd}`", ""]
        if note:
            lines += [note, ""]
        lines.append(r["table"].strip() if r.get("table") else "(no table: see the stage's output)")
    pic = pareto(out)
    if pic:
        lines += ["", "## Run time against error", "", "![pareto](pareto.png)"]
    lines += ["", "Ideas measured and not kept: [docs/tried.md](docs/tried.md)."]
    (out / "BENCHMARKS.generated.md").write_text("\n".join(lines) + "\n")
    summary = {"command": command, "total_s": total, "machine": mach,
               "stages": {k: {kk: vv for kk, vv in v.items() if kk != "table"} for k, v in done.items()}}
    (out / "bench_suite.json").write_text(json.dumps(summary, indent=1))
    echo(f"wrote {out / 'BENCHMARKS.generated.md'}" + (f", {pic}" if pic else "") + f" in {total / 60:.1f} min")
    return summary
