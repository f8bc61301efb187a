"""A coefficient matrix used as a BRDF: evaluation, non-negativity and importance sampling.

This is what lets the result of one simulation be the microscale BRDF of the next (the
fibres of a thread, then a cloth woven of such threads): :class:`MatrixBRDF` wraps a
:class:`basis.CoefficientMatrix` in the BRDF contract (``eval``, ``channels``,
``isotropic``) and adds a tabulated importance sampler (``sample``, ``pdf``) that the
microgeometry simulator's :class:`~project.microgeometry.MicroBRDF` facets use.

Sampling (a piecewise-constant density, exact ``pdf``). For a table of incident nodes --
theta_i uniform in [0, pi/2], and, for an anisotropic matrix, phi_i uniform in [0, 2 pi) --
the non-negative part of f cos(theta_o) is integrated over a grid of equal-solid-angle exit
cells (uniform in z_o and in the azimuth *relative to the incident azimuth*) and normalised
into a discrete distribution over the cells. Drawing w_o for an arbitrary w_i:

1. choose one incident node at random with the (bi)linear interpolation weights of w_i
   between its neighbouring nodes;
2. choose a cell of that node from its discrete CDF, and a uniform point inside the cell;
   the cell's azimuth is relative, so the node's lobe is turned to the azimuth of w_i.

The density of the drawn w_o is therefore the same mixture, sum_k weight_k p_k(cell) /
Omega_cell, which is what :meth:`MatrixBRDF.pdf` returns: ``sample`` and ``pdf`` are exactly
consistent, which is all an unbiased estimator f cos / pdf needs. How well the density follows
f cos only changes the variance. A floor of ``DEFENSIVE`` (1 %) of the uniform density is
mixed in, so the pdf is positive on the whole upper hemisphere and the estimator stays
unbiased on its own, even where the table misses a lobe narrower than a cell.

Two uniforms per sample suffice: the node and the cell are chosen with the first one, whose
remainder (rescaled to [0, 1)) then places the point in z inside the cell; 53-bit uniforms
keep about 40 bits after both choices.
"""

from __future__ import annotations

import hashlib
import warnings

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis import CoefficientMatrix
from basis.validation import as_directions, choice, nonneg_int

from .brdf import BRDF

__all__ = ["ALBEDO_WARN", "DEFENSIVE", "MatrixBRDF"]

#: fraction of the uniform (cosine-free) density mixed into every tabulated density
DEFENSIVE = 0.01
#: sub-points per exit cell side used to integrate f cos over the cell (midpoint rule)
_SUB = 2
#: default relative tolerance for negative values, see ``MatrixBRDF(tol=...)``
_TOL = 1e-2
#: a tabulated directional albedo above this warns: the BRDF would create energy (5 % is
#: above the Monte Carlo noise of usable estimates and the midpoint-rule error of the table)
ALBEDO_WARN = 1.05


