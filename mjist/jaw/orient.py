"""Units and orientation of a user's jaw pair, detected or given, and the conversion into the jaw frame.

Every jaw scene works in the **jaw frame**: metres, x towards the patient's left, +y superior
(from the mandible towards the maxilla), +z anterior (towards the incisors); the maxilla is
fixed. Scans come in millimetres or metres, with any axis up. This module finds

* the **units** from the size of each jaw: a dental arch is 40–80 mm wide, a whole mandible
  with its rami about 120 mm, so a largest extent of 15–300 reads as millimetres and of
  0.015–0.3 as metres (anything else is refused and asks for ``units``);
* the **up axis** (one of ±x, ±y, ±z) from the two jaws themselves: the mandible is moved a
  short way along each of the six axes and coal measures the exact gap; the pair opens
  fastest when the mandible moves down, away from the maxilla;
* the **anterior axis** from the arch's own shape (``mjist.jaw.arch``);

and converts both meshes once, with the same rotation and scale, so every later step sees the
jaw frame. The conversion is a rotation and a scale about the file's origin: a pair already in
the jaw frame (the bundled jaws, the shared CBCT pair) comes through unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

UNITS = {"m": 1.0, "mm": 1e-3}
AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
        "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
# largest extent of one jaw, in its file's numbers, that reads as each unit (an arch alone is
# 40-80 mm wide, a mandible with rami ~120 mm, a maxilla with the fossae ~130 mm)
UNIT_RANGES = {"m": (0.015, 0.3), "mm": (15.0, 300.0)}
PROBE = 2e-3  # m: how far the mandible moves along each axis to find which way opens the pair
REACH = 0.01  # m: the jaws must come into contact within this distance along the up axis
# touch_offset's tests within this many tolerances of the vertices' touch use only the faces that
# can meet there (milliseconds instead of seconds on dense scans); a pair whose edges meet
# farther before its vertices do falls back to the whole meshes
NEAR_STEPS = 64


@dataclass
class Orientation:
    """How a jaw pair's files map into the jaw frame: ``p_jaw = scale[jaw] * R @ p_file``."""

    units: str  # "m", "mm", or "mm,m" (maxilla, mandible) for jaws stored differently
    up: str  # file axis pointing superior, e.g. "+z"
    anterior: np.ndarray  # file direction pointing anterior (unit, perpendicular to up)
    R: np.ndarray  # rows: the jaw frame's x (left), y (up), z (anterior) in file coordinates
    scales: tuple  # metres per file unit: (maxilla, mandible)
    detected: dict = field(default_factory=dict)  # what was detected (not given), with the evidence

    @property
    def identity(self) -> bool:
        return self.scales == (1.0, 1.0) and np.array_equal(self.R, np.eye(3))

    def apply(self, V, jaw: str) -> np.ndarray:
        """File coordinates ``(n, 3)`` of ``jaw`` ("maxilla" or "mandible") in the jaw frame."""
        s = self.scales[0 if jaw == "maxilla" else 1]
        V = np.asarray(V, np.float64)
        return V if s == 1.0 and np.array_equal(self.R, np.eye(3)) else s * (V @ self.R.T)

    def as_dict(self) -> dict:
        return {"units": self.units, "up": self.up, "anterior": [float(a) for a in self.anterior],
                "scales": list(self.scales), "rotation": self.R.tolist(), "detected": self.detected}


def unit_of(extent: float) -> str | None:
    for name, (lo, hi) in UNIT_RANGES.items():
        if lo <= extent <= hi:
            return name
    return None


def parse_units(units) -> tuple[str, str]:
    """``units`` as (maxilla, mandible): "auto", "mm", "m", or "mm,m" for jaws stored differently."""
    parts = [u.strip().lower() for u in str(units).split(",")] if not isinstance(units, (tuple, list)) else list(units)
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2 or any(u not in ("auto", *UNITS) for u in parts):
        raise ValueError(f"units={units!r}: use auto, mm or m (or 'mm,m' for a maxilla and mandible stored differently)")
    return parts[0], parts[1]


