"""Measurement text files: table, CSV and Cornell readers, detection, errors, round trips, fuzz.

Files are written here by hand (the Cornell one in the layout of the files pbrt-v2 ships: a
comment header, the wavelength count alone on a line, the wavelengths over two lines, one
sample per line) and expected directions come from explicit sin/cos formulas.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from project import Measurements, read_table
from project.measured import read_measurements, write_measurements


def direction(theta, phi):
    theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)],
                    axis=-1)


WL = np.arange(400.0, 701.0, 50.0)  # 7 wavelengths


def cornell_text(rows: np.ndarray, wl: np.ndarray = WL, name: str = "Test Paint") -> str:
    """A Cornell .brdf file laid out like pbrt-v2's scenes/brdfs files."""
    half = (len(wl) + 1) // 2
    lines = ["# Cornell University, Program of Computer Graphics", f"# {name}",
             "# High-gloss Paint", "", "# num wls", str(len(wl)), "", "# wls",
             " ".join(f"{w:g}" for w in wl[:half]), " ".join(f"{w:g}" for w in wl[half:]), "",
             "# theta i, phi i, theta s, phi_s, spectral sample values", ""]
    lines += [" ".join(f"{x:.6f}" for x in r) for r in rows]
    return "\n".join(lines) + "\n"


@pytest.fixture
def cornell_rows(rng):
    """12 samples: theta_i 10..80 deg at phi_i = 0, as in the real files; values >= 0."""
    n = 12
    ti = np.radians(rng.choice([10.0, 20.0, 40.0, 80.0], n))
    to = rng.uniform(0, 1.38, n)
    po = rng.uniform(-np.pi, np.pi, n)
    vals = rng.uniform(0, 30, (n, WL.size))
    vals[:3, :2] = 0.0
    return np.column_stack([ti, np.zeros(n), to, po, vals])


@pytest.fixture
def cornell_file(tmp_path, cornell_rows):
    p = tmp_path / "paint.brdf"
    p.write_text(cornell_text(cornell_rows))
    return p


# ----------------------------------------------------------------------------------- Cornell
def test_cornell(cornell_file, cornell_rows):
    m = read_measurements(cornell_file)
    r = np.round(cornell_rows, 6)  # the file's printed precision
    assert isinstance(m, Measurements) and len(m) == 12 and m.channels == WL.size
    np.testing.assert_array_equal(m.wavelengths, WL)
    np.testing.assert_array_equal(m.values, r[:, 4:])  # float() of the printed text
    # sin/cos of the printed angles: within an ulp or two of the unit vectors built here
    np.testing.assert_allclose(m.wi, direction(r[:, 0], r[:, 1]), rtol=0, atol=4e-16)
    np.testing.assert_allclose(m.wo, direction(r[:, 2], r[:, 3]), rtol=0, atol=4e-16)
    assert m.isotropic is True and m.name == "paint" and m.source == cornell_file
    assert m.info["format"] == "cornell" and m.info["angles"] == "radians"
    assert "by extension .brdf and content" in m.info["format_detected"]
    assert m.info["description"] == ("Cornell University, Program of Computer Graphics / "
                                     "Test Paint / High-gloss Paint")
    assert m.channel_names[0] == "400 nm"


def test_cornell_one_line_and_other_extension(tmp_path, cornell_rows):
    # pbrt-v2 reads numbers wherever they are: all on one line, after an inline comment
    text = "2 500 600 # wavelengths\n" + " ".join(
        " ".join(repr(float(x)) for x in row[:6]) for row in cornell_rows)
    p = tmp_path / "flat.txt"
    p.write_text(text)
    m = read_measurements(p)
    assert m.info["format"] == "cornell" and m.channels == 2
    np.testing.assert_array_equal(m.values, cornell_rows[:, 4:6])


