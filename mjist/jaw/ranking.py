"""Judging a settled mandible pose by how the teeth meet, on the true surfaces.

Maximum intercuspation is the most closed position the mandible reaches at zero penetration
with the teeth interlocked on both sides. Each pose is judged by exactly that, with the
meshes themselves (not the inner spheres):

1. **touch**: the mandible is turned about the hinge (the closing path) until the two arches
   just touch: no occlusal point of either arch inside the other (exact signed distances).
2. **interocclusal distance**: at that pose, every occlusal point's distance to the other
   arch (both ways, capped at ``CAP``: a point further away says nothing about how the teeth
   meet), averaged within each region of the dentition (left/right × anterior/premolar/molar
   in the maxillary arch's frame), then over the regions, each counting the same.

``score = −interocclusal distance (mm)``: one physical quantity and no weights to fit. A pose
that closes one side and leaves the other open pays for every open region; a cusp-on-cusp pose
pays for the height it holds the arches apart by. The contact figures (points within
``CONTACT`` of the other arch, regions touched, left/right balance) are reported beside it, not
added to it.

Everything here is array-in, array-out over a ``OcclusalSample`` made once per pair.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry.surface import Surface, build_surface, signed_distances

CAP = 3e-3  # m: interocclusal distances are capped here (the occlusal points lie within it at the reference)
CONTACT = 1e-4  # m: an occlusal point this close to the other arch counts as a contact (articulating paper)
REACH = 3e-3  # m: occlusal points: vertices facing the other arch within this of it at the sample's pose
FACING = 0.3  # cosine: a vertex faces the other arch when its normal is this close to the closing direction
POINTS = 2000  # occlusal points per arch, spread evenly over those found
TOUCH_TOL = 1e-7  # rad: the touch iteration stops when its last turn is below this (~10 nm at the incisors)
TOUCH_ITERS = 12
REGIONS = ("left-anterior", "left-premolar", "left-molar", "right-anterior", "right-premolar", "right-molar")


@dataclass
class OcclusalSample:
    """Both arches' occlusal points and surfaces, made once per pair (``occlusal_sample``).

    Points are in each mesh's own frame; poses are 4x4 world poses of the meshes' frames.
    """

    maxilla_surface: Surface
    mandible_surface: Surface
    maxilla_pose: np.ndarray  # (4, 4): the maxilla is fixed
    hinge: np.ndarray  # (3,) world point on the hinge axis
    axis: np.ndarray  # (3,) world hinge axis; a positive turn about it opens the mandible
    up: np.ndarray  # (3,) world closing direction (from the mandible towards the maxilla)
    mandible_points: np.ndarray  # (n, 3) mandible frame
    mandible_regions: np.ndarray  # (n,) index into REGIONS
    maxilla_points: np.ndarray  # (m, 3) maxilla frame
    maxilla_regions: np.ndarray  # (m,)

    @property
    def regions(self) -> tuple[int, ...]:
        """Regions with occlusal points on both arches (a missing tooth row drops out)."""
        return tuple(r for r in range(len(REGIONS)) if (self.mandible_regions == r).any() and (self.maxilla_regions == r).any())


@dataclass
class Judgement:
    """How the teeth meet at one pose, after ``touch``."""

    score: float  # −interocclusal_mm
    interocclusal_mm: float  # mean capped distance between the arches over the dentition (regions equal)
    region_mm: dict  # region -> its mean interocclusal distance (both ways)
    contact_fraction: float  # occlusal points (both arches) within CONTACT of the other
    regions_in_contact: list  # regions with at least one contact point
    balance: float  # 1 − |L − R| / (L + R) over the contact points
    turn_deg: float  # the hinge turn that brought the pose to touch (negative: closed further)
    pose: np.ndarray  # (4, 4) mandible frame at touch

    def as_dict(self) -> dict:
        d = asdict(self)
        d["pose"] = self.pose.tolist()
        return d


def _facing(V, F, direction) -> np.ndarray:
    import trimesh

    return trimesh.Trimesh(V, F, process=False).vertex_normals @ direction > FACING


def _spread(P, n: int) -> np.ndarray:
    return P[np.linspace(0, len(P) - 1, min(n, len(P))).astype(np.int64)] if len(P) else P


def _occlusal(V, F, P_self, other: Surface, P_other, direction, n: int) -> np.ndarray:
    """Vertices of ``(V, F)`` facing ``direction`` (world) within ``REACH`` of ``other``."""
    cand = np.flatnonzero(_facing(V, F, P_self[:3, :3].T @ direction))
    T = np.linalg.inv(P_other) @ P_self
    d, _ = signed_distances(other, V[cand] @ T[:3, :3].T + T[:3, 3])
    return _spread(V[cand[np.abs(d) < REACH]], n)


def occlusal_sample(maxilla, mandible, maxilla_pose, mandible_pose, frame, hinge, axis=(1.0, 0.0, 0.0), up=(0.0, 0.0, 1.0),
                    surfaces: tuple[Surface, Surface] | None = None, n: int = POINTS) -> OcclusalSample:
    """The occlusal points of both arches at a pose where they meet.

    Parameters
    ----------
    maxilla, mandible : (V, F)
        Each mesh in its own frame.
    maxilla_pose, mandible_pose : (4, 4)
        World poses at which the occlusal surfaces are picked (the arches within ``REACH``).
    frame : arch.ArchFrame
        The maxillary arch's frame (world): labels the regions.
    hinge, axis : (3,)
        The hinge axis (world); a positive turn about ``axis`` opens the mandible.
    up : (3,)
        World closing direction.
    surfaces : (Surface, Surface), optional
        The meshes already packed (``geometry.surface.build_surface``).
    """
    up = np.asarray(up, float)
    Sx, Sd = surfaces or (build_surface(*maxilla), build_surface(*mandible))
    Px, Pd = np.asarray(maxilla_pose, float), np.asarray(mandible_pose, float)
    pd = _occlusal(*mandible, Pd, Sx, Px, up, n)
    px = _occlusal(*maxilla, Px, Sd, Pd, -up, n)

    def labels(P, pose):
        names = frame.regions(P @ pose[:3, :3].T + pose[:3, 3]) if len(P) else []
        return np.array([REGIONS.index(r) for r in names], np.int64)

    return OcclusalSample(Sx, Sd, Px, np.asarray(hinge, float), np.asarray(axis, float) / np.linalg.norm(axis), up,
                          pd, labels(pd, Pd), px, labels(px, Px))


def distances(s: OcclusalSample, mandible_pose) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Signed distances (negative inside) of the mandible's occlusal points to the maxilla and of
    the maxilla's to the mandible, and how fast each grows per radian of hinge opening."""
    Pm = np.asarray(mandible_pose, float)
    Px = s.maxilla_pose
    T = np.linalg.inv(Px) @ Pm
    a, ga = signed_distances(s.maxilla_surface, s.mandible_points @ T[:3, :3].T + T[:3, 3])
    Wa = s.mandible_points @ Pm[:3, :3].T + Pm[:3, 3]
    ra = np.einsum("ij,ij->i", ga @ Px[:3, :3].T, np.cross(s.axis, Wa - s.hinge))
    Ti = np.linalg.inv(Pm) @ Px
    b, gb = signed_distances(s.mandible_surface, s.maxilla_points @ Ti[:3, :3].T + Ti[:3, 3])
    Wb = s.maxilla_points @ Px[:3, :3].T + Px[:3, 3]
    rb = -np.einsum("ij,ij->i", gb @ Pm[:3, :3].T, np.cross(s.axis, Wb - s.hinge))  # the maxilla moves the other way
    return a, ra, b, rb


