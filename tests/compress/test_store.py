"""compress.save / compress.load: bit-exact round trips of matrices, fitted models and
hybrids, precision, back-compatibility with schemas 1 and 2, and a damaged-file fuzz: every
load either returns what was saved or raises ValueError naming the file."""

from __future__ import annotations

import json
import time

import h5py
import numpy as np
import pytest

import basis
from basis import CoefficientMatrix
from compress import Hybrid, hybrid, load, save
from compress.store import FORMAT, READABLE_VERSIONS, SCHEMA_VERSION
from project import FittedModel
from project.models import Lambert
from tests.conftest import random_directions


def _iso(b: basis.Basis, rng: np.random.Generator, channels: int | None = 3,
         quantity: str = "f_cos") -> CoefficientMatrix:
    cos_idx = b.azimuthal_blocks().cos
    blocks = []
    for idx in cos_idx:
        shape = (idx.size, idx.size) if channels is None else (channels, idx.size, idx.size)
        x = rng.normal(size=shape)
        blocks.append(x + np.swapaxes(x, -1, -2))
    return CoefficientMatrix.from_blocks(b, blocks, quantity)


INFO = {"source": "Phong(kd=0.3)", "method": "quadrature", "nodes": (64, 130),
        "error_estimate": 1.25e-15, "converged": True, "truncation_error": None,
        "standard_error": np.arange(6.0).reshape(2, 3) / 7, "count": np.int64(7),
        "nested": {"list": [1, 2.5, "x"], "nan": float("nan")}}


@pytest.mark.parametrize("b, channels", [
    (basis.HemiZernike(6), 3), (basis.HemiHarmonics(5), None),
    (basis.HemiHarmonics(4, parity="even"), 1), (basis.SphericalHarmonics(3), 3)])
def test_round_trip_isotropic_bit_exact(tmp_path, rng, b, channels):
    cm = _iso(b, rng, channels)
    cm.info.update(INFO)
    back = load(save(cm, tmp_path / "c.h5"))
    assert back.basis == b and back.quantity == cm.quantity and back.is_isotropic
    assert back.matrix.shape == cm.matrix.shape
    for x, y in zip(back.blocks, cm.blocks, strict=True):
        assert np.array_equal(x, y)  # bit exact: float64 written, symmetric blocks
    assert back.info.keys() == cm.info.keys()
    assert back.info["nodes"] == (64, 130) and isinstance(back.info["nodes"], tuple)
    assert np.array_equal(back.info["standard_error"], INFO["standard_error"])
    assert back.info["standard_error"].dtype == np.float64
    assert back.info["count"] == 7 and back.info["truncation_error"] is None
    assert back.info["nested"]["list"] == [1, 2.5, "x"]
    assert np.isnan(back.info["nested"]["nan"])


def test_round_trip_dense(tmp_path, rng):
    b = basis.HemiZernike(3)
    x = rng.normal(size=(2, b.size, b.size))
    cm = CoefficientMatrix(b, x + x.swapaxes(1, 2), "f", isotropic=False)
    back = load(save(cm, tmp_path / "d.h5"))
    assert not back.is_isotropic and back.quantity == "f"
    assert np.array_equal(back.matrix, cm.matrix)


def test_schema_layout(tmp_path, rng):
    cm = _iso(basis.HemiZernike(4), rng, 3)
    cm.info.update(source="test", seconds=0.5)
    save(cm, tmp_path / "s.h5")
    with h5py.File(tmp_path / "s.h5", "r") as f:
        # text attributes are fixed-length UTF-8 (h5py reads them as bytes)
        assert f.attrs["format"] == FORMAT.encode()
        assert f.attrs["schema_version"] == SCHEMA_VERSION == 6
        assert f.attrs["reciprocal"]
        assert f.attrs["content"] == b"coefficients" and f.attrs["dtype"] == b"float64"
        assert f.attrs["basis_kind"] == b"zernike" and f.attrs["basis_order"] == 4
        assert f.attrs["storage"] == b"isotropic" and f.attrs["channels"] == 3
        # blocks, not dense; upper triangles only: k_m = 3, 2, 2, 1, 1
        assert list(f["blocks"].attrs["sizes"]) == [3, 2, 2, 1, 1]
        assert f["blocks/m0"].shape == (3, 6) and f["blocks/m4"].shape == (3, 1)
        assert all(f[f"blocks/m{m}"].fletcher32 for m in range(5))
        assert "matrix" not in f
        assert f["provenance"].attrs["source"] == b"test"
        assert json.loads(f.attrs["info"])["seconds"] == 0.5
        # superblock version >= 2: metadata checksums (HDF5 file format specification)
        assert f.id.get_create_plist().get_version()[0] >= 2


@pytest.mark.parametrize("dtype, rel", [("float32", 2.0**-24), ("float16", 2.0**-11)])
def test_reduced_precision(tmp_path, rng, dtype, rel):
    cm = _iso(basis.HemiZernike(4), rng, 3)
    back = load(save(cm, tmp_path / "p.h5", dtype=dtype))
    # round to nearest: relative error of each entry <= unit roundoff of the dtype
    # (float16 normal range: every entry here is > 6e-5 in magnitude or exactly 0)
    a, b = back.matrix, cm.matrix
    assert np.all(np.abs(a - b) <= rel * np.abs(b) + 1e-7 * (dtype == "float16"))
    assert not np.array_equal(a, b)


