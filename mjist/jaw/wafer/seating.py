"""Proof that a wafer seats both arches: coal's exact distance between the wafer and each arch
at its seated pose (the maxilla as stored, the mandible at ``mandible_transform``), the deepest
penetration where they meet (vertices inside the other mesh), and each cusp tip's distance to
the wafer, which must be the clearance (the imprints are real, not a flat plate)."""
from __future__ import annotations

import numpy as np

PENETRATION_MM = 0.02  # deepest allowed overlap of an arch and the wafer
TIP_SLACK_MM = 0.05  # a cusp tip lies within the clearance plus this of the wafer


def seating(maxilla, mandible, wafer, clearance: float, tips: dict) -> dict:
    """Each arch against the wafer, all ``(V, F)`` in one frame (the mandible at its seated pose):
    coal's distance, the deepest overlap and the cusp tips' distances to the wafer (m in, mm out)."""
    from ...geometry.bvh import BVH
    from ..exact import coal_bvh, coal_distance

    Vw, Fw = (np.ascontiguousarray(a) for a in wafer)
    bw = coal_bvh(Vw, Fw)
    wbvh = BVH.of_triangles(Vw, Fw)
    I4 = np.eye(4)
    out = {}
    for name, (V, F) in (("maxilla", maxilla), ("mandible", mandible)):
        V = np.ascontiguousarray(V, dtype=np.float64)
        F = np.ascontiguousarray(F, dtype=np.int64)
        gap = coal_distance(coal_bvh(V, F), I4, bw, I4)
        abvh = BVH.of_triangles(V, F)
        # the deepest overlap: wafer vertices inside the arch, arch vertices inside the wafer
        depth = 0.0
        if gap <= 0.0:
            inside_a = abvh.contains(np.ascontiguousarray(Vw), V, F)
            if inside_a.any():
                depth = max(depth, float(abvh.distance(np.ascontiguousarray(Vw[inside_a]), V, F).max()))
            inside_w = wbvh.contains(V, Vw, Fw)
            if inside_w.any():
                depth = max(depth, float(wbvh.distance(np.ascontiguousarray(V[inside_w]), Vw, Fw).max()))
        T = np.ascontiguousarray(tips[name], dtype=np.float64).reshape(-1, 3)
        td = wbvh.distance(T, Vw, Fw) if len(T) else np.empty(0)
        out[name] = {"coal_distance_mm": float(gap) * 1e3, "penetration_mm": depth * 1e3, "cusp_tips": len(T),
                     "tip_distance_median_mm": float(np.median(td)) * 1e3 if len(td) else None,
                     "tip_distance_max_mm": float(td.max()) * 1e3 if len(td) else None,
                     "ok": depth * 1e3 <= PENETRATION_MM and len(td) >= 3
                     and float(td.max()) * 1e3 <= clearance * 1e3 + TIP_SLACK_MM}
    out["ok"] = out["maxilla"]["ok"] and out["mandible"]["ok"]
    return out
