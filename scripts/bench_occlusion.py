"""Occlusion search wall time: 256 starts on the bundled jaws with 1 and 2 rollout threads.

    python scripts/bench_occlusion.py [--starts 256] [--threads 1,2]

Same seed for every run, so every run closes the same starts; reports the closing time
(rollout only), the whole search (scoring, clustering, coal polish of the best 3), starts and
candidates per second, and the best candidate's distance to the designed occlusion.
Writes ``out/bench_occlusion.{json,png}``.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from mjist.jaw import occlusion

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--starts", type=int, default=256)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_occlusion"))
    a = ap.parse_args()
    rows = []
    for t in [int(x) for x in a.threads.split(",")]:
        res = occlusion.search(starts=a.starts, seed=0, threads=t, progress=False)
        res["_handle"].detach()
        best = res["candidates"][0]
        # each start closes until it settles: the steps it took are its closing time over the timestep
        steps = sum(r["seconds"] for r in res["landscape"]) / res["_model"].opt.timestep
        rows.append({"threads": t, "starts": a.starts, "simulate_s": res["simulate_s"], "total_s": res["total_s"],
                     "setup_s": res["setup_s"], "starts_per_second": res["starts_per_second"],
                     "candidates": len(res["candidates"]), "best_error": best["error"], "best_starts": best["starts"],
                     "steps": steps})
        print(f"{t} thread(s): {a.starts} starts closed in {res['simulate_s']:.2f} s ({res['starts_per_second']:.1f} starts/s, "
              f"{steps / res['simulate_s'] / 1e3:.1f} k steps/s), search {res['total_s']:.2f} s; "
              f"best: {best['starts']} starts, {best['error']['max_mm']:.3f} mm max / {best['error']['rotation_deg']:.3f}° "
              f"from the designed occlusion", flush=True)
    out = Path(a.out)
    os.makedirs(out.parent, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    md = ["| rollout threads | starts | closing s | whole search s | starts/s | best vs designed occlusion |", "|---|---|---|---|---|---|"]
    for r in rows:
        e = r["best_error"]
        md.append(f"| {r['threads']} | {r['starts']} | {r['simulate_s']:.2f} | {r['total_s']:.2f} | {r['starts_per_second']:.1f} | "
                  f"{e['max_mm']:.3f} mm max, {e['rotation_deg']:.3f}° ({r['best_starts']} starts in its basin) |")
    out.with_suffix(".md").write_text("\n".join(md) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.bar([str(r["threads"]) for r in rows], [r["simulate_s"] for r in rows], label="closing (rollout)")
    ax.bar([str(r["threads"]) for r in rows], [r["total_s"] - r["simulate_s"] for r in rows],
           bottom=[r["simulate_s"] for r in rows], label="setup, scoring, coal polish")
    ax.set_xlabel("rollout threads")
    ax.set_ylabel(f"seconds for {a.starts} starts")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)


if __name__ == "__main__":
    main()
