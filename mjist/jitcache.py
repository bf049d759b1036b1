"""numba's on-disk cache, emptied when any mjist source changes.

numba keys a cached kernel on its own file only: a kernel that compiles in a function of
another module keeps the old version of it after that module changes (the penalty-force
cfunc in ``mujoco/forces.py`` links in the hook's contact path from ``mujoco/hook.py``, so a
change of ``hook.py`` alone would leave the old contact law in the penalty forces). ``check``
runs when ``mjist`` is imported, before any kernel loads: it hashes every source of the package,
subpackages included, and, when the hash differs from the one the cache was built with, removes
the numba files from every ``__pycache__`` of the package (the default cache place; with
``NUMBA_CACHE_DIR`` set, that folder is the user's to manage). Everything then compiles once
more.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

STAMP = "mjist-sources.sha256"
NUMBA_FILES = (".nbi", ".nbc")


def sources_digest(pkg: Path) -> str:
    """SHA-256 over the paths and bytes of the package's ``*.py`` files, subpackages included."""
    h = hashlib.sha256()
    for p in sorted(pkg.rglob("*.py")):
        h.update(p.relative_to(pkg).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def check(pkg: Path | None = None) -> bool:
    """Drop the numba cache of ``pkg`` (default: mjist) if its sources changed; True if dropped."""
    pkg = Path(__file__).parent if pkg is None else Path(pkg)
    cache = pkg / "__pycache__"
    digest = sources_digest(pkg)
    stamp = cache / STAMP
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        cache.mkdir(exist_ok=True)
        for folder in pkg.rglob("__pycache__"):
            for f in folder.iterdir():
                if f.suffix in NUMBA_FILES:
                    f.unlink(missing_ok=True)
        stamp.write_text(digest)
    except OSError:  # a read-only install: numba could not have cached there either
        return False
    return True
