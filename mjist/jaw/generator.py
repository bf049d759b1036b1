"""Procedural maxilla and mandible in centric occlusion (the bundled jaw models).

An implicit solid per jaw (negative inside), polygonised by marching cubes
(scikit-image), cleaned and checked by trimesh. Millimetres inside this module, metres
in the output; frame as ``mjist.jaw``: +y up, +z anterior, x left-right.

How the teeth interdigitate: both jaws share one *occlusal interface*, a height field
``y = f(s, v)`` over arch coordinates (``s`` arc length along the lower central-fossa line
from the midline, ``v`` outward offset from it). Lower cusps are its maxima and upper cusps
its minima, so every cusp of one jaw sits in a fossa or embrasure of the other. The lower
crowns lie below ``f``, the upper crowns above ``f + g``, where the clearance ``g ≥ 0``
vanishes only at the designed occlusal contacts (the upper palatal and the lower buccal
cusp tips of premolars and molars) and is 0.35 mm elsewhere. In the design pose the jaws
therefore touch at those points and nowhere do they overlap: that pose is the ground truth.

Anatomy: 14 teeth per jaw (central and lateral incisors, canine, two premolars, two molars per
side, with their usual crown sizes), class I molar relation (the upper first molar half a
cusp distal to the lower one), upper buccal cusps overlapping the lower ones. Mandible:
alveolar body, rami, coronoid processes, condyles. Maxilla: alveolar process, palate and
basal body, plus the two glenoid fossae (separate closed shells, as in the CBCT maxilla)
cupping the condyles with a 1.5 mm joint space.

Other patients: ``Anatomy`` varies the arch's width and depth, the crowns' size, crowding of
the incisors, a class II/III shift of the arches along each other, a posterior crossbite on
one side and missing teeth. Each change moves the crowns in the ``(s, v)`` plane or the cusps
of the shared interface, so every variant keeps the guarantee above: its design pose touches
and nowhere overlaps. ``Anatomy()`` is the bundled pair.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
from numba import njit, prange

# --- teeth (mm), midline to distal, one side; the other side is the mirror image -------------
KINDS = ("central incisor", "lateral incisor", "canine", "first premolar", "second premolar",
         "first molar", "second molar")
LOWER_W = np.array([5.4, 5.9, 6.9, 7.0, 7.1, 11.2, 10.5])  # mesiodistal crown widths
LOWER_B = np.array([5.8, 6.2, 7.7, 7.8, 8.2, 10.4, 10.1])  # buccolingual
UPPER_W = np.array([8.6, 6.6, 7.6, 7.0, 6.6, 10.3, 9.2])
UPPER_B = np.array([7.0, 6.2, 8.0, 9.2, 9.1, 11.3, 11.0])
TAPER = np.array([0.75, 0.75, 0.55, 0.25, 0.2, 0.15, 0.15])  # occlusal narrowing of the crown
UPPER_SHIFT = 1.8  # upper crowns sit this far outward (buccal overlap)
MIDLINE_GAP = 0.15
INTERPROXIMAL = 0.3  # half gap between neighbouring crowns at their widest

# cusps: tooth, position along the crown (fraction from mesial), v (mm), height, σ_s, σ_v
# (σ_s < 0 means "fraction of the crown width": incisal edges)
LOWER_CUSPS = [
    (0, 0.5, 0.0, 0.6, -0.35, 1.2), (1, 0.5, 0.0, 0.6, -0.35, 1.2), (2, 0.5, 0.3, 1.6, 1.8, 1.8),
    (3, 0.5, 2.0, 1.8, 1.6, 1.6), (3, 0.5, -2.2, 0.6, 1.4, 1.4),
    (4, 0.5, 2.1, 1.6, 1.6, 1.6), (4, 0.5, -2.2, 1.1, 1.5, 1.5),
    (5, 0.2, 2.6, 1.5, 1.6, 1.6), (5, 0.5, 2.8, 1.5, 1.6, 1.6), (5, 0.82, 2.4, 1.2, 1.4, 1.4),
    (5, 0.28, -2.6, 1.7, 1.7, 1.7), (5, 0.72, -2.6, 1.6, 1.7, 1.7),
    (6, 0.25, 2.6, 1.5, 1.8, 1.7), (6, 0.72, 2.6, 1.4, 1.8, 1.7),
    (6, 0.28, -2.6, 1.6, 1.8, 1.7), (6, 0.72, -2.6, 1.5, 1.8, 1.7),
]
UPPER_CUSPS = [
    (0, 0.5, 1.5, 0.6, -0.35, 1.2), (1, 0.5, 1.5, 0.6, -0.35, 1.2), (2, 0.5, 1.8, 1.6, 1.8, 1.8),
    (3, 0.5, 4.6, 1.7, 1.6, 1.6), (3, 0.5, 0.0, 1.5, 1.5, 1.5),
    (4, 0.5, 4.6, 1.6, 1.6, 1.6), (4, 0.5, 0.0, 1.5, 1.5, 1.5),
    (5, 0.25, 4.8, 1.4, 1.7, 1.6), (5, 0.72, 4.8, 1.3, 1.7, 1.6),
    (5, 0.35, 0.0, 1.8, 2.0, 1.8), (5, 0.8, 0.0, 1.1, 1.6, 1.5),
    (6, 0.3, 4.7, 1.3, 1.7, 1.6), (6, 0.75, 4.6, 1.2, 1.6, 1.6), (6, 0.4, 0.0, 1.6, 1.9, 1.8),
]
CLEARANCE = 0.35  # upper-lower clearance away from the designed contacts (mm)
CONTACT_SIGMA = 0.9

# --- arch (lower central-fossa line), x >= 0 half: quarter ellipse then the ramus line -------
ARCH_A, ARCH_B, ARCH_Z0 = 26.0, 42.0, 40.0
RAMUS_ANGLE = math.radians(25.0)
S_MAX = 130.0

# ramus outline in (s, y): coronoid, sigmoid notch, condylar neck, posterior border, angle
RAMUS = np.array([
    [60.0, -8.0], [66.0, 6.0], [70.0, 21.0], [73.0, 19.0], [79.0, 9.0], [85.0, 12.0],
    [89.0, 21.0], [93.0, 20.0], [95.0, 5.0], [96.0, -20.0], [92.0, -31.0], [80.0, -33.0], [60.0, -33.0],
])
CONDYLE_S, CONDYLE_Y, CONDYLE_AXES = 91.0, 27.0, np.array([9.5, 4.8, 4.8])  # semi-axes x, y, z
JOINT_SPACE = 1.5


CROSSBITE_SHIFT = 4.6  # mm: upper posterior crowns moved lingually so their buccal cusps sit in the lower fossae
SIDES = ("left", "right")  # side 0 is +x (the patient's left: up × anterior), side 1 is -x


@dataclass(frozen=True)
class Anatomy:
    """One patient's variation of the design (the defaults are the bundled pair).

    Attributes
    ----------
    arch_width, arch_depth : float
        Scale of the arch's half width and of its depth (the fossa line's ellipse).
    tooth_size : float
        Scale of every crown's mesiodistal and buccolingual size.
    crowding : float
        mm: lateral incisors displaced lingually by this much, canines buccally by half of it.
    class_shift : float
        mm along the arch: > 0 class II (the lower teeth distal to the upper), < 0 class III.
    crossbite : str
        "none", "left" or "right": a posterior crossbite (premolars and molars) on that side.
    missing : tuple
        Missing teeth as ``(jaw, side, tooth)``: "maxilla"/"mandible", "left"/"right", 0
        (central incisor) … 6 (second molar).
    """

    arch_width: float = 1.0
    arch_depth: float = 1.0
    tooth_size: float = 1.0
    crowding: float = 0.0
    class_shift: float = 0.0
    crossbite: str = "none"
    missing: tuple = field(default_factory=tuple)

    def __post_init__(self):
        if self.crossbite not in ("none",) + SIDES:
            raise ValueError(f"crossbite={self.crossbite!r}: use none, left or right")
        for m in self.missing:
            if len(m) != 3 or m[0] not in ("maxilla", "mandible") or m[1] not in SIDES or not 0 <= int(m[2]) < len(KINDS):
                raise ValueError(f"missing tooth {m!r}: give (maxilla|mandible, left|right, 0..{len(KINDS) - 1})")
        for k in ("arch_width", "arch_depth", "tooth_size"):
            if not 0.7 <= getattr(self, k) <= 1.3:
                raise ValueError(f"{k}={getattr(self, k)}: keep it within 0.7..1.3 of the design")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["missing"] = [list(m) for m in self.missing]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Anatomy":
        return cls(**{**d, "missing": tuple(tuple(m) for m in d.get("missing", ()))})


DESIGN = Anatomy()


def tooth_layout(anatomy: Anatomy = DESIGN):
    """Crown intervals ``[s0, s1]`` along the arch, lower and upper, one side (mm)."""
    lw, uw = LOWER_W * anatomy.tooth_size, UPPER_W * anatomy.tooth_size
    lo = MIDLINE_GAP + max(anatomy.class_shift, 0.0) + np.concatenate([[0.0], np.cumsum(lw)[:-1]])
    up = MIDLINE_GAP + max(-anatomy.class_shift, 0.0) + np.concatenate([[0.0], np.cumsum(uw)[:-1]])
    return np.stack([lo, lo + lw], 1), np.stack([up, up + uw], 1)


def _tooth_table(anatomy: Anatomy, jaw: str) -> np.ndarray:
    """Per side and tooth: buccolingual offset of the crown (mm) and 1 if present, ``(2, 7, 2)``."""
    T = np.zeros((2, len(KINDS), 2))
    T[:, :, 1] = 1.0
    T[:, 1, 0] -= anatomy.crowding
    T[:, 2, 0] += 0.5 * anatomy.crowding
    if jaw == "maxilla" and anatomy.crossbite != "none":
        T[SIDES.index(anatomy.crossbite), 3:, 0] -= CROSSBITE_SHIFT
    for j, side, t in anatomy.missing:
        if j == jaw:
            T[SIDES.index(side), int(t), 1] = 0.0
    return T


def _cusp_table(cusps, intervals):
    """Rows: s, v, height, σ_s, σ_v (absolute, mm)."""
    out = []
    for t, frac, v, h, ss, sv in cusps:
        s0, s1 = intervals[t]
        w = s1 - s0
        out.append([s0 + frac * w, v, h, (-ss * w) if ss < 0 else ss, sv])
    return np.array(out)


def contact_table(lower_cusps, upper_cusps, crossbite: bool = False):
    """Designed occlusal contacts (s, v) of premolars and molars: the supporting cusp tips, upper
    palatal and lower buccal (in a crossbite: upper buccal, shifted, and lower lingual)."""
    if crossbite:
        up = upper_cusps[(upper_cusps[:, 1] > 4.0) & (upper_cusps[:, 0] > 20.0)]
        lo = lower_cusps[(lower_cusps[:, 1] < -1.5) & (lower_cusps[:, 0] > 20.0)]
        return np.vstack([up[:, :2] - [0.0, CROSSBITE_SHIFT], lo[:, :2]])
    pal = upper_cusps[(np.abs(upper_cusps[:, 1]) < 0.5) & (upper_cusps[:, 0] > 20.0)]
    buc = lower_cusps[(lower_cusps[:, 1] > 1.5) & (lower_cusps[:, 0] > 20.0)]
    return np.vstack([pal[:, :2], buc[:, :2]])


def _sided_cusps(UC, ivu, crossbite: bool):
    """The upper cusp table of one side: in a crossbite the posterior cusps move lingually with their crowns."""
    if not crossbite:
        return UC
    UC = UC.copy()
    UC[UC[:, 0] >= ivu[3, 0], 1] -= CROSSBITE_SHIFT
    return UC


def arch_polyline(n=6000, anatomy: Anatomy = DESIGN):
    """Points and arc lengths of the x >= 0 half of the lower central-fossa line."""
    a, b = ARCH_A * anatomy.arch_width, ARCH_B * anatomy.arch_depth
    phi = np.linspace(0.0, np.pi / 2, n // 2)
    p1 = np.stack([a * np.sin(phi), ARCH_Z0 - b * (1 - np.cos(phi))], 1)
    d = np.array([math.sin(RAMUS_ANGLE), -math.cos(RAMUS_ANGLE)])
    seg = np.linalg.norm(np.diff(p1, axis=0), axis=1).sum()
    t = np.linspace(0.0, S_MAX - seg, n // 2)[1:]
    p2 = p1[-1] + t[:, None] * d
    # blend the corner: the ellipse ends heading -z, the line diverges at RAMUS_ANGLE
    P = np.vstack([p1, p2])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    return P, s


def arch_coordinates(x, z, anatomy: Anatomy = DESIGN):
    """``(s, v)`` of points ``(x, z)``: arc length (symmetric, ≥ 0) and outward offset (mm)."""
    from scipy.spatial import cKDTree

    P, S = arch_polyline(anatomy=anatomy)
    ax = np.abs(x)
    q = np.stack([ax, z], 1)
    _, i = cKDTree(P).query(q)
    i = np.clip(i, 0, len(P) - 2)
    t = P[i + 1] - P[i]
    L = np.linalg.norm(t, axis=1)
    t = t / L[:, None]
    rel = q - P[i]
    u = np.einsum("ij,ij->i", rel, t)
    s = S[i] + u
    n = np.stack([-t[:, 1], t[:, 0]], 1)  # outward: +z at the midline, +x at the molars
    v = np.einsum("ij,ij->i", rel, n)
    return s, v


def arch_point(s, v, anatomy: Anatomy = DESIGN):
    """``(x, z)`` on the x >= 0 side at arc length ``s`` and offset ``v``."""
    P, S = arch_polyline(anatomy=anatomy)
    i = int(np.clip(np.searchsorted(S, s) - 1, 0, len(P) - 2))
    t = (P[i + 1] - P[i]) / np.linalg.norm(P[i + 1] - P[i])
    p = P[i] + (s - S[i]) * t
    n = np.array([-t[1], t[0]])
    return p + v * n


# --- the implicit field (numba) -----------------------------------------------------------


@njit(cache=True)
def _smin(a, b, k):
    h = max(k - abs(a - b), 0.0) / k
    return min(a, b) - h * h * k * 0.25


@njit(cache=True)
def _smax(a, b, k):
    return -_smin(-a, -b, k)


@njit(cache=True)
def _round_box2(px, py, hx, hy, r):
    qx = abs(px) - hx + r
    qy = abs(py) - hy + r
    return math.sqrt(max(qx, 0.0) ** 2 + max(qy, 0.0) ** 2) + min(max(qx, qy), 0.0) - r


@njit(cache=True)
def _gauss_sum(s, v, C):
    acc = 0.0
    for k in range(C.shape[0]):
        ds = (s - C[k, 0]) / C[k, 3]
        dv = (v - C[k, 1]) / C[k, 4]
        e = ds * ds + dv * dv
        if e < 16.0:
            acc += C[k, 2] * math.exp(-e)
    return acc


@njit(cache=True)
def interface(s, v, LC, UC, CT):
    """Occlusal interface ``f`` and clearance ``g`` at arch coordinates ``(s, v)``."""
    f = _gauss_sum(s, v, LC) - _gauss_sum(s, v, UC)
    near = 0.0
    for k in range(CT.shape[0]):
        ds = s - CT[k, 0]
        dv = v - CT[k, 1]
        near = max(near, math.exp(-(ds * ds + dv * dv) / (CONTACT_SIGMA * CONTACT_SIGMA)))
    return f, CLEARANCE * (1.0 - near)


@njit(cache=True)
def _crowns(s, v, y, f, g, iv, B, T, taper, upper):
    """Union of the crowns (field, < 0 inside) of one jaw at one point (``T``: the side's tooth table)."""
    d = 1e9
    for t in range(iv.shape[0]):
        if T[t, 1] == 0.0:
            continue
        s0 = iv[t, 0]
        s1 = iv[t, 1]
        if s < s0 - 3.0 or s > s1 + 3.0:
            continue
        sc = 0.5 * (s0 + s1)
        hw = 0.5 * (s1 - s0) - INTERPROXIMAL
        if upper:
            vc = UPPER_SHIFT + T[t, 0]
            occ = min(max((3.0 - y) / 4.5, 0.0), 1.0)  # 0 at the height of contour, 1 at the edge
            top = y - 9.5  # cervical end, inside the alveolar bone
            cut = (f + g) - y  # upper crowns lie above f + g
        else:
            vc = T[t, 0]
            occ = min(max((y + 3.0) / 4.5, 0.0), 1.0)
            top = -9.5 - y
            cut = y - f
        hb = 0.5 * B[t] * (1.0 - taper[t] * occ)
        r = min(2.2, 0.45 * min(hw, hb))
        side = _round_box2(s - sc, v - vc, hw, hb, r)
        crown = _smax(_smax(side, cut, 1.2), top, 0.5)
        d = min(d, crown)
    return d


@njit(cache=True)
def _seg_dist(px, py, ax, ay, bx, by):
    ex = bx - ax
    ey = by - ay
    wx = px - ax
    wy = py - ay
    t = min(max((wx * ex + wy * ey) / (ex * ex + ey * ey), 0.0), 1.0)
    dx = wx - t * ex
    dy = wy - t * ey
    return math.sqrt(dx * dx + dy * dy)


@njit(cache=True)
def _polygon(px, py, P):
    """Signed distance to a simple polygon (negative inside)."""
    n = P.shape[0]
    d = 1e18
    inside = False
    for i in range(n):
        j = (i + 1) % n
        d = min(d, _seg_dist(px, py, P[i, 0], P[i, 1], P[j, 0], P[j, 1]))
        if (P[i, 1] > py) != (P[j, 1] > py):
            x = P[i, 0] + (py - P[i, 1]) / (P[j, 1] - P[i, 1]) * (P[j, 0] - P[i, 0])
            if px < x:
                inside = not inside
    return -d if inside else d


@njit(cache=True)
def _ellipsoid(px, py, pz, ax, ay, az):
    """Approximate signed distance to an axis-aligned ellipsoid (scaled, good near the surface)."""
    k0 = math.sqrt((px / ax) ** 2 + (py / ay) ** 2 + (pz / az) ** 2)
    k1 = math.sqrt((px / (ax * ax)) ** 2 + (py / (ay * ay)) ** 2 + (pz / (az * az)) ** 2)
    if k1 == 0.0:
        return -min(ax, min(ay, az))
    return k0 * (k0 - 1.0) / k1


@njit(cache=True)
def mandible_field(x, y, z, s, v, LC, UC2, CT2, ivl, B, T2, SH, cond_c):
    side = 0 if x >= 0.0 else 1
    f, g = interface(s, v, LC, UC2[side], CT2[side])
    d = _crowns(s, v, y, f, g, ivl, B, T2[side], TAPER, False)
    # alveolar body along the arch, wider posteriorly
    hv = 5.2 + 2.0 * min(max((s - 20.0) / 35.0, 0.0), 1.0)
    body = _round_box2(v, y + 20.0, hv, 13.5, 4.5)
    body = max(body, s - 70.0)
    # ramus: the outline in (s, y), 6 mm thick, rounded
    pr = _polygon(s, y, RAMUS)
    q = abs(v) - 3.0
    ramus = math.sqrt(max(pr, 0.0) ** 2 + max(q, 0.0) ** 2) + min(max(pr, q), 0.0) - 1.0
    bone = _smin(body, ramus, 6.0)
    ax_ = abs(x)
    cond = _ellipsoid(ax_ - cond_c[0], y - cond_c[1], z - cond_c[2], CONDYLE_AXES[0], CONDYLE_AXES[1], CONDYLE_AXES[2])
    bone = _smin(bone, cond, 3.0)
    return _smin(d, bone, 0.8)


@njit(cache=True)
def maxilla_field(x, y, z, s, v, LC, UC2, CT2, ivu, B, T2, SH, cond_c):
    side = 0 if x >= 0.0 else 1
    f, g = interface(s, v, LC, UC2[side], CT2[side])
    d = _crowns(s, v, y, f, g, ivu, B, T2[side], TAPER, True)
    # alveolar process over the crowns (following a crossbite's lingual step from the canine
    # to the first premolar), palate and basal body inside the arch
    hv = 5.0 + 2.0 * min(max((s - 20.0) / 35.0, 0.0), 1.0)
    alv = _round_box2(v - (UPPER_SHIFT + SH[side] * min(max((s - SH[2]) / 6.0, 0.0), 1.0)), y - 16.0, hv, 7.5, 3.5)
    inner = _round_box2(v + 10.0, y - 19.0, 16.0, 4.5, 3.0)  # palate: the inside of the U
    base = _smin(alv, inner, 4.0)
    base = max(base, s - 62.0)
    d = _smin(d, base, 0.8)
    # glenoid fossae: a block of temporal bone with a socket one joint space above the condyle
    ax_ = abs(x)
    px = ax_ - cond_c[0]
    py = y - cond_c[1]
    pz = z - cond_c[2]
    bx = abs(px) - (CONDYLE_AXES[0] + 5.0)
    by = abs(py - 6.0) - 7.5
    bz = abs(pz) - (CONDYLE_AXES[2] + 6.0)
    block = math.sqrt(max(bx, 0.0) ** 2 + max(by, 0.0) ** 2 + max(bz, 0.0) ** 2) + min(max(bx, max(by, bz)), 0.0) - 1.0
    sock = _ellipsoid(px, py, pz, CONDYLE_AXES[0] + JOINT_SPACE, CONDYLE_AXES[1] + JOINT_SPACE, CONDYLE_AXES[2] + JOINT_SPACE)
    fossa = max(block, -sock)
    return min(d, fossa)


@njit(cache=True, parallel=True)
def _fill(which, xs, ys, zs, S, V, LC, UC2, CT2, iv, B, T2, SH, cond_c, out):
    for i in prange(xs.shape[0]):
        for k in range(zs.shape[0]):
            s = S[i, k]
            v = V[i, k]
            for j in range(ys.shape[0]):
                if which == 0:
                    out[i, j, k] = mandible_field(xs[i], ys[j], zs[k], s, v, LC, UC2, CT2, iv, B, T2, SH, cond_c)
                else:
                    out[i, j, k] = maxilla_field(xs[i], ys[j], zs[k], s, v, LC, UC2, CT2, iv, B, T2, SH, cond_c)


# --- generation ---------------------------------------------------------------------------

DEFAULT_SPACING = 0.5  # mm: ~100k vertices per jaw (97k maxilla, 116k mandible)


def design(anatomy: Anatomy = DESIGN):
    """Everything the fields need: cusp tables (the upper and the contacts per side), crown
    intervals, tooth tables, crown sizes, condyle centre (mm)."""
    ivl, ivu = tooth_layout(anatomy)
    LC = _cusp_table(LOWER_CUSPS, ivl)
    UC = _cusp_table(UPPER_CUSPS, ivu)
    cross = [anatomy.crossbite == side for side in SIDES]
    UC2 = np.stack([_sided_cusps(UC, ivu, c) for c in cross])
    CTs = [contact_table(LC, UC, c) for c in cross]
    m = max(len(c) for c in CTs)  # pad with far-away points (no effect on the clearance)
    CT2 = np.stack([np.vstack([c, np.full((m - len(c), 2), 1e6)]) for c in CTs])
    cx, cz = arch_point(CONDYLE_S, 0.0, anatomy)
    cond = np.array([cx, CONDYLE_Y, cz])
    # the maxillary alveolar process's lingual step in a crossbite: amount per side, where it starts
    SH = np.array([-CROSSBITE_SHIFT * c for c in cross] + [ivu[3, 0] - 6.0])
    return {"LC": LC, "UC": UC, "UC2": UC2, "CT": CTs, "CT2": CT2, "ivl": ivl, "ivu": ivu, "condyle": cond,
            "Bl": LOWER_B * anatomy.tooth_size, "Bu": UPPER_B * anatomy.tooth_size, "SH": SH,
            "Tl": _tooth_table(anatomy, "mandible"), "Tu": _tooth_table(anatomy, "maxilla"), "anatomy": anatomy}


def _grid(lo, hi, h):
    n = np.ceil((np.asarray(hi) - np.asarray(lo)) / h).astype(int) + 1
    return [lo[i] + h * np.arange(n[i]) for i in range(3)]


def _polygonise(which, D, xs, ys, zs, h):
    import trimesh
    from skimage.measure import marching_cubes

    field = np.empty((len(xs), len(ys), len(zs)))
    X, Z = np.meshgrid(xs, zs, indexing="ij")
    S, V = arch_coordinates(X.ravel(), Z.ravel(), D["anatomy"])
    S = S.reshape(X.shape)
    V = V.reshape(X.shape)
    iv, B, T = (D["ivl"], D["Bl"], D["Tl"]) if which == 0 else (D["ivu"], D["Bu"], D["Tu"])
    _fill(which, xs, ys, zs, S, V, D["LC"], D["UC2"], D["CT2"], iv, B, T, D["SH"], D["condyle"], field)
    # keep the zero level off the lattice points: a vertex on a lattice point makes slivers
    # that collapse when written to file (|f| ~ mm, so this moves the surface < 1e-4 mm)
    field[np.abs(field) < 1e-4] = 1e-4
    # pad with "outside" so every surface closes
    field = np.pad(field, 1, constant_values=1e3)
    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(h, h, h), allow_degenerate=False)
    verts += np.array([xs[0], ys[0], zs[0]]) - h
    m = trimesh.Trimesh(verts, faces, process=True)
    if m.volume < 0:
        m.invert()
    return m