def test_cornell_negative_values_allowed(tmp_path, cornell_rows):
    cornell_rows[0, 4] = -0.25
    p = tmp_path / "noisy.brdf"
    p.write_text(cornell_text(cornell_rows))
    d = read_measurements(p).describe()
    assert d["negative_values"] == 1 and d["value_range"][0][0] == -0.25


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace("\n7\n", "\n8\n"), r"line 14, column 1: wavelengths must be > 0 and "
                                            r"strictly increasing \(nm\), got 0.5 after 700.0"),
    (lambda t: t.replace("\n7\n", "\n6\n"), r"line 25: the wavelength count 6 \(line 6\) "
                                            r"does not fit the body"),
    (lambda t: t.rsplit(" ", 1)[0] + "\n", r"line 25: the wavelength count 7 \(line 6\) does "
                                           "not fit the body: 131 numbers"),
    (lambda t: t.replace("\n7\n", "\n7.5\n"), "line 6, column 1: the first number must be the "
                                              "wavelength count"),
    (lambda t: t.replace("0.000000", "abc", 1), "line 14, column 2: cell must be a number, "
                                                "got 'abc'"),
    (lambda t: t.replace("0.000000", "nan", 1), "line 14, column 2: cell must be finite"),
    (lambda t: t.replace("\n400 450", "\n400 inf"), "line 9, column 2: cell must be finite"),
    (lambda t: t.replace("\n0.", "\n1.6", 1), r"line 14: theta_i must lie in \[0, pi/2\] "
                                              "radians, got 1.6"),
    (lambda t: "# only comments\n\n", r"holds no data \(line 1 to 2"),
    (lambda t: "", "holds no data"),
], ids=["wl-order", "count-small", "truncated", "count-float", "word", "nan", "inf-wl",
        "theta", "comments", "empty"])
def test_cornell_errors(tmp_path, cornell_rows, edit, match):
    cornell_rows[0, 0] = 0.5
    p = tmp_path / "bad.brdf"
    p.write_text(edit(cornell_text(cornell_rows)))
    with pytest.raises(ValueError, match=match) as info:
        read_measurements(p, "cornell")
    assert "bad.brdf" in str(info.value)


# --------------------------------------------------------------------------------------- CSV
def test_csv_named_columns_and_units(tmp_path):
    p = tmp_path / "gonio.csv"
    p.write_text("# name: blue paint\n# isotropic: false\n"
                 "Theta_In (deg);phi-in [deg];theta_s_deg;PHI_S degrees;sample;weight;wl_450;"
                 "wl_550\n"
                 "30;0;45;180;A;2;0.25;0.5\n"
                 "60;10;0;0;B;0.5;-0.01;0.125\n")
    m = read_measurements(p)
    assert m.name == "blue paint" and m.isotropic is False
    np.testing.assert_array_equal(m.wavelengths, [450, 550])
    assert m.channel_names == ("450 nm", "550 nm")
    np.testing.assert_array_equal(m.values, [[0.25, 0.5], [-0.01, 0.125]])
    np.testing.assert_array_equal(m.weights, [2.0, 0.5])
    np.testing.assert_allclose(m.wi, direction(np.radians([30, 60]), np.radians([0, 10])),
                               rtol=0, atol=4e-16)
    np.testing.assert_allclose(m.wo, direction(np.radians([45, 0]), np.radians([180, 0])),
                               rtol=0, atol=4e-16)
    assert m.info["format"] == "csv" and m.info["format_detected"] == "by extension .csv"
    assert m.info["angles"] == "degrees"
    assert m.info["angles_from"] == "stated in the column names"
    assert m.info["ignored_columns"] == ["sample"]


@pytest.mark.parametrize("header, rows, angles, unit, source", [
    ("theta_i,phi_i,theta_o,phi_o,R,G,B", "30,0,80,90,1,2,3", None, "degrees",
     r"detected: theta up to 80 > pi/2 \(line 2\), read as degrees"),
    ("theta_i,phi_i,theta_o,phi_o,R,G,B", "0.5,0,1.2,3,1,2,3", None, "radians",
     "detected: every theta <= pi/2 \\(max 1.2\\), read as radians; pass angles='degrees'"),
    ("theta_i,phi_i,theta_o,phi_o,R,G,B", "0.5,0,1.2,3,1,2,3", "degrees", "degrees",
     "the angles argument"),
    ("theta_i [rad],phi_i,theta_v,phi_v,R,G,B", "0.5,0,1.2,3,1,2,3", None, "radians",
     r"stated in the column names \(theta_i\), taken for the others"),
    ("theta_i [rad],phi_i,theta_r,phi_r,R,G,B", "0.5,0,1.2,3,1,2,3", "radians", "radians",
     "stated in the column names and the angles argument"),
])
def test_csv_angle_units(tmp_path, header, rows, angles, unit, source):
    p = tmp_path / "a.csv"
    p.write_text(f"{header}\n{rows}\n")
    m = read_measurements(p, angles=angles)
    assert m.info["angles"] == unit and m.channel_names == ("R", "G", "B")
    assert re.match(source, m.info["angles_from"]), m.info["angles_from"]
    theta = np.array([float(x) for x in rows.split(",")[:4]])
    if unit == "degrees":
        theta = np.radians(theta)
    np.testing.assert_allclose(m.wo, direction(theta[2:3], theta[3:4]), rtol=0, atol=4e-16)


