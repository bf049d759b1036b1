"""The seed paper's figures on our trees: speed vs leaves (Fig. 6), speed vs tree depth for ~3k
and ~16k leaves (Figs. 7-8), error vs leaves (Fig. 9), and the backtracking / multipoint
speedups over plain distance traversal in and out of contact.

Every configuration replays the same chewing motion of the mandible against the maxilla
(``mjist.jaw.chewing_motion``) and is compared frame by frame with coal's exact distance.
Trees are built with ``leaves=N`` (the packing stops after the N largest spheres, so the
voxelization refines until N spheres fit: the paper's "voxelization quality" axis) and, for
the depth figures, with branching factors 2..16 on the same N (depth = the tree's height).

Error definitions (Fig. 9): absolute error = d_IST − d_coal over the separated frames;
relative error = (d_IST − d_coal) / d_coal over frames with d_coal ≥ 0.1 mm (the relative
error of a distance query is undefined at contact). The certified bound ε_A + ε_B is
plotted with them: the absolute error never exceeds it.

Writes ``bench_paper.json``, ``bench_paper.png`` and ``bench_paper.md`` into ``--out``.

    python scripts/bench_paper.py            # real pair (../shared/data/jaw) + bundled jaws
    python scripts/bench_paper.py --quick    # bundled pair, 300 frames, 1k-10k leaves
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_query import CLENCH, coal_replay, pairs_available, stats, timed, write_outputs  # noqa: E402
from benchlib import tree_for  # noqa: E402

import mjist  # noqa: E402
from mjist.jaw import pair as jaw  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
REL_MIN = 1e-4  # m: frames closer than this have no meaningful relative error

FULL = {"frames": 1000, "leaves": [1000, 3000, 10000, 30000, 100000, 300000],
        "depth_leaves": [3000, 16000], "branching": [2, 3, 4, 6, 8, 12, 16]}
QUICK = {"frames": 300, "leaves": [1000, 3000, 10000], "depth_leaves": [3000], "branching": [2, 4, 16]}


def _tree(path, leaves, branching):
    """A tree with ``leaves`` leaves and ``branching``, and its build's own seconds (cached or not)."""
    tree, _, _ = tree_for(path, leaves=leaves, branching=branching)
    return tree, float(tree.timings["total"])


def measure(ta, tb, poses, truth, contact):
    """Time every traversal along ``poses``; errors against ``truth`` (coal)."""
    I = np.eye(4)
    q = mjist.Query(ta, tb)
    row = {"leaves": [ta.num_leaves, tb.num_leaves], "depth": [ta.depth, tb.depth],
           "error_bound": q.error_bound, "coverage": [ta.coverage, tb.coverage], "methods": {}}
    for name, call in (
        ("distance", lambda a, b: q.distance(a, b, method="distance")),
        ("backtracking", lambda a, b: q.distance(a, b, method="backtracking")),
        ("backtracking+skip", lambda a, b: q.distance(a, b, method="backtracking", skip=True)),
        ("multipoint", lambda a, b: q.contacts(a, b, max_contacts=4, split_depth=3)),
        ("penetration_volume", q.penetration_volume),
    ):
        q.reset()
        call(I, poses[0])  # warm (compiled code is cached; this loads it)
        q.reset()
        ts, rs = timed(call, poses)
        s = {**stats(ts), "in_contact": stats(ts[contact]) if contact.any() else None,
             "separated": stats(ts[~contact]) if (~contact).any() else None}
        if name == "distance":
            d = np.array([r.distance for r in rs])
            eb = np.array([r.error_bound for r in rs])
            sep = truth > 0
            err = d[sep] - truth[sep]
            rel_ok = truth >= REL_MIN
            rel = (d[rel_ok] - truth[rel_ok]) / truth[rel_ok]
            s.update(err_max=float(err.max()) if err.size else 0.0, err_median=float(np.median(err)) if err.size else 0.0,
                     rel_err_max=float(rel.max()) if rel.size else 0.0,
                     rel_err_median=float(np.median(rel)) if rel.size else 0.0,
                     bound_violations=int(np.sum((truth > d + 1e-9) | (d - eb > truth + 1e-9))))
        row["methods"][name] = s
    m = row["methods"]
    row["speedup"] = {}
    for part in ("in_contact", "separated"):
        base = m["distance"][part]
        if base is None:
            continue
        row["speedup"][part] = {k: base["median_us"] / m[k][part]["median_us"]
                                for k in ("backtracking", "backtracking+skip", "multipoint")}
    return row


