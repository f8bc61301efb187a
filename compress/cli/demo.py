"""What ``scatmodes demo`` shows.

The bases, their sizes and measured orthonormality, pictures of the first Helmholtz surface
scattering modes (Figure 1 of Koenderink, van Doorn & Stavridi 1996), two built-in models
projected at a few orders (resolution against error), and a small Monte Carlo simulation of
a Gaussian surface against Beckmann + Smith (Figure 6 of Westin, Arvo & Torrance 1992).

On a first run numba compiles the kernels (about 25 s of one core, then cached on disk):
:class:`CompileAhead` compiles the Zernike kernel and the simulation's kernels in a second
process while this one compiles the harmonics', the quadrature's and the evaluator of
coefficient matrices (with no simulation, the second process takes the evaluator), so that
the first run costs about half of the compilation more than a cached one. A cached run
starts no second process.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numba.core import event as numba_event

import basis
from project.io import atomic_path

__all__ = ["COMPILE_STEPS", "FIXED", "STUDY_TOL", "CompileAhead", "basis_table",
           "compile_evaluator", "compile_projection", "compile_simulation", "compile_zernike",
           "demo_models", "model_study",
           "modes_orthonormality_error", "orthonormality_error", "plot_inplane", "plot_modes",
           "resolution_deg", "resolution_rows", "simulate_demo", "to_markdown"]

#: Relative tolerance of the demo's projections (``project.project`` defaults to 1e-6 for
#: models): the printed errors agree to five digits with 1e-6, at a quarter of the time
#: (the sharp Cook-Torrance lobe at order 2 alone needs 9 s at 1e-6).
STUDY_TOL = 1e-4


class CompileAhead:
    """Compile the kernels of named steps in a second Python process while the caller goes on.

    numba compiles on one core and holds a process-wide lock while it does, so a second
    process is the only way to compile two kernels at once; it writes numba's on-disk cache,
    from which the caller's process then loads them (the same machine code, so the same
    bits). :meth:`wait` blocks until a step's kernels are compiled. If the process cannot
    start or fails, each step compiles its kernels itself, as without this class.

    Parameters
    ----------
    steps : dict of str to tuple of int
        Step name (a key of :data:`COMPILE_STEPS`) -> its integer arguments, compiled in
        this order.
    lazy : bool
        Start the process only when this process first compiles a kernel (numba's
        ``numba:compile`` event, which fires on a cache miss only): a run whose kernels are
        all cached starts none, since loading them twice would only take a core from the
        caller. False starts it at once.

    Notes
    -----
    The process runs ``python -c`` with this module's :func:`_compile_main`, not
    :mod:`multiprocessing`, whose spawned children re-import the caller's main script.
    """

    def __init__(self, steps: dict[str, tuple[int, ...]], *, lazy: bool = False) -> None:
        self._steps = dict(steps)
        self._pending = list(steps)
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()
        self._listener: Any = None
        if not steps:
            return
        if lazy:
            self._listener = _OnCompile(self._start)
            numba_event.register("numba:compile", self._listener)
        else:
            self._start()

    def _start(self) -> None:
        with self._lock:
            self._unlisten()
            if self._proc is not None or not self._pending:
                return
            root = str(Path(__file__).resolve().parents[2])  # the folder holding compress/
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(
                [root, *filter(None, [os.environ.get("PYTHONPATH")])]))
            argv = [f"{name}:{','.join(map(str, self._steps[name]))}" for name in self._pending]
            try:
                self._proc = subprocess.Popen(
                    [sys.executable, "-c", "from compress.cli.demo import _compile_main; "
                     "_compile_main()", *argv], stdin=subprocess.DEVNULL,
                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True)
            except OSError:  # no second process here: each step compiles its own kernels
                self._pending = []

    def _unlisten(self) -> None:
        if self._listener is not None:
            numba_event.unregister("numba:compile", self._listener)
            self._listener = None

    @property
    def started(self) -> bool:
        """Whether the compiling process was started."""
        return self._proc is not None

    def wait(self, name: str) -> bool:
        """Wait until the kernels of step ``name`` are compiled; return True if they are.

        False if the step was not asked for, was already waited for, or its kernels are
        left to the caller (no process was started, or it failed).
        """
        with self._lock:
            proc = self._proc
            if proc is None:
                self._unlisten()  # from here on the caller compiles what it needs itself
                if name in self._pending:
                    del self._pending[:self._pending.index(name) + 1]
                return False
        if name not in self._pending:
            return False
        while self._pending:
            line = proc.stdout.readline().strip()  # type: ignore[union-attr]
            if not line:  # the process ended early: the steps left compile in place
                self._pending = []
                return False
            if line in self._pending:
                del self._pending[:self._pending.index(line) + 1]
                if line == name:
                    return True
        return False

    def close(self) -> None:
        """Stop the process if it is still compiling (numba's cache writes are atomic)."""
        with self._lock:
            self._unlisten()
            if self._proc is not None:
                if self._proc.poll() is None:
                    self._proc.terminate()
                self._proc.wait()
                self._proc.stdout.close()  # type: ignore[union-attr]
                self._proc = None
            self._pending = []

    def __enter__(self) -> CompileAhead:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _OnCompile(numba_event.Listener):
    """Calls ``start`` when numba begins to compile a kernel (a cache miss)."""

    def __init__(self, start: Any) -> None:
        self._start = start

    def on_start(self, event: Any) -> None:
        self._start()

    def on_end(self, event: Any) -> None:
        pass


def _compile_main() -> None:
    """Compile the steps named on the command line (``NAME:ARG,ARG``), print each name done."""
    warnings.simplefilter("ignore")
    for item in sys.argv[1:]:
        name, _, args = item.partition(":")
        COMPILE_STEPS[name](*(int(a) for a in args.split(",") if a))
        print(name, flush=True)


def compile_zernike() -> None:
    """Compile the Zernike kernel (both of its strategies: low and high orders)."""
    w = np.array([[0.6, 0.0, 0.8]])
    basis.HemiZernike(2).eval(w)
    basis.HemiZernike(8).eval(w)


def compile_projection() -> None:
    """Compile the quadrature kernels of the model study (Phong in hemispherical harmonics).

    The same call as :func:`model_study` makes (so the same kernels with the same argument
    types); with the harmonics, whose kernel step 1 compiles first, it needs no Zernike
    kernel. The errors' evaluator is :func:`compile_evaluator`.
    """
    from project import project

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        project(demo_models()["phong"], basis.HemiHarmonics(2), tol=STUDY_TOL)


def compile_evaluator() -> None:
    """Compile the fused evaluator of isotropic coefficient matrices (the study's errors).

    One kernel serves every basis kind.
    """
    b = basis.HemiZernike(2)
    w = np.array([[0.6, 0.0, 0.8]])
    blocks = [np.eye(i.size)[None] for i in b.azimuthal_blocks().cos]
    basis.CoefficientMatrix.from_blocks(b, blocks, "f_cos").eval(w, w)


def compile_simulation(resolution: int = 64, order: int = 8) -> None:
    """Compile the tracer and estimator kernels with :func:`simulate_demo`'s argument types."""
    from project.microgeometry import GaussianSurface, simulate

    surface = GaussianSurface(1.0, 6.5, resolution=resolution, seed=7)
    simulate(surface, basis.HemiZernike(order), rays=64, seed=1, progress=False)


#: What :class:`CompileAhead` can compile: step name -> function of integer arguments.
COMPILE_STEPS = {"zernike": compile_zernike, "evaluator": compile_evaluator,
                 "projection": compile_projection, "simulation": compile_simulation}


def orthonormality_error(b: basis.Basis) -> float:
    """Return max |G - I| of the Gram matrix G computed with the basis' exact quadrature rule."""
    rule = b.exact_rule()
    v = b.eval(rule.points)
    g = v.T @ (rule.weights[:, None] * v)
    return float(np.max(np.abs(g - np.eye(b.size))))


def modes_orthonormality_error(modes: basis.HelmholtzModes) -> float:
    """Return max |G - I| for Helmholtz modes on H x H with a product of exact hemisphere rules."""
    rule = modes.hemisphere.exact_rule()
    p, w = rule.points, rule.weights
    g = np.zeros((modes.size, modes.size))
    for k in range(p.shape[0]):  # one incident node at a time keeps memory at O(nodes * size)
        v = modes.eval(p[k], p)
        g += (w[k] * w[:, None] * v).T @ v
    return float(np.max(np.abs(g - np.eye(modes.size))))


def basis_table(orders: tuple[int, ...] = (2, 4, 8, 16, 32), points: int = 20_000,
                seed: int = 0, wait: Callable[[str], object] | None = None) -> list[dict]:
    """Return one row per (basis, order): size, orthonormality error, evaluation ns per function.

    Rows are ordered by order, then spherical harmonics, hemispherical harmonics, Zernike;
    they are computed one basis kind after the other, and ``wait("zernike")`` (such as
    :meth:`CompileAhead.wait`), if given, is called before the Zernike functions' first
    evaluation.
    """
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(points, 3))
    w[:, 2] = np.abs(w[:, 2])
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    kinds = (basis.SphericalHarmonics, basis.HemiHarmonics, basis.HemiZernike)
    rows: list[dict] = [{} for _ in range(len(orders) * len(kinds))]
    for k, kind in enumerate(kinds):
        if kind is basis.HemiZernike and wait is not None:
            wait("zernike")
        for i, n in enumerate(orders):
            b = kind(n)
            b.eval(w[:1])  # compile outside the timing
            t0 = time.perf_counter()
            b.eval(w)
            dt = time.perf_counter() - t0
            rows[i * len(kinds) + k] = {"basis": repr(b), "order": n, "size": b.size,
                                        "orthonormality error": orthonormality_error(b),
                                        "ns per value": 1e9 * dt / (points * b.size)}
    for n in (2, 4, 8):
        m = basis.HelmholtzModes(n)
        rows.append({"basis": repr(m), "order": n, "size": m.size,
                     "orthonormality error": modes_orthonormality_error(m),
                     "ns per value": float("nan")})
    return rows


