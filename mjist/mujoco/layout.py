"""The binary layout shared by the Python side and the cfuncs, declared once.

The cfuncs (``hook``, ``forces``) read everything through int64 words: a registry root, one
entry per attached model, per (MjData, pair) state slots, output rows and scratch carved from
MuJoCo's per-``mjData`` stack. ``attach`` and ``registry`` write the same words. Every offset
here is computed from the list of fields it follows, so adding a field moves the ones after
it everywhere at once; numba reads these module globals as compile-time constants.
"""
from __future__ import annotations

import math
from enum import IntEnum, auto

import numpy as np
from numba import njit

from ..geometry import surface as sf
from ..query import narrow as nw
from ..query import primitive as cp
from ..query import traverse as tv
from . import abi


def _offsets(*sizes: int) -> tuple[int, ...]:
    """Start of each field laid out one after another, then the total size."""
    out, o = [], 0
    for s in sizes:
        out.append(o)
        o += s
    return (*out, o)


# ---- registry root ----------------------------------------------------------------------
MAX_MODELS = 64
SLOTS = (  # collision-table slots the hook can take over (hook.COLLISION_TABLE); the root keeps their originals in this order
    (abi.GEOM_MESH, abi.GEOM_MESH),
    (abi.GEOM_MESH, abi.GEOM_SDF),
    (abi.GEOM_SDF, abi.GEOM_SDF),
    (cp.SPHERE, abi.GEOM_MESH),
    (cp.CAPSULE, abi.GEOM_MESH),
    (cp.CYLINDER, abi.GEOM_MESH),
    (cp.BOX, abi.GEOM_MESH),
)
# number of models; each slot's original function; the mjcb_passive found before ours;
# then (model address, entry address) per model
ROOT_N, ROOT_ORIG, ROOT_PASSIVE, ROOT_MODELS, ROOT_WORDS = _offsets(1, len(SLOTS), 1, 2 * MAX_MODELS)

# ---- model entry ---------------------------------------------------------------------------


class Entry(IntEnum):
    """The int64 words of a model entry, in order (addresses are of numpy arrays the entry
    keeps alive); ``ENTRY_WORDS`` of them."""

    NGEOM = 0  # model.ngeom
    GSLOT = auto()  # per geom: its IST index k (-1: not managed)
    NMAN = auto()  # managed geoms (nman)
    CAP = auto()  # per pair p = ka * nman + kb: contacts written at most (0: not managed, -1: penalty)
    TREES = auto()  # per k: (packed tree address, node count, traverse.exit_directions (n, 4) address)
    OFFSET = auto()  # per pair: subtracted from the IST distance (metres)
    XPOS = auto()  # offset in mjData of geom_xpos
    XMAT = auto()  # ... of geom_xmat
    ALLOC = auto()  # address of mj_stackAllocByte
    MARK = auto()  # ... of mj_markStack
    FREE = auto()  # ... of mj_freeStack
    KEYS = auto()  # the (MjData, pair) state slots' keys
    NSLOT = auto()  # ... their count
    ISTATE = auto()  # ... their int64 state (IW words each)
    FSTATE = auto()  # ... their float64 state (FW words each)
    STACK = auto()  # traversal stack capacity
    NCAND = auto()  # candidate capacity
    SPLIT = auto()  # contact-group depth
    SKIP = auto()  # motion-bound skipping on/off
    COUNT = auto()  # the counters (Count)
    NARENA = auto()  # offset in mjData of narena
    PSTACK = auto()  # ... of pstack
    PARENA = auto()  # ... of parena
    POOL = auto()  # ... of threadpool
    TIME = auto()  # offset in mjData of time
    EPS = auto()  # per pair: ε1 + ε2
    GPRIM = auto()  # primitives: per geom, its index (-1: none)
    NPRIM = auto()  # ... their count
    PRIM = auto()  # ... their (nprim, 4) table [type, size0..2]
    PCAP = auto()  # per (primitive, tree): contacts written at most
    POFF = auto()  # ... offset
    NUP = auto()  # levels contact normals climb at least (penalty mode: smooth force directions)
    NPEN = auto()  # forces: penalty rows' count
    PEN = auto()  # ... penalty rows (Pen)
    NCPL = auto()  # ... coupling rows' count
    CPL = auto()  # ... coupling rows (CPL_*)
    POUT = auto()  # ... output rows (O_*)
    APPLYFT = auto()  # address of mj_applyFT
    OBJVEL = auto()  # ... of mj_objectVelocity
    QFRCP = auto()  # offset in mjData of qfrc_passive
    BXPOS = auto()  # ... of xpos
    BXQUAT = auto()  # ... of xquat
    BXIPOS = auto()  # ... of xipos
    MOCPOS = auto()  # ... of mocap_pos
    MOCQUAT = auto()  # ... of mocap_quat
    NBODY = auto()  # model.nbody
    NMOCAP = auto()  # model.nmocap
    DT_NS = auto()  # the model's timestep in nanoseconds
    NARROW = auto()  # mesh–mesh narrow phase: 0 the leaf spheres, else groups measured on the surfaces per call
    SURF = auto()  # per k, SURF_W words: surface floats, ints (addresses), vertices, faces, BVH nodes, grid header, table, values (addresses), bricks; see geometry.surface
    HOLD = auto()  # per pair: how far B may move from where its surface contacts were measured before they are again (0: never held)


