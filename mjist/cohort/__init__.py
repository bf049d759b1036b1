"""Cohorts: many jaw pairs through load → trees → occlusion search → contact map, resumably, on Ray.

``mjist.cohort.run(input, out)`` / ``mjist cohort INPUT --out DIR``: ``manifest`` finds the
patients, ``stages`` is what happens to one patient, ``backends`` runs the stages (in this
process, or as Ray tasks on this machine or a cluster), ``runner`` resumes, records and
reports (``report``), ``synthetic`` writes a cohort whose occlusions are known. Ray is an
optional dependency (``pip install 'mjist[cluster]'``) imported only when a cohort runs on it.
"""
from .manifest import Patient, discover
from .runner import run

__all__ = ["run", "discover", "Patient"]
