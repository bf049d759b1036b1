"""``<custom>`` settings of the MuJoCo layer: what they are, how the MJCF spells them, their checks.

Configuration lives in the MJCF, MuJoCo's own way (``<custom>`` elements), and any of it
can be overridden by ``attach`` keyword arguments:

.. code-block:: xml

    <custom>
      <text    name="mjist_geoms"       data="maxilla mandible"/>  <!-- or "all" (default) -->
      <numeric name="mjist_max_error"   data="0.0003"/>  <!-- metres; default 0.5 % of the mesh size -->
      <numeric name="mjist_contacts"    data="4"/>       <!-- per pair, ≤ MuJoCo's cap -->
      <text    name="mjist_offset"      data="mean"/>    <!-- none | mean | a distance in metres -->
      <text    name="mjist_mode"        data="constraint"/>
      <numeric name="mjist_split_depth" data="5"/>  <!-- contact groups; default 5 (penalty: 3) -->
      <text    name="mjist_skip"        data="true"/>
      <text    name="mjist_primitives"  data="ist"/>     <!-- or native: hull contacts -->
      <text    name="mjist_narrowphase" data="spheres"/> <!-- or surface: distances of the meshes -->
      <numeric name="mjist_surface_groups" data="8"/>   <!-- groups measured on the meshes per call -->
      <numeric name="mjist_surface_hold" data="0"/>     <!-- metres; default 0.5 % of ε1+ε2, 0: measure every call -->
    </custom>
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from ..errors import ConfigError

_MODES = ("constraint", "penalty")
_NARROW = ("spheres", "surface")
_LAWS = ("contacts", "volume")
# penalty defaults (see the README's haptic section for the stability reasoning)
DEFAULT_STIFFNESS = {"contacts": 1.0e4, "volume": 2.0e11}  # N/m per contact group; N/m³
PENALTY_NORMAL_CLIMB = 2  # penalty normals from the leaf pair's ancestors 2 levels up (no jumps between siblings)
HUNT_CROSSLEY_ALPHA = 2.0  # s/m: damping = α·stiffness (force ∝ depth·velocity, zero at first touch)
DEFAULT_COUPLING = (2000.0, None, 2.0, None)  # k_t N/m, c_t N·s/m, k_r N·m/rad, c_r N·m·s/rad (None: critical)
_TRUE = {"true": True, "1": True, "yes": True, "on": True, "false": False, "0": False, "no": False, "off": False}
# surface contacts are held (their depths moved with the pose, first order) while B stays within
# this fraction of ε1+ε2 of where they were measured: more holds a resting pair over more of its
# motion (fewer measurements, no contact set flipping under micrometre jitter), less sees sooner a
# spot that comes into contact while they are held (at most the hold late) and keeps the depths'
# second-order error (hold² × curvature) smaller
SURFACE_HOLD = 0.005
SDF_OCTREE_DEPTH = 1  # native octree kept minimal for mesh-backed sdf geoms the IST takes over


@dataclass
class Config:
    """How the IST stands in for MuJoCo's mesh contacts (see the module docstring)."""

    geoms: list[str] | str = "all"
    max_error: float | None = None
    contacts: int | None = None
    offset: str | float = "mean"
    mode: str = "constraint"
    split_depth: int | None = None  # contact groups: 5 in constraint mode, 3 in penalty mode
    skip: bool = True
    state_slots: int = 256
    candidates: int = 256
    branching: int = 4
    seed: int = 0
    primitives: str = "ist"
    penalty: str = "contacts"
    stiffness: float | None = None
    damping: float | None = None
    coupling: str | None = None
    coupling_gains: object = None
    narrowphase: str = "spheres"
    # contact groups measured on the surfaces per pair call in constraint mode, the deepest
    # first: each costs tens of µs, and more find more of the places that touch at once
    # (penalty forces take every group's overlap depth, see hook._surface_penalty)
    surface_groups: int = 8
    surface_hold: float | None = None  # metres; None: SURFACE_HOLD × (ε1+ε2); 0: measured every call

    def validate(self) -> "Config":
        if self.mode not in _MODES:
            raise ConfigError(f"mjist_mode={self.mode!r} must be 'constraint' (MuJoCo contacts) or 'penalty' (forces)")
        if self.penalty not in _LAWS:
            raise ConfigError(f"mjist_penalty={self.penalty!r} must be 'contacts' (Σ k·depth·n over contact groups) "
                              "or 'volume' (k·penetration volume)")
        for name in ("stiffness", "damping"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"mjist_{name}={v} must be a finite number ≥ 0 (SI units)")
        if self.coupling is not None and len(str(self.coupling).split()) != 2:
            raise ConfigError(f"mjist_coupling={self.coupling!r} must name two bodies: 'HANDLE BODY' "
                              "(a mocap body, then the body it drives)")
        if self.coupling_gains is not None:
            g = np.atleast_1d(np.asarray(self.coupling_gains, float))
            if g.size != 4 or not np.all(np.isfinite(g)) or np.any(g < 0):
                raise ConfigError(f"mjist_coupling_gains={g.tolist()} needs 4 numbers ≥ 0: k_t (N/m) c_t (N·s/m) "
                                  "k_r (N·m/rad) c_r (N·m·s/rad)")
        if self.max_error is not None and not (math.isfinite(self.max_error) and self.max_error > 0):
            raise ConfigError(f"mjist_max_error={self.max_error} must be a positive distance in metres (e.g. 0.0003)")
        if self.contacts is not None and not (1 <= int(self.contacts) <= 50):
            raise ConfigError(f"mjist_contacts={self.contacts} must be between 1 and 50 (MuJoCo's cap still applies)")
        if isinstance(self.offset, str):
            if self.offset not in ("none", "mean"):
                try:
                    self.offset = float(self.offset)
                except ValueError:
                    raise ConfigError(f"mjist_offset={self.offset!r} must be 'none', 'mean' or a distance in metres") from None
        if not isinstance(self.offset, str) and not (math.isfinite(self.offset) and self.offset >= 0):
            raise ConfigError(f"mjist_offset={self.offset} must be ≥ 0 (metres)")
        if self.split_depth is None:
            # constraint contacts: one per group, and a group at depth 3 (about a centimetre of
            # a jaw) spans both slopes of a cusp, so its normal flips as the deepest pair moves and
            # a clenched jaw chatters. The penalty law sums over groups, so its force scale stays
            # with the groups it was tuned on.
            self.split_depth = 5 if self.mode == "constraint" else 3
        if not 0 <= int(self.split_depth) <= 16:
            raise ConfigError(f"mjist_split_depth={self.split_depth} must be between 0 and 16")
        if not 1 <= int(self.state_slots) <= 1 << 20:
            raise ConfigError(f"mjist_state_slots={self.state_slots} must be between 1 and 2^20")
        if self.primitives not in ("ist", "native"):
            raise ConfigError(f"mjist_primitives={self.primitives!r} must be 'ist' (leaf spheres against the primitive) "
                              "or 'native' (MuJoCo's convex-hull contacts)")
        if self.narrowphase not in _NARROW:
            raise ConfigError(f"mjist_narrowphase={self.narrowphase!r} must be 'spheres' (contacts of the leaf spheres) "
                              "or 'surface' (the IST finds where, the meshes say how far)")
        if self.narrowphase == "surface" and self.mode == "penalty" and self.penalty != "contacts":
            raise ConfigError(f"mjist_narrowphase='surface' gives depths, not volumes: mjist_penalty={self.penalty!r} "
                              "sums leaf-sphere overlap volumes; use mjist_penalty='contacts' or "
                              "mjist_narrowphase='spheres'")
        if not 1 <= int(self.candidates) <= 4096:
            raise ConfigError(f"mjist_candidates={self.candidates} must be between 1 and 4096")
        if not 1 <= int(self.surface_groups) <= int(self.candidates):
            raise ConfigError(f"mjist_surface_groups={self.surface_groups} must be between 1 and mjist_candidates "
                              f"({self.candidates})")
        if self.surface_hold is not None and not (math.isfinite(self.surface_hold) and self.surface_hold >= 0):
            raise ConfigError(f"mjist_surface_hold={self.surface_hold} must be a distance ≥ 0 in metres "
                              "(0 measures the surfaces on every call)")
        return self


