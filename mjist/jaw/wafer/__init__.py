"""Surgical wafers (occlusal splints): ``mjist wafer`` (docs/wafer.md).

One decision per module:

``shape``      the wafer between two arches at their occlusion (height fields, opened by a ball)
``grid``       the height-field grid: surfaces seen along up, grey morphology by a ball
``outline``    where the wafer lies (the dentition's outline), how deep it wraps the crowns, the cusp tips
``opening``    how far the mandible opens about the hinge for the wafer's thickness
``mesh``       the closed mesh of two height fields
``printable``  proof: closed, one shell, embedded, thick enough
``seating``    proof: both arches seat (coal), every cusp in its imprint
``holding``    proof: the mandible held under pushes (MuJoCo with mjist contacts)
``job``        the command: where the occlusion comes from, frames and units, files
``picture``    wafer.png
"""
from .job import main, make
from .shape import WaferShape

__all__ = ["make", "main", "WaferShape"]