def test_atomic_write_leaves_no_partial_file(tmp_path, rng, monkeypatch):
    cm = _iso(basis.HemiZernike(2), rng, 1)
    target = tmp_path / "a.h5"
    save(cm, target)
    before = target.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(h5py.Group, "create_group", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save(_iso(basis.HemiZernike(2), rng, 1), target)
    assert target.read_bytes() == before  # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5"]  # no temporary left


def test_truncated_file(tmp_path, rng):
    path = save(_iso(basis.HemiZernike(6), rng, 3), tmp_path / "t.h5")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="damaged or truncated HDF5 file"):
        load(path)


def test_not_hdf5(tmp_path):
    p = tmp_path / "x.h5"
    p.write_bytes(b"hello world, not hdf5")
    with pytest.raises(ValueError, match="is not an HDF5 file"):
        load(p)


def test_foreign_hdf5(tmp_path):
    p = tmp_path / "foreign.h5"
    with h5py.File(p, "w") as f:
        f["data"] = np.arange(3)
    with pytest.raises(ValueError, match="not a scatmodes file .no format attribute"):
        load(p)


@pytest.mark.parametrize("version", [7, 0])
def test_unknown_version(tmp_path, rng, version):
    p = save(_iso(basis.HemiZernike(2), rng, 1), tmp_path / "v.h5")
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = version
    with pytest.raises(ValueError, match=rf"schema version {version}; .* reads schema "
                                         r"versions 1, 2, 3, 4, 5, 6: upgrade scatmodes"):
        load(p)


def test_unknown_basis_kind(tmp_path, rng):
    p = save(_iso(basis.HemiZernike(2), rng, 1), tmp_path / "k.h5")
    with h5py.File(p, "r+") as f:
        f.attrs["basis_kind"] = "wavelets"
    with pytest.raises(ValueError, match="unknown basis kind 'wavelets' .* 'harmonics-even'"):
        load(p)


def test_damaged_content(tmp_path, rng):
    p = save(_iso(basis.HemiZernike(3), rng, 1), tmp_path / "m.h5")
    with h5py.File(p, "r+") as f:
        del f["blocks/m2"]
    with pytest.raises(ValueError, match="is damaged"):
        load(p)


def test_missing_file_and_bad_args(tmp_path, rng):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load(tmp_path / "none.h5")
    with pytest.raises(TypeError, match="save stores a basis.CoefficientMatrix, .* got "
                                        "ndarray"):
        save(np.eye(2), tmp_path / "x.h5")
    cm = _iso(basis.HemiZernike(2), rng, 1)
    with pytest.raises(ValueError, match="dtype must be one of"):
        save(cm, tmp_path / "x.h5", dtype="int8")
    big = CoefficientMatrix(basis.HemiZernike(0), [[1e6]])
    with pytest.raises(ValueError, match="cannot hold the values of the matrix up to 1e"):
        save(big, tmp_path / "x.h5", dtype="float16")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        save(_iso(basis.HemiZernike(2), rng, 1), tmp_path / "nodir" / "x.h5")


def test_info_entries_that_cannot_be_stored_are_dropped_with_a_warning(tmp_path, rng):
    cm = _iso(basis.HemiZernike(2), rng, 1)
    cm.info.update(source="ok", bad=object(), nested={"keep": 1, "fn": print},
                   strings=np.array(["a"]), **{"tuple": (1, object())})
    with pytest.warns(UserWarning, match=r"\['bad'\], \['nested'\]\['fn'\], "
                                         r"\['strings'\], \['tuple'\] are not numbers"):
        back = load(save(cm, tmp_path / "x.h5"))
    assert back.info == {"source": "ok", "nested": {"keep": 1}}


# -- schemas 1 and 2 --------------------------------------------------------------------------
def _write_legacy(cm: CoefficientMatrix, path, version: int):
    """Write ``cm`` as scatmodes wrote schema 1 (0.1.0) or 2: h5py's default (earliest) file
    format, variable-length string attributes, no checksums, no ``content`` attribute; schema
    1 named the hemisphere harmonics "hemi_sh" with a separate basis_parity and had no
    dtype attribute."""
    b = cm.basis
    with h5py.File(path, "w") as f:
        a = f.attrs
        a["format"] = FORMAT
        a["schema_version"] = version
        a["library"] = "scatmodes 0.1.0"
        a["basis_kind"] = b.kind
        if version == 1:
            a["basis_parity"] = getattr(b, "parity", "all")
            if isinstance(b, basis.HemiHarmonics):
                a["basis_kind"] = "hemi_sh"
        else:
            a["dtype"] = "float64"
        a["basis_order"] = b.order
        a["quantity"] = cm.quantity
        a["channels"] = cm.channels
        a["scalar"] = cm.is_scalar
        a["storage"] = "isotropic"
        a["info"] = json.dumps(cm.info)
        g = f.create_group("blocks")
        for m, blk in enumerate(cm.stored):
            iu = np.triu_indices(blk.shape[-1])
            g[f"m{m}"] = blk[:, iu[0], iu[1]]
        g.attrs["sizes"] = [blk.shape[-1] for blk in cm.stored]
        f.create_group("provenance")
    return path


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("b, channels", [
    (basis.HemiHarmonics(4), 3), (basis.HemiHarmonics(3, parity="even"), None),
    (basis.HemiZernike(3), 1), (basis.SphericalHarmonics(2), 3)])
