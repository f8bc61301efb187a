"""The fitted model and the fit: :class:`FittedModel` and :func:`fit_model`.

Both are re-exported by :mod:`project.fitting`, whose notes list the families and the
modules that describe them. Here: the "factored" family, whose lobe lives in
:mod:`project.factored`, and how the parametric families are fitted.

The "factored" family
---------------------
``"factored"`` (kd, tables and colour weights: 271 reals, 2168 bytes, at the defaults)
    f = kd/pi + sum_k w_k A_k(theta_h) B_k(theta_d) C_k(phi_d), the non-parametric factored
    lobe of :class:`project.factored.FactoredLobe` (non-negative piecewise-linear tables in
    the half/difference angles of Rusinkiewicz 1998), fitted by
    :func:`project.factored.fit_factored` (non-negative alternating least squares on a
    quadrature rule in those angles; ``metric="l2"`` only). The options are those of
    ``fit_factored`` (``rank``, ``bins``, ``warp``, ``warp_d``, ``color``, ...) and the
    error pairs below. Parameters: ``kd`` (C,), ``h_table`` (rank, n_h, 1 or C),
    ``d_table`` (rank, n_d, 1 or C), optionally ``phi_table`` (rank, n_phi) and
    ``weights`` (rank, C), and the node spacings ``warp`` and ``warp_d`` (the exponents of
    :data:`project.factored.WARPS` and :data:`~project.factored.D_WARPS`; not counted in
    ``nparams``). ``phi_turn="full"`` (default ``"half"``, also for a BRDF whose
    ``reciprocal`` is False) fits phi_d tables over the whole turn, which hold the
    antisymmetric part of non-reciprocal data; such a model has ``reciprocal`` False and
    its params hold ``phi_turn`` = 1.0 (params without it are half-turn lobes).

The "tucker" family
-------------------
``"tucker"`` (knots, factor values at the knots, a core and a colour factor)
    :class:`project.tucker.TuckerBRDF`, a Tucker tensor of piecewise-linear curves in
    (theta_h, theta_d, phi_d) with knots placed per material: the coupling of the angles
    that a factored lobe cannot hold, in a few kilobytes. ``fit_model(brdf, "tucker",
    budget=2048)`` calls :func:`project.tucker.fit_tucker` (options ``budget``, ``ranks``,
    ``knots``, ``color_rank``, ``grid``, ``warp_d``, ``phi_turn``), which chooses the
    ranks and knots within the budget of stored reals.

The "tabulated" family
----------------------
``"tabulated"`` (a (n_h, n_d, m, C) table of q = f cos cos and three grid options)
    :class:`project.tabulated.TabulatedBRDF`, a trilinear table in (theta_h, theta_d, phi_d)
    at any resolution, phi_d over the whole turn for non-reciprocal data. "Fitting" is
    sampling: ``fit_model(brdf, "tabulated", bins=(n_h, n_d, n_phi))`` calls
    :func:`project.tabulated.tabulate` (options ``bins``, ``quantity``, ``phi_turn``,
    ``warp_d``, ``sample``) and reports the errors on the error pairs below.

Fitting
-------
The parametric families are fitted as follows (for ``"factored"`` see its module). The
fitting pairs are ``peak_resolving_pairs(n, seed=seed)``; the BRDF is evaluated there once.
Residuals, one per pair and channel:

- ``metric="l2"``: sqrt(w) (q_model - q) / ||q_c||, q = f cos theta_i cos theta_o, w the
  pair weights and ||q_c||^2 = sum w q_c^2 per channel, so the cost 0.5 sum r^2 is half the
  sum over channels of the squared relative l2 errors of :func:`project.sampling.relative_l2`
  (each channel counts equally, whatever its brightness);
- ``metric="log"``: sqrt(w / sum w) (log(1 + f_model cos theta_i) - log(1 + f cos theta_i)),
  the log metric of :func:`project.sampling.log_rms`.

They are minimised by ``scipy.optimize.least_squares`` (trust-region reflective, bounds,
analytic Jacobians (for "lambert+ggx" and "lambert+beckmann" in closed form, computed with
the residuals in one pass over the pairs; for "rr8807" the derivative of Lambda in p comes
from the derivative of its quadrature, splined alike), roughness and exponents in log
scale) from ``restarts`` starting points.

"lambert+ggx", "lambert+beckmann" and one-lobe "lafortune" in the l2 metric are solved by
variable projection (Golub & Pereyra 1973): their linear parameters (kd and ks, or kd and
rho) follow per channel in closed form within their bounds for given nonlinear ones, and
the search runs over the nonlinear parameters alone ((log alpha, F0) for the microfacet
lobes), starting from a grid over their whole range (alpha in [5e-4, 1.5], 49 values on a
log scale, and seven F0): restart 0 from the grid's best point, restart k from the k-th
best local minimum of the grid's profile (another basin: a clear coat and a flake lobe),
else a random point. This is a global search at the cost of a few hundred passes over the
pairs (a 1,439-sample, 31-wavelength goniometer table: 1-2 s a fit instead of 19-36 s).
From 8 channels on, the other fits take LSMR steps on a sparse Jacobian.

For the other fits, restart 0 picks the nonlinear parameters (roughness, or lobe direction
and exponent) on a small grid, the others draw them at random from ``SeedSequence([seed,
restart])``; for each start the parameters that enter linearly (kd, ks, rho) are solved by
non-negative least squares. For "rr8807" the nonlinear start is (F0, sigma, p, a) with one
F0 for all channels. For "dsbrdf", whose channels are fitted one at a time, restart 0 is the
paper's initialisation (the best single lobe, constant in theta_d, on a grid of (kappa,
gamma), then kappa and gamma halved for each further lobe) and the others draw constant
curves at random; its least squares stop when a step lowers the cost by less than 1e-6
relative (``ftol``, instead of scipy's 1e-8), because the cost is flat along lobes that fade
out over part of theta_d: on a glossy Cook-Torrance the final costs then lie within 3e-4 of
the 1e-7 ones with 3 to 10 times fewer evaluations. The best restart is kept; if it stopped
on ``max_nfev`` instead of a tolerance, a RuntimeWarning reports the best error reached.
``info`` reports the errors on ``peak_resolving_pairs(error_n, seed=error_seed)``, a second,
independent set (default ``error_seed = seed + 1``: another scrambling), so they are not
biased by the fit. Both sets use the lobe ``widths`` option; the default (0.02, 0.08, 0.3)
resolves lobes down to alpha ~0.02 well and sharper ones without bias but with more
variance: on the blue-acrylic surrogate (alpha = 0.008) the standard error of the
lambert+ggx l2 error is 0.0035 with the default and 0.0007 with ``widths=(0.005, 0.02, 0.08,
0.3)`` (65536 pairs, both l2 = 0.600).

``info["param_stderr"]`` is the usual linearised standard error
sqrt(diag((J^T J)^-1) s^2), s^2 = sum r^2 / (m - p), at the optimum (in the natural units of
each parameter, through the derivative of the log scale). The residuals are the misfit of a
model, not independent noise, so read it as the local sensitivity of the fit (how far a
parameter moves before the cost rises by one residual variance), not as a confidence
interval. A parameter with no effect on the residuals (a zero column of J, or a direction
J does not see) gets ``inf``; a nearly undetermined one (``alpha`` and ``f0`` when ``ks`` is
~0) gets a large value, unless the residuals are themselves ~0 (data the family reproduces
exactly), when every parameter looks well determined. A parameter at a bound is linearised
as if it were free.
"""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import ThreadpoolController

