"""A first run's compile of the collision cfunc, on two cores.

numba compiles under one global lock, so a process compiles one kernel at a time. The collision
body ``hook.collide`` calls two large kernels that share few callees: ``pair_distance`` (distance
requests) and ``pair_contacts`` (contacts); together they are nearly all of a first run's
compile. When ``pair_contacts`` is not in numba's on-disk cache, ``attach`` calls ``start``
before it loads the trees: a child process compiles ``pair_contacts`` into that cache meanwhile.
When the slot's cfunc is compiled, ``compile_split`` compiles ``pair_distance`` and the
primitive path in this process and waits for the child; the cfunc then loads the child's
kernels from the cache instead of compiling them. The compiled code is the same either way; only
the wall time of a first run changes (BENCHMARKS.md, "A new user's first run").

A process starts at most one child: where numba cannot keep a cache, a second would compile for
nothing. Nothing here can fail a run: a child that cannot start, fails or takes longer than
``CHILD_TIMEOUT_S`` leaves its kernels to this process, which compiles them as it would have.
"""
from __future__ import annotations

import atexit
import subprocess
import sys

from numba import types

CHILD_TIMEOUT_S = 900.0  # the child's compile takes about a minute on a slow core; past this it is stuck
# the argument types ``hook.collide`` calls its kernels with (its typing decides them: the entry
# words as a C array, pointers as int64, geom ids int32; ``pair_contacts``' ``soft`` is the literal
# False there). A test checks that a compiled ``collide`` holds exactly these signatures.
_E = types.Array(types.int64, 1, "C")
_I, _G, _F = types.int64, types.int32, types.float64
DISTANCE_SIG = (_E, _I, _I, _G, _G, _F, _I, _I, _I)
CONTACTS_SIG = (_E, _I, _I, _I, _G, _G, _F, _I, _I, _I, types.literal(False))
PRIMITIVE_SIG = (_E, _I, _I, _G, _G, _I, _I, _F)


def cached(py_func, sig) -> bool:
    """Whether numba's on-disk cache holds ``py_func`` compiled for ``sig`` on this machine."""
    from numba.core.caching import FunctionCache
    from numba.core.registry import cpu_target

    try:
        cache = FunctionCache(py_func)
        key = cache._index_key(sig, cpu_target.target_context.codegen())
        return key in cache._cache_file._load_index()
    except Exception:  # a cache numba cannot read is a cache miss
        return False


_CHILD: dict = {}  # "process": the running child of ``start``; "started": whether one ever ran here


def start() -> None:
    """Start the child when a collision cfunc will compile from nothing (nothing of
    ``pair_contacts`` in numba's cache), so it compiles while this process loads trees."""
    from . import hook

    if _CHILD.get("started") or hook._CFUNCS or cached(hook.pair_contacts.py_func, CONTACTS_SIG):
        return
    _CHILD["started"] = True
    try:
        _CHILD["process"] = subprocess.Popen([sys.executable, "-c", "from mjist.mujoco import prewarm; prewarm.child()"],
                                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                             stderr=subprocess.DEVNULL)
    except OSError:  # no interpreter to start: this process compiles everything
        return
    atexit.register(_stop)


def compile_split(cfunc_body, cfunc_sig) -> bool:
    """Before the cfunc of ``cfunc_body`` compiles: when it would compile from nothing, compile
    ``pair_distance`` here while the child (``start``, started now if it was not) compiles the
    rest, and wait for it. True when a child was used."""
    from . import hook

    if cached(cfunc_body, cfunc_sig):  # the cfunc loads whole: no kernel of its compiles
        _stop()
        return False
    start()
    child = _CHILD.get("process")
    if child is None:
        return False
    try:
        hook.pair_distance.compile(DISTANCE_SIG)
        hook._collide_prim.compile(PRIMITIVE_SIG)
        child.wait(timeout=CHILD_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pass
    finally:
        _stop()
    return True


def _stop() -> None:
    child = _CHILD.pop("process", None)
    if child is not None and child.poll() is None:
        child.kill()
        child.wait()


def child() -> None:
    """The child's half, ``pair_contacts``, into numba's cache."""
    from . import hook

    hook.pair_contacts.compile(CONTACTS_SIG)
