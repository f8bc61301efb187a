"""Projection of a BRDF onto a basis: M_jk = int int q(w_i, w_o) b_j(w_i) b_k(w_o) dw_i dw_o.

Every basis function separates as b_k(theta, phi) = P_k(cos theta) A_k(phi) with
A_k = cos(m phi), sin(|m| phi) or 1, so the double integral is a product rule: Gauss-Legendre
in z = cos(theta) for each direction and the uniform rule in azimuth, whose azimuthal sums
are Fourier transforms.

Isotropic BRDFs depend on the azimuths through dphi = phi_i - phi_o only, and evenly. With
F_m(z_i, z_o) = int_0^{2 pi} q cos(m dphi) d dphi the matrix is block diagonal by m:

    M^(m) = c_m P_m^T W F_m W P_m,     c_0 = 2 pi, c_m = pi (m > 0),

P_m the (nodes, k_m) table of the radial factors with azimuthal order m and W the z weights.
The samples form a (z_i, z_o, dphi) grid with dphi in [0, pi]; when q is also reciprocal and
mirror symmetric (y -> -y), so that F_m is symmetric in (z_i, z_o), only z_i <= z_o is
evaluated. Measured tables need not be mirror symmetric; both triangles are then sampled
(and, for a BRDF that is neither reciprocal nor mirror symmetric, both signs of dphi) and
the blocks project the even part of q. That is O(N^2 N_phi) evaluations and
O(N^3) arithmetic instead of the O(N^4) of a dense product rule. A pilot chooses the
(z_i, z_o) rule among the tensor Gauss rules in z and in sqrt(z) and a rule in
((z_i + z_o) / 2, z_i - z_o) graded towards the diagonal, where the specular ridge of a
sharp measured material lies; tensor rules put a node pair on its crest for every node and
misjudge it until their spacing is well below its width.

Anisotropic BRDFs use the (z_i, phi_i, z_o, phi_o) grid with Fourier transforms in both
azimuths, processed a few (z_i, z_o) pairs at a time so memory stays bounded; reciprocal ones
only on the pairs z_i <= z_o (the other half is the transpose). Their z rule is Gauss in z or
in sqrt(z), chosen by a pilot: the second removes the 1/sqrt(cos theta) horizon singularity
of Ward's lobe, on which Gauss in z converges only like 1/N.

Non-reciprocal BRDFs (``brdf.reciprocal`` False) are sampled on every (z_i, z_o) pair, so
the matrix is general; ``project(..., reciprocal=True)`` keeps its symmetric part, the
projection of the reciprocal part (q + q^T) / 2, which is also the closest reciprocal
representation in L2.

The node counts start from the order; the z and azimuth rules are doubled separately, each
time the one whose last doubling changed the result more, until the sum of the changes
is below the tolerance. That sum is returned as the error estimate (a conservative one, since
the finer result is returned). The azimuth rules are nested (the rule with twice the
intervals holds every node of the other), so for isotropic BRDFs doubling the azimuths
evaluates only the new nodes, and every rule carries its own azimuth estimate for free, the
change from the rule made of its even nodes; the diagonal rule doubles its nodes along and
across the ridge separately.
"""

from __future__ import annotations

import time
import warnings
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import roots_legendre
from threadpoolctl import threadpool_limits

from basis import Basis, CoefficientMatrix
from basis.jit import loopjit, run_parallel
from basis.validation import check_bytes, choice, nonneg_int

__all__ = ["default_quantity", "project", "radial_table"]

#: Pairs evaluated per call of ``brdf.eval``: bounds the memory of one chunk (~100 MB for RGB).
CHUNK = 1 << 21

#: Relative L2 truncation error above which ``project`` warns that the BRDF is too sharp for
#: the order (the truncated expansion rings and overshoots).
GIBBS_ERROR = 0.1


def project(
    brdf: Any,
    basis: Basis,
    *,
    quantity: str = "auto",
    method: str = "quadrature",
    tol: float = 1e-6,
    isotropic: bool | None = None,
    nodes: tuple[int, int] | None = None,
    max_nodes: int = 512,
    max_evaluations: int = 100_000_000,
    samples: int | None = None,
    seed: int = 0,
    reciprocal: bool | None = None,
) -> CoefficientMatrix:
    """Coefficient matrix of a BRDF in a basis (the L2 projection onto the basis products).

    Parameters
    ----------
    brdf : BRDF
        Any object with ``eval(wi, wo)``, ``channels`` and ``isotropic``. ``eval`` takes
        float64 unit vectors of shape (..., 3) in the local frame (z the surface normal,
        both directions pointing away from the surface) and returns (...) or
        (..., channels) values. Ideal mirror terms listed in ``brdf.delta`` are projected in
        closed form.
    basis : basis.Basis
        ``HemiZernike``, ``HemiHarmonics`` or ``SphericalHarmonics`` (for the full sphere the
        BRDF is zero below the horizon, so only the upper hemisphere is integrated).
    quantity : {"auto", "f_cos", "f"}
        What the matrix represents: f cos(theta_i) cos(theta_o) (the choice of Westin, Arvo
        & Torrance 1992, sec. 2.5: bounded at grazing, mirror terms have finite
        coefficients) or f. ``"auto"`` (default) picks what stays accurate on all of H x H
        when the matrix is evaluated as a BRDF, see :func:`default_quantity`: ``"f_cos"``
        for bases that vanish on the horizon (the odd hemisphere harmonics) and for BRDFs
        with mirror terms, ``"f"`` otherwise.
    method : {"quadrature", "montecarlo", "lstsq"}
        ``"quadrature"``: the product rule above, refined by doubling until converged.
        ``"montecarlo"``: scrambled Sobol points in (z_i, phi_i, z_o, phi_o), for BRDFs that
        are expensive to evaluate; the error estimate is the standard error over 8
        independent scrambles. ``"lstsq"``: a least-squares fit (:func:`project.fit`) to the
        BRDF sampled at Sobol pairs, twice as many as there are unknowns unless ``samples``
        says otherwise. Sobol counts are rounded up to a power of two.
    tol : float
        Quadrature only: target for the estimated max |error| of the coefficients, relative
        to max |M|. The default 1e-6 is far below every truncation error met in practice;
        smooth analytic models reach 1e-12 cheaply, but models with kinks (Oren-Nayar's
        max(0, cos dphi)) or tabulated data (trilinear MERL, which converges like N^-2) stall
        near 1e-7 and 1e-4: ask for what the data can give.
    isotropic : bool or None
        Treat the BRDF as isotropic (a function of |phi_i - phi_o|). None: ``brdf.isotropic``.
    nodes : (n_z, n_phi), optional
        Quadrature only: use this rule (nodes in z per direction, in azimuth) once, with no
        refinement; the error estimate then compares with the rule of half the size. The z
        rule is then Gauss-Legendre in z (no pilot chooses the sqrt(z) rule).
    max_nodes : int
        Quadrature only: refinement stops (with a warning) when ``n_z`` would exceed this, or
        ``n_phi`` four times this.
    max_evaluations : int
        Quadrature only: refinement also stops (with a warning) before a rule that would
        evaluate the BRDF at more pairs than this (an anisotropic rule costs n_z^2 n_phi^2).
    samples : int, optional
        Monte Carlo and least squares: number of direction pairs (Monte Carlo default
        2**16 per scramble).
    seed : int
        Seed of the Sobol scrambles.
    reciprocal : bool or None
        Form of the matrix. None (default): ``brdf.reciprocal`` (True when the BRDF does not
        say). True: symmetric, the projection of the reciprocal part (q + q^T) / 2 of a
        non-reciprocal BRDF (the closest reciprocal representation; the rest, the
        antisymmetric part, is lost). False: the general matrix of
        :class:`basis.CoefficientMatrix` with ``reciprocal=False``, which also holds the
        antisymmetric part (twice the numbers of a symmetric one; for a reciprocal BRDF it
        is symmetric to quadrature precision).

    Returns
    -------
    CoefficientMatrix
        Isotropic block form for isotropic BRDFs. ``info`` holds ``method``, ``nodes``,
        ``evaluations``, ``error_estimate`` (absolute, max over entries), ``rel_error``,
        ``converged``, ``truncation_error`` (relative L2 error of the truncated expansion
        against the BRDF itself, by Parseval; None with mirror terms, whose norm is
        infinite; for ``reciprocal=True`` on a non-reciprocal BRDF it includes the
        antisymmetric part left out), ``reciprocal`` (the form chosen),
        ``antisymmetric_part`` (||(M - M^T) / 2||_F / ||q||, max over channels, of the general
        projection: the relative L2 norm of the projected antisymmetric part, which a
        symmetric matrix misses; 0 when sampled only on z_i <= z_o), ``tail_fraction``
        (relative RMS of the coefficients of the last two
        degrees), ``seconds``, for anisotropic BRDFs ``asymmetry`` (max |M - M^T| / max |M|
        before symmetrising; 0 for reciprocal ones, which are symmetric by construction) and,
        after refinement, ``azimuth_rule`` and ``z_rule`` (``"gauss"``, ``"sqrt"`` or, isotropic
        only, ``"diagonal"``).

    Warns
    -----
    RuntimeWarning
        When the quadrature did not reach ``tol`` within ``max_nodes`` nodes, or when the
        truncated expansion misses more than 10 % of the BRDF's L2 norm (the BRDF is too
        sharp for the order: expect Gibbs ringing; raise the order or filter).

    Raises
    ------
    ValueError
        For ``quantity="f"`` with mirror (delta) terms: their coefficients diverge.

    Examples
    --------
    Lambert with albedo 0.5 in Westin's form is one coefficient, 2a/3 on b_10:

    >>> from basis import HemiHarmonics
    >>> from project.models import Lambert
    >>> cm = project(Lambert(0.5), HemiHarmonics(3))
    >>> k = cm.basis.index(1, 0)
    >>> round(float(cm.matrix[k, k]), 12), cm.info["error_estimate"] < 1e-14
    (0.333333333333, True)
    """
    t0 = time.perf_counter()
    _check_brdf(brdf)
    if not isinstance(basis, Basis):
        raise TypeError(f"basis must be a basis object (e.g. basis.HemiZernike(8)), got "
                        f"{type(basis).__name__}")
    quantity = choice(quantity, "quantity", ("auto", "f_cos", "f"))
    method = choice(method, "method", ("quadrature", "montecarlo", "lstsq"))
    iso = bool(brdf.isotropic) if isotropic is None else bool(isotropic)
    if reciprocal is None:
        rec = bool(getattr(brdf, "reciprocal", True))
    elif isinstance(reciprocal, bool | np.bool_):
        rec = bool(reciprocal)
    else:
        raise TypeError(f"reciprocal must be None, True or False, got {reciprocal!r}")
    deltas = tuple(getattr(brdf, "delta", ()) or ())
    if quantity == "auto":
        quantity = default_quantity(basis, brdf)
    if deltas and quantity == "f":
        raise ValueError("quantity must be 'f_cos' for a BRDF with mirror (delta) terms: with "
                         "quantity='f' their coefficients int b_j b_k / cos(theta) diverge")
    if not (isinstance(tol, float | int) and 0 < tol < 1):
        raise ValueError(f"tol must be a number in (0, 1), got {tol!r}")
    # the result and its working copies, before any node is placed or the BRDF evaluated
    # (the rules then check each chunk of evaluations on their own)
    ch = int(brdf.channels)
    if iso:
        k = np.bincount(basis.azimuthal[basis.azimuthal >= 0])
        nz = basis.order + 2  # the first z rule, (nz, nz, m) azimuthal transforms
        need = 8.0 * ch * (_RESULT_COPIES * float(np.sum(k * k)) + nz * nz * k.size)
    else:
        need = 8.0 * ch * _RESULT_COPIES * float(basis.size) ** 2
    check_bytes(need, f"projecting {brdf!r} on {basis!r} ({ch} channel(s), "
                      f"{'isotropic blocks' if iso else 'a dense matrix'})")

    if method == "quadrature":
        blocks_or_dense, info = _quadrature(brdf, basis, quantity, iso, tol, nodes, max_nodes,
                                            max_evaluations)
    elif method == "montecarlo":
        blocks_or_dense, info = _montecarlo(brdf, basis, quantity, iso, samples, seed, rec)
    else:
        return _lstsq(brdf, basis, quantity, iso, rec, samples, seed, t0)

    scalar = _is_scalar(brdf)
    if deltas:
        blocks_or_dense = _add_deltas(blocks_or_dense, deltas, basis, iso)
    norm2 = info.pop("norm2")
    info["reciprocal"] = rec
    info["antisymmetric_part"] = _antisymmetric_part(blocks_or_dense, norm2)
    if iso:
        blocks = [b[..., 0] if scalar else np.moveaxis(b, -1, 0) for b in blocks_or_dense]
        cm = CoefficientMatrix.from_blocks(basis, blocks, quantity, reciprocal=rec)
    else:
        m = blocks_or_dense
        scale = float(np.max(np.abs(m))) or 1.0
        info["asymmetry"] = float(np.max(np.abs(m - m.swapaxes(0, 1)))) / scale
        m = m[..., 0] if scalar else np.moveaxis(m, -1, 0)
        cm = CoefficientMatrix(basis, m, quantity, symmetrize=rec, isotropic=False,
                               reciprocal=rec)
    trunc = None if deltas else truncation_error(cm, norm2)
    info.update(tail_fraction=tail_fraction(cm), truncation_error=trunc,
                seconds=time.perf_counter() - t0, source=repr(brdf), quantity=quantity)
    cm.info.update(info)
    if trunc is not None and trunc > GIBBS_ERROR:
        warnings.warn(f"the expansion of {brdf!r} in {basis!r} misses {100 * trunc:.3g} % of "
                      "its L2 norm: the BRDF is too sharp for the order (expect Gibbs ringing) "
                      "or ill suited to the basis (e.g. quantity='f' in odd harmonics); raise "
                      "the order, filter (compress.smooth) or change the basis or quantity",
                      RuntimeWarning, stacklevel=2)
    return cm


