"""MuJoCo scenes of a jaw pair: jaw closure by muscle-like actuators.

The jaw frame is +y up, +z anterior, metres (``mjist.jaw``); MuJoCo's cameras and gravity are
+z up, so the whole jaw sits in a body rotated by 90° about x. The maxilla is fixed; the
mandible hangs on a hinge through the condyles with two small slides (protrusion and
lateral shift, soft springs standing in for the joint capsule), and four spatial tendons
(masseter and temporalis, both sides) pull it closed through first-order activation
dynamics, like muscles. ``models/jaw_closure.xml`` is this generator's output for the
bundled jaws; ``jaw_closure_xml`` makes the same scene for any pair (e.g. the CBCT pair).
"""
from __future__ import annotations

import numpy as np

OPEN_DEG = 8.0  # initial opening (keyframe "open")


def _v(x) -> str:
    return " ".join(f"{float(a):.6g}" for a in x)


# mjist's <custom> settings after mjist_geoms and mjist_max_error: constraint contacts (closure,
# search) or penalty forces with the virtual coupling (haptics)
# Contact groups are subtrees at depth 5 (a few millimetres of a jaw), not 3 (about a
# centimetre): a group holds one contact, its deepest leaf pair, and a depth-3 group can span
# both slopes of a cusp; when the deepest pair moves from one slope to the other the contact
# normal flips and a clenched jaw cycles between the two. At depth 5 it rests still.
CONSTRAINT = ('    <text name="mjist_offset" data="mean"/>\n'
              '    <numeric name="mjist_contacts" data="4"/>\n'
              '    <numeric name="mjist_split_depth" data="5"/>')


def _penalty(law: str) -> str:
    return ('    <text name="mjist_mode" data="penalty"/>\n'
            f'    <text name="mjist_penalty" data="{law}"/>\n'
            '    <text name="mjist_offset" data="none"/>\n'
            '    <text name="mjist_coupling" data="handle mandible"/>')


def _settings(max_error, rest: str) -> str:
    """The scenes' ``<custom>`` block: the jaw geoms, ``max_error`` when given, then ``rest``."""
    me = f'\n    <numeric name="mjist_max_error" data="{max_error:g}"/>' if max_error else ""
    return f'  <custom>\n    <text name="mjist_geoms" data="maxilla mandible"/>{me}\n{rest}\n  </custom>'


def _inertial(inertial, R=np.eye(3), t=(0.0, 0.0, 0.0), indent: int = 6) -> str:
    """An ``<inertial>`` element for mass properties given in mandible mesh coordinates, placed in
    a body whose frame maps mesh coordinates by ``R``, ``t`` (empty when ``inertial`` is None)."""
    if inertial is None:
        return ""
    pos = R @ np.asarray(inertial["pos"], float) + np.asarray(t, float)
    II = R @ np.asarray(inertial["inertia"], float) @ R.T
    full = (II[0, 0], II[1, 1], II[2, 2], II[0, 1], II[0, 2], II[1, 2])
    return (" " * indent + '<!-- mass properties of a whole mandible: the scanned part is only the teeth -->\n'
            + " " * indent + f'<inertial pos="{_v(pos)}" mass="{inertial["mass"]:g}" fullinertia="{_v(full)}"/>\n')


def _assets(maxilla: str, mandible: str) -> str:
    return f'  <asset>\n    <mesh name="maxilla" file="{maxilla}"/>\n    <mesh name="mandible" file="{mandible}"/>\n  </asset>'


