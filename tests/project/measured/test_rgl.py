"""RGL-EPFL ``.bsdf`` tensor files: the container, the evaluation, conventions, damaged files.

References are independent of ``project.measured.rgl``:

- files are assembled byte by byte here (``tensor_bytes``) from the layout read by the
  reference loader rgl-epfl/brdf-loader (``Tensor::Tensor`` in ``powitacq_rgb.inl``);
- ``reference_f_cos`` re-derives the loader's ``BRDF::eval`` (Dupuy & Jakob 2018) in plain
  numpy/scipy, one pair at a time: incidence weights as hat functions, the inverse VNDF warp
  as integrals of the bilinear density computed with ``np.trapezoid`` on the nodes plus the
  end point (exact for piecewise-linear integrands), tables read with scipy's
  ``RegularGridInterpolator``; no CDF tables;
- Mitsuba 3's ``measured`` plugin (scalar_rgb) on the real files, when mitsuba is installed.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from project.measured import RGLBRDF, read_rgl, read_tensor_file, write_tensor_file

ROOT = Path(__file__).resolve().parents[3]
LOCAL = ROOT / "tests" / "data" / "paper_white_rgb.bsdf"
SHARED = ROOT.parent / "shared" / "data" / "rgl"
REAL = ["paper_white_rgb", "colodur_napoli_4f_rgb", "vch_golden_yellow_rgb"]
CODES = {np.dtype("u1"): 1, np.dtype("i1"): 2, np.dtype("<u2"): 3, np.dtype("<i2"): 4,
         np.dtype("<u4"): 5, np.dtype("<i4"): 6, np.dtype("<u8"): 7, np.dtype("<i8"): 8,
         np.dtype("<f2"): 9, np.dtype("<f4"): 10, np.dtype("<f8"): 11}
F32 = np.float32


def real_file(name: str) -> Path:
    """A real material: the copy in tests/data, else ../shared/data/rgl (skip if absent)."""
    if LOCAL.stem == name and LOCAL.is_file():
        return LOCAL
    path = SHARED / f"{name}.bsdf"
    if not path.is_file():
        pytest.skip(f"{path} not present (the RGL files live in ../shared/data/rgl)")
    return path


def tensor_bytes(fields: dict, align: int = 8) -> bytes:
    """A tensor file assembled by hand: preamble, field headers, data aligned to ``align``."""
    arrays = [(k.encode(), np.asarray(v, order="C")) for k, v in fields.items()]
    head = len(b"tensor_file\0") + 2 + 4 + sum(2 + len(k) + 2 + 1 + 8 + 8 * a.ndim
                                               for k, a in arrays)
    offset = -(-head // align) * align
    header = b"tensor_file\0" + bytes([1, 0]) + struct.pack("<I", len(arrays))
    body = b""
    for k, a in arrays:
        header += struct.pack("<H", len(k)) + k + struct.pack("<H", a.ndim)
        header += struct.pack("<B", CODES[a.dtype]) + struct.pack("<Q", offset + len(body))
        header += b"".join(struct.pack("<Q", s) for s in a.shape)
        body += a.tobytes() + bytes(-a.nbytes % align)
    return header + bytes(offset - len(header)) + body


def synthetic_fields(rng: np.random.Generator, *, n_phi: int = 1, span: float = 2 * np.pi,
                     n_theta: int = 4, vndf: tuple[int, int] = (9, 7), m: int = 6,
                     wavelengths: np.ndarray | None = None, jacobian: int = 1) -> dict:
    """Random fields with the published layout; slices dip below 0 to exercise the clamp."""
    theta = np.sort(np.concatenate([[0.0, np.pi / 2], rng.uniform(0.1, 1.4, n_theta - 2)]))
    phi = (-np.pi + np.linspace(0.0, span, n_phi)) if n_phi > 1 else np.zeros(1)
    nc = 3 if wavelengths is None else len(wavelengths)
    f = {
        "version": np.array([1, 0], np.uint32),
        "description": np.frombuffer(b"synthetic test material", np.uint8),
        "phi_i": phi.astype(F32), "theta_i": theta.astype(F32),
        "sigma": rng.uniform(0.2, 1.0, (3, 10)).astype(F32),
        "ndf": rng.uniform(0.0, 2.0, (5, 8)).astype(F32),
        "vndf": rng.uniform(0.05, 1.0, (n_phi, n_theta, *vndf)).astype(F32),
        "luminance": rng.uniform(0.0, 1.0, (n_phi, n_theta, m, m)).astype(F32),
        "jacobian": np.array([jacobian], np.uint8),
    }
    slab = rng.uniform(-0.2, 1.0, (n_phi, n_theta, nc, m, m)).astype(F32)
    if wavelengths is None:
        f["rgb"] = slab
    else:
        f["spectra"] = slab
        f["wavelengths"] = np.asarray(wavelengths, F32)
    return f


def upper(rng: np.random.Generator, n: int) -> np.ndarray:
    w = rng.normal(size=(n, 3))
    w[:, 2] = np.abs(w[:, 2])
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def reference_f_cos(fields: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """The reference loader's eval, f cos(theta_o), re-derived in numpy (module docstring)."""
    theta_n = fields["theta_i"].astype(float)
    phi_n = fields["phi_i"].astype(float)
    iso = phi_n.size <= 2
    reduction = 1 if iso else round(2 * np.pi / (phi_n[-1] - phi_n[0]))
    slab = (fields["spectra"] if "wavelengths" in fields else fields["rgb"]).astype(float)
    vndf = fields["vndf"].astype(float)
    ny, nx = vndf.shape[2:]
    xg, yg = np.linspace(0, 1, nx), np.linspace(0, 1, ny)
    # each incidence slice of the VNDF scaled to integrate to 1 over the unit square
    vndf = vndf / np.trapezoid(np.trapezoid(vndf, xg, axis=3), yg, axis=2)[..., None, None]
    grid = lambda t: (np.linspace(0, 1, t.shape[0]), np.linspace(0, 1, t.shape[1]))  # noqa: E731
    ndf = RegularGridInterpolator(grid(fields["ndf"]), fields["ndf"].astype(float))
    sigma = RegularGridInterpolator(grid(fields["sigma"]), fields["sigma"].astype(float))

    def hats(nodes, x):  # linear-interpolation weights on the nodes, constant outside
        if nodes.size == 1:
            return np.ones(1)
        t = np.interp(x, nodes, np.arange(nodes.size))
        return np.maximum(0.0, 1.0 - np.abs(np.arange(nodes.size) - t))

    def angles(w):
        return math.atan2(math.hypot(w[0], w[1]), w[2]), math.atan2(w[1], w[0])

    out = np.zeros((len(wi), slab.shape[2]))
    for k, (a, b) in enumerate(zip(wi, wo, strict=True)):
        if a[2] <= 0 or b[2] <= 0:
            continue
        a, b = a.copy(), b.copy()
        if reduction >= 2:  # Mitsuba 3: fold w_i into the stored azimuth range
            flip_y = not np.signbit(a[1])
            flip_x = (not np.signbit(a[0])) if reduction == 4 else flip_y
            if flip_x:
                a[0], b[0] = -a[0], -b[0]
            if flip_y:
                a[1], b[1] = -a[1], -b[1]
        h = (a + b) / np.linalg.norm(a + b)
        th_i, ph_i = angles(a)
        th_m, ph_m = angles(h)
        ui = (np.sqrt(2 * th_i / np.pi), (ph_i + np.pi) / (2 * np.pi))
        um = (np.sqrt(2 * th_m / np.pi),
              np.mod(((ph_m - ph_i) if iso else ph_m) + np.pi, 2 * np.pi) / (2 * np.pi))
        wts = np.outer(hats(phi_n, ph_i), hats(theta_n, th_i))
        dens = np.einsum("pt,ptyx->yx", wts, vndf)
        # marginal in y: integral of the row totals (linear in y between nodes) up to um_y
        rows = np.trapezoid(dens, xg, axis=1)
        ys = np.append(yg[yg < um[1]], um[1])
        sy = np.trapezoid(np.interp(ys, yg, rows), ys) / np.trapezoid(rows, yg)
        # conditional in x: the density along y = um_y, integrated up to um_x
        row = np.array([np.interp(um[1], yg, dens[:, j]) for j in range(nx)])
        xs = np.append(xg[xg < um[0]], um[0])
        sx = np.trapezoid(np.interp(xs, xg, row), xs) / np.trapezoid(row, xg)
        blend = np.einsum("pt,ptcyx->cyx", wts, slab)
        value = np.array([RegularGridInterpolator(grid(s), s)((sy, sx)) for s in blend])
        value = np.maximum(value, 0.0)
        if fields["jacobian"][0]:
            value *= ndf((um[1], um[0])) / (4 * sigma((ui[1], ui[0])))
        out[k] = value
    return out


