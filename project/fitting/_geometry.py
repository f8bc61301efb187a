"""The geometry of a set of direction pairs, computed once and shared by every family."""

from __future__ import annotations

from functools import cached_property

import numpy as np
from numpy.typing import NDArray


class _Geometry:
    """Flat pair geometry: cosines, c_d = w_i . h and the products of Lafortune's form.

    Each quantity is computed when a family first asks for it: a family reads a few of them
    (the microfacet families none, through their own kernel), and a fitted model is
    evaluated on a fresh geometry.
    """

    def __init__(self, wi: NDArray, wo: NDArray) -> None:
        # as given (within 1e-6 of unit length): CookTorrance renormalises them itself
        self.wi, self.wo = np.ascontiguousarray(wi), np.ascontiguousarray(wo)
        self.n = self.wi.shape[0]

    @cached_property
    def _unit(self) -> tuple[NDArray, NDArray]:
        wi = self.wi / np.linalg.norm(self.wi, axis=1)[:, None]
        wo = self.wo / np.linalg.norm(self.wo, axis=1)[:, None]
        return wi, wo

    @cached_property
    def ci(self) -> NDArray:
        return np.clip(self._unit[0][:, 2], 0.0, 1.0)

    @cached_property
    def co(self) -> NDArray:
        return np.clip(self._unit[1][:, 2], 0.0, 1.0)

    @cached_property
    def cd(self) -> NDArray:
        wi, wo = self._unit
        return np.clip(0.5 * np.linalg.norm(wi + wo, axis=1), 0.0, 1.0)

    @cached_property
    def u(self) -> NDArray:
        wi, wo = self._unit
        return wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]

    @cached_property
    def v(self) -> NDArray:
        wi, wo = self._unit
        return wi[:, 2] * wo[:, 2]

    @cached_property
    def _half(self) -> tuple[NDArray, NDArray]:
        """Return cos theta_h and sin^2 theta_h of the half vector (0 and 0 where w_i = -w_o)."""
        wi, wo = self._unit
        h = wi + wo
        hn2 = np.sum(h * h, axis=1)
        hn2 = np.where(hn2 > 0.0, hn2, 1.0)
        return (np.clip(h[:, 2] / np.sqrt(hn2), 0.0, 1.0),
                np.clip((h[:, 0] ** 2 + h[:, 1] ** 2) / hn2, 0.0, 1.0))

    @cached_property
    def ch(self) -> NDArray:
        return self._half[0]

    @cached_property
    def sh2(self) -> NDArray:
        return self._half[1]

    @cached_property
    def si(self) -> NDArray:
        """Return sin theta_i (rr8807, dsbrdf)."""
        return np.hypot(self._unit[0][:, 0], self._unit[0][:, 1])

    @cached_property
    def so(self) -> NDArray:
        return np.hypot(self._unit[1][:, 0], self._unit[1][:, 1])