def test_schema_1_and_2_files_still_load(tmp_path, rng, version, b, channels):
    cm = _iso(b, rng, channels)
    cm.info.update(source="old")
    back = load(_write_legacy(cm, tmp_path / "old.h5", version))
    assert back.basis == b and back.info == {"source": "old"}
    assert np.array_equal(back.matrix, cm.matrix) and back.is_scalar == cm.is_scalar
    # the old files are checked as strictly as new ones
    with h5py.File(tmp_path / "old.h5", "r+") as f:
        f.attrs["basis_parity" if version == 1 else "basis_kind"] = "sideways"
        if version == 1:
            f.attrs["basis_kind"] = "hemi_sh"
    with pytest.raises(ValueError, match="sideways"):
        load(tmp_path / "old.h5")
    assert READABLE_VERSIONS == (1, 2, 3, 4, 5, 6)


@pytest.mark.parametrize("kind", basis.KINDS)
def test_every_order_of_every_kind_round_trips(tmp_path, rng, kind):
    # load checks the block sizes against a closed form before it builds a basis: every
    # (kind, order, storage) must pass it
    for order in range(1 if kind == "harmonics" else 0, 9):
        b = basis.make_basis(kind, order)
        cm = _iso(b, rng, 2)
        dense = CoefficientMatrix(b, cm.matrix, cm.quantity, isotropic=False)
        for x in (cm, dense):
            back = load(save(x, tmp_path / "o.h5"))
            assert back.basis == b and np.array_equal(back.matrix, x.matrix)
            assert back.is_isotropic == x.is_isotropic


# -- schema 3: fitted models and hybrids ------------------------------------------------------
def _ggx() -> FittedModel:
    return FittedModel("lambert+ggx", {"kd": [0.5, 0.4, 0.3], "ks": [1, 1, 1], "alpha": 0.2,
                                       "f0": 1.0},
                       info={"l2": 0.031, "param_stderr": {"alpha": np.float64(1e-3)},
                             "cost": [0.5, 0.25], "converged": True})


def _lafortune() -> FittedModel:
    return FittedModel("lafortune", {"kd": [0.2, 0.3, 0.1],
                                     "rho": [[0.5, 0.4, 0.3], [0.1, 0.2, 0.1]],
                                     "cx": [-1.0, -0.7], "cz": [1.0, 1.0], "n": [20.0, 4.5]})


def _pairs(rng, n=500):
    return random_directions(rng, n, upper=True), random_directions(rng, n, upper=True)


@pytest.mark.parametrize("make", [_ggx, _lafortune])
def test_fitted_model_round_trip_bit_exact(tmp_path, rng, make):
    m = make()
    back = load(save(m, tmp_path / "m.h5"))
    assert isinstance(back, FittedModel) and back.family == m.family
    assert back.params.keys() == m.params.keys()
    for k, v in m.params.items():
        assert back.params[k].dtype == np.float64 and back.params[k].shape == v.shape
        assert np.array_equal(back.params[k], v)
    wi, wo = _pairs(rng)
    assert np.array_equal(back.eval(wi, wo), m.eval(wi, wo))
    assert back.info.keys() == m.info.keys()
    if m.info:
        assert back.info["param_stderr"] == {"alpha": 1e-3} and back.info["cost"] == [0.5, 0.25]
    with h5py.File(tmp_path / "m.h5", "r") as f:
        assert f.attrs["content"] == b"model" and f.attrs["family"] == m.family.encode()
        assert f["params/kd"].fletcher32 and list(f["params/kd"].attrs["shape"]) == [3]


def test_fitted_model_float32(tmp_path, rng):
    m = _lafortune()
    back = load(save(m, tmp_path / "m32.h5", dtype="float32"))
    with h5py.File(tmp_path / "m32.h5", "r") as f:
        assert f["params/rho"].dtype == np.float32
    for k, v in m.params.items():
        assert back.params[k].dtype == np.float64
        np.testing.assert_array_equal(back.params[k], v.astype(np.float32))
    wi, wo = _pairs(rng)
    np.testing.assert_allclose(back.eval(wi, wo), m.eval(wi, wo), rtol=1e-5)


class _ByHand:
    """Not a FittedModel: anything with family and params is stored as one."""

    family = "lambert+beckmann"
    params = {"kd": np.array([0.3]), "ks": np.array([0.7]), "alpha": np.array(0.3),
              "f0": np.array(0.04)}


def test_any_model_with_family_and_params(tmp_path, rng):
    back = load(save(_ByHand(), tmp_path / "d.h5"))
    ref = FittedModel(_ByHand.family, _ByHand.params)
    wi, wo = _pairs(rng)
    assert isinstance(back, FittedModel) and back.info == {}
    assert np.array_equal(back.eval(wi, wo), ref.eval(wi, wo))


def test_models_that_could_not_be_read_back_are_refused(tmp_path):
    bad = _ByHand()
    bad.params = {**_ByHand.params, "alpha": np.array(-1.0)}
    with pytest.raises(ValueError, match=r"load would rebuild it as project.FittedModel\("
                                         r"'lambert\+beckmann', params\), which refuses"):
        save(bad, tmp_path / "x.h5")
    bad.params = {**_ByHand.params, "kd": np.array([np.nan])}
    with pytest.raises(ValueError, match="holds non-finite values"):
        save(bad, tmp_path / "x.h5")
    bad.params = {**_ByHand.params, "kd": "red"}
    with pytest.raises(TypeError, match="parameter 'kd' must be numbers, got 'red'"):
        save(bad, tmp_path / "x.h5")
    bad.params = {**_ByHand.params, "a/b": np.array(1.0)}
    with pytest.raises(ValueError, match="without '/'"):
        save(bad, tmp_path / "x.h5")
    bad.family = 3
    with pytest.raises(TypeError, match="family must be a string"):
        save(bad, tmp_path / "x.h5")
    assert not list(tmp_path.iterdir())  # refused before any file was created