def run_pair(label, folder, cfg):
    mx, md, info = jaw.load_pair(folder)
    paths = (Path(info["paths"]["maxilla"]), Path(info["paths"]["mandible"]))
    print(f"[{label}] {paths[0]} + {paths[1]}", flush=True)
    bx, bd = jaw.coal_bvh(mx.vertices, mx.faces), jaw.coal_bvh(md.vertices, md.faces)
    touch = float(info["mandible_pose"][1, 3])
    poses = jaw.chewing_motion(cfg["frames"], info["hinge"], contact_offset=touch + CLENCH)
    coal_t, coal_d = coal_replay(bx, bd, poses)
    truth = np.maximum(coal_d, 0.0)
    contact = coal_d <= 0
    res = {"vertices": [int(len(mx.vertices)), int(len(md.vertices))], "frames": len(poses),
           "contact_frames": int(contact.sum()),
           "coal": {**stats(coal_t), "in_contact": stats(coal_t[contact]) if contact.any() else None,
                    "separated": stats(coal_t[~contact])},
           "leaves_sweep": [], "depth_sweep": {}}

    def pair_trees(n, b):
        ta, sa = _tree(paths[0], n, b)
        tb, sb = _tree(paths[1], n, b)
        return ta, tb, sa + sb

    for n in cfg["leaves"]:
        ta, tb, sec = pair_trees(n, 4)
        row = measure(ta, tb, poses, truth, contact)
        row.update(target_leaves=n, branching=4, build_s=sec)
        res["leaves_sweep"].append(row)
        m = row["methods"]
        print(f"  leaves {n:>7d} ε {row['error_bound'] * 1e3:6.3f} mm  distance {m['distance']['median_us']:7.1f} µs"
              f"  backtracking {m['backtracking']['median_us']:7.1f}  multipoint {m['multipoint']['median_us']:7.1f}"
              f"  volume {m['penetration_volume']['median_us']:7.1f}  max err {m['distance']['err_max'] * 1e3:.3f} mm"
              f"  rel {m['distance']['rel_err_median']:.3f}/{m['distance']['rel_err_max']:.3f}", flush=True)
    for n in cfg["depth_leaves"]:
        rows = []
        for b in cfg["branching"]:
            ta, tb, sec = pair_trees(n, b)
            row = measure(ta, tb, poses, truth, contact)
            row.update(target_leaves=n, branching=b, build_s=sec)
            rows.append(row)
            m = row["methods"]
            print(f"  leaves {n:>6d} branching {b:>2d} depth {row['depth']}  distance {m['distance']['median_us']:7.1f} µs"
                  f"  backtracking {m['backtracking']['median_us']:7.1f}  multipoint {m['multipoint']['median_us']:7.1f}"
                  f"  volume {m['penetration_volume']['median_us']:7.1f}", flush=True)
        res["depth_sweep"][str(n)] = rows
    print(f"  coal median {np.median(coal_t):.0f} µs", flush=True)
    return res