#: Copies of the coefficients alive at the peak of :func:`project`: the sum being built, its
#: transpose, the asymmetry check, the channel-first copy and CoefficientMatrix's symmetric
#: part and checks.
_RESULT_COPIES = 6


def _antisymmetric_part(blocks_or_dense: Any, norm2: NDArray) -> float:
    """||(M - M^T) / 2||_F / ||q||, max over channels (blocks m > 0 count twice)."""
    parts = blocks_or_dense if isinstance(blocks_or_dense, list) else [blocks_or_dense]
    mult = 1.0 if not isinstance(blocks_or_dense, list) else None
    a2 = np.zeros(np.shape(norm2))
    for m, b in enumerate(parts):  # (k, k, channels)
        d = 0.5 * (b - b.swapaxes(0, 1))
        a2 = a2 + (mult or (1.0 if m == 0 else 2.0)) * np.sum(d * d, axis=(0, 1))
    norm2 = np.asarray(norm2, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(norm2 > 0, np.sqrt(a2 / np.where(norm2 > 0, norm2, 1.0)), 0.0)
    return float(np.max(rel, initial=0.0))


def default_quantity(basis: Basis, brdf: Any = None) -> str:
    """Return the quantity to represent a BRDF by in ``basis`` when the user does not say.

    Parameters
    ----------
    basis : basis.Basis
    brdf : BRDF, optional
        Only its ``delta`` (mirror) terms matter.

    Returns
    -------
    {"f_cos", "f"}
        ``"f_cos"`` when the basis vanishes on the horizon (``basis.vanishes_on_horizon``:
        the odd hemisphere harmonics, whose q / (cos theta_i cos theta_o) has a finite limit
        there) or when the BRDF has mirror terms (they have no coefficients as ``"f"``);
        ``"f"`` otherwise.

    Notes
    -----
    A ``"f_cos"`` expansion in a basis that does not vanish on the horizon does not vanish
    there either, while the true q does; evaluating f = q / (cos theta_i cos theta_o) then
    amplifies the truncation error without bound near grazing angles. Measured on Phong
    (kd 0.3, ks 0.4, n 20) in HemiZernike(12), relative RMS error of f over 200,000 pairs
    uniform in solid angle on H x H: 84 as ``"f_cos"`` (max |f_hat| 5,000 times max f), 0.061
    as ``"f"`` (the L2 projection of f itself, whose error over H x H is exactly the Parseval
    truncation error). Raising ``min_cos`` of :meth:`basis.CoefficientMatrix.eval` does not
    rescue ``"f_cos"`` (0.2 to 1.0 for min_cos between 0.02 and 0.3). BRDFs whose f is not
    square integrable (Ward's original normalisation, f ~ 1 / sqrt(cos theta_i cos theta_o))
    converge slowly as ``"f"``; project them as ``"f_cos"`` into the odd harmonics.

    Examples
    --------
    >>> from basis import HemiHarmonics, HemiZernike
    >>> default_quantity(HemiZernike(8)), default_quantity(HemiHarmonics(8))
    ('f', 'f_cos')
    """
    if getattr(basis, "vanishes_on_horizon", False) or getattr(brdf, "delta", ()):
        return "f_cos"
    return "f"


def _check_brdf(brdf: Any) -> None:
    for attr in ("eval", "channels", "isotropic"):
        if not hasattr(brdf, attr):
            raise TypeError(f"brdf must have eval(wi, wo), channels and isotropic (see "
                            f"project.brdf.BRDF); {type(brdf).__name__} has no {attr!r}")


def _is_scalar(brdf: Any) -> bool:
    """Return True when brdf.eval returns (...) rather than (..., channels)."""
    v = np.asarray(brdf.eval(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0])))
    return v.ndim == 0


def _eval_pairs(brdf: Any, wi: NDArray, wo: NDArray, channels: int,
                evaluate: Any = None) -> NDArray[np.float64]:
    """Evaluate brdf (by ``evaluate``, default its ``eval``) at (n, 3) pairs, checked finite."""
    v = np.asarray((evaluate or brdf.eval)(wi, wo), dtype=np.float64).reshape(wi.shape[0],
                                                                             channels)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{brdf!r} returned non-finite values at {int(np.sum(~np.isfinite(v)))}"
                         " sample pairs; the model is not defined everywhere on the hemisphere")
    return v


# -- the radial factors -----------------------------------------------------------------------
def radial_table(basis: Basis, z: NDArray[np.float64]) -> NDArray[np.float64]:
    """P_k(z) for every basis function; the same as ``basis.radial(z)``.

    Kept for code written against scatmodes 0.1; see :meth:`basis.Basis.radial`.

    Parameters
    ----------
    basis : basis.Basis
    z : (n,) array of float
        cos(theta).

    Returns
    -------
    (n, size) ndarray
    """
    return basis.radial(z)


def _top(az: NDArray) -> int:
    """Highest azimuthal order present (blocks run over m = 0..top)."""
    return int(np.max(np.abs(az)))