class MatrixBRDF(BRDF):
    """A :class:`basis.CoefficientMatrix` evaluated and importance-sampled as a BRDF.

    Parameters
    ----------
    matrix : CoefficientMatrix or SimulationResult
        The BRDF, of either quantity ("f" or "f_cos"), any basis and any channels; a
        :class:`~project.microgeometry.SimulationResult` stands for its ``.matrix``.
    negative : {"raise", "clamp"}
        Truncated and noisy expansions have negative lobes. ``"raise"``: refuse a matrix
        whose values on the sampling table fall below ``-tol * max f`` (the error gives the
        most negative value). ``"clamp"``: accept it and evaluate max(f, 0); the energy this
        adds is reported in :attr:`clamp_bias`. In both modes ``eval`` returns max(f, 0),
        so negative values within the tolerance are clamped too (and counted).
    tol : float
        Relative tolerance of negative values for ``negative="raise"``, in [0, 1).
    min_cos : float
        For ``quantity="f_cos"``: f = q / (cos theta_i cos theta_o) with both cosines
        lifted to at least ``min_cos`` (see :meth:`basis.CoefficientMatrix.eval`).
    incident : (n_theta, n_phi) pair of int
        Incident nodes of the sampling table: ``n_theta`` >= 2 in theta_i (uniform in
        [0, pi/2]) and ``n_phi`` >= 1 in phi_i (used only for anisotropic matrices).
    cells : (n_z, n_phi) pair of int
        Exit cells per node: ``n_z`` >= 1 in z_o and ``n_phi`` >= 1 in relative azimuth
        (a multiple of the incident ``n_phi`` for anisotropic matrices).

    Attributes
    ----------
    matrix : CoefficientMatrix
    channels : int
    isotropic : bool
        That of the matrix (its storage form).
    clamp_bias : float
        Largest increase of the directional albedo caused by clamping, max over the incident
        nodes and channels of int_H max(-f, 0) cos(theta_o) dw_o (0 for a non-negative
        matrix). The clamped BRDF's albedo is that of the matrix plus this much at most (up
        to the midpoint-rule error of the table).
    clamp_table : (n_nodes, channels) ndarray
        The same per incident node (rows as ``albedo_table``).
    min_value, max_value : float
        Smallest and largest f met on the sampling table (before clamping).
    albedo_table : (n_nodes, channels) ndarray
        Directional albedo of the clamped BRDF at the incident nodes (row a * n_phi + b for
        theta node a and phi node b), by the midpoint rule on the exit cells.

    Raises
    ------
    TypeError
        If ``matrix`` is not a CoefficientMatrix (or a result holding one).
    ValueError
        For ``negative="raise"`` and a matrix with negative lobes beyond ``tol``; for
        non-finite values on the table; for bad table sizes.

    Warns
    -----
    RuntimeWarning
        When the clamped BRDF's tabulated albedo exceeds ``ALBEDO_WARN`` (1.05) at some
        incidence: used as a microscale BRDF it would create energy there.

    Notes
    -----
    Bases: any basis of a CoefficientMatrix is accepted, including full-sphere
    ``SphericalHarmonics`` (only the upper hemisphere is used; below the horizon f is 0
    by the BRDF contract). With ``quantity="f_cos"`` the choice matters near the horizon:
    odd ``HemiHarmonics`` vanish on the horizon, so q / (cos cos) tends to a finite limit
    and the lifting changes f by O(min_cos) there. Other bases (``HemiZernike``, even
    harmonics, full sphere) do not vanish on the horizon, and a truncated or noisy q keeps
    a residual there, which the division amplifies by up to 1 / min_cos per direction: the
    directional albedo at grazing incidence can then exceed 1 (check
    :attr:`albedo_table`). For recursion prefer ``quantity="f"``, or ``"f_cos"`` in odd
    ``HemiHarmonics`` (what :func:`~project.microgeometry.simulate` estimates in any basis
    you choose), or a larger ``min_cos``.

    Sampling and pdf: see the module docstring; exact consistency of :meth:`sample` and
    :meth:`pdf`, positive pdf on the upper hemisphere. Multi-channel matrices are sampled
    by the mean of their channels.

    Examples
    --------
    >>> import numpy as np
    >>> from basis import HemiHarmonics
    >>> from project import project
    >>> from project.models import Lambert
    >>> brdf = MatrixBRDF(project(Lambert(0.5), HemiHarmonics(3)))
    >>> round(float(brdf.eval([0, 0, 1.0], [0.6, 0, 0.8])), 10), brdf.clamp_bias
    (0.1591549431, 0.0)
    >>> wo = brdf.sample(np.array([[0.6, 0, 0.8]]), np.array([[0.3, 0.7]]))
    >>> bool(brdf.pdf(np.array([[0.6, 0, 0.8]]), wo)[0] > 0)
    True
    """

    def __init__(
        self,
        matrix: CoefficientMatrix,
        *,
        negative: str = "raise",
        tol: float = _TOL,
        min_cos: float = 1e-3,
        incident: tuple[int, int] = (16, 16),
        cells: tuple[int, int] = (32, 64),
    ) -> None:
        if not isinstance(matrix, CoefficientMatrix) and isinstance(
                getattr(matrix, "matrix", None), CoefficientMatrix):
            matrix = matrix.matrix  # a SimulationResult
        if not isinstance(matrix, CoefficientMatrix):
            raise TypeError(f"matrix must be a basis.CoefficientMatrix (or a SimulationResult), "
                            f"got {type(matrix).__name__}")
        self.negative = choice(negative, "negative", ("raise", "clamp"))
        tol = float(tol)
        if not 0.0 <= tol < 1.0:
            raise ValueError(f"tol must lie in [0, 1), got {tol!r}")
        min_cos = float(min_cos)
        if not 0.0 < min_cos < 1.0:
            raise ValueError(f"min_cos must lie in (0, 1), got {min_cos!r}")
        n_t, n_pi = _pair(incident, "incident", (2, 1))
        n_z, n_ph = _pair(cells, "cells", (1, 1))
        self.matrix = matrix
        self.channels = matrix.channels
        self.isotropic = matrix.is_isotropic
        self.reciprocal = bool(getattr(matrix, "reciprocal", True))
        self._scalar = matrix.is_scalar
        self.tol, self.min_cos = tol, min_cos
        if self.isotropic:
            n_pi = 1
        elif n_ph % n_pi:
            raise ValueError(f"cells[1] must be a multiple of incident[1] = {n_pi} for an "
                             f"anisotropic matrix, got {n_ph}")
        self._shape = (n_t, n_pi, n_z, n_ph)
        self._build_table()

    # -- the table ------------------------------------------------------------------------

    def _build_table(self) -> None:
        n_t, n_pi, n_z, n_ph = self._shape
        theta = np.linspace(0.0, 0.5 * np.pi, n_t)
        zi = np.cos(theta)
        zi[-1] = 0.0
        si = np.sqrt(1.0 - zi * zi)
        phi_i = 2.0 * np.pi * np.arange(n_pi) / n_pi
        wi = np.stack([si[:, None] * np.cos(phi_i), si[:, None] * np.sin(phi_i),
                       np.broadcast_to(zi[:, None], (n_t, n_pi))], axis=-1).reshape(-1, 3)
        # exit sub-points, _SUB x _SUB per cell, absolute azimuth (z rows, phi columns)
        zo = (np.arange(n_z * _SUB) + 0.5) / (n_z * _SUB)
        po = 2.0 * np.pi * (np.arange(n_ph * _SUB) + 0.5) / (n_ph * _SUB)
        so = np.sqrt(1.0 - zo * zo)
        wo = np.stack([so[:, None] * np.cos(po), so[:, None] * np.sin(po),
                       np.broadcast_to(zo[:, None], (zo.size, po.size))], axis=-1)
        with np.errstate(over="ignore", invalid="ignore"):  # reported just below
            f = self.matrix.eval(wi[:, None, None, :], wo[None], min_cos=self.min_cos)
        f = f.reshape(n_t * n_pi, zo.size, po.size, self.channels)
        if not np.all(np.isfinite(f)):
            raise ValueError("matrix must evaluate to finite values, got NaN or inf on the "
                             "sampling table")
        self.min_value, self.max_value = float(f.min()), float(f.max())
        low = -self.tol * max(self.max_value, 0.0)
        if self.negative == "raise" and self.min_value < low:
            k = np.unravel_index(int(np.argmin(f)), f.shape)
            raise ValueError(
                f"matrix must be non-negative as a BRDF: it reaches f = {self.min_value:.4g} "
                f"(below -tol * max f = {low:.4g}) at theta_i = "
                f"{np.degrees(np.arccos(wi[k[0], 2])):.1f} deg, theta_o = "
                f"{np.degrees(np.arccos(zo[k[1]])):.1f} deg (negative lobes of a truncated "
                "or noisy expansion); pass negative='clamp' to use max(f, 0) (the added "
                "energy is reported as clamp_bias), or smooth the matrix first "
                "(compress.smooth)")
        g = f * zo[None, :, None, None]  # f cos(theta_o)
        cell = 2.0 * np.pi / (n_z * n_ph)  # solid angle of a cell
        shape = (n_t * n_pi, n_z, _SUB, n_ph, _SUB, self.channels)
        pos = np.maximum(g, 0.0).reshape(shape).mean(axis=(2, 4)) * cell  # (N, n_z, n_ph, C)
        neg = np.maximum(-g, 0.0).reshape(shape).mean(axis=(2, 4)) * cell
        self.albedo_table = pos.sum(axis=(1, 2))
        self.clamp_table = neg.sum(axis=(1, 2))
        self.clamp_bias = float(self.clamp_table.max())
        top = float(self.albedo_table.max())
        if top > ALBEDO_WARN:
            k = int(np.argmax(self.albedo_table.max(axis=1)))
            warnings.warn(
                f"the matrix as a BRDF reflects more than it receives: directional albedo "
                f"up to {top:.4g} at theta_i = {np.degrees(np.arccos(wi[k, 2])):.1f} deg "
                f"(of which clamping adds {self.clamp_table[k].max():.3g}); as a microscale "
                "BRDF it creates energy there. Causes: q = f cos cos that does not vanish "
                "on the horizon (use quantity 'f_cos' only with odd HemiHarmonics, or "
                "quantity 'f', or a larger min_cos), or negative lobes removed by clamping "
                "(smooth the matrix, compress.smooth)", RuntimeWarning, stacklevel=3)
        # one density per node over (z cell, relative azimuth cell): node b at azimuth
        # phi_b = 2 pi b / n_pi starts its relative cells at absolute cell b n_ph / n_pi
        mass = pos.mean(axis=-1).reshape(n_t, n_pi, n_z, n_ph)
        for b in range(1, n_pi):
            mass[:, b] = np.roll(mass[:, b], -b * (n_ph // n_pi), axis=-1)
        mass = mass.reshape(n_t * n_pi, n_z * n_ph)
        tot = mass.sum(axis=1, keepdims=True)
        prob = np.where(tot > 0, mass / np.where(tot > 0, tot, 1.0), 1.0 / mass.shape[1])
        prob = (1.0 - DEFENSIVE) * prob + DEFENSIVE / mass.shape[1]
        self._prob = prob  # (nodes, cells)
        cdf = np.cumsum(prob, axis=1)
        cdf[:, -1] = 1.0
        # one increasing array over all nodes: node k occupies [k, k + 1)
        self._cdf = (cdf + np.arange(prob.shape[0])[:, None]).reshape(-1)
        self._cell = cell

    # -- the BRDF contract ----------------------------------------------------------------

    def _eval(self, wi: NDArray, wo: NDArray) -> NDArray:
        f = self.matrix.eval(wi, wo, min_cos=self.min_cos)
        return np.maximum(f.reshape(wi.shape[0], self.channels), 0.0)

    # -- sampling -------------------------------------------------------------------------

    def _nodes(self, wi: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """(n, 4) node rows and weights of the bilinear interpolation, and phi_i (n,)."""
        n_t, n_pi, _, _ = self._shape
        z = np.clip(wi[:, 2], 0.0, 1.0)
        pos = np.arccos(z) / (0.5 * np.pi) * (n_t - 1)
        a0 = np.minimum(np.floor(pos).astype(np.int64), n_t - 2)
        ta = np.clip(pos - a0, 0.0, 1.0)
        phi = np.arctan2(wi[:, 1], wi[:, 0]) % (2.0 * np.pi)
        if n_pi > 1:
            pb = phi / (2.0 * np.pi) * n_pi
            b0 = np.floor(pb).astype(np.int64) % n_pi
            tb = np.clip(pb - np.floor(pb), 0.0, 1.0)
        else:
            b0 = np.zeros(z.size, np.int64)
            tb = np.zeros(z.size)
        b1 = (b0 + 1) % n_pi
        rows = np.stack([a0 * n_pi + b0, (a0 + 1) * n_pi + b0, a0 * n_pi + b1,
                         (a0 + 1) * n_pi + b1], axis=1)
        wts = np.stack([(1 - ta) * (1 - tb), ta * (1 - tb), (1 - ta) * tb, ta * tb], axis=1)
        return rows, wts, phi

    def sample(self, wi: ArrayLike, u: ArrayLike) -> NDArray[np.float64]:
        """Draw exit directions from the tabulated density of f cos(theta_o).

        Parameters
        ----------
        wi : (n, 3) array_like of float
            Unit vectors towards the light, z >= 0.
        u : (n, 2) array_like of float
            Uniforms in [0, 1).

        Returns
        -------
        (n, 3) ndarray
            Unit vectors with z > 0, distributed with density :meth:`pdf` (per solid angle).
        """
        wi = as_directions(wi, "wi", upper=True).reshape(-1, 3)
        u = np.asarray(u, dtype=np.float64)
        if u.shape != (wi.shape[0], 2):
            raise ValueError(f"u must have shape ({wi.shape[0]}, 2), got shape {u.shape}")
        _, _, n_z, n_ph = self._shape
        ncell = n_z * n_ph
        rows, wts, phi = self._nodes(wi)
        cw = np.cumsum(wts, axis=1)
        u1 = u[:, 0]
        k = np.minimum(np.sum(u1[:, None] >= cw, axis=1), 3)
        k = np.where(wts[np.arange(k.size), k] > 0, k, np.argmax(wts, axis=1))
        lo = np.take_along_axis(cw, k[:, None], 1)[:, 0] - wts[np.arange(k.size), k]
        node = rows[np.arange(k.size), k]
        v = np.clip((u1 - lo) / wts[np.arange(k.size), k], 0.0, 1.0)
        t = node + v
        idx = np.searchsorted(self._cdf, t, side="right")
        idx = np.clip(idx, node * ncell, node * ncell + ncell - 1)
        c = idx - node * ncell
        low = np.where(c > 0, self._cdf[np.maximum(idx - 1, 0)], node)
        v = np.clip((t - low) / self._prob[node, c], 0.0, 1.0 - 1e-16)
        j, m = np.divmod(c, n_ph)
        z = (j + v) / n_z
        ph = phi + 2.0 * np.pi * (m + u[:, 1]) / n_ph
        s = np.sqrt(np.maximum((1.0 - z) * (1.0 + z), 0.0))
        return np.stack([s * np.cos(ph), s * np.sin(ph), z], axis=-1)

    def pdf(self, wi: ArrayLike, wo: ArrayLike) -> NDArray[np.float64]:
        """Return the density per solid angle of :meth:`sample` at ``wo`` (0 below the horizon).

        Parameters
        ----------
        wi, wo : (n, 3) array_like of float
            Unit vectors, wi with z >= 0.

        Returns
        -------
        (n,) ndarray
        """
        wi = as_directions(wi, "wi", upper=True).reshape(-1, 3)
        wo = as_directions(wo, "wo").reshape(-1, 3)
        if wo.shape != wi.shape:
            raise ValueError(f"wo must have the shape of wi {wi.shape}, got {wo.shape}")
        _, _, n_z, n_ph = self._shape
        rows, wts, phi = self._nodes(wi)
        j = np.clip(np.floor(wo[:, 2] * n_z).astype(np.int64), 0, n_z - 1)
        rel = (np.arctan2(wo[:, 1], wo[:, 0]) - phi) % (2.0 * np.pi)
        m = np.clip(np.floor(rel / (2.0 * np.pi) * n_ph).astype(np.int64), 0, n_ph - 1)
        p = np.sum(wts * self._prob[rows, (j * n_ph + m)[:, None]], axis=1) / self._cell
        return np.where(wo[:, 2] > 0, p, 0.0)

    def __repr__(self) -> str:
        checksum = hashlib.sha256(np.ascontiguousarray(self.matrix.matrix).tobytes()).hexdigest()
        form = "isotropic" if self.isotropic else "dense"
        return (f"MatrixBRDF({self.matrix.basis!r}, quantity={self.matrix.quantity!r}, {form}, "
                f"sha256={checksum[:12]}, negative={self.negative!r})")


def _pair(value: object, name: str, low: tuple[int, int]) -> tuple[int, int]:
    try:
        a, b = value  # type: ignore[misc]
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a pair of integers, got {value!r}") from None
    a = nonneg_int(a, f"{name}[0]")
    b = nonneg_int(b, f"{name}[1]")
    if a < low[0] or b < low[1]:
        raise ValueError(f"{name} must be at least {low}, got {(a, b)}")
    return a, b
