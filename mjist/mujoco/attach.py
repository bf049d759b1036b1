"""Plug IST contacts into MuJoCo: ``mjist.attach(model)`` and ``mjist.load_model(path)``.

After attaching, an unmodified ``mujoco.mj_step`` loop, ``mujoco.viewer`` and
``mujoco.rollout`` get IST contacts for the managed geom pairs; the work happens in the
numba cfuncs of ``mjist.hook`` with no Python in the step.

Settings: ``mjist.mujoco.config``; what the model holds: ``scene``; the attached model:
``handle``; the words the cfuncs read: ``layout``.
"""
from __future__ import annotations

import math
import time
import warnings

import mujoco
import numpy as np

from ..errors import ConfigError
from ..geometry import sdfgrid
from ..query import primitive as cp
from . import abi, layout, prewarm
from .config import (
    DEFAULT_COUPLING,
    DEFAULT_STIFFNESS,
    HUNT_CROSSLEY_ALPHA,
    PENALTY_NORMAL_CLIMB,
    SDF_OCTREE_DEPTH,
    SURFACE_HOLD,
    Config,
    read_config,
)
from .handle import Handle, PairInfo
from .scene import can_collide, geom_name, managed_geoms, mesh_of, warn_primitive_pairs


def _mean_gap(tree, V, F) -> float:
    g = tree.info.get("mean_gap")
    if g is None:
        from ..builder.bound import surface_gaps

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
        ``mjist.mujoco.scene.mesh_of(model, g)``); others are built or loaded from the cache.
    cache_dir : path, optional
        Tree cache folder (default ``$MJIST_CACHE`` or ``~/.cache/mjist``).
    progress : bool
        Progress bars while building trees.
    **settings
        Override the MJCF ``<custom>`` settings: ``geoms``, ``max_error``, ``contacts``,
        ``offset``, ``mode``, ``split_depth``, ``skip``, ``state_slots``, ``candidates``,
        ``narrowphase``.

    Returns
    -------
    Handle
        ``.detach()``, ``.pairs``, ``.trees``, ``.stats()``. A model with no managed pair
        installs nothing.

    Raises
    ------
    ConfigError
        Invalid settings (unknown key, a geom that is not a mesh, ...).
    mjist.mujoco.abi.MuJoCoABIError
        MuJoCo version or struct layout not the verified one.
    """
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
    warn_primitive_pairs(model, wanted, cfg.primitives == "ist")
    if not pairs and not prim_pairs and cfg.coupling is None:
        return handle
    used = sorted({g for p in pairs for g in p} | {a for _, a in prim_pairs})
    if len(used) > layout.MAX_GEOMS:
        raise ConfigError(f"{len(used)} IST geoms can meet: at most {layout.MAX_GEOMS} are supported per model "
                          "(use mjist_geoms to pick)")
    prewarm.start()  # a first run: the collision kernels compile on another core while the trees load
    gap = _load_trees(model, cfg, handle, used, trees, cache_dir, progress)
    slot_of = {g: k for k, g in enumerate(used)}
    arrays, slots = _tree_tables(model, handle, slot_of, cache_dir)
    _surface_tables(model, cfg, handle, slot_of, arrays, cache_dir)
    slots |= _pair_tables(model, cfg, handle, pairs, slot_of, gap, arrays)
    slots |= _primitive_tables(model, cfg, handle, prim_pairs, slot_of, gap, arrays)
    pen, cpl, pair_index = _force_tables(model, cfg, handle, slot_of, len(used))
    if not handle.pairs and not handle.primitive_pairs and not len(cpl):
        return handle
    _install(model, cfg, handle, arrays, slots, pen, cpl, pair_index)
    return handle


def _build_params(cfg: Config) -> dict:
    """``mjist.build`` arguments of a model's trees (with the mesh, the tree cache's key)."""
    return {"max_error": cfg.max_error, "branching": int(cfg.branching), "seed": int(cfg.seed)}


def geom_tree(model: mujoco.MjModel, geom: str, *, cache_dir=None, progress: bool = False):
    """The tree ``attach`` gives geom ``geom`` of ``model``, loaded from the cache or built into it.

    Lets a tree be built ahead, e.g. in another process (``mjist.cohort`` builds a pair's two trees
    in parallel); a later ``attach`` with the same ``cache_dir`` finds it. Returns ``(tree, hit)``.
    """
    from ..cache import cached_tree

    g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
    if g < 0:
        raise ConfigError(f"geom_tree: the model has no geom named {geom!r}")
    V, F = mesh_of(model, g)
    return cached_tree(V, F, _build_params(read_config(model)), folder=cache_dir, progress=progress, name=geom)


def _load_trees(model, cfg: Config, handle: Handle, used: list[int], trees, cache_dir, progress) -> dict[int, float]:
    """Trees of the managed geoms into ``handle`` (given, cached or built); each geom's mean surface gap."""
    from ..cache import cached_tree

    params = _build_params(cfg)
    trees = dict(trees or {})
    t0 = time.perf_counter()
    gap = {}
    by_mesh = {}  # geoms sharing a mesh share its tree
    for g in used:
        name = geom_name(model, g)
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
    return gap


