"""Where a cohort's stages run: in this process one patient at a time, or as Ray tasks.

Both take a patient and hand back its finished result; the runner does not know which it has.
On Ray a patient is a small graph: ``prepare`` → two ``tree`` tasks (one per jaw, in parallel)
→ ``search`` (→ ``wafer`` when asked), each task one CPU and retried when its worker dies (``RETRIES``). Ray is
imported here only, when a Ray backend is made.
"""
from __future__ import annotations

import os
import socket
import time

from . import stages

RETRIES = 2  # a task whose worker dies (killed, out of memory) runs again this many times
INSTALL = ("mjist cohort runs its patients on Ray, which is not installed: pip install 'mjist[cluster]' "
           "(or run on this machine one patient at a time with --serial)")


# Ray's switch between a single-machine run (every server on the loopback address) and a cluster
# (servers on the node's external address). Ray reads it at import in each of its processes.
_LOCAL_SWITCH = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def import_ray(local: bool):
    """``ray``, set up so that a ``local`` run's servers (GCS, raylets, workers, agents) listen
    on 127.0.0.1 only. A cluster run (an address given) leaves Ray's networking as it is.

    Ray resolves ``127.0.0.1`` given as the node address to the machine's external address,
    unless it runs in single-machine mode; that mode is chosen by an environment variable its
    server processes inherit, and by a constant the driver reads at each lookup (set here too
    when ``ray`` was imported before this call)."""
    if local:
        os.environ[_LOCAL_SWITCH] = "0"
    import ray
    from ray._private import ray_constants

    if local:
        ray_constants.ENABLE_RAY_CLUSTER = False
    return ray


def loopback_only(node_ip: str) -> bool:
    """Whether Ray's node address is a loopback address."""
    return node_ip.startswith("127.") or node_ip in ("::1", "localhost")


def run_patient(patient, out_dir: str, settings: dict, searched: dict | None = None) -> dict:
    """All stages of one patient in this process (the serial backend's unit of work); with
    ``searched`` (its finished result without a wafer) only ``prepare`` and ``wafer``."""
    prep = stages.prepare(patient, out_dir, settings)
    if searched is not None:
        return stages.wafer(patient, prep, searched, out_dir, settings) if prep["status"] == "ok" else _failed(prep, searched)
    tmx = stages.tree(prep, "maxilla", settings)
    tmd = stages.tree(prep, "mandible", settings)
    res = _combine(prep, tmx, tmd, stages.search(patient, prep, tmx, tmd, out_dir, settings))
    return stages.wafer(patient, prep, res, out_dir, settings) if settings.get("wafer") else res


def _failed(prep, searched) -> dict:
    """A finished result whose ``prepare`` failed when only its wafer was to be made."""
    return {**searched, "status": "error", "stage": prep["stage"], "error": prep["error"], "traceback": prep.get("traceback", "")}


def _combine(prep, tmx, tmd, final) -> dict:
    """The stage results of one patient as its result record (status, row, times, trees)."""
    res = {"status": final["status"], "worker": socket.gethostname()}
    if final["status"] != "ok":
        res.update(stage=final["stage"], error=final["error"], traceback=final.get("traceback", ""))
    else:
        res["row"] = final["row"]
    times = {}
    if prep.get("status") == "ok":
        times["prepare_s"] = prep["seconds"]
        res["notes"] = prep["pair"].get("notes", [])
    for name, t in (("maxilla", tmx), ("mandible", tmd)):
        if t.get("status") == "ok" and "cache_hit" in t:
            times[f"tree_{name}_s"] = t["seconds"]
            res.setdefault("trees", {})[name] = {k: t[k] for k in ("cache_hit", "error_bound_mm", "leaves")}
    if final["status"] == "ok":
        s = final["seconds"]
        times.update(search_s=s["search"], contact_map_s=s["contact_map"], outputs_s=s["outputs"])
    times["work_s"] = sum(v for k, v in times.items())
    res["times"] = times
    return res


class Serial:
    """One patient at a time in this process."""

    name = "serial"
    slots = 1

    def __init__(self, out_dir: str, settings: dict):
        self.out_dir, self.settings = out_dir, settings
        self._queue = {}

    def submit(self, patient, searched: dict | None = None):
        """Queue a patient: all its stages, or with ``searched`` (its result without a wafer) its wafer alone."""
        self._queue[patient.id] = (patient, searched)
        return patient.id

    def wait(self, handles, timeout: float):
        h = handles[0]
        patient, searched = self._queue.pop(h)
        return [(h, run_patient(patient, self.out_dir, self.settings, searched))]

    def map(self, fn, items):
        return [fn(*a) for a in items]

    def close(self):
        pass


# Ray tasks: module-level functions, so workers import them by reference from the installed mjist


def _prepare_task(patient, out_dir, settings):
    stages.crash_point(patient.id, "prepare")
    return stages.prepare(patient, out_dir, settings)