# ----------------------------------------------------------------------------- container


def test_reads_hand_made_file(tmp_path):
    fields = {name: (np.arange(6).reshape(2, 3) * 3).astype(dt) for name, dt in
              [("u8", "u1"), ("i8", "i1"), ("u16", "<u2"), ("i16", "<i2"), ("u32", "<u4"),
               ("i32", "<i4"), ("u64", "<u8"), ("i64", "<i8"), ("f16", "<f2"),
               ("f32", "<f4"), ("f64", "<f8")]}
    fields["scalar"] = np.array(7.5)
    fields["empty"] = np.zeros((0, 4), "<f4")
    path = tmp_path / "t.bsdf"
    path.write_bytes(tensor_bytes(fields))  # misaligned data is refused: test_misaligned_field
    got = read_tensor_file(path)
    assert list(got) == list(fields)
    for k, v in fields.items():
        assert got[k].dtype == v.dtype and got[k].shape == v.shape, k
        np.testing.assert_array_equal(got[k], v)
        assert not got[k].flags.writeable


def test_write_matches_hand_made_layout(tmp_path, rng):
    fields = synthetic_fields(rng)
    written = write_tensor_file(tmp_path / "s.bsdf", fields)
    assert written.read_bytes() == tensor_bytes(fields)
    # the published files use the same 8-byte alignment: their first offset is 416
    real = read_tensor_file(LOCAL)
    assert tensor_bytes(real) == LOCAL.read_bytes()