def _tree_tables(model, handle: Handle, slot_of: dict, cache_dir=None) -> tuple[dict, set]:
    """The packed trees, their exit directions (cached beside the trees) and the per-geom index
    the cfuncs read; the traversal stack they need. The meshes packed for exact distances
    (``by_mesh``, built when the exits or the surface narrow phase need them) are kept for the
    surface narrow phase."""
    from ..cache import cached_exits
    from ..geometry.surface import build_surface
    from ..query.traverse import exit_directions, pack, stack_size

    nman = len(slot_of)
    gslot = np.full(model.ngeom, -1, np.int64)
    packed, exits, by_mesh = [], [], {}
    tree_tab = np.zeros(3 * nman, np.int64)
    t0 = time.perf_counter()
    for g, k in slot_of.items():
        gslot[g] = k
        N = pack(handle.trees[geom_name(model, g)])
        mid = int(model.geom_dataid[g])
        V, F = mesh_of(model, g)

        def surface(mid=mid, V=V, F=F):
            if mid not in by_mesh:
                by_mesh[mid] = build_surface(V, F)
            return by_mesh[mid]

        X = cached_exits(N, V, F, lambda N=N: exit_directions(N, surface()), folder=cache_dir)
        packed.append(N)
        exits.append(X)
        tree_tab[3 * k] = N.ctypes.data
        tree_tab[3 * k + 1] = N.shape[0]
        tree_tab[3 * k + 2] = X.ctypes.data
    handle.exit_seconds = time.perf_counter() - t0
    ns = max([stack_size(a, b) for a in packed for b in packed] + [stack_size(a) for a in packed] + [2])
    arrays = {"gslot": gslot, "trees": tree_tab, "packed": packed, "exits": exits, "by_mesh": by_mesh, "stack": ns,
              "cap": np.zeros(nman * nman, np.int64), "offset": np.zeros(nman * nman, np.float64),
              "eps": np.zeros(nman * nman, np.float64), "hold": np.zeros(nman * nman, np.float64)}
    return arrays, set()


