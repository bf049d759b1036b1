"""A surgical wafer (occlusal splint) between two arches at their occlusion.

The wafer is the space between the arches, opened about the hinge, over the dentition's
outline, with both arches' imprints offset by a clearance. It is made on a grid in the
maxillary arch's frame (u left, v anterior, w up) as two **height fields**:

* the **upper face** is the maxilla's surface seen from below, offset down by the clearance
  (a ball of that radius dropped from below onto surface samples: ``grid``), the **lower face**
  the mandible's seen from above, offset up. A height field has no undercut along up, so the
  maxilla seats into the wafer and lifts off it straight; a boolean subtraction of the teeth
  would leave wafer material in the crowns' undercuts that locks the wafer or breaks off;
* faces are capped ``IMPRINT`` beyond the cusp tips (the wafer wraps the crowns that far) and
  kept inside the dentition's outline (where the arches face each other within ``REACH`` at
  the occlusion) widened by ``RIM``;
* the solid between the faces is **opened** by a ball of diameter ``thickness``: eroded, then
  dilated (grey morphology with a ball-shaped structure, ``grid.erode``), which removes every
  part a ball of that diameter cannot reach — fins between deep imprints, knife edges — and
  rounds the outer edges with that ball's radius. Every point of the wafer then lies in a ball
  of diameter ``thickness`` inside it, the printable minimum thickness;
* the mandible is opened about the hinge by the **smallest angle** at which such a ball fits
  between the offset faces everywhere over the dentition (bisection on coal's exact distance
  between the arches' occlusal parts, then checked on the grid: ``opening``);
* the mesh is built from the two fields: a top and a bottom triangle per grid half-square and
  a wall along the outline, so it is one closed, consistently wound shell by construction, and
  cannot self-intersect (the top field lies above the bottom one: ``mesh``).

Everything here is in one Cartesian frame in metres (the search scene's world); ``job.make``
turns it into the maxilla file's own frame and units.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..scenepair import apply_pose
from .grid import Grid, basis, dilate, dilate_mask, erode, erode_mask, surface_samples
from .mesh import closed_mesh
from .opening import Faces, find
from .outline import CLOSE, IMPRINT, REACH, RIM, TIP, cap, crop, cusp_tips, outline

GRID = 1.5e-4  # m: grid spacing; the faces between nodes err by about GRID**2 / (8 * the imprint's radius)
SAMPLE = 6.0e-5  # m: surface sample spacing (the ball drop between samples errs by about SAMPLE**2 / (4 * ball radius))
FACING_UP = 0.3  # the maxilla's faces with a normal below this along up are seen from below (its occlusal side)
FACING_DOWN = -0.5  # the mandible's faces with a normal above this along up are seen from above


@dataclass
class WaferShape:
    """A wafer in the frame of the arches given to ``shape`` (metres)."""

    vertices: np.ndarray
    faces: np.ndarray
    opening_deg: float  # the mandible turned open about the hinge from the occlusion
    opening_source: str  # "smallest" (found) or "given"
    mandible_pose: np.ndarray  # 4x4: the occluded mandible's vertices -> where they seat on the wafer
    clearance: float
    thickness: float
    arch_gap: float  # coal's exact distance between the arches' occlusal parts at the opening
    grid: float
    cusps: dict = field(default_factory=dict)  # "maxilla", "mandible": (n, 3) cusp tips over the wafer (seated poses)
    timings: dict = field(default_factory=dict)


def shape(maxilla, mandible, up, anterior, hinge, hinge_axis, *, clearance: float = 1e-4, thickness: float = 1.5e-3,
          opening_deg: float | None = None, grid: float = GRID) -> WaferShape:
    """The wafer between ``maxilla`` and ``mandible`` (each ``(V, F)``, the mandible at its
    occlusion), in their frame (metres).

    Parameters
    ----------
    up, anterior : (3,)
        The maxillary arch's up and anterior directions (``arch.ArchFrame``).
    hinge, hinge_axis : (3,)
        The condylar axis; a positive turn about ``hinge_axis`` opens the mandible.
    clearance : float
        Gap between each arch and its imprint (m).
    thickness : float
        Minimum thickness of the wafer (m): a ball of this diameter fits at every point.
    opening_deg : float, optional
        The mandible's opening about the hinge; default the smallest that leaves room for
        ``thickness`` between the offset arches everywhere over the dentition.
    """
    from ..exact import coal_bvh

    t0 = time.perf_counter()
    (Vx, Fx), (Vd, Fd) = [(np.asarray(V, float), np.asarray(F, np.int64)) for V, F in (maxilla, mandible)]
    if clearance < 0 or thickness <= 0:
        raise ValueError(f"clearance {clearance * 1e3:g} mm and thickness {thickness * 1e3:g} mm: the clearance must be ≥ 0 "
                         "and the thickness > 0")
    faces, band = _faces((Vx, Fx), (Vd, Fd), up, anterior, clearance, thickness, grid)
    g = faces.grid
    t_samples = time.perf_counter()
    arches = (coal_bvh(Vx, Fx[crop(Vx, Fx, g, faces.inside, band)]), coal_bvh(Vd, Fd[crop(Vd, Fd, g, faces.inside, band)]))
    op = find(faces, arches, hinge, hinge_axis, thickness, opening_deg)
    t_open = time.perf_counter()
    top, bottom, centre = _open_by_ball(faces, op.bottom, thickness)
    # the rim's columns: the balls' union thins to nothing at their equators, which a grid cannot
    # facet (the last square would be a knife edge); the outline is cut where the wafer is still
    # the thickness tall, leaving a wall there with the balls' rounded fillets above and below
    valid = np.isfinite(top) & np.isfinite(bottom) & (top - bottom >= thickness)
    V, F = closed_mesh(top, bottom, valid, g)
    t_mesh = time.perf_counter()
    seat = erode_mask(centre, g, TIP)  # cusps with the wafer all round them
    cusps = {"maxilla": cusp_tips(Vx, Fx, g, seat, band, -1, other=(Vd, Fd)),
             "mandible": apply_pose(op.pose, cusp_tips(Vd, Fd, g, seat, band, +1, other=(Vx, Fx)))}
    return WaferShape(V, F, float(np.degrees(op.theta)), op.source, op.pose, clearance, thickness, op.arch_gap, grid, cusps,
                      {"samples_s": t_samples - t0, "opening_s": t_open - t_samples, "mesh_s": t_mesh - t_open})


def _faces(maxilla, mandible, up, anterior, clearance, thickness, h) -> tuple[Faces, float]:
    """The grid over the occlusal table, the upper face, the outline and the mandible's samples
    (``opening.Faces``), and the band about the occlusal level the faces come from."""
    from ..arch import occlusal_points

    (Vx, Fx), (Vd, Fd) = maxilla, mandible
    B = basis(up, anterior)
    P = occlusal_points(Vx, Vd, Fd, reach=REACH)
    if len(P) < 20:
        raise ValueError(f"the arches are more than {REACH * 1e3:g} mm apart at the given occlusion (only {len(P)} maxillary "
                         "points within reach): pass the pose where the teeth meet (--pose occlusion.json or --search)")
    L = (P - P.mean(axis=0)) @ B.T
    margin = RIM + CLOSE + IMPRINT
    g = Grid(B, P.mean(axis=0), L[:, :2].min(axis=0) - margin, L[:, :2].max(axis=0) + margin, h)
    band = float(np.ptp(L[:, 2])) + 4 * IMPRINT + 2 * thickness
    rho = max(clearance, 1.5 * h)  # the ball dropped; shifted back to the clearance below
    everywhere = np.ones(g.shape, bool)
    sx = surface_samples(Vx, Fx, SAMPLE, (_normals(Vx, Fx) @ B[2] < FACING_UP) & crop(Vx, Fx, g, everywhere, band))
    Hx = g.drop(sx, rho, -1) + (rho - clearance)
    sd = surface_samples(Vd, Fd, SAMPLE, (_normals(Vd, Fd) @ B[2] > FACING_DOWN) & crop(Vd, Fd, g, everywhere, band))
    Hd0 = g.drop(sd, rho, +1) - (rho - clearance)
    inside = outline(Hx - Hd0 - 2 * clearance, g)
    # the mandible's samples over the outline (and a margin for the opening's shift), in the grid's frame
    sd = sd[g.over(sd, dilate_mask(inside, g, 2 * IMPRINT))]
    upper = np.minimum(Hx, cap(Hx, inside, g, -1))
    return Faces(g, upper, g.local(sd), inside, rho, clearance), band


def _open_by_ball(faces: Faces, bottom, thickness):
    """The solid between ``faces.upper`` and ``bottom`` opened by a ball of diameter
    ``thickness`` (and half a grid step): the centres where the ball fits, then the union of the
    balls. Returns the top and bottom fields and the centres' mask."""
    g, inside = faces.grid, faces.inside
    r = 0.5 * thickness + 0.5 * g.h
    hi_c = erode(np.where(inside, faces.upper, np.inf), g, r)
    lo_c = dilate(np.where(inside, bottom, -np.inf), g, r)
    centre = erode_mask(inside, g, r) & (hi_c >= lo_c) & np.isfinite(hi_c) & np.isfinite(lo_c)
    return dilate(np.where(centre, hi_c, -np.inf), g, r), erode(np.where(centre, lo_c, np.inf), g, r), centre


def _normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
