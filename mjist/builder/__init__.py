"""The tree builder: mesh → lattice levels (``voxelize``) → inner spheres (``packing``) →
hierarchy (``hierarchy``) → certified error bound (``bound``), run by ``pipeline`` with the
tuning constants of ``params``."""
