"""Cohorts on local Ray: error rows, resuming, a killed worker, results independent of workers.

Small synthetic patients (1.5 mm polygonisation, 1 mm trees, 4 search starts) keep a patient to
seconds; the accuracy of the search is measured by ``scripts/bench_cohort.py``, not here.
"""
from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mjist.cohort import discover, report, run, synthetic

pytest.importorskip("ray")

FAST = {"max_error": 1e-3, "starts": 4, "seconds": 0.2, "picture": False}
GOOD = ("synthetic-0000", "synthetic-0003")


@pytest.fixture(scope="module")
def cohort_input(tmp_path_factory):
    """Two synthetic patients and one whose maxilla file is not a mesh."""
    folder = tmp_path_factory.mktemp("input")
    for name in GOOD:
        synthetic.write_patient(folder / name, synthetic.anatomy(0, int(name[-4:])), spacing=1.5)
    bad = folder / "broken"
    shutil.copytree(folder / GOOD[0], bad)
    (bad / "maxilla.obj").write_text("this is not a mesh\n")
    (bad / synthetic.DESIGN_FILE).unlink()
    return folder


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("trees"))


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _without_times(rows):
    return [{k: v for k, v in r.items() if k not in report.TIME_COLUMNS} for r in rows]


@pytest.fixture(scope="module")
def two_workers(cohort_input, cache, tmp_path_factory):
    out = tmp_path_factory.mktemp("two")
    return out, run(cohort_input, out, workers=2, progress=False, cache=cache, **FAST)


def _against_design(patient, result):
    """The best candidate (``occlusion.json``'s transform of the mandible file) against the design
    brought to first touch along +y by coal, computed here: largest shift of the mandible's
    vertices within 3 mm of the maxilla and the rotation (``_reference``); and the sides of the
    midline (x) where the meshes come within 0.1 mm of each other there."""
    import _reference as ref
    import numpy as np
    import trimesh

    mx, md = (trimesh.load(patient / f"{n}.obj", force="mesh", process=False) for n in ("maxilla", "mandible"))
    a, Vd = (mx.vertices, mx.faces), np.asarray(md.vertices)
    V0 = Vd + [0.0, ref.first_touch(a, (Vd, md.faces), [0.0, 1.0, 0.0], reach=3e-3), 0.0]
    idx = ref.near_vertices(V0, a, 3e-3)
    M = np.asarray(json.loads((result / "occlusion.json").read_text())["mandible_transform"][0])
    Vc = Vd @ M[:3, :3].T + M[:3, 3]
    e = {"max_mm": ref.largest_shift(Vc[idx], V0[idx]) * 1e3, "rotation_deg": ref.rotation_between_deg(Vc[idx], V0[idx])}
    near = ref.near_vertices(Vc, a, 1e-4)  # articulating paper: as the ranking counts a contact
    sides = {"left" if x > 0 else "right" for x in Vc[near, 0]}
    return e, sides


def test_bad_patient_is_an_error_row_and_the_others_finish(two_workers, cohort_input):
    out, s = two_workers
    assert (s["patients"], s["done"], s["failed"], s["backend"]) == (3, 2, 1, "ray")
    rows = {r["patient"]: r for r in _rows(out / "cohort.csv")}
    assert rows["broken"]["status"] == "error" and rows["broken"]["error_stage"] == "load"
    assert "broken" in rows["broken"]["error"] or "maxilla" in rows["broken"]["error"]
    for name in GOOD:
        r = rows[name]
        e, sides = _against_design(cohort_input / name, out / "patients" / name)
        print(name, "vs design at first touch:", e, "contact sides", sides, "row", r["design_max_mm"], r["both_sides"])
        # a regression guard at these coarse settings (1 mm trees, 4 starts; measured 0.26-0.37 mm):
        # scripts/bench_cohort.py measures the search's accuracy
        assert r["status"] == "ok" and e["max_mm"] < 0.6 and e["rotation_deg"] < 1.0, e
        assert float(r["design_max_mm"]) == pytest.approx(e["max_mm"], abs=0.35)  # the row measures from the design itself
        assert r["both_sides"] == str(sides == {"left", "right"})
        assert 0.0 < float(r["interocclusal_mm"]) < 6.0  # 2 x the 3 mm cap at most
        for f in ("occlusion.json", "landscape.png", "contact_map.json", "contact_map_maxilla.png", "result.json"):
            assert (out / "patients" / name / f).exists(), f
    assert (out / "cohort.png").exists()


