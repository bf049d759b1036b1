"""Bring-your-own-jaws check: other people's conventions, end to end.

Makes, from a jaw pair in the jaw frame (the bundled jaws, the shared CBCT pair), the pairs a
user brings: converted to millimetres with +z superior (and the anterior along -y), cropped to
the teeth (no condyles, rami or fossae: two exact half-space cuts with manifold3d), and a
cropped copy with holes cut into the gingiva (an open surface). Then runs each through
``mjist scene``, ``mjist demo --data``, ``mjist occlusion --data`` and ``mjist haptic --data``
with no flags and with explicit flags, and measures the occlusion search against the designed
occlusion (the source pair's stored pose, brought into the converted frame).

    python scripts/byo_jaws.py [--source models|../shared/data/jaw] [--out out/byo] [--starts 32]

Writes ``out/byo/byo.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

# jaw frame (x left, y up, z anterior) -> the converted files' frame: x left, y posterior, z up
TO_FILE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _load(path) -> trimesh.Trimesh:
    m = trimesh.load(path, force="mesh", process=False)
    m.merge_vertices(merge_tex=True, merge_norm=True)
    return m


def _crop(m: trimesh.Trimesh, keep_below: float | None, keep_above: float | None, back: float) -> trimesh.Trimesh:
    """Exact half-space cuts (jaw frame, metres): keep y within the band and z in front of ``back``."""
    import manifold3d

    s = manifold3d.Manifold(manifold3d.Mesh(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)))
    s = s.trim_by_plane((0.0, 0.0, 1.0), back)  # keep z >= back
    if keep_above is not None:
        s = s.trim_by_plane((0.0, 1.0, 0.0), keep_above)
    if keep_below is not None:
        s = s.trim_by_plane((0.0, -1.0, 0.0), -keep_below)
    out = s.to_mesh()
    return trimesh.Trimesh(np.asarray(out.vert_properties[:, :3], np.float64), np.asarray(out.tri_verts, np.int64), process=False)


def _holes(m: trimesh.Trimesh, other: trimesh.Trimesh, n: int = 5, radius: float = 1.0e-3, seed: int = 0) -> trimesh.Trimesh:
    """Faces removed around ``n`` gingiva points (vertices over 4 mm from the other jaw)."""
    from mjist.geometry.bvh import BVH

    V = np.asarray(m.vertices)
    rng = np.random.default_rng(seed)
    cand = rng.choice(len(V), min(len(V), 4000), replace=False)
    d = BVH.of_triangles(other.vertices, other.faces).distance(V[cand], np.asarray(other.vertices, float), np.asarray(other.faces, np.int64))
    far = cand[d > 4e-3]
    keep = np.ones(len(m.faces), bool)
    C = m.triangles_center
    for i in rng.choice(far, n, replace=False):
        keep &= np.linalg.norm(C - V[i], axis=1) > radius
    out = trimesh.Trimesh(V, m.faces[keep], process=False)
    out.remove_unreferenced_vertices()
    return out


def variants(source, out) -> dict:
    """The converted pairs of ``source`` in ``out/<name>/``: {name: (folder, S)} with ``S`` the 4x4
    map from the jaw frame (metres) to the files' frame."""
    from mjist.jaw.pair import load_pair

    mx, md = _load(Path(source) / "maxilla.obj"), _load(Path(source) / "mandible.obj")
    _, _, info = load_pair(source)
    pose = info["mandible_pose"]
    md_occ = md.copy()
    md_occ.apply_transform(pose)  # the designed occlusion is the stored pose of the converted files
    fr = info["arches"]["mandible"]
    y0 = float(fr.origin[1])
    back = float(fr.origin[2] - fr.depth - 2e-3)  # behind the last molars
    S = np.eye(4)
    S[:3, :3] = 1000.0 * TO_FILE
    pairs = {"mm_z": (mx, md_occ),
             "mm_z_teeth": (_crop(mx, None, y0 - 10e-3, back), _crop(md_occ, y0 + 10e-3, None, back))}
    pairs["mm_z_teeth_holes"] = (_holes(pairs["mm_z_teeth"][0], pairs["mm_z_teeth"][1]),
                                 _holes(pairs["mm_z_teeth"][1], pairs["mm_z_teeth"][0], seed=1))
    out_dirs = {}
    for name, (a, b) in pairs.items():
        folder = Path(out) / name
        os.makedirs(folder, exist_ok=True)
        for jaw, m in (("maxilla", a), ("mandible", b)):
            c = m.copy()
            c.apply_transform(S)
            c.export(folder / f"{jaw}.stl")
        out_dirs[name] = (folder, S)
    return out_dirs


def _run(cmd, log) -> dict:
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    log.write(f"$ {' '.join(map(str, cmd))}\n{p.stdout}\n{p.stderr}\n")
    return {"cmd": " ".join(map(str, cmd)), "returncode": p.returncode, "seconds": round(time.perf_counter() - t, 1),
            "stderr_tail": p.stderr.strip().splitlines()[-1:] if p.returncode else []}