from basis.validation import nonneg_int

from ..brdf import BRDF
from ..crossval import fold_report, out_of_fold
from ..factored import D_WARPS, PHI_TURNS, WARPS, FactoredLobe, fit_factored, kept_for
from ..measurements import Measurements
from ..sampling import (
    DEFAULT_WIDTHS,
    PairSamples,
    _evaluate,
    brdf_errors,
    peak_resolving_pairs,
    value_errors,
)
from ..tabulated import TabulatedBRDF, tabulate
from ..tucker import TuckerBRDF, fit_tucker
from ._geometry import _Geometry
from ._solver import _covariance, _solve
from .dsbrdf import _DSBRDF, DS_COEFFS
from .grid import GRID_OPTIONS as _GRID_OPTIONS
from .grid import grid_model, grid_reals, grid_resolution, pack_symmetric, sample_grid
from .lafortune import _Lafortune
from .microfacet import _Microfacet
from .rr8807 import _P, _RR8807, _wavelengths

__all__ = ["DEFAULTS", "FACTORED_OPTIONS", "FAMILIES", "GRID_OPTIONS", "METRICS",
           "SAMPLE_DEFAULTS", "TABULATED_OPTIONS", "TUCKER_OPTIONS", "FittedModel", "fit_model"]

#: The parametric families :func:`fit_model` knows.
FAMILIES = ("lambert+ggx", "lambert+beckmann", "lafortune", "factored", "dsbrdf", "rr8807",
            "tabulated", "tucker", "grid")
#: The families whose model is a table-like object of their own module (not parametric).
_TABLES = ("factored", "tabulated", "tucker", "grid")
METRICS = ("l2", "log")
#: Options of :func:`fit_model` and their defaults (``lobes`` is for "lafortune", default 1,
#: and "dsbrdf", default 3; ``wavelength`` for "rr8807").
DEFAULTS = {"n": 2 ** 14, "seed": 0, "restarts": 4, "lobes": None, "max_nfev": None,
            "error_n": 2 ** 16, "error_seed": None, "widths": DEFAULT_WIDTHS,
            "wavelength": None}
_LOBES = {"lafortune": 1, "dsbrdf": 3}
#: Options of :func:`fit_model` for measurements (``folds``: of the cross-validation, 0 to
#: skip it).
SAMPLE_DEFAULTS = {"seed": 0, "restarts": 4, "lobes": None, "max_nfev": None,
                   "wavelength": None, "folds": 10}
#: Options of :func:`fit_model` for family "factored": those of
#: :func:`project.factored.fit_factored`, and the error pairs.
FACTORED_OPTIONS = ("rank", "bins", "warp", "warp_d", "color", "samples", "diffuse", "seed",
                    "max_iter", "tol", "accelerate", "phi_turn")
#: Options of :func:`fit_model` for family "tabulated": those of :func:`project.tabulated.
#: tabulate` (fitting is tabulating), and the error pairs.
TABULATED_OPTIONS = ("bins", "quantity", "phi_turn", "warp_d", "sample")
#: Options of :func:`fit_model` for family "tucker": those of :func:`project.tucker.
#: fit_tucker`, and the error pairs.
TUCKER_OPTIONS = ("budget", "ranks", "knots", "color_rank", "grid", "warp_d", "phi_turn")
#: Options of :func:`fit_model` for family "grid" (:mod:`project.fitting.grid`).
GRID_OPTIONS = _GRID_OPTIONS
_ERROR_OPTIONS = ("error_n", "error_seed", "widths")


def _check_family(family: object) -> str:
    if not isinstance(family, str) or family not in FAMILIES:
        raise ValueError(f"family must be one of {', '.join(map(repr, FAMILIES))}, got "
                         f"{family!r}")
    return family


