"""Closing open, many-piece anatomy (``mjist.geometry.repair``) on the shared CBCT jaws made into
the surfaces users bring, against the original closed surface.

    python scripts/open_scans.py [--source ../shared/data/jaw] [--deviation 0.2,0.5] [--out out/open_scans]

Each jaw (in mm) is made into two kinds of open surface:

- ``ct``: like a CT segmentation: cut open at the top (the scan's edge), holes of 0.3-5 mm
  punched, 50 closed specks scattered (some inside the bone), 6 loose patches cut free (50+ pieces);
- ``seams``: split along five planes into 25 or so pieces that stop sharing vertices (a bone
  exported region by region), with a 3 mm hole.

Each is closed with ``close_surface`` at each allowed deviation. Reported per case: the method
taken (or the refusal and why), the deviation of the input's vertices (Hausdorff, mean), the
added area (with MeshFix's overlapping shells, mostly inside the solid), how much the closed
solid differs from the original's (the volume in one and not the other over the original's,
from the winding numbers at random points: the ``ct`` surfaces lack their cut-off top), and the
time. Writes ``<out>/open_scans.{json,md}``.
The generators are also the tests' (``tests/geometry/test_repair.py``).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parent.parent


def split_along_seams(tm, seams, seed=0):
    """``tm``'s faces in pieces cut along random planes through it: faces keep their place, the
    pieces stop sharing vertices (a segmentation exported region by region)."""
    rng = np.random.default_rng(seed)
    C = tm.triangles_center
    label = np.zeros(len(tm.faces), np.int64)
    for _ in range(seams):
        n = rng.normal(size=3)
        label = 2 * label + ((C - C[rng.integers(len(C))]) @ n > 0)
    V, F, parts = np.asarray(tm.vertices), np.asarray(tm.faces), []
    for k in np.unique(label):
        u, inv = np.unique(F[label == k], return_inverse=True)
        parts.append(trimesh.Trimesh(V[u], inv.reshape(-1, 3), process=False))
    return trimesh.util.concatenate(parts)


def ct_like(V, F, up=1, seed=0, open_frac=0.1, holes=(0.3, 0.6, 1.2, 2.5, 5.0), specks=50, patches=6):
    """A closed surface in mm made like a CT segmentation: cut open at the top, holes punched, closed
    specks scattered (some inside the bone), loose patches cut free by 1 mm rings."""
    rng = np.random.default_rng(seed)
    C = V[F].mean(1)
    drop = C[:, up] > V[:, up].max() - open_frac * np.ptp(V[:, up])
    for r in holes:
        drop |= np.linalg.norm(C - C[rng.choice(np.flatnonzero(~drop))], axis=1) < r
    for _ in range(patches):
        d = np.linalg.norm(C - C[rng.choice(np.flatnonzero(~drop))], axis=1)
        r = rng.uniform(1.5, 3.0)
        drop |= (d > r) & (d < r + 1.0)
    parts = [trimesh.Trimesh(V, F[~drop], process=False)]
    for _ in range(specks):
        s = trimesh.creation.icosphere(1, radius=rng.uniform(0.2, 0.8))
        s.apply_translation(V[rng.integers(len(V))] + rng.normal(0.0, 1.0, 3))
        parts.append(s)
    out = trimesh.util.concatenate(parts)
    out.remove_unreferenced_vertices()
    return out


def seams_case(V, F):
    keep = np.linalg.norm(V[F].mean(1) - V[0], axis=1) > 3.0
    return split_along_seams(trimesh.Trimesh(V, F[keep], process=False), 5)


def main(argv=None):
    from mjist.errors import MeshError
    from mjist.geometry.mesh import load_mesh
    from mjist.geometry.repair import _solid_mismatch, close_surface

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--source", default=str(ROOT.parent / "shared" / "data" / "jaw"))
    ap.add_argument("--deviation", default="0.2,0.5", help="allowed deviations, mm")
    ap.add_argument("--out", default=str(ROOT / "out" / "open_scans"))
    a = ap.parse_args(argv)
    rows = []
    for jaw in ("maxilla", "mandible"):
        m = load_mesh(Path(a.source) / f"{jaw}.obj")
        V, F = m.vertices * 1000.0, m.faces
        original = trimesh.Trimesh(V, F, process=False)
        for kind, scan in (("ct", ct_like(V, F)), ("seams", seams_case(V, F))):
            for dev in (float(x) for x in a.deviation.split(",")):
                row = {"jaw": jaw, "kind": kind, "pieces": len(scan.split(only_watertight=False)),
                       "vertices": len(scan.vertices), "allowed_mm": dev}
                t0 = time.perf_counter()
                try:
                    out, c = close_surface(scan, dev)
                except MeshError as exc:
                    row.update(seconds=time.perf_counter() - t0, refused=str(exc))
                    rows.append(row)
                    print(row)
                    continue
                row["seconds"] = time.perf_counter() - t0
                row.update(method=c.method, hausdorff_mm=c.hausdorff, mean_mm=c.mean_deviation, added_mm2=c.added_area,
                           left_out=c.left_out, inner_vertices=c.inner, out_vertices=len(out.vertices),
                           solid_vs_original=_solid_mismatch(original, out))
                rows.append(row)
                print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()})
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "open_scans.json").write_text(json.dumps(rows, indent=2))
    lines = ["| jaw | surface | pieces | allowed | method | input moved: max, mean | added | solid differs from the original | time |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "refused" in r:
            why = r["refused"].split("(", 2)[-1].split("):")[0]
            lines.append(f"| {r['jaw']} | {r['kind']} | {r['pieces']} | {r['allowed_mm']} mm | refused: {why} | | | | "
                         f"{r['seconds']:.0f} s |")
            continue
        lines.append(f"| {r['jaw']} | {r['kind']} | {r['pieces']} | {r['allowed_mm']} mm | {r['method']} | "
                     f"{r['hausdorff_mm']:.3f}, {r['mean_mm']:.4f} mm | {r['added_mm2']:.0f} mm² | "
                     f"{100 * r['solid_vs_original']:.1f}% | {r['seconds']:.0f} s |")
    (out / "open_scans.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