def detect_units(maxilla_V, mandible_V, units="auto") -> tuple[str, dict]:
    """The pair's length unit, ``(unit, evidence)``; refuses jaws whose sizes disagree.

    Raises
    ------
    ValueError
        A jaw whose size fits no unit, or two jaws whose sizes read as different units.
    """
    given = parse_units(units)
    ext = {name: float(np.ptp(np.asarray(V), axis=0).max()) for name, V in (("maxilla", maxilla_V), ("mandible", mandible_V))}
    found = {}
    for (name, e), u in zip(ext.items(), given):
        if u != "auto":
            found[name] = u
            continue
        found[name] = unit_of(e)
        if found[name] is None:
            raise ValueError(
                f"cannot tell the units of the {name}: its largest extent is {e:g} in file units, which is neither "
                f"a jaw in metres ({UNIT_RANGES['m'][0]}-{UNIT_RANGES['m'][1]}) nor in millimetres "
                f"({UNIT_RANGES['mm'][0]:g}-{UNIT_RANGES['mm'][1]:g}); pass units=mm or units=m (--units)")
    sizes = {name: ext[name] * UNITS[found[name]] for name in ext}
    if found["maxilla"] != found["mandible"]:
        if all(u == "auto" for u in given):
            raise ValueError(
                f"the jaws look like different units: maxilla {ext['maxilla']:g} wide reads as {found['maxilla']}, "
                f"mandible {ext['mandible']:g} as {found['mandible']}; export both in the same units, or pass "
                f"units={found['maxilla']},{found['mandible']} (--units) to convert each")
        return f"{found['maxilla']},{found['mandible']}", {"extent": ext}
    big, small = max(sizes.values()), min(sizes.values())
    if big > 4.0 * small:
        raise ValueError(
            f"the jaws differ in size by {big / small:.1f}x (maxilla {sizes['maxilla'] * 1e3:.0f} mm, mandible "
            f"{sizes['mandible'] * 1e3:.0f} mm as {found['maxilla']}): mismatched units? export both in the same "
            "units, or pass units per jaw (--units mm,m)")
    return found["maxilla"], {"extent": ext}


def scales(unit: str) -> tuple[float, float]:
    """Metres per file unit for (maxilla, mandible)."""
    a, b = parse_units(unit)
    return UNITS[a], UNITS[b]


def _collides(bvh_a, bvh_b, t) -> bool:
    from .exact import coal_collides

    P = np.eye(4)
    P[:3, 3] = t
    return coal_collides(bvh_a, np.eye(4), bvh_b, P)


def _gap(bvh_a, bvh_b, t) -> float:
    from .exact import coal_distance

    P = np.eye(4)
    P[:3, 3] = t
    return 0.0 if _collides(bvh_a, bvh_b, t) else coal_distance(bvh_a, np.eye(4), bvh_b, P)


def detect_up(bvh_maxilla, bvh_mandible, up="auto") -> tuple[str, dict]:
    """The file axis pointing from the mandible to the maxilla, for two jaws in metres.

    Each of the six axis directions moves the mandible by ``PROBE``; coal's exact gap after the
    move is largest when it moves down (away from the maxilla). Given ``up`` is checked the same
    way: a pair that opens when the mandible moves *up* has its upper and lower jaws swapped.

    Raises
    ------
    ValueError
        No direction opens the pair clearly (ask for ``up``), or the given ``up`` contradicts
        the geometry (upper and lower jaws swapped).
    """
    gaps = {name: _gap(bvh_maxilla, bvh_mandible, -PROBE * np.asarray(v)) for name, v in AXES.items()}
    order = sorted(gaps, key=lambda k: -gaps[k])  # "+y" here means: moving the mandible along -y opens most
    best, second = order[0], order[1]
    evidence = {"gap_after_moving_down_mm": {k: round(v * 1e3, 4) for k, v in gaps.items()}}
    clear = gaps[best] - gaps[second] > 0.25 * PROBE
    if up != "auto":
        if up not in AXES:
            raise ValueError(f"up={up!r}: use auto, +x, -x, +y, -y, +z or -z")
        flip = "-" + up[1] if up[0] == "+" else "+" + up[1]
        if clear and best == flip:
            raise ValueError(
                f"with up={up} the maxilla lies below the mandible (the pair opens when the mandible moves up): "
                f"upper and lower jaws swapped? swap the two files, or pass up={flip}")
        return up, evidence
    if not clear:
        raise ValueError(
            "cannot tell which way is up: moving the mandible along no axis opens the pair clearly "
            f"(gaps after {PROBE * 1e3:g} mm: " + ", ".join(f"{k} {v * 1e3:.2f} mm" for k, v in gaps.items())
            + "); are the jaws facing each other in occlusion? pass up=+x|-x|+y|-y|+z|-z (--up)")
    return best, evidence