def test_rerun_does_nothing(two_workers, cohort_input, cache):
    out, _ = two_workers
    before = (out / "cohort.csv").read_text()
    s = run(cohort_input, out, serial=True, progress=False, cache=cache, **FAST)
    assert (s["ran"], s["skipped"]) == (0, 3)
    assert (out / "cohort.csv").read_text() == before


def test_half_written_patient_is_not_taken_as_done(two_workers, cohort_input, cache, tmp_path):
    out, _ = two_workers
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "patients" / GOOD[1] / "result.json").write_text('{"status": "ok", "patient": "synthetic-0003", "ke')
    s = run(cohort_input, copy, serial=True, progress=False, cache=cache, **FAST)
    assert s["ran"] == 1 and s["done"] == 2
    assert _without_times(_rows(copy / "cohort.csv")) == _without_times(_rows(out / "cohort.csv"))


def test_killed_worker_is_retried_and_one_worker_gives_the_same_rows(two_workers, cohort_input, cache, tmp_path, monkeypatch):
    out, _ = two_workers
    flags = tmp_path / "crash"
    flags.mkdir()
    (flags / f"{GOOD[0]}.search").touch()
    (flags / f"{GOOD[1]}.tree-maxilla").touch()
    monkeypatch.setenv("MJIST_COHORT_CRASH_ONCE", str(flags))
    s = run(cohort_input, tmp_path / "one", workers=1, progress=False, cache=cache, **FAST)
    assert not list(flags.iterdir()), "the injected crashes did not happen"
    assert (s["done"], s["failed"]) == (2, 1)
    assert _without_times(_rows(tmp_path / "one" / "cohort.csv")) == _without_times(_rows(out / "cohort.csv"))


def test_manifest_gives_per_patient_options(cohort_input, tmp_path):
    m = tmp_path / "cohort.csv"
    m.write_text("patient,folder,units,up\n"
                 f"a,{cohort_input / GOOD[0]},m,+y\n"
                 f"b,{cohort_input / GOOD[1]},,\n")
    a, b = discover(m)
    assert (a.id, a.units, a.up, b.units) == ("a", "m", "+y", "auto")
    m.write_text("folder\nx\n")
    with pytest.raises(ValueError, match="patient"):
        discover(m)