def _surface_tables(model, cfg: Config, handle: Handle, slot_of: dict, arrays: dict, cache_dir=None) -> None:
    """With ``mjist_narrowphase='surface'``: each managed mesh packed for the surface narrow phase
    (``geometry.surface``, shared by geoms of one mesh) and the per-geom table the cfuncs read."""
    nman = len(slot_of)
    tab = np.zeros(layout.SURF_W * max(nman, 1), np.int64)
    by_mesh = arrays.pop("by_mesh")  # built for exit directions not in the cache; kept only when measured on
    arrays.update(surf=tab, surfaces=[])
    if cfg.narrowphase != "surface":
        return
    from ..cache import cached_grid
    from ..geometry.surface import add_grid, build_surface

    t0 = time.perf_counter()
    for g in slot_of:
        mid = int(model.geom_dataid[g])
        if mid not in by_mesh:
            by_mesh[mid] = build_surface(*mesh_of(model, g))
        s = by_mesh[mid]
        if s.grid_spacing == 0.0:
            V, F = mesh_of(model, g)
            s.grid = cached_grid(V, F, lambda s=s: add_grid(s).grid, folder=cache_dir)
    for g, k in slot_of.items():
        s = by_mesh[int(model.geom_dataid[g])]
        handle.surfaces[geom_name(model, g)] = s
        gh, gt, gv = s.grid
        tab[layout.SURF_W * k:layout.SURF_W * (k + 1)] = [s.floats.ctypes.data, s.ints.ctypes.data, *s.sizes, gh.ctypes.data,
                                                gt.ctypes.data, gv.ctypes.data, gv.size // sdfgrid.NODES]
    arrays["surfaces"] = list(by_mesh.values())  # kept alive with the entry
    handle.surface_seconds = time.perf_counter() - t0


def _pair_offset(cfg: Config, gap: float, eps: float, what: str) -> float:
    """The distance subtracted from the pair's IST distance (``mjist_offset``)."""
    if cfg.offset == "none":
        return 0.0
    if cfg.offset == "mean":
        return gap
    o = float(cfg.offset)
    if o > eps:
        warnings.warn(f"mjist_offset {o:g} m exceeds the bound {eps:g} m of {what}: contacts will start before the "
                      "surfaces touch", RuntimeWarning, stacklevel=4)
    return o


def _pair_tables(model, cfg: Config, handle: Handle, pairs, slot_of: dict, gap: dict, arrays: dict) -> set:
    """Cap, offset and ε of each mesh–mesh pair into ``arrays``; returns the table slots they use."""
    from . import registry

    nman = len(slot_of)
    cap, off, eps_pair, hold = arrays["cap"], arrays["offset"], arrays["eps"], arrays["hold"]
    slots = set()
    for a, b in pairs:
        c = _pair_cap(model, a, b, cfg)
        if c < 1:
            continue
        eps = handle.trees[geom_name(model, a)].error_bound + handle.trees[geom_name(model, b)].error_bound
        o = 0.0 if cfg.narrowphase == "surface" else _pair_offset(cfg, gap[a] + gap[b], eps,
                                                                 f"{geom_name(model, a)} ↔ {geom_name(model, b)} (ε1+ε2)")
        ka, kb = slot_of[a], slot_of[b]
        if cfg.mode == "penalty":
            c = -1  # the hook writes no contact; forces.py applies the pair's force
        cap[ka * nman + kb] = cap[kb * nman + ka] = c
        off[ka * nman + kb] = off[kb * nman + ka] = o
        eps_pair[ka * nman + kb] = eps_pair[kb * nman + ka] = eps
        if cfg.narrowphase == "surface" and 0 < c <= layout.KP:
            h = SURFACE_HOLD * eps if cfg.surface_hold is None else cfg.surface_hold
            hold[ka * nman + kb] = hold[kb * nman + ka] = h
        slots.add(registry.slot_of(model.geom_type[a], model.geom_type[b]))
        handle.pairs.append(PairInfo(geom_name(model, a), geom_name(model, b), (a, b), max(c, 0), o, eps, cfg.mode))
    return slots


def _primitive_tables(model, cfg: Config, handle: Handle, prim_pairs, slot_of: dict, gap: dict, arrays: dict) -> set:
    """The primitives' table, per-geom index, caps and offsets into ``arrays``; returns the table slots."""
    from . import registry

    nman = len(slot_of)
    prims = sorted({b for b, _ in prim_pairs})
    prim_of = {b: i for i, b in enumerate(prims)}
    gprim = np.full(model.ngeom, -1, np.int64)
    prim_tab = np.zeros((max(len(prims), 1), 4), np.float64)
    pcap = np.zeros(max(len(prims), 1) * nman, np.int64)
    poff = np.zeros(max(len(prims), 1) * nman, np.float64)
    for b, i in prim_of.items():
        gprim[b] = i
        prim_tab[i] = [model.geom_type[b], *model.geom_size[b]]
    slots = set()
    for b, a in prim_pairs:
        c = _pair_cap(model, b, a, cfg)
        if c < 1:
            continue
        eps = handle.trees[geom_name(model, a)].error_bound
        o = 0.0 if cfg.offset == "none" else gap[a] if cfg.offset == "mean" else float(cfg.offset)
        i, k = prim_of[b], slot_of[a]
        pcap[i * nman + k] = c
        poff[i * nman + k] = o
        slots.add(registry.slot_of(model.geom_type[b], model.geom_type[a]))
        handle.primitive_pairs.append(PairInfo(geom_name(model, b), geom_name(model, a), (b, a), c, o, eps))
    arrays.update(gprim=gprim, prim=prim_tab, pcap=pcap, poff=poff, nprim=len(prims))
    return slots


def _install(model, cfg: Config, handle: Handle, arrays: dict, slots: set, pen, cpl, pair_index) -> None:
    """Check the scratch fits MuJoCo's arena, write the model's entry words and register it."""
    from . import registry

    ns, nc = arrays["stack"], int(cfg.candidates)
    cmax = int(max(arrays["cap"].max(), arrays["pcap"].max(), 1))
    need = layout.scratch_bytes(ns, nc, cmax)
    if model.narena < 8 * need:
        raise ConfigError(
            f"the model's arena ({model.narena} bytes) is too small for the IST scratch ({need} bytes per pair call): "
            f"raise it with <size memory=\"{max(16, 8 * need // (1 << 20) + 1)}M\"/>"
        )
    off_d = abi.data_offsets()
    abi.verify_offsets(mujoco.MjData(model), off_d)
    S = int(cfg.state_slots)
    arrays.update({
        "keys": np.zeros(S, np.int64), "istate": np.zeros(S * layout.IW, np.int64),
        "fstate": np.zeros(S * layout.FW, np.float64), "counters": np.zeros(layout.N_COUNT, np.int64),
        "pen": np.ascontiguousarray(pen if len(pen) else np.zeros((1, layout.PEN_W))),
        "cpl": np.ascontiguousarray(cpl if len(cpl) else np.zeros((1, layout.CPL_W))),
        "pout": np.zeros((S, layout.PO), np.float64),
    })
    entry = registry.ModelEntry(model, arrays, slots)
    _write_words(entry.words, model, cfg, arrays, off_d, len(pen), len(cpl))
    entry.passive = bool(len(pen) or len(cpl))
    entry.pair_index = pair_index
    registry.add(entry)
    handle._entry = entry


def _write_words(E, model, cfg: Config, arrays: dict, off_d: dict, npen: int, ncpl: int) -> None:
    """The model entry the cfuncs read (``layout.Entry``)."""
    L = layout
    addr = {L.Entry.GSLOT: "gslot", L.Entry.CAP: "cap", L.Entry.TREES: "trees", L.Entry.OFFSET: "offset", L.Entry.KEYS: "keys",
            L.Entry.ISTATE: "istate", L.Entry.FSTATE: "fstate", L.Entry.COUNT: "counters", L.Entry.EPS: "eps", L.Entry.HOLD: "hold", L.Entry.GPRIM: "gprim",
            L.Entry.PRIM: "prim", L.Entry.PCAP: "pcap", L.Entry.POFF: "poff", L.Entry.PEN: "pen", L.Entry.CPL: "cpl", L.Entry.POUT: "pout",
            L.Entry.SURF: "surf"}
    for word, name in addr.items():
        E[word] = arrays[name].ctypes.data
    data_field = {L.Entry.XPOS: "geom_xpos", L.Entry.XMAT: "geom_xmat", L.Entry.NARENA: "narena", L.Entry.PSTACK: "pstack",
                  L.Entry.PARENA: "parena", L.Entry.POOL: "threadpool", L.Entry.TIME: "time", L.Entry.QFRCP: "qfrc_passive",
                  L.Entry.BXPOS: "xpos", L.Entry.BXQUAT: "xquat", L.Entry.BXIPOS: "xipos", L.Entry.MOCPOS: "mocap_pos",
                  L.Entry.MOCQUAT: "mocap_quat"}
    for word, name in data_field.items():
        E[word] = off_d[name]
    functions = {L.Entry.ALLOC: "mj_stackAllocByte", L.Entry.MARK: "mj_markStack", L.Entry.FREE: "mj_freeStack",
                 L.Entry.APPLYFT: "mj_applyFT", L.Entry.OBJVEL: "mj_objectVelocity"}
    for word, name in functions.items():
        E[word] = abi.fn_address(name)
    E[L.Entry.NGEOM] = model.ngeom
    E[L.Entry.NMAN] = len(arrays["packed"])
    E[L.Entry.NSLOT] = int(cfg.state_slots)
    E[L.Entry.STACK] = arrays["stack"]
    E[L.Entry.NCAND] = int(cfg.candidates)
    E[L.Entry.SPLIT] = int(cfg.split_depth)
    E[L.Entry.SKIP] = int(bool(cfg.skip))
    E[L.Entry.NPRIM] = arrays["nprim"]
    E[L.Entry.NUP] = PENALTY_NORMAL_CLIMB if cfg.mode == "penalty" else 0
    E[L.Entry.NPEN] = npen
    E[L.Entry.NCPL] = ncpl
    E[L.Entry.NBODY] = model.nbody
    E[L.Entry.NMOCAP] = model.nmocap
    E[L.Entry.DT_NS] = int(round(model.opt.timestep * 1e9))
    E[L.Entry.NARROW] = int(cfg.surface_groups) if cfg.narrowphase == "surface" else 0


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
    """Rows of ``mjist.mujoco.forces``: penalty pairs and the virtual coupling (validated)."""
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
        groups = layout.PEN_CAP if cfg.contacts is None else min(int(cfg.contacts), layout.PEN_CAP)
        # the contact stiffness budget: a push at a point r from the centre of mass moves it
        # like a mass 1/(1/m + r²/I); explicit steps are stable below 4 m_eff/dt², keep 4x margin
        m_eff = _effective_mass(model, body[1], b)
        kmax = m_eff / (dt * dt)
        pen.append([pair_index[p.ids], a, b, body[0], body[1], law, k, c, kmax, groups])
        if law == forces.CONTACTS and k > kmax:
            warnings.warn(f"mjist_stiffness {k:g} N/m per contact group on {geom_name(model, b)!r} (effective mass {m_eff:.3g} kg "
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
        cpl.append([int(model.body_mocapid[h]), b, kt, ct, kr, cr, *model.body_ipos[b]])
    return np.array(pen, np.float64).reshape(-1, layout.PEN_W), np.array(cpl, np.float64).reshape(-1, layout.CPL_W), pair_index


def load_model(path, *, sdf_octree_depth: int | None = SDF_OCTREE_DEPTH, **kwargs) -> tuple[mujoco.MjModel, Handle]:
    """Compile an MJCF file and attach the IST: ``(model, handle)``.

    Mesh-backed ``sdf`` geoms get a minimal native octree (``sdf_octree_depth``) because the
    IST answers their pairs; pairs it does not manage would use that coarse octree. SDF plugin
    geoms keep theirs (and MuJoCo's collision, unless ``mjist_geoms`` names them).
    Keyword arguments go to ``attach``.
    """
    import os

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"MJCF file {path!r} does not exist")
    spec = mujoco.MjSpec.from_file(path)
    if sdf_octree_depth is not None:
        sdf_meshes = {g.meshname for g in spec.geoms
                      if g.type == mujoco.mjtGeom.mjGEOM_SDF and g.meshname and not g.plugin.active}
        for mesh in spec.meshes:
            if mesh.name in sdf_meshes and hasattr(mesh, "octree_maxdepth"):
                mesh.octree_maxdepth = int(sdf_octree_depth)
    model = spec.compile()
    return model, attach(model, **kwargs)
