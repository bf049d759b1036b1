"""Exceptions raised by mjist. Each message names the problem and the fix."""


class MeshError(ValueError):
    """The input mesh cannot be filled with inner spheres (open, inverted, degenerate, ...)."""


class TreeFileError(ValueError):
    """A saved tree (or cache entry) is corrupt, of another format version, or for another mesh."""


class ConfigError(ValueError):
    """The model's mjist configuration (MJCF ``<custom>`` or ``attach`` arguments) is invalid."""
