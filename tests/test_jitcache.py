"""numba's cache is dropped when any source of the package changes (``mjist.jitcache``)."""
from mjist import jitcache


def test_cache_is_dropped_when_a_source_changes_and_kept_otherwise(tmp_path):
    (tmp_path / "hook.py").write_text("x = 1\n")
    (tmp_path / "forces.py").write_text("y = 2\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()

    def numba_files():
        return sorted(p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc"))

    def compile_something():
        for name in ("forces._penalty-1.py311.nbi", "forces._penalty-1.py311.1.nbc"):
            (cache / name).write_bytes(b"cached")

    compile_something()
    (cache / "forces.cpython-311.pyc").write_bytes(b"bytecode")
    assert jitcache.check(tmp_path)  # no stamp yet: who knows what these were built from
    assert numba_files() == [] and (cache / "forces.cpython-311.pyc").exists()
    compile_something()
    assert not jitcache.check(tmp_path)  # same sources: the cache stays
    assert len(numba_files()) == 2
    (tmp_path / "hook.py").write_text("x = 3\n")  # another module than the cached kernel's
    assert jitcache.check(tmp_path)
    assert numba_files() == []
    assert not jitcache.check(tmp_path)


def test_importing_a_changed_package_drops_its_stale_kernels(tmp_path):
    """The real import: a copy of the package, imported in fresh processes, keeps a cached kernel
    while its sources stay the same and drops it once one of them changes."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import mjist

    copy = tmp_path / "mjist"
    shutil.copytree(Path(mjist.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__", "models"))

    def import_copy():
        out = subprocess.run([sys.executable, "-c", "import mjist; print(mjist.__file__)"], cwd=tmp_path,
                             capture_output=True, text=True, env={"PATH": "", "PYTHONPATH": str(tmp_path), "NUMBA_CACHE_DIR": ""})
        assert out.returncode == 0, out.stderr[-1500:]
        assert Path(out.stdout.strip()).parent == copy  # the copy, not the installed package

    import_copy()
    kernel = copy / "query" / "__pycache__" / "traverse._nearest-1.py311.nbi"
    kernel.parent.mkdir(exist_ok=True)
    kernel.write_bytes(b"cached")
    import_copy()
    assert kernel.exists()  # same sources: kept
    with open(copy / "query" / "traverse.py", "a") as fh:
        fh.write("\n# changed\n")
    import_copy()
    assert not kernel.exists()  # a source changed: dropped


def test_a_change_in_one_subpackage_drops_every_subpackages_kernels(tmp_path):
    # the penalty cfunc of mujoco/forces.py inlines code of mujoco/hook.py and query/traverse.py
    (tmp_path / "__init__.py").write_text("")
    for sub in ("mujoco", "query"):
        (tmp_path / sub / "__pycache__").mkdir(parents=True)
        (tmp_path / sub / "__init__.py").write_text("")
    (tmp_path / "query" / "traverse.py").write_text("z = 1\n")
    (tmp_path / "mujoco" / "forces.py").write_text("y = 2\n")
    kernel = tmp_path / "mujoco" / "__pycache__" / "forces._passive-1.py311.nbi"
    assert jitcache.check(tmp_path)
    kernel.write_bytes(b"cached")
    assert not jitcache.check(tmp_path) and kernel.exists()
    (tmp_path / "query" / "traverse.py").write_text("z = 2\n")
    assert jitcache.check(tmp_path)
    assert not kernel.exists()