def jaw_closure_xml(maxilla: str, mandible: str, hinge, mandible_pos=(0.0, 0.0, 0.0), *, half_width: float = 0.045,
                    open_deg: float = OPEN_DEG, muscle_force: float = 40.0, meshdir: str | None = None,
                    max_error: float | None = 5e-4, title: str = "bundled jaw pair", inertial: dict | None = None,
                    hinge_note: str = "", condylar_stop: bool | None = None) -> str:
    """MJCF text of the jaw-closure scene.

    Parameters
    ----------
    maxilla, mandible : str
        Mesh files (relative to ``meshdir`` when given).
    hinge : (3,)
        Condyle centre in the mandible mesh's coordinates (jaw frame).
    mandible_pos : (3,)
        Translation of the mandible mesh in the ground-truth occlusion (jaw frame).
    half_width : float
        Half the distance between the condyles (places the muscles).
    open_deg : float
        Opening of the ``open`` keyframe.
    muscle_force : float
        Peak force of each of the four closing muscles (N).
    max_error : float, optional
        ``mjist_max_error`` written into the ``<custom>`` settings (metres).
    inertial : dict, optional
        The mandible's mass properties (``mass``, ``pos``, ``inertia`` in mesh coordinates), for
        a mandible scanned without its bone (``arch.anatomical_inertia``); default from the mesh.
    condylar_stop : bool, optional
        A condylar guidance on the protrusion slide: a stiff stop against retrusion behind the
        seated position (the stored relation). Default: on for a teeth-only mandible (``inertial``
        given); ``pair_scene`` turns it on for every user pair.
    hinge_note : str
        Where the hinge comes from and how sure it is, written into the scene as a comment.
    """
    h = np.asarray(hinge, float)
    w = float(half_width)
    # muscle attachment points, jaw frame, relative to the hinge (adult human proportions)
    sites_world, sites_jaw = [], []
    for side, sx in (("r", -1.0), ("l", 1.0)):
        x = sx * 0.95 * w
        sites_world.append((f"masseter_{side}_origin", h + (x - h[0], 0.004, 0.030)))
        sites_jaw.append((f"masseter_{side}_insertion", h + (x - h[0], -0.050, 0.008)))
        sites_world.append((f"temporalis_{side}_origin", h + (0.9 * x - h[0], 0.035, 0.002)))
        sites_jaw.append((f"temporalis_{side}_insertion", h + (0.85 * x - h[0], -0.004, 0.020)))
    p = np.asarray(mandible_pos, float)
    sw = "\n".join(f'      <site name="{n}" pos="{_v(np.asarray(s) + p)}" size="0.002" rgba="0.8 0.2 0.2 1"/>' for n, s in sites_world)
    sj = "\n".join(f'        <site name="{n}" pos="{_v(s)}" size="0.002" rgba="0.8 0.2 0.2 1"/>' for n, s in sites_jaw)
    tendons = "\n".join(
        f'    <spatial name="{m}_{s}" width="0.0015" rgba="0.75 0.25 0.25 1"><site site="{m}_{s}_origin"/>'
        f'<site site="{m}_{s}_insertion"/></spatial>'
        for m in ("masseter", "temporalis") for s in ("r", "l")
    )
    acts = "\n".join(
        f'    <general name="{m}_{s}" tendon="{m}_{s}" dyntype="filter" dynprm="0.04" ctrlrange="0 1" '
        f'gainprm="{-muscle_force:g}" biastype="none"/>'
        for m in ("masseter", "temporalis") for s in ("r", "l")
    )
    md = f'\n  <compiler meshdir="{meshdir}"/>' if meshdir else ""
    # the cusps' inclines under the closing force drive the mandible back along the arch, and
    # nothing holds the condyles in their seat without condyles and fossae in the meshes (a
    # segmentation's joint space lets them slide back too): the condylar guidance stops retrusion
    # at the seated position (the stored relation) with a stiff one-sided limit, as the fossa's
    # back wall and the ligaments do, and leaves protrusion on its soft spring
    stop = inertial is not None if condylar_stop is None else condylar_stop
    protrusion = 'range="0 0.003" solreflimit="0.002 1" solimplimit="0.95 0.99 0.0001"' if stop else 'range="-0.003 0.003"'
    return f"""<mujoco model="jaw_closure">{_hinge_comment(hinge_note)}
  <!-- Jaw closure ({title}): maxilla fixed, mandible on a condylar hinge with protrusive and
       lateral play, closed by masseter and temporalis. Generated by mjist.jaw.scenes.jaw_closure_xml.
       IST contacts: mjist.load_model(this file); native hull contacts: mujoco.MjModel.from_xml_path. -->{md}
  <option timestep="0.001" integrator="implicitfast"/>
  <visual><global offwidth="1600" offheight="900"/><quality shadowsize="4096"/></visual>
{_settings(max_error, CONSTRAINT)}
  <default>
    <geom solref="0.004 1" solimp="0.95 0.99 0.0005" friction="0.3"/>
  </default>
{_assets(maxilla, mandible)}
  <worldbody>
    <light pos="0 -0.4 0.3" dir="0 1 -0.6" diffuse="0.8 0.8 0.8"/>
    <light pos="0.3 -0.2 0.4" dir="-0.5 0.4 -0.8" diffuse="0.4 0.4 0.4"/>
    <body name="skull" euler="90 0 0">
      <geom name="maxilla" type="mesh" mesh="maxilla" rgba="0.93 0.87 0.76 1"/>
{sw}
      <body name="mandible" pos="{_v(p)}">
        <joint name="hinge" type="hinge" axis="1 0 0" pos="{_v(h)}" range="-3 25" damping="0.02"/>
        <joint name="protrusion" type="slide" axis="0 0 1" pos="{_v(h)}" {protrusion} stiffness="300" damping="2"/>
        <joint name="lateral" type="slide" axis="1 0 0" pos="{_v(h)}" range="-0.003 0.003" stiffness="300" damping="2"/>
{_inertial(inertial, indent=8)}        <geom name="mandible" type="mesh" mesh="mandible" density="1900" rgba="0.75 0.82 0.93 1"/>
{sj}
      </body>
    </body>
  </worldbody>
  <tendon>
{tendons}
  </tendon>
  <actuator>
{acts}
  </actuator>
  <keyframe>
    <key name="open" qpos="{np.radians(open_deg):.6g} 0 0"/>
    <key name="occlusion" qpos="0 0 0"/>
  </keyframe>
</mujoco>
"""