class _Sum:
    """A BRDF that is a lobe plus a Lambertian: the residual of a hybrid is one coefficient."""

    isotropic = True
    reciprocal = True
    channels = 3

    def __init__(self, a, b):
        self.a, self.b = a, b

    def eval(self, wi, wo):
        return self.a.eval(wi, wo) + self.b.eval(wi, wo)


@pytest.mark.parametrize("make", [_ggx, _lafortune])
def test_hybrid_round_trip_bit_exact(tmp_path, rng, make):
    lobe = make()
    # quantity f: float32 rounding of an f_cos residual is amplified by 1/(cos cos) at
    # grazing, which is not what this test is about
    h = hybrid(_Sum(lobe, Lambert([0.3, 0.2, 0.1])), 4, lobe=lobe, error_samples=0,
               quantity="f")
    h.info["note"] = np.arange(4.0)
    back = load(save(h, tmp_path / "h.h5"))
    assert isinstance(back, Hybrid) and isinstance(back.lobe, FittedModel)
    assert back.lobe.family == lobe.family and back.lobe.info.keys() == lobe.info.keys()
    assert np.array_equal(back.residual.matrix, h.residual.matrix)
    assert back.residual.basis == h.residual.basis
    assert back.residual.quantity == h.residual.quantity
    wi, wo = _pairs(rng)
    assert np.array_equal(back.eval(wi, wo), h.eval(wi, wo))
    assert back.info.keys() == h.info.keys() and back.info["source"] == h.info["source"]
    assert np.array_equal(back.info["note"], h.info["note"])
    assert back.nbytes == h.nbytes
    with h5py.File(tmp_path / "h.h5", "r") as f:
        assert f.attrs["content"] == b"hybrid" and set(f) == {"lobe", "residual", "provenance"}
        assert f["residual/blocks/m0"].fletcher32
    back32 = load(save(h, tmp_path / "h32.h5", dtype="float32"))
    np.testing.assert_allclose(back32.eval(wi, wo), h.eval(wi, wo), rtol=1e-5, atol=1e-7)


def test_hybrid_with_an_unstorable_lobe(tmp_path):
    res = CoefficientMatrix(basis.HemiZernike(0), [[0.1]], "f")
    with pytest.raises(TypeError, match="the lobe of this Hybrid, Lambert, has no family and "
                                        "params"):
        save(Hybrid(Lambert(0.5), res), tmp_path / "x.h5")


def test_factored_round_trip(tmp_path, rng):
    # the family "factored" of project.fit_model: tables, weights and warp exponents
    from project.factored import fit_factored
    from project.models import CookTorrance

    lobe = fit_factored(CookTorrance(0.1, 0.2, "ggx", ior=1.5), rank=1, bins=(8, 6))
    for m in (lobe, FittedModel("factored", lobe.params, info=lobe.info)):
        back = load(save(m, tmp_path / "f.h5"))
        assert isinstance(back, FittedModel) and back.family == "factored"
        for k, v in m.params.items():
            assert np.array_equal(back.params[k], np.broadcast_to(v, back.params[k].shape))
        wi, wo = _pairs(rng)
        assert np.array_equal(back.eval(wi, wo), m.eval(wi, wo))



# every family of project.fit_model is a family name and a dict of float arrays: the generic
# storage needs no code per family
OTHER_FAMILIES = {
    "dsbrdf": {"kappa": np.linspace(0.1, 2.0, 36).reshape(2, 6, 3),
               "gamma": np.linspace(1.0, 50.0, 36).reshape(2, 6, 3)},
    "rr8807": {"kd": [0.2, 0.3, 0.4], "ks": [0.5, 0.6, 0.7], "kw": [0.1, 0.1, 0.1],
               "f0": [0.04, 0.05, 0.06], "sigma": 0.3, "p": 0.8, "a": 20.0},
}


@pytest.mark.parametrize("family", sorted(OTHER_FAMILIES))
def test_other_families_round_trip(tmp_path, rng, family):
    from project.fitting import FAMILIES

    if family not in FAMILIES:
        pytest.skip(f"project.fit_model has no family {family!r}")
    m = FittedModel(family, OTHER_FAMILIES[family])
    back = load(save(m, tmp_path / "o.h5"))
    assert back.family == family and back.params.keys() == m.params.keys()
    wi, wo = _pairs(rng)
    assert np.array_equal(back.eval(wi, wo), m.eval(wi, wo))

# -- damaged and foreign files ----------------------------------------------------------------
def _zernike3(tmp_path, rng, name="b.h5"):
    """A valid file: HemiZernike(3) in 3 channels, blocks m0..m3 with k_m = 2, 2, 1, 1."""
    return save(_iso(basis.HemiZernike(3), rng, 3), tmp_path / name)


def _edit(path, change):
    with h5py.File(path, "r+") as f:
        change(f)
    return path


def _refused(path, match):
    """load(path) raises ValueError matching ``match`` and naming the file."""
    with pytest.raises(ValueError, match=match) as err:
        load(path)
    assert repr(str(path)) in str(err.value)
    return str(err.value)


def test_scalar_flag_with_three_channels_is_refused(tmp_path, rng):
    path = _zernike3(tmp_path, rng)
    _edit(path, lambda f: f.attrs.modify("scalar", True))
    _refused(path, "is damaged: the matrix in / is marked scalar .no channel axis. but holds 3 "
                   "channels")
    # and a scalar file whose datasets hold 3 channels
    _edit(path, lambda f: f.attrs.modify("channels", 1))
    _refused(path, r"/blocks/m0 has shape \(3, 3\), the schema needs \(1, 3\)")


