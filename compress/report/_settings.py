"""What the report shows and how finely: angles, lights, sample counts, sizes, candidates."""

from __future__ import annotations

import math
from typing import Any

#: Incidence angles (degrees) of the lobe plots.
INCIDENCE_DEG = (0.0, 30.0, 60.0, 75.0)
#: Lights of the sphere pictures and of the image error: unit vectors in the frame of the
#: view (0, 0, 1): from the view direction, 45 degrees and 75 degrees off it.
LIGHTS = ((0.0, 0.0, 1.0),
          (math.sin(math.radians(45.0)), 0.0, math.cos(math.radians(45.0))),
          (0.0, math.sin(math.radians(75.0)), math.cos(math.radians(75.0))))
_VIEW = (0.0, 0.0, 1.0)
#: Published sizes of compact MERL representations (bytes per material), for the charts.
PUBLISHED = {"neural BRDF (Sztrajman et al. 2021)": 2700,
             "factored microfacet (Bagher et al. 2016)": 3200,
             "RGL adaptive tensor (Dupuy & Jakob 2018), ~16 KiB a channel": 3 * 16384}
#: Candidates of the small table computed when the input holds none: a microfacet lobe, a
#: rank-1 factored lobe, two Zernike orders and three half/difference tables, one storage
#: type (float32): about 2 s of CPU on a MERL table.
REPORT_CANDIDATES: tuple[dict[str, Any], ...] = (
    {"form": "model", "family": "lambert+ggx", "restarts": 1},
    {"form": "model", "family": "factored", "rank": 1, "bins": (32, 24)},
    {"form": "modal", "kind": "zernike", "order": 4},
    {"form": "modal", "kind": "zernike", "order": 8},
    {"form": "model", "family": "tabulated", "bins": (16, 12, 4)},
    {"form": "model", "family": "tabulated", "bins": (24, 16, 16)},
    {"form": "model", "family": "tabulated", "bins": (32, 24, 16)},
)
#: The same for measurements (fitted to the samples, cross-validated).
_SAMPLE_CANDIDATES: tuple[dict[str, Any], ...] = (
    {"form": "model", "family": "lambert+ggx"},
    {"form": "model", "family": "lafortune", "lobes": 1, "restarts": 2},
    {"form": "modal", "kind": "zernike", "order": 2},
    {"form": "modal", "kind": "zernike", "order": 4},
)
#: Wavelengths (nm) whose nearest measured channels a report of a spectral table shows (and
#: fits): a blue, a green and a red.
SHOWN_NM = (450.0, 550.0, 650.0)
#: Band edges (degrees) of theta_i and theta_o in section 4.
BANDS_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
#: Pairs of the error estimates (project.sampling.peak_resolving_pairs); seed of the pairs.
ERROR_PAIRS = 1 << 15
_SEED = 2027
#: Pairs of the reciprocity estimate (about 0.1 s on a MERL table).
RECIPROCITY_PAIRS = 1 << 14
#: Side of the sphere pictures in pixels (that of the image error).
SPHERE_SIZE = 128
#: Pixels per side of the outgoing-hemisphere heat maps.
_HEAT = 61
#: Decades below the peak that a logarithmic radius spans in the polar plots.
_DECADES = 4
_DPI = 80
