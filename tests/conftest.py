from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"
MISSING_IN_CI = ("{path} is missing: CI (CI=true) runs the real-data tests (marked 'shared') and does not skip "
                 "them; put the shared data folder beside the project (../shared/data) or unset CI to skip them")


def _in_ci() -> bool:
    import os

    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def pytest_configure(config):
    """Under CI, stop at once when the shared real data is missing (its tests would only skip).
    With pytest-xdist workers, compile the shared kernels once in the controller first
    (``_warm``); each worker then loads them from numba's cache."""
    if _in_ci() and not SHARED.is_dir():
        raise pytest.UsageError(MISSING_IN_CI.format(path=SHARED))
    if getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput"):
        import sys

        sys.path.insert(0, str(Path(__file__).parent))
        import _warm

        _warm.compile_kernels()


@pytest.fixture(scope="session")
def cache(tmp_path_factory):
    """One tree cache for the session: the jaw trees are built once for every MuJoCo test."""
    return str(tmp_path_factory.mktemp("treecache"))


def load_script(*parts):
    """A file of the repository (``scripts/``, ``examples/``) imported as a module and registered in
    ``sys.modules``: numba's on-disk cache finds a kernel's module again by its name."""
    import importlib.util
    import sys

    path = ROOT.joinpath(*parts)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    return mod


def shared_path(*parts) -> Path:
    """A file of ../shared/data, or skip the test when the folder is absent (fresh clones; under
    CI the test fails instead)."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        if _in_ci():
            pytest.fail(MISSING_IN_CI.format(path=p), pytrace=False)
        pytest.skip(f"{p} not present (shared data is only beside the project on dev/CI machines)")
    return p


def gaps_to_union(points, centers, radii):
    """Exact distance (clamped at 0) from each point to the union of spheres: the nearest centre's
    sphere bounds it from above, so only spheres whose centres lie within that bound plus the
    largest radius can do better, and those are all measured (scipy's k-d tree finds them)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, float)
    kd = cKDTree(centers)
    d, i = kd.query(points)
    upper = d - radii[i]
    out = np.empty(len(points))
    for k, near in enumerate(kd.query_ball_point(points, upper + radii.max())):
        near = np.asarray(near, np.int64)
        out[k] = (np.linalg.norm(centers[near] - points[k], axis=1) - radii[near]).min() if len(near) else upper[k]
    return np.maximum(out, 0.0)


def winding_numbers(points, vertices, faces):
    """Generalized winding number of each point (sum of triangle solid angles / 4 pi,
    Van Oosterom–Strackee): 1 inside a closed outward-wound surface, 0 outside, whatever its
    self-intersections. Independent of the ray casting under test; O(points x faces)."""
    T = np.asarray(vertices, float)[np.asarray(faces)]
    out = np.empty(len(points))
    for i, p in enumerate(np.asarray(points, float)):
        a, b, c = T[:, 0] - p, T[:, 1] - p, T[:, 2] - p
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la + np.einsum("ij,ij->i", c, a) * lb
        out[i] = np.arctan2(num, den).sum() / (2.0 * np.pi)
    return out


def coal_depth(bvh, Pa, Pb):
    """coal: deepest triangle-pair penetration of two meshes (``bvh``: their coal BVHs) at 4x4
    poses ``Pa``, ``Pb`` (0 when they do not touch)."""
    from mjist.jaw.exact import coal_depth as depth

    return depth(bvh[0], Pa, bvh[1], Pb)


@pytest.fixture(scope="session")
def teeth_only(tmp_path_factory):
    """The shared pair in its stored occlusion, in mm with +z up, cropped 9 mm either side of the
    occlusal level (no condyles, rami or fossae)."""
    from mjist.jaw.pair import load_pair

    src = shared_path("jaw")
    byo = load_script("scripts", "byo_jaws.py")
    mx, md = byo._load(src / "maxilla.obj"), byo._load(src / "mandible.obj")
    _, _, info = load_pair(src)
    md.apply_transform(info["mandible_pose"])
    y0 = float(info["arches"]["mandible"].origin[1])
    S = np.eye(4)
    S[:3, :3] = 1000.0 * byo.TO_FILE
    folder = tmp_path_factory.mktemp("teeth_mm_z")
    for name, m in (("maxilla", mx), ("mandible", md)):
        c = byo._crop(m, y0 + 9e-3, y0 - 9e-3, -1.0)
        c.apply_transform(S)
        c.export(folder / f"{name}.stl")
    return folder