def _clean_metres(m):
    """Scale to metres at the file precision (1 nm) and check the result is a clean closed solid."""
    from ..geometry.mesh import load_mesh

    m.apply_scale(1e-3)
    m.vertices = np.round(m.vertices, 9)
    load_mesh((m.vertices, m.faces))  # raises MeshError if the file would not be a clean solid


def generate(spacing: float = DEFAULT_SPACING, anatomy: Anatomy = DESIGN):
    """The two jaws of ``anatomy`` (default: the bundled pair) in the design (centric occlusion) pose, in metres.

    Returns
    -------
    maxilla, mandible : trimesh.Trimesh
    meta : dict
        ``metadata(spacing)``: ``hinge`` (condyle centre, m), designed contact points (m), ...
    """
    D = design(anatomy)
    c = D["condyle"]
    xmax = c[0] + CONDYLE_AXES[0] + 8.0
    zlo = c[2] - CONDYLE_AXES[2] - 14.0
    zhi = ARCH_Z0 + 10.0
    mand = _polygonise(0, D, *_grid([-xmax, -36.0, zlo], [xmax, 34.0, zhi], spacing), spacing)
    maxi = _polygonise(1, D, *_grid([-xmax, -5.0, zlo], [xmax, 43.0, zhi], spacing), spacing)
    for m in (mand, maxi):
        _clean_metres(m)
    return maxi, mand, metadata(spacing, D)