def designed_error(occ_json) -> dict:
    """The best candidate against the scene's reference (the designed occlusion: the files store
    the mandible there, and the reference is where it first touches moving along up)."""
    res = json.loads(Path(occ_json).read_text())
    best = res["candidates"][0]
    return {"max_mm": best["error"]["max_mm"], "rms_mm": best["error"]["rms_mm"], "rotation_deg": best["error"]["rotation_deg"],
            "starts": best["starts"], "regions": best["regions"], "both_sides": any(r.startswith("left") for r in best["regions"])
            and any(r.startswith("right") for r in best["regions"])}


def pose_difference(scene_a, occ_a, scene_b, occ_b) -> dict:
    """Best candidates of two searches of the same jaws (scenes in the same world frame): the
    largest displacement of a mandible vertex between them (mm) and the rotation (degrees)."""
    import mujoco
    from scipy.spatial.transform import Rotation

    from mjist.mujoco.scene import geom_pose_at, mesh_of

    m = mujoco.MjModel.from_xml_path(str(scene_a))
    g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "mandible")
    V, _ = mesh_of(m, g)
    a = json.loads(Path(occ_a).read_text())["candidates"][0]
    b = json.loads(Path(occ_b).read_text())["candidates"][0]
    A, B = geom_pose_at(m, g, a["pos"], a["quat"]), geom_pose_at(m, g, b["pos"], b["quat"])
    dv = np.linalg.norm(V @ (A[:3, :3] - B[:3, :3]).T + (A[:3, 3] - B[:3, 3]), axis=1)
    e = {"max_mm": float(dv.max() * 1e3), "rotation_deg": float(np.degrees(Rotation.from_matrix(A[:3, :3] @ B[:3, :3].T).magnitude()))}
    return {"max_mm": e["max_mm"], "rotation_deg": e["rotation_deg"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=None, help="jaw-frame pair folder (default: the bundled jaws)")
    ap.add_argument("--out", default="out/byo")
    ap.add_argument("--starts", type=int, default=32)
    ap.add_argument("--only", help="comma-separated variants")
    args = ap.parse_args(argv)
    from mjist.jaw import BUNDLED

    source = Path(args.source or BUNDLED)
    out = Path(args.out) / source.name
    os.makedirs(out, exist_ok=True)
    report = {"source": str(source), "variants": {}}
    mjist = [sys.executable, "-m", "mjist.cli"]
    with open(out / "byo.log", "w") as log:
        orig = out / "original"
        report["original"] = _run([*mjist, "occlusion", "--data", source, "--out-dir", orig, "--starts", str(args.starts), "-q"], log)
        for name, (folder, _S) in variants(source, out / "data").items():
            if args.only and name not in args.only.split(","):
                continue
            flags = ["--units", "mm", "--up", "+z", "--repair", "on" if "holes" in name else "off"]
            r = {}
            for tag, extra in (("auto", []), ("flags", flags)):
                o = out / name / tag
                r[tag] = {
                    "scene": _run([*mjist, "scene", folder / "maxilla.stl", folder / "mandible.stl", "--kind", "occlusion",
                                   "-o", o / "scene" / "scene.xml", *extra], log),
                    "demo": _run([*mjist, "demo", "--data", folder, "--out-dir", o / "demo", "--no-picture", "-q", *extra], log),
                    "occlusion": _run([*mjist, "occlusion", "--data", folder, "--out-dir", o / "occlusion", "--starts",
                                       str(args.starts), "-q", *extra], log),
                    "haptic": _run([*mjist, "haptic", "--data", folder, "--out-dir", o / "haptic", "--trajectory", "close",
                                    "--seconds", "0.3", "-q", *extra], log),
                }
                if r[tag]["occlusion"]["returncode"] == 0:
                    r[tag]["occlusion"]["result"] = designed_error(o / "occlusion" / "occlusion.json")
                    pj = json.loads((o / "occlusion" / "pair.json").read_text())
                    r[tag]["pair"] = {k: pj[k] for k in ("hinge_source", "teeth_only", "notes")}
            if name == "mm_z" and report["original"]["returncode"] == 0 and r["auto"]["occlusion"]["returncode"] == 0:
                r["same_pose_as_original"] = pose_difference(
                    orig / "occlusion_search.xml", orig / "occlusion.json", out / name / "auto" / "occlusion" / "occlusion_search.xml",
                    out / name / "auto" / "occlusion" / "occlusion.json")
            report["variants"][name] = r
            print(name, json.dumps(r.get("same_pose_as_original")), json.dumps({t: {k: (v.get("returncode"), v.get("seconds"), v.get("result")) for k, v in r[t].items()
                                        if isinstance(v, dict) and "returncode" in v} for t in r}, indent=None))
    (out / "byo.json").write_text(json.dumps(report, indent=1, default=str))
    print(f"written {out / 'byo.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