def test_write_rejects_bool(tmp_path):
    with pytest.raises(ValueError, match="field 'm' must have an integer or float16/32/64"):
        write_tensor_file(tmp_path / "b.bsdf", {"m": np.zeros(3, bool)})


# ----------------------------------------------------------------------------- evaluation


CASES = {
    "isotropic": {},
    "isotropic-2-phi": {"n_phi": 2},
    "anisotropic": {"n_phi": 5},
    "reduction-2": {"n_phi": 4, "span": np.pi},
    "reduction-4": {"n_phi": 3, "span": np.pi / 2},
    "spectral": {"wavelengths": np.array([400.0, 550.0, 700.0, 850.0])},
    "no-jacobian": {"jacobian": 0, "n_theta": 2},
}


@pytest.mark.parametrize("case", list(CASES))
def test_matches_reference_formulas(case, rng, tmp_path):
    fields = synthetic_fields(rng, **CASES[case])
    brdf = read_rgl(write_tensor_file(tmp_path / f"{case}.bsdf", fields))
    wi, wo = upper(rng, 300), upper(rng, 300)
    ref = reference_f_cos(fields, wi, wo)
    got = brdf.eval(wi, wo) * wo[:, 2:3]  # ours is f; the reference returns f cos(theta_o)
    # both float64; they differ by rounding in the angles (asin vs atan2) and in the order
    # of the sums: observed <= 2.5e-15 of the largest value over the cases; 1e-12 allowed
    # (400x headroom, and far below the float32 precision of the data)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert (ref == 0).any(), "the random slices must exercise the clamp at 0"