def _hinge_comment(note: str) -> str:
    return f"\n  <!-- hinge: {note} -->" if note else ""


def jaw_to_world(R, t):
    """A jaw-frame pose (+y up) as MuJoCo world pose (+z up): the scene's 90° turn about x."""
    Rx = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return Rx @ R, Rx @ t


def mandible_pose(hinge, mandible_pos, hinge_deg=0.0, offset=(0.0, 0.0, 0.0)):
    """World pose (R, t) of the mandible body: opened by ``hinge_deg`` about the condylar axis,
    then moved by ``offset`` (jaw frame: x lateral, y up, z anterior), from the occlusion."""
    a = np.radians(hinge_deg)
    c, s = np.cos(a), np.sin(a)
    Rh = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    h = np.asarray(hinge, float)
    t = np.asarray(mandible_pos, float) + h - Rh @ h + np.asarray(offset, float)
    return jaw_to_world(Rh, t)


def _quat(R) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def haptic_jaw_xml(maxilla: str, mandible: str, hinge, mandible_pos=(0.0, 0.0, 0.0), *, open_deg: float = 3.0,
                   max_error: float | None = 5e-4, law: str = "contacts", meshdir: str | None = None,
                   title: str = "bundled jaw pair", inertial: dict | None = None, hinge_note: str = "") -> str:
    """MJCF text of the haptic scene: a free mandible driven by a mocap handle through a virtual coupling.

    The maxilla is fixed; the mandible is a free body (no gravity: the device carries it); the
    ``handle`` mocap body is the haptic device; ``mjist_coupling`` couples the two with a 6-DoF
    spring–damper whose force the device displays; the jaw pair is a penalty pair
    (``mjist_mode="penalty"``, law ``law``) with offset ``none``, so a non-zero contact force
    always means the meshes intersect.
    """
    Ro, to = mandible_pose(hinge, mandible_pos, open_deg)
    Rc, tc = mandible_pose(hinge, mandible_pos, 0.0)
    qo, qc = _quat(Ro), _quat(Rc)
    md = f'\n  <compiler meshdir="{meshdir}"/>' if meshdir else ""
    return f"""<mujoco model="haptic_jaw">{_hinge_comment(hinge_note)}
  <!-- Haptic jaw ({title}): the maxilla is fixed, the mandible is a free body driven by the
       haptic device's handle (a mocap body) through a 6-DoF virtual coupling; tooth contact is
       rendered as IST penalty forces. Generated by mjist.jaw.scenes.haptic_jaw_xml; run it with
       `mjist haptic` (or mjist.load_model + mj_step, moving data.mocap_pos/quat). -->{md}
  <option timestep="0.001" gravity="0 0 0"/>
  <visual><global offwidth="1600" offheight="900"/></visual>
{_settings(max_error, _penalty(law))}
{_assets(maxilla, mandible)}
  <worldbody>
    <light pos="0 -0.4 0.3" dir="0 1 -0.6" diffuse="0.8 0.8 0.8"/>
    <body name="skull" euler="90 0 0">
      <geom name="maxilla" type="mesh" mesh="maxilla" rgba="0.93 0.87 0.76 1"/>
      <site name="hinge" pos="{_v(np.asarray(mandible_pos, float) + np.asarray(hinge, float))}" size="0.002"/>
    </body>
    <body name="mandible" pos="{_v(to)}" quat="{_v(qo)}">
      <freejoint name="mandible"/>
{_inertial(inertial)}      <geom name="mandible" type="mesh" mesh="mandible" density="1900" rgba="0.75 0.82 0.93 1"/>
    </body>
    <body name="handle" mocap="true" pos="{_v(to)}" quat="{_v(qo)}">
      <geom type="sphere" size="0.003" contype="0" conaffinity="0" rgba="0.9 0.3 0.2 0.6"/>
    </body>
  </worldbody>
  <keyframe>
    <key name="open" qpos="{_v(to)} {_v(qo)}" mpos="{_v(to)}" mquat="{_v(qo)}"/>
    <key name="occlusion" qpos="{_v(tc)} {_v(qc)}" mpos="{_v(tc)}" mquat="{_v(qc)}"/>
  </keyframe>
</mujoco>
"""