@pytest.mark.parametrize("kind, order, channels", [
    ("sh", 2800, 3), ("zernike", 1000, 3), ("harmonics", 2800, 1), ("zernike", 3, 10**12)])
def test_small_file_claiming_a_huge_size_is_refused_at_once(tmp_path, rng, kind, order,
                                                             channels):
    path = _zernike3(tmp_path, rng)

    def claim(f):
        f.attrs["basis_kind"], f.attrs["basis_order"] = kind, order
        f.attrs.modify("channels", channels)

    _edit(path, claim)
    t0 = time.perf_counter()
    _refused(path, rf"claims a {kind} basis of order {order} with {channels} channel\(s\) "
                   r"\(isotropic\), \d+ bytes of coefficients, but the file has only \d+ bytes")
    assert time.perf_counter() - t0 < 1.0  # no basis of that order was built


def test_order_beyond_the_basis_limit(tmp_path, rng):
    path = _edit(_zernike3(tmp_path, rng), lambda f: f.attrs.modify("basis_order", 1001))
    _refused(path, r"/@basis_order is 1001, expected 0..1000")


def test_overflowing_and_non_finite_values_are_refused(tmp_path, rng):
    path = _zernike3(tmp_path, rng)

    def put(value):
        def change(f):
            f["blocks/m0"][0, 0] = value  # h5py rewrites the chunk and its checksum
        return change

    _edit(path, put(1.7e308))  # finite, but its square is not
    _refused(path, r"the coefficients in / reach 1.7e\+308, so large that their sum of squares "
                   "overflows")
    _edit(path, put(np.inf))
    _refused(path, r"/blocks/m0 holds 1 non-finite value\(s\)")
    model = save(_ggx(), tmp_path / "m.h5")
    _edit(model, lambda f: f["params/ks"].write_direct(np.full(3, 1e300)))
    _refused(model, "the parameters in / reach 1e\\+300")


def test_links_and_external_storage_are_refused(tmp_path, rng):
    path = _zernike3(tmp_path, rng)
    copy = tmp_path / "copy.h5"
    copy.write_bytes(path.read_bytes())

    def soft(f):  # m2 and m3 have the same shape: followed, the link would load m3's data
        del f["blocks/m2"]
        f["blocks/m2"] = h5py.SoftLink("/blocks/m3")

    _refused(_edit(path, soft), "is refused: /blocks/m2 is a soft link to '/blocks/m3'")
    path.write_bytes(copy.read_bytes())

    def external(f):
        del f["blocks/m2"]
        f["blocks/m2"] = h5py.ExternalLink(str(copy), "/blocks/m2")

    _refused(_edit(path, external), "/blocks/m2 is an external link to .*copy.h5")
    path.write_bytes(copy.read_bytes())
    _refused(_edit(path, lambda f: f.__setitem__("extra", h5py.ExternalLink("x.h5", "/"))),
             "/extra is an external link")
    path.write_bytes(copy.read_bytes())
    raw = tmp_path / "raw.bin"
    raw.write_bytes(np.zeros(3).tobytes())

    def external_storage(f):
        del f["blocks/m2"]
        f["blocks"].create_dataset("m2", shape=(3, 1), dtype="f8",
                                   external=[(str(raw), 0, 24)])

    _refused(_edit(path, external_storage), "/blocks/m2 keeps its data in external file")


def test_checksum_detects_changed_bytes(tmp_path, rng):
    path = _zernike3(tmp_path, rng)
    with h5py.File(path, "r") as f:
        where = f["blocks/m1"].id.get_chunk_info(0).byte_offset
    data = bytearray(path.read_bytes())
    data[where + 5] ^= 0x10  # one bit of one coefficient
    path.write_bytes(bytes(data))
    _refused(path, "/blocks/m1 cannot be read .its Fletcher-32 checksum does not match")


def _set_attr(name, value, where="/"):
    def change(f):
        f[where].attrs[name] = value
    return change


def _replace(name, **kwargs):
    def change(f):
        del f[name]
        f.create_dataset(name, **kwargs)
    return change


def _json(text):
    return _set_attr("info", text)


