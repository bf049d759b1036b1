"""The jaw application: a user's jaw pairs and their occlusion (``pair``, with ``orient`` for
units and axes and ``arch`` for each arch's own frame), the procedural jaw generator
(``generator``), scene writers (``scenes``), jaw closure (``demo``), the simulated haptic
device (``haptic``), the occlusion search (``occlusion``) and its contact map (``contactmap``)."""
from __future__ import annotations

from pathlib import Path


def bundled_models() -> Path:
    """The folder of the bundled jaws and their scenes.

    An installed wheel carries them as package data (``mjist/jaw/models``); a source checkout
    keeps them in ``models/`` at the top of the repository.
    """
    here = Path(__file__).resolve().parent
    packaged = here / "models"
    return packaged if packaged.is_dir() else here.parents[1] / "models"


BUNDLED = bundled_models()


def contact_map(model, handle, pos, quat, **kwargs) -> dict:
    """The occlusal contact map of an occlusion-search scene with the mandible body at ``pos``,
    ``quat`` (``contactmap.contact_map``; write it with ``contactmap.write``)."""
    from .contactmap import contact_map as _contact_map

    return _contact_map(model, handle, pos, quat, **kwargs)
