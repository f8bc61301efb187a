"""Atomic file output (see :func:`project._io.atomic_path`, which every writer shares)."""

from project._io import atomic_path

__all__ = ["atomic_path"]
