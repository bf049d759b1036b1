"""On-disk cache of built trees, keyed by mesh content and build parameters.

A scene's second start loads its trees instead of rebuilding them. The key hashes the
vertex and face bytes (as MuJoCo compiled them), the build parameters, the builder version
and the tree format version, so any change of mesh, scale, parameters or builder builds a
new tree; a corrupt or foreign entry is rebuilt and overwritten.

Entries are looked up in the cache folder first, then in the read-only folders of
``prebuilt_folders`` (the bundled jaws' trees ship with the package, so a new user's first
``mjist demo`` loads them instead of compiling the builder and building them). A prebuilt
entry has the same key as a cached one, so it is only ever found for the very mesh, parameters
and builder it was made with.
"""
from __future__ import annotations

import hashlib
import json
import os
import warnings

import numpy as np

from .errors import TreeFileError
from .tree import FORMAT_VERSION, InnerSphereTree, load_tree


def cache_dir(path=None) -> str:
    """The cache folder: ``path``, else ``$MJIST_CACHE``, else ``$XDG_CACHE_HOME/mjist`` (``~/.cache/mjist``)."""
    if path is None:
        path = os.environ.get("MJIST_CACHE") or os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "mjist"
        )
    return os.fspath(path)


PREBUILT: list[str] | None = None  # None: ``prebuilt_folders``'s default; a list replaces it ([]: none)


def prebuilt_folders() -> list[str]:
    """Read-only folders searched after the cache: the bundled jaws' ``trees`` folder
    (``scripts/make_jaws.py --trees`` writes it), unless ``PREBUILT`` says otherwise."""
    if PREBUILT is not None:
        return list(PREBUILT)
    from .jaw import bundled_models

    return [os.fspath(bundled_models() / "trees")]


def _find(folder: str, name: str) -> list[str]:
    """``name`` in the cache folder, then in the prebuilt folders: the paths that exist."""
    return [p for p in (os.path.join(f, name) for f in [folder, *prebuilt_folders()]) if os.path.exists(p)]


def _explicit(params: dict) -> dict:
    """``params`` without the entries equal to ``build``'s defaults, so ``sparse=False`` and no
    ``sparse`` at all name the same tree."""
    import inspect

    from .builder.pipeline import build

    defaults = {k: p.default for k, p in inspect.signature(build).parameters.items() if p.default is not inspect.Parameter.empty}
    return {k: v for k, v in params.items()
            if not (k in defaults and type(v) is type(defaults[k]) and isinstance(v, (bool, int, float, str, type(None)))
                    and v == defaults[k])}


def tree_key(vertices, faces, params: dict) -> str:
    """Content key of a tree: mesh bytes + build parameters (those not at their defaults) +
    builder and format versions."""
    from .builder.pipeline import BUILDER_VERSION

    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(faces, np.int64).tobytes())
    h.update(json.dumps(_explicit(params), sort_keys=True).encode())
    h.update(f"format{FORMAT_VERSION}builder{BUILDER_VERSION}".encode())
    return h.hexdigest()[:40]


def cached_tree(vertices, faces, params: dict, *, folder=None, progress: bool = False, name: str = "") -> tuple[InnerSphereTree, bool]:
    """Load the tree of ``(vertices, faces)`` built with ``params`` from the cache, or build and store it.

    Returns ``(tree, hit)``. ``params`` are ``mjist.build`` keyword arguments.
    """
    from .builder.pipeline import build

    folder = cache_dir(folder)
    key = tree_key(vertices, faces, params)
    path = os.path.join(folder, f"{key}.ist.npz")
    for found in _find(folder, f"{key}.ist.npz"):
        try:
            return load_tree(found), True
        except TreeFileError as exc:
            warnings.warn(f"rebuilding cached tree{' of ' + name if name else ''}: {exc}", RuntimeWarning, stacklevel=2)
    tree = build((vertices, faces), progress=progress, **params)
    try:
        os.makedirs(folder, exist_ok=True)
        tree.save(path)
    except OSError as exc:  # a read-only cache only costs the rebuild next time
        warnings.warn(f"cannot write the tree cache {folder!r} ({exc}); set MJIST_CACHE to a writable folder", RuntimeWarning, stacklevel=2)
    return tree, False


