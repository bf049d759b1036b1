"""Command line: ``mjist build``, ``info``, ``scene``, ``demo``, ``render``, ``view``, ``haptic``, ``occlusion``,
``cohort``, ``bench``."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

from .jaw import BUNDLED as MODELS


def _report(tree, out: str | None, mesh: str) -> str:
    s = tree.stats()
    t = s["timings"]
    lines = [
        f"mesh        {mesh}: {s['mesh_vertices']} vertices, {s['mesh_faces']} faces, {s['mesh_shells']} shell(s)",
        f"leaves      {s['leaves']}   nodes {s['nodes']}   depth {s['depth']}   branching {s['params']['branching']}",
        f"error bound ε = {s['error_bound']:.6g} (certified; true gap >= {s['error_lower']:.6g}), mesh units",
        f"coverage    {100 * s['coverage']:.1f} % of the mesh volume   leaf radii {s['min_leaf_radius']:.3g} .. {s['max_leaf_radius']:.3g}",
        "time        " + "  ".join(f"{k} {v:.2f}s" for k, v in t.items()),
    ]
    if s.get("repairs"):
        lines.append("repairs     " + "; ".join(s["repairs"]))
    c = s.get("closure")
    if c:
        lines.append(f"closed      the input lies within {c['hausdorff']:.3g} of the closed surface (mean {c['mean_deviation']:.3g}, "
                     f"{c['method']}): against the input, ε is {s['error_bound'] + c['hausdorff']:.6g}")
    if s.get("crossed_faces"):
        lines.append(f"surface     {s['crossed_faces']} faces cross others (self-intersections, overlapping shells): "
                     "inside is the nonzero winding number")
    if s.get("stalled_faces"):
        lines.append(f"open        {s['stalled_faces']} faces ({s['stalled_area']:.3g} mesh units²) beside solid thinner "
                     "than the lattice reaches: ε counts them")
    if out:
        lines.append(f"saved       {out}")
    return "\n".join(lines)


def _cmd_build(args) -> int:
    from .builder.pipeline import build
    from .errors import MeshError

    meshes = args.mesh or sorted(str(p) for p in MODELS.glob("*.stl")) + sorted(str(p) for p in MODELS.glob("*.obj"))
    if not meshes:
        print("mjist build: no MESH given and no bundled models found", file=sys.stderr)
        return 2
    if args.output and len(meshes) > 1:
        print("mjist build: -o/--output takes one MESH; build several into --out-dir", file=sys.stderr)
        return 2
    for mesh in meshes:
        out = args.output or os.path.join(args.out_dir, Path(mesh).stem + ".ist.npz")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                tree = build(
                    mesh, max_error=args.max_error, leaves=args.leaves, branching=args.branching,
                    seed=args.seed, repair=args.repair, max_deviation=args.max_deviation, min_coverage=args.min_coverage,
                    sparse=args.sparse,
                    progress=not args.quiet,
                )
        except (MeshError, ValueError) as exc:
            print(f"mjist build: {mesh}: {exc}", file=sys.stderr)
            return 1
        for w in caught:
            print(f"warning: {w.message}", file=sys.stderr)
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        tree.save(out)
        print(_report(tree, out, mesh))
        if args.json:
            with open(args.json if len(meshes) == 1 else f"{args.json}.{Path(mesh).stem}.json", "w") as fh:
                json.dump(tree.stats(), fh, indent=2)
        print()
    return 0


def _cmd_info(args) -> int:
    from .errors import TreeFileError
    from .tree import load_tree

    try:
        tree = load_tree(args.tree)
    except TreeFileError as exc:
        print(f"mjist info: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(tree.stats(), indent=2))
    return 0


def _user_errors(name: str, run, extra: tuple = ()) -> int:
    """Run a command; bad input (mesh, config, missing file, bad value) becomes one line and exit 1."""
    from .errors import ConfigError, MeshError

    try:
        return run()
    except (ConfigError, MeshError, FileNotFoundError, ValueError, *extra) as exc:
        print(f"mjist {name}: {exc}", file=sys.stderr)
        return 1


def _pair_options(args) -> dict:
    """The jaw-pair options of ``--data`` and ``mjist scene`` (``jaw.scenes.pair_scene``)."""
    hinge = None
    if args.hinge:
        try:
            hinge = [float(a) for a in args.hinge.split(",")]
        except ValueError:
            hinge = []
        if len(hinge) != 3:
            raise ValueError(f"--hinge {args.hinge!r}: give x,y,z in the maxilla file's coordinates and units")
    opts = {"units": args.units, "up": args.up, "hinge": hinge, "repair": args.repair}
    if getattr(args, "max_deviation", None) is not None:
        opts["max_deviation_mm"] = args.max_deviation
    files = (getattr(args, "maxilla_file", None), getattr(args, "mandible_file", None))
    if any(files):
        if not all(files):
            raise ValueError("pass both --maxilla FILE and --mandible FILE (or --data FOLDER)")
        if getattr(args, "data", None):
            raise ValueError("pass either --data FOLDER or --maxilla FILE --mandible FILE, not both")
        opts["maxilla"], opts["mandible"] = files
    if getattr(args, "tmj", None) is not None:
        opts["tmj"] = args.tmj == "on"
    return opts


def _cmd_demo(args) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from .jaw import demo

    return _user_errors("demo", lambda: demo.main(
        scene=args.scene, data=args.data, native=args.native, seconds=args.seconds, out=args.out_dir,
        picture=not args.no_picture, max_error=args.max_error, progress=not args.quiet, pair=_pair_options(args),
        narrowphase=args.narrowphase))


def _cmd_render(args) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    import mujoco

    from .errors import ConfigError
    from .jaw import demo
    from .mujoco.attach import load_model

    try:
        model, handle = (mujoco.MjModel.from_xml_path(args.scene), None) if args.native else load_model(args.scene)
    except (ConfigError, FileNotFoundError, ValueError) as exc:
        print(f"mjist render: {exc}", file=sys.stderr)
        return 1
    d = mujoco.MjData(model)
    if args.key:
        k = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, args.key)
        if k < 0:
            print(f"mjist render: the scene has no keyframe {args.key!r}", file=sys.stderr)
            return 1
        mujoco.mj_resetDataKeyframe(model, d, k)
    mujoco.mj_forward(model, d)
    print(demo.render(model, d, args.output, handle=handle, depth=args.spheres))
    if handle is not None:
        handle.detach()
    return 0


def _cmd_view(args) -> int:
    from pathlib import Path

    target = Path(args.scene)
    if target.is_dir() or target.suffix == ".html":  # an output folder (or its page): its 3D report
        from . import report

        def show():
            path, opened = report.show(target, rebuild=args.rebuild)
            print(f"report        {path}" + ("" if opened else " (no display here: open it in a browser)"))
            return 0

        return _user_errors("view", show)
    from .mujoco import view

    try:
        return _user_errors("view", lambda: view.view(args.scene, depth=args.spheres, key=args.key, native=args.native,
                                                      control=args.ctrl, seconds=args.seconds))
    except RuntimeError as exc:  # no display: the viewer cannot open a window
        print(f"mjist view: cannot open the viewer ({exc}); on a headless machine use `mjist render`", file=sys.stderr)
        return 1


def _cmd_haptic(args) -> int:
    from .jaw import haptic

    return _user_errors("haptic", lambda: haptic.main(
        scene=args.scene, trajectory=args.trajectory, law=args.law, seconds=args.seconds, out=args.out_dir,
        progress=not args.quiet, data=args.data, pair=_pair_options(args)), extra=(RuntimeError,))


def _cmd_occlusion(args) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from .jaw import occlusion

    return _user_errors("occlusion", lambda: occlusion.main(
        scene=args.scene, data=args.data, starts=args.starts, translation=args.translation, rotation_deg=args.rotation,
        threads=args.threads, seed=args.seed, top=args.top, out=args.out_dir, progress=not args.quiet,
        pair={**_pair_options(args), "register": not args.given_pose}, contact_map=not args.no_contact_map, picture=not args.no_picture))


def _cmd_scene(args) -> int:
    from .jaw.scenes import pair_scene

    def run():
        opts = _pair_options(args)
        if args.max_error is not None:
            opts["max_error"] = args.max_error
        path = pair_scene(None, None, args.kind, maxilla=args.maxilla, mandible=args.mandible, output=args.output,
                          progress=not args.quiet, **opts)
        print(f"written       {path} (and {path.parent / 'pair.json'}: what was detected)")
        return 0

    return _user_errors("scene", run)


def _cmd_cohort(args) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from .cohort import run

    def go():
        if args.input is None and not args.synthetic:
            raise ValueError("give INPUT (a folder of patient folders, or a manifest CSV) or --synthetic N")
        try:
            s = run(args.input, args.out, synthetic_n=args.synthetic, seed=args.seed, spacing=args.spacing,
                    workers=args.workers, address=args.address, serial=args.serial, retry_failed=args.retry_failed,
                    progress=not args.quiet, max_error=args.max_error, starts=args.starts, picture=not args.no_picture,
                    cache=args.cache, wafer=args.wafer)
        except RuntimeError as exc:  # Ray or scikit-image missing: the message says what to install
            print(f"mjist cohort: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            return 130
        print(f"cohort        {s['done']} done, {s['failed']} failed ({s['skipped']} from an earlier run) in "
              f"{s['seconds']:.0f} s on {s['backend']} ({s['slots']} CPUs)")
        if "design" in s:
            d = s["design"]
            print(f"design        {d['within_target']}/{d['patients']} best candidates within 0.2 mm and 1° of the designed "
                  f"occlusion; median {d['median_max_mm']:.3f} mm, worst {d['worst_max_mm']:.3f} mm / {d['worst_rotation_deg']:.3f}°")
        for pid in s["failed_patients"]:
            print(f"failed        {pid} (see cohort.csv and patients/{pid}/result.json)")
        print(f"written       {s['csv']}" + (f", {s['figure']}" if s["figure"] else "") + f", {s['page']}")
        return 0 if not s["failed"] else 1

    return _user_errors("cohort", go)


def _cmd_wafer(args) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from .jaw import wafer

    return _user_errors("wafer", lambda: wafer.main(
        args.folder, output=args.output, pose=args.pose, search=args.search, opening_deg=args.opening,
        clearance_mm=args.clearance, thickness_mm=args.thickness, pair=_pair_options(args), hold=not args.no_hold,
        picture=not args.no_picture, starts=args.starts, seed=args.seed, threads=args.threads, progress=not args.quiet),
        extra=(RuntimeError,))


def _cmd_bench(args) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from . import bench

    def run():
        res = bench.run(quick=args.quick, out=args.out_dir, only=args.only.split(",") if args.only else None)
        return 0 if all(s["returncode"] == 0 for s in res["stages"].values()) else 1

    return _user_errors("bench", run)


def _add_build(sub) -> None:
    b = sub.add_parser("build", help="build the Inner Sphere Tree of a closed mesh (default: the bundled models)")
    b.add_argument("mesh", nargs="*", help="STL/OBJ/PLY file(s); default: every mesh in models/")
    b.add_argument("-o", "--output", help="output .npz (default: OUT_DIR/<mesh>.ist.npz)")
    b.add_argument("--out-dir", default="out", help="directory for outputs (default: out/)")
    b.add_argument("--max-error", type=float, default=None, help="target certified error bound ε, mesh units")
    b.add_argument("--leaves", type=int, default=None, help="maximum number of leaf spheres")
    b.add_argument("--branching", type=int, default=4, help="children per node (default 4)")
    b.add_argument("--seed", type=int, default=0, help="clustering seed (default 0)")
    b.add_argument("--min-coverage", type=float, default=None,
                   help="also fill interior gaps until the leaves fill this volume fraction (e.g. 0.85)")
    b.add_argument("--sparse", action="store_true",
                   help="keep only spheres that close a surface gap: same ε, fewer leaves (for queries, not resting contact)")
    b.add_argument("--repair", action="store_true",
                   help="fix winding, inversion and degenerate faces; close an open or many-piece surface (MeshFix, else "
                        "the winding number), reporting how far that moves it")
    b.add_argument("--max-deviation", type=float, default=None, metavar="D",
                   help="with --repair: refuse a closing that moves an input vertex farther than D (mesh units; default "
                        "0.2%% of the mesh's size, 0.2 mm on a 100 mm jaw)")
    b.add_argument("--json", help="also write the report as JSON to this file")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    b.set_defaults(func=_cmd_build)


def _add_info(sub) -> None:
    i = sub.add_parser("info", help="print the statistics of a saved tree")
    i.add_argument("tree")
    i.set_defaults(func=_cmd_info)


def _add_demo(sub) -> None:
    dm = sub.add_parser("demo", help="simulate jaw closure with IST contacts (default: the bundled jaws)")
    dm.add_argument("--scene", help="MJCF scene (default: models/jaw_closure.xml)")
    dm.add_argument("--data", help="folder with maxilla + mandible meshes (e.g. ../shared/data/jaw): builds its scene")
    dm.add_argument("--native", action="store_true", help="MuJoCo's own (convex hull) mesh contacts, for comparison")
    dm.add_argument("--seconds", type=float, default=1.0, help="simulated time (default 1 s)")
    dm.add_argument("--max-error", type=float, default=None, help="override the scene's mjist_max_error (metres)")
    dm.add_argument("--narrowphase", choices=("surface", "spheres"), default="surface",
                    help="surface (default): contacts measured on the meshes, the jaws rest on the true surfaces; "
                         "spheres: the trees' spheres, a mean surface gap off them")
    dm.add_argument("--out-dir", default="out/demo", help="summary JSON and picture (default out/demo)")
    dm.add_argument("--no-picture", action="store_true", help="skip the rendering")
    dm.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    _add_pair_options(dm, files=True)
    dm.set_defaults(func=_cmd_demo)


def _add_render(sub) -> None:
    r = sub.add_parser("render", help="render a scene headless (MUJOCO_GL=egl or osmesa) with its contacts")
    r.add_argument("scene")
    r.add_argument("-o", "--output", default="out/render.png")
    r.add_argument("--key", help="keyframe to show (default: the model's qpos0)")
    r.add_argument("--native", action="store_true", help="without the IST")
    r.add_argument("--spheres", type=int, default=None, metavar="DEPTH", help="draw the tree spheres at this depth")
    r.set_defaults(func=_cmd_render)


def _add_view(sub) -> None:
    v = sub.add_parser("view", help="open MuJoCo's viewer with IST contacts (a scene), or an output folder's 3D report.html")
    v.add_argument("scene", nargs="?", default=str(MODELS / "jaw_closure.xml"),
                   help="a scene (MJCF), or the output folder of mjist occlusion / wafer / demo --data / cohort")
    v.add_argument("--rebuild", action="store_true", help="write the output folder's report.html again from its files")
    v.add_argument("--spheres", type=int, default=None, metavar="DEPTH", help="draw the tree spheres at this depth")
    v.add_argument("--key", help="start from this keyframe (e.g. open)")
    v.add_argument("--ctrl", type=float, default=None, help="set every actuator's control (1 closes the jaw)")
    v.add_argument("--seconds", type=float, default=None, help="close after this much simulated time")
    v.add_argument("--native", action="store_true", help="without the IST")
    v.set_defaults(func=_cmd_view)


def _add_haptic(sub) -> None:
    hp = sub.add_parser("haptic", help="drive the mandible with a simulated haptic device; log forces, plot them")
    hp.add_argument("scene", nargs="?", default=None, help="haptic scene (default: models/haptic_jaw.xml)")
    hp.add_argument("--trajectory", default="chewing",
                    help="close, lateral_left, lateral_right, protrusion, chewing, press, push, hold, or a CSV file "
                         "(time, x, y, z, qw, qx, qy, qz)")
    hp.add_argument("--law", choices=("contacts", "volume"), default=None, help="penalty law (default: the scene's)")
    hp.add_argument("--seconds", type=float, default=None, help="length of a scripted trajectory")
    hp.add_argument("--data", help="folder with maxilla + mandible meshes (e.g. ../shared/data/jaw): builds its scene")
    hp.add_argument("--out-dir", default="out/haptic", help="log (.npz), summary (.json) and plot (.png)")
    hp.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    _add_pair_options(hp, files=True)
    hp.set_defaults(func=_cmd_haptic)


def _add_occlusion(sub) -> None:
    oc = sub.add_parser("occlusion", help="search where the teeth fit: close many starting poses in parallel, rank them")
    oc.add_argument("scene", nargs="?", default=None, help="occlusion-search scene (default: models/occlusion_search.xml)")
    oc.add_argument("--data", help="folder with maxilla + mandible meshes (e.g. ../shared/data/jaw): builds its scene")
    oc.add_argument("--starts", type=int, default=64, help="starting poses (default 64)")
    oc.add_argument("--translation", type=float, default=None,
                    help="start shifts up to this far, metres (default 0.002; 0.003 around a registered pair)")
    oc.add_argument("--rotation", type=float, default=None, help="start turns up to this many degrees (default 3; 5 registered)")
    oc.add_argument("--threads", type=int, default=None, help="rollout threads (default: CPU count)")
    oc.add_argument("--seed", type=int, default=0)
    oc.add_argument("--top", type=int, default=5, help="candidates to report (default 5)")
    oc.add_argument("--out-dir", default="out/occlusion", help="occlusion.json, landscape.png, best.png")
    oc.add_argument("--no-contact-map", action="store_true", help="skip the occlusal contact map of the best pose")
    oc.add_argument("--no-picture", action="store_true", help="skip the rendering of the best pose (no GL needed)")
    oc.add_argument("--given-pose", action="store_true",
                    help="search around the pose the files give (default: register the arches from their shapes and "
                         "search from there, the given pose one more start)")
    oc.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    _add_pair_options(oc, tmj=True, files=True)
    oc.set_defaults(func=_cmd_occlusion)


def _add_pair_options(p, tmj: bool = False, files: bool = False) -> None:
    """Options for a user's jaw pair: units, up axis, hinge, repair (all detected by default);
    with ``files``, ``--maxilla FILE --mandible FILE`` instead of ``--data FOLDER``."""
    g = p.add_argument_group("jaw pair (with --data or mjist scene)")
    if files:
        g.add_argument("--maxilla", dest="maxilla_file", metavar="FILE",
                       help="the upper arch's mesh, named outright (with --mandible, instead of --data)")
        g.add_argument("--mandible", dest="mandible_file", metavar="FILE", help="the lower arch's mesh (with --maxilla)")
    g.add_argument("--units", default="auto", help="auto (default), mm, m, or mm,m for a maxilla and mandible stored differently")
    g.add_argument("--up", default="auto", choices=("auto", "+x", "-x", "+y", "-y", "+z", "-z"),
                   help="file axis pointing superior (default: detected from how the jaws open)")
    g.add_argument("--hinge", help="condylar axis centre x,y,z in the maxilla file's coordinates and units "
                                   "(default: the condyles, or Bonwill's estimate for teeth-only scans)")
    g.add_argument("--repair", default="auto", choices=("auto", "on", "off"),
                   help="auto (default): close an open or many-piece scan and warn; on: also fix winding and degenerate "
                        "faces; off: refuse them")
    g.add_argument("--max-deviation", type=float, default=None, metavar="MM",
                   help="refuse a closing that moves a scan's vertex farther than MM millimetres (default 0.2)")
    if tmj:
        g.add_argument("--tmj", default="on", choices=("on", "off"),
                       help="the occlusion search's soft TMJ joint at the hinge (default on; off: a free mandible)")


def _add_scene(sub) -> None:
    sc = sub.add_parser("scene", help="write a MuJoCo scene (MJCF) for your own maxilla + mandible meshes")
    sc.add_argument("maxilla", help="maxilla (upper jaw) mesh: STL/OBJ/PLY")
    sc.add_argument("mandible", help="mandible (lower jaw) mesh")
    sc.add_argument("--kind", choices=("closure", "occlusion", "haptic"), default="closure",
                    help="jaw closure by muscles, occlusion search, or haptic device (default closure)")
    sc.add_argument("-o", "--output", default="out/scene/scene.xml", help="MJCF file to write (default out/scene/scene.xml)")
    sc.add_argument("--max-error", type=float, default=None, help="mjist_max_error of the scene (metres, default 0.0003)")
    sc.add_argument("-q", "--quiet", action="store_true", help="do not print what was detected")
    _add_pair_options(sc, tmj=True)
    sc.set_defaults(func=_cmd_scene)


def _add_cohort(sub) -> None:
    co = sub.add_parser("cohort", help="many jaw pairs: trees, occlusion search and contact map per patient, on Ray, resumable")
    co.add_argument("input", nargs="?", help="folder of patient folders (each a maxilla + mandible mesh; optional "
                                             "manifest.csv beside them) or a manifest CSV")
    co.add_argument("--out", default="out/cohort", help="output folder (default out/cohort); a rerun resumes it")
    co.add_argument("--synthetic", type=int, default=0, metavar="N",
                    help="generate N procedural patients with known occlusions into OUT/input and run them")
    co.add_argument("--spacing", type=float, default=0.5, help="synthetic patients' polygonisation spacing, mm (default 0.5)")
    co.add_argument("--seed", type=int, default=0, help="synthetic cohort and search seed (default 0)")
    co.add_argument("--workers", type=int, default=None, help="local Ray CPUs (default: all of this machine's)")
    co.add_argument("--address", default=None, help="Ray cluster address (default $RAY_ADDRESS, else a local Ray)")
    co.add_argument("--serial", action="store_true", help="no Ray: one patient at a time in this process")
    co.add_argument("--retry-failed", action="store_true", help="run patients that failed before again")
    co.add_argument("--starts", type=int, default=64, help="occlusion-search starts per patient (default 64)")
    co.add_argument("--max-error", type=float, default=3e-4, help="trees' certified error bound, metres (default 0.0003)")
    co.add_argument("--cache", default=None, help="tree cache folder (default $MJIST_CACHE or ~/.cache/mjist; "
                                                   "on a cluster: a folder every node mounts)")
    co.add_argument("--no-picture", action="store_true", help="skip each patient's rendering")
    co.add_argument("--wafer", action="store_true", help="also make and prove a surgical wafer at each best occlusion "
                                                         "(patients/<id>/wafer.stl, .json, .png; figures in cohort.csv)")
    co.add_argument("-q", "--quiet", action="store_true", help="no progress")
    co.set_defaults(func=_cmd_cohort)


def _add_wafer(sub) -> None:
    wf = sub.add_parser("wafer", help="make a surgical wafer at the occlusion, prove it prints, seats and holds; write it as STL")
    wf.add_argument("folder", nargs="?", default=None, help="folder with the two arches (default: the bundled pair)")
    src = wf.add_mutually_exclusive_group()
    src.add_argument("--pose", metavar="OCCLUSION_JSON", help="the occlusion.json of `mjist occlusion` on this pair: its best pose")
    src.add_argument("--search", action="store_true", help="search the occlusion first (default: the pair's own occlusion)")
    wf.add_argument("--opening", type=float, default=None, metavar="DEG",
                    help="open the mandible this far about the hinge (default: the smallest that leaves --thickness)")
    wf.add_argument("--clearance", type=float, default=0.1, metavar="MM", help="gap between each arch and its imprint (default 0.1)")
    wf.add_argument("--thickness", type=float, default=1.5, metavar="MM", help="minimum thickness of the wafer (default 1.5)")
    wf.add_argument("-o", "--output", default="out/wafer/wafer.stl",
                    help="the wafer, in the maxilla file's frame and units (default out/wafer/wafer.stl; wafer.json and "
                         "wafer.png beside it)")
    wf.add_argument("--no-hold", action="store_true", help="skip the holding proof in MuJoCo")
    wf.add_argument("--no-picture", action="store_true", help="skip the picture (no GL needed)")
    wf.add_argument("--starts", type=int, default=64, help="with --search: starting poses (default 64)")
    wf.add_argument("--seed", type=int, default=0, help="with --search")
    wf.add_argument("--threads", type=int, default=None, help="with --search: rollout threads (default: CPU count)")
    wf.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    _add_pair_options(wf, files=True)
    wf.set_defaults(func=_cmd_wafer)


def _add_bench(sub) -> None:
    bn = sub.add_parser("bench", help="run the benchmark suite; write BENCHMARKS.generated.md and pareto.png")
    bn.add_argument("--quick", action="store_true", help="small sizes, under 5 minutes")
    bn.add_argument("--only", help="comma-separated stages: build, query, paper, scaling, mujoco, slide, haptic, occlusion, "
                                   "real_occlusion, cohort, wafer")
    bn.add_argument("--out-dir", default="out/bench")
    bn.set_defaults(func=_cmd_bench)


def build_parser() -> argparse.ArgumentParser:
    """The ``mjist`` command line: every subcommand and its options."""
    from . import __version__

    p = argparse.ArgumentParser(prog="mjist", description="Inner Sphere Tree collision detection for MuJoCo. "
                                "Lengths given on the command line are in metres (MuJoCo's unit), except "
                                "`mjist build`'s, which are in the mesh's own units; angles in degrees.")
    p.add_argument("--version", action="version", version=f"mjist {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True)
    for add in (_add_build, _add_info, _add_scene, _add_demo, _add_render, _add_view, _add_haptic, _add_occlusion, _add_wafer, _add_cohort,
                _add_bench):
        add(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    t = time.perf_counter()
    rc = args.func(args)
    if args.cmd == "build" and rc == 0:
        print(f"done in {time.perf_counter() - t:.1f}s")
    return rc


if __name__ == "__main__":
    sys.exit(main())