def test_without_ray_the_command_says_how_to_install_it(tmp_path, monkeypatch, capsys):
    from mjist import cli

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    assert cli.main(["cohort", str(tmp_path), "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "pip install 'mjist[cluster]'" in err and "--serial" in err, err


def test_the_rest_of_mjist_does_not_import_ray():
    code = ("import sys, mjist, mjist.cli, mjist.cohort, mjist.jaw.occlusion, mjist.jaw.scenes; "
            "print(json.dumps('ray' in sys.modules))")
    out = subprocess.run([sys.executable, "-c", "import json; " + code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) is False


def test_a_local_ray_listens_on_loopback_only(tmp_path):
    """A local cohort backend (no address) starts Ray whose every listening socket, in the
    driver and in each process Ray started, is on a loopback address (read from the kernel's
    socket table by psutil, not from Ray)."""
    code = """
import json, os, psutil
from mjist.cohort import backends
b = backends.make("ray", OUT, {}, workers=1)
assert b.map(lambda x: abs(x), [(-2,), (3,)]) == [2, 3]  # a task ran
me = psutil.Process()
procs = [me, *me.children(recursive=True)]
listening = []
for p in procs:
    try:
        listening += [(p.name(), c.laddr.ip) for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
    except psutil.Error:
        pass
b.close()
print(json.dumps(listening))
""".replace("OUT", repr(str(tmp_path)))
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    listening = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(listening) >= 3  # the GCS, a raylet and the driver's own server at least
    outside = [(name, ip) for name, ip in listening if not (ip.startswith("127.") or ip in ("::1", "::ffff:127.0.0.1"))]
    assert not outside, f"Ray processes listen beyond loopback: {outside}"


@pytest.mark.slow
def test_a_cohort_survives_losing_a_node(cohort_input, cache, tmp_path):
    """A two-node local Ray cluster (``ray.cluster_utils.Cluster``: a head with one CPU, a worker
    node with two) runs the cohort; the worker node is killed while patients run on it. Ray
    retries the lost tasks (and rebuilds their lost inputs) on the head: every patient finishes
    once, with the rows a serial run gives, and a rerun does nothing."""
    import threading
    import time

    from ray.cluster_utils import Cluster

    from mjist.cohort.backends import import_ray

    import_ray(local=True)  # the test's cluster is local: on loopback, reached through its address
    reference = run(cohort_input, tmp_path / "serial", serial=True, progress=False, cache=cache, **FAST)
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    node = cluster.add_node(num_cpus=2)
    cluster.wait_for_nodes()
    out = tmp_path / "cluster"
    killed = {}

    def kill_when_running():
        # as soon as the first patient has started writing, the others are on the worker node's CPUs
        deadline = time.time() + 120
        while time.time() < deadline and not any((out / "patients").glob("*/*")):
            time.sleep(0.1)
        cluster.remove_node(node, allow_graceful=False)
        killed["at"] = time.time()

    t = threading.Thread(target=kill_when_running, daemon=True)
    try:
        t.start()
        s = run(cohort_input, out, address=cluster.address, progress=False, cache=cache, **FAST)
        t.join(timeout=150)
        assert "at" in killed, "the worker node was not removed during the run"
        assert (s["done"], s["failed"]) == (2, 1)
        rows = _rows(out / "cohort.csv")
        assert sorted(r["patient"] for r in rows) == sorted(["broken", *GOOD])  # each patient once
        assert _without_times(rows) == _without_times(_rows(tmp_path / "serial" / "cohort.csv"))
        again = run(cohort_input, out, address=cluster.address, progress=False, cache=cache, **FAST)
        assert again["ran"] == 0 and again["skipped"] == 3
    finally:
        cluster.shutdown()
    assert reference["done"] == 2


@pytest.mark.slow
def test_a_cohort_makes_and_proves_a_wafer_per_patient(cohort_input, cache, tmp_path):
    """``--wafer`` on a searched cohort: each good patient gets its wafer and proofs beside its
    search, which is not run again, the row their figures; a rerun does nothing. (These patients' 1.5 mm facets end their cusps in sharp
    vertices, whose imprints a 0.15 mm grid makes up to 0.05 mm deeper than the clearance:
    ``scripts/bench_wafer.py`` measures the seating on real scans, not this test.)"""
    out = tmp_path / "wafers"
    first = run(cohort_input, out, serial=True, progress=False, cache=cache, **FAST)
    assert (first["done"], first["failed"]) == (2, 1)
    searched = {name: (out / "patients" / name / "occlusion.json").read_bytes() for name in GOOD}
    before = {r["patient"]: r for r in _rows(out / "cohort.csv")}
    # the same cohort with --wafer: the searched patients get their wafers alone
    s = run(cohort_input, out, serial=True, progress=False, cache=cache, wafer=True, **FAST)
    assert (s["done"], s["failed"], s["ran"], s["skipped"]) == (2, 1, 2, 1)
    rows = {r["patient"]: r for r in _rows(out / "cohort.csv")}
    for name in GOOD:
        assert (out / "patients" / name / "occlusion.json").read_bytes() == searched[name]  # not searched again
        assert rows[name]["search_s"] == before[name]["search_s"] and float(rows[name]["wafer_s"]) > 0
    for name in GOOD:
        r = rows[name]
        meta = json.loads((out / "patients" / name / "wafer.json").read_text())
        assert r["wafer_ok"] == str(meta["ok"]) and float(r["wafer_min_thickness_mm"]) >= 1.5
        assert float(r["wafer_opening_deg"]) == pytest.approx(meta["opening_deg"], abs=1e-3)
        # the wafer judged here from the files: closed and solid (trimesh), neither arch overlapping
        # it by more than the seating proof's 0.02 mm (coal's exact distance, mandible where the
        # wafer holds it)
        import _reference as ref
        import trimesh

        w = trimesh.load(out / "patients" / name / "wafer.stl", force="mesh")
        assert w.is_watertight and w.volume > 0 and w.body_count == 1
        mx, md = (trimesh.load(cohort_input / name / f"{n}.obj", force="mesh", process=False) for n in ("maxilla", "mandible"))
        M = np.asarray(meta["mandible_transform"])
        for arch in ((mx.vertices, mx.faces), (np.asarray(md.vertices) @ M[:3, :3].T + M[:3, 3], md.faces)):
            assert ref.exact_distance((w.vertices, w.faces), arch) >= -2e-5  # metres
        seat = meta["proofs"]["seating"]
        assert float(r["wafer_tip_gap_max_mm"]) == pytest.approx(max(seat[k]["tip_distance_max_mm"] for k in ("maxilla", "mandible")), abs=1e-4)
        assert (out / "patients" / name / "wafer.stl").stat().st_size > 0
    again = run(cohort_input, out, serial=True, progress=False, cache=cache, wafer=True, **FAST)
    assert (again["ran"], again["skipped"]) == (0, 3)
