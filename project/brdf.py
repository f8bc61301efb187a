"""What every BRDF in the library shares: the evaluation contract and ideal mirror terms.

A BRDF is any object with ``eval(wi, wo)``, ``channels`` and ``isotropic``; ``wi`` and ``wo``
are float64 unit vectors of shape (..., 3) in the local frame (z the surface normal), both
pointing away from the surface.
:class:`BRDF` implements that contract once (validation, broadcasting, the horizon, channel
shapes), so analytic models and measured data only write ``_eval`` on clean flat arrays.

Ideal mirror terms are delta functions and cannot be sampled; a BRDF lists them in
``delta`` as :class:`MirrorDelta` objects, which the projection integrates in closed form.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basis.quadrature import hemisphere_rule
from basis.validation import as_directions, broadcast_batch, check_bytes

__all__ = ["BRDF", "MirrorDelta", "as_color", "broadcast_channels"]


def as_color(value: ArrayLike, name: str, *, low: float | None = 0.0,
             high: float | None = None, open_low: bool = False) -> NDArray[np.float64]:
    """Return a scalar or per-channel parameter as a 1-D float64 array (length 1 or channels).

    Parameters
    ----------
    value : float or (channels,) array_like of float
    name : str
        Argument name for error messages.
    low, high : float or None
        Inclusive bounds (``open_low`` makes the lower bound exclusive); None for no bound.
    """
    try:
        v = np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number or a sequence of numbers (one per channel), "
                        f"got {value!r}") from None
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"{name} must be a number or a 1-D sequence (one per channel), got "
                         f"shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if low is not None and (np.any(v <= low) if open_low else np.any(v < low)):
        raise ValueError(f"{name} must be {'>' if open_low else '>='} {low}, got {value!r}")
    if high is not None and np.any(v > high):
        raise ValueError(f"{name} must be <= {high}, got {value!r}")
    return v


def broadcast_channels(**params: NDArray[np.float64]) -> int:
    """Return the common channel count of per-channel parameters (each of length 1 or C)."""
    sizes = {k: v.size for k, v in params.items()}
    many = {s for s in sizes.values() if s > 1}
    if len(many) > 1:
        raise ValueError("per-channel parameters must have the same length (or length 1), got "
                         + ", ".join(f"{k}: {s}" for k, s in sizes.items()))
    return many.pop() if many else 1


class MirrorDelta:
    """An ideal mirror term f = R(cos theta_i) delta(w_o - mirror(w_i)) / cos theta_i.

    ``delta`` is with respect to solid angle and mirror(x, y, z) = (-x, -y, z), so the term
    reflects the fraction R(cos theta_i) of the incident energy: its directional albedo is R.
    Such a term has no finite coefficients for ``quantity="f"`` (the 1/cos theta_i makes the
    integrals diverge); for ``"f_cos"`` they are one-hemisphere integrals
    int_H R(z) b_j(w) b_k(mirror(w)) z dw, computed by quadrature in ``project``.

    Parameters
    ----------
    reflectance : float or (channels,) array_like of float, or callable
        A constant R in [0, 1] (per channel), or a function of cos theta (array of shape (n,))
        returning (n, channels) values in [0, 1] (e.g. Fresnel).
    channels : int
        Needed only when ``reflectance`` is callable.
    """

    def __init__(self, reflectance: ArrayLike | object, channels: int | None = None) -> None:
        if callable(reflectance):
            if channels is None:
                raise ValueError("channels must be given when reflectance is a function")
            self._fn = reflectance
            self._const = None
            self.channels = int(channels)
        else:
            self._const = as_color(reflectance, "reflectance", low=0.0, high=1.0)
            self._fn = None
            self.channels = self._const.size

    @property
    def is_constant(self) -> bool:
        """True when R does not depend on the angle (then ``constant`` holds it)."""
        return self._const is not None

    @property
    def constant(self) -> NDArray[np.float64] | None:
        """(channels,) constant reflectance, or None when it depends on the angle."""
        return None if self._const is None else self._const.copy()

    def reflectance(self, cos_theta: ArrayLike) -> NDArray[np.float64]:
        """Evaluate R at the given cosines: (n,) in, (n, channels) out."""
        c = np.asarray(cos_theta, dtype=np.float64).reshape(-1)
        if self._const is not None:
            return np.broadcast_to(self._const, (c.size, self.channels)).copy()
        r = np.asarray(self._fn(c), dtype=np.float64).reshape(c.size, self.channels)
        return r

    def __repr__(self) -> str:
        r = "R(theta)" if self._const is None else np.array2string(self._const, precision=4)
        return f"MirrorDelta({r})"


class BRDF:
    """Base class of analytic and measured BRDFs.

    Subclasses set ``channels`` (int), ``isotropic`` (bool) and ``reciprocal`` (bool), may set
    ``delta`` (tuple of :class:`MirrorDelta`) and implement
    ``_eval(wi, wo) -> (n, channels)`` on C-contiguous (n, 3) float64 unit vectors that all
    lie in the upper hemisphere (z >= 0, possibly exactly 0). ``_eval`` must return finite,
    non-negative values wherever the model is defined; the horizon handling, broadcasting and
    output shape live here.
    """

    channels: int = 1
    isotropic: bool = True
    reciprocal: bool = True
    delta: tuple[MirrorDelta, ...] = ()
    #: True when scalar parameters were given: ``eval`` then returns shape (...) not (..., 1).
    _scalar: bool = True

    def eval(self, wi: ArrayLike, wo: ArrayLike) -> NDArray[np.float64]:
        """Evaluate the BRDF f(w_i, w_o) in 1/sr, without the delta terms.

        Parameters
        ----------
        wi, wo : (..., 3) array_like of float
            Unit vectors towards the light and towards the viewer (local frame, z = normal);
            batch shapes broadcast.

        Returns
        -------
        (...) ndarray for a one-channel model given scalar parameters, else (..., channels)
            Zero where either direction lies below the horizon (z < 0).
        """
        wi = as_directions(wi, "wi")
        wo = as_directions(wo, "wo")
        shape = broadcast_batch(wi, wo)
        n = int(np.prod(shape))
        check_bytes(8.0 * n * (6 + 2 * self.channels), f"evaluating {self!r} at {n} pairs")
        wi = np.broadcast_to(wi, (*shape, 3)).reshape(-1, 3)
        wo = np.broadcast_to(wo, (*shape, 3)).reshape(-1, 3)
        out = np.zeros((n, self.channels))
        up = (wi[:, 2] >= 0.0) & (wo[:, 2] >= 0.0)
        if np.all(up):
            out[:] = self._eval(np.ascontiguousarray(wi), np.ascontiguousarray(wo))
        elif np.any(up):
            out[up] = self._eval(np.ascontiguousarray(wi[up]), np.ascontiguousarray(wo[up]))
        out = out.reshape(*shape, self.channels)
        return out[..., 0] if self._scalar and self.channels == 1 else out

    def _eval(self, wi: NDArray[np.float64], wo: NDArray[np.float64]) -> NDArray[np.float64]:
        raise NotImplementedError

    def albedo(self, wi: ArrayLike, *, n_theta: int = 256, n_phi: int = 512) -> NDArray:
        """Compute the directional albedo, the reflectances of the delta terms included.

        albedo(w_i) = int_H f(w_i, w_o) cos(theta_o) dw_o + the delta reflectances.

        A numerical reference by a Gauss-Legendre x uniform product rule over w_o; sharp
        lobes need more nodes (check by doubling ``n_theta`` and ``n_phi``).

        Parameters
        ----------
        wi : (..., 3) array_like of float
        n_theta, n_phi : int
            Nodes of the product rule in cos(theta_o) and phi_o.

        Returns
        -------
        (...) or (..., channels) ndarray, like :meth:`eval`
        """
        wi = as_directions(wi, "wi")
        batch = wi.shape[:-1]
        flat = wi.reshape(-1, 3)
        rule = hemisphere_rule(n_theta, n_phi)
        wts = rule.weights * rule.points[:, 2]
        out = np.empty((flat.shape[0], self.channels))
        for k, w in enumerate(flat):  # one incidence at a time keeps memory at one rule
            f = self.eval(w, rule.points).reshape(rule.points.shape[0], self.channels)
            out[k] = wts @ f
        for d in self.delta:
            out += np.where(flat[:, 2:3] >= 0, d.reflectance(flat[:, 2]), 0.0)
        out[flat[:, 2] < 0] = 0.0
        out = out.reshape(*batch, self.channels)
        return out[..., 0] if self._scalar and self.channels == 1 else out

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