# MJCF name -> (Config field, kind)
_KEYS = {
    "mjist_geoms": ("geoms", "text"),
    "mjist_max_error": ("max_error", "numeric"),
    "mjist_contacts": ("contacts", "numeric"),
    "mjist_offset": ("offset", "text"),
    "mjist_mode": ("mode", "text"),
    "mjist_split_depth": ("split_depth", "numeric"),
    "mjist_skip": ("skip", "text"),
    "mjist_state_slots": ("state_slots", "numeric"),
    "mjist_candidates": ("candidates", "numeric"),
    "mjist_surface_groups": ("surface_groups", "numeric"),
    "mjist_surface_hold": ("surface_hold", "numeric"),
    "mjist_branching": ("branching", "numeric"),
    "mjist_seed": ("seed", "numeric"),
    "mjist_primitives": ("primitives", "text"),
    "mjist_penalty": ("penalty", "text"),
    "mjist_stiffness": ("stiffness", "numeric"),
    "mjist_damping": ("damping", "numeric"),
    "mjist_coupling": ("coupling", "text"),
    "mjist_coupling_gains": ("coupling_gains", "numeric"),
    "mjist_narrowphase": ("narrowphase", "text"),
}


def _customs(model) -> dict[str, tuple[str, object]]:
    out = {}
    for i in range(model.ntext):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_TEXT, i) or ""
        adr, size = model.text_adr[i], model.text_size[i]
        raw = bytes(model.text_data[adr:adr + size]).split(b"\0")[0].decode()
        out[name] = ("text", raw)
    for i in range(model.nnumeric):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_NUMERIC, i) or ""
        adr, size = model.numeric_adr[i], model.numeric_size[i]
        out[name] = ("numeric", np.array(model.numeric_data[adr:adr + size]))
    return out