def test_real_file_matches_reference_formulas(rng):
    fields = read_tensor_file(LOCAL)
    brdf = read_rgl(LOCAL)
    wi, wo = upper(rng, 300), upper(rng, 300)
    ref = reference_f_cos(fields, wi, wo)
    # same reasoning as above; observed 3.4e-15 of the largest value
    np.testing.assert_allclose(brdf.eval(wi, wo) * wo[:, 2:3], ref, rtol=0,
                               atol=1e-12 * ref.max())


@pytest.mark.parametrize("name", REAL)
def test_matches_mitsuba(name, rng):
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 (in the [test] extra) is not installed")
    path = real_file(name)
    mi.set_variant("scalar_rgb")  # RGB files need an RGB variant (Mitsuba's own check)
    plugin = mi.load_dict({"type": "measured", "filename": str(path)})
    ctx, si = mi.BSDFContext(), mi.SurfaceInteraction3f()
    wi, wo = upper(rng, 1000), upper(rng, 1000)
    ref = np.empty((len(wi), 3))
    for k in range(len(wi)):  # Mitsuba's si.wi takes the incidence slot, like our wi
        si.wi = mi.Vector3f(*wi[k])
        ref[k] = np.array(plugin.eval(ctx, si, mi.Vector3f(*wo[k])))
    got = read_rgl(path).eval(wi, wo) * wo[:, 2:3]  # Mitsuba returns f cos(theta_o)
    # Mitsuba does not clamp negative slices (vch_golden_yellow has out-of-gamut values)
    np.testing.assert_array_equal(got[ref < 0], 0.0)
    ref = np.maximum(ref, 0.0)
    # Mitsuba computes in float32: inputs and angles carry ~6e-8 relative error, amplified
    # by the sqrt warp and by steep tables (the NDF of the glossy vinyl spans 19 decades).
    # Observed over 3 x 3000 pairs: |diff| <= 4.4e-6 x the largest value and <= 8e-5
    # relative; allowed: 1e-4 relative plus 2e-5 of the largest value
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=2e-5 * ref.max())


def test_rotation_invariance(rng):
    """Isotropic files depend on relative azimuths only; reduction-2 files on phi mod pi."""
    wi, wo = upper(rng, 200), upper(rng, 200)
    a = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    fields = synthetic_fields(rng)
    for k in ("sigma", "ndf"):  # one row per table, as in the published isotropic files
        fields[k] = np.broadcast_to(fields[k][:1], fields[k].shape).copy()
    iso = RGLBRDF(fields)
    # rounding of atan2 in the two frames: observed 1e-15 of the largest value; 1e-12
    ref = iso.eval(wi, wo)
    np.testing.assert_allclose(iso.eval(wi @ rot.T, wo @ rot.T), ref, rtol=0,
                               atol=1e-12 * ref.max())
    aniso = RGLBRDF(synthetic_fields(rng, n_phi=5))
    ref = aniso.eval(wi, wo)
    assert np.abs(aniso.eval(wi @ rot.T, wo @ rot.T) - ref).max() > 1e-3 * ref.max()
    half = RGLBRDF(synthetic_fields(rng, n_phi=4, span=np.pi))
    flip = np.diag([-1.0, -1.0, 1.0])  # rotation by pi
    np.testing.assert_array_equal(half.eval(wi @ flip, wo @ flip), half.eval(wi, wo))


def test_horizon():
    """f cos(theta_o) tends to a constant at grazing w_o (the reference), so f ~ 1/cos."""
    brdf = read_rgl(LOCAL)
    wi = np.array([np.sin(0.5), 0.0, np.cos(0.5)])
    zs = np.array([1e-5, 1e-7, 1e-9, 1e-11])
    wo = np.stack([np.sqrt(1 - zs ** 2), np.zeros(4), zs], axis=-1)
    fc = brdf.eval(wi, wo) * zs[:, None]
    # f cos changes by O(z) once z is small: 0.5 % between z = 1e-3 and 1e-5 (steep tables
    # near grazing), so at most ~5e-5 relative from 1e-5 on; 1e-3 allowed
    np.testing.assert_allclose(fc[1:], np.broadcast_to(fc[0], fc[1:].shape), rtol=1e-3)
    assert np.all(fc > 1e-3)  # observed 0.008-0.009: not 0 at grazing
    # on the horizon, below it, or with z below float32's smallest subnormal: 0 (reference)
    for z in (0.0, -1e-3, 5e-46):
        w = np.array([np.sqrt(1 - z * z), 0.0, z])
        assert brdf.eval(wi, w).tolist() == [0.0, 0.0, 0.0], z
        assert brdf.eval(w, wi).tolist() == [0.0, 0.0, 0.0], z
    assert np.isfinite(brdf.eval(wi, [1.0, 0.0, 1e-44])).all()