def test_csv_mixed_units_per_column(tmp_path):
    p = tmp_path / "mixed.csv"
    p.write_text("theta_i_deg,phi_i_rad,theta_o_deg,phi_o_rad,f\n30,0.5,60,-1,0.3\n")
    m = read_measurements(p)
    assert m.info["angles"] == {"theta_i": "degrees", "phi_i": "radians",
                                "theta_o": "degrees", "phi_o": "radians"}
    np.testing.assert_allclose(m.wi, direction([np.radians(30)], [0.5]), rtol=0, atol=4e-16)
    assert m.channel_names == ("f",)


def test_csv_quotes_tabs_and_whitespace(tmp_path):
    p = tmp_path / "w.dat"
    p.write_text('"theta_i","phi_i","theta_o","phi_o","red, linear"\n1,0,2,0,0.5\n')
    m = read_measurements(p)
    assert m.channel_names == ("red, linear",) and m.info["format"] == "csv"
    assert m.info["format_detected"] == "by content: a header row (line 1)"
    p.write_text("theta_i\tphi_i\ttheta_o\tphi_o\tf 1\n1\t0\t2\t0\t0.5\n")
    assert read_measurements(p).channel_names == ("f 1",)
    p.write_text("theta_i phi_i theta_o phi_o 450nm 500\n1 0 2 0 0.5 0.25\n")
    np.testing.assert_array_equal(read_measurements(p).wavelengths, [450, 500])