def _gauss_z(n: int) -> tuple[NDArray, NDArray]:
    t, w = roots_legendre(n)
    return 0.5 * (t + 1.0), 0.5 * w


#: The rules in z = cos(theta): Gauss-Legendre in z, or in t = sqrt(z) (see _z_nodes).
ZMAPS = ("gauss", "sqrt")
#: Isotropic BRDFs also try the diagonal rule in (z_i, z_o) (see _diagonal_pairs).
ISO_ZMAPS = ("gauss", "sqrt", "diagonal")


def _z_nodes(n: int, zmap: str) -> tuple[NDArray, NDArray]:
    """Nodes and weights of an n-point rule for int_0^1 g(z) dz.

    ``"gauss"`` is Gauss-Legendre in z. ``"sqrt"`` is Gauss-Legendre in t = sqrt(z)
    (z = t^2, dz = 2 t dt): an integrand a(z) + b(z) / sqrt(z) with a, b smooth becomes
    2 t a(t^2) + 2 b(t^2), smooth in t, so the rule converges spectrally where plain Gauss
    converges like 1/n (the classical substitution for algebraic end-point singularities,
    P. J. Davis and P. Rabinowitz, Methods of Numerical Integration, 2nd ed., 1984,
    sec. 2.12). Ward's original lobe (Ward 1992, eq. 5a) carries 1/sqrt(cos theta_i
    cos theta_o) and is the case it is for; on a polynomial in z it needs twice the nodes.
    """
    t, w = _gauss_z(n)
    if zmap == "gauss":
        return t, w
    return t * t, 2.0 * t * w