def shift_mm(A, B, points) -> float:
    """Largest shift (mm) of ``points`` (a mesh's frame) between its poses ``A`` and ``B`` (4x4)."""
    return float(np.linalg.norm(points @ (A[:3, :3] - B[:3, :3]).T + (A[:3, 3] - B[:3, 3]), axis=1).max() * 1e3)


def hinge_turn(s: OcclusalSample, mandible_pose, phi: float) -> np.ndarray:
    """The mandible pose turned by ``phi`` (rad, positive opens) about the hinge axis."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(phi * s.axis).as_matrix()
    T[:3, 3] = s.hinge - T[:3, :3] @ s.hinge
    return T @ np.asarray(mandible_pose, float)


def touch(s: OcclusalSample, mandible_pose) -> tuple[np.ndarray, float]:
    """The mandible turned about the hinge until the arches just touch: (pose, turn in rad).

    Each step linearises every occlusal point's signed distance in the turn and takes the turn
    at which the last of them clears (penetrating) or the first reaches the other arch
    (apart); about three steps reach ``TOUCH_TOL``.
    """
    P = np.asarray(mandible_pose, float)
    total = 0.0
    for _ in range(TOUCH_ITERS):
        a, ra, b, rb = distances(s, P)
        d, r = np.r_[a, b], np.r_[ra, rb]
        moving = r > 1e-4  # points that separate as the jaw opens (the others face elsewhere)
        if not moving.any():
            break
        phi = float(np.max(-d[moving] / r[moving]))
        P = hinge_turn(s, P, phi)
        total += phi
        if abs(phi) < TOUCH_TOL:
            break
    return P, total


def judge(s: OcclusalSample, mandible_pose, frame=None) -> Judgement:
    """Touch, then the interocclusal distance and contact figures (``Judgement``)."""
    P, turn = touch(s, mandible_pose)
    a, _, b, _ = distances(s, P)
    a, b = np.clip(a, 0.0, CAP), np.clip(b, 0.0, CAP)
    region_mm, touched = {}, []
    left = right = 0
    for r in s.regions:
        ia, ib = s.mandible_regions == r, s.maxilla_regions == r
        region_mm[REGIONS[r]] = float((a[ia].mean() + b[ib].mean()) * 1e3)
        k = int((a[ia] < CONTACT).sum() + (b[ib] < CONTACT).sum())
        if k:
            touched.append(REGIONS[r])
        if REGIONS[r].startswith("left"):
            left += k
        else:
            right += k
    inter = float(np.mean(list(region_mm.values()))) if region_mm else CAP * 2e3
    n = len(a) + len(b)
    return Judgement(score=-inter, interocclusal_mm=inter, region_mm=region_mm,
                     contact_fraction=float(((a < CONTACT).sum() + (b < CONTACT).sum()) / max(n, 1)),
                     regions_in_contact=touched, balance=1.0 - abs(left - right) / (left + right) if left + right else 0.0,
                     turn_deg=float(np.degrees(turn)), pose=P)


@dataclass
class Candidate:
    """One basin of the search: where its starts settled, how the teeth meet there, how sure."""

    rank: int
    score: float  # Judgement.score of the reported pose
    pos: np.ndarray  # mandible body position at touch
    quat: np.ndarray  # w, x, y, z
    starts: int  # starts that settled in this basin
    interocclusal_mm: float
    contact_fraction: float
    regions: list = field(default_factory=list)  # regions in contact
    region_mm: dict = field(default_factory=dict)
    balance: float = 0.0
    turn_deg: float = 0.0  # hinge turn from the settled pose to touch
    settled: bool = True  # some start of the basin settled (drift below occlusion.SETTLED)
    drift_mm_s: float = 0.0  # median over the basin's starts of the tooth points' drift at the end of closing
    last_step_mm: float = 0.0  # the best start's largest tooth-point move over its last step
    score_spread: float = 0.0  # range of the scores of the basin's starts
    coal_distance_mm: float | None = None  # coal's exact distance at the reported pose
    error: dict | None = None  # against the scene's reference occlusion

    def as_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}