# ----------------------------------------------------------------------------- real files


@pytest.mark.parametrize("name", REAL)
def test_real_files_finite_and_nonnegative(name, rng):
    brdf = read_rgl(real_file(name))
    wi, wo = upper(rng, 20000), upper(rng, 20000)
    wi[:100] = [1.0, 0.0, 1e-12]  # grazing pairs and the normal included
    wo[100:200] = [0.0, 0.0, 1.0]
    f = brdf.eval(wi, wo)
    assert f.shape == (20000, 3)
    assert np.isfinite(f).all() and (f >= 0).all()


def test_paper_albedo():
    """White paper reflects most light; its blue channel is lifted by optical brighteners."""
    brdf = read_rgl(LOCAL)
    t = np.radians([0.0, 30.0, 60.0])
    wi = np.stack([np.sin(t), 0 * t, np.cos(t)], axis=-1)
    a = brdf.albedo(wi)
    # observed 0.82-0.99 (doubling the rule changes the 4th digit); bounds from physics:
    # a white paper reflects 75-100 % and cannot reflect more than it receives
    assert a.shape == (3, 3)
    assert np.all((a >= 0.75) & (a <= 1.0)), a


def test_attributes_and_repr():
    brdf = read_rgl(LOCAL)
    assert repr(brdf) == ("RGLBRDF(name='paper_white_rgb', description='White A4 paper "
                          "(160 gsm)', channels=3, isotropic=True)")
    assert (brdf.channels, brdf.channel_names, brdf.wavelengths) == (3, ("R", "G", "B"), None)
    assert brdf.isotropic and not brdf.reciprocal and brdf.jacobian and brdf.reduction == 1
    assert brdf.path == LOCAL and brdf.name == "paper_white_rgb"
    assert set(brdf.fields) == {"version", "description", "phi_i", "theta_i", "sigma", "ndf",
                                "vndf", "luminance", "rgb", "jacobian", "valid"}
    # the last node is pi/2 rounded down to float32 (1 ulp below np.float32(np.pi / 2))
    assert brdf.theta_i.shape == (8,) and 0 < np.pi / 2 - float(brdf.theta_i[-1]) < 1e-7
    assert brdf.phi_i.tolist() == [0.0]
    assert brdf.valid.shape == (1, 8, 32, 32) and brdf.valid.dtype == bool
    assert brdf.valid.sum() == 8 * np.unpackbits(brdf.fields["valid"]).sum() // 8
    for a in (*brdf.fields.values(), brdf.valid):
        assert not a.flags.writeable
    with pytest.raises(TypeError):
        brdf.fields["rgb"] = None  # type: ignore[index]


def test_spectral_attributes(rng):
    brdf = RGLBRDF(synthetic_fields(rng, wavelengths=[400.0, 550.5]))
    assert brdf.channels == 2 and brdf.channel_names == ("400 nm", "550.5 nm")
    assert brdf.wavelengths.tolist() == [400.0, 550.5]
    assert brdf.eval([0, 0, 1.0], [0, 0, 1.0]).shape == (2,)
    assert brdf.name is None and brdf.path is None and brdf.valid is None


# ----------------------------------------------------------------------------- bad input


def test_bad_paths(tmp_path):
    with pytest.raises(FileNotFoundError, match="RGL file .*missing.bsdf' does not exist"):
        read_rgl(tmp_path / "missing.bsdf")
    with pytest.raises(IsADirectoryError, match="must be a RGL file, got the directory"):
        read_rgl(tmp_path)
    with pytest.raises(FileNotFoundError, match="tensor file .*nope' does not exist"):
        read_tensor_file(tmp_path / "nope")
    with pytest.raises(TypeError, match="path must be a str or os.PathLike, got NoneType"):
        read_rgl(None)
    with pytest.raises(TypeError, match="fields must be a mapping"):
        RGLBRDF([1, 2])