# -- quadrature -------------------------------------------------------------------------------
def _quadrature(brdf, basis, quantity, iso, tol, nodes, max_nodes, max_evaluations):
    order = basis.order
    step = _aniso_rule
    if iso:  # folding z_i <= z_o needs reciprocity and mirror symmetry (see _iso_rule)
        brdf_rec, mirror = bool(getattr(brdf, "reciprocal", True)), _mirror_symmetric(brdf)
        fold = brdf_rec and mirror
        signs = 1 if brdf_rec or mirror else 2  # both signs of dphi sampled
        step = partial(_iso_rule, fold=fold, both_signs=signs == 2)
    if nodes is not None:
        nz, nphi = (nonneg_int(v, "nodes") for v in nodes)
        if nz < 1 or nphi < 2 * order + 2:
            raise ValueError(f"nodes must be (n_z >= 1, n_phi >= 2 * order + 2 = {2 * order + 2}"
                             f"), got {tuple(nodes)}")
        fine, ev1, norm2 = step(brdf, basis, quantity, nz, nphi + nphi % 2)
        coarse, ev0, _ = step(brdf, basis, quantity, max(1, nz // 2),
                              max(2 * order + 2, nphi // 2 + (nphi // 2) % 2))
        err, scale = _diff(fine, coarse)
        return fine, dict(method="quadrature", nodes=(nz, nphi), evaluations=ev0 + ev1,
                          error_estimate=err, rel_error=err / scale,
                          converged=err <= tol * scale, norm2=norm2)
    max_nodes = nonneg_int(max_nodes, "max_nodes")
    budget = nonneg_int(max_evaluations, "max_evaluations")
    if iso:
        return _iso_quadrature(brdf, basis, quantity, tol, max_nodes, budget, fold, signs == 2)

    def cost(nz: int, nphi: int) -> int:
        return nz * nz * max(4 * order + 2, nphi // 2) * (nphi + 2)

    # z and phi converge at different rates (a lobe near the pole needs few Gauss nodes, the
    # near-horizon corner wi ~ -wo many azimuths), so each is doubled on its own: the change
    # from doubling one with the other fixed estimates that one's error, and the one with the
    # larger estimate is doubled next. The estimate returned is the sum of the two.
    nz, nphi = max(order + 2, 4), 2 * order + 2
    evals = 0
    # Azimuth rule: a pilot as costly as the isotropic one (_iso_quadrature) would dominate
    # the run, so the uniform rule is kept only when it has converged from the first azimuth
    # rule to twice that on the first z rule (trigonometric polynomials, which it integrates
    # exactly); otherwise the graded rule is used (what makes Ward converge).
    grading = ANISO_GRADING
    if cost(nz, 2 * nphi) <= budget:
        a, ev_a, _ = step(brdf, basis, quantity, nz, nphi, 1)
        b, ev_b, _ = step(brdf, basis, quantity, nz, 2 * nphi, 1)
        evals += ev_a + ev_b
        if _diff(b, a)[0] <= tol * _diff(b, b)[1]:
            grading = 1
    err = {"z": np.inf, "phi": np.inf}
    zmap = "gauss"
    if 2 * nz > max_nodes or cost(2 * nz, nphi) > budget:
        step = partial(step, grading=grading)
        cur, ev, norm2 = step(brdf, basis, quantity, nz, nphi)
        evals += ev
    else:
        # The z rule: Gauss in z or in sqrt(z) (_z_nodes), whichever changes less from nz
        # to 2 nz nodes on the first azimuth rule; the finer result of the one kept goes on
        # with that change as its z error estimate. (From nz / 2 to nz the sqrt rule can
        # still be too coarse for a lobe and lose to Gauss even where it converges far
        # faster: Ward 0.2 x 0.4, order 12, changes 0.017 against 0.014 from 7 to 14 nodes,
        # 7e-5 against 6e-3 from 14 to 28.)
        trial = {}
        for zm in ZMAPS:
            a, ev_a, _ = step(brdf, basis, quantity, nz, nphi, grading, zm)
            b, ev_b, n2 = step(brdf, basis, quantity, 2 * nz, nphi, grading, zm)
            trial[zm], evals = (_diff(b, a)[0], b, n2), evals + ev_a + ev_b
        zmap = min(ZMAPS, key=lambda zm: trial[zm][0])
        err["z"], cur, norm2 = trial[zmap]
        nz *= 2
        step = partial(step, grading=grading, zmap=zmap)
    cap = {"z": max_nodes, "phi": 4 * max_nodes}
    while True:
        scale = _diff(cur, cur)[1]
        total = err["z"] + err["phi"]
        if total <= tol * scale:
            break
        nxt = {"z": (2 * nz, nphi), "phi": (nz, 2 * nphi)}
        dim = max((d for d in err if 2 * (nz if d == "z" else nphi) <= cap[d]
                   and cost(*nxt[d]) <= budget), key=lambda d: err[d], default=None)
        if dim is None:
            break
        nz, nphi = (2 * nz, nphi) if dim == "z" else (nz, 2 * nphi)
        new, ev, norm2 = step(brdf, basis, quantity, nz, nphi)
        evals += ev
        err[dim] = _diff(new, cur)[0]
        cur = new
    converged = _not_converged_warning(brdf, basis, tol, err, scale, (nz, nphi), max_nodes,
                                       budget, 3)
    err_total = sum(err.values())
    return cur, dict(method="quadrature", nodes=(nz, nphi), evaluations=evals,
                     error_estimate=err_total, rel_error=err_total / scale, converged=converged,
                     norm2=norm2, azimuth_rule="uniform" if grading == 1 else
                     f"graded (p = {grading})", z_rule=zmap)


def _not_converged_warning(brdf, basis, tol, err, scale, nodes, max_nodes, budget,
                           stacklevel) -> bool:
    """Return whether the estimates sum to tol or less; warn when they do not."""
    total = sum(err.values())
    if total <= tol * scale:
        return True
    parts = ", ".join(f"{d} {e / scale:.2g}" for d, e in err.items())
    warnings.warn(f"projection of {brdf!r} onto {basis!r} did not reach tol = {tol:.3g}: "
                  f"estimated relative error {total / scale:.3g} ({parts}) with {nodes[0]} x "
                  f"{nodes[1]} nodes (max_nodes = {max_nodes}, 4 x that in phi; "
                  f"max_evaluations = {budget:.3g}); the BRDF is sharper than the rule "
                  "resolves: raise the limits or accept the error", RuntimeWarning,
                  stacklevel=stacklevel + 1)
    return False


def _iso_quadrature(brdf, basis, quantity, tol, max_nodes, budget, fold, both_signs):
    """Refine the isotropic rule until the estimated error is below tol (see _quadrature).

    Each refinement doubles one dimension of the rule: the azimuths, or the z rule (for the
    diagonal rule its along-ridge nodes s or its across-ridge nodes d, on their own). The
    azimuth rules are nested (_IsoGrid), so doubling the azimuths evaluates only the new
    nodes, and every rule comes with the azimuth error estimate of its own z rule for free:
    the change from the rule with half its azimuths. The z estimates are the changes of the
    last doubling of each. The estimate returned is their sum.
    """
    order = basis.order
    grid = partial(_IsoGrid, brdf, basis, quantity, fold=fold, both_signs=both_signs)
    nz, nphi = max(order + 2, 4), 2 * order + 2
    pilot = 16 * (order + 1)
    evals = 0
    # Azimuth rule: a pilot on the coarse z rule keeps the uniform rule when it has already
    # converged between 16 (order + 1) and 32 (order + 1) azimuths (smooth or polynomial
    # BRDFs) or when the graded rule is not 10x better there (kinks away from dphi = 0, pi,
    # as in Oren-Nayar). The 32 (order + 1) rule contains the other: one sampling each.
    change = {}
    for g in (1, GRADING):
        run = grid(nz, grading=g)
        run.sample(2 * pilot)
        b, change[g], _ = run.result()
        evals += run.evaluations
        if g == 1 and change[1] <= tol * _diff(b, b)[1]:
            break
    grading = 1 if len(change) == 1 or change[GRADING] >= 0.1 * change[1] else GRADING
    grid = partial(grid, grading=grading)

    def cost(ns: int, nd: int, nphi: int) -> int:
        return _IsoGrid.pair_count(ns, zmap, fold, nd) * (nphi // 2 + 1) * (1 + both_signs)

    zmap = "gauss"
    if 2 * nz > max_nodes or cost(2 * nz, 2 * nz, nphi) > budget:
        err = {"z": np.inf}
    else:
        # The (z_i, z_o) rule: the tensor Gauss rule in z or in sqrt(z), or the diagonal
        # rule (_diagonal_pairs), whichever changes least from nz to 2 nz nodes on the
        # pilot's azimuths, 16 (order + 1). The tensor rules put a pair exactly on z_i = z_o
        # for every node and, for a specular ridge narrower than their spacing, sample its
        # crest with the weight of a whole cell: their change under doubling then shrinks
        # while the error does not (blue-acrylic MERL in HemiZernike(24): change 4.7e-3 at
        # 416 nodes, error 2.7e-2). The diagonal rule changes 10x less there from 26 to 52
        # nodes (0.018 against 0.14); smooth lobes (Phong n = 20, Cook-Torrance GGX 0.3)
        # change 1e-8 or less on the Gauss rule and keep it.
        trial = {}
        for zm in ISO_ZMAPS:
            a, b = grid(nz, zm), grid(2 * nz, zm)
            a.sample(pilot)
            b.sample(pilot)
            trial[zm] = _diff(b.result()[0], a.result()[0])[0]
            evals += a.evaluations + b.evaluations
        zmap = min(ISO_ZMAPS, key=trial.get)
        nz *= 2
        # The diagonal rule doubles its nodes along the ridge (s) and across it (d)
        # separately: they converge at different rates (blue-acrylic in HemiZernike(24),
        # error against a brute-force reference with (s, d) nodes (208, 104), (208, 208),
        # (416, 104), (416, 208): 2.2e-5, 1.9e-5, 1.7e-5, 4.6e-6).
        err = {"s": trial[zmap], "d": trial[zmap]} if zmap == "diagonal" else {"z": trial[zmap]}
    ns = nd = nz
    cur = grid(ns, zmap, nd=nd)
    cur.sample(nphi)
    evals += cur.evaluations
    blocks, _, norm2 = cur.result()
    err["phi"] = _phi_estimate(cur.changes)
    cap = {"z": max_nodes, "s": max_nodes, "d": max_nodes, "phi": 4 * max_nodes}
    # The diagonal rule may double s or d as a combination of rules (sparse grids, the
    # combination technique of Griebel, Schneider & Zenger 1992): after s went from S / 2 to
    # S at D nodes, M(S, 2D) ~ M(S, D) + M(S/2, 2D) - M(S/2, D), exact when the error is
    # a sum of an s part and a d part, and the new rule costs half of the (S, 2D) one (its
    # mirror for s after d). Its estimate for the doubled dimension is the size of the
    # correction, M(S/2, 2D) - M(S/2, D): the change that doubling it makes at S / 2, the
    # same conservative kind as the others. Blue-acrylic in HemiZernike(24), error against
    # a brute-force reference with 800 azimuths: M(416, 104) 1.7e-5, M(416, 208) 4.6e-6,
    # the combination 5.4e-6.
    seen = {(ns, nd): cur} if zmap == "diagonal" else {}
    terms = [(1.0, cur)]  # the result: sum of coefficient * rule
    while True:
        scale = _diff(blocks, blocks)[1]
        if sum(err.values()) <= tol * scale:
            break
        nxt = {"z": (2 * ns, 2 * nd, nphi), "s": (2 * ns, nd, nphi), "d": (ns, 2 * nd, nphi),
               "phi": (ns, nd, 2 * nphi)}
        combine = {"s": (ns, nd // 2), "d": (ns // 2, nd)}  # the rule one step back
        combine = {k: v for k, v in combine.items() if len(terms) == 1 and v in seen}
        size = {"z": 2 * ns, "s": 2 * ns, "d": 2 * nd, "phi": 2 * nphi}

        costs = {d: (sum(cost(*t.dims, 2 * nphi) for _, t in terms) if d == "phi"  # all double
                     else cost(*_combination_dims(d, ns, nd), nphi) if d in combine
                     else cost(*nxt[d])) for d in err}
        dim = max((d for d in err if size[d] <= cap[d] and costs[d] <= budget),
                  key=err.get, default=None)
        if dim is None:
            break
        if dim == "phi":
            for _, t in terms:
                before = t.evaluations
                t.refine()
                evals += t.evaluations - before
            nphi *= 2
        elif dim in combine:
            back = seen[combine[dim]]
            while 2 * back.half < nphi:  # the rule one step back, at these azimuths
                before = back.evaluations
                back.refine()
                evals += back.evaluations - before
            new = grid(*_combination_dims(dim, ns, nd)[:1], zmap,
                       nd=_combination_dims(dim, ns, nd)[1])
            new.sample(nphi)
            evals += new.evaluations
            terms = [(1.0, cur), (1.0, new), (-1.0, back)]
            ns, nd = nxt[dim][:2]
        else:
            ns, nd, nphi = nxt[dim]
            cur = grid(ns, zmap, nd=nd)
            cur.sample(nphi)
            evals += cur.evaluations
            terms = [(1.0, cur)]
            if zmap == "diagonal":
                seen = {k: v for k, v in seen.items() if k in ((ns // 2, nd), (ns, nd // 2))}
                for v in seen.values():
                    v.release()
                seen[(ns, nd)] = cur
        new_blocks, norm2, changes = _combine(terms)
        err["phi"] = _phi_estimate(changes)
        if dim in combine:  # the correction: the change doubling makes one step back
            err[dim] = _diff(terms[1][1].result()[0], terms[2][1].result()[0])[0]
        elif dim != "phi":
            err[dim] = _diff(new_blocks, blocks)[0]
        blocks = new_blocks
    converged = _not_converged_warning(brdf, basis, tol, err, scale, (ns, nphi), max_nodes,
                                       budget, 4)
    err_total = sum(err.values())
    info = dict(method="quadrature", nodes=(ns, nphi), evaluations=evals,
                error_estimate=err_total, rel_error=err_total / scale, converged=converged,
                norm2=norm2, azimuth_rule="uniform" if grading == 1 else
                f"graded (p = {grading})", z_rule=zmap)
    if zmap == "diagonal":
        info["diagonal_nodes"] = _IsoGrid.node_counts(ns, nd)
        if len(terms) > 1:
            info["combination"] = " ".join(
                f"{'+' if c > 0 else '-'} {'{} x {}'.format(*t.diagonal_nodes)}"
                for c, t in terms)[2:]
    return blocks, info


def _combination_dims(dim: str, ns: int, nd: int) -> tuple[int, int]:
    """(s, d) nodes of the new rule of a combination that doubles ``dim`` from (ns, nd)."""
    return (ns // 2, 2 * nd) if dim == "d" else (2 * ns, nd // 2)


def _combine(terms) -> tuple[list[NDArray], NDArray, tuple]:
    """Blocks, ||q||^2 and azimuth changes of sum coefficient * rule (each at its result())."""
    out = None
    for c, t in terms:
        b, _, n2 = t.result()
        d2, d1 = t.changes
        parts = (b, [n2], d2, d1)
        scaled = [None if x is None else [c * y for y in x] for x in parts]
        out = scaled if out is None else [
            None if x is None or y is None else [u + v for u, v in zip(x, y, strict=True)]
            for x, y in zip(out, scaled, strict=True)]
    return out[0], out[1][0], (out[2], out[3])


def _maxabs(blocks: list[NDArray] | None) -> float:
    """Return max |entry| over a list of blocks, inf for None (not available)."""
    if blocks is None:
        return np.inf
    return max(float(np.max(np.abs(b), initial=0.0)) for b in blocks)


def _phi_estimate(changes: tuple) -> float:
    """Azimuth error estimate of a rule from the blocks of its last two changes.

    The change c2 from the rule with half the azimuths bounds the error of that coarser
    rule; the finer one returned is better by the convergence factor. When the change
    before, c1 (from a quarter to a half), shows convergence at least like N^-2
    (c2 <= c1 / 4, the rate of the trapezoid rule on the kinks of trilinear tables, which
    smooth BRDFs exceed), the error of the finer rule is taken as c2 / 3, its bound for an
    error that keeps shrinking by 4 or more per doubling; otherwise c2.
    """
    c2, c1 = _maxabs(changes[0]), _maxabs(changes[1])
    return c2 / 3.0 if np.isfinite(c1) and c2 <= 0.25 * c1 else c2


def _diff(a, b) -> tuple[float, float]:
    if isinstance(a, list):
        err = max(float(np.max(np.abs(x - y), initial=0.0)) for x, y in zip(a, b, strict=True))
        scale = max(float(np.max(np.abs(x), initial=0.0)) for x in a)
    else:
        err, scale = float(np.max(np.abs(a - b))), float(np.max(np.abs(a)))
    return err, (scale if scale > 0 else 1.0)



def _azimuth_nodes(nphi: int, grading: int) -> tuple[NDArray, NDArray]:
    """Nodes and weights on [0, pi] for int_0^pi g(dphi) d dphi, nphi / 2 intervals.

    ``grading`` 1 is the trapezoid rule (spectrally accurate for smooth periodic g); p > 1
    is the trapezoid rule after the sigmoidal substitution dphi = pi t^p / (t^p + (1-t)^p),
    which crowds nodes towards dphi = 0 and pi. Half-vector lobes (Cook-Torrance, Ward,
    Blinn-Phong) sit at dphi = pi and narrow like cos(theta) near the horizon, where the
    uniform rule converges only algebraically; the graded rule resolves them.

    Both are trapezoid rules in t = k / (nphi / 2), so the rule with twice the intervals
    holds these nodes (bit for bit) at its even k: the rules are nested.
    """
    dphi, raw = _azimuth_raw(nphi // 2, grading)
    return dphi, raw / (nphi // 2)


def _azimuth_raw(half: int, grading: int, odd: bool = False) -> tuple[NDArray, NDArray]:
    """Nodes of the azimuth rule with ``half`` intervals and ``half`` times their weights.

    ``odd``: only the nodes at odd k, those that the rule with half the intervals lacks.
    """
    t = np.arange(half + 1) / half
    if odd:
        t = t[1::2]
    if grading == 1:
        u, du = t, np.ones_like(t)
    else:
        a, b = t**grading, (1.0 - t) ** grading
        u = a / (a + b)
        du = grading * (t * (1.0 - t)) ** (grading - 1) / (a + b) ** 2
    raw = np.pi * du
    if not odd:
        raw[[0, -1]] *= 0.5
    return np.pi * u, raw


#: Sigmoidal grading of the azimuth rule tried against the uniform one (see _azimuth_nodes).
GRADING = 6

#: Grading of the anisotropic dphi rule. Milder than GRADING: p = 6 leaves the middle of each
#: panel three times sparser than the uniform rule and needs twice the azimuths before it
#: converges. Ward 0.2 x 0.4 in HemiZernike(12) (28 sqrt-rule z nodes), max error relative
#: to max |M| with 52, 104, 208 azimuths: p = 6: 0.12, 1.4e-3, 3e-11; p = 4: 0.04, 1.5e-7,
#: 5e-9; p = 3: 1.3e-3, 6e-7, 1e-8 (alpha 0.05 x 0.1: p = 4 3e-6 and 5e-8 at 104 and 208).
ANISO_GRADING = 4


def _diagonal_pairs(n: int, grading: int,
                    nd: int | None = None) -> tuple[NDArray, NDArray, NDArray]:
    """Pairs (z_i, z_o) and weights of a rule for int int_{z_i >= z_o} g dz_i dz_o.

    In s = (z_i + z_o) / 2 and d = z_i - z_o (unit Jacobian) the triangle z_i >= z_o is
    0 <= d <= D(s) = 2 min(s, 1 - s): Gauss-Legendre in s on [0, 1/2] and [1/2, 1] (the
    kink of D), n / 2 nodes each, and in tau with d = D(s) tau^p, nd / 2 nodes (nd = n by
    default), which crowds them towards the diagonal d = 0 where the specular ridge of a
    sharp isotropic BRDF lies (its width in z_i - z_o is about 2 sin(theta) times its width
    in theta_h). n nd / 2 pairs, as many as the folded n x n tensor rule when nd = n.
    """
    k = max(1, n // 2)
    t, w = _gauss_z(k)
    s = np.concatenate([0.5 * t, 0.5 + 0.5 * t])
    ws = np.concatenate([0.5 * w, 0.5 * w])
    if nd is not None and max(1, nd // 2) != k:
        t, w = _gauss_z(max(1, nd // 2))
    big = 2.0 * np.minimum(s, 1.0 - s)  # D(s)
    d = big[:, None] * t[None, :] ** grading
    wd = big[:, None] * grading * t[None, :] ** (grading - 1) * w[None, :]
    zi = (s[:, None] + 0.5 * d).ravel()
    zo = (s[:, None] - 0.5 * d).ravel()
    return zi, zo, (ws[:, None] * wd).ravel()


#: Grading of the diagonal rule towards z_i = z_o (see _diagonal_pairs).
DIAGONAL_GRADING = 3


def _mirror_symmetric(brdf: Any) -> bool:
    """Return True when f(w_i, w_o) = f(S w_i, S w_o) for the mirror S: y -> -y.

    An isotropic BRDF with this (bilateral) symmetry is even in dphi. Analytic models have
    it; measured tables need not (the blue-acrylic MERL surrogate: f at dphi = 3.1 and
    -3.1, z_i = 0.3, z_o = 0.31, differs by 12 %). Checked on 1024 scrambled Sobol pairs to
    1e-10 relative to max |f| (rounding of the models is ~1e-15).
    """
    wi, wo = _sobol_pairs(1024, 12345)
    flip = np.array([1.0, -1.0, 1.0])
    ch = int(brdf.channels)
    a, b = _eval_pairs(brdf, wi, wo, ch), _eval_pairs(brdf, wi * flip, wo * flip, ch)
    return bool(np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(a)))


def _evaluator(brdf: Any):
    """Return a function (wi, wo) -> values for quadrature nodes, unit vectors with z >= 0.

    For a :class:`project.brdf.BRDF` that keeps the base class's ``eval`` that is ``_eval``
    itself: the nodes meet its contract (C-contiguous (n, 3) unit vectors in the upper
    hemisphere), so the checks, horizon masks and copies of ``eval`` would change nothing
    (a tenth of the time of a MERL table lookup).
    """
    from .brdf import BRDF

    if isinstance(brdf, BRDF) and type(brdf).eval is BRDF.eval:
        ch = int(brdf.channels)

        def evaluate(wi: NDArray, wo: NDArray) -> NDArray:
            v = np.asarray(brdf._eval(wi, wo), dtype=np.float64)
            if v.shape != (wi.shape[0], ch) or not v.flags.writeable:
                v = np.array(np.broadcast_to(v, (wi.shape[0], ch)))
            return v

        return evaluate
    return brdf.eval


class _IsoGrid:
    """An isotropic BRDF sampled on one (z_i, z_o) rule and a nested azimuth rule.

    ``sample(nphi)`` evaluates the rule with nphi / 2 azimuth intervals on [0, pi],
    ``refine()`` doubles them by evaluating the new nodes only (the rules are nested,
    _azimuth_nodes), and ``result()`` returns the blocks together with the change from the
    rule with half the azimuths, which costs no evaluation: per pair the sums
    sum_j r_j cos(m dphi_j) q_j (r_j = half w_j, the same number for a node in both rules)
    are kept for the current rule and for its even nodes.

    Only dphi in [0, pi] is sampled (w_o at azimuth -dphi), and F_m(z_i, z_o) =
    2 int_0^pi q cos(m dphi) holds for BRDFs even in dphi. ``fold`` (default: the BRDF is
    reciprocal) samples only z_i >= z_o and mirrors; that needs F_m symmetric in
    (z_i, z_o), i.e. reciprocal and even. Otherwise both triangles are sampled: the pair
    (z_o, z_i) at -dphi is (z_i, z_o) at +dphi by reciprocity and isotropy, so the
    symmetrised blocks (CoefficientMatrix.from_blocks) project the even part exactly. A
    BRDF that is neither reciprocal nor mirror symmetric gives no such relation:
    ``both_signs`` then samples w_o at +dphi as well and projects the even part
    (q(dphi) + q(-dphi)) / 2, so the general blocks are exact too; ||q||^2 then counts both
    signs (the odd part, which no isotropic block holds, included).

    ``zmap`` ``"gauss"`` or ``"sqrt"`` is a tensor rule in (z_i, z_o) (_z_nodes), nz nodes
    per direction; ``"diagonal"`` the rule of _diagonal_pairs with (nz, nd) nodes, whose
    pairs lie on no tensor grid, so each block is then a sum over pairs,
    c_m sum_p w_p F_m(p) P_j(z_i,p) P_k(z_o,p).
    """

    def __init__(self, brdf, basis, quantity, nz, zmap="gauss", grading=1, fold=None,
                 both_signs=False, nd=None):
        self.brdf, self.basis, self.quantity = brdf, basis, quantity
        self.zmap, self.grading, self.both_signs = zmap, grading, bool(both_signs)
        self.ch = int(brdf.channels)
        self.top = _top(basis.azimuthal)
        rec = bool(getattr(brdf, "reciprocal", True)) if fold is None else bool(fold)
        self.reciprocal = rec
        self._dims = (nz, nz if nd is None else nd)
        if zmap == "diagonal":
            self.diagonal_nodes = self.node_counts(nz, nd)
            zi, zo, pw = _diagonal_pairs(nz, DIAGONAL_GRADING, nd)
            self._base = zi.size
            self._kinds = np.bincount(basis.azimuthal[basis.azimuthal >= 0])
            if not rec:  # the triangle z_i < z_o too, by swapping
                zi, zo, pw = np.concatenate([zi, zo]), np.concatenate([zo, zi]), np.tile(pw, 2)
        else:
            self.z, self.wz = _z_nodes(nz, zmap)
            self.ia, self.ib = (np.triu_indices(nz) if rec
                                else np.indices((nz, nz)).reshape(2, -1))
            zi, zo = self.z[self.ia], self.z[self.ib]
            pw = self.wz[self.ia] * self.wz[self.ib]
        self.zi, self.zo, self.pw = zi, zo, pw
        # ||q||^2 = sum_p w_p 2 pi int_0^{2 pi} q^2, pairs off the diagonal twice when folded
        self.norm_weight = pw * (np.where(zi == zo, 1.0, 2.0) if rec else 1.0)
        self.half = 0  # azimuth intervals sampled so far
        self.evaluations = 0
        # sums of the rule and of those with a half and a quarter of its azimuths,
        # (pairs, channels, top + 1)
        self._sums = self._prev = self._prev2 = None
        self.changes = (None, None)  # set by result()
        self._result = None  # (azimuth intervals, what result() returned for them)
        self._tables = None  # radial tables of the diagonal rule's pairs, when they fit
        self._sq = np.zeros(self.ch)
        self._eval = _evaluator(brdf)
        # a BRDF that reads and sums the rule in one pass (MERLBRDF: no direction or value
        # arrays, 2.5x faster)
        self._fused = getattr(brdf, "_isotropic_sums", None)

    @property
    def dims(self) -> tuple[int, int]:
        """(s, d) nodes the rule was built with (for the evaluation budget)."""
        return self._dims

    @staticmethod
    def node_counts(nz: int, nd: int | None = None) -> tuple[int, int]:
        """Nodes of the diagonal rule along the ridge (s) and across it (d, per side)."""
        return 2 * max(1, nz // 2), max(1, (nz if nd is None else nd) // 2)

    def release(self) -> None:
        """Drop the radial tables kept for the next result() (recomputed when needed)."""
        self._tables = None

    @staticmethod
    def pair_count(nz: int, zmap: str, fold: bool, nd: int | None = None) -> int:
        """(z_i, z_o) pairs sampled by the rule (for the evaluation budget)."""
        if zmap == "diagonal":
            n = 2 * max(1, nz // 2) * max(1, (nz if nd is None else nd) // 2)
            return n if fold else 2 * n
        return nz * (nz + 1) // 2 if fold else nz * nz

    def sample(self, nphi: int) -> None:
        """Evaluate the rule with nphi / 2 azimuth intervals (nothing sampled before)."""
        half = nphi // 2
        # the rules with a half and a quarter of the intervals first (their nodes are all
        # in this one): each result() then has the last two changes for free
        k = 0
        while k < 2 and half % (2 << k) == 0:
            k += 1
        self._sums, self._sq = self._sample(*_azimuth_raw(half >> k, self.grading))
        self.half = half >> k
        for _ in range(k):
            self.refine()

    def refine(self) -> None:
        """Double the azimuth intervals, evaluating the BRDF at the new nodes only."""
        dphi, raw = _azimuth_raw(2 * self.half, self.grading, odd=True)
        sums, sq = self._sample(dphi, raw)
        self._prev2, self._prev = self._prev, self._sums
        self._sums = self._sums + sums
        self._sq = self._sq + sq
        self.half *= 2

    def result(self) -> tuple[list[NDArray], float, NDArray]:
        """Blocks, max |change| from half the azimuths (inf when odd) and ||q||^2.

        Also sets ``changes``: the blocks of the changes from a half to all the azimuths and
        from a quarter to a half (None where not sampled), for :func:`_phi_estimate` and for
        combinations of rules.
        """
        h, c = self.half, self.ch
        if self._result is not None and self._result[0] == h:
            return self._result[1]
        f = [self._sums * (2.0 / h)]  # F_m, (pairs, channels, m)
        d1 = None
        if self._prev is not None:
            f.append(f[0] - self._prev * (4.0 / h))
            if self._result is not None and self._result[0] == h // 2:
                d1 = self.changes[0]  # what the last result() found, before refine()
            elif self._prev2 is not None:
                f.append(self._prev * (4.0 / h) - self._prev2 * (8.0 / h))
        both = self._blocks(np.concatenate(f, axis=1))  # one product per m for all
        parts = [[b[..., i * c:(i + 1) * c] for b in both] for i in range(len(f))]
        parts += [None] * (3 - len(parts))
        self.changes = (parts[1], parts[2] if d1 is None else d1)
        self._result = (h, (parts[0], _maxabs(parts[1]), 4.0 * np.pi * self._sq / h))
        return self._result[1]

    def _sample(self, dphi: NDArray, raw: NDArray) -> tuple[NDArray, NDArray]:
        """Sum raw q cos(m dphi) per pair and raw q^2 over the given azimuths."""
        ch, nj, npairs = self.ch, dphi.size, self.zi.size
        check_bytes(8.0 * min(npairs, CHUNK) * nj * (ch + 6) + 16.0 * npairs * ch * self.top,
                    f"sampling {self.brdf!r} on {npairs} x {nj} nodes")
        cosr = raw[:, None] * np.cos(np.outer(dphi, np.arange(self.top + 1)))  # (nj, m)
        cd, sd = np.cos(dphi), np.sin(dphi)
        sti = np.sqrt((1.0 - self.zi) * (1.0 + self.zi))
        sto = np.sqrt((1.0 - self.zo) * (1.0 + self.zo))
        sums = np.empty((npairs, ch, self.top + 1))
        sq = np.zeros(ch)
        if self._fused is not None and not self.both_signs:
            zz = self.zi * self.zo if self.quantity == "f_cos" else np.ones(npairs)
            sqp = np.empty((npairs, ch))
            if self._fused(sti, self.zi, sto, self.zo, cd, sd, zz, cosr, raw, sums, sqp):
                _check_sums(self.brdf, sums)
                self.evaluations += npairs * nj
                return sums, self.norm_weight @ sqp
        rows = max(1, CHUNK // nj)
        for s in range(0, npairs, rows):
            sl = slice(s, s + rows)
            n = self.zi[sl].size
            wi, wo = _iso_directions(sti[sl], self.zi[sl], sto[sl], self.zo[sl], cd, sd)
            q = self._values(wi, wo).reshape(n, nj, ch)
            zz = (self.zi[sl] * self.zo[sl] if self.quantity == "f_cos" else np.ones(n))
            if self.both_signs:  # the even part (q(dphi) + q(-dphi)) / 2; ||q||^2 of both
                wo[:, 1] *= -1.0
                q2 = self._values(wi, wo).reshape(n, nj, ch)
                qq = 0.5 * (q * q + q2 * q2) * (zz * zz)[:, None, None]
                q = 0.5 * (q + q2)
                del q2
            sqp = np.empty((n, ch))
            _azimuth_sums(np.ascontiguousarray(q), zz, cosr, raw, sums[sl], sqp)
            if self.both_signs:
                sqp = np.tensordot(qq, raw, axes=([1], [0]))
            sq += self.norm_weight[sl] @ sqp
        self.evaluations += npairs * nj * (1 + self.both_signs)
        return sums, sq

    def _values(self, wi: NDArray, wo: NDArray) -> NDArray:
        return _eval_pairs(self.brdf, wi, wo, self.ch, self._eval)

    def _blocks(self, f: NDArray) -> list[NDArray]:
        """Blocks [(k_m, k_m, c)] from F_m at the pairs, f (pairs, c, top + 1)."""
        basis, az, c = self.basis, self.basis.azimuthal, f.shape[1]
        if self.zmap == "diagonal":
            return self._diagonal_blocks(f)
        nz = self.z.size
        full = np.empty((nz, nz, self.top + 1, c))
        full[self.ia, self.ib] = f.transpose(0, 2, 1)
        if self.reciprocal:
            full[self.ib, self.ia] = f.transpose(0, 2, 1)
        p = basis.radial(self.z) * self.wz[:, None]
        blocks = []
        for m in range(self.top + 1):
            pm = p[:, az == m]
            cm = 2.0 * np.pi if m == 0 else np.pi
            blocks.append(cm * np.einsum("aj,abc,bk->jkc", pm, full[:, :, m], pm,
                                         optimize=True))
        return blocks

    def _diagonal_blocks(self, f: NDArray) -> list[NDArray]:
        """Blocks of the diagonal rule: c_m sum_p w_p F_m(p) P_m(z_i,p) P_m(z_o,p)^T.

        Unfolded, the second half of the pairs is the first swapped (z_o, z_i), so its sum
        is the transpose of the same sum over the first half with its own F_m: one set of
        radial tables serves both, each channel set in one matrix product per m.
        """
        c, n = f.shape[1], self._base
        ft = np.moveaxis(f, 2, 0)  # (m, pairs, channels): one pass, then contiguous rows
        # unfolded: F at (z_i, z_o), then at (z_o, z_i), as 2 c channels of the first half
        ft = (np.ascontiguousarray(ft) if self.reciprocal
              else np.concatenate([ft[:, :n], ft[:, n:]], axis=2))
        cc = ft.shape[2]
        blocks = [np.zeros((k, cc, k)) for k in self._kinds]
        # products with k_m <= order / 2 + 1 rows: threaded BLAS only adds overhead (20x the
        # time on two busy cores); the (pairs, k, channels) operands are formed a few
        # thousand pairs at a time, so they stay in cache
        sub = 2048
        with threadpool_limits(1, user_api="blas"):
            for sl, tables in self._diagonal_tables():
                w = self.pw[sl, None]
                for m, (a, b) in enumerate(tables):
                    wf = ft[m, sl] * ((2.0 * np.pi if m == 0 else np.pi) * w)
                    k = a.shape[1]
                    acc = blocks[m].reshape(k * cc, k)  # a view: += accumulates in place
                    for s0 in range(0, wf.shape[0], sub):
                        x = a[s0:s0 + sub, :, None] * wf[s0:s0 + sub, None, :]
                        acc += x.reshape(-1, k * cc).T @ b[s0:s0 + sub]
        blocks = [b.transpose(0, 2, 1) for b in blocks]  # (k, k, channels)
        if self.reciprocal:
            return [b + b.swapaxes(0, 1) for b in blocks]
        return [b[..., :c] + b[..., c:].swapaxes(0, 1) for b in blocks]

    def _diagonal_tables(self):
        """Yield (slice, [(P_m(z_i), P_m(z_o)) for each m]) over chunks of the base pairs.

        Kept for the next call when all fit in TABLE_BYTES (the refinement asks for the
        blocks of the same pairs after every doubling of the azimuths).
        """
        if self._tables is not None:
            yield from self._tables
            return
        az = self.basis.azimuthal
        cols = [np.flatnonzero(az == m) for m in range(self.top + 1)]
        keep = 16.0 * self._base * sum(x.size for x in cols) <= TABLE_BYTES
        kept = []
        for s0 in range(0, self._base, CHUNK // 64):
            sl = slice(s0, min(s0 + CHUNK // 64, self._base))
            ri, ro = self.basis.radial(self.zi[sl]), self.basis.radial(self.zo[sl])
            tables = [(np.ascontiguousarray(ri[:, x]), np.ascontiguousarray(ro[:, x]))
                      for x in cols]
            if keep:
                kept.append((sl, tables))
            yield sl, tables
        if keep:
            self._tables = kept


def _check_sums(brdf: Any, sums: NDArray) -> None:
    """Refuse non-finite azimuthal sums (a non-finite value at some sample pair)."""
    if not np.all(np.isfinite(sums)):
        raise ValueError(f"{brdf!r} returned non-finite values at some sample pairs; the model "
                         "is not defined everywhere on the hemisphere")


#: Bytes of radial tables an isotropic diagonal rule keeps between refinements.
TABLE_BYTES = 1 << 28


def _azimuth_sums(q, scale, cosr, raw, sums, sq) -> None:
    """sums[p, c, m] = sum_j cosr[j, m] q[p, j, c] scale[p], sq[p, c] = sum_j raw_j (q s)^2.

    q (n, nj, c) values at pair p, azimuth j; scale (n,) factor of pair p (cos cos for f_cos);
    cosr (nj, m) = raw_j cos(m dphi_j). Pairs are summed on threads, each in the same order.
    """
    n, nj, nc = q.shape
    # a part of at least ~1e5 multiply-adds (~0.1 ms) outweighs the hand-off to a thread
    grain = max(1, (1 << 17) // max(nj * nc * cosr.shape[1], 1))
    run_parallel(_azimuth_sums_kernel, n, q, scale, cosr, raw, sums, sq, grain=grain)


@loopjit
def _azimuth_sums_kernel(first, stop, q, scale, cosr, raw, sums, sq):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel); arguments as _azimuth_sums.
    _, nj, nc = q.shape
    nm = cosr.shape[1]
    # an unsigned index: no negative-index test on a[p] (basis.jit.loopjit)
    for p in range(np.uint64(first), np.uint64(stop)):
        acc = np.zeros(nm)
        for c in range(nc):
            acc[:] = 0.0
            s2 = 0.0
            for j in range(nj):
                v = q[p, j, c] * scale[p]
                s2 += raw[j] * v * v
                for m in range(nm):
                    acc[m] += cosr[j, m] * v
            for m in range(nm):
                sums[p, c, m] = acc[m]
            sq[p, c] = s2


@loopjit
def _iso_directions_kernel(first, stop, sti, zi, sto, zo, cd, sd, wi,
                           wo):  # pragma: no cover - compiled
    # Pairs first .. stop - 1 (run_parallel). Pair p, azimuth j -> row p * nj + j:
    # w_i = (sin theta_i, 0, z_i) at azimuth 0 and w_o at azimuth -dphi_j
    # unsigned p and j (k = p * nj + j as well): no negative-index tests (basis.jit.loopjit)
    nj = np.uint64(cd.size)
    for p in range(np.uint64(first), np.uint64(stop)):
        # read once: numba cannot tell that the stores to wi, wo miss these arrays
        a, b, c, e = sti[p], zi[p], sto[p], zo[p]
        for j in range(nj):
            k = p * nj + j
            wi[k, 0] = a
            wi[k, 1] = 0.0
            wi[k, 2] = b
            wo[k, 0] = c * cd[j]
            wo[k, 1] = -c * sd[j]
            wo[k, 2] = e


def _iso_directions(sti, zi, sto, zo, cd, sd) -> tuple[NDArray, NDArray]:
    """(pairs * azimuths, 3) incident and outgoing directions of the isotropic rule."""
    n = sti.size * cd.size
    wi, wo = np.empty((n, 3)), np.empty((n, 3))
    # ~0.1 ms of stores per part
    run_parallel(_iso_directions_kernel, sti.size, sti, zi, sto, zo, cd, sd, wi, wo,
                 grain=max(1, 8192 // max(cd.size, 1)))
    return wi, wo


def _iso_rule(brdf, basis, quantity, nz, nphi, grading=1, zmap="gauss", fold=None,
              both_signs=False, nd=None):
    """Isotropic blocks [(k_m, k_m, channels)], evaluations and ||q||^2 of one rule.

    nz z nodes (and nd across the diagonal for ``zmap="diagonal"``) and nphi azimuths: see
    :class:`_IsoGrid`.
    """
    grid = _IsoGrid(brdf, basis, quantity, nz, zmap, grading, fold, both_signs, nd)
    grid.sample(nphi)
    blocks, _, norm2 = grid.result()
    return blocks, grid.evaluations, norm2


def _aniso_rule(brdf, basis, quantity, nz, nphi, grading=1, zmap="gauss", nfi=None):
    """Dense (size, size, channels) matrix from the 4-D rule in (z_i, phi_i, z_o, dphi).

    The outgoing azimuth is phi_o = phi_i - dphi, so half-vector lobes sit at dphi = pi
    whatever phi_i is, and the dphi rule can be graded there as in the isotropic case
    (two sigmoidal panels [0, pi], [pi, 2 pi]). phi_i takes the uniform rule. With
    Q(k, dphi) = int q e^{-i k phi_i} dphi_i (an FFT, |k| <= 2 order) and
    R(k, b) = int Q(k, dphi) e^{-i b dphi} d dphi, writing each A(phi) as two exponentials
    gives int int q A_mu(phi_i) A_nu(phi_i - dphi) = sum alpha alpha' R(-(s m + t n), t n).

    For a reciprocal BRDF only the pairs z_i <= z_o are sampled: the block of a pair
    (z_b, z_a) is the transpose of that of (z_a, z_b), because swapping the two directions
    of every term of the integral maps one onto the other. The result is S + S^T with S the
    sum over z_a < z_b and half the diagonal, exactly symmetric.
    """
    z, wz = _z_nodes(nz, zmap)
    ch = int(brdf.channels)
    order = basis.order
    nfi = max(4 * order + 2, nphi // 2) if nfi is None else nfi
    nfi += nfi % 2
    phi = 2.0 * np.pi * np.arange(nfi) / nfi
    u, w = _azimuth_nodes(nphi, grading)
    dphi = np.concatenate([u, 2.0 * np.pi - u])
    wd = np.concatenate([w, w])
    nd = dphi.size
    st = np.sqrt((1.0 - z) * (1.0 + z))
    sidx = basis.azimuthal + order  # signed azimuthal -> 0..2 order
    wp = basis.radial(z) * wz[:, None]  # (nz, size)
    coef, kidx, bidx = _exponential_pairs(order)
    eb = np.exp(-1j * np.outer(dphi, np.arange(-order, order + 1))) * wd[:, None]  # (nd, 2N+1)
    keep = np.arange(-2 * order, 2 * order + 1) % nfi
    reciprocal = bool(getattr(brdf, "reciprocal", True))
    ia, ib = np.triu_indices(nz) if reciprocal else np.indices((nz, nz)).reshape(2, -1)
    # a pair on the diagonal stands for itself only in S + S^T: half its weight
    half = np.where(ia == ib, 0.5, 1.0) if reciprocal else np.ones(ia.size)
    mat = np.zeros((basis.size, basis.size, ch))
    norm2 = np.zeros(ch)
    per = nfi * nd
    check_bytes(8.0 * per * min(ia.size, max(1, CHUNK // per)) * (ch + 6),
                f"sampling {brdf!r} on the 4-D rule")
    cpi, spi = np.cos(phi), np.sin(phi)
    po = phi[:, None] - dphi[None, :]  # (nfi, nd)
    cpo, spo = np.cos(po), np.sin(po)
    rows = max(1, CHUNK // per)
    for s0 in range(0, ia.size, rows):
        a, b = ia[s0:s0 + rows], ib[s0:s0 + rows]
        n = a.size
        wi = np.empty((n, nfi, nd, 3))
        wi[..., 0] = (st[a, None] * cpi)[:, :, None]
        wi[..., 1] = (st[a, None] * spi)[:, :, None]
        wi[..., 2] = z[a, None, None]
        wo = np.empty_like(wi)
        wo[..., 0] = st[b, None, None] * cpo
        wo[..., 1] = st[b, None, None] * spo
        wo[..., 2] = z[b, None, None]
        q = _eval_pairs(brdf, wi.reshape(-1, 3), wo.reshape(-1, 3), ch).reshape(n, nfi, nd, ch)
        del wi, wo
        if quantity == "f_cos":
            q *= (z[a] * z[b])[:, None, None, None]
        h = half[s0:s0 + rows]
        # ||q||^2: a sampled pair counts for itself and, folded, for its mirror (2 h)
        pw = wz[a] * wz[b] * (2.0 * h if reciprocal else 1.0)
        norm2 += (2.0 * np.pi / nfi) * np.einsum("p,d,psdc->c", pw, wd, q * q)
        fq = np.fft.fft(q, axis=1)[:, keep] * (2.0 * np.pi / nfi)  # Q(k, dphi): (p, 4N+1, nd, ch)
        r = np.einsum("pkdc,dt->pktc", fq, eb, optimize=True)  # (p, 4N+1, 2N+1, ch)
        t = np.real(np.einsum("pxyec,xye->pxyc", r[:, kidx, bidx], coef))
        # t: (p, 2N+1, 2N+1, ch) over signed (mu, nu); contract z_i and z_o
        tg = t[:, sidx][:, :, sidx] * h[:, None, None, None]
        mat += np.einsum("pj,pk,pjkc->jkc", wp[a], wp[b], tg, optimize=True)
    if reciprocal:
        mat += mat.swapaxes(0, 1).copy()
    return mat, ia.size * per, norm2


def _exponential_pairs(order: int) -> tuple[NDArray, NDArray, NDArray]:
    """Expand the products A_mu(x) A_nu(x - d) of azimuthal factors in exponentials.

    Returns the coefficients and (k, b) positions of A_mu(x) A_nu(x - d) =
    sum alpha e^{i(s m x + t n (x - d))}, for signed mu, nu in -order..order: arrays of shape
    (2N+1, 2N+1, 4).
    """
    sig = np.arange(-order, order + 1)
    m = np.abs(sig)
    # alpha(s) for s = +1, -1: cos -> 1/2, 1/2; sin -> 1/(2i), -1/(2i); constant -> 1, 0
    alpha = np.where(sig[:, None] > 0, np.array([0.5, 0.5], dtype=complex),
                     np.where(sig[:, None] < 0, np.array([-0.5j, 0.5j]),
                              np.array([1.0, 0.0], dtype=complex)))
    signs = np.array([1, -1])
    coef = np.empty((sig.size, sig.size, 4), dtype=complex)
    kidx = np.empty((sig.size, sig.size, 4), dtype=np.int64)
    bidx = np.empty((sig.size, sig.size, 4), dtype=np.int64)
    for c, (i, j) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        sm, tn = signs[i] * m[:, None], signs[j] * m[None, :]
        coef[:, :, c] = alpha[:, i][:, None] * alpha[:, j][None, :]
        kidx[:, :, c] = -(sm + tn) + 2 * order
        bidx[:, :, c] = np.broadcast_to(tn, (sig.size, sig.size)) + order
    return coef, kidx, bidx


# -- mirror terms -----------------------------------------------------------------------------
def _add_deltas(blocks_or_dense, deltas, basis, iso):
    """Add int_H R(z) b_j(w) b_k(mirror w) z dw for each MirrorDelta (isotropic blocks).

    b_k(mirror w) = (-1)^m b_k(w) since mirror turns phi into phi + pi; the azimuthal
    integral of A_j A_k is pi (m > 0) or 2 pi (m = 0) when they match, 0 otherwise. With a
    constant R the integrand is a polynomial in z for HemiZernike (exact with
    order/2 + 2 nodes); for HemiHarmonics or an angle-dependent R the rule is refined by
    doubling to rounding level.
    """
    order = basis.order
    az = basis.azimuthal
    out = blocks_or_dense
    for d in deltas:
        n, prev = order + 4, None
        while True:
            z, wz = _gauss_z(n)
            r = d.reflectance(z)  # (n, channels)
            p = basis.radial(z)
            blocks = []
            for m in range(_top(az) + 1):
                pm = p[:, az == m]
                c = (2.0 * np.pi if m == 0 else np.pi) * (-1.0) ** m
                blocks.append(c * np.einsum("aj,ac,ak->jkc", pm, (wz * z)[:, None] * r, pm))
            if prev is not None and _diff(blocks, prev)[0] <= 1e-14 * _diff(blocks, prev)[1]:
                break
            if n > 4096:
                warnings.warn(f"the mirror term {d!r} converged only to "
                              f"{_diff(blocks, prev)[0]:.3g}", RuntimeWarning, stacklevel=3)
                break
            prev, n = blocks, 2 * n
        if iso:
            out = [o + b for o, b in zip(out, blocks, strict=True)]
        else:
            dense = np.zeros_like(out)
            for m, b in enumerate(blocks):
                for sign in ((1, -1) if m else (1,)):
                    idx = np.flatnonzero(az == sign * m)
                    dense[idx[:, None], idx] = b
            out = out + dense
    return out


# -- Monte Carlo and least squares ------------------------------------------------------------
def _sobol_pairs(n: int, seed: int) -> tuple[NDArray, NDArray]:
    """Draw 2^ceil(log2 n) direction pairs, uniform in solid angle on H x H.

    The pairs come from a scrambled Sobol sequence (a power of two keeps the balance
    properties of the points).
    """
    from scipy.stats import qmc

    u = qmc.Sobol(d=4, scramble=True, seed=seed).random_base2(max(1, int(n - 1).bit_length()))
    return _uniform_hemisphere(u[:, 0], u[:, 1]), _uniform_hemisphere(u[:, 2], u[:, 3])


def _uniform_hemisphere(u: NDArray, v: NDArray) -> NDArray:
    z = u
    s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = 2.0 * np.pi * v
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)


def _montecarlo(brdf, basis, quantity, iso, samples, seed, rec=True):
    n = 1 << 16 if samples is None else nonneg_int(samples, "samples")
    if n < 2:
        raise ValueError(f"samples must be >= 2 for method='montecarlo', got {n}")
    ch = int(brdf.channels)
    reps = 8
    ests = []
    for r in range(reps):
        wi, wo = _sobol_pairs(n, np.random.SeedSequence([seed, r]).generate_state(1)[0])
        n = wi.shape[0]
        acc = np.zeros((basis.size, basis.size, ch))
        sq = np.zeros(ch)
        for s in range(0, n, CHUNK // 8):
            a, b = wi[s:s + CHUNK // 8], wo[s:s + CHUNK // 8]
            q = _eval_pairs(brdf, a, b, ch)
            if quantity == "f_cos":
                q = q * (a[:, 2] * b[:, 2])[:, None]
            bi, bo = basis.eval(a), basis.eval(b)
            acc += np.einsum("nj,nc,nk->jkc", bi, q, bo, optimize=True)
            sq += np.sum(q * q, axis=0)
        norm2 = sq * (2.0 * np.pi) ** 2 / n
        est = acc * (2.0 * np.pi) ** 2 / n
        ests.append(0.5 * (est + est.swapaxes(0, 1)) if rec else est)
    ests = np.array(ests)
    mean = ests.mean(axis=0)
    stderr = ests.std(axis=0, ddof=1) / np.sqrt(reps)
    scale = float(np.max(np.abs(mean))) or 1.0
    info = dict(method="montecarlo", samples=n * reps, evaluations=n * reps,
                error_estimate=float(np.max(stderr)), rel_error=float(np.max(stderr)) / scale,
                converged=True, standard_error=stderr, norm2=norm2)
    if iso:
        iso_cm = CoefficientMatrix(basis, np.moveaxis(mean, -1, 0), isotropic=False,
                                   reciprocal=rec).to_isotropic()
        return [np.moveaxis(b, 0, -1) for b in iso_cm.stored], info
    return mean, info


def _lstsq(brdf, basis, quantity, iso, rec, samples, seed, t0):
    from .lstsq import fit, unknowns

    n = (2 * unknowns(basis, iso, reciprocal=rec).count if samples is None
         else nonneg_int(samples, "samples"))
    wi, wo = _sobol_pairs(n, seed)
    n = wi.shape[0]
    v = _eval_pairs(brdf, wi, wo, int(brdf.channels))
    values = v[:, 0] if _is_scalar(brdf) else v
    cm = fit(wi, wo, values, basis, quantity=quantity, isotropic=iso, reciprocal=rec)
    cm.info.update(seconds=time.perf_counter() - t0, source=repr(brdf), samples=n)
    return cm


# -- diagnostics ------------------------------------------------------------------------------
def truncation_error(cm: CoefficientMatrix, norm2: NDArray[np.float64]) -> float:
    """Relative L2 error ||q - q_N|| / ||q|| of the truncated expansion, max over channels.

    By Parseval ||q - q_N||^2 = ||q||^2 - ||M||_F^2 for an orthonormal basis, with ||q||^2
    from the same quadrature as M. The subtraction limits the resolution to about
    sqrt(rounding of ||q||^2) ~ 1e-8.
    """
    m = cm.matrix.reshape(-1, cm.basis.size, cm.basis.size)
    mf = np.sum(m * m, axis=(1, 2))
    norm2 = np.asarray(norm2, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(norm2 > 0, np.maximum(0.0, 1.0 - mf / norm2), 0.0)
    return float(np.sqrt(np.max(rel)))


def tail_fraction(cm: CoefficientMatrix) -> float:
    """Relative RMS of the coefficients with either degree >= order - 1.

    A converged expansion has a small tail; a large one means the truncation rings.
    """
    if cm.order < 2:
        return 0.0
    m = cm.matrix.reshape(-1, cm.basis.size, cm.basis.size)
    deg = cm.basis.degree
    tail = (deg[:, None] >= cm.order - 1) | (deg[None, :] >= cm.order - 1)
    total = float(np.sum(m * m))
    return float(np.sqrt(np.sum(m[:, tail] ** 2) / total)) if total > 0 else 0.0
