"""A dental arch's own frame: occlusal plane, midline, anterior direction, regions, hinge, mass.

Nothing here assumes where the arch lies in its file: the frame comes from the arch's
occlusal surface (the vertices within reach of the other arch at the occlusion), so a scan
whose arch sits at x = 16–92 mm labels its left and right sides correctly.

* **Up** is given (``mjist.jaw.orient`` detects it); the occlusal plane is the least-squares
  plane of the occlusal points, reported as its tilt from up.
* **Midline**: the arch is mirror-symmetric about it. Its direction is the in-plane principal
  axis (or the one across it) of the occlusal points, refined with their offset by minimising
  the mirror mismatch (median nearest-neighbour distance of the mirrored points).
* **Anterior** is the end of the midline where the arch closes (the incisors sit on the
  midline, the molars away from it).
* **Regions**: left/right of the midline × anterior / premolar / molar by the distance
  behind the most anterior occlusal point (fractions of the arch's depth).
* **Hinge** of a teeth-only mandible: Bonwill's equilateral triangle (condyles 100 mm apart,
  each 100 mm from the lower incisal point) tilted by Balkwill's angle (26°) above the
  occlusal plane: the condylar axis' centre lies 86.6 mm from the incisal point, 77.8 mm
  behind it and 38.0 mm above it.
* **Mass** of a teeth-only mandible: the mass and inertia of a whole adult mandible (the
  shared CBCT mandible at bone density), placed relative to the incisal point as on that
  mandible, so a scene of the teeth alone moves like a jaw.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BAND = 6e-3  # m: occlusal points within this height of the touching teeth (drops the TMJ surfaces)
MIDLINE = 4e-3  # m: points this close to the midline count as "on" it (the incisors)
# fractions of the arch depth behind the most anterior occlusal point: incisors and canines,
# premolars, then molars
REGION_CUTS = (0.3, 0.55)
BONWILL_SIDE = 0.100  # m: Bonwill triangle side (condyle to condyle, condyle to incisal point)
BALKWILL_DEG = 26.0  # angle between the Bonwill triangle and the occlusal plane
# how far the hinge estimate may be from the true condylar axis (m, about one standard deviation):
# adult intercondylar widths and incisal-to-condyle distances spread by about a tenth around
# Bonwill's 100 mm, Balkwill's angle by about 5°; a fit to the condyles themselves is within a millimetre
BONWILL_UNCERTAINTY = 0.010
CONDYLE_UNCERTAINTY = 0.001
# how far forward or back of their given place the condyles may sit in occlusion when a pair is
# given open (its pose says where they are, not where they seat); the search samples the seat over
# this. A pair given in occlusion has them seated: 0
SEAT_UNCERTAINTY = 0.002
RAMUS_HEIGHT = 0.015
# a dental arch runs 35-55 mm front to back; the first contact of a pair given open (condyles in
# their fossae) spans under 20 mm: points this shallow are not the teeth meeting
ARCH_MIN_DEPTH = 0.025  # m: a mandible reaching this far above its occlusal plane has rami and condyles
# a whole adult mandible (the shared CBCT mandible, bone density 1900 kg/m^3): mass, inertia
# about its centre of mass (jaw-frame axes x left, y up, z anterior: ixx iyy izz ixy ixz iyz)
# and the centre of mass relative to the lower incisal point (jaw frame)
MANDIBLE_MASS = 0.110
MANDIBLE_INERTIA = (8.07e-5, 1.628e-4, 1.347e-4, 0.0, 0.0, 2.46e-5)
MANDIBLE_COM_FROM_INCISAL = (0.0, -0.0084, -0.0388)

@dataclass
class ArchFrame:
    """One arch's frame in the coordinates of the points it was fitted to."""

    origin: np.ndarray  # on the midline, in the occlusal plane, at the most anterior occlusal point
    left: np.ndarray
    up: np.ndarray
    anterior: np.ndarray
    depth: float  # m, front to back of the occlusal points
    width: float  # m, side to side
    plane_tilt_deg: float  # occlusal plane normal against up
    symmetry_mm: float  # median mirror mismatch of the occlusal points (how symmetric the fit is)
    incisal: np.ndarray  # highest occlusal point on the midline at the front (a mandible's incisal point)

    def local(self, P) -> np.ndarray:
        """Points ``(n, 3)`` as (lateral, height, behind-the-front) in this frame (m)."""
        X = np.asarray(P, float) - self.origin
        return np.stack([X @ self.left, X @ self.up, -(X @ self.anterior)], axis=-1)

    def regions(self, P) -> list[str]:
        """Region name of each point: ``left|right-anterior|premolar|molar``."""
        L = self.local(np.atleast_2d(P))
        out = []
        for lat, _, back in L:
            f = back / max(self.depth, 1e-9)
            part = "anterior" if f < REGION_CUTS[0] else "premolar" if f < REGION_CUTS[1] else "molar"
            out.append(f"{'left' if lat > 0 else 'right'}-{part}")
        return out

    def as_dict(self) -> dict:
        return {"origin": self.origin.tolist(), "left": self.left.tolist(), "up": self.up.tolist(),
                "anterior": self.anterior.tolist(), "depth_mm": self.depth * 1e3, "width_mm": self.width * 1e3,
                "plane_tilt_deg": self.plane_tilt_deg, "symmetry_mm": self.symmetry_mm,
                "incisal": self.incisal.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "ArchFrame":
        """The frame ``as_dict`` wrote."""
        v = {k: np.asarray(d[k], float) for k in ("origin", "left", "up", "anterior", "incisal")}
        return cls(depth=d["depth_mm"] * 1e-3, width=d["width_mm"] * 1e-3, plane_tilt_deg=d["plane_tilt_deg"],
                   symmetry_mm=d["symmetry_mm"], **v)


def _mirror_error(X, tree, lat_dir, offset) -> float:
    s = X @ lat_dir - offset
    M = X - 2.0 * s[:, None] * lat_dir
    return float(np.median(tree.query(M)[0]))


def arch_frame(points, up) -> ArchFrame:
    """The frame of an arch from its occlusal points ``(n, 3)`` (m) and the up direction.

    Raises ``ValueError`` when there are too few points to fit (the arches do not meet).
    """
    from scipy.spatial import cKDTree

    up = np.asarray(up, float) / np.linalg.norm(up)
    P = np.asarray(points, float)
    if len(P) < 20:
        raise ValueError(f"only {len(P)} occlusal points: the two arches barely meet; place them in occlusion")
    h = P @ up
    P = P[np.abs(h - np.median(h)) < BAND]
    fit = P[np.linspace(0, len(P) - 1, min(len(P), 1500)).astype(np.int64)]
    e1 = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    c = fit.mean(axis=0)
    X2 = np.stack([(fit - c) @ e1, (fit - c) @ e2], axis=1)
    tree = cKDTree(X2)
    _, vecs = np.linalg.eigh(np.cov(X2.T))

    def search(angles, offsets):
        best = (np.inf, None, 0.0, 0.0)
        for a in angles:
            lat = np.array([-np.sin(a), np.cos(a)])
            for off in offsets:
                err = _mirror_error(X2, tree, lat, off)
                if err < best[0]:
                    best = (err, lat, off, a)
        return best

    # the symmetry line is a principal axis of a symmetric point set: a coarse grid about both,
    # then a fine one about the best
    coarse = min((search(np.arctan2(v[1], v[0]) + np.radians(np.arange(-6.0, 6.5, 2.0)), np.arange(-6e-3, 6.5e-3, 1e-3))
                  for v in vecs.T), key=lambda b: b[0])
    best = search(coarse[3] + np.radians(np.arange(-2.0, 2.25, 0.5)), coarse[2] + np.arange(-1e-3, 1.05e-3, 2.5e-4))
    err, lat2, off, _ = best
    ax2 = np.array([lat2[1], -lat2[0]])
    s = X2 @ lat2 - off
    t = X2 @ ax2
    on_line = np.abs(s) < MIDLINE
    if on_line.sum() >= 5:
        forward = float(np.mean(t[on_line]) - np.mean(t))
    else:  # no incisors: the arch is narrower at its front than across the molars
        lo, hi = np.quantile(t, [0.2, 0.8])
        forward = float(np.ptp(s[t < lo]) - np.ptp(s[t > hi]))
    if forward < 0:
        ax2 = -ax2
    anterior = ax2[0] * e1 + ax2[1] * e2
    left = np.cross(up, anterior)
    mid = c + off * (lat2[0] * e1 + lat2[1] * e2)  # on the symmetry line
    a = (P - mid) @ anterior
    front = a.max()
    lat = (P - mid) @ left
    near_front = (np.abs(lat) < MIDLINE) & (a > front - 4e-3)
    tip = P[near_front][np.argmax(P[near_front] @ up)] if near_front.any() else P[np.argmax(a)]
    incisal = mid + front * anterior + float((tip - mid) @ up) * up
    _, _, vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
    tilt = float(np.degrees(np.arccos(min(1.0, abs(vt[2] @ up)))))
    origin = mid + front * anterior + float(np.median((P - mid) @ up)) * up
    return ArchFrame(origin=origin, left=left, up=up, anterior=anterior, depth=float(np.ptp(a)), width=float(np.ptp(lat)),
                     plane_tilt_deg=tilt, symmetry_mm=err * 1e3, incisal=incisal)


def occlusal_points(V, other_V, other_F, reach: float = 3e-3, up=None) -> np.ndarray:
    """Vertices of ``V`` within ``reach`` (m) of the other surface (both in one frame).

    With ``up``, only those within ``BAND`` in height of the closest tenth (the teeth that
    touch: a TMJ keeps its joint space, so its surfaces, also within ``reach`` of each other,
    drop out however many vertices they have).
    """
    from ..geometry.bvh import BVH

    V = np.asarray(V, float)
    lo, hi = other_V.min(axis=0) - reach, other_V.max(axis=0) + reach
    cand = np.flatnonzero(((V >= lo) & (V <= hi)).all(axis=1))
    if cand.size == 0:
        return V[:0]
    d = BVH.of_triangles(other_V, other_F).distance(V[cand], other_V, other_F, within=reach)
    keep = d < reach
    P, d = V[cand[keep]], d[keep]
    if up is None or len(P) == 0:
        return P
    h = P @ (np.asarray(up, float) / np.linalg.norm(up))
    closest = np.argsort(d, kind="stable")[:max(1, len(d) // 10)]
    return P[np.abs(h - np.median(h[closest])) < BAND]


def facing_band(V, F, direction) -> np.ndarray:
    """Vertices of ``(V, F)`` facing ``direction`` within ``BAND`` of the surface's extreme along it:
    a maxilla's occlusal surface for ``direction`` down, wherever the mandible is."""
    import trimesh

    d = np.asarray(direction, float) / np.linalg.norm(direction)
    V = np.asarray(V, float)
    h = V @ d
    facing = trimesh.Trimesh(V, F, process=False).vertex_normals @ d > 0.5
    return V[facing & (h > h.max() - BAND)]


def has_rami(mandible_V, frame: ArchFrame) -> bool:
    """Whether the mandible rises ``RAMUS_HEIGHT`` above its occlusal plane (rami and condyles)."""
    return float(np.max((np.asarray(mandible_V) - frame.origin) @ frame.up)) > RAMUS_HEIGHT


def bonwill_hinge(frame: ArchFrame) -> np.ndarray:
    """Centre of the condylar axis estimated from the lower incisal point (Bonwill, Balkwill)."""
    reach = BONWILL_SIDE * np.sqrt(3.0) / 2.0
    a = np.radians(BALKWILL_DEG)
    return frame.incisal - reach * np.cos(a) * frame.anterior + reach * np.sin(a) * frame.up


def anatomical_inertia(frame: ArchFrame) -> dict:
    """Mass, centre of mass and full inertia (about the centre, jaw-frame axes) of a whole
    mandible, for a teeth-only one whose frame is ``frame`` (jaw frame)."""
    com = frame.incisal + np.asarray(MANDIBLE_COM_FROM_INCISAL) @ np.array([frame.left, frame.up, frame.anterior])
    ixx, iyy, izz, ixy, ixz, iyz = MANDIBLE_INERTIA
    return {"mass": MANDIBLE_MASS, "pos": com, "inertia": np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])}