# (edit of the valid HemiZernike(3) file, what the message says)
DAMAGE = [
    (_set_attr("basis_order", "3"), "/@basis_order must be an integer, got str '3'"),
    (_set_attr("basis_order", 3.0), "/@basis_order must be an integer, got float"),
    (_set_attr("channels", [3, 3]), "/@channels must be an integer, got an array of int64"),
    (_set_attr("channels", 0), "/@channels is 0, expected >= 1"),
    (_set_attr("scalar", "no"), "/@scalar must be a boolean"),
    (_set_attr("quantity", "radiance"), "/@quantity is 'radiance', expected one of 'f', 'f_cos'"),
    (_set_attr("storage", 7), "/@storage must be a string, got int64 7"),
    (_set_attr("dtype", "float128"), "/@dtype is 'float128', expected one of"),
    (_set_attr("dtype", "float32"), "/blocks/m0 holds float64, expected float32"),
    (_set_attr("content", "movie"), "/@content is 'movie', expected one of"),
    (_set_attr("basis_kind", b"\xff\xfe"), "/@basis_kind is not UTF-8 text"),
    (lambda f: f.attrs.__delitem__("quantity"), "the attribute /@quantity is missing"),
    (_replace("blocks/m1", data=np.zeros((3, 3), np.int64)), "/blocks/m1 holds int64, "
                                                             "expected float64"),
    (_replace("blocks/m1", data=np.full((3, 3), b"x")), "/blocks/m1 holds |S1"),
    (_replace("blocks/m1", data=np.zeros((3, 4))), r"/blocks/m1 has shape \(3, 4\), the "
                                                   r"schema needs \(3, 3\)"),
    (_replace("blocks/m1", data=np.zeros(9)), r"/blocks/m1 has shape \(9,\)"),
    (_replace("blocks/m1", data=np.zeros((3, 3)), compression="gzip"), "uses HDF5 filters"),
    (_replace("blocks/m1", shape=(3, 3), dtype="f8"), "/blocks/m1 should hold 72 bytes but "
                                                      "the file stores 0"),
    (lambda f: f.__delitem__("blocks"), "/blocks is missing"),
    (lambda f: f.__delitem__("blocks/m3"), "should hold datasets m0..m3 .*; missing m3"),
    (lambda f: f["blocks"].create_dataset("m9", data=np.zeros((3, 1))), "unexpected m9"),
    (lambda f: f["blocks"].create_group("m1x"), "unexpected m1x"),
    (_json("{not json"), "/@info is not valid info JSON"),
    (_json("[1, 2]"), "/@info must hold a JSON object, got list"),
    (_json("[" * 100_000 + "]" * 100_000), "/@info is not valid info JSON"),
    (_json('{"a": {"__ndarray__": [1], "dtype": "O", "shape": [1]}}'), "not valid info JSON"),
    (_json('{"a": {"__ndarray__": [1, 2], "dtype": "<f8", "shape": [3]}}'),
     "malformed __ndarray__"),
    (_json('{"a": {"__float__": "1e999"}}'), "malformed __float__"),
    (_set_attr("format", 3), "not a scatmodes file .format attribute int64 3"),
    (_set_attr("schema_version", "3"), "schema version str '3'; .* upgrade scatmodes"),
    (_set_attr("schema_version", 2), "/blocks/m0 .*"),  # schema 2 has no checksums: fine,
]


@pytest.mark.parametrize("change, match", DAMAGE)
def test_damaged_metadata(tmp_path, rng, change, match):
    path = _edit(_zernike3(tmp_path, rng), change)
    if match == "/blocks/m0 .*":  # a file relabelled as schema 2 still loads
        assert load(path).basis == basis.HemiZernike(3)
        return
    _refused(path, match)


def test_sizes_attribute_must_agree(tmp_path, rng):
    path = _edit(_zernike3(tmp_path, rng), _set_attr("sizes", [2, 2, 1, 2], "blocks"))
    _refused(path, r"/blocks/@sizes is an array of int64 with shape \(4,\), zernike order 3 "
                   r"has the block sizes \[2, 2, 1, 1\]")


def test_hybrid_parts_must_agree(tmp_path, rng):
    h = Hybrid(_ggx(), _iso(basis.HemiZernike(2), rng, 3, quantity="f"))
    path = save(h, tmp_path / "h.h5")

    def two_channels(f):  # a valid 2-channel lobe against a 3-channel residual
        for name in ("kd", "ks"):
            del f[f"lobe/params/{name}"]
            d = f.create_dataset(f"lobe/params/{name}", data=[0.5, 0.5], fletcher32=True)
            d.attrs["shape"] = [2]

    _refused(_edit(path, two_channels), "its content is inconsistent: lobe and residual "
                                        "channels must match or one be 1, got 2 and 3")
    path = save(h, tmp_path / "h.h5")
    _refused(_edit(path, _set_attr("family", "phong", "lobe")),
             "/lobe/@family is 'phong', which this library does not know")
    path = save(h, tmp_path / "h.h5")
    _refused(_edit(path, _set_attr("shape", [4], "lobe/params/kd")),
             r"/lobe/params/kd has shape \(3,\), the schema needs \(4,\)")
    path = save(h, tmp_path / "h.h5")
    _refused(_edit(path, lambda f: f.__delitem__("lobe/params/f0")),
             "content is inconsistent: params of family 'lambert.ggx' must be exactly")


# -- fuzz: damaged variants of valid files ----------------------------------------------------
def _same(a, b) -> bool:
    """True if two loaded objects hold the same numbers, family and info keys."""
    if type(a) is not type(b):
        return False
    if isinstance(a, Hybrid):
        return _same(a.lobe, b.lobe) and _same(a.residual, b.residual)
    if isinstance(a, CoefficientMatrix):
        return (a.basis == b.basis and a.quantity == b.quantity
                and np.array_equal(a.matrix, b.matrix) and a.info.keys() == b.info.keys())
    return (a.family == b.family and a.params.keys() == b.params.keys()
            and all(np.array_equal(a.params[k], b.params[k]) for k in a.params))


def _finite(obj) -> bool:
    if isinstance(obj, Hybrid):
        return _finite(obj.lobe) and _finite(obj.residual)
    if isinstance(obj, CoefficientMatrix):
        return bool(np.all(np.isfinite(obj.matrix)))
    return all(np.all(np.isfinite(v)) for v in obj.params.values())


def _structure(path):
    """(attribute owners with their attribute names, dataset paths) of a file."""
    owners, datasets = {"/": list(h5py.File(path, "r").attrs)}, []
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            owners["/" + name] = list(obj.attrs)
            if isinstance(obj, h5py.Dataset):
                datasets.append("/" + name)
        f.visititems(visit)
    return owners, datasets