@pytest.mark.parametrize("text, kwargs, match", [
    ("theta_i,phi_i,theta_o,f\n1,2,3,4\n", {}, r"line 1: the header must name the angle "
                                                r"columns .* missing phi_o"),
    ("theta_i,phi_i,theta_o,phi_o,theta_in,f\n1,2,3,4,5,6\n", {},
     "line 1, column 5: theta_i must be given once"),
    ("theta_i,phi_i,theta_o,phi_o\n1,2,3,4\n", {}, "line 1: the file must hold at least one "
                                                   "numeric value column"),
    ("theta_i,phi_i,theta_o,phi_o,f\n", {}, "line 1: the file must hold at least one data row"),
    ("theta_i,phi_i,theta_o,phi_o,f\n1,2,3,4\n", {}, "line 2: every row must have 5 cells"),
    ("theta_i,phi_i,theta_o,phi_o,f\n1,2,3,4,5\n1,2,3,4,x\n", {},
     "line 3, column 5: cell must be a number, got 'x'"),
    ("theta_i,phi_i,theta_o,phi_o,f\n1,2,3,4,inf\n", {}, "line 2, column 5: cell must be finite"),
    ("theta_i,phi_i,theta_o,phi_o,f\n1,2,3,4,5\n91,0,3,4,5\n", {},
     r"line 3, column 1: theta_i must lie in \[0, 90\] degrees, got 91.0"),
    ("phi_o,theta_o,phi_i,theta_i,f\n0,-0.1,0,0.2,1\n", {},
     r"line 2, column 2: theta_o must lie in \[0, pi/2\] radians, got -0.1"),
    ("theta_i_deg,phi_i,theta_o,phi_o,f\n1,2,3,4,5\n", {"angles": "radians"},
     r"line 1: angles='radians' contradicts the unit stated in the header for theta_i"),
    ("theta_i_deg,phi_i_rad,theta_o,phi_o,f\n1,2,3,4,5\n", {},
     "line 1: the header states both degrees and radians"),
    ("theta_i,phi_i,theta_o,phi_o,600nm,500nm\n1,2,3,4,5,6\n", {},
     "line 1, column 6: wavelength columns must be strictly increasing"),
    ("theta_i,phi_i,theta_o,phi_o,f,weight\n1,2,3,4,5,-1\n", {},
     "line 2, column 6: weight must be >= 0, got -1.0"),
    ("theta_i,phi_i,theta_o,phi_o,f,weight\n1,2,3,4,5,0\n", {},
     "line 1: the weights must not all be zero"),
    ("theta_i,phi_i,theta_o,phi_o,f,f\n1,2,3,4,5,6\n", {},
     "line 1, column 6: channel names must be distinct, got 'f' twice"),
    ("# header only\n", {}, r"holds no data \(line 1 to 1"),
])
def test_csv_errors(tmp_path, text, kwargs, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        read_measurements(p, **kwargs)
    assert "bad.csv" in str(info.value)


# ------------------------------------------------------------------------------------- table
def test_table_reads_like_read_table(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# theta_i phi_i theta_o phi_o R G B\n"
                 "30 0 45 180 0.1 0.2 0.3\n"
                 "60, 10, 0, 0, 0.4, -0.5, 0.6\n")
    m = read_measurements(p)
    wi, wo, values = read_table(p)
    np.testing.assert_array_equal(m.wi, wi / np.linalg.norm(wi, axis=1, keepdims=True))
    np.testing.assert_array_equal(m.values, values)
    assert m.channel_names == ("R", "G", "B") and m.isotropic is None
    assert m.info["format"] == "table" and m.info["angles"] == "degrees"
    assert m.info["format_detected"] == "by content: numeric rows"


@pytest.mark.parametrize("text, match", [
    ("30 0 45 180\n", "t.txt', line 1: a row must have 5 columns"),
    ("30 0 45 180 1\n30 0 45 180 1 2 3\n", "t.txt', line 2: every row must have 5 columns"),
    ("95 0 45 180 1\n", r"t.txt', line 1: theta_i must lie in \[0, 90\] degrees"),
])
def test_table_errors(tmp_path, text, match):
    p = tmp_path / "t.txt"
    p.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_measurements(p, "table")


@pytest.mark.parametrize("first", ["inf", "1e999", "-inf"])
@pytest.mark.parametrize("rest", [" 0 45 180 1\n", "\n"], ids=["row", "alone"])
def test_first_number_not_finite(tmp_path, first, rest):
    # format detection once took int() of the first number: OverflowError on inf
    p = tmp_path / "t.txt"
    p.write_text(first + rest)
    with pytest.raises(ValueError, match=f"'{p}', line 1") as info:
        read_measurements(p)
    assert "must be finite" in str(info.value) or "must have 5 columns" in str(info.value)


@pytest.mark.parametrize("fmt, text", [
    ("table", "# theta_i phi_i theta_o phi_o R G B\n30 0 45 180 0.1 0.2 0.3\n"),
    ("table", "30 0 45 180 0.1 0.2 0.3\n"),
    ("csv", "theta_i [deg],phi_i [deg],theta_o [deg],phi_o [deg],R\n30,0,45,180,0.1\n"),
    ("cornell", "1\n500\n0.5 0 0.7 3.1 0.1\n"),
])
def test_byte_order_mark(tmp_path, fmt, text):
    """A UTF-8 byte-order mark is skipped in every format, detected or given."""
    plain, marked = tmp_path / "plain.txt", tmp_path / "marked.txt"
    plain.write_text(text)
    marked.write_bytes(b"\xef\xbb\xbf" + text.encode())
    for given in (None, fmt):
        a, b = read_measurements(plain, given), read_measurements(marked, given)
        assert b.info["format"] == fmt
        np.testing.assert_array_equal(b.values, a.values)  # the same text: bit for bit
        np.testing.assert_array_equal(b.wi, a.wi)
    if fmt == "table":
        np.testing.assert_array_equal(read_table(marked)[2], read_table(plain)[2])


@pytest.mark.parametrize("cell", ["1_5", "0.1_5", "1e1_0", "\u0661", "\u0663\u0660",
                                  "\uff11", "1\u0665"],
                         ids=["underscore", "fraction", "exponent", "arabic-indic",
                              "arabic-indic-2", "fullwidth", "mixed"])
@pytest.mark.parametrize("fmt, text, line", [
    ("table", "30 0 45 180 {}\n", 1),
    ("csv", "theta_i,phi_i,theta_o,phi_o,R\n0.5,0,0.7,3,{}\n", 2),
    ("cornell", "1\n500\n0.5 0 0.7 3 {}\n", 3),
])
def test_numbers_in_ascii_digits_only(tmp_path, cell, fmt, text, line):
    """float() reads "1_5" as 15 and other scripts' digits: refused, as the OBJ reader does."""
    assert float(cell) >= 0  # what the tables once accepted
    p = tmp_path / "t.txt"
    p.write_text(text.format(cell), encoding="utf-8")
    for given in (None, fmt):
        with pytest.raises(ValueError, match=f"'{p}', line {line}, column 5: cell must be a "
                                             f"number, got '{cell}' \\(ASCII digits only"):
            read_measurements(p, given)


# ------------------------------------------------------------------------ paths and options
def test_bad_paths_and_options(tmp_path, cornell_file):
    with pytest.raises(FileNotFoundError, match="measurement file .*nope.csv' does not exist"):
        read_measurements(tmp_path / "nope.csv")
    with pytest.raises(IsADirectoryError, match="must be a measurement file, got the directory"):
        read_measurements(tmp_path)
    with pytest.raises(ValueError, match="format must be one of 'table', 'csv', 'cornell', "
                                         "got 'xml'"):
        read_measurements(cornell_file, "xml")
    with pytest.raises(ValueError, match="angles must be one of 'degrees', 'radians', got 'deg'"):
        read_measurements(cornell_file, angles="deg")
    with pytest.raises(ValueError, match="the Cornell format holds angles in radians"):
        read_measurements(cornell_file, angles="degrees")
    p = tmp_path / "t.txt"
    p.write_text("1 2 3 4 5\n")
    with pytest.raises(ValueError, match="the table format holds angles in degrees"):
        read_measurements(p, angles="radians")
    p.write_bytes(b"theta_i,phi_i,theta_o,phi_o,f\n1,2,3,4,\xff\n")
    with pytest.raises(ValueError, match=r"t.txt', line 2, byte 9: the file must be UTF-8 "
                                         "text, got byte 0xff"):
        read_measurements(p)


@pytest.mark.parametrize("reader, what", [(read_measurements, "measurement"),
                                          (read_table, "table")])
def test_fifo_refused(on_fifo, reader, what):
    # opening a FIFO blocks until a writer appears: refused before it is opened
    with pytest.raises(ValueError, match=f"{what} file '.*pipe.txt' must be a regular file, "
                                         r"got a FIFO \(named pipe\)"):
        on_fifo(reader, "pipe.txt")


# ------------------------------------------------------------------------------ round trips
@pytest.fixture
def spectral_set(rng):
    n = 25
    ti, to = rng.uniform(0, np.pi / 2, n), rng.uniform(0, np.pi / 2, n)
    ti[0], to[1] = 0.0, np.pi / 2  # the pole and the horizon
    pi, po = rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, n)
    return Measurements(direction(ti, pi), direction(to, po), rng.normal(0.1, 1, (n, 4)),
                        wavelengths=[450.0, 532.5, 600.0, 700.0], isotropic=True,
                        name="round trip")


