"""What ``scatmodes demo`` shows: the bases, their sizes and measured orthonormality, and
pictures of the first Helmholtz surface scattering modes (the seed paper's Figure 1)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

import basis

from ._io import atomic_path


def orthonormality_error(b: basis.Basis) -> float:
    """max |G - I| of the Gram matrix G computed with the basis' exact quadrature rule."""
    rule = b.exact_rule()
    v = b.eval(rule.points)
    g = v.T @ (rule.weights[:, None] * v)
    return float(np.max(np.abs(g - np.eye(b.size))))


def modes_orthonormality_error(modes: basis.HelmholtzModes) -> float:
    """max |G - I| for Helmholtz modes on H x H with a product of exact hemisphere rules."""
    rule = modes.hemisphere.exact_rule()
    p, w = rule.points, rule.weights
    g = np.zeros((modes.size, modes.size))
    for k in range(p.shape[0]):  # one incident node at a time keeps memory at O(nodes * size)
        v = modes.eval(p[k], p)
        g += (w[k] * w[:, None] * v).T @ v
    return float(np.max(np.abs(g - np.eye(modes.size))))


def basis_table(orders: tuple[int, ...] = (2, 4, 8, 16, 32), points: int = 20_000,
                seed: int = 0) -> list[dict]:
    """One row per (basis, order): size, orthonormality error, evaluation ns per function."""
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(points, 3))
    w[:, 2] = np.abs(w[:, 2])
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    rows = []
    for n in orders:
        for b in (basis.SphericalHarmonics(n), basis.HemiHarmonics(n), basis.HemiZernike(n)):
            b.eval(w[:1])  # compile outside the timing
            t0 = time.perf_counter()
            b.eval(w)
            dt = time.perf_counter() - t0
            rows.append({"basis": repr(b), "order": n, "size": b.size,
                         "orthonormality error": orthonormality_error(b),
                         "ns per value": 1e9 * dt / (points * b.size)})
    for n in (2, 4, 8):
        m = basis.HelmholtzModes(n)
        rows.append({"basis": repr(m), "order": n, "size": m.size,
                     "orthonormality error": modes_orthonormality_error(m),
                     "ns per value": float("nan")})
    return rows


def to_markdown(rows: list[dict]) -> str:
    """A markdown table of dict rows (numbers in short scientific form)."""
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        cells = [f"{r[k]:.2e}" if isinstance(r[k], float) and k != "ns per value"
                 else (f"{r[k]:.2f}" if isinstance(r[k], float) else str(r[k])) for k in keys]
        lines.append("| " + " | ".join(cells).replace("nan", "-") + " |")
    return "\n".join(lines)


def plot_modes(path: str | Path, order: int = 4, theta_i: float = np.pi / 4) -> Path:
    """Disk plots of every isotropic mode S_nm^l(theta_i, w_o) up to ``order``.

    Each panel shows the outgoing hemisphere on Lambert's equal-area disk (centre = normal,
    rim = horizon, incident azimuth 0 to the right), as in the seed paper's Figure 1.
    """
    modes = basis.HelmholtzModes(order)
    r = np.linspace(0.0, 1.0, 61)  # equal-area radius rho = sqrt(2) sin(theta/2)
    ph = np.linspace(-np.pi, np.pi, 121)
    rr, pp = np.meshgrid(r, ph, indexing="ij")
    theta = 2.0 * np.arcsin(rr / np.sqrt(2.0))
    wo = basis.from_angles(theta, pp)
    wi = basis.from_angles(theta_i, 0.0)
    v = modes.eval(wi, wo)
    ncol = 5
    nrow = -(-modes.size // ncol)
    fig = Figure(figsize=(2.2 * ncol, 2.3 * nrow))
    for k, (n, m, l) in enumerate(modes.indices):
        ax = fig.add_subplot(nrow, ncol, k + 1, projection="polar")
        lim = float(np.max(np.abs(v[..., k]))) or 1.0
        ax.pcolormesh(pp, rr, v[..., k], cmap="RdBu_r", vmin=-lim, vmax=lim, shading="auto")
        ax.set_title(f"n={n} m={m} l={l}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"Helmholtz surface scattering modes up to order {order}, "
                 f"theta_i = {np.degrees(theta_i):.0f} deg (red +, blue -)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    return Path(path)
