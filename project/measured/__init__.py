"""Measured BRDFs: one module per source.

- :mod:`project.measured.merl`: the MERL database's ``.binary`` tables (Matusik et al. 2003):
  :func:`read_merl`, :func:`write_merl`, :class:`MERLBRDF`.
- :mod:`project.measured.rgl`: the RGL-EPFL database's ``.bsdf`` tensor files (Dupuy &
  Jakob 2018): :func:`read_rgl`, :class:`RGLBRDF`, :func:`read_tensor_file`,
  :func:`write_tensor_file`.
- :mod:`project.measured.mbsdf`: NVIDIA MDL measured BSDF files (``.mbsdf``, the MDL SDK's
  "NVIDIA ARC MBSDF V1"): :func:`read_mbsdf`, :func:`write_mbsdf`, :class:`MBSDFBRDF`.
- :mod:`project.measured.tables`: scattered measurements in text files (plain tables, CSV,
  the Cornell ``.brdf`` format): :func:`read_measurements`, :func:`write_measurements`.
"""

from .mbsdf import MBSDFBRDF, read_mbsdf, texel_centres, write_mbsdf
from .merl import MERL_BYTES, MERL_SCALE, MERL_SHAPE, MERLBRDF, merl_grid, read_merl, write_merl
from .rgl import RGLBRDF, read_rgl, read_tensor_file, write_tensor_file
from .tables import read_measurements, write_measurements

__all__ = [
    "MBSDFBRDF",
    "MERL_BYTES",
    "MERL_SCALE",
    "MERL_SHAPE",
    "MERLBRDF",
    "RGLBRDF",
    "merl_grid",
    "read_mbsdf",
    "read_measurements",
    "read_merl",
    "read_rgl",
    "read_tensor_file",
    "texel_centres",
    "write_mbsdf",
    "write_measurements",
    "write_merl",
    "write_tensor_file",
]
