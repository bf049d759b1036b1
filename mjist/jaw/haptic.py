"""A simulated haptic device moving the mandible against the maxilla: ``mjist haptic``.

The device is the scene's ``handle`` mocap body; the mandible follows it through the virtual
coupling and meets the maxilla through IST penalty forces (``mjist.mujoco.forces``), all inside
``mj_step``. A device trajectory is a handle pose per 1 ms step: scripted ones (``close``,
``lateral_left``, ``lateral_right``, ``protrusion``, ``chewing``, ``press``, ``push``, ``hold``) move the
handle about the condylar hinge (the scene's ``hinge`` site) relative to the ``occlusion``
keyframe; a CSV file (``time, x, y, z, qw, qx, qy, qz``, world frame, seconds and metres) is
replayed, resampled to the timestep (linear positions, slerp orientations).

``run`` logs per step: handle and mandible pose, the coupling force/torque (the device
displays their opposite), contact force, contact groups, deepest penetration, penetration
volume, and the loop time (mocap update → ``mj_step`` → force readout).
"""
from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..mujoco import layout
from ..mujoco.attach import load_model
from ..mujoco.handle import Handle
from . import pair as jawmod
from .scenes import pair_scene

SCENE = jawmod.BUNDLED / "haptic_jaw.xml"
PRESS_DEG = -0.3  # how far past the occlusion the scripted paths push the handle (about the hinge)


