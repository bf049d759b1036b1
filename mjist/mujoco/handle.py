"""``Handle``: an attached model, its trees and managed pairs, the hook's counters and outputs."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import mujoco
import numpy as np

from . import layout
from .config import Config


@dataclass
class PairInfo:
    """One IST-managed geom pair."""

    geom1: str
    geom2: str
    ids: tuple[int, int]
    cap: int  # contacts written at most (≤ mj_maxContact)
    offset: float  # subtracted from the IST distance (metres)
    error_bound: float  # ε_1 + ε_2
    mode: str = "constraint"  # or "penalty": forces from mjist.mujoco.forces, no MuJoCo contact

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
    surfaces: dict[str, object] = field(default_factory=dict)  # mjist_narrowphase surface: geometry.surface.Surface by geom
    surface_seconds: float = 0.0  # building them
    exit_seconds: float = 0.0  # the leaves' exit directions (deep contacts' normals), surfaces included
    _entry: object = None

    @property
    def attached(self) -> bool:
        from . import registry

        return self._entry is not None and registry.is_attached(self._entry)

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
        if self._entry is None:
            return {}
        c = self._entry.counters
        return {name: int(c[i]) for i, name in enumerate(layout.COUNTER_NAMES)}

    def output_rows(self, data) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Live views of the first penalty pair's and the coupling's output rows for ``data``
        (``layout.O_*``; ``None`` until the first step of ``data`` wrote them).

        They update in place at every step of this ``data``: a device loop reads forces without
        Python per step.
        """
        pen = [p for p in self.pairs if p.mode == "penalty"]
        nman = len(self.trees)
        pair = self._row(data, self._entry.pair_index[pen[0].ids]) if pen and self._entry is not None else None
        has_coupling = self._entry is not None and self._entry.words[layout.Entry.NCPL] > 0
        return pair, (self._row(data, nman * nman) if has_coupling else None)

    def _row(self, data, pk: int):
        keys = self._entry.arrays["keys"]
        hit = np.flatnonzero(keys == layout.slot_key_py(data._address, pk))
        return self._entry.arrays["pout"][hit[0]] if hit.size else None

    def haptic(self, data) -> dict:
        """Last wrenches ``mjist.mujoco.forces`` applied for ``data``: per penalty pair and per coupling.

        Pairs: ``force``/``torque`` on geom2's body (world, torque about its centre of mass),
        ``contacts`` (contact groups, or overlapping leaf pairs for the volume law), ``depth``
        (deepest, metres), ``volume`` (m³). Couplings: ``force`` at the body's origin and
        ``torque`` on the body (the device displays their opposite).
        """
        L = layout
        out = {"pairs": {}, "coupling": None, "time": float(data.time)}
        if self._entry is None:
            return out
        for p in self.pairs:
            if p.mode != "penalty":
                continue
            r = self._row(data, self._entry.pair_index[p.ids])
            if r is not None:
                out["pairs"][f"{p.geom1}/{p.geom2}"] = {
                    "force": r[L.O_F:L.O_F + 3].copy(), "torque": r[L.O_T:L.O_T + 3].copy(),
                    "contacts": int(r[L.O_N]), "depth": float(r[L.O_DEPTH]), "volume": float(r[L.O_VOL])}
        if self._entry.words[L.Entry.NCPL]:
            r = self._row(data, len(self.trees) ** 2)
            if r is not None:
                out["coupling"] = {"force": r[L.O_F:L.O_F + 3].copy(), "torque": r[L.O_T:L.O_T + 3].copy()}
        return out

    def forget(self, data) -> None:
        """Forget the coherence and device state kept for ``data`` (e.g. a new MjData that may sit
        at the address of a freed one, at the same time: a reset to an earlier time is seen).
        Sphere contacts never depend on it; surface contacts held from a pose within
        ``mjist_surface_hold`` and the side of approach of deep ones do, and the coupling's
        handle-velocity estimate does for one step."""
        if self._entry is not None:
            keys = self._entry.arrays["keys"]
            mine = np.flatnonzero((keys & layout.KEY_DATA_MASK) == int(data._address))
            # keys stay (open addressing); a slot whose time is +inf reads as fresh at its next use
            self._entry.arrays["fstate"].reshape(-1, layout.FW)[mine, layout.F_TIME] = np.inf

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
