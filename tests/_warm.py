"""Compiles the kernels most tests share, once, before pytest-xdist starts its workers: numba
compiles a kernel in each process that finds no cached copy, so two workers starting together
would both compile every kernel (minutes each) instead of loading the one copy written here."""
import tempfile
from pathlib import Path

import numpy as np

XML = """<mujoco>
  <asset><mesh name="ball" file="{ball}"/></asset>
  <worldbody>
    <geom name="floor" type="mesh" mesh="ball"/>
    <geom name="box" type="box" size="0.004 0.004 0.004" pos="0.03 0 0"/>
    <geom name="sphere" type="sphere" size="0.004" pos="-0.03 0 0"/>
    <body pos="0 0 0.021"><freejoint/><geom name="top" type="mesh" mesh="ball"/></body>
  </worldbody>
</mujoco>"""


def compile_kernels():
    import mujoco
    import trimesh

    import mjist

    with tempfile.TemporaryDirectory() as tmp:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.01)
        ball = Path(tmp) / "ball.obj"
        mesh.export(ball)
        tree = mjist.build((mesh.vertices, mesh.faces), max_error=0.001)
        q = mjist.Query(tree, tree)
        pose = np.eye(4)
        pose[2, 3] = 0.019
        q.distance(np.eye(4), pose)
        q.contacts(np.eye(4), pose)
        q.penetration_volume(np.eye(4), pose)
        qs = mjist.Query(tree, tree, meshes=((mesh.vertices, mesh.faces),) * 2)
        qs.distance(np.eye(4), pose)
        qs.contacts(np.eye(4), pose)
        for settings in ({}, {"narrowphase": "surface"}, {"mode": "penalty", "stiffness": 100.0}):
            model = mujoco.MjModel.from_xml_string(XML.format(ball=ball))
            handle = mjist.attach(model, cache_dir=tmp, max_error=0.001, **settings)
            data = mujoco.MjData(model)
            for _ in range(3):
                mujoco.mj_step(model, data)
            mujoco.mj_geomDistance(model, data, 0, 3, 0.01, None)
            handle.detach()