COLORS = {"distance": "C0", "backtracking": "C1", "backtracking+skip": "C2", "multipoint": "C3", "penetration_volume": "C4"}


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(2, 3, figsize=(17, 9.5))
    for pi, (label, r) in enumerate(results.items()):
        ls = "-" if pi == 0 else "--"
        sw = r["leaves_sweep"]
        n = [np.sqrt(x["leaves"][0] * x["leaves"][1]) for x in sw]
        for m, c in COLORS.items():
            axs[0, 0].plot(n, [x["methods"][m]["median_us"] for x in sw], ls, marker="o", color=c, label=f"{label} {m}")
        axs[0, 0].axhline(r["coal"]["median_us"], color="k", ls=ls, lw=1, label=f"{label} coal")
        for ax, key in ((axs[0, 1], 0), (axs[0, 2], 1)):
            keys = list(r["depth_sweep"])
            if key >= len(keys):
                continue
            rows = r["depth_sweep"][keys[key]]
            dep = [0.5 * (x["depth"][0] + x["depth"][1]) for x in rows]
            for m in ("distance", "backtracking", "multipoint", "penetration_volume"):
                ax.plot(dep, [x["methods"][m]["median_us"] for x in rows], ls, marker="o", color=COLORS[m], label=f"{label} {m}")
            for x, d in zip(rows, dep):
                ax.annotate(f"B={x['branching']}", (d, x["methods"]["distance"]["median_us"]), fontsize=6)
            ax.set_title(f"speed vs tree depth, {keys[key]} leaves (paper Fig. {7 + key})")
        eb = [x["error_bound"] * 1e3 for x in sw]
        axs[1, 0].plot(n, eb, ls, marker="s", color="C3", label=f"{label} certified ε_A+ε_B")
        axs[1, 0].plot(n, [x["methods"]["distance"]["err_max"] * 1e3 for x in sw], ls, marker="o", color="C0", label=f"{label} max abs error")
        axs[1, 0].plot(n, [x["methods"]["distance"]["err_median"] * 1e3 for x in sw], ls, marker="^", color="C2", label=f"{label} median abs error")
        axs[1, 1].plot(n, [100 * x["methods"]["distance"]["rel_err_max"] for x in sw], ls, marker="o", color="C0", label=f"{label} max")
        axs[1, 1].plot(n, [100 * x["methods"]["distance"]["rel_err_median"] for x in sw], ls, marker="^", color="C2", label=f"{label} median")
        fine = sw[-1]
        w = 0.2
        for j, part in enumerate(("in_contact", "separated")):
            sp = fine["speedup"].get(part)
            if sp is None:
                continue
            x = np.arange(3) + (2 * pi + j) * w
            axs[1, 2].bar(x, list(sp.values()), width=w, label=f"{label}, {part.replace('_', ' ')}")
            axs[1, 2].set_xticks(np.arange(3) + 1.5 * w, list(sp.keys()))
    axs[0, 0].set_title("speed vs number of leaves (paper Fig. 6)")
    axs[0, 0].set_xlabel("leaves (geometric mean of the two trees)")
    for ax in (axs[0, 0], axs[0, 1], axs[0, 2]):
        ax.set_yscale("log")
        ax.set_ylabel("median µs per frame")
    for ax in (axs[0, 1], axs[0, 2]):
        ax.set_xlabel("tree depth (mean of the two trees)")
    axs[0, 0].set_xscale("log")
    axs[1, 0].set_title("absolute error vs number of leaves (paper Fig. 9)")
    axs[1, 0].set_ylabel("mm")
    axs[1, 1].set_title(f"relative error vs leaves (frames with d ≥ {REL_MIN * 1e3:g} mm)")
    axs[1, 1].set_ylabel("%")
    for ax in (axs[1, 0], axs[1, 1]):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("leaves")
    axs[1, 2].set_title("speedup over plain distance (finest tree, median)")
    axs[1, 2].set_yscale("log")
    for ax in axs.flat:
        if ax.has_data():
            ax.legend(fontsize=6)
        else:
            ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(results, meta) -> str:
    L = [f"Paper figures ({meta['frames']} frames of one chewing motion; {meta['machine']}; "
         f"command `{meta['command']}`, {meta['seconds']:.0f} s).", ""]
    for label, r in results.items():
        L += [f"**{label} pair** ({r['vertices'][0]:,} / {r['vertices'][1]:,} vertices, {r['contact_frames']} of "
              f"{r['frames']} frames in contact; coal {r['coal']['median_us']:.0f} µs median).", "",
              "Fig. 6 and 9: speed and error vs leaves (branching 4); medians µs per frame; errors mm / %:", "",
              "| leaves | depth | ε_A+ε_B mm | distance | backtracking | +skip | multipoint | pen. volume | × coal (distance) "
              "| max / median abs err | max / median rel err | bound viol. | build s (both) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for x in r["leaves_sweep"]:
            m = x["methods"]
            d = m["distance"]
            L.append(f"| {x['leaves'][0]:,} / {x['leaves'][1]:,} | {x['depth'][0]}/{x['depth'][1]} | {x['error_bound'] * 1e3:.3f} "
                     f"| {d['median_us']:.1f} | {m['backtracking']['median_us']:.1f} | {m['backtracking+skip']['median_us']:.1f} "
                     f"| {m['multipoint']['median_us']:.1f} | {m['penetration_volume']['median_us']:.1f} "
                     f"| {r['coal']['median_us'] / d['median_us']:.0f} | {d['err_max'] * 1e3:.3f} / {d['err_median'] * 1e3:.3f} "
                     f"| {100 * d['rel_err_max']:.1f} / {100 * d['rel_err_median']:.1f} | {d['bound_violations']} "
                     f"| {x['build_s']:.1f} |")
        L += ["", "Speedup over plain distance traversal (medians), finest tree of the sweep:", "",
              "| frames | plain µs | backtracking | backtracking+skip | multipoint |", "|---|---|---|---|---|"]
        fine = r["leaves_sweep"][-1]
        for part, sp in fine["speedup"].items():
            L.append(f"| {part.replace('_', ' ')} | {fine['methods']['distance'][part]['median_us']:.1f} | {sp['backtracking']:.2f}× "
                     f"| {sp['backtracking+skip']:.1f}× | {sp['multipoint']:.2f}× |")
        for n, rows in r["depth_sweep"].items():
            L += ["", f"Figs. 7-8: speed vs tree depth, {int(n):,} leaves (medians µs):", "",
                  "| branching | depth | distance | backtracking | multipoint | pen. volume | build s |", "|---|---|---|---|---|---|---|"]
            for x in rows:
                m = x["methods"]
                L.append(f"| {x['branching']} | {x['depth'][0]}/{x['depth'][1]} | {m['distance']['median_us']:.1f} "
                         f"| {m['backtracking']['median_us']:.1f} | {m['multipoint']['median_us']:.1f} "
                         f"| {m['penetration_volume']['median_us']:.1f} | {x['build_s']:.1f} |")
        L.append("")
    return "\n".join(L) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="bundled pair, 300 frames, 1k-10k leaves, depth at 3k only")
    ap.add_argument("--pairs", default="real,bundled")
    ap.add_argument("--out", default=str(ROOT / "out"))
    a = ap.parse_args(argv)
    cfg = QUICK if a.quick else FULL
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    avail = pairs_available()
    want = [p for p in (["bundled"] if a.quick else a.pairs.split(",")) if p in avail]
    if not want:
        print("no jaw pair found", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    results = {p: run_pair(p, avail[p], cfg) for p in want}
    meta = {"frames": cfg["frames"], "config": cfg, "seconds": time.perf_counter() - t0,
            "command": "python scripts/bench_paper.py" + (" --quick" if a.quick else ""),
            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"}
    write_outputs(out, "bench_paper", {"meta": meta, "results": results}, lambda path: plot(results, path), markdown(results, meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