def read_config(model, **overrides) -> Config:
    """The model's ``<custom>`` mjist settings, then ``overrides`` (``None`` values ignored)."""
    cfg = Config()
    for name, (kind, value) in _customs(model).items():
        if not name.startswith("mjist_"):
            continue
        if name not in _KEYS:
            raise ConfigError(f"unknown mjist setting {name!r} in <custom>: the known ones are {', '.join(sorted(_KEYS))}")
        fld, want = _KEYS[name]
        if kind != want:
            raise ConfigError(f"<custom> {name!r} must be a <{want}> element, not <{kind}>")
        if kind == "numeric" and fld == "coupling_gains":
            cfg.coupling_gains = value
        elif kind == "numeric":
            if value.size != 1 or not np.isfinite(value[0]):
                raise ConfigError(f"<numeric name={name!r}> needs exactly one finite number, got {value.tolist()}")
            v = float(value[0])
            if fld in ("contacts", "split_depth", "state_slots", "candidates", "surface_groups", "branching", "seed"):
                if v != int(v):
                    raise ConfigError(f"<numeric name={name!r}> must be an integer, got {v}")
                v = int(v)
            setattr(cfg, fld, v)
        elif fld == "skip":
            if value.strip().lower() not in _TRUE:
                raise ConfigError(f"<text name='mjist_skip'> must be true or false, got {value!r}")
            cfg.skip = _TRUE[value.strip().lower()]
        elif fld == "geoms":
            names = value.split()
            cfg.geoms = "all" if names == ["all"] else names
        else:
            setattr(cfg, fld, value.strip())
    for k, v in overrides.items():
        if v is not None:
            if not hasattr(cfg, k):
                raise TypeError(f"attach() got an unknown setting {k!r}")
            setattr(cfg, k, v)
    return cfg.validate()