def occlusion_search_xml(maxilla: str, mandible: str, hinge, mandible_pos=(0.0, 0.0, 0.0), *, closing: float = 30.0,
                         lin_damping: float = 3.0, ang_damping: float = 0.003, tmj_timeconst: float = 0.01,
                         max_error: float | None = 5e-4, meshdir: str | None = None, title: str = "bundled jaw pair",
                         inertial: dict | None = None, tmj: bool = True, hinge_note: str = "") -> str:
    """MJCF text of the occlusion-search scene: a free, damped mandible pulled onto the maxilla.

    ``closing`` (m/s²) is the closing acceleration standing in for the elevator muscles (the
    scene's gravity points from the mandible to the maxilla); the free joint's damping settles
    the mandible where the cusps hold it. IST constraint contacts (offset ``mean``), low friction
    (wet enamel), so the cusps can guide it into intercuspation. ``tmj`` seats the condyles in a
    soft ball joint at the hinge; off, the mandible is free and only the teeth and the closing
    force decide its pose. ``inertial`` as for ``jaw_closure_xml``.
    """
    seat = _v(jaw_to_world(np.eye(3), np.asarray(mandible_pos, float) + np.asarray(hinge, float))[1])
    tmj_xml = (f"""  <equality>
    <!-- the temporomandibular joints seat the condyles in their fossae: a soft ball joint at the
         condylar axis' centre (it yields, so the teeth, not the joint, decide the final pose).
         Its seat is the mocap body "condyles": the search moves it with each start, because
         where the condyles sit in occlusion is known only as well as the pair's given pose -->
    <connect name="tmj" body1="mandible" body2="condyles" anchor="{seat}" solref="{tmj_timeconst:g} 1"/>
  </equality>
""" if tmj else "")
    seat_body = f'\n    <body name="condyles" mocap="true" pos="{seat}"/>' if tmj else ""
    Rc, tc = mandible_pose(hinge, mandible_pos, 0.0)
    qc = _quat(Rc)
    md = f'\n  <compiler meshdir="{meshdir}"/>' if meshdir else ""
    return f"""<mujoco model="occlusion_search">{_hinge_comment(hinge_note)}
  <!-- Occlusion search ({title}): the maxilla is fixed, the mandible is a free body pulled
       towards it (gravity stands in for the closing muscles) and damped, so it settles where
       the teeth hold it. Generated by mjist.jaw.scenes.occlusion_search_xml; used by
       mjist.jaw.occlusion.search / `mjist occlusion`. -->{md}
  <option timestep="0.001" integrator="implicitfast" gravity="0 0 {closing:g}"/>
  <visual><global offwidth="1600" offheight="900"/></visual>
{_settings(max_error, CONSTRAINT)}
  <default>
    <geom solref="0.004 1" solimp="0.95 0.99 0.0005" friction="0.1"/>
  </default>
{_assets(maxilla, mandible)}
  <worldbody>
    <light pos="0 -0.4 0.3" dir="0 1 -0.6" diffuse="0.8 0.8 0.8"/>
    <body name="skull" euler="90 0 0">
      <geom name="maxilla" type="mesh" mesh="maxilla" rgba="0.93 0.87 0.76 1"/>
      <site name="hinge" pos="{_v(np.asarray(mandible_pos, float) + np.asarray(hinge, float))}" size="0.002"/>
    </body>{seat_body}
    <body name="mandible">
      <!-- a free joint's damping is one number for translation and rotation; separate joints
           damp each with its own time constant (about 0.1 s for this jaw's mass and inertia).
           The body frame is the world frame at qpos 0; the geom carries the occlusion pose. -->
      <joint name="x" type="slide" axis="1 0 0" damping="{lin_damping:g}"/>
      <joint name="y" type="slide" axis="0 1 0" damping="{lin_damping:g}"/>
      <joint name="z" type="slide" axis="0 0 1" damping="{lin_damping:g}"/>
      <joint name="rotation" type="ball" damping="{ang_damping:g}"/>
{_inertial(inertial, Rc, tc)}      <geom name="mandible" type="mesh" mesh="mandible" pos="{_v(tc)}" quat="{_v(qc)}" density="1900" rgba="0.75 0.82 0.93 1"/>
    </body>
  </worldbody>
{tmj_xml}  <keyframe>
    <key name="occlusion" qpos="0 0 0 1 0 0 0"/>
  </keyframe>
</mujoco>
"""