def _has_crown(T, iv, s) -> bool:
    """Whether a crown of the side's tooth table ``T`` covers arc length ``s``."""
    return any(T[t, 1] > 0.0 and iv[t, 0] <= s <= iv[t, 1] for t in range(len(iv)))


def metadata(spacing: float = DEFAULT_SPACING, D: dict | None = None, anatomy: Anatomy = DESIGN) -> dict:
    """What the design says about the jaws without polygonising them: units, frame, hinge,
    condyles and the designed contact points (both sides, on the occlusal interface)."""
    D = design(anatomy) if D is None else D
    c = D["condyle"]
    pts = []
    for side in (0, 1):
        for s, v in D["CT"][side]:
            f, _ = interface(s, v, D["LC"], D["UC2"][side], D["CT2"][side])
            if not all(_has_crown(D[T][side], D[iv], s) for T, iv in (("Tl", "ivl"), ("Tu", "ivu"))):
                continue  # its tooth is missing
            x, z = arch_point(s, v, D["anatomy"])
            pts.append([x if side == 0 else -x, f, z])
    if D["anatomy"] == DESIGN:  # the bundled pair's order: each contact with its mirror image
        n = len(pts) // 2
        pts = [p for i in range(n) for p in (pts[i], pts[n + i])]
    meta = {
        "units": "m",
        "frame": "+y up (superior), +z anterior, x left-right; maxilla fixed",
        "hinge": (np.array([0.0, c[1], c[2]]) * 1e-3).tolist(),
        "condyles": [(np.array([c[0], c[1], c[2]]) * 1e-3).tolist(), (np.array([-c[0], c[1], c[2]]) * 1e-3).tolist()],
        "designed_contacts": (np.array(pts) * 1e-3).tolist(),
        "spacing_mm": spacing,
        "teeth_per_jaw": 2 * len(KINDS),
    }
    if D["anatomy"] != DESIGN:
        meta["anatomy"] = D["anatomy"].as_dict()
        meta["teeth_per_jaw"] = {j: int(D[k][:, :, 1].sum()) for j, k in (("maxilla", "Tu"), ("mandible", "Tl"))}
    return meta
