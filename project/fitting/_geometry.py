"""The geometry of a set of direction pairs, computed once and shared by every family."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class _Geometry:
    """Flat pair geometry: cosines, c_d = w_i . h and the products of Lafortune's form."""

    def __init__(self, wi: NDArray, wo: NDArray) -> None:
        # as given (within 1e-6 of unit length): CookTorrance renormalises them itself
        self.wi, self.wo = np.ascontiguousarray(wi), np.ascontiguousarray(wo)
        wi = wi / np.linalg.norm(wi, axis=1)[:, None]
        wo = wo / np.linalg.norm(wo, axis=1)[:, None]
        self.ci = np.clip(wi[:, 2], 0.0, 1.0)
        self.co = np.clip(wo[:, 2], 0.0, 1.0)
        self.cd = np.clip(0.5 * np.linalg.norm(wi + wo, axis=1), 0.0, 1.0)
        self.u = wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]
        self.v = wi[:, 2] * wo[:, 2]
        self.n = wi.shape[0]
        # half vector: cos and sin^2 of theta_h; sines of theta_i, theta_o (rr8807, dsbrdf)
        h = wi + wo
        hn2 = np.sum(h * h, axis=1)
        hn2 = np.where(hn2 > 0.0, hn2, 1.0)
        self.ch = np.clip(h[:, 2] / np.sqrt(hn2), 0.0, 1.0)
        self.sh2 = np.clip((h[:, 0] ** 2 + h[:, 1] ** 2) / hn2, 0.0, 1.0)
        self.si = np.hypot(wi[:, 0], wi[:, 1])
        self.so = np.hypot(wo[:, 0], wo[:, 1])