def assert_same(back, m):
    np.testing.assert_array_equal(back.values, m.values)  # repr-exact: bit for bit
    np.testing.assert_array_equal(back.weights, m.weights)
    # directions are rebuilt from the written angles: a few ulp
    np.testing.assert_allclose(back.wi, m.wi, rtol=0, atol=1e-15)
    np.testing.assert_allclose(back.wo, m.wo, rtol=0, atol=1e-15)
    assert back.name == m.name and back.isotropic == m.isotropic
    assert back.channel_names == m.channel_names


@pytest.mark.parametrize("fmt, suffix", [("csv", ".csv"), ("cornell", ".brdf"),
                                         ("csv", ".txt"), ("cornell", ".dat")])
def test_round_trip_spectral(tmp_path, spectral_set, fmt, suffix):
    p = write_measurements(tmp_path / f"m{suffix}", spectral_set, fmt)
    back = read_measurements(p)
    assert back.info["format"] == fmt
    assert_same(back, spectral_set)
    np.testing.assert_array_equal(back.wavelengths, spectral_set.wavelengths)
    # angles written are read back exactly: a second trip writes the same file
    again = write_measurements(tmp_path / f"again{suffix}", back, fmt)
    assert read_measurements(again).values.tobytes() == back.values.tobytes()


def test_round_trip_csv_weights_and_names(tmp_path, rng):
    n = 10
    ti = rng.uniform(0, 1.5, n)
    m = Measurements(direction(ti, 0.3), direction(ti[::-1], -2.0), rng.normal(size=(n, 2)),
                     weights=rng.uniform(0, 3, n), channel_names=["diffuse", "spec ular"],
                     isotropic=False, name="weighted")
    back = read_measurements(write_measurements(tmp_path / "w.csv", m))
    assert_same(back, m)
    unnamed = read_measurements(write_measurements(tmp_path / "u.csv", _unnamed(m)))
    assert unnamed.name == "u"  # no name: the file's


def _unnamed(m):
    return Measurements(m.wi, m.wo, m.values, weights=m.weights)