def _tree_task(patient, prep, geom, settings):
    stages.crash_point(patient.id, f"tree-{geom}")
    return stages.tree(prep, geom, settings)


def _search_task(patient, prep, tmx, tmd, out_dir, settings):
    stages.crash_point(patient.id, "search")
    final = stages.search(patient, prep, tmx, tmd, out_dir, settings)
    return _combine(prep, tmx, tmd, final)


def _wafer_task(patient, prep, res, out_dir, settings):
    stages.crash_point(patient.id, "wafer")
    if prep["status"] != "ok" and res.get("status") == "ok":  # only the wafer was to be made
        return _failed(prep, res)
    return stages.wafer(patient, prep, res, out_dir, settings)


class Ray:
    """Patients as Ray task graphs on a local Ray (``workers`` CPUs) or a cluster (``address``)."""

    name = "ray"

    def __init__(self, out_dir: str, settings: dict, *, workers: int | None = None, address: str | None = None):
        local = address is None and not os.environ.get("RAY_ADDRESS")
        try:
            ray = import_ray(local)
        except ImportError as exc:
            raise RuntimeError(INSTALL) from exc
        self.ray = ray
        self._own = not ray.is_initialized()
        if self._own:
            # mjist's and numba's settings (MJIST_CACHE, NUMBA_CACHE_DIR, MUJOCO_GL, ...) reach every worker
            env = {k: v for k, v in os.environ.items() if k.startswith(("MJIST_", "NUMBA_", "MUJOCO_GL"))}
            # a task holds one CPU: numba's threads beyond that would oversubscribe the node
            env.setdefault("NUMBA_NUM_THREADS", "1")
            ray.init(address=address, num_cpus=None if address else workers, include_dashboard=False,
                     log_to_driver=False, logging_level="ERROR", runtime_env={"env_vars": env})
            node_ip = ray.util.get_node_ip_address()
            if local and not loopback_only(node_ip):
                ray.shutdown()
                raise RuntimeError(f"the local Ray started on {node_ip}, not on 127.0.0.1; this Ray version ignores "
                                   f"{_LOCAL_SWITCH}=0 and would listen on the network: run the cohort on this machine with "
                                   "--serial, or on a Ray cluster you started with --address")
        self.slots = max(1, int(ray.cluster_resources().get("CPU", 1)))
        opts = {"num_cpus": 1, "max_retries": RETRIES}
        self._prepare = ray.remote(**opts)(_prepare_task)
        self._tree = ray.remote(**opts)(_tree_task)
        self._search = ray.remote(**opts)(_search_task)
        self._wafer = ray.remote(**opts)(_wafer_task)
        self.out_dir, self.settings = out_dir, settings
        self._refs = {}

    def submit(self, patient, searched: dict | None = None):
        """A patient's task graph, or with ``searched`` (its result without a wafer) prepare → wafer."""
        prep = self._prepare.remote(patient, self.out_dir, self.settings)
        if searched is not None:
            ref = self._wafer.remote(patient, prep, searched, self.out_dir, self.settings)
            self._refs[ref] = patient.id
            return ref
        tmx = self._tree.remote(patient, prep, "maxilla", self.settings)
        tmd = self._tree.remote(patient, prep, "mandible", self.settings)
        ref = self._search.remote(patient, prep, tmx, tmd, self.out_dir, self.settings)
        if self.settings.get("wafer"):
            ref = self._wafer.remote(patient, prep, ref, self.out_dir, self.settings)
        self._refs[ref] = patient.id
        return ref

    def wait(self, handles, timeout: float):
        done, _ = self.ray.wait(list(handles), num_returns=1, timeout=timeout)
        out = []
        for ref in done:
            self._refs.pop(ref, None)
            try:
                out.append((ref, self.ray.get(ref)))
            except Exception as exc:  # the worker died more than RETRIES times, or Ray itself failed
                out.append((ref, {"status": "error", "stage": "worker", "worker": "",
                                  "error": f"{type(exc).__name__}: the task failed {RETRIES + 1} times "
                                           f"({str(exc).strip().splitlines()[0][:200] if str(exc).strip() else 'no message'})",
                                  "times": {}}))
        return out

    def map(self, fn, items):
        task = self.ray.remote(num_cpus=1, max_retries=RETRIES)(fn)
        return self.ray.get([task.remote(*a) for a in items])

    def close(self):
        if self._own and self.ray.is_initialized():
            self.ray.shutdown()


def make(kind: str, out_dir: str, settings: dict, *, workers=None, address=None):
    """``Serial`` or ``Ray`` (``RuntimeError`` with the install command when Ray is missing)."""
    if kind == "serial":
        return Serial(out_dir, settings)
    t0 = time.perf_counter()
    b = Ray(out_dir, settings, workers=workers, address=address)
    b.startup_s = time.perf_counter() - t0
    return b
