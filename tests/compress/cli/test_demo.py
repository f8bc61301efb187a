"""compress.cli.demo: the numbers ``scatmodes demo`` prints, against exact quadrature facts."""

from __future__ import annotations

import numpy as np
import pytest

import basis
from compress.cli.demo import (
    modes_orthonormality_error,
    orthonormality_error,
    resolution_deg,
    to_markdown,
)


@pytest.mark.parametrize("b", [basis.HemiZernike(8), basis.HemiHarmonics(8),
                               basis.SphericalHarmonics(8)], ids=repr)
def test_orthonormality_error_is_rounding(b):
    # exact rules: the Gram matrix is I up to rounding (sums of ~100 O(1) products)
    assert orthonormality_error(b) < 1e-13


def test_orthonormality_error_sees_a_wrong_basis():
    # negative control: functions scaled by 1/2 have the Gram matrix I / 4
    class Halved(basis.HemiZernike):
        def _eval_flat(self, dirs, out):
            super()._eval_flat(dirs, out)
            out *= 0.5

    assert orthonormality_error(Halved(2)) == pytest.approx(0.75)


def test_modes_orthonormality_error_is_rounding():
    assert modes_orthonormality_error(basis.HelmholtzModes(4)) < 1e-13


def test_resolution_and_markdown():
    assert resolution_deg(8) == 22.5 and resolution_deg(0) == np.inf
    md = to_markdown([{"basis": "Z(2)", "error": 1.5e-16, "ns per value": 3.25,
                       "gap": float("nan")}])
    assert md.splitlines() == ["| basis | error | ns per value | gap |", "|---|---|---|---|",
                               "| Z(2) | 1.50e-16 | 3.2 | - |"]


def test_basis_table_rows_in_order_and_waits_before_zernike():
    from compress.cli.demo import basis_table

    calls = []

    def wait(kind):  # records which rows exist when the table waits
        calls.append((kind, len(seen)))

    seen = []
    orig = basis.HemiZernike.eval

    def spy(self, *a, **k):
        seen.append(self.order)
        return orig(self, *a, **k)

    basis.HemiZernike.eval = spy
    try:
        rows = basis_table(orders=(2, 4), points=50, wait=wait)
    finally:
        basis.HemiZernike.eval = orig
    assert calls == [("zernike", 0)]  # once, before any Zernike evaluation
    names = [r["basis"].split("(")[0] for r in rows[:6]]
    assert names == ["SphericalHarmonics", "HemiHarmonics", "HemiZernike"] * 2
    assert [r["order"] for r in rows[:6]] == [2, 2, 2, 4, 4, 4]


# -- the model study's tolerance and the compilation in a second process -----------------
def test_study_tol_changes_no_printed_digit():
    # reference: the same study at project's default tolerance for models, 1e-6; the demo
    # prints l2 with three significant digits, and 1e-4 moves it by < 1e-5 (observed 1e-7)
    from compress.cli.demo import STUDY_TOL, demo_models, model_study

    phong = demo_models()["phong"]
    fast, exact = model_study(phong, (2, 4), tol=STUDY_TOL), model_study(phong, (2, 4), tol=1e-6)
    for a, b in zip(fast.rows, exact.rows, strict=True):
        assert (a["kind"], a["order"]) == (b["kind"], b["order"])
        assert abs(a["l2"] - b["l2"]) <= 1e-5 * b["l2"], (a["kind"], a["order"])


def test_compile_ahead_reports_each_step():
    from compress.cli.demo import CompileAhead

    with CompileAhead({"zernike": (), "simulation": (16,)}) as ahead:
        assert ahead.wait("study") is False  # not asked for
        assert ahead.wait("zernike") is True
        assert ahead.wait("simulation") is True
        assert ahead.wait("simulation") is False  # already waited for


def test_compile_ahead_failure_means_compile_in_place():
    # negative control: an unknown step makes the process fail before printing its name
    from compress.cli.demo import CompileAhead

    with CompileAhead({"nonexistent": ()}) as ahead:
        assert ahead.wait("nonexistent") is False
    with CompileAhead({}) as ahead:  # nothing asked: no process at all
        assert ahead._proc is None and ahead.wait("study") is False


def test_lazy_compile_ahead_starts_only_on_a_cache_miss():
    import numba

    from compress.cli.demo import CompileAhead

    # nothing compiles (every kernel cached, or none called): no second process
    with CompileAhead({"simulation": (16,)}, lazy=True) as ahead:
        assert not ahead.started
        assert ahead.wait("simulation") is False
    # a compilation (an uncached function, so numba's compile event fires) starts it
    with CompileAhead({"simulation": (16,)}, lazy=True) as ahead:
        numba.njit(lambda x: x + 1)(1)
        assert ahead.started
        assert ahead.wait("simulation") is True


def _deterministic(out: str) -> list[str]:
    """The demo's lines without wall times: tables without their timing column, sim facts."""
    keep = []
    for line in out.splitlines():
        if line.startswith("| ") and "|" in line[2:]:
            cells = line.split("|")[1:-1]
            keep.append("|".join(cells[:-1]))  # the last column is a time (ns)
        elif line.startswith(("energy:", "relative L2", "measured Beckmann")):
            keep.append(line)
        elif "asymmetry Q" in line:
            keep.append(line.rpartition("asymmetry")[2])
    return keep


def test_compile_ahead_gives_the_same_numbers(tmp_path, capsys):
    # reference: the same demo with every kernel compiled (or loaded) in this process
    from compress.cli import main

    argv = ["demo", "--orders", "2", "--points", "200", "--study-orders", "2", "--rays",
            "2000", "--resolution", "16", "--no-progress"]
    outs = []
    for flag in ("--compile-ahead", "--no-compile-ahead"):
        assert main([*argv, "--out", str(tmp_path / flag), flag]) == 0
        outs.append(_deterministic(capsys.readouterr().out))
    assert len(outs[0]) >= 12 and any("asymmetry" not in x and "Q =" in x for x in outs[0])
    assert outs[0] == outs[1]


def test_simulation_is_compared_with_the_model_in_its_own_quantity():
    # Westin, Arvo & Torrance (1992, fig. 6): a lossless mirror Gaussian surface is close to
    # Beckmann + Smith (F = 1); the model omits only multiple scattering (here ~4 % of the
    # energy), so the matrices of f cos cos agree in M_00 to that share, and their distance
    # is the order-8 truncation of the model (~14 %) plus Monte Carlo noise, far below the
    # ~0.9 of comparing an f matrix with an f cos cos one
    from compress.cli.demo import simulate_demo

    out = simulate_demo(rays=20_000, resolution=48)
    sim, ref = out["result"].matrix, out["curves"]["same, order 8"]
    assert sim.quantity == ref.quantity == "f_cos"
    assert sim.matrix[0, 0] == pytest.approx(0.5, abs=1e-3)  # lossless: albedo 1, exactly
    assert ref.matrix[0, 0] == pytest.approx(0.5, rel=0.1)
    assert out["difference"] < 0.3