@pytest.mark.parametrize("channels", [1, 3])
def test_round_trip_table(tmp_path, rng, channels):
    n = 8
    ti = rng.uniform(0, np.pi / 2, n)
    names = ("0",) if channels == 1 else ("R", "G", "B")
    m = Measurements(direction(ti, 1.0), direction(ti[::-1], -1.0), rng.normal(size=(n, channels)),
                     channel_names=names, name="tab", isotropic=True)
    back = read_measurements(write_measurements(tmp_path / "t.txt", m, "table"))
    assert back.info["format"] == "table"
    assert_same(back, m)


@pytest.mark.parametrize("meas_kwargs, fmt, match", [
    ({"weights": [1.0, 2.0]}, "table", "the table format holds no weights"),
    ({"values": np.ones((2, 2))}, "table", "the table format holds 1 or 3 channels, got 2"),
    ({"values": np.ones((2, 3)), "wavelengths": [1, 2, 3]}, "table", "holds no wavelengths"),
    ({}, "cornell", "the cornell format needs wavelengths"),
    ({"wavelengths": [500], "isotropic": False}, "cornell", "stated anisotropic"),
    ({"channel_names": ["theta_v"]}, "csv", r"channel name 'theta_v' would not read back"),
    ({"channel_names": ["450nm"]}, "csv", r"channel name '450nm' would not read back"),
    ({"name": "a\nb"}, "csv", "meas.name must be one line"),
])
def test_write_refuses_what_the_format_cannot_hold(tmp_path, meas_kwargs, fmt, match):
    kw = {"values": np.ones(2), **meas_kwargs}
    m = Measurements(direction([0.1, 0.2], 0.0), direction([0.3, 0.4], 0.0), kw.pop("values"),
                     **kw)
    with pytest.raises(ValueError, match=match):
        write_measurements(tmp_path / "x", m, fmt)
    assert list(tmp_path.iterdir()) == []


def test_write_bad_arguments(tmp_path, spectral_set):
    with pytest.raises(TypeError, match="meas must be a project.Measurements, got dict"):
        write_measurements(tmp_path / "x.csv", {})
    with pytest.raises(ValueError, match="format must be one of"):
        write_measurements(tmp_path / "x.csv", spectral_set, "json")
    with pytest.raises(IsADirectoryError, match="got the directory"):
        write_measurements(tmp_path, spectral_set)


def test_write_replaces_atomically(tmp_path, spectral_set):
    p = tmp_path / "m.csv"
    p.write_text("old")
    write_measurements(p, spectral_set)
    assert p.read_text().startswith("# scatmodes measurements")
    assert [q.name for q in tmp_path.iterdir()] == ["m.csv"]


# ------------------------------------------------------------------------------------- fuzz
def _check_outcome(path, fmt):
    """Reading either succeeds with finite data or raises ValueError naming file and line."""
    try:
        m = read_measurements(path, fmt)
    except ValueError as exc:
        msg = str(exc)
        assert path.name in msg, msg
        assert "line" in msg, msg
        return "error"
    assert np.isfinite(m.values).all() and np.isfinite(m.wi).all() and np.isfinite(m.wo).all()
    assert np.all(m.wi[:, 2] >= 0) and np.all(m.wo[:, 2] >= 0)
    return "read"


@pytest.mark.parametrize("fmt", ["cornell", "csv", None])
def test_fuzz_truncations_garbage_and_flips(tmp_path, cornell_rows, spectral_set, fmt, rng):
    if fmt == "cornell":
        good = cornell_text(cornell_rows).encode()
        suffix = ".brdf"
    else:
        good = write_measurements(tmp_path / "good.csv", spectral_set).read_bytes()
        suffix = ".csv" if fmt == "csv" else ".dat"
    path = tmp_path / f"fuzz{suffix}"
    outcomes = {"read": 0, "error": 0}
    cases = [good[:k] for k in sorted(set(rng.integers(0, len(good), 40).tolist()))]
    cases += [rng.integers(0, 256, 200, dtype=np.uint8).tobytes(), b"\x00" * 50, b"#",
              b"\n\n\n", b"1", b"theta_i\n", good + b"garbage\n"]
    for _ in range(150):
        b = bytearray(good)
        for i in rng.integers(0, len(b), rng.integers(1, 4)):
            b[i] = int(rng.integers(0, 256))
        cases.append(bytes(b))
    for data in cases:
        path.write_bytes(data)
        outcomes[_check_outcome(path, fmt)] += 1
    assert outcomes["error"] > 0 and outcomes["read"] > 0, outcomes