def _smooth(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _lerp(t, t0, t1, a, b):
    return a + (b - a) * _smooth((t - t0) / (t1 - t0))


def _close(t):
    # from 4° open: the bundled teeth start ~1.3 mm apart, clear of the 2 x 0.5 mm ε of the scene
    return _lerp(t, 0.0, 1.0, 4.0, PRESS_DEG), (0.0, 0.0, 0.0)


def _excursion(axis, sign):
    def f(t):
        th = _lerp(t, 0.0, 0.3, 1.0, PRESS_DEG)
        s = sign * 0.003 * (_smooth((t - 0.3) / 0.7) - _smooth((t - 1.2) / 0.6))
        off = [0.0, 0.0, 0.0]
        off[axis] = s
        return th, tuple(off)
    return f


def _chewing(t):
    """1 s cycles: open 5° and swing 2 mm to one side (alternating), close, press into the occlusion."""
    u = t % 1.0
    if u < 0.8:
        th = 5.0 * np.sin(np.pi * u / 0.8) ** 2
    else:
        th = PRESS_DEG * np.sin(np.pi * (u - 0.8) / 0.2) ** 2
    lat = 0.002 * np.sin(np.pi * min(u / 0.8, 1.0)) ** 2 * (1 if int(t) % 2 == 0 else -1)
    return th, (lat, 0.0, 0.0)


def _press(t):
    return _lerp(t, 0.0, 1.5, 0.5, -1.0), (0.0, 0.0, 0.0)


def _push(t):
    return _lerp(t, 0.0, 1.0, 0.5, -3.0), (0.0, 0.0, 0.0)


def _hold(t):
    return PRESS_DEG, (0.0, 0.0, 0.0)


TRAJECTORIES = {  # name -> (hinge angle in degrees and jaw-frame offset in metres at time t, duration s)
    "close": (_close, 1.5),
    "lateral_left": (_excursion(0, 1.0), 2.0),
    "lateral_right": (_excursion(0, -1.0), 2.0),
    "protrusion": (_excursion(2, 1.0), 2.0),
    "chewing": (_chewing, 2.0),
    "press": (_press, 1.5),
    "push": (_push, 1.5),
    "hold": (_hold, 60.0),
}


@dataclass
class DevicePath:
    """Handle poses per step: ``pos (n, 3)``, ``quat (n, 4)`` (w, x, y, z), world frame."""

    name: str
    pos: np.ndarray
    quat: np.ndarray
    dt: float

    @property
    def steps(self) -> int:
        return int(self.pos.shape[0])


def _occlusion(model):
    from .scenes import reference_pose

    pos, _, R, hinge, R_jaw = reference_pose(model)
    return pos, R, hinge, R_jaw[:, 0].copy(), R_jaw  # the jaw frame's x axis is the hinge axis


def scripted(model, name: str, seconds: float | None = None) -> DevicePath:
    """Handle poses of a scripted trajectory for ``model`` (a haptic scene)."""
    if name not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {name!r}: use one of {', '.join(TRAJECTORIES)} or a CSV file")
    f, dur = TRAJECTORIES[name]
    dur = float(seconds or dur)
    dt = float(model.opt.timestep)
    n = int(round(dur / dt))
    p0, R0, hinge, axis, R_jaw = _occlusion(model)
    pos = np.empty((n, 3))
    quat = np.empty((n, 4))
    for i in range(n):
        th, off = f((i + 1) * dt)
        Rh = Rotation.from_rotvec(np.radians(th) * axis)
        pos[i] = hinge + Rh.apply(p0 - hinge) + R_jaw @ np.asarray(off, float)
        x, y, z, w = (Rh * Rotation.from_matrix(R0)).as_quat()
        quat[i] = (w, x, y, z)
    return DevicePath(name, pos, quat, dt)


def load_csv(path, dt: float) -> DevicePath:
    """A recorded device motion (``time, x, y, z, qw, qx, qy, qz`` per row, header optional) at step ``dt``."""
    rows = []
    with open(path, newline="") as fh:
        for r in csv.reader(fh):
            if not r or r[0].strip().startswith("#"):
                continue
            try:
                row = [float(x) for x in r]
            except ValueError:
                if rows:
                    raise ValueError(f"{path}: row {len(rows) + 1} is not 8 numbers: {r}") from None
                continue  # a header
            if len(row) != 8:
                raise ValueError(f"{path}: row {len(rows) + 1} has {len(row)} numbers, not 8 (time, x, y, z, qw, qx, qy, qz)")
            rows.append(row)
    a = np.asarray(rows, float)
    if a.ndim != 2 or a.shape[1] != 8 or a.shape[0] < 2:
        raise ValueError(f"{path}: need ≥ 2 rows of 8 numbers: time, x, y, z, qw, qx, qy, qz")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{path}: contains NaN or infinite values")
    t = a[:, 0]
    if np.any(np.diff(t) <= 0):
        raise ValueError(f"{path}: time must increase strictly from row to row")
    q = a[:, 4:8]
    nq = np.linalg.norm(q, axis=1)
    if np.any(nq < 1e-9):
        raise ValueError(f"{path}: a quaternion is zero")
    q = q / nq[:, None]
    ts = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    ts = ts[ts <= t[-1] + 1e-12]
    pos = np.stack([np.interp(ts, t, a[:, 1 + k]) for k in range(3)], axis=1)
    rot = Slerp(t, Rotation.from_quat(q[:, [1, 2, 3, 0]]))(ts).as_quat()
    return DevicePath(Path(path).stem, pos, rot[:, [3, 0, 1, 2]], dt)


def save_csv(path_obj: DevicePath, out) -> str:
    """Write a device path as CSV (the format ``load_csv`` reads)."""
    t = (np.arange(path_obj.steps) + 1) * path_obj.dt
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time", "x", "y", "z", "qw", "qx", "qy", "qz"])
        for i in range(path_obj.steps):
            w.writerow([f"{t[i]:.6f}", *(f"{v:.9g}" for v in path_obj.pos[i]), *(f"{v:.9g}" for v in path_obj.quat[i])])
    return str(out)


def readout(handle: Handle, data) -> tuple[np.ndarray, np.ndarray]:
    """Live views of the penalty pair's and the coupling's output rows for ``data`` (after one step).

    They update in place at every step of this ``data`` (no Python per step to read forces);
    a row that does not exist reads as zeros.
    """
    pen, cpl = handle.output_rows(data)
    return (pen if pen is not None else np.zeros(layout.PO)), (cpl if cpl is not None else np.zeros(layout.PO))


def run(model, handle: Handle, path: DevicePath, *, start: str | None = "auto", progress: bool = False) -> dict:
    """Drive the handle along ``path`` with ``mj_step``; return the per-step log (numpy arrays)."""
    from ..mujoco import registry

    if not registry.passive_is_ours():
        raise RuntimeError("mjcb_passive no longer holds mjist's callback (mujoco.set_mjcb_passive replaced it): "
                           "penalty forces and the coupling would not be applied; re-attach the model")
    d = mujoco.MjData(model)
    handle.forget(d)  # a freed MjData may have lived at this address
    b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "mandible")
    # start with the mandible on the handle (at rest), so the coupling starts unloaded
    d.qpos[:3] = path.pos[0]
    d.qpos[3:7] = path.quat[0]
    d.mocap_pos[0] = path.pos[0]
    d.mocap_quat[0] = path.quat[0]
    mujoco.mj_forward(model, d)
    pen_row, cpl_row = readout(handle, d)
    n = path.steps
    log = {k: np.zeros((n, w)) for k, w in (("handle_pos", 3), ("handle_quat", 4), ("mandible_pos", 3), ("mandible_quat", 4),
                                            ("coupling_force", 3), ("coupling_torque", 3), ("contact_force", 3),
                                            ("contact_torque", 3))}
    log.update({k: np.zeros(n) for k in ("contacts", "depth", "volume", "loop_us", "time")})
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, desc=f"haptic {path.name}", unit="step", leave=False)
    mp, mq = d.mocap_pos, d.mocap_quat
    F = layout
    for i in range(n):
        t0 = time.perf_counter()
        mp[0] = path.pos[i]
        mq[0] = path.quat[i]
        mujoco.mj_step(model, d)
        fc = cpl_row[F.O_F:F.O_F + 3].copy()
        log["loop_us"][i] = (time.perf_counter() - t0) * 1e6
        log["coupling_force"][i] = fc
        log["coupling_torque"][i] = cpl_row[F.O_T:F.O_T + 3]
        log["contact_force"][i] = pen_row[F.O_F:F.O_F + 3]
        log["contact_torque"][i] = pen_row[F.O_T:F.O_T + 3]
        log["contacts"][i] = pen_row[F.O_N]
        log["depth"][i] = pen_row[F.O_DEPTH]
        log["volume"][i] = pen_row[F.O_VOL]
        log["handle_pos"][i] = path.pos[i]
        log["handle_quat"][i] = path.quat[i]
        log["mandible_pos"][i] = d.xpos[b]
        log["mandible_quat"][i] = d.xquat[b]
        log["time"][i] = d.time
        if bar is not None and i % 100 == 0:
            bar.update(100)
    if bar is not None:
        bar.close()
    log["_data"] = d
    return log