def _family(family: object, channels: int, lobes: int = 1,
            wavelength: NDArray | None = None):
    _check_family(family)
    if family == "lafortune":
        return _Lafortune(lobes, channels)
    if family == "dsbrdf":
        return _DSBRDF(lobes, channels)
    if family == "rr8807":
        return _RR8807(channels, _wavelengths(wavelength, channels))
    return _Microfacet(family.split("+")[1], channels)


# -- the fitted model -------------------------------------------------------------------------

class FittedModel(BRDF):
    """A parametric BRDF fitted by :func:`fit_model` (or built from known parameters).

    Parameters
    ----------
    family : {"lambert+ggx", "lambert+beckmann", "lafortune", "factored", "dsbrdf", "rr8807",
              "tabulated"}
    params : dict of str to array_like of float
        The family's parameters (its module, listed in :mod:`project.fitting`): ``kd``,
        ``ks`` (C,), ``alpha``, ``f0`` (scalars) for the microfacet families; ``kd`` (C,),
        ``rho`` (L, C), ``cx`` (< 0), ``cz`` (= 1), ``n`` (L,) for "lafortune"; the tables of
        :attr:`project.factored.FactoredLobe.params` for "factored"; ``kappa``, ``gamma``
        (K, 6, C) for "dsbrdf"; :attr:`project.tabulated.TabulatedBRDF.params` (``table``,
        ``warp_d``, ``phi_turn``, ``cosines``) for "tabulated"; ``kd``, ``ks``, ``kw``,
        ``f0`` (C,), ``sigma``, ``p``,
        ``a`` (scalars) and optionally ``wavelength`` (C,) for "rr8807". C, the number of
        channels, is the length of ``kd`` (the last axis of ``kappa``).
    info : dict, optional
        What :func:`fit_model` measured (empty for a model built by hand).

    Attributes
    ----------
    family : str
    params : dict of str to ndarray
        Copies of the parameters (read-only arrays).
    nparams : int
        Number of real parameters (2 C + 2; C + L (C + 2); 12 K C; 4 C + 3).
    nbytes : int
        8 * nparams (float64 storage).
    info : dict
        ``"l2"``, ``"log"``, ``"l2_stderr"`` (on pairs independent of the fit),
        ``"iterations"``, ``"restarts"``, ``"cost"`` (per restart), ``"converged"``,
        ``"param_stderr"``, ``"seconds"``, and more (see :func:`fit_model`).

    Examples
    --------
    >>> m = FittedModel("lambert+ggx", {"kd": [0.5, 0.4, 0.3], "ks": [1.0, 1.0, 1.0],
    ...                                 "alpha": 0.2, "f0": 1.0})
    >>> m.nparams, m.nbytes, m.channels
    (8, 64, 3)
    >>> from project.models import CookTorrance
    >>> w = np.array([0.6, 0.0, 0.8])
    >>> bool(np.allclose(m.eval(w, w), CookTorrance([0.5, 0.4, 0.3], 0.2, "ggx").eval(w, w)))
    True
    """

    isotropic = True
    reciprocal = True

    def __init__(self, family: str, params: Mapping[str, ArrayLike], *,
                 info: dict | None = None) -> None:
        if not isinstance(params, Mapping):
            raise TypeError(f"params must be a dict of parameter arrays, got "
                            f"{type(params).__name__}")
        if _check_family(family) == "factored":
            self._init_factored(params, info)
            return
        if family == "tabulated":
            self._init_tabulated(params, info)
            return
        if family == "tucker":
            # TuckerBRDF checks the keys, the shapes and the grid options
            self._model = TuckerBRDF.from_params(dict(params))
            self._adopt("tucker", info)
            return
        if family == "grid":
            self._init_grid(params, info)
            return
        if family == "dsbrdf":
            kappa = _param(params, "kappa", 3, low=0.0)
            if kappa.ndim != 3 or kappa.shape[1] != DS_COEFFS or 0 in kappa.shape:
                raise ValueError(f"params['kappa'] must have shape (lobes, {DS_COEFFS}, "
                                 f"channels), got {kappa.shape}")
            c = kappa.shape[2]
            model = _DSBRDF(kappa.shape[0], c)
            shapes = {"kappa": kappa.shape, "gamma": kappa.shape}
        else:
            c = _param(params, "kd", 1).size
        if family == "rr8807":
            model = _RR8807(c, _wavelengths(params.get("wavelength"), c))
            shapes = {"kd": (c,), "ks": (c,), "kw": (c,), "f0": (c,), "sigma": (), "p": (),
                      "a": (), "wavelength": (c,)}
        elif family == "lafortune":
            n = _param(params, "n", 1, low=0.0)
            model = _Lafortune(n.size, c)
            shapes = {"kd": (c,), "rho": (n.size, c), "cx": (n.size,), "cz": (n.size,),
                      "n": (n.size,)}
        elif family != "dsbrdf":
            model = _Microfacet(family.split("+")[1], c)
            shapes = {"kd": (c,), "ks": (c,), "alpha": (), "f0": ()}
        if family == "rr8807" and "wavelength" not in params:  # optional: the default
            params = {**params, "wavelength": model.lam}
        if set(params) != set(shapes):
            raise ValueError(f"params of family {family!r} must be exactly "
                             f"{sorted(shapes)}, got {sorted(params)}")
        lows = {"kd": 0.0, "ks": 0.0, "rho": 0.0, "n": 0.0, "f0": 0.0, "kw": 0.0,
                "gamma": 0.0, "kappa": 0.0}
        p = {}
        for name, shape in shapes.items():
            v = _param(params, name, len(shape), low=lows.get(name))
            if v.shape != shape:
                raise ValueError(f"params[{name!r}] must have shape {shape} (channels "
                                 f"{c} from {'kappa' if family == 'dsbrdf' else 'kd'}), "
                                 f"got {v.shape}")
            v.flags.writeable = False
            p[name] = v
        if "alpha" in p and not (p["alpha"] > 0.0 and p["f0"] <= 1.0):
            raise ValueError(f"alpha must be > 0 and f0 <= 1, got {float(p['alpha'])}, "
                             f"{float(p['f0'])}")
        if "cx" in p and not (np.all(p["cz"] == 1.0) and np.all(p["cx"] < 0.0)):
            raise ValueError(f"cz must be 1 (the scale of C is in rho) and cx < 0 (forward "
                             f"lobes) for every lobe, got cx={p['cx']}, cz={p['cz']}")
        if "sigma" in p and not (p["sigma"] > 0.0 and _P[0] <= p["p"] <= _P[1]
                                 and p["a"] > 0.0):
            raise ValueError(f"sigma and a must be > 0 and p in [{_P[0]}, {_P[1]}] (where the "
                             f"shadowing is tabulated), got sigma={float(p['sigma'])}, "
                             f"p={float(p['p'])}, a={float(p['a'])}")
        self.family = family
        self.params = p
        self.channels = c
        self._scalar = c == 1
        self._model = model
        self._x = model.vector(p)
        self.nparams = int(model.p)
        self.nbytes = 8 * self.nparams
        self.info = {} if info is None else dict(info)

    def _init_factored(self, params: Mapping[str, ArrayLike], info: dict | None) -> None:
        required = {"kd", "h_table", "d_table", "warp", "warp_d"}
        allowed = required | {"phi_table", "weights", "phi_turn"}
        if not required <= set(params) <= allowed:
            raise ValueError(f"params of family 'factored' must hold {sorted(required)} and "
                             f"optionally 'phi_table', 'weights' and 'phi_turn', got "
                             f"{sorted(params)}")
        warps = {}
        for name, table in (("warp", WARPS), ("warp_d", D_WARPS)):
            v = _param(params, name, 0)
            names = [k for k, p in table.items() if v.ndim == 0 and p == float(v)]
            if not names:
                raise ValueError(f"params[{name!r}] must be the exponent of one of the warps "
                                 f"{table}, got {v}")
            warps[name] = names[0]
        if "phi_turn" in params:  # absent: a half-turn lobe (the only kind before 'full')
            v = _param(params, "phi_turn", 0)
            names = [k for k, p in PHI_TURNS.items() if v.ndim == 0 and p == float(v)]
            if not names:
                raise ValueError(f"params['phi_turn'] must be the fraction of the turn of one "
                                 f"of {PHI_TURNS}, got {v}")
            warps["phi_turn"] = names[0]
        # FactoredLobe checks shapes, signs and channels of the tables
        self._model = FactoredLobe(
            _param(params, "kd", 1, low=0.0), params["h_table"], params["d_table"],
            phi_table=params.get("phi_table"), weights=params.get("weights"), **warps)
        self._adopt("factored", info)

    def _init_grid(self, params: Mapping[str, ArrayLike], info: dict | None) -> None:
        if set(params) != {"table"}:
            raise ValueError(f"params of family 'grid' must be exactly ['table'], got "
                             f"{sorted(params)}")
        self._model, symmetric = grid_model(params["table"])
        n, m = self._model.resolution
        self.family = "grid"
        self.reciprocal = symmetric
        self.params = {"table": self._model.table}
        # what compress.save writes: a symmetric table as its upper triangle, the reals
        # nparams counts (FittedModel("grid", ...) accepts either form)
        self.stored_params = {"table": pack_symmetric(self._model.table)} if symmetric \
            else self.params
        self.channels = self._model.channels
        self._scalar = self.channels == 1
        self.nparams = grid_reals((n, m), self.channels, symmetric)
        self.nbytes = 8 * self.nparams
        self.info = {} if info is None else dict(info)

    def _init_tabulated(self, params: Mapping[str, ArrayLike], info: dict | None) -> None:
        # TabulatedBRDF checks the keys, the table and the grid options
        self._model = TabulatedBRDF.from_params(dict(params))
        self._adopt("tabulated", info)

    def _adopt(self, family: str, info: dict | None) -> None:
        """Take the attributes of a tabulated family from the model it wraps."""
        self.family = family
        self.reciprocal = self._model.reciprocal
        self.params = self._model.params
        self.channels = self._model.channels
        self._scalar = self.channels == 1
        self.nparams = self._model.nparams
        self.nbytes = self._model.nbytes
        self.info = {} if info is None else dict(info)

    def _eval(self, wi: NDArray, wo: NDArray) -> NDArray:
        if self.family in _TABLES:
            return self._model._eval(wi, wo)
        return self._model.value(self._x, _Geometry(wi, wo))

    def __repr__(self) -> str:
        if self.family == "factored":
            m = self._model
            turn = "" if m.phi_turn == "half" else f", phi_turn={m.phi_turn!r}"
            return (f"FittedModel('factored', rank={m.rank}, bins={m.bins}, warp={m.warp!r}, "
                    f"warp_d={m.warp_d!r}{turn}, channels={self.channels}, "
                    f"nbytes={self.nbytes})")
        if self.family == "tucker":
            m = self._model
            return (f"FittedModel('tucker', knots={m.knot_counts}, ranks={m.ranks}, "
                    f"color_rank={m.color_rank}, warp_d={m.warp_d!r}, "
                    f"phi_turn={m.phi_turn!r}, channels={self.channels}, "
                    f"nbytes={self.nbytes})")
        if self.family == "grid":
            n, m = self._model.resolution
            return (f"FittedModel('grid', resolution=({n}, {m}), symmetric={self.reciprocal}, "
                    f"channels={self.channels}, nbytes={self.nbytes})")
        if self.family == "tabulated":
            m = self._model
            return (f"FittedModel('tabulated', bins={m.bins}, warp_d={m.warp_d!r}, "
                    f"phi_turn={m.phi_turn!r}, quantity={m.quantity!r}, "
                    f"channels={self.channels}, nbytes={self.nbytes})")

        def fmt(v: NDArray) -> str:
            return np.array2string(np.asarray(v), precision=4, separator=", ")
        args = ", ".join(f"{k}={fmt(v)}" for k, v in self.params.items())
        return f"FittedModel({self.family!r}, {args})"