EXITS_VERSION = 1  # bump when traverse.exit_directions changes what it computes


GRID_VERSION = 1  # bump when surface.add_grid's defaults or sdfgrid's layout change


def _entry(arrays, tag: str, suffix: str, folder) -> tuple[str, str]:
    """The cache folder and the file name of an entry keyed by ``arrays``' bytes and ``tag``."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(a.tobytes())
    h.update(tag.encode())
    return cache_dir(folder), f"{h.hexdigest()[:40]}{suffix}"


def _store(folder: str, name: str, write) -> None:
    """Writes an entry through ``write(file)`` into a temporary file and moves it into place (a
    reader sees the whole file or none); a read-only cache only costs the computation next time."""
    path = os.path.join(folder, name)
    try:
        os.makedirs(folder, exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except OSError:
        pass


def cached_grid(vertices, faces, compute, *, folder=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A mesh's narrow-band grid (``geometry.surface.add_grid`` with its default spacing: header,
    table, faces), from the cache or from ``compute()`` (then stored). Keyed by the mesh's bytes,
    the default spacing and ``GRID_VERSION``; an unreadable or inconsistent file is recomputed."""
    from .geometry import sdfgrid
    from .geometry import surface as sf

    folder, name = _entry((np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int64)),
                          f"grid{GRID_VERSION}/{sdfgrid.BRICK}/{sf.GRID_EDGE}/{sf.GRID_BAND}", ".grid.npz", folder)
    for found in _find(folder, name):
        try:
            with np.load(found, allow_pickle=False) as z:
                H, T, V = z["header"], z["table"], z["values"]
            dims = H[4:7].astype(np.int64) if H.shape == (sdfgrid.HDR_W,) else None
            if (dims is not None and H.dtype == np.float64 and np.isfinite(H).all() and H[3] > 0
                    and T.dtype == np.int32 and T.size == int(np.prod(dims)) and V.dtype == np.int32
                    and V.size % sdfgrid.NODES == 0 and int(T.max(initial=-1)) < V.size // sdfgrid.NODES
                    and int(V.min(initial=-1)) >= -1 and int(V.max(initial=-1)) < len(faces)):
                return np.ascontiguousarray(H), np.ascontiguousarray(T), np.ascontiguousarray(V)
        except (OSError, ValueError, KeyError):
            pass
    H, T, V = compute()
    # compressed: the face ids of neighbouring nodes repeat (about 7x smaller)
    _store(folder, name, lambda f: np.savez_compressed(f, header=H, table=T, values=V))
    return H, T, V


def cached_exits(N, vertices, faces, compute, *, folder=None) -> np.ndarray:
    """The exit directions of packed tree ``N`` over its mesh (``traverse.exit_directions``), from
    the cache or from ``compute()`` (then stored). Keyed by the packed tree's and the mesh's bytes,
    so a tree given by the caller is found too; an unreadable or mismatched file is recomputed."""
    folder, name = _entry((np.ascontiguousarray(N, np.float64), np.ascontiguousarray(vertices, np.float64),
                           np.ascontiguousarray(faces, np.int64)), f"exits{EXITS_VERSION}", ".exits.npy", folder)
    for found in _find(folder, name):
        try:
            X = np.load(found, allow_pickle=False)
            if X.shape == (N.shape[0], 4) and X.dtype == np.float64 and np.isfinite(X).all():
                return np.ascontiguousarray(X)
        except (OSError, ValueError):
            pass
    X = np.ascontiguousarray(compute(), np.float64)
    _store(folder, name, lambda f: np.save(f, X))
    return X