ENTRY_WORDS = len(Entry)

# ---- counters ------------------------------------------------------------------------------


class Count(IntEnum):
    """The counters, in order (racy increments from several threads: statistics only);
    ``Handle.stats`` reports each under its name in lower case."""

    CALLS = 0
    CONTACT_CALLS = auto()
    CONTACTS = auto()
    SKIPPED = auto()
    STATELESS = auto()
    NO_STACK = auto()
    BAD_POSE = auto()
    FAILED = auto()  # a traversal or a surface query gave no answer (the call wrote none, or dropped that group)
    FRONT_CALLS = auto()
    FRONT_REFRESHES = auto()
    VISITS = auto()
    FRONT_GROUPS = auto()
    PRIMITIVE_CALLS = auto()
    PRIMITIVE_CONTACTS = auto()
    OVER_STIFFNESS_BUDGET = auto()  # penalty steps whose summed contact stiffness exceeded the explicit stability bound
    DISTANCE_CALLS = auto()  # calls answered with the distance only (mj_geomDistance, distance sensors)
    SURFACE_GROUPS = auto()  # contact groups measured on the surfaces (mjist_narrowphase surface)
    HELD_CALLS = auto()  # surface contact calls answered by last measurement's contacts (the pair moved less than the hold)


N_COUNT = len(Count)
COUNTER_NAMES = tuple(c.name.lower() for c in Count)

# ---- state slot of one (MjData, pair) ----------------------------------------------------
KP = 16  # contact groups remembered for next frame
NG = 256  # groups of the motion-bounded front
# int64 words: closest leaf pair, remembered groups' count, front's count, the groups, the front
I_PAIR, I_NPREV, I_NFRONT, I_PREV, I_FRONT, IW = _offsets(2, 1, 1, 4 * KP, 4 * NG)
# a held surface contact: its distance, point and normal (A's frame), B's surface point (B's frame),
# the way it was measured (geometry.surface.contact_distance)
H_DIST, H_POINT, H_NORMAL, H_B, H_WAY, HOLD_W = _offsets(1, 3, 3, 3, 1)
# float64 words: distance-skip reference (pose, distance, valid), slot time, front reference
# (valid, pose, threshold reached, contact threshold), last pose (+ valid), the margin it serves,
# last step's contacts (count; per contact: point, normal, A's frame; the time they were
# written) for the side of approach;
# the surface contacts held (valid, the pose they were measured at, count; per contact ``HOLD_W``)
F_REF, F_D, F_OK, F_TIME, F_FOK, F_FXF, F_FT0, F_FTHR, F_LXF, F_LOK, F_MARGIN, F_NPN, F_PN, F_PT, F_HOK, F_HXF, F_HN, \
    F_HC, FW = _offsets(12, 1, 1, 1, 1, 12, 1, 1, 12, 1, 1, 1, 6 * KP, 1, 1, 12, 1, HOLD_W * KP)

# ---- slot keys: an MjData address and a pair index in one int64 ---------------------------
KEY_SHIFT = 48  # user-space addresses fit in 48 bits (x86-64, AArch64)
KEY_DATA_MASK = (1 << KEY_SHIFT) - 1
KEY_OTHER = np.int64(-(1 << 63))  # a pair's second slot: calls with another margin than the steps'
# pair indices below 2**15 (bit 63 is KEY_OTHER): nman² pairs and one coupling key after them
MAX_GEOMS = math.isqrt((1 << (63 - KEY_SHIFT)) - 2)


@njit(cache=True)
def slot_key(d, p, other):
    """Key of the state slot of MjData ``d`` and pair (or coupling) ``p``."""
    key = d | (p << KEY_SHIFT)
    if other:
        key |= KEY_OTHER
    return key


def slot_key_py(data_address: int, p: int) -> int:
    """``slot_key`` from Python (a numpy int64 comparable key)."""
    return int(data_address) | (int(p) << KEY_SHIFT)


# ---- forces: rows of penalty pairs and couplings, output rows -------------------------------


