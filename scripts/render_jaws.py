"""Render a jaw pair in its occlusion pose with MuJoCo's offscreen renderer (headless).

    MUJOCO_GL=egl python scripts/render_jaws.py                      # bundled jaws → models/jaws.png
    MUJOCO_GL=egl python scripts/render_jaws.py --jaw ../shared/data/jaw --out out/real_jaws.png

Use ``MUJOCO_GL=osmesa`` where there is no GPU/EGL.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent

XML = """
<mujoco>
  <visual><global offwidth="{w}" offheight="{h}"/><quality shadowsize="4096"/></visual>
  <asset>
    <mesh name="maxilla" file="{maxilla}"/>
    <mesh name="mandible" file="{mandible}"/>
  </asset>
  <worldbody>
    <light pos="0 0.3 0.4" dir="0 -0.5 -1" diffuse="0.8 0.8 0.8"/>
    <light pos="0.2 0.1 0.3" dir="-0.4 -0.2 -1" diffuse="0.4 0.4 0.4"/>
    <body euler="90 0 0">  <!-- the jaws are +y up; MuJoCo's cameras are +z up -->
      <geom type="mesh" mesh="maxilla" group="1" rgba="0.93 0.87 0.76 1"/>
      <body pos="{dx} {dy} {dz}"><geom type="mesh" mesh="mandible" rgba="0.75 0.82 0.93 1"/></body>
    </body>
  </worldbody>
</mujoco>
"""


def render(maxilla, mandible, out, offset=(0.0, 0.0, 0.0), size=(1800, 600)):
    w, h = size
    xml = XML.format(w=w, h=h, maxilla=os.path.abspath(maxilla), mandible=os.path.abspath(mandible),
                     dx=offset[0], dy=offset[1], dz=offset[2])
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    r = mujoco.Renderer(m, h, w // 3)
    centre = d.geom_xpos.mean(axis=0)
    span = 2.2 * float(np.max(m.geom_rbound))
    views = []
    # front; oblique from the side; the lower arch from above with the maxilla hidden
    for az, el, dist, hide_maxilla in ((90.0, 0.0, 0.85, False), (150.0, -15.0, 1.05, False), (90.0, -80.0, 0.75, True)):
        cam = mujoco.MjvCamera()
        cam.lookat[:] = centre
        cam.distance = dist * span
        cam.azimuth = az
        cam.elevation = el
        opt = mujoco.MjvOption()
        opt.geomgroup[1] = 0 if hide_maxilla else 1
        r.update_scene(d, camera=cam, scene_option=opt)
        views.append(r.render())
    img = np.concatenate(views, axis=1)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(out, img)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--jaw", default=str(ROOT / "models"), help="folder with maxilla + mandible meshes")
    ap.add_argument("--out", default=str(ROOT / "models" / "jaws.png"))
    a = ap.parse_args()
    folder = Path(a.jaw)
    ext = ".stl" if (folder / "maxilla.stl").exists() else ".obj"
    offset = (0.0, 0.0, 0.0)
    pose = folder / "occlusion.json"
    if pose.exists():
        P = np.array(json.loads(pose.read_text())["mandible_pose"])
        offset = tuple(P[:3, 3])
    print(render(folder / f"maxilla{ext}", folder / f"mandible{ext}", a.out, offset))


if __name__ == "__main__":
    main()