def _edits(path):
    """(label, change) pairs: every attribute made wrong, every dataset broken."""
    owners, datasets = _structure(path)
    bad_values = ["x", 2**40, np.array([1, 2])]
    for owner, names in owners.items():
        for name in names:
            for v in bad_values:
                yield f"{owner}@{name}={v!r}", _set_attr(name, v, owner)
            yield f"del {owner}@{name}", lambda f, o=owner, n=name: f[o].attrs.__delitem__(n)
    for content in ("coefficients", "model", "hybrid"):
        yield f"content={content}", _set_attr("content", content)
    for owner, names in owners.items():  # plausible values that contradict the datasets
        if "basis_order" in names:
            for name, v in [("scalar", True), ("channels", 1), ("channels", 4),
                            ("basis_order", 4), ("basis_order", 1), ("basis_kind", "sh"),
                            ("basis_kind", "harmonics"), ("storage", "dense")]:
                yield f"{owner}@{name}={v!r}", _set_attr(name, v, owner)
    for i, d in enumerate(datasets):
        other = datasets[(i + 1) % len(datasets)]

        def reshape(f, d=d):
            x = f[d][()]
            del f[d]
            f.create_dataset(d, data=np.concatenate([x, x[..., :1]], axis=-1))
            f[d].attrs["shape"] = [x.shape[-1] + 1]

        def fill(value, d=d):
            return lambda f: f[d].write_direct(np.full(f[d].shape, value, f[d].dtype))

        def relink(link, d=d):
            def change(f):
                del f[d]
                f[d] = link
            return change

        yield f"{d} as int", lambda f, d=d: _replace(d, data=f[d][()].astype(np.int64))(f)
        yield f"{d} reshaped", reshape
        yield f"del {d}", lambda f, d=d: f.__delitem__(d)
        yield f"{d} -> soft link to {other}", relink(h5py.SoftLink(other))
        yield f"{d} -> external link", relink(h5py.ExternalLink(str(path), d))

        def virtual(f, d=d):
            shape, dtype = f[d].shape, f[d].dtype
            layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
            layout[...] = h5py.VirtualSource(str(path), d, shape=shape)
            del f[d]
            f.create_virtual_dataset(d, layout)

        def external_storage(f, d=d):
            x = f[d][()]
            raw = path.with_name(path.name + d.replace("/", "_") + ".bin")
            raw.write_bytes(x.tobytes())
            del f[d]
            f.create_dataset(d, shape=x.shape, dtype=x.dtype, external=[(str(raw), 0, x.nbytes)])

        yield f"{d} -> virtual dataset", virtual
        yield f"{d} -> external storage", external_storage
        yield f"reference to {d}", lambda f, d=d: f.create_dataset("ref", data=f[d].ref,
                                                                   dtype=h5py.ref_dtype)
        yield f"region reference to {d}", lambda f, d=d: f.create_dataset(
            "ref", data=f[d].regionref[:1], dtype=h5py.regionref_dtype)
        yield f"attribute reference to {d}", lambda f, d=d: f.attrs.__setitem__("ref", f[d].ref)
        yield f"{d} compressed", lambda f, d=d: _replace(d, data=f[d][()], compression="gzip")(f)
        yield f"{d} nan", fill(np.nan)
        yield f"{d} huge", fill(1.7e308)


_CONTENT = {"matrix": "coefficients", "model": "model", "hybrid": "hybrid"}


def test_fuzz_damaged_files_never_load_wrong(tmp_path, rng):
    # Variants of three valid files (a matrix, a model, a hybrid): bytes flipped at random
    # offsets, truncations, and every attribute and dataset made wrong through h5py. A load
    # either returns exactly what was saved (a flipped byte in unused space) or raises
    # ValueError naming the file (OSError for I/O); never another exception, never other
    # numbers. Only files written by save are fuzzed: schema 1 and 2 files have no metadata
    # checksums, and the HDF5 library itself may crash on some damaged bytes of those.
    fuzz = np.random.default_rng(14)
    originals = {
        "matrix": CoefficientMatrix.from_blocks(
            basis.HemiZernike(3), _iso(basis.HemiZernike(3), rng, 3).blocks, "f_cos",
            info={"source": "fuzz", "errors": np.arange(3.0)}),
        "model": _lafortune(),
        "hybrid": Hybrid(_ggx(), _iso(basis.HemiZernike(2), rng, 3, quantity="f"),
                         {"l2": 0.5}),
    }
    outcomes: dict[str, dict[str, int]] = {}
    wrong = []
    variant = tmp_path / "variant.h5"

    def attempt(group, label, obj, *, must_fail=False):
        try:
            back = load(variant)
        except ValueError as exc:
            outcome = "ValueError"
            if repr(str(variant)) not in str(exc):
                wrong.append(f"{label}: message without the file name: {exc}")
        except OSError:
            outcome = "OSError"
        except Exception as exc:  # noqa: BLE001 - the point of the test
            outcome = type(exc).__name__
            wrong.append(f"{label}: {type(exc).__name__}: {exc}")
        else:
            outcome = "loaded"
            if must_fail or not _finite(back) or not _same(back, obj):
                wrong.append(f"{label}: loaded {back!r}")
        counts = outcomes.setdefault(group, {})
        counts[outcome] = counts.get(outcome, 0) + 1

    t0 = time.perf_counter()
    for name, obj in originals.items():
        base = save(obj, tmp_path / f"{name}.h5")
        data = base.read_bytes()
        for i in range(50):
            buf = bytearray(data)
            for offset in fuzz.integers(0, len(buf), size=fuzz.integers(1, 9)):
                buf[offset] ^= int(fuzz.integers(1, 256))
            variant.write_bytes(bytes(buf))
            attempt("flipped bytes", f"{name} flip {i}", obj)
        for n in fuzz.integers(0, len(data), size=10):
            variant.write_bytes(data[:n])
            attempt("truncated", f"{name} cut at {n}", obj)
        for label, change in _edits(base):
            variant.write_bytes(data)
            with h5py.File(variant, "r+") as f:
                change(f)
            # information-only and optional attributes may change or go; a change of
            # anything else must be refused
            harmless = ("@library" in label or "/provenance" in label
                        or label == f"content={_CONTENT[name]}" or label.startswith("del ")
                        and label.endswith("@sizes"))
            attempt("h5py edits", f"{name} {label}", obj, must_fail=not harmless)
    seconds = time.perf_counter() - t0
    total = sum(sum(c.values()) for c in outcomes.values())
    print(f"\nfuzz: {total} variants in {seconds:.1f} s: {outcomes}")
    assert not wrong, "\n".join(wrong[:20])
    assert total > 400
    assert outcomes["flipped bytes"]["ValueError"] > 100
    assert outcomes["h5py edits"]["ValueError"] > 200


