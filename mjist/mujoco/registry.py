"""The process-wide registry the collision hook reads, and the collision-table slots.

MuJoCo's ``mjCOLLISIONFUNC`` is one global table, so the registry is global too: a root
array (original function of each taken-over slot, then ``(mjModel address, entry address)``
per attached model) whose address sits in the word the cfuncs read. Every change builds a
new root and publishes it with one aligned store, so a step running on another thread sees
either the old or the new registry, never a half-written one. Old arrays are kept alive for
the life of the process (a few hundred bytes each).
"""
from __future__ import annotations

import atexit
import threading

import numpy as np

from . import abi, hook
from .layout import ENTRY_WORDS, MAX_MODELS, ROOT_MODELS, ROOT_N, ROOT_ORIG, ROOT_PASSIVE, ROOT_WORDS, SLOTS

_LOCK = threading.Lock()
_ENTRIES: dict[int, "ModelEntry"] = {}  # mjModel address -> entry
_ORIGINAL: dict[int, int] = {}  # table index -> MuJoCo's own function (recorded before any change)
_INSTALLED: set[int] = set()  # slots currently holding our cfuncs
_KEEP: list = []  # every root ever published (readers may still hold one)
_PASSIVE = {"installed": False, "previous": 0}  # mjcb_passive: ours installed? what was there before


def slot_of(t1: int, t2: int) -> int:
    """Index in ``layout.SLOTS`` of the collision-table slot of geom types ``t1``, ``t2``."""
    key = (min(t1, t2), max(t1, t2))
    return SLOTS.index(key)


def _record_originals():
    """Remember MuJoCo's own slot functions (once per process, before we write any)."""
    if _ORIGINAL:
        return
    table = abi.collision_table()
    for t1, t2 in SLOTS:
        idx = abi.table_index(t1, t2)
        _ORIGINAL[idx] = int(table[idx] or 0)


class ModelEntry:
    """Arrays of one attached model (owned here so their memory outlives every step)."""

    def __init__(self, model, arrays: dict, slots: set[int]):
        self.model = model
        self.address = int(model._address)
        self.arrays = arrays
        self.slots = slots  # which table slots this model needs
        self.words = np.zeros(ENTRY_WORDS, np.int64)
        self.counters = arrays["counters"]
        self.passive = False  # needs the mjcb_passive callback (penalty pairs or a coupling)
        self.pair_index = {}  # (geom1, geom2) -> the pair's slot index p


def is_attached(entry: ModelEntry) -> bool:
    """Whether ``entry`` is in the registry the cfuncs read."""
    return _ENTRIES.get(entry.address) is entry


def _publish():
    root = np.zeros(ROOT_WORDS, np.int64)
    for s, (t1, t2) in enumerate(SLOTS):
        root[ROOT_ORIG + s] = _ORIGINAL.get(abi.table_index(t1, t2), 0)
    root[ROOT_PASSIVE] = _PASSIVE["previous"]
    entries = list(_ENTRIES.values())  # at most MAX_MODELS: add() refuses more
    for i, e in enumerate(entries):
        root[ROOT_MODELS + 2 * i] = e.address
        root[ROOT_MODELS + 2 * i + 1] = e.words.ctypes.data
    root[ROOT_N] = len(entries)
    _KEEP.append(root)
    abi.set_registry(root.ctypes.data)


def _sync_table():
    """Install our cfuncs in the slots some attached model needs; restore the others."""
    table = abi.collision_table()
    needed = set()
    for e in _ENTRIES.values():
        needed |= e.slots
    for s, (t1, t2) in enumerate(SLOTS):
        idx = abi.table_index(t1, t2)
        if s in needed and s not in _INSTALLED:
            table[idx] = hook.cfunc_address(t1, t2)
            _INSTALLED.add(s)
        elif s not in needed and s in _INSTALLED:
            table[idx] = _ORIGINAL[idx] or None
            _INSTALLED.discard(s)
    want = any(e.passive for e in _ENTRIES.values())
    if want == _PASSIVE["installed"]:
        return
    from . import forces

    cb = abi.passive_callback()
    ours = forces.passive().address
    if want:
        cb.value = ours
        _PASSIVE["installed"] = True
    else:
        if (cb.value or 0) == ours:  # someone who replaced ours keeps their callback
            cb.value = _PASSIVE["previous"] or None
        _PASSIVE["installed"] = False


def _capture_passive() -> None:
    """Remember the mjcb_passive in place before ours goes in (ours calls it first)."""
    from . import forces

    if not any(e.passive for e in _ENTRIES.values()):
        return
    cur = abi.passive_callback().value or 0
    if not _PASSIVE["installed"]:
        _PASSIVE["previous"] = 0 if cur == forces.passive().address else int(cur)
    elif cur != forces.passive().address:
        # someone replaced ours since (e.g. mujoco.set_mjcb_passive): chain theirs, put ours back
        _PASSIVE["previous"] = int(cur)
        _PASSIVE["installed"] = False


def passive_is_ours() -> bool:
    """Whether ``mjcb_passive`` still holds mjist's callback (a later ``mujoco.set_mjcb_passive`` replaces it)."""
    from . import forces

    return (abi.passive_callback().value or 0) == forces.passive().address


def check_slots(slots: set[int]) -> None:
    """Refuse when a slot holds a function that is neither MuJoCo's nor ours."""
    _record_originals()
    table = abi.collision_table()
    for s in slots:
        t1, t2 = SLOTS[s]
        idx = abi.table_index(t1, t2)
        cur = int(table[idx] or 0)
        if cur not in (_ORIGINAL[idx], hook.compiled_address(t1, t2)):
            raise RuntimeError(
                f"mjCOLLISIONFUNC[{t1}][{t2}] holds a function that is neither MuJoCo's nor mjist's "
                f"(0x{cur:x}): another library replaced it; detach that library first, mjist will not chain it"
            )


def add(entry: ModelEntry) -> None:
    with _LOCK:
        check_slots(entry.slots)
        if entry.address in _ENTRIES:
            raise RuntimeError("this MjModel is already attached: call handle.detach() first")
        if len(_ENTRIES) >= MAX_MODELS:  # checked before the entry joins: a refusal leaves the registry as it was
            raise RuntimeError(f"at most {MAX_MODELS} models can be attached at once: detach some first")
        _ENTRIES[entry.address] = entry
        _capture_passive()
        _publish()
        _sync_table()


def remove(entry: ModelEntry) -> None:
    with _LOCK:
        if _ENTRIES.get(entry.address) is not entry:
            return
        del _ENTRIES[entry.address]
        _sync_table()  # restore the table first, then drop the entry
        _publish()


def table_is_original() -> bool:
    """Every slot mjist may take over holds MuJoCo's own function."""
    table = abi.collision_table()
    _record_originals()
    return all(int(table[abi.table_index(t1, t2)] or 0) == _ORIGINAL[abi.table_index(t1, t2)] for t1, t2 in SLOTS)


@atexit.register
def _restore_at_exit():
    with _LOCK:
        _ENTRIES.clear()
        if _INSTALLED:
            _sync_table()