def _param(params: Mapping, name: str, ndim: int, *, low: float | None = None) -> NDArray:
    if name not in params:
        raise ValueError(f"params must hold {name!r}, got the keys {sorted(params)}")
    try:
        v = np.array(params[name], dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"params[{name!r}] must be numbers, got {params[name]!r}") from None
    if ndim >= 1 and v.ndim == 0:
        v = v.reshape(1)
    if not np.all(np.isfinite(v)) or (low is not None and np.any(v < low)):
        raise ValueError(f"params[{name!r}] must be finite"
                         + ("" if low is None else f" and >= {low}") + f", got {v}")
    return v


# -- fitting ----------------------------------------------------------------------------------

def fit_model(brdf: object, family: str, *, metric: str = "l2", **options) -> FittedModel:
    """Fit a parametric family to a BRDF by weighted non-linear least squares.

    Parameters
    ----------
    brdf : BRDF
        Any object with ``eval(wi, wo)`` returning finite values >= 0 (an analytic model,
        :func:`project.measured.read_merl`, a coefficient matrix...). Delta terms are not
        fitted (warned).
    family : str
        One of ``"lambert+ggx"``, ``"lambert+beckmann"``, ``"lafortune"``, ``"factored"``,
        ``"dsbrdf"``, ``"rr8807"``, ``"tabulated"``, ``"tucker"``. See each family's module
        (listed in :mod:`project.fitting`) for its parameters and bounds.
    metric : {"l2", "log"}
        What the fit minimises: the relative l2 error of q = f cos theta_i cos theta_o, or
        the RMS of log(1 + f cos theta_i) (module notes).
    **options
        ``n`` (fitting pairs, default 16384), ``seed`` (default 0), ``restarts`` (starting
        points, default 4; use 8 or more for multi-lobe Lafortune), ``lobes`` (lobes of
        "lafortune", default 1, or of "dsbrdf", default 3), ``wavelength`` ("rr8807": um
        per channel, default the report's RGB for 3 channels), ``max_nfev`` (function
        evaluations per restart, default scipy's 100 x the number of parameters, per
        channel for "dsbrdf"), ``error_n`` (pairs of the error estimate,
        default 65536), ``error_seed`` (default ``seed + 1``, must differ from ``seed``) and
        ``widths`` (the lobe widths of :func:`project.sampling.peak_resolving_pairs` for both
        pair sets; add a narrower one for very sharp highlights, module notes).

    Returns
    -------
    FittedModel
        ``info`` holds ``"l2"``, ``"log"``, ``"l2_stderr"`` (:func:`project.sampling.
        brdf_errors` on the independent error pairs), ``"fit_l2"`` or ``"fit_log"`` (the
        minimised error on the fitting pairs, largest channel), ``"iterations"`` (Jacobian
        evaluations of the best restart), ``"nfev"`` (per restart), ``"restarts"``,
        ``"cost"`` (final 0.5 sum r^2 per restart), ``"status"`` (scipy's, per restart),
        ``"best_restart"``, ``"converged"``, ``"param_stderr"`` (dict like ``params``),
        ``"metric"``, ``"samples"`` (descriptions of both pair sets) and ``"seconds"``.
        For "factored": the errors, ``"fit_l2"`` (on the fitting rule) and the report of
        :func:`project.factored.fit_factored` (``"iterations"``, ``"converged"``,
        ``"floor"``, ``"history"``, ...).

    Raises
    ------
    TypeError
        ``brdf`` has no ``eval``, an option is unknown or of the wrong type.
    ValueError
        Unknown family (the known ones are listed) or metric, an option out of range, or
        the BRDF returns non-finite or negative values, or only zeros, at the fitting pairs.

    Warns
    -----
    RuntimeWarning
        The best restart stopped at ``max_nfev`` without meeting a tolerance; the message
        gives the best error reached.

    Examples
    --------
    >>> from project.models import CookTorrance
    >>> fit = fit_model(CookTorrance([0.3, 0.2, 0.1], 0.15, "ggx"), "lambert+ggx",
    ...                 n=2048, restarts=1, error_n=2048)
    >>> round(float(fit.params["alpha"]), 3), fit.nparams
    (0.15, 8)
    >>> bool(fit.info["l2"] < 1e-3) and fit.info["converged"]
    True
    """
    start = time.perf_counter()
    if not isinstance(metric, str) or metric not in METRICS:
        raise ValueError(f"metric must be one of {', '.join(map(repr, METRICS))}, got "
                         f"{metric!r}")
    if isinstance(brdf, Measurements):
        return _fit_samples(brdf, _check_family(family), metric, options, start)
    if _check_family(family) == "factored":
        return _fit_factored(brdf, metric, options, start)
    if family == "tabulated":
        return _fit_tabulated(brdf, metric, options, start)
    if family == "tucker":
        return _fit_tucker(brdf, metric, options, start)
    if family == "grid":
        return _fit_grid(brdf, metric, options, start)
    opts = _options(family, options)
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must be a BRDF (an object with eval(wi, wo)) or "
                        f"project.Measurements, got {type(brdf).__name__}")
    if getattr(brdf, "delta", ()):
        warnings.warn(f"{brdf!r} has delta (ideal mirror) terms; fit_model fits only its "
                      "eval() part", UserWarning, stacklevel=2)
    samples = _pairs(opts["n"], opts["seed"], opts["widths"])
    f = _target(brdf, samples)
    model = _family(family, f.shape[1], opts["lobes"], opts["wavelength"])
    fitted, report = _fit_parametric(family, model, _Geometry(samples.wi, samples.wo), f,
                                     samples.weights, metric, opts)
    err = _errors(brdf, fitted, _pairs(opts["error_n"], opts["error_seed"], opts["widths"]))
    fitted.info = {
        **err, **report,
        "samples": {"fit": samples.description,
                    "error": f"error_n={opts['error_n']}, error_seed={opts['error_seed']}"},
        "seconds": time.perf_counter() - start,
    }
    return fitted