@pytest.mark.parametrize("reader, what", [(read_rgl, "RGL"), (read_tensor_file, "tensor")])
def test_fifo_refused(on_fifo, reader, what):
    # opening a FIFO blocks until a writer appears: refused before it is opened
    with pytest.raises(ValueError, match=f"{what} file '.*pipe.bsdf' must be a regular file, "
                                         r"got a FIFO \(named pipe\)"):
        on_fifo(reader, "pipe.bsdf")


def _replace(fields: dict, **kw) -> dict:
    out = dict(fields)
    for k, v in kw.items():
        if v is None:
            del out[k]
        else:
            out[k] = v
    return out


@pytest.fixture(scope="module")
def good() -> dict:
    return {k: np.array(v) for k, v in read_tensor_file(LOCAL).items()}


def _nan(a: np.ndarray, value: float = np.nan) -> np.ndarray:
    a = a.copy()
    a.flat[a.size // 2] = value
    return a


@pytest.mark.parametrize("change, match", [
    (lambda f: _replace(f, rgb=None), "required field 'rgb' is missing"),
    (lambda f: _replace(f, sigma=None), "required field 'sigma' is missing"),
    (lambda f: _replace(f, rgb=f["rgb"].astype("<f8")),
     "field 'rgb' must have dtype float32, got float64"),
    (lambda f: _replace(f, theta_i=f["theta_i"].astype("<f2")),
     "field 'theta_i' must have dtype float32, got float16"),
    (lambda f: _replace(f, jacobian=np.array([1], "<u2")),
     "field 'jacobian' must have dtype uint8"),
    (lambda f: _replace(f, jacobian=np.array([7], "u1")), "field 'jacobian' must be 0 or 1"),
    (lambda f: _replace(f, jacobian=np.array([1, 1], "u1")),
     r"field 'jacobian' must have shape \(1,\)"),
    (lambda f: _replace(f, rgb=f["rgb"][:, :, :2]), r"field 'rgb' must have shape \(1, 8, 3"),
    (lambda f: _replace(f, vndf=f["vndf"][:, :7]), r"field 'vndf' must have shape \(1, 8, n_y"),
    (lambda f: _replace(f, ndf=f["ndf"][0]), r"field 'ndf' must have 2 dimension\(s\)"),
    (lambda f: _replace(f, sigma=f["sigma"][:1]), "field 'sigma' must have at least 2 x 2"),
    (lambda f: _replace(f, luminance=f["luminance"][..., :5]),
     "field 'luminance' must have shape"),
    (lambda f: _replace(f, theta_i=f["theta_i"][::-1].copy()),
     "field 'theta_i' must increase strictly"),
    (lambda f: _replace(f, theta_i=f["theta_i"] * F32(2)), r"field 'theta_i' must lie in"),
    (lambda f: _replace(f, phi_i=np.linspace(-1, 1, 3, dtype=F32)),
     "field 'phi_i' must span 2 pi, pi or pi/2"),
    (lambda f: _replace(f, sigma=np.zeros_like(f["sigma"])), "field 'sigma' must be > 0"),
    (lambda f: _replace(f, ndf=-f["ndf"] - 1), "field 'ndf' must be >= 0"),
    (lambda f: _replace(f, vndf=-f["vndf"] - 1), "field 'vndf' must be >= 0"),
    (lambda f: _replace(f, vndf=np.zeros_like(f["vndf"])),
     "field 'vndf' must have a positive integral in every slice"),
    (lambda f: _replace(f, wavelengths=np.array([500.0, 600, 700], F32)),
     "required field 'spectra' is missing"),
    (lambda f: _replace(f, wavelengths=np.array([600.0, 500, 700], F32),
                        spectra=f["rgb"]), "field 'wavelengths' must be > 0 nm and increase"),
] + [(lambda f, k=k, v=v: _replace(f, **{k: _nan(f[k], v)}),
      f"field '{k}' must be finite, 1 of")
     for k in ("theta_i", "sigma", "ndf", "vndf", "luminance", "rgb")
     for v in (np.nan, np.inf)],
    ids=lambda x: None if callable(x) else "")
def test_bad_fields(tmp_path, good, change, match):
    path = tmp_path / "bad.bsdf"
    write_tensor_file(path, change(good))
    with pytest.raises(ValueError, match=f"RGL file '{path}': .*{match}"):
        read_rgl(path)


@pytest.mark.parametrize("make, match", [
    (lambda b: b"", "0 bytes, fewer than the 18-byte preamble"),
    (lambda b: b"P3\n" + b[3:], "must start with b'tensor_file"),
    (lambda b: b[:12] + bytes([2, 0]) + b[14:], "format version 2.0; only 1.0"),
    (lambda b: b[:14] + struct.pack("<I", 10 ** 6) + b[18:], "declares 1000000 fields"),
    (lambda b: b[:-8], r"field 'valid' \(uint8, shape \(1024,\), 1024 bytes at offset 657904\) "
                       "must lie between"),
    (lambda b: b[:200], r"ends past the end of the file \(200 bytes\)"),
], ids=["empty", "magic", "version", "field-count", "short-data", "short-header"])
def test_damaged_container(tmp_path, make, match):
    path = tmp_path / "damaged.bsdf"
    path.write_bytes(make(LOCAL.read_bytes()))
    with pytest.raises(ValueError, match=f"tensor file '{path}'.*{match}"):
        read_rgl(path)


def test_unknown_type_and_bad_names(tmp_path, good):
    data = bytearray(tensor_bytes(good))
    at = data.index(b"description") + len("description") + 2  # ndim (2 bytes), then type
    data[at] = 12
    path = tmp_path / "type.bsdf"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="field 'description' has unknown type code 12"):
        read_rgl(path)
    data = bytearray(tensor_bytes(good))
    data[data.index(b"phi_i")] = 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"the name of field #2 is not UTF-8"):
        read_rgl(path)
    data = bytearray(tensor_bytes(good))
    data[data.index(b"ndf"):data.index(b"ndf") + 3] = b"vdf"
    data[data.index(b"vndf"):data.index(b"vndf") + 4] = b"sigm"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="field 'sigm' appears twice|required field"):
        read_rgl(path)


