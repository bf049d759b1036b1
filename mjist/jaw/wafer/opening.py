"""How far the mandible opens about the hinge for the wafer: the smallest turn at which a ball
of the wafer's thickness fits between the offset arches everywhere over the dentition.

Bisection on coal's exact distance between the arches' occlusal parts finds where the turn
leaves room; the grid's ball test (the upper face fixed, the lower one from the turned
mandible's samples) has the last word and opens further in small steps when it disagrees.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scenepair import apply_pose
from .grid import dilate, erode, erode_mask
from .outline import cap

MAX_OPENING_DEG = 20.0
BISECT_TOL_DEG = 1e-3  # the bisection stops this close to the exact opening
STEP_DEG = 0.05  # the grid test's steps past the bisection's answer: smaller is a thinner wafer, more tests


def hinge_turn(theta: float, hinge, axis) -> np.ndarray:
    """4x4 rotation by ``theta`` (rad) about ``axis`` through ``hinge``."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.asarray(axis, float) / np.linalg.norm(axis) * theta).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(hinge, float) - R @ np.asarray(hinge, float)
    return T


@dataclass
class Faces:
    """The wafer's faces on the grid before the opening: the fixed upper one and what makes the lower one."""

    grid: object  # grid.Grid
    upper: np.ndarray  # the maxilla offset down by the clearance, capped at the imprint depth
    mandible: np.ndarray  # (n, 3) the mandible's occlusal samples in the grid's frame, at the occlusion
    inside: np.ndarray  # the dentition's outline (grid mask)
    rho: float  # the radius of the dropped ball
    clearance: float

    def lower(self, T) -> np.ndarray:
        """The lower face with the mandible moved by ``T`` (world 4x4): offset up, capped."""
        g = self.grid
        G = g.to_grid()
        Hd = g.drop_local(apply_pose(G @ T @ np.linalg.inv(G), self.mandible), self.rho, +1) - (self.rho - self.clearance)
        return np.maximum(Hd, cap(Hd, self.inside, g, +1))


@dataclass
class Opening:
    theta: float  # rad
    source: str  # "smallest" or "given"
    pose: np.ndarray  # 4x4: the turn about the hinge
    bottom: np.ndarray  # the lower face at that turn
    arch_gap: float  # coal's distance between the occlusal parts there


def find(faces: Faces, arches, hinge, axis, thickness: float, opening_deg=None) -> Opening:
    """The opening for a wafer of ``thickness`` (``opening_deg`` when given, else the smallest).

    ``arches``: coal BVHs of the maxilla's and the mandible's occlusal parts (world, at the occlusion).
    """
    from ..exact import coal_distance

    g = faces.grid
    r = 0.5 * thickness + 0.5 * g.h  # the opening ball: half the thickness and half a grid step of margin
    core = erode_mask(faces.inside, g, r)
    hi_c = erode(np.where(faces.inside, faces.upper, np.inf), g, r)  # the highest ball centres under the upper face

    def fits(theta) -> tuple[bool, np.ndarray]:
        bottom = faces.lower(hinge_turn(theta, hinge, axis))
        lo_c = dilate(np.where(faces.inside, bottom, -np.inf), g, r)
        return bool(np.all(hi_c[core] >= lo_c[core])), bottom

    bx, bd = arches
    I4 = np.eye(4)

    def gap(theta):
        return coal_distance(bx, I4, bd, hinge_turn(theta, hinge, axis))

    need = 2 * r + 2 * faces.clearance  # the ball and the clearances: where the grid's test should pass
    if opening_deg is None:
        theta, ok, bottom = _smallest(gap, fits, need)
        source = "smallest"
    else:
        theta = np.radians(float(opening_deg))
        ok, bottom = fits(theta)
        source = "given"
    if not ok:
        raise ValueError(f"opened {np.degrees(theta):.2f}° about the hinge, the arches leave less than {thickness * 1e3:g} mm "
                         f"(+ {faces.clearance * 1e3:g} mm clearance each side) over part of the dentition: open more "
                         "(--opening) or leave --opening out for the smallest opening that fits")
    return Opening(theta, source, hinge_turn(theta, hinge, axis), bottom, float(gap(theta)))


def _smallest(gap, fits, need):
    """Bisection of the turn on ``gap`` ≥ ``need``, then ``fits`` (the grid) in ``STEP_DEG`` steps."""
    lo, hi = 0.0, np.radians(MAX_OPENING_DEG)
    if gap(hi) < need:
        raise ValueError(f"even opened {MAX_OPENING_DEG:g}° about the hinge the arches stay closer than "
                         f"{need * 1e3:.2f} mm over the dentition: check the hinge (--hinge) and the occlusion")
    if gap(0.0) >= need:
        hi = 0.0
    for _ in range(40):
        if hi - lo < np.radians(BISECT_TOL_DEG):
            break
        mid = 0.5 * (lo + hi)
        if gap(mid) >= need:
            hi = mid
        else:
            lo = mid
    theta = hi
    ok, bottom = fits(theta)
    while not ok and theta < np.radians(MAX_OPENING_DEG):
        theta += np.radians(STEP_DEG)
        ok, bottom = fits(theta)
    return theta, ok, bottom
