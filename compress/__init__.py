"""What is done with coefficients.

Truncation, filtering, low rank, storage precision, order selection, error/resolution studies
and charts, HDF5 storage, pictures of a BRDF on a lit sphere, and the ``scatmodes`` command.

Imports flow one way: ``compress`` -> ``project`` -> ``basis``.

The public names are imported on first use (PEP 562): the ``scatmodes`` command imports this
package, and answers ``--version`` and ``--help`` without loading numba, SciPy, h5py or
matplotlib. Submodules such as :mod:`compress.mitsuba` load when first named.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what static tools see; at run time __getattr__ imports these on first use
    from basis import __version__ as __version__

    from .evaluate import FastEvaluator, evaluate
    from .hybrid import Hybrid, hybrid
    from .render import render_sphere, tonemap
    from .report import report
    from .scene import Environment, ScenePlan, for_scene, select_order
    from .selection import NoCandidateError, select
    from .store import load, save
    from .study import (
        KINDS,
        METRICS,
        Study,
        errors,
        make_basis,
        pareto_front,
        reference_samples,
        study,
    )
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

#: public name -> the submodule that defines it
_EXPORTS = {
    "FastEvaluator": "evaluate", "evaluate": "evaluate",
    "Hybrid": "hybrid", "hybrid": "hybrid",
    "render_sphere": "render", "tonemap": "render",
    "report": "report",
    "Environment": "scene", "ScenePlan": "scene", "for_scene": "scene", "select_order": "scene",
    "NoCandidateError": "selection", "select": "selection",
    "load": "store", "save": "store",
    "KINDS": "study", "METRICS": "study", "Study": "study", "errors": "study",
    "make_basis": "study", "pareto_front": "study", "reference_samples": "study",
    "study": "study",
    "Ringing": "truncate", "lowrank": "truncate", "precision": "truncate", "ringing": "truncate",
    "smooth": "truncate", "smoothing_factors": "truncate", "truncate": "truncate",
    "unique_coefficients": "truncate",
}

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
    "report",
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


def __getattr__(name: str) -> Any:
    """Import a public name, ``__version__`` or a submodule on first use (PEP 562)."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    elif name == "__version__":  # one version for the distribution
        from basis import __version__ as value
    elif not name.startswith("__") and importlib.util.find_spec(f"{__name__}.{name}"):
        return importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later look-ups are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__, "__version__"})


class _Package(types.ModuleType):
    """The package's module type: a submodule import does not hide a function of its name."""

    def __setattr__(self, name: str, value: Any) -> None:
        # importing compress.truncate (the module) binds it on the package; the public name
        # is the function truncate, which __getattr__ fetches from that module
        if name in _EXPORTS and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
