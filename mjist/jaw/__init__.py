"""The jaw application: jaw pairs and their occlusion (``pair``), the procedural jaw generator
(``generator``), scene writers (``scenes``), jaw closure (``demo``), the simulated haptic
device (``haptic``) and the occlusion search (``occlusion``)."""
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
