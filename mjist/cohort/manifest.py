"""Which patients a cohort holds, and the key that says whether a patient's result is current.

INPUT is a folder of patient folders (each as ``mjist.jaw.pair.load_pair`` reads it: a maxilla
and a mandible mesh, optionally ``design.json``), optionally with a ``manifest.csv`` beside them
giving per-patient options; or a manifest CSV itself. Manifest columns (all but ``patient``
optional): ``patient``, ``folder`` or ``maxilla`` + ``mandible`` (paths relative to the CSV),
``units``, ``up``, ``hinge`` ("x y z", the maxilla file's units), ``repair``.
"""
from __future__ import annotations

import csv
import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

from .synthetic import DESIGN_FILE

MANIFEST = "manifest.csv"
OPTIONS = ("units", "up", "hinge", "repair")


@dataclass(frozen=True)
class Patient:
    """One jaw pair of a cohort: where its meshes are and how to read them."""

    id: str
    folder: str | None = None
    maxilla: str | None = None
    mandible: str | None = None
    units: str = "auto"
    up: str = "auto"
    hinge: tuple | None = None
    repair: str = "auto"

    def pair_options(self) -> dict:
        """Keyword arguments of ``load_pair`` / ``pair_scene``."""
        return {"maxilla": self.maxilla, "mandible": self.mandible, "units": self.units, "up": self.up,
                "hinge": self.hinge, "repair": self.repair}

    def files(self) -> list[Path]:
        """The input files whose bytes decide the result (those that exist)."""
        if self.maxilla or self.mandible:
            cand = [Path(p) for p in (self.maxilla, self.mandible) if p]
        else:
            f = Path(self.folder)
            cand = [f / f"{n}{e}" for n in ("maxilla", "mandible") for e in (".obj", ".stl", ".ply")]
            cand += [f / "occlusion.json"]
        cand += [Path(self.folder or Path(self.maxilla or ".").parent) / DESIGN_FILE]
        return [p for p in cand if p.is_file()]

    def design(self) -> Path | None:
        """The designed occlusion (a synthetic patient's ``design.json``), if the patient has one."""
        p = Path(self.folder or Path(self.maxilla or ".").parent) / DESIGN_FILE
        return p if p.is_file() else None


def _row_options(row: dict, base: Path) -> dict:
    out = {}
    for k in ("folder", "maxilla", "mandible"):
        if row.get(k):
            out[k] = str((base / row[k]).resolve())
    for k in OPTIONS:
        v = (row.get(k) or "").strip()
        if v:
            out[k] = tuple(float(x) for x in v.replace(",", " ").split()) if k == "hinge" else v
            if k == "hinge" and len(out[k]) != 3:
                raise ValueError(f"got {len(out[k])} numbers")
    return out


def _read_manifest(path: Path) -> dict[str, dict]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if rows and "patient" not in rows[0]:
        raise ValueError(f"{path}: a manifest needs a 'patient' column (and folder, or maxilla + mandible; "
                         f"optional {', '.join(OPTIONS)})")
    out = {}
    for i, row in enumerate(rows):
        pid = (row.get("patient") or "").strip()
        if not pid:
            raise ValueError(f"{path}, row {i + 2}: empty patient id")
        if pid in out:
            raise ValueError(f"{path}: patient {pid!r} appears twice")
        try:
            out[pid] = _row_options(row, path.parent)
        except ValueError as exc:
            raise ValueError(f"{path}, patient {pid!r}: hinge must be three numbers 'x y z' ({exc})") from exc
    return out


def discover(input) -> list[Patient]:
    """The cohort's patients, sorted by id.

    Raises ``FileNotFoundError``/``ValueError`` naming the problem when INPUT is neither a
    folder of patient folders nor a manifest CSV.
    """
    path = Path(input)
    if not path.exists():
        raise FileNotFoundError(f"cohort input {path} does not exist: give a folder of patient folders or a manifest CSV")
    if path.is_file():
        rows = _read_manifest(path)
        patients = []
        for pid, o in rows.items():
            if "folder" not in o and not ("maxilla" in o and "mandible" in o):
                raise ValueError(f"{path}, patient {pid!r}: give a folder, or both maxilla and mandible")
            patients.append(Patient(id=pid, **o))
        return sorted(patients, key=lambda p: p.id)
    extra = _read_manifest(path / MANIFEST) if (path / MANIFEST).exists() else {}
    folders = sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith((".", "_")))
    if not folders and not extra:
        raise ValueError(f"{path} holds no patient folders (each with a maxilla and a mandible mesh)")
    patients = {f.name: Patient(id=f.name, folder=str(f.resolve())) for f in folders}
    for pid, o in extra.items():
        base = asdict(patients[pid]) if pid in patients else {"id": pid}
        patients[pid] = Patient(**{**base, **o})
    return [patients[k] for k in sorted(patients)]


def patient_key(p: Patient, settings: dict, version: str) -> str:
    """Hash of everything a patient's result depends on: its files' bytes, its options, the
    cohort settings that change results and mjist's version."""
    h = hashlib.sha256()
    for f in p.files():
        h.update(f.name.encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    h.update(json.dumps({**asdict(p), "settings": settings, "version": version}, sort_keys=True, default=str).encode())
    return h.hexdigest()[:24]
