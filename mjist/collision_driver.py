"""Plug IST contacts into MuJoCo: ``mjist.attach(model)`` and ``mjist.load_model(path)``.

After attaching, an unmodified ``mujoco.mj_step`` loop, ``mujoco.viewer`` and
``mujoco.rollout`` get IST contacts for the managed geom pairs; the work happens in the
numba cfuncs of ``mjist.hook`` with no Python in the step.

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
    </custom>
"""
from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field

import mujoco
import numpy as np

from . import collision_primitive as cp
from . import mjabi as abi
from .errors import ConfigError

_MODES = ("constraint", "penalty")
_LAWS = ("contacts", "volume")
# penalty defaults (see the README's haptic section for the stability reasoning)
DEFAULT_STIFFNESS = {"contacts": 1.0e4, "volume": 2.0e11}  # N/m per contact group; N/m³
PENALTY_NORMAL_CLIMB = 2  # penalty normals from the leaf pair's ancestors 2 levels up (no jumps between siblings)
HUNT_CROSSLEY_ALPHA = 2.0  # s/m: damping = α·stiffness (force ∝ depth·velocity, zero at first touch)
DEFAULT_COUPLING = (2000.0, None, 2.0, None)  # k_t N/m, c_t N·s/m, k_r N·m/rad, c_r N·m·s/rad (None: critical)
_TRUE = {"true": True, "1": True, "yes": True, "on": True, "false": False, "0": False, "no": False, "off": False}
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
            # constraint contacts: one per group, and a group at depth 3 (7-10 mm of a jaw) spans
            # both slopes of a cusp, so its normal flips as the deepest pair moves: the clenched
            # bundled jaw chattered (BENCHMARKS, session 19). The penalty law sums over groups,
            # so its force scale stays with the groups it was tuned on.
            self.split_depth = 5 if self.mode == "constraint" else 3
        if not 0 <= int(self.split_depth) <= 16:
            raise ConfigError(f"mjist_split_depth={self.split_depth} must be between 0 and 16")
        if not 1 <= int(self.state_slots) <= 1 << 20:
            raise ConfigError(f"mjist_state_slots={self.state_slots} must be between 1 and 2^20")
        if self.primitives not in ("ist", "native"):
            raise ConfigError(f"mjist_primitives={self.primitives!r} must be 'ist' (leaf spheres against the primitive) "
                              "or 'native' (MuJoCo's convex-hull contacts)")
        if not 1 <= int(self.candidates) <= 4096:
            raise ConfigError(f"mjist_candidates={self.candidates} must be between 1 and 4096")
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
    "mjist_branching": ("branching", "numeric"),
    "mjist_seed": ("seed", "numeric"),
    "mjist_primitives": ("primitives", "text"),
    "mjist_penalty": ("penalty", "text"),
    "mjist_stiffness": ("stiffness", "numeric"),
    "mjist_damping": ("damping", "numeric"),
    "mjist_coupling": ("coupling", "text"),
    "mjist_coupling_gains": ("coupling_gains", "numeric"),
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
            if fld in ("contacts", "split_depth", "state_slots", "candidates", "branching", "seed"):
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


# --------------------------------------------------------------------------- scene analysis


def _is_ist_geom(model, g: int) -> bool:
    t = model.geom_type[g]
    return t == abi.GEOM_MESH or (t == abi.GEOM_SDF and model.geom_dataid[g] >= 0)