def raw_container(fields: list[tuple[str, int, int, tuple]], size: int) -> bytes:
    """A tensor file of ``size`` bytes whose headers say anything: (name, code, offset, shape)."""
    header = b"tensor_file\0" + bytes([1, 0]) + struct.pack("<I", len(fields))
    for name, code, offset, shape in fields:
        header += struct.pack("<H", len(name)) + name.encode()
        header += struct.pack(f"<HBQ{len(shape)}Q", len(shape), code, offset, *shape)
    assert len(header) <= size
    return header + bytes(size - len(header))


@pytest.mark.parametrize("shape", [(2**40, 2**40, 0), (2**64 - 1, 0), (1,) * 65],
                         ids=["2^40-2^40-0", "2^64-0", "65-dims"])
def test_shape_numpy_cannot_hold(tmp_path, shape):
    path = tmp_path / "shape.bsdf"
    path.write_bytes(raw_container([("a", 10, 1024, shape)], 1028))  # room for 4 bytes
    with pytest.raises(ValueError, match=f"tensor file '{path}': field 'a' has shape "
                                         r"\(.*\), which numpy cannot hold"):
        read_rgl(path)


def _offset_at(data: bytes, name: bytes) -> int:
    """Position of the offset in the header of field ``name`` (after ndim and type code)."""
    return data.index(struct.pack("<H", len(name)) + name) + 2 + len(name) + 3


