"""What is done with coefficients.

Truncation, filtering, low rank, storage precision, order selection, error/resolution studies
and charts, HDF5 storage, pictures of a BRDF on a lit sphere, and the ``scatmodes`` command.

Imports flow one way: ``compress`` -> ``project`` -> ``basis``.
"""

from basis import __version__  # noqa: F401 - one version for the distribution

from .evaluate import FastEvaluator, evaluate
from .hybrid import Hybrid, hybrid
from .render import render_sphere, tonemap
from .scene import Environment, ScenePlan, for_scene, select_order
from .selection import NoCandidateError, select
from .store import load, save
from .study import KINDS, METRICS, Study, errors, make_basis, pareto_front, reference_samples, study
from .truncate import (
    Ringing,
    lowrank,
    precision,
    ringing,
    smooth,
    smoothing_factors,
    truncate,
    unique_coefficients,
)

__all__ = [
    "KINDS",
    "METRICS",
    "NoCandidateError",
    "Environment",
    "FastEvaluator",
    "Hybrid",
    "Ringing",
    "ScenePlan",
    "Study",
    "errors",
    "evaluate",
    "for_scene",
    "hybrid",
    "load",
    "lowrank",
    "make_basis",
    "pareto_front",
    "precision",
    "reference_samples",
    "render_sphere",
    "ringing",
    "save",
    "select",
    "select_order",
    "smooth",
    "smoothing_factors",
    "study",
    "tonemap",
    "truncate",
    "unique_coefficients",
]