#: columns printed in fixed point (the others in short scientific form)
FIXED = ("ns per value", "resolution deg", "eval ns")


def to_markdown(rows: list[dict]) -> str:
    """Format dict rows as a markdown table (numbers in short scientific form, NaN as '-')."""
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        cells = [f"{r[k]:.2e}" if isinstance(r[k], float) and k not in FIXED
                 else (f"{r[k]:.1f}" if isinstance(r[k], float) else str(r[k])) for k in keys]
        lines.append("| " + " | ".join(cells).replace("nan", "-") + " |")
    return "\n".join(lines)


def plot_modes(path: str | Path, order: int = 4, theta_i: float = np.pi / 4) -> Path:
    """Plot every isotropic mode S_nm^l(theta_i, w_o) up to ``order`` on a disk.

    Each panel shows the outgoing hemisphere on Lambert's equal-area disk (centre = normal,
    rim = horizon, incident azimuth 0 to the right), as in Figure 1 of Koenderink, van Doorn
    & Stavridi (1996).
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


# -- models ----------------------------------------------------------------------------------
def demo_models() -> dict[str, Any]:
    """Return the demo's two built-in models by file-name label.

    A glossy Phong lobe (no mirror term, so the error is finite at every order) and a rough
    Beckmann Cook-Torrance.
    """
    from project import models

    return {"phong": models.Phong(0.3, 0.4, 20.0),
            "cooktorrance": models.CookTorrance(0.2, 0.3)}


def resolution_deg(order: int) -> float:
    """Return 180 deg / order: the half period of the highest degree kept (inf at order 0)."""
    return 180.0 / order if order > 0 else float("inf")


def model_study(brdf: Any, orders: tuple[int, ...],
                kinds: tuple[str, ...] = ("zernike", "harmonics"), tol: float = STUDY_TOL) -> Any:
    """Run compress.study of ``brdf`` at ``orders`` (odd harmonics skip order 0).

    ``tol`` is the relative tolerance of each quadrature projection (``project.project``).
    """
    from ..study import Study, study

    parts = [study(brdf, k, [o for o in orders if o > 0 or k != "harmonics"], tol=tol)
             for k in kinds if any(o > 0 or k != "harmonics" for o in orders)]
    return Study([r for p in parts for r in p.rows], parts[0].source, parts[0].quantity,
                 parts[0].sampling, [m for p in parts for m in p.messages])


def resolution_rows(name: str, st: Any) -> list[dict]:
    """Return compact rows of a study: order, resolution, size, errors, evaluation time."""
    return [{"model": name, "basis": r["kind"], "order": r["order"],
             "resolution deg": resolution_deg(r["order"]), "coefficients": r["coefficients"],
             "l2": float(r["l2"]), "max abs 1/sr": float(r["max_abs"]),
             "eval ns": float(r["eval_ns"])} for r in st.rows]


# -- simulation ------------------------------------------------------------------------------
def simulate_demo(rays: int = 30_000, resolution: int = 64, seed: int = 1, order: int = 8,
                  progress: bool = False) -> dict[str, Any]:
    """Run a small simulation in the manner of Westin, Arvo & Torrance 1992.

    A mirror-faceted Gaussian surface (sigma/tau = 1/6.5) in HemiZernike(order), compared
    with Beckmann + Smith (F = 1) at the measured roughness.

    Returns a dict with ``lines`` (printable summary), ``curves`` (label -> BRDF-like object
    for :func:`plot_inplane`), ``title``, ``result`` and ``difference`` (relative Frobenius
    distance of the simulated and projected model matrices).
    """
    from project import project
    from project.microgeometry import GaussianSurface, simulate
    from project.models import CookTorrance

    surface = GaussianSurface(1.0, 6.5, resolution=resolution, seed=7)
    b = basis.HemiZernike(order)
    res = simulate(surface, b, rays=rays, seed=seed, progress=progress)
    m = surface.roughness
    model = CookTorrance(0.0, m, ior=None)
    with warnings.catch_warnings():  # the Gibbs warning: reported below as a number
        warnings.simplefilter("ignore", RuntimeWarning)
        # the simulation estimates f cos cos: compare like with like
        ref = project(model, b, quantity=res.matrix.quantity)
    diff = float(np.linalg.norm(res.matrix.matrix - ref.matrix) / np.linalg.norm(ref.matrix))
    e = res.energy
    lines = [f"{surface!r}",
             f"measured Beckmann roughness m = {m:.4f} (nominal {surface.nominal_roughness:.4f})",
             f"{res.rays} rays in {res.seconds:.2f} s ({res.rays_per_second:.3g} rays/s), "
             f"asymmetry Q = {res.asymmetry:.3g}",
             f"energy: reflected {e['reflected']:.4f}, absorbed {e['absorbed']:.4f}, escaped "
             f"{e['escaped']:.4f}; single scattering {res.single_scatter:.4f} (the rest left "
             "after 2+ reflections, which Beckmann + Smith omits)",
             f"relative L2 distance simulated vs projected Beckmann + Smith: {diff:.3g} "
             f"(M_00: {res.matrix.matrix[0, 0]:.4f} vs {ref.matrix[0, 0]:.4f}); order {order} "
             f"itself misses {100 * ref.info['truncation_error']:.3g} % of the model's L2 norm"]
    return {"lines": lines, "result": res, "difference": diff,
            "curves": {"simulated": res.matrix, "Beckmann + Smith": model,
                       f"same, order {order}": ref},
            "title": f"{rays} rays, HemiZernike({order}), Gaussian surface m = {m:.3f}"}


def plot_inplane(path: str | Path, curves: dict[str, Any], incidences=(0.0, 30.0, 60.0),
                 title: str = "") -> Path:
    """Plot in-plane f cos(theta_o) at each incidence (degrees) for every object with ``eval``.

    Positive theta_o is the forward (specular) side.
    """
    theta_o = np.radians(np.linspace(-89.0, 89.0, 357))
    wo = np.stack([-np.sin(theta_o), np.zeros_like(theta_o), np.cos(theta_o)], axis=-1)
    fig = Figure(figsize=(4.4 * len(incidences), 3.4))
    styles = ["-", "--", ":", "-."]
    for j, ti in enumerate(incidences):
        ax = fig.add_subplot(1, len(incidences), j + 1)
        wi = np.array([np.sin(np.radians(ti)), 0.0, np.cos(np.radians(ti))])
        for k, (label, obj) in enumerate(curves.items()):
            v = np.asarray(obj.eval(wi, wo))
            v = v if v.ndim == 1 else v[..., 0]
            ax.plot(np.degrees(theta_o), v * wo[:, 2], styles[k % 4], label=label)
        ax.set_title(f"theta_i = {ti:g} deg")
        ax.set_xlabel("theta_o (deg, + forward)")
    fig.axes[0].set_ylabel("f cos(theta_o)  [1/sr]")
    fig.axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    return Path(path)