def _fit_parametric(family: str, model, geom: _Geometry, f: NDArray, w: NDArray, metric: str,
                    opts: dict, stacklevel: int = 3) -> tuple[FittedModel, dict]:
    """Fit ``model`` to values ``f`` (n, C) at ``geom`` with weights ``w``.

    Every restart is run and the best kept. Returns the model and the report of the fit
    (what ``info`` holds); warns at ``stacklevel`` (0: not) when the fit did not converge.
    """
    c = f.shape[1]
    lo, hi = model.bounds
    runs = []
    # the solver factors tall, narrow Jacobians (samples x ~10 parameters) at every step:
    # a second BLAS thread only adds synchronisation, and when another process holds a core
    # it costs 40x (SVD of 4317 x 15: 4 ms on one thread, 175 ms on two, 2 cores loaded)
    with _blas().limit(limits=1, user_api="blas"):
        for k in range(opts["restarts"]):
            rng = np.random.default_rng(np.random.SeedSequence([opts["seed"], k]))
            runs.append(_solve(model, geom, f, w, metric, k, rng, opts["max_nfev"]))
    costs = [float(r.cost) for r in runs]
    best = int(np.argmin(costs))
    run = runs[best]
    r2 = (run.fun.reshape(geom.n, c) ** 2).sum(axis=0)
    fit_err = float(np.sqrt(r2.max()))  # per-channel relative l2 (or log RMS) on the fit pairs
    converged = bool(run.status > 0)
    if not converged and stacklevel:
        why = (f"every one of the {opts['restarts']} restarts stopped" if
               all(r.status == 0 for r in runs) else "the best restart stopped")
        warnings.warn(f"fit_model({family!r}, metric={metric!r}) did not converge: {why} at "
                      f"max_nfev={opts['max_nfev']}; best {metric} error reached on the "
                      f"fitting pairs {fit_err:.4g} (raise max_nfev or restarts)",
                      RuntimeWarning, stacklevel=stacklevel)
    x = np.clip(run.x, lo, hi)
    with _blas().limit(limits=1, user_api="blas"):
        cov = _covariance(run.jac, run.fun, model.p)
    report = {
        f"fit_{metric}": fit_err,
        "iterations": int(run.njev or 0),
        "nfev": [int(r.nfev) for r in runs],
        "restarts": opts["restarts"],
        "cost": costs,
        "status": [int(r.status) for r in runs],
        "best_restart": best,
        "converged": converged,
        "param_stderr": model.natural_stderr(x, cov),
        "metric": metric,
    }
    return FittedModel(family, model.params(x)), report