class Pen(IntEnum):
    """The float64 columns of a penalty pair's row; ``PEN_W`` of them."""

    PAIR = 0  # pair index
    G1 = auto()  # geoms
    G2 = auto()
    B1 = auto()  # bodies (-1: static)
    B2 = auto()
    LAW = auto()  # force law
    K = auto()  # stiffness k
    C = auto()  # damping c
    KMAX = auto()  # the explicit stability bound K_max
    GROUPS = auto()  # contact groups summed


PEN_W = len(Pen)
# coupling: mocap id, body, gains k_t c_t k_r c_r, the body's centre of mass in its frame (3)
CPL_MOCAP, CPL_BODY, CPL_KT, CPL_CT, CPL_KR, CPL_CR, CPL_COM, CPL_W = _offsets(1, 1, 1, 1, 1, 1, 3)
# output row per (MjData, pair | coupling) slot: force, torque, contacts, depth, volume, time;
# the coupling's handle velocity, angular velocity, last position, last quaternion (+ valid)
O_F, O_T, O_N, O_DEPTH, O_VOL, O_TIME, O_VH, O_WH, O_PH, O_QH, O_HOK, PO = _offsets(3, 3, 1, 1, 1, 1, 3, 3, 3, 4, 1)

# ---- scratch on MuJoCo's stack ------------------------------------------------------------
# Bytes of MuJoCo's arena left free beyond a call's scratch: MuJoCo allocates after the
# collision phase in the same step, and running it out aborts the step with an error.
STACK_RESERVE = 65536
POSE_W = 44  # two 4x4 poses and the 3x4 relative transform
PAIR_GEOM_W = nw.GEOM_W  # per candidate: normal, the two ball points, contact point (tv.leaf_geometry), way
SURF_F = sf.REFINE_W + 8  # the surface narrow phase: local_distance's temporaries and answer
SURF_W = 9  # Entry.SURF words per managed geom
PRIM_F = 50  # the primitive path: two poses, transform, the primitive's query point (6)
PEN_CAP = 64  # contact groups a penalty pair sums at most (the deepest and most spread when more)
SMALL = 64  # float64 words of the forces' per-call temporaries


@njit(cache=True)
def pair_floats(ns, nc):
    """float64 words of a pair call: poses, stack values, candidate values, dmin, geometry rows,
    the stateless slot, the blend accumulator; then the surface narrow phase's candidate values
    and temporaries."""
    return POSE_W + ns + nc * (2 + PAIR_GEOM_W) + FW + tv.BLEND_W + nc + SURF_F


@njit(cache=True)
def pair_ints(ns, nc, cap):
    """int64 words of a pair call: stack pairs, candidates, chosen, closest pair, stateless slot,
    the surface queries' stack."""
    return 2 * ns + 4 * nc + cap + 2 + IW + sf.STACK


@njit(cache=True)
def pair_scratch_bytes(ns, nc, cap):
    return 8 * pair_floats(ns, nc) + 8 * pair_ints(ns, nc, cap) + 64


@njit(cache=True)
def prim_floats(nc):
    """float64 words of a tree–primitive call: PRIM_F, values, dmin, geometry rows."""
    return PRIM_F + nc * (cp.GEOM_W + 2)


@njit(cache=True)
def prim_ints(ns, nc, cap):
    """int64 words of a tree–primitive call: stack, candidates (group, leaf), chosen."""
    return ns + 2 * nc + cap


@njit(cache=True)
def prim_scratch_bytes(ns, nc, cap):
    return 8 * prim_floats(nc) + 8 * prim_ints(ns, nc, cap) + 64


@njit(cache=True)
def forces_small_floats():
    """float64 words of the forces' fixed part: a contact buffer, temporaries, a spare output row."""
    return PEN_CAP * abi.PRECONTACT_DOUBLES + SMALL + PO


@njit(cache=True)
def forces_big_bytes(ns, nc):
    """The forces' traversal scratch: a pair call's, or the penetration volume's (poses, stack)."""
    own = 8 * (POSE_W + ns) + 8 * (2 * ns + 2) + 64
    return max(pair_scratch_bytes(ns, nc, PEN_CAP), own)


@njit(cache=True)
def forces_scratch_bytes(ns, nc):
    return 8 * forces_small_floats() + forces_big_bytes(ns, nc) + 128


def scratch_bytes(ns: int, nc: int, cap: int) -> int:
    """The most any cfunc call of a model takes from MuJoCo's stack, reserve included."""
    return int(max(pair_scratch_bytes(ns, nc, cap), prim_scratch_bytes(ns, nc, cap),
                   forces_scratch_bytes(ns, nc))) + STACK_RESERVE
