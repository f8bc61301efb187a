"""Measured BRDFs: one module per source.

- :mod:`project.measured.merl`: the MERL database's ``.binary`` tables (Matusik et al. 2003):
  :func:`read_merl`, :func:`write_merl`, :class:`MERLBRDF`.
"""

from .merl import MERL_BYTES, MERL_SCALE, MERL_SHAPE, MERLBRDF, merl_grid, read_merl, write_merl

__all__ = [
    "MERL_BYTES",
    "MERL_SCALE",
    "MERL_SHAPE",
    "MERLBRDF",
    "merl_grid",
    "read_merl",
    "write_merl",
]