@functools.cache
def _blas() -> ThreadpoolController:
    """Return the thread pools of the loaded libraries, found once (~5 ms a search)."""
    return ThreadpoolController()


def _fit_samples(meas: Measurements, family: str, metric: str, options: dict,
                 start: float) -> FittedModel:
    """fit_model(measurements, family): a weighted fit to the samples, cross-validated."""
    if family in _TABLES:
        raise ValueError(
            f"family {family!r} tabulates a BRDF on a dense rule in the half/difference angles "
            "and needs a BRDF that can be evaluated anywhere; scattered samples do not cover "
            f"its tables. Fit a parametric family to {meas!r} ('lambert+ggx', "
            "'lambert+beckmann', 'lafortune', 'dsbrdf', 'rr8807'), or compare them with "
            "compress.select(measurements, tol)")
    unknown = sorted(set(options) - set(SAMPLE_DEFAULTS))
    if unknown:
        hint = (" (the samples are the measurements: n, error_n, error_seed and widths "
                "choose pairs of a BRDF)" if set(unknown) & set(DEFAULTS) else "")
        raise TypeError(f"fit_model() got unknown option(s) {', '.join(map(repr, unknown))} "
                        f"for measurements{hint}; the options are "
                        f"{', '.join(map(repr, SAMPLE_DEFAULTS))}")
    opts = _options(family, {k: v for k, v in options.items() if k != "folds"})
    k = nonneg_int(options.get("folds", SAMPLE_DEFAULTS["folds"]), "folds")
    if k == 1:
        raise ValueError("folds must be 0 (no cross-validation) or >= 2, got 1")
    wavelength = opts["wavelength"]
    if family == "rr8807" and wavelength is None and meas.wavelengths is not None:
        wavelength = meas.wavelengths / 1000.0  # nm -> um
    model = _family(family, meas.channels, opts["lobes"], wavelength)
    fit_values = meas.values
    if metric == "log" and np.any(fit_values * meas.wi[:, 2:3] <= -1.0):
        raise ValueError("the log metric needs f cos(theta_i) > -1 at every sample; "
                         f"{meas!r} has values below that")

    def fit_on(m: Measurements, stacklevel: int = 0) -> tuple[FittedModel, dict]:
        return _fit_parametric(family, model, _Geometry(m.wi, m.wo), m.values, m.weights,
                               metric, opts, stacklevel=stacklevel)

    fitted, report = fit_on(meas, stacklevel=4)
    info: dict = {"l2": None, "l2_stderr": None, "log": None, "log_stderr": None}
    if k:
        folds = meas.folds(k, seed=opts["seed"], by="pairs")
        if np.unique(folds).size >= 2:
            (pred,) = out_of_fold(meas, lambda m: fit_on(m)[0], folds)
            info = fold_report(meas, pred, folds, "pairs", start)
            info.pop("seconds")
    fitted.info = {**info, **report, "samples": {"fit": repr(meas), "count": len(meas)},
                   "seconds": time.perf_counter() - start}
    if info["l2"] is not None and info["l2"] >= 1.0:
        warnings.warn(f"fit_model({family!r}) predicts the held-out samples of {meas!r} no "
                      f"better than zero: cross-validated l2 error {info['l2']:.3g} >= 1. "
                      "The family cannot follow these data; compare the families (and "
                      "expansions) with compress.select(measurements, tol)", RuntimeWarning,
                      stacklevel=3)
    return fitted