def test_file_open_for_writing_elsewhere(tmp_path, rng):
    # a writer in another process holds the file (HDF5 file locking and the superblock's
    # open-for-writing mark): load says so instead of calling the file damaged; killed, the
    # writer leaves the mark behind, and the message says how to clear it
    import subprocess
    import sys

    path = _zernike3(tmp_path, rng)
    with subprocess.Popen(
            [sys.executable, "-c", f"import h5py, time; f = h5py.File({str(path)!r}, 'r+'); "
                                   "print('open', flush=True); time.sleep(60)"],
            stdout=subprocess.PIPE, text=True) as holder:
        try:
            assert holder.stdout.readline().strip() == "open"
            with pytest.raises(BlockingIOError, match="is open for writing in another "
                                                      "process; try again"):
                load(path)
        finally:
            holder.kill()
    with pytest.raises(BlockingIOError, match="a writer crashed: 'h5clear -s FILE' removes "
                                              "the mark"):
        load(path)


# -- general (non-reciprocal) matrices: schema 4 ------------------------------------------------
@pytest.mark.parametrize("storage", ["isotropic", "dense"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_general_matrix_round_trips_bit_for_bit(tmp_path, rng, storage, dtype):
    b = basis.HemiZernike(4)
    if storage == "isotropic":
        blocks = [rng.normal(size=(3, i.size, i.size)) for i in b.azimuthal_blocks().cos]
        cm = CoefficientMatrix.from_blocks(b, blocks, "f", reciprocal=False)
    else:
        cm = CoefficientMatrix(b, rng.normal(size=(3, b.size, b.size)), "f", isotropic=False,
                               reciprocal=False)
    cm = CoefficientMatrix(b, cm.matrix.astype(dtype).astype(np.float64), "f",
                           isotropic=storage == "isotropic", reciprocal=False)
    p = save(cm, tmp_path / "g.h5", dtype=dtype)
    with h5py.File(p, "r") as f:
        assert not f.attrs["reciprocal"]
        # whole blocks, k_m^2 numbers: k_m = 3, 2, 2, 1, 1 (dense: 15^2)
        if storage == "isotropic":
            assert f["blocks/m0"].shape == (3, 9) and f["blocks/m1"].shape == (3, 4)
        else:
            assert f["matrix"].shape == (3, b.size**2)
    back = load(p)
    assert not back.reciprocal and back.is_isotropic == (storage == "isotropic")
    # values representable in the dtype: exact round trip
    assert np.array_equal(back.matrix, cm.matrix)


def test_general_hybrid_residual_round_trips(tmp_path, rng):
    b = basis.HemiZernike(3)
    blocks = [rng.normal(size=(3, i.size, i.size)) for i in b.azimuthal_blocks().cos]
    res = CoefficientMatrix.from_blocks(b, blocks, "f", reciprocal=False)
    back = load(save(Hybrid(_ggx(), res), tmp_path / "h.h5"))
    assert not back.residual.reciprocal
    assert np.array_equal(back.residual.matrix, res.matrix)


def test_schema_3_file_loads_as_reciprocal(tmp_path, rng):
    # a schema-3 file is a schema-4 file without the reciprocal attribute
    cm = _iso(basis.HemiZernike(3), rng, 3)
    p = save(cm, tmp_path / "v3.h5")
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = 3
        del f.attrs["reciprocal"]
    back = load(p)
    assert back.reciprocal and np.array_equal(back.matrix, cm.matrix)


def test_schema_4_needs_the_reciprocal_flag(tmp_path, rng):
    p = save(_iso(basis.HemiZernike(2), rng, 1), tmp_path / "r.h5")
    with h5py.File(p, "r+") as f:
        del f.attrs["reciprocal"]
    with pytest.raises(ValueError, match="reciprocal"):
        load(p)
    with h5py.File(p, "r+") as f:
        f.attrs["reciprocal"] = "yes"
    with pytest.raises(ValueError, match="reciprocal must be a boolean"):
        load(p)


@pytest.mark.parametrize("version", [4, 5])
def test_schema_4_and_5_files_still_load(tmp_path, rng, version):
    """Schemas 5 and 6 only add the "tucker" and "grid" families: a file that says 4 or 5
    reads as before."""
    cm = _iso(basis.HemiZernike(3), rng, 3)
    p = save(cm, tmp_path / "v.h5")
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = version
    assert np.array_equal(load(p).matrix, cm.matrix)