def _geom_name(model, g: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom #{g}"


def managed_geoms(model, cfg: Config) -> list[int]:
    """Geom ids the configuration asks for (validated)."""
    if cfg.geoms == "all":
        return [g for g in range(model.ngeom) if _is_ist_geom(model, g)]
    out = []
    for name in cfg.geoms:
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if g < 0:
            raise ConfigError(f"mjist_geoms names {name!r}, which is not a geom of this model: check the name or use 'all'")
        if not _is_ist_geom(model, g):
            raise ConfigError(
                f"mjist_geoms names {name!r}, a {mujoco.mjtGeom(model.geom_type[g]).name} geom: only mesh geoms "
                "(type='mesh', or type='sdf' with a mesh) can get an Inner Sphere Tree"
            )
        out.append(g)
    return out


def can_collide(model, g1: int, g2: int) -> bool:
    """Whether MuJoCo's broad phase can ever pass the pair ``(g1, g2)`` to the narrow phase."""
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return False
    for i in range(model.npair):
        if {model.pair_geom1[i], model.pair_geom2[i]} == {g1, g2}:
            return True
    b1, b2 = model.geom_bodyid[g1], model.geom_bodyid[g2]
    w1, w2 = model.body_weldid[b1], model.body_weldid[b2]
    if w1 == w2:
        return False  # same rigid body (or both static)
    if not (model.geom_contype[g1] & model.geom_conaffinity[g2] or model.geom_contype[g2] & model.geom_conaffinity[g1]):
        return False
    if not (model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT):
        p1, p2 = model.body_weldid[model.body_parentid[w1]], model.body_weldid[model.body_parentid[w2]]
        if w1 != 0 and w2 != 0 and (p1 == w2 or p2 == w1):
            return False
    sig = (min(b1, b2) << 16) + max(b1, b2)
    return sig not in set(int(s) for s in model.exclude_signature)


def mesh_of(model, g: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of geom ``g``'s mesh in the geom frame (as MuJoCo compiled them)."""
    mid = model.geom_dataid[g]
    va, vn = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
    fa, fn = model.mesh_faceadr[mid], model.mesh_facenum[mid]
    V = np.array(model.mesh_vert[va:va + vn], dtype=np.float64)
    F = np.array(model.mesh_face[fa:fa + fn], dtype=np.int64)
    return V, F


@dataclass
class PairInfo:
    """One IST-managed geom pair."""

    geom1: str
    geom2: str
    ids: tuple[int, int]
    cap: int  # contacts written at most (≤ mj_maxContact)
    offset: float  # subtracted from the IST distance (metres)
    error_bound: float  # ε_1 + ε_2
    mode: str = "constraint"  # or "penalty": forces from mjist.forces, no MuJoCo contact

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Handle:
    """An attached model: its trees, managed pairs and the hook's counters.

    ``detach()`` (or leaving a ``with`` block, or interpreter exit) gives the geoms back to
    MuJoCo's own collision functions.
    """

    model: mujoco.MjModel
    config: Config
    geoms: dict[str, int] = field(default_factory=dict)
    trees: dict[str, object] = field(default_factory=dict)
    pairs: list[PairInfo] = field(default_factory=list)
    primitive_pairs: list[PairInfo] = field(default_factory=list)  # geom1 = the primitive
    build_seconds: float = 0.0
    cache_hits: int = 0
    _entry: object = None

    @property
    def attached(self) -> bool:
        from . import registry

        return self._entry is not None and registry._ENTRIES.get(self._entry.address) is self._entry

    def detach(self) -> None:
        """Give the managed pairs back to MuJoCo; restore the table when no model needs it."""
        if self._entry is not None:
            from . import registry

            registry.remove(self._entry)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.detach()

    def stats(self) -> dict:
        """Hook counters since attach: calls, calls with contacts, contacts, skipped, ..."""
        from . import hook

        if self._entry is None:
            return {}
        c = self._entry.counters
        return {
            "calls": int(c[hook.C_CALLS]), "contact_calls": int(c[hook.C_CONTACT_CALLS]),
            "contacts": int(c[hook.C_CONTACTS]), "skipped": int(c[hook.C_SKIPPED]),
            "stateless": int(c[hook.C_STATELESS]), "no_stack": int(c[hook.C_NOSTACK]),
            "bad_pose": int(c[hook.C_BADPOSE]), "failed": int(c[hook.C_FALLBACK]),
            "front_calls": int(c[hook.C_FRONT]), "front_refreshes": int(c[hook.C_REFRESH]),
            "visits": int(c[hook.C_VISITS]), "front_groups": int(c[hook.C_GROUPS]),
            "primitive_calls": int(c[hook.C_PRIM_CALLS]), "primitive_contacts": int(c[hook.C_PRIM_CONTACTS]),
            "over_stiffness_budget": int(c[hook.C_STIFF]),
        }

    def haptic(self, data) -> dict:
        """Last wrenches ``mjist.forces`` applied for ``data``: per penalty pair and per coupling.

        Pairs: ``force``/``torque`` on geom2's body (world, torque about its centre of mass),
        ``contacts`` (contact groups, or overlapping leaf pairs for the volume law), ``depth``
        (deepest, metres), ``volume`` (m³). Couplings: ``force`` at the body's origin and
        ``torque`` on the body (the device displays their opposite).
        """
        from . import forces, hook

        out = {"pairs": {}, "coupling": None, "time": float(data.time)}
        if self._entry is None:
            return out
        keys = self._entry.arrays["keys"]
        rows = self._entry.arrays["pout"]
        nman = int(self._entry.words[hook.E_NMAN])

        def row(pk):
            hit = np.flatnonzero(keys == (int(data._address) | (int(pk) << 48)))
            return rows[hit[0]] if hit.size else None

        for p in self.pairs:
            if p.mode != "penalty":
                continue
            r = row(self._entry.pair_index[p.ids])
            if r is not None:
                out["pairs"][f"{p.geom1}/{p.geom2}"] = {
                    "force": r[forces.O_F:forces.O_F + 3].copy(), "torque": r[forces.O_T:forces.O_T + 3].copy(),
                    "contacts": int(r[forces.O_N]), "depth": float(r[forces.O_DEPTH]), "volume": float(r[forces.O_VOL])}
        if self._entry.arrays["cpl"].shape[0] and self._entry.words[forces.E_NCPL]:
            r = row(nman * nman)
            if r is not None:
                out["coupling"] = {"force": r[forces.O_F:forces.O_F + 3].copy(), "torque": r[forces.O_T:forces.O_T + 3].copy()}
        return out

    def forget(self, data) -> None:
        """Forget the coherence and device state kept for ``data`` (e.g. a new MjData that may sit
        at the address of a freed one; answers of the collision hook never depend on it, the
        coupling's handle-velocity estimate does for one step)."""
        from . import hook

        if self._entry is not None:
            keys = self._entry.arrays["keys"]
            mine = np.flatnonzero((keys & ((1 << 48) - 1)) == int(data._address))
            # keys stay (open addressing); a slot whose time is +inf reads as fresh at its next use
            self._entry.arrays["fstate"].reshape(-1, hook.FW)[mine, hook.F_TIME] = np.inf

    def reset_state(self) -> None:
        """Forget every (MjData, pair) coherence slot (answers do not change, only speed)."""
        if self._entry is not None:
            self._entry.arrays["keys"][:] = 0

    def summary(self) -> str:
        lines = [f"mjist: {len(self.pairs)} IST pair(s), {len(self.trees)} tree(s) "
                 f"({self.cache_hits} from cache, {self.build_seconds:.1f} s building)"]
        for name, t in self.trees.items():
            lines.append(f"  {name}: {t.num_leaves} leaves, depth {t.depth}, ε {t.error_bound * 1e3:.3f} mm, "
                         f"mean gap {t.info.get('mean_gap', float('nan')) * 1e3:.3f} mm")
        for p in self.pairs:
            lines.append(f"  {p.geom1} ↔ {p.geom2}: ≤ {p.cap} contacts, offset {p.offset * 1e3:.3f} mm, "
                         f"ε1+ε2 {p.error_bound * 1e3:.3f} mm")
        for p in self.primitive_pairs:
            lines.append(f"  {p.geom1} (primitive) ↔ {p.geom2}: ≤ {p.cap} contacts, offset {p.offset * 1e3:.3f} mm, "
                         f"ε {p.error_bound * 1e3:.3f} mm")
        return "\n".join(lines)


def _mean_gap(tree, V, F) -> float:
    g = tree.info.get("mean_gap")
    if g is None:
        from .bound import surface_gaps

        g = float(surface_gaps(V, F, tree.leaf_centers, tree.leaf_radii).mean())
        tree.info["mean_gap"] = g
    return float(g)


def attach(model: mujoco.MjModel, *, trees: dict | None = None, cache_dir=None, progress: bool = False, **settings) -> Handle:
    """Make MuJoCo use Inner Sphere Tree contacts for the model's mesh geom pairs.

    Parameters
    ----------
    model : mujoco.MjModel
        Keeps working with plain ``mj_step``, the viewer and ``mujoco.rollout``.
    trees : dict, optional
        Prebuilt trees by geom name (in the geom's mesh frame, i.e. built from
        ``mjist.collision_driver.mesh_of(model, g)``); others are built or loaded from the cache.
    cache_dir : path, optional
        Tree cache folder (default ``$MJIST_CACHE`` or ``~/.cache/mjist``).
    progress : bool
        Progress bars while building trees.
    **settings
        Override the MJCF ``<custom>`` settings: ``geoms``, ``max_error``, ``contacts``,
        ``offset``, ``mode``, ``split_depth``, ``skip``, ``state_slots``, ``candidates``.

    Returns
    -------
    Handle
        ``.detach()``, ``.pairs``, ``.trees``, ``.stats()``. A model with no managed pair
        installs nothing.

    Raises
    ------
    ConfigError
        Invalid settings (unknown key, a geom that is not a mesh, ...).
    mjist.mjabi.MuJoCoABIError
        MuJoCo version or struct layout not the verified one.
    """
    import time

    from . import forces, hook, registry
    from .cache import cached_tree
    from .traverse import pack, stack_size

    if not isinstance(model, mujoco.MjModel):
        raise TypeError(f"attach() needs a mujoco.MjModel, got {type(model).__name__}")
    cfg = read_config(model, **settings)
    abi.check_version()
    wanted = managed_geoms(model, cfg)
    pairs = [(a, b) for i, a in enumerate(wanted) for b in wanted[i + 1:] if can_collide(model, a, b)]
    prim_pairs = []  # (primitive geom, mesh geom)
    if cfg.primitives == "ist":
        prim_pairs = [(b, a) for a in wanted if model.geom_type[a] == abi.GEOM_MESH for b in range(model.ngeom)
                      if model.geom_type[b] in cp.TYPES and can_collide(model, a, b)]
    handle = Handle(model=model, config=cfg)
    _warn_primitive_pairs(model, wanted, cfg.primitives == "ist")
    if not pairs and not prim_pairs and cfg.coupling is None:
        return handle
    used = sorted({g for p in pairs for g in p} | {a for _, a in prim_pairs})
    if len(used) > 181:
        raise ConfigError(f"{len(used)} IST geoms can meet: at most 181 are supported per model (use mjist_geoms to pick)")

    # trees (cache keyed by the compiled mesh and the build parameters)
    params = {"max_error": cfg.max_error, "branching": int(cfg.branching), "seed": int(cfg.seed)}
    trees = dict(trees or {})
    t0 = time.perf_counter()
    gap = {}
    by_mesh = {}  # geoms sharing a mesh share its tree
    for g in used:
        name = _geom_name(model, g)
        V, F = mesh_of(model, g)
        if name not in trees:
            mid = int(model.geom_dataid[g])
            if mid not in by_mesh:
                tree, hit = cached_tree(V, F, params, folder=cache_dir, progress=progress, name=name)
                handle.cache_hits += int(hit)
                by_mesh[mid] = tree
            trees[name] = by_mesh[mid]
        gap[g] = _mean_gap(trees[name], V, F)
        handle.trees[name] = trees[name]
        handle.geoms[name] = g
    handle.build_seconds = time.perf_counter() - t0

    # registry arrays
    nman = len(used)
    slot_of = {g: k for k, g in enumerate(used)}
    gslot = np.full(model.ngeom, -1, np.int64)
    packed = []
    tree_tab = np.zeros(3 * nman, np.int64)
    for g, k in slot_of.items():
        gslot[g] = k
        N = pack(handle.trees[_geom_name(model, g)])
        packed.append(N)
        tree_tab[3 * k] = N.ctypes.data
        tree_tab[3 * k + 1] = N.shape[0]
    ns = max([stack_size(a, b) for a in packed for b in packed] + [cp.stack_size(a) for a in packed] + [2])
    cap = np.zeros(nman * nman, np.int64)
    off = np.zeros(nman * nman, np.float64)
    eps_pair = np.zeros(nman * nman, np.float64)
    slots = set()
    for a, b in pairs:
        c = _pair_cap(model, a, b, cfg)
        if c < 1:
            continue
        eps = handle.trees[_geom_name(model, a)].error_bound + handle.trees[_geom_name(model, b)].error_bound
        if cfg.offset == "none":
            o = 0.0
        elif cfg.offset == "mean":
            o = gap[a] + gap[b]
        else:
            o = float(cfg.offset)
            if o > eps:
                warnings.warn(f"mjist_offset {o:g} m exceeds ε1+ε2 = {eps:g} m of {_geom_name(model, a)} ↔ "
                              f"{_geom_name(model, b)}: contacts will start before the surfaces touch", RuntimeWarning, stacklevel=2)
        ka, kb = slot_of[a], slot_of[b]
        if cfg.mode == "penalty":
            c = -1  # the hook writes no contact; forces.py applies the pair's force
        cap[ka * nman + kb] = cap[kb * nman + ka] = c
        off[ka * nman + kb] = off[kb * nman + ka] = o
        eps_pair[ka * nman + kb] = eps_pair[kb * nman + ka] = eps
        slots.add(registry._slot_of(model.geom_type[a], model.geom_type[b]))
        handle.pairs.append(PairInfo(_geom_name(model, a), _geom_name(model, b), (a, b), max(c, 0), o, eps, cfg.mode))
    prims = sorted({b for b, _ in prim_pairs})
    prim_of = {b: i for i, b in enumerate(prims)}
    gprim = np.full(model.ngeom, -1, np.int64)
    prim_tab = np.zeros((max(len(prims), 1), 4), np.float64)
    pcap = np.zeros(max(len(prims), 1) * nman, np.int64)
    poff = np.zeros(max(len(prims), 1) * nman, np.float64)
    for b, i in prim_of.items():
        gprim[b] = i
        prim_tab[i] = [model.geom_type[b], *model.geom_size[b]]
    for b, a in prim_pairs:
        c = _pair_cap(model, b, a, cfg)
        if c < 1:
            continue
        eps = handle.trees[_geom_name(model, a)].error_bound
        o = 0.0 if cfg.offset == "none" else gap[a] if cfg.offset == "mean" else float(cfg.offset)
        i, k = prim_of[b], slot_of[a]
        pcap[i * nman + k] = c
        poff[i * nman + k] = o
        slots.add(registry._slot_of(model.geom_type[b], model.geom_type[a]))
        handle.primitive_pairs.append(PairInfo(_geom_name(model, b), _geom_name(model, a), (b, a), c, o, eps))
    pen, cpl, pair_index = _force_tables(model, cfg, handle, slot_of, nman)
    if not handle.pairs and not handle.primitive_pairs and not len(cpl):
        return handle

    cmax = int(max(cap.max(), pcap.max(), 1))
    need = int(max(hook.scratch_bytes(ns, int(cfg.candidates), cmax), hook.prim_scratch_bytes(ns, int(cfg.candidates), cmax),
                   forces.scratch_bytes(ns, int(cfg.candidates)))) + 65536
    if model.narena < 8 * need:
        raise ConfigError(
            f"the model's arena ({model.narena} bytes) is too small for the IST scratch ({need} bytes per pair call): "
            f"raise it with <size memory=\"{max(16, 8 * need // (1 << 20) + 1)}M\"/>"
        )
    off_d = abi.data_offsets()
    abi.verify_offsets(mujoco.MjData(model), off_d)
    S = int(cfg.state_slots)
    arrays = {
        "gslot": gslot, "cap": cap, "trees": tree_tab, "offset": off, "eps": eps_pair, "packed": packed,
        "keys": np.zeros(S, np.int64), "istate": np.zeros(S * hook.IW, np.int64),
        "fstate": np.zeros(S * hook.FW, np.float64), "counters": np.zeros(hook.N_COUNT, np.int64),
        "gprim": gprim, "prim": prim_tab, "pcap": pcap, "poff": poff,
        "pen": np.ascontiguousarray(pen if len(pen) else np.zeros((1, forces.PEN_W))),
        "cpl": np.ascontiguousarray(cpl if len(cpl) else np.zeros((1, forces.CPL_W))),
        "pout": np.zeros((S, forces.PO), np.float64),
    }
    entry = registry.ModelEntry(model, arrays, slots)
    E = entry.words
    E[hook.E_NGEOM] = model.ngeom
    E[hook.E_GSLOT] = gslot.ctypes.data
    E[hook.E_NMAN] = nman
    E[hook.E_CAP] = cap.ctypes.data
    E[hook.E_TREES] = tree_tab.ctypes.data
    E[hook.E_OFFSET] = off.ctypes.data
    E[hook.E_XPOS] = off_d["geom_xpos"]
    E[hook.E_XMAT] = off_d["geom_xmat"]
    E[hook.E_ALLOC] = abi.fn_address("mj_stackAllocByte")
    E[hook.E_MARK] = abi.fn_address("mj_markStack")
    E[hook.E_FREE] = abi.fn_address("mj_freeStack")
    E[hook.E_KEYS] = arrays["keys"].ctypes.data
    E[hook.E_NSLOT] = S
    E[hook.E_ISTATE] = arrays["istate"].ctypes.data
    E[hook.E_FSTATE] = arrays["fstate"].ctypes.data
    E[hook.E_STACK] = ns
    E[hook.E_NCAND] = int(cfg.candidates)
    E[hook.E_SPLIT] = int(cfg.split_depth)
    E[hook.E_SKIP] = int(bool(cfg.skip))
    E[hook.E_COUNT] = arrays["counters"].ctypes.data
    E[hook.E_NARENA] = off_d["narena"]
    E[hook.E_PSTACK] = off_d["pstack"]
    E[hook.E_PARENA] = off_d["parena"]
    E[hook.E_POOL] = off_d["threadpool"]
    E[hook.E_TIME] = off_d["time"]
    E[hook.E_EPS] = eps_pair.ctypes.data
    E[hook.E_GPRIM] = gprim.ctypes.data
    E[hook.E_NPRIM] = len(prims)
    E[hook.E_PRIM] = prim_tab.ctypes.data
    E[hook.E_PCAP] = pcap.ctypes.data
    E[hook.E_POFF] = poff.ctypes.data
    E[hook.E_NUP] = PENALTY_NORMAL_CLIMB if cfg.mode == "penalty" else 0
    E[forces.E_NPEN] = len(pen)
    E[forces.E_PEN] = arrays["pen"].ctypes.data
    E[forces.E_NCPL] = len(cpl)
    E[forces.E_CPL] = arrays["cpl"].ctypes.data
    E[forces.E_POUT] = arrays["pout"].ctypes.data
    E[forces.E_APPLYFT] = abi.fn_address("mj_applyFT")
    E[forces.E_OBJVEL] = abi.fn_address("mj_objectVelocity")
    E[forces.E_QFRCP] = off_d["qfrc_passive"]
    E[forces.E_BXPOS] = off_d["xpos"]
    E[forces.E_BXQUAT] = off_d["xquat"]
    E[forces.E_BXIPOS] = off_d["xipos"]
    E[forces.E_MOCPOS] = off_d["mocap_pos"]
    E[forces.E_MOCQUAT] = off_d["mocap_quat"]
    E[forces.E_NBODY] = model.nbody
    E[forces.E_NMOCAP] = model.nmocap
    E[forces.E_DT_NS] = int(round(model.opt.timestep * 1e9))
    entry.passive = bool(len(pen) or len(cpl))
    entry.pair_index = pair_index
    registry.add(entry)
    handle._entry = entry
    return handle


def _pair_cap(model, g1: int, g2: int, cfg: Config) -> int:
    """Contacts a pair may write: MuJoCo's buffer for it (with and without margin), then the setting."""
    c = min(mujoco.mj_maxContact(model, g1, g2, 0), mujoco.mj_maxContact(model, g1, g2, 1))
    return c if cfg.contacts is None else min(c, int(cfg.contacts))


def _effective_mass(model, body: int, geom: int) -> float:
    """Smallest mass a point push anywhere on ``geom`` sees on ``body`` (translation + rotation)."""
    m = float(model.body_subtreemass[body])
    inertia = float(model.body_inertia[body].min())
    r = float(model.geom_rbound[geom]) + float(np.linalg.norm(model.geom_pos[geom] - model.body_ipos[body]))
    return 1.0 / (1.0 / m + r * r / max(inertia, 1e-30))


def _force_tables(model, cfg: Config, handle: Handle, slot_of: dict, nman: int):
    """Rows of ``mjist.forces``: penalty pairs and the virtual coupling (validated)."""
    from . import forces

    dt = float(model.opt.timestep)
    pen, pair_index = [], {}
    for p in handle.pairs:
        a, b = p.ids
        ka, kb = slot_of[a], slot_of[b]
        pair_index[p.ids] = ka * nman + kb
        if p.mode != "penalty":
            continue
        body = [int(model.geom_bodyid[g]) if model.body_weldid[model.geom_bodyid[g]] != 0 else -1 for g in (a, b)]
        if body[1] < 0:  # forces act on geom2's body: make it the movable one
            a, b, body = b, a, body[::-1]
            pair_index[p.ids] = kb * nman + ka
        if body[1] < 0:
            continue
        k = cfg.stiffness if cfg.stiffness is not None else DEFAULT_STIFFNESS[cfg.penalty]
        c = cfg.damping if cfg.damping is not None else HUNT_CROSSLEY_ALPHA * k
        law = forces.CONTACTS if cfg.penalty == "contacts" else forces.VOLUME
        groups = forces.PEN_CAP if cfg.contacts is None else min(int(cfg.contacts), forces.PEN_CAP)
        # the contact stiffness budget: a push at a point r from the centre of mass moves it
        # like a mass 1/(1/m + r²/I); explicit steps are stable below 4 m_eff/dt², keep 4x margin
        m_eff = _effective_mass(model, body[1], b)
        kmax = m_eff / (dt * dt)
        pen.append([pair_index[p.ids], a, b, body[0], body[1], law, k, c, kmax, groups])
        if law == forces.CONTACTS and k > kmax:
            warnings.warn(f"mjist_stiffness {k:g} N/m per contact group on {_geom_name(model, b)!r} (effective mass {m_eff:.3g} kg "
                          f"at dt = {dt:g} s) leaves no stability margin: explicit steps are stable while (groups in contact)"
                          f" × k < {4 * kmax:.3g} N/m; lower it or the timestep", RuntimeWarning, stacklevel=3)
    cpl = []
    if cfg.coupling is not None:
        hname, bname = str(cfg.coupling).split()
        h = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, hname)
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, bname)
        if h < 0 or model.body_mocapid[h] < 0:
            raise ConfigError(f"mjist_coupling: {hname!r} must be a mocap body (<body name={hname!r} mocap=\"true\">), the device handle")
        if b < 0 or model.body_weldid[b] == 0:
            raise ConfigError(f"mjist_coupling: {bname!r} must be a movable body of the model (e.g. with a <freejoint/>)")
        mass = float(model.body_subtreemass[b])
        inertia = float(model.body_inertia[b].min())
        kt, ct, kr, cr = DEFAULT_COUPLING if cfg.coupling_gains is None else [float(x) for x in np.ravel(cfg.coupling_gains)]
        ct = 2.0 * math.sqrt(kt * mass) if ct is None else ct  # critical damping
        cr = 2.0 * math.sqrt(kr * inertia) if cr is None else cr
        # explicit spring–damper on a mass: stable for k·dt²/m < 4 and c·dt/m < 2; keep a 4x margin
        for what, kk, cc, mm, unit in (("translational", kt, ct, mass, "kg"), ("rotational", kr, cr, inertia, "kg·m²")):
            if kk * dt * dt / mm > 1.0 or cc * dt / mm > 0.5:
                raise ConfigError(
                    f"mjist_coupling_gains: the {what} coupling (k {kk:g}, c {cc:g}) on {bname!r} ({mm:g} {unit}) is unstable at "
                    f"dt = {dt:g} s: keep k ≤ {mm / dt / dt:g} and c ≤ {0.5 * mm / dt:g}, or lower the timestep")
        cpl.append([int(model.body_mocapid[h]), b, kt, ct, kr, cr, *model.body_ipos[b], 0.0])
    return np.array(pen, np.float64).reshape(-1, forces.PEN_W), np.array(cpl, np.float64).reshape(-1, forces.CPL_W), pair_index


