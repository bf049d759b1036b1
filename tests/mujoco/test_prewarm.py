"""A first run's compile on two processes (``mujoco/prewarm.py``): the child's kernels are the
ones the collision cfunc calls, so this process loads them from numba's cache instead of
compiling them, and the contacts are the same as with everything compiled in one process."""
import json
import os
import subprocess
import sys

import pytest

PROBE = r"""
import json, sys, time
import numpy as np
from numba.core import event

compiled = []
class Listener(event.Listener):
    def on_start(self, ev):
        compiled.append(getattr(getattr(ev.data["dispatcher"], "py_func", None), "__name__", "?"))
    def on_end(self, ev):
        pass
event.register("numba:compile", Listener())

import mujoco, trimesh
import mjist
from mjist.mujoco import hook, prewarm

mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.01)
mesh.export(sys.argv[1] + "/ball.obj")
xml = f'''<mujoco><asset><mesh name="ball" file="{sys.argv[1]}/ball.obj"/></asset><worldbody>
<geom name="floor" type="mesh" mesh="ball"/>
<body pos="0 0 0.0195"><freejoint/><geom name="top" type="mesh" mesh="ball"/></body></worldbody></mujoco>'''
model = mujoco.MjModel.from_xml_string(xml)
t = time.perf_counter()
handle = mjist.attach(model, max_error=0.001, narrowphase="surface", cache_dir=sys.argv[1])
seconds = time.perf_counter() - t
d = mujoco.MjData(model)
depths = []
for _ in range(50):
    mujoco.mj_step(model, d)
    depths.append(sorted(float(c.dist) for c in d.contact[:d.ncon]))
sigs = {n: [str(s) for s in getattr(hook, n).signatures] for n in ("pair_distance", "pair_contacts", "_collide_prim")}
print(json.dumps({"compiled": compiled, "signatures": sigs, "seconds": seconds, "depths": depths,
                  "expected": {"pair_distance": str(prewarm.DISTANCE_SIG), "pair_contacts": str(prewarm.CONTACTS_SIG),
                               "_collide_prim": str(prewarm.PRIMITIVE_SIG)}}))
"""


def _probe(tmp_path, mode):
    env = dict(os.environ)
    if mode == "first":
        env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")  # nothing compiled yet
    work = tmp_path / mode
    work.mkdir()
    p = subprocess.run([sys.executable, "-c", PROBE, str(work), mode], capture_output=True, text=True, env=env,
                       timeout=1200)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # a compile from nothing, about a minute
def test_a_first_run_loads_the_childs_kernels_and_steps_the_same(tmp_path):
    split = _probe(tmp_path, "first")
    # the kernels collide's typing asked for are exactly the signatures the two halves compiled
    for name, sig in split["expected"].items():
        assert split["signatures"][name] == [sig], (name, split["signatures"][name])
    assert "pair_contacts" not in split["compiled"]  # loaded from the child's cache entry
    assert "pair_distance" in split["compiled"]
    cached = _probe(tmp_path, "cached")  # the package's own cache, compiled as every other test finds it
    assert split["depths"] == cached["depths"] and any(split["depths"])
