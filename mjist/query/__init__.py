"""Queries on trees: tree–tree kernels (``traverse``), tree–primitive kernels (``primitive``),
contact selection (``select``), and the Python API (``api``: ``Query`` and its results)."""