def muscle_half_width(mandible_vertices) -> float:
    """Half the distance between the closing muscles' insertions: 85 % of the mandible's half width."""
    x = np.asarray(mandible_vertices)[:, 0]
    return 0.5 * float(x.max() - x.min()) * 0.85


KINDS = {"closure": "jaw_closure.xml", "occlusion": "occlusion_search.xml", "haptic": "haptic_jaw.xml"}


def pair_scene(folder, out_dir, kind: str, *, maxilla=None, mandible=None, units="auto", up="auto", hinge=None,
               repair="auto", max_deviation_mm=None, tmj: bool = True, output=None, progress: bool = True,
               register: bool = False, **kwargs):
    """Write the ``kind`` scene ("closure", "occlusion" or "haptic") of a user's jaw pair; return its path.

    The pair (``folder``, or ``maxilla`` + ``mandible`` files) is read by ``pair.load_pair`` with
    ``units``, ``up``, ``hinge``, ``repair`` (detected when "auto") and ``max_deviation_mm``. A pair already in the
    jaw frame is referenced where it lies; any other (converted, repaired, or an STL beyond
    MuJoCo's 200 k-face limit) is written once as OBJ in the jaw frame beside the scene.
    ``tmj`` keeps the occlusion search's soft TMJ ball joint at the hinge (also at Bonwill's
    estimate: the joint yields, and without it the closing force behind the arch tips a free
    teeth-only mandible over its molars). ``pair.json`` beside the scene records what
    was detected. ``register`` places the mandible from the arches' shapes, ignoring its given
    pose (``pair.load_pair``); ``pair.json`` then records how, and where the files put it
    (``given_from_reference``). ``max_error`` is 0.3 mm unless given; other ``kwargs`` go to the scene writer.
    """
    import json
    import os
    from pathlib import Path

    from .pair import load_pair

    if kind not in KINDS:
        raise ValueError(f"scene kind {kind!r} must be one of {', '.join(KINDS)}")
    writers = {"closure": jaw_closure_xml, "occlusion": occlusion_search_xml, "haptic": haptic_jaw_xml}
    mx, md, info = load_pair(folder, maxilla=maxilla, mandible=mandible, units=units, up=up, hinge=hinge, repair=repair,
                             max_deviation_mm=max_deviation_mm, register=register)
    occlusion = np.asarray(info["mandible_pose"], float)  # the (registered) mandible mesh -> its occlusion, jaw frame
    given = np.asarray(info.get("given", np.eye(4)), float)  # the mandible mesh -> where its file put it
    path = Path(output) if output else Path(out_dir) / KINDS[kind]
    os.makedirs(path.parent, exist_ok=True)
    files = {k: os.path.abspath(v) for k, v in info["paths"].items()}
    pose = np.asarray(info["mandible_pose"], float)
    hinge_mesh = np.asarray(info["hinge"], float)
    Vd = md.vertices
    if not np.allclose(pose[:3, :3], np.eye(3), atol=1e-12):
        # the scenes place the mandible at its occlusion by a translation: an occlusion that turns
        # it (a pair closed about its condyles) is baked into the mandible's vertices instead
        Vd = md.vertices @ pose[:3, :3].T + pose[:3, 3]
        hinge_mesh = pose[:3, :3] @ hinge_mesh + pose[:3, 3]
        if info.get("inertial") is not None:
            i = dict(info["inertial"])
            i["pos"] = pose[:3, :3] @ np.asarray(i["pos"]) + pose[:3, 3]
            i["inertia"] = pose[:3, :3] @ np.asarray(i["inertia"]) @ pose[:3, :3].T
            info["inertial"] = i
        pose = np.eye(4)
    if info["export"] or Vd is not md.vertices:
        import trimesh

        from ..geometry.mesh import single_precision

        for name, V, F in (("maxilla", mx.vertices, mx.faces), ("mandible", Vd, md.faces)):
            files[name] = os.path.abspath(path.parent / f"{name}.jaw.obj")
            # MuJoCo reads vertices as float32: two distinct vertices closer than that resolution
            # (a few nm in metres) would become one and leave zero-area faces its tree build
            # refuses; the mesh is written as MuJoCo will see it, cleaned of those slivers, at
            # full precision (the exporter's default 8 decimals would round them together too)
            V, F, removed, flipped = single_precision(V, F)
            if removed:
                info["notes"].append(f"{name}: {removed} zero-area faces removed where vertices closer than MuJoCo's "
                                     "float32 resolution become one")
            if flipped:
                info["notes"].append(f"{name}: {flipped} slivers that MuJoCo's float32 rounding flattens flipped away "
                                     "(each with its neighbour across its long edge)")
            trimesh.Trimesh(V, F, process=False).export(files[name], digits=17)
    kwargs.setdefault("max_error", 3e-4)
    if kind == "closure":
        kwargs.setdefault("half_width", 0.045 if info["teeth_only"] else muscle_half_width(Vd))
        kwargs.setdefault("condylar_stop", True)
    if kind == "occlusion":
        kwargs.setdefault("tmj", bool(tmj))
    kwargs.setdefault("inertial", info.get("inertial"))
    hinge_world = pose[:3, :3] @ hinge_mesh + pose[:3, 3]
    kwargs.setdefault("hinge_note", f"{info['hinge_source']}, centre {_v(hinge_world * 1e3)} mm (jaw frame), "
                                    f"uncertain by about {info['hinge_uncertainty'] * 1e3:g} mm")
    title = f"jaw pair of {folder}" if maxilla is None else f"jaw pair {maxilla} + {mandible}"
    xml = writers[kind](files["maxilla"], files["mandible"], hinge_mesh, pose[:3, 3],
                        title=title, **kwargs)
    path.write_text(xml)
    summary = {"scene": str(path), "kind": kind, "meshes": files,
               "given": {k: os.path.abspath(v) for k, v in info["paths"].items()}, "hinge": np.asarray(info["hinge"]).tolist(),
               "hinge_source": info["hinge_source"], "hinge_uncertainty_mm": info["hinge_uncertainty"] * 1e3,
               "occlusion_source": info["source"], "seat_uncertainty_mm": info["seat_uncertainty"] * 1e3,
               "teeth_only": info["teeth_only"],
               "mandible_pose": (occlusion @ np.linalg.inv(given)).tolist(),  # the mandible file -> its occlusion
               "given_from_reference": (given @ np.linalg.inv(occlusion)).tolist(),
               "orientation": info["orientation"].as_dict(), "arches": {k: f.as_dict() for k, f in info["arches"].items()},
               "notes": info["notes"]}
    if "registration" in info:
        summary["registration"] = info["registration"]
    (path.parent / "pair.json").write_text(json.dumps(summary, indent=1))
    if progress:
        for n in info["notes"]:
            print(f"pair: {n}")
    return path


def reference_pose(model, key: str = "occlusion", body: str = "mandible", site: str = "hinge"):
    """The mandible at a scene's reference keyframe: body position, quaternion (w-first),
    rotation matrix, the hinge site's position and its frame (column 0: the hinge axis; the
    columns are the jaw frame's axes in the world). Raises ``ValueError`` naming what is missing."""
    import mujoco

    k = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key)
    s = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
    b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if k < 0:
        raise ValueError(f"the scene needs a {key!r} keyframe (the mandible's reference pose)")
    if s < 0:
        raise ValueError(f"the scene needs a {site!r} site on the condylar axis (see mjist.jaw.scenes)")
    if b < 0:
        raise ValueError(f"the scene needs a body named {body!r}")
    d = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d, k)
    mujoco.mj_forward(model, d)
    return (d.xpos[b].copy(), d.xquat[b].copy(), d.xmat[b].reshape(3, 3).copy(), d.site_xpos[s].copy(),
            d.site_xmat[s].reshape(3, 3).copy())