def _warn_primitive_pairs(model, wanted: list[int], ist: bool) -> None:
    """Say which IST geom ↔ primitive pairs keep MuJoCo's convex-hull contacts."""
    prim = (abi.GEOM_SPHERE, abi.GEOM_CAPSULE, abi.GEOM_BOX, int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_ELLIPSOID))
    hits = []
    for a in wanted:
        for b in range(model.ngeom):
            t = model.geom_type[b]
            if t not in prim or not can_collide(model, a, b):
                continue
            if ist and t in cp.TYPES and model.geom_type[a] == abi.GEOM_MESH:
                continue  # answered by the leaf spheres
            hits.append(f"{_geom_name(model, a)} ↔ {_geom_name(model, b)}")
    if hits:
        why = ("ellipsoids and sdf-type geoms keep MuJoCo's native contacts" if ist
               else "mjist_primitives='native'")
        warnings.warn(
            f"these pairs use MuJoCo's native contacts, which treat the mesh as its convex hull ({why}; exact only "
            "where the primitive meets the hull's surface; planes and height fields are exact): " + ", ".join(hits[:8])
            + (" ..." if len(hits) > 8 else ""), RuntimeWarning, stacklevel=3)


def load_model(path, *, sdf_octree_depth: int | None = SDF_OCTREE_DEPTH, **kwargs) -> tuple[mujoco.MjModel, Handle]:
    """Compile an MJCF file and attach the IST: ``(model, handle)``.

    Mesh-backed ``sdf`` geoms get a minimal native octree (``sdf_octree_depth``) because the
    IST answers their pairs; pairs it does not manage would use that coarse octree.
    Keyword arguments go to ``attach``.
    """
    import os

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"MJCF file {path!r} does not exist")
    spec = mujoco.MjSpec.from_file(path)
    if sdf_octree_depth is not None:
        sdf_meshes = {g.meshname for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_SDF and g.meshname}
        for mesh in spec.meshes:
            if mesh.name in sdf_meshes and hasattr(mesh, "octree_maxdepth"):
                mesh.octree_maxdepth = int(sdf_octree_depth)
    model = spec.compile()
    return model, attach(model, **kwargs)
