"""Automated articulation: the occlusion found from wherever the arches are given.

The shared casts are stored in occlusion at first touch (their README: the lab's bite moved down
to where coal first finds them touching), so the stored pose is the reference; every other
arrangement is a rigid move this test makes itself. The error is measured here, on the lower
cast's own occlusal vertices (within 3 mm of the upper at the stored pose, trimesh's distances),
from the transform ``occlusion.json`` reports for the mandible file, not from the search's own
figures. Skipped when ../shared/data is absent.
"""
import numpy as np
import pytest
import trimesh
from conftest import shared_path
from scipy.spatial.transform import Rotation

# a regression guard, not the goal: the search from a registration lands within the range its starts
# cover (half their 3 mm / 5° spread); the target is 0.3 mm / 0.5°, and BENCHMARKS.md ("Any start")
# has what it reaches (0.4-1.2 mm). Before the registration this case came back 5-11 mm off.
MAX_MM, MAX_DEG = 1.5, 2.5


def _error(M, G, P) -> tuple[float, float]:
    A = np.asarray(M) @ G
    d = np.linalg.norm(P @ A[:3, :3].T + A[:3, 3] - P, axis=1).max()
    return float(d), float(np.degrees(Rotation.from_matrix(A[:3, :3]).magnitude()))


@pytest.mark.shared
def test_casts_given_in_an_unrelated_frame_come_back_to_their_occlusion(tmp_path, cache):
    from mjist.jaw import occlusion

    folder = shared_path("orthocast")
    up, lo = (trimesh.load(folder / f, process=False) for f in ("upper.ply", "lower.ply"))
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("xyz", [70.0, -125.0, 30.0], degrees=True).as_matrix()
    G[:3, 3] = [50.0, -20.0, 10.0]  # mm
    given = tmp_path / "given"
    given.mkdir()
    up.export(given / "upper.ply")
    moved = lo.copy()
    moved.apply_transform(G)
    moved.export(given / "lower.ply")
    res = occlusion.search(data=given, seed=0, progress=False, cache_dir=cache, out_dir=tmp_path / "out")
    res["_handle"].detach()
    d = np.abs(trimesh.proximity.signed_distance(up, lo.vertices[::10]))
    P = lo.vertices[::10][d < 3.0]
    err = _error(res["mandible_transform"][0], G, P)
    print("casts from an unrelated frame: best", err, "registration", res["registration"]["score_mm"])
    assert err[0] < MAX_MM and err[1] < MAX_DEG
    assert not res["given"]["touching"] and not res["given"]["is_start"]  # 50 mm away: not a start
    assert res["given"]["from_registration"]["max_mm"] > 40.0