def _pairs(n: int, seed: int, widths: object) -> PairSamples:
    """Return ``peak_resolving_pairs(n, seed=seed, widths=widths)``, the last few kept.

    Fits of one BRDF in a row (the candidates of ``compress.select``) measure their errors
    on the same pairs; drawing them takes about as long as a small fit. PairSamples are
    read-only, so sharing them is safe.
    """
    try:
        key = tuple(float(x) for x in widths)  # type: ignore[attr-defined]
    except (TypeError, ValueError):  # let peak_resolving_pairs say what is wrong
        return peak_resolving_pairs(n, seed=seed, widths=widths)  # type: ignore[arg-type]
    return _cached_pairs(n, seed, key)


def _errors(brdf: object, fitted: object, pairs: PairSamples) -> dict:
    """Return ``brdf_errors(brdf, fitted, pairs)``; the BRDF's values there are kept.

    Inside :func:`project.factored.reuse_samples` (the candidates of ``compress.select``)
    every fit of one BRDF measures its errors on the same pairs (:func:`_pairs`): the BRDF
    is evaluated there once (the same values, so the same errors bit for bit).
    """
    kept = kept_for(brdf, ("error pairs", id(pairs)),
                  lambda: {"f": _evaluate(brdf, "reference_brdf", pairs), "pairs": pairs})
    if kept["pairs"] is not pairs:  # another set of pairs at a recycled id
        return brdf_errors(brdf, fitted, pairs)
    return value_errors(kept["f"], _evaluate(fitted, "approx", pairs), pairs)


@functools.lru_cache(maxsize=4)
def _cached_pairs(n: int, seed: int, widths: tuple[float, ...]) -> PairSamples:
    return peak_resolving_pairs(n, seed=seed, widths=widths)


def _table_options(family: str, metric: str, options: dict,
                   own: tuple[str, ...]) -> tuple[dict, PairSamples, str]:
    """Check the options of a tabulated family (its own and those of the error pairs).

    Returns the family's own options, the independent error pairs and their description.
    """
    if metric != "l2":
        raise ValueError(f"family {family!r} is measured in the l2 metric only, got metric="
                         f"{metric!r}")
    unknown = sorted(set(options) - set(own) - set(_ERROR_OPTIONS) - {"seed"})
    if unknown:
        raise TypeError(f"fit_model() got unknown option(s) {', '.join(map(repr, unknown))} "
                        f"for family {family!r}; its options are "
                        f"{', '.join(map(repr, own + _ERROR_OPTIONS))}")
    seed = nonneg_int(options.get("seed", 0), "seed")
    error_n = nonneg_int(options.get("error_n", DEFAULTS["error_n"]), "error_n")
    error_seed = options.get("error_seed")
    error_seed = seed + 1 if error_seed is None else nonneg_int(error_seed, "error_seed")
    pairs = _pairs(error_n, error_seed, options.get("widths", DEFAULTS["widths"]))
    return ({k: v for k, v in options.items() if k in own}, pairs,
            f"error_n={error_n}, error_seed={error_seed}")


def _fit_factored(brdf: object, metric: str, options: dict, start: float) -> FittedModel:
    """fit_model(brdf, "factored"): fit_factored, then the errors on independent pairs."""
    own, pairs, described = _table_options("factored", metric, options, FACTORED_OPTIONS)
    lobe = fit_factored(brdf, **own)
    fitted = FittedModel("factored", lobe.params)
    fitted.info = {**lobe.info, **_errors(brdf, fitted, pairs), "fit_l2": lobe.info["error"],
                   "metric": metric, "rank": lobe.rank, "bins": lobe.bins, "warp": lobe.warp,
                   "warp_d": lobe.warp_d, "phi_turn": lobe.phi_turn, "restarts": 1,
                   "samples": {"fit": "project.factored.rusinkiewicz_rule",
                               "error": described},
                   "seconds": time.perf_counter() - start}
    return fitted


def _fit_tabulated(brdf: object, metric: str, options: dict, start: float) -> FittedModel:
    """fit_model(brdf, "tabulated"): tabulate, then the errors on independent pairs."""
    own, pairs, described = _table_options("tabulated", metric, options, TABULATED_OPTIONS)
    tab = tabulate(brdf, **own)
    fitted = FittedModel("tabulated", tab.params)
    fitted.info = {**tab.info, **_errors(brdf, fitted, pairs), "metric": metric,
                   "warp_d": tab.warp_d, "phi_turn": tab.phi_turn, "quantity": tab.quantity,
                   "restarts": 1,
                   "samples": {"fit": "project.tabulated.tabulate (grid nodes)",
                               "error": described},
                   "seconds": time.perf_counter() - start}
    return fitted


