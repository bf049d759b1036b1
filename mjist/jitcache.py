"""numba's on-disk cache, emptied when any mjist source changes.

numba keys a cached kernel on its own file only: a kernel that compiles in a function of
another module keeps the old version of it after that module changes (the penalty-force
cfunc in ``forces.py`` inlines ``hook._managed``; an editable install that pulled a change
of ``hook.py`` alone went on with the old contact law). ``check`` runs when ``mjist`` is
imported, before any kernel loads: it hashes every source of the package and, when the hash
differs from the one the cache was built with, removes the numba files from the package's
``__pycache__`` (the default cache place; with ``NUMBA_CACHE_DIR`` set, that folder is the
user's to manage). Everything then compiles once more.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

STAMP = "mjist-sources.sha256"
NUMBA_FILES = (".nbi", ".nbc")


def sources_digest(pkg: Path) -> str:
    """SHA-256 over the names and bytes of the package's ``*.py`` files."""
    h = hashlib.sha256()
    for p in sorted(pkg.glob("*.py")):
        h.update(p.name.encode())
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
        for f in cache.iterdir():
            if f.suffix in NUMBA_FILES:
                f.unlink(missing_ok=True)
        stamp.write_text(digest)
    except OSError:  # a read-only install: numba could not have cached there either
        return False
    return True
