"""Behaviour fingerprint: hashes of trees, contacts and jaw-application outputs (JSON).

Run before and after a change that must not change behaviour (a refactor, a move of code);
equal fingerprints mean the same trees bit for bit, the same contacts and the same closure and
occlusion results. Uses only the public API and the CLI, so it runs on either side of a move.

    python scripts/fingerprint.py --out out/fingerprint_before.json
    python scripts/fingerprint.py --out out/fingerprint_after.json --compare out/fingerprint_before.json

Timings are dropped before hashing (any key that names a time or a rate), and so is the
scene's path (the checkout's place); everything else,
floats included, is hashed exactly. The shared CBCT pair and bunny are used when
``../shared/data`` is present. Trees are built into a fresh cache folder, never reused.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"
TIME_WORDS = ("_s", "_us", "seconds", "per_second", "timings", "time", "hook", "ready")


def _timeless(obj):
    """``obj`` without the entries whose key names a time, a rate or hook counters."""
    if isinstance(obj, dict):
        return {k: _timeless(v) for k, v in obj.items()
                if k != "scene" and not any(k.endswith(w) or k == w.strip("_") or w in k for w in TIME_WORDS)}
    if isinstance(obj, list):
        return [_timeless(v) for v in obj]
    return obj


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def tree_fingerprint(tree) -> dict:
    h = hashlib.sha256()
    for name in ("leaf_centers", "leaf_radii", "centers", "radii", "child_start", "child_count", "parent"):
        h.update(np.ascontiguousarray(getattr(tree, name)).tobytes())
    return {"arrays": h.hexdigest()[:16], "leaves": int(tree.num_leaves), "eps": float(tree.error_bound),
            "coverage": float(tree.coverage)}


def trees() -> dict:
    import mjist

    out = {}
    jobs = [("bundled_mandible", ROOT / "models" / "mandible.obj", 5e-4),
            ("bundled_maxilla", ROOT / "models" / "maxilla.obj", 5e-4)]
    if SHARED.exists():
        jobs += [("bunny", SHARED / "stanford" / "bunny.obj", None),
                 ("cbct_mandible", SHARED / "jaw" / "mandible.obj", 3e-4),
                 ("cbct_maxilla", SHARED / "jaw" / "maxilla.obj", 3e-4)]
    for name, path, eps in jobs:
        out[name] = tree_fingerprint(mjist.build(str(path), max_error=eps))
        print(name, out[name], flush=True)
    return out


def queries() -> dict:
    """Distances and contacts of the bundled pair at a few poses near occlusion."""
    import mjist

    a = mjist.build(str(ROOT / "models" / "maxilla.obj"), max_error=5e-4)
    b = mjist.build(str(ROOT / "models" / "mandible.obj"), max_error=5e-4)
    q = mjist.Query(a, b)
    rng = np.random.default_rng(0)
    res = []
    for _ in range(8):
        P = np.eye(4)
        P[:3, 3] = rng.uniform(-1e-3, 1e-3, 3) + [0, 0.5e-3, 0]
        dd = q.distance(np.eye(4), P)
        cc = q.contacts(np.eye(4), P)
        res.append([float(dd.distance), float(dd.error_bound), int(cc.count),
                    np.asarray(cc.positions).tolist(), np.asarray(cc.normals).tolist(), np.asarray(cc.depths).tolist()])
    return {"digest": _digest(res), "first": res[0][:2]}


def cli(args: list[str], out_json: str, work: Path, env: dict) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    out = work / args[0]
    cmd = [sys.executable, "-m", "mjist.cli", *args, "--out-dir", str(out), "-q"]
    r = subprocess.run(cmd, env=env, cwd=work, capture_output=True, text=True)
    if r.returncode:
        return {"error": r.stderr[-2000:]}
    data = _timeless(json.loads((out / out_json).read_text()))
    return {"digest": _digest(data), "data": data}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="out/fingerprint.json")
    p.add_argument("--compare", help="a fingerprint JSON to compare with (exit 1 when they differ)")
    p.add_argument("--skip-trees", action="store_true", help="only the queries and the CLI outputs")
    args = p.parse_args()
    cache = tempfile.mkdtemp(prefix="mjist-fp-cache-")
    os.environ["MJIST_CACHE"] = cache
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    work = Path(tempfile.mkdtemp(prefix="mjist-fp-"))
    fp = {}
    if not args.skip_trees:
        fp["trees"] = trees()
    fp["queries"] = queries()
    print("queries", fp["queries"], flush=True)
    fp["demo"] = cli(["demo", "--no-picture"], "closure_ist.json", work, env)
    print("demo", fp["demo"].get("digest"), fp["demo"].get("error", ""), flush=True)
    if SHARED.exists():
        fp["demo_cbct"] = cli(["demo", "--no-picture", "--data", str(SHARED / "jaw"), "--seconds", "0.3"],
                              "closure_ist.json", work / "cbct", env)
        print("demo_cbct", fp["demo_cbct"].get("digest"), fp["demo_cbct"].get("error", ""), flush=True)
    fp["occlusion"] = cli(["occlusion", "--starts", "16", "--threads", "2"], "occlusion.json", work, env)
    print("occlusion", fp["occlusion"].get("digest"), fp["occlusion"].get("error", ""), flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    Path(args.out).write_text(json.dumps(fp, indent=1))
    if args.compare:
        ref = json.loads(Path(args.compare).read_text())

        def canonical(part):  # the CLI parts re-filtered, so an older fingerprint compares too
            return _timeless(part["data"]) if isinstance(part, dict) and "data" in part else part

        diff = [k for k in fp if _digest(canonical(fp[k])) != _digest(canonical(ref.get(k)))]
        for k in diff:
            print(f"DIFFERS: {k}")
        print("same behaviour" if not diff else f"{len(diff)} part(s) differ")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