def _fit_grid(brdf: object, metric: str, options: dict, start: float) -> FittedModel:
    """fit_model(brdf, "grid"): sample at the cell centres, then the errors."""
    own, pairs, described = _table_options("grid", metric, options, GRID_OPTIONS)
    if not callable(getattr(brdf, "eval", None)):
        raise TypeError(f"brdf must be a BRDF (an object with eval(wi, wo)), got "
                        f"{type(brdf).__name__}")
    resolution = grid_resolution(brdf, own.get("resolution"))
    symmetric = own.get("symmetric", True)
    if not isinstance(symmetric, (bool, np.bool_)):
        raise TypeError(f"symmetric must be True or False, got {symmetric!r}")
    fitted = FittedModel("grid", {"table": sample_grid(brdf, resolution, bool(symmetric))})
    fitted.info = {**_errors(brdf, fitted, pairs), "metric": metric,
                   "resolution": resolution, "symmetric": bool(symmetric), "restarts": 1,
                   "samples": {"fit": f"the cell centres of a {resolution} MBSDF grid",
                               "error": described},
                   "seconds": time.perf_counter() - start}
    return fitted


def _fit_tucker(brdf: object, metric: str, options: dict, start: float) -> FittedModel:
    """fit_model(brdf, "tucker"): fit_tucker, then the errors on independent pairs."""
    own, pairs, described = _table_options("tucker", metric, options, TUCKER_OPTIONS)
    t = fit_tucker(brdf, **own)
    fitted = FittedModel("tucker", t.params)
    fitted.info = {**t.info, **_errors(brdf, fitted, pairs), "metric": metric,
                   "warp_d": t.warp_d, "phi_turn": t.phi_turn, "restarts": 1,
                   "samples": {"fit": f"project.tucker.fit_tucker (grid {t.info['grid']})",
                               "error": described},
                   "seconds": time.perf_counter() - start}
    return fitted


def _options(family: str, options: dict) -> dict:
    unknown = sorted(set(options) - set(DEFAULTS))
    if unknown:
        raise TypeError(f"fit_model() got unknown option(s) {', '.join(map(repr, unknown))}; "
                        f"the options are {', '.join(map(repr, DEFAULTS))}")
    if "lobes" in options and family not in _LOBES:
        raise ValueError(f"option 'lobes' applies to families 'lafortune' and 'dsbrdf' only, "
                         f"got family {family!r}")
    if "wavelength" in options and family != "rr8807":
        raise ValueError(f"option 'wavelength' applies to family 'rr8807' only, got family "
                         f"{family!r}")
    o = {**DEFAULTS, **options}
    if o["lobes"] is None:
        o["lobes"] = _LOBES.get(family, 1)
    o["n"] = nonneg_int(o["n"], "n")
    o["seed"] = nonneg_int(o["seed"], "seed")
    o["restarts"] = nonneg_int(o["restarts"], "restarts", maximum=1000)
    o["lobes"] = nonneg_int(o["lobes"], "lobes", maximum=8)
    o["error_n"] = nonneg_int(o["error_n"], "error_n")
    if o["restarts"] < 1:
        raise ValueError(f"restarts must be >= 1, got {o['restarts']}")
    if o["lobes"] < 1:
        raise ValueError(f"lobes must be >= 1, got {o['lobes']}")
    if o["max_nfev"] is not None:
        o["max_nfev"] = nonneg_int(o["max_nfev"], "max_nfev")
        if o["max_nfev"] < 1:
            raise ValueError(f"max_nfev must be >= 1 or None, got {o['max_nfev']}")
    o["error_seed"] = o["seed"] + 1 if o["error_seed"] is None else \
        nonneg_int(o["error_seed"], "error_seed")
    if o["error_seed"] == o["seed"]:
        raise ValueError(f"error_seed must differ from seed (the errors are measured on pairs "
                         f"independent of the fit), got {o['error_seed']} for both")
    return o


def _target(brdf: object, samples) -> NDArray[np.float64]:
    """Evaluate the BRDF at the fitting pairs as (n, C), checked finite, >= 0, not all 0."""
    f = np.asarray(brdf.eval(samples.wi, samples.wo), dtype=np.float64)
    if f.ndim not in (1, 2) or f.shape[0] != len(samples):
        raise ValueError(f"brdf.eval(wi, wo) must return shape (n,) or (n, channels) for n = "
                         f"{len(samples)} pairs, got {f.shape}")
    f = f.reshape(len(samples), -1)
    bad = ~np.isfinite(f)
    if bad.any():
        i = int(np.argwhere(bad)[0, 0])
        raise ValueError(f"brdf must be finite at the fitting pairs: {int(bad.sum())} values "
                         f"are NaN or inf (first at wi={samples.wi[i]}, wo={samples.wo[i]})")
    if np.any(f < 0.0):
        i = int(np.argwhere(f < 0.0)[0, 0])
        raise ValueError(f"brdf must be >= 0 at the fitting pairs: {int(np.sum(f < 0))} "
                         f"values are negative, min {f.min():.6g} (first at wi="
                         f"{samples.wi[i]}, wo={samples.wo[i]})")
    if np.any(np.all(f == 0.0, axis=0)):
        raise ValueError("brdf must not be 0 at every fitting pair (channel "
                         f"{int(np.flatnonzero(np.all(f == 0.0, axis=0))[0])})")
    return f