def test_overlapping_fields(tmp_path, good):
    # the header of 'luminance' pointed at the bytes of 'rgb': float32 of the same slices,
    # read without complaint before, giving another BRDF
    data = bytearray(tensor_bytes(good))
    rgb = data[_offset_at(data, b"rgb"):_offset_at(data, b"rgb") + 8]
    at = _offset_at(data, b"luminance")
    data[at:at + 8] = rgb
    path = tmp_path / "overlap.bsdf"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=f"tensor file '{path}': fields .* overlap"):
        read_rgl(path)
    path.write_bytes(raw_container([("a", 10, 64, (2,)), ("b", 10, 68, (2,))], 80))
    with pytest.raises(ValueError, match=f"tensor file '{path}': fields 'a' and 'b' overlap "
                                         r"\(bytes 68 to 71 belong to both\)"):
        read_tensor_file(path)


def test_adjacent_and_empty_fields_do_not_overlap(tmp_path):
    path = tmp_path / "adjacent.bsdf"
    path.write_bytes(raw_container([("a", 10, 88, (2,)), ("b", 10, 96, (2,)),
                                    ("c", 10, 88, (0,))], 104))
    fields = read_tensor_file(path)
    assert [v.shape for v in fields.values()] == [(2,), (2,), (0,)]


def test_misaligned_field(tmp_path, good):
    path = tmp_path / "misaligned.bsdf"
    path.write_bytes(raw_container([("a", 10, 66, (2,))], 80))
    with pytest.raises(ValueError, match=f"tensor file '{path}': field 'a' \\(float32\\) "
                                         "must start at an offset that is a multiple of its "
                                         "item size 4, got offset 66"):
        read_tensor_file(path)
    data = bytearray(tensor_bytes(good))  # the published layout, 'ndf' moved by 2 bytes
    at = _offset_at(data, b"ndf")
    data[at:at + 8] = struct.pack("<Q", struct.unpack_from("<Q", data, at)[0] + 2)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=f"tensor file '{path}': field 'ndf' .*multiple of "
                                         "its item size 4"):
        read_rgl(path)


# ----------------------------------------------------------------------------- fuzzing


def _read_or_value_error(path: Path, wi: np.ndarray, wo: np.ndarray) -> bool:
    """Read a damaged file: ValueError, or a BRDF whose values are finite and >= 0."""
    try:
        brdf = read_rgl(path)
    except ValueError as e:
        assert str(path) in str(e)
        return False
    f = brdf.eval(wi, wo)
    assert np.isfinite(f).all() and (f >= 0).all()
    return True


def test_fuzz_truncations(tmp_path):
    data = LOCAL.read_bytes()
    path = tmp_path / "cut.bsdf"
    cuts = sorted({*range(0, 420, 3), *np.linspace(420, len(data) - 1, 120).astype(int)})
    for n in cuts:
        path.write_bytes(data[:n])
        with pytest.raises(ValueError, match=f"tensor file '{path}'"):
            read_rgl(path)


def test_fuzz_header_bytes(tmp_path, rng):
    """Every byte of the header, flipped: a ValueError or a valid BRDF, never a crash."""
    data = LOCAL.read_bytes()
    path = tmp_path / "flip.bsdf"
    wi, wo = upper(rng, 64), upper(rng, 64)
    read = 0
    for at in range(412):  # the header of the published file ends at byte 412
        for mask in (0xFF, 0x01):
            damaged = bytearray(data)
            damaged[at] ^= mask
            path.write_bytes(bytes(damaged))
            read += _read_or_value_error(path, wi, wo)
    assert 0 < read < 824  # some flips hit unused bytes or fields, most are caught


def test_fuzz_data_bytes(tmp_path, rng):
    """Random bytes of the data overwritten with random values (NaN patterns included)."""
    data = LOCAL.read_bytes()
    path = tmp_path / "noise.bsdf"
    wi, wo = upper(rng, 64), upper(rng, 64)
    for _ in range(150):
        damaged = bytearray(data)
        at = int(rng.integers(412, len(data) - 4))
        damaged[at:at + 4] = rng.choice([b"\xff\xff\xff\x7f", b"\x00\x00\x80\x7f",
                                         rng.bytes(4)])
        path.write_bytes(bytes(damaged))
        _read_or_value_error(path, wi, wo)