def summary(log: dict) -> dict:
    """Loop time and force figures of a run."""
    lt = log["loop_us"]
    fc = np.linalg.norm(log["coupling_force"], axis=1)
    fk = np.linalg.norm(log["contact_force"], axis=1)
    return {
        "steps": int(lt.size),
        "loop_us_median": float(np.median(lt)), "loop_us_p99": float(np.percentile(lt, 99)),
        "loop_us_max": float(lt.max()),
        "device_force_max_N": float(fc.max()), "contact_force_max_N": float(fk.max()),
        "contact_steps": int(np.count_nonzero(log["contacts"])), "depth_max_mm": float(log["depth"].max() * 1e3),
        "volume_max_mm3": float(log["volume"].max() * 1e9),
        "force_step_max_N": float(np.abs(np.diff(log["contact_force"], axis=0)).max()) if lt.size > 1 else 0.0,
        "finite": bool(all(np.all(np.isfinite(v)) for k, v in log.items() if isinstance(v, np.ndarray))),
    }


def plot(log: dict, out, title: str = "") -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = log["time"]
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    ax[0].plot(t, np.linalg.norm(log["coupling_force"], axis=1), label="device force |F| (coupling)")
    ax[0].plot(t, np.linalg.norm(log["contact_force"], axis=1), label="contact force |F| (IST penalty)", alpha=0.8)
    ax[0].set_ylabel("N")
    ax[0].legend(fontsize=8)
    ax[1].plot(t, log["depth"] * 1e3, label="deepest contact (mm)")
    ax[1].plot(t, log["volume"] * 1e9, label="penetration volume (mm³)")
    ax[1].legend(fontsize=8)
    ax[2].plot(t, log["loop_us"], lw=0.5)
    ax[2].set_ylabel("loop µs")
    ax[2].set_yscale("log")
    ax[2].set_xlabel("simulated time (s)")
    ax[0].set_title(title)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return str(out)


def main(scene=None, trajectory: str = "chewing", law: str | None = None, seconds: float | None = None,
         out="out/haptic", progress: bool = True, data=None, pair: dict | None = None) -> int:
    """``mjist haptic``: ``data`` is a jaw-pair folder read with ``pair`` options (``scenes.pair_scene``)."""
    if data is not None or (pair or {}).get("maxilla"):
        scene = pair_scene(data, out, "haptic", progress=progress, **(pair or {}))
    scene = Path(scene or SCENE)
    settings = {"penalty": law} if law else {}
    model, handle = load_model(scene, progress=progress, **settings)
    print(handle.summary())
    try:
        if trajectory in TRAJECTORIES:
            path = scripted(model, trajectory, seconds)
        else:
            path = load_csv(trajectory, float(model.opt.timestep))
        log = run(model, handle, path, progress=progress)
        log.pop("_data")
        s = summary(log)
        s.update(trajectory=path.name, scene=str(scene), law=handle.config.penalty,
                 error_bound_mm=handle.pairs[0].error_bound * 1e3 if handle.pairs else None)
        out = Path(out)
        os.makedirs(out, exist_ok=True)
        np.savez_compressed(out / f"{path.name}_log.npz", **log)
        (out / f"{path.name}.json").write_text(json.dumps(s, indent=2))
        png = plot(log, out / f"{path.name}.png", f"{path.name}: {handle.config.penalty} law, ε1+ε2 = {s['error_bound_mm']:.2f} mm")
        print(f"loop          {s['loop_us_median']:.1f} µs median, {s['loop_us_p99']:.1f} µs p99 (mocap → mj_step → forces), "
              f"{s['steps']} steps")
        print(f"forces        device up to {s['device_force_max_N']:.2f} N, contact up to {s['contact_force_max_N']:.2f} N, "
              f"deepest {s['depth_max_mm']:.3f} mm, volume up to {s['volume_max_mm3']:.3f} mm³")
        print(f"written       {out / (path.name + '_log.npz')}, {out / (path.name + '.json')}, {png}")
    finally:
        handle.detach()
    return 0