def touch_offset(bvh_maxilla, bvh_mandible, up, reach: float = REACH, tol: float = 1e-6, meshes=None) -> float:
    """Offset of the mandible along ``up`` (m, file axes, metres) at which the jaws just touch:
    the largest offset known apart, within ``tol`` of touching (bisection on coal's collision test).

    ``meshes``: ``((V_maxilla, F_maxilla), (V_mandible, F_mandible))`` in the coal BVHs' frame. With
    them, rays along ``up`` from every vertex to the other jaw give where a vertex first meets the
    other surface, and the bisection starts within a few µm of it (an edge meeting an edge first
    is found by the bisection all the same): a few collision tests instead of twenty, which on
    dense scans cost seconds each.

    Raises ``ValueError`` when they do not meet within ``reach`` (two arches that never face
    each other)."""
    u = np.asarray(up, float)
    hit0 = _collides(bvh_maxilla, bvh_mandible, 0.0 * u)
    if hit0:  # move down until apart
        a, b = 0.0, -reach
        if _collides(bvh_maxilla, bvh_mandible, b * u):
            raise ValueError(f"the jaws still intersect after moving the mandible {reach * 1e3:g} mm down: "
                             "are they two copies of one jaw, or is up wrong? pass up=... (--up)")
    else:  # move up until touching
        a, b = reach, 0.0
        if not _collides(bvh_maxilla, bvh_mandible, a * u):
            raise ValueError(
                f"the jaws do not meet within {reach * 1e3:g} mm of the mandible moving up: the two arches do not face "
                "each other (not a maxilla and a mandible of one patient, not in occlusion, or up is wrong); pass "
                "up=... (--up) or place the jaws in occlusion")
    bx, bd = bvh_maxilla, bvh_mandible
    if meshes is not None:
        a, b, (bx, bd) = _vertex_bracket(bvh_maxilla, bvh_mandible, u, meshes, a, b, tol)
    while abs(a - b) > tol:
        m = 0.5 * (a + b)
        if _collides(bx, bd, m * u):
            a = m
        else:
            b = m
    return b


def _vertex_bracket(bvh_maxilla, bvh_mandible, u, meshes, a: float, b: float, tol: float):
    """``touch_offset``'s bracket (touching ``a``, apart ``b``) narrowed around the offset where a
    vertex of one jaw first meets the other (rays along ``u`` from the apart pose ``b``), and the
    coal BVHs that answer for every offset inside it: the faces that can meet there, or the
    whole jaws."""
    from ..geometry.bvh import BVH
    from .exact import coal_bvh, near_faces

    (Vx, Fx), (Vd, Fd) = ((np.asarray(V, float), np.asarray(F)) for V, F in meshes)
    up_hits = BVH.of_triangles(Vx, Fx).first_hits(Vd + b * u, u, Vx, Fx)  # mandible vertices rising into the maxilla
    down_hits = BVH.of_triangles(Vd, Fd).first_hits(Vx - b * u, -u, Vd, Fd)  # maxilla vertices, the mandible's view
    t = b + min(float(up_hits.min(initial=np.inf)), float(down_hits.min(initial=np.inf)))
    whole = (bvh_maxilla, bvh_mandible)
    if not b < t < a:
        return a, b, whole
    a = t  # a vertex lies on the other surface: touching (coal counts meshes within about 1 µm as touching)
    # the tests near t see only the faces that can meet within NEAR_STEPS of it
    near = near_faces((Vx, Fx), (Vd + t * u, Fd), NEAR_STEPS * tol)
    near = (coal_bvh(Vx, Fx[near[0]]), coal_bvh(Vd, Fd[near[1]])) if near[0].any() and near[1].any() else None
    step = 2.0 * tol
    while t - step > b:  # an edge may meet an edge before any vertex meets a face: step back until apart
        bvhs = near if near is not None and step <= NEAR_STEPS * tol else whole
        if not _collides(*bvhs, (t - step) * u):
            return a, t - step, bvhs
        a = t - step
        step *= 16.0
    return a, b, whole


def frame_matrix(up: str, anterior) -> np.ndarray:
    """Rows x (left) = up × anterior, y = up, z = anterior, in file coordinates."""
    y = np.asarray(AXES[up], float)
    z = np.asarray(anterior, float)
    z = z - (z @ y) * y
    z /= np.linalg.norm(z)
    return np.array([np.cross(y, z), y, z])


def snap(direction, up: str, max_deg: float = 10.0) -> np.ndarray:
    """``direction`` (perpendicular to ``up``) replaced by the nearest file axis within ``max_deg``,
    so a scan stored along its axes converts by an exact axis permutation."""
    d = np.asarray(direction, float)
    best = max((np.asarray(v) for k, v in AXES.items() if k[1] != up[1]), key=lambda v: float(v @ d))
    return best if float(best @ d) >= np.cos(np.radians(max_deg)) else d / np.linalg.norm(d)
