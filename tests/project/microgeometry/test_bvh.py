"""bvh.py: meshes and OBJ input, and the BVH -- triangles, x/y cylinders, spheres and finite
tubes (with or without caps) against brute force, the outer side of every primitive, the
periodic tiling, the SAH build and its stack-depth guarantee, and bad input.

References are independent numpy brute force: every ray against every primitive (Cramer's
rule for triangles, textbook quadratics solved in a local frame of each primitive -- not the
cross-product form of the kernels --, discs by a plane test), with the periodic copies laid
out explicitly. Distances agree to ~1e-10 (both sides round at ~1e-15 relative on distances
of order 1; the textbook quadratic loses a few digits to cancellation, whence the margin).
"""

from __future__ import annotations

import numpy as np
import pytest

# private _STACK, _build, _periodic_hit, _prim_bounds: the build's depth guarantee, the
# primitive bounds and the walk's front flag are checked directly
from project.microgeometry.bvh import (
    _STACK,
    BVH,
    CYLINDER,
    SPHERE,
    TRIANGLE,
    TUBE,
    Mesh,
    _build,
    _periodic_hit,
    _prim_bounds,
)

# -- brute-force references -------------------------------------------------------------------

def brute_triangles(o, d, tri):
    """(n,) first hit distance of rays (n, 3) with triangles (T, 3, 3), by Cramer's rule on
    o + t d = v0 + u e1 + v e2 for every pair (a different formulation from the kernel's)."""
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    a = np.stack([np.broadcast_to(-d[:, None], (o.shape[0], tri.shape[0], 3)),
                  np.broadcast_to(e1, (o.shape[0], tri.shape[0], 3)),
                  np.broadcast_to(e2, (o.shape[0], tri.shape[0], 3))], axis=-1)
    rhs = o[:, None] - tri[None, :, 0]
    with np.errstate(all="ignore"):
        sol = np.linalg.solve(a, rhs[..., None])[..., 0]
    t, u, v = sol[..., 0], sol[..., 1], sol[..., 2]
    ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & np.isfinite(t)
    return np.where(ok, t, np.inf).min(axis=1)


def brute_cylinders(o, d, cyl):
    """(n,) first hit distance with open tubes (C, 9) (axis, p, cz, r, lo, hi): every root of
    the circle equation, kept when t > 0 and the point lies inside the cut."""
    best = np.full(o.shape[0], np.inf)
    for axis, p, cz, r, lo, hi, *_ in cyl:
        i, j = (1, 0) if axis == 0 else (0, 1)  # across, along
        a = d[:, i] ** 2 + d[:, 2] ** 2
        b = 2 * ((o[:, i] - p) * d[:, i] + (o[:, 2] - cz) * d[:, 2])
        c = (o[:, i] - p) ** 2 + (o[:, 2] - cz) ** 2 - r * r
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.maximum(disc, 0))
        for t in ((-b - sq) / (2 * a), (-b + sq) / (2 * a)):
            u = o[:, j] + t * d[:, j]
            ok = (disc >= 0) & (t > 0) & (u >= lo) & (u <= hi)
            best = np.where(ok & (t < best), t, best)
    return best


def _nearest(best_t, best_n, t, n, ok):
    take = ok & (t > 0) & (t < best_t)
    best_t = np.where(take, t, best_t)
    best_n = np.where(take[:, None], n, best_n)
    return best_t, best_n


def brute_spheres(o, d, sph):
    """(n,) first hit distance and (n, 3) outward normal of rays with spheres (S, 9)."""
    best_t = np.full(o.shape[0], np.inf)
    best_n = np.zeros((o.shape[0], 3))
    for cx, cy, cz, r, *_ in sph:
        oc = o - [cx, cy, cz]
        a = np.sum(d * d, 1)
        b = 2 * np.sum(oc * d, 1)
        c = np.sum(oc * oc, 1) - r * r
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.maximum(disc, 0))
        for t in ((-b - sq) / (2 * a), (-b + sq) / (2 * a)):
            n = (o + t[:, None] * d - [cx, cy, cz]) / r
            best_t, best_n = _nearest(best_t, best_n, t, n, disc >= 0)
    return best_t, best_n


def brute_tubes(o, d, tub):
    """(n,) first hit distance and (n, 3) outward normal with tubes (T, 9) = (p0, p1, r,
    caps): the ray in a local frame (e1, e2, u) of each tube, the circle x^2 + y^2 = r^2 for
    0 <= z <= L, and the discs z = 0, L when capped."""
    best_t = np.full(o.shape[0], np.inf)
    best_n = np.zeros((o.shape[0], 3))
    for row in tub:
        p0, p1, r, caps = row[0:3], row[3:6], row[6], row[7]
        length = np.linalg.norm(p1 - p0)
        u = (p1 - p0) / length
        h = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
        e1 = h - (h @ u) * u
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        frame = np.stack([e1, e2, u])
        lo_ = (o - p0) @ frame.T
        ld = d @ frame.T
        a = ld[:, 0] ** 2 + ld[:, 1] ** 2
        b = 2 * (lo_[:, 0] * ld[:, 0] + lo_[:, 1] * ld[:, 1])
        c = lo_[:, 0] ** 2 + lo_[:, 1] ** 2 - r * r
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.maximum(disc, 0))
        with np.errstate(all="ignore"):
            for t in ((-b - sq) / (2 * a), (-b + sq) / (2 * a)):
                p = lo_ + t[:, None] * ld
                n = np.column_stack([p[:, 0], p[:, 1], np.zeros_like(t)]) / r @ frame
                ok = (disc >= 0) & (a > 0) & (p[:, 2] >= 0) & (p[:, 2] <= length)
                best_t, best_n = _nearest(best_t, best_n, t, n, ok)
            if caps:
                for z, sign in ((0.0, -1.0), (length, 1.0)):
                    t = (z - lo_[:, 2]) / ld[:, 2]
                    p = lo_ + t[:, None] * ld
                    ok = np.isfinite(t) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= r * r)
                    best_t, best_n = _nearest(best_t, best_n, t, np.broadcast_to(sign * u, p.shape),
                                              ok)
    return best_t, best_n


def random_rays(rng, n, lo, hi):
    o = rng.uniform(lo, hi, (n, 3))
    d = rng.normal(size=(n, 3))
    return o, d / np.linalg.norm(d, axis=1)[:, None]


def random_cylinders(rng, n):
    cyl = np.zeros((n, 9))
    cyl[:, 0] = rng.integers(0, 2, n)
    cyl[:, 1] = rng.uniform(-1, 1, n)
    cyl[:, 2] = rng.uniform(-1, 1, n)
    cyl[:, 3] = rng.uniform(0.05, 0.3, n)
    cyl[:, 4] = rng.uniform(-1.5, 0, n)
    cyl[:, 5] = cyl[:, 4] + rng.uniform(0.2, 2, n)
    return cyl


def random_spheres(rng, n):
    sph = np.zeros((n, 9))
    sph[:, 0:3] = rng.uniform(-1, 1, (n, 3))
    sph[:, 3] = rng.uniform(0.05, 0.4, n)
    return sph


def random_tubes(rng, n, caps):
    """Tubes with random axes, the first three vertical, along x and along y."""
    axis = rng.normal(size=(n, 3))
    axis[:3] = np.eye(3)[[2, 0, 1]]
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    tub = np.zeros((n, 9))
    tub[:, 0:3] = rng.uniform(-1, 1, (n, 3))
    tub[:, 3:6] = tub[:, 0:3] + rng.uniform(0.2, 1.5, n)[:, None] * axis
    tub[:, 6] = rng.uniform(0.05, 0.3, n)
    tub[:, 7] = caps
    return tub


def expected_normal(d, outward):
    """The kernels' normal: the outward one turned to face the ray (front = d.n <= 0)."""
    s = np.where(np.sum(d * outward, 1) <= 0, 1.0, -1.0)
    return s[:, None] * outward


# -- meshes -----------------------------------------------------------------------------------

def test_mesh_keeps_vertices_and_faces():
    m = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    assert m.vertices.shape == (4, 3) and m.faces.dtype == np.int64
    assert m.triangles().shape == (2, 3, 3) and repr(m) == "Mesh(vertices=4, faces=2)"


def test_obj_subset(tmp_path):
    path = tmp_path / "quad.obj"
    path.write_text("# a quad and a triangle\no thing\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                    "vt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 3//1 4\nv 0 0 1\nf -1 1 2\n")
    m = Mesh.from_obj(path)
    # the quad is fanned around its first corner; -1 is the last vertex read (index 4)
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 0, 1]]
    np.testing.assert_array_equal(m.vertices[4], [0, 0, 1])


@pytest.mark.parametrize("vertices, faces, exc, match", [
    ([[0, 0, 0], [1, 0, np.nan], [0, 1, 0]], [[0, 1, 2]], ValueError,
     r"vertices must be finite: 1 of 3 are NaN or inf \(first: vertex 1\)"),
    ([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], ValueError, r"vertices must have shape \(V, 3\)"),
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], ValueError,
     r"non-degenerate triangles: 1 of 1 have zero area \(first: face 0 = \[0, 1, 2\]\)"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 1]], ValueError, r"non-degenerate"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], ValueError,
     r"faces must index vertices 0 \.\. 2: 1 faces do not"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.zeros((0, 3), int), ValueError,
     r"faces must hold at least one triangle"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0.0, 1.0, 2.0]], TypeError,
     r"faces must be integer vertex indices"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2, 0]], ValueError,
     r"faces must have shape \(F, 3\)"),
])
def test_bad_mesh(vertices, faces, exc, match):
    with pytest.raises(exc, match=match):
        Mesh(vertices, faces)


@pytest.mark.parametrize("text, match", [
    ("v 0 0 0\nv 1 0 0\n", r"at least one f line"),
    ("v 0 0\nf 1 1 1\n", r"v line must hold three numbers"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"f line must have >= 3 corners"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"OBJ vertex indices start at 1"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf a b c\n", r"f line must hold vertex indices"),
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", r"non-degenerate"),
])
def test_bad_obj(tmp_path, text, match):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        Mesh.from_obj(path)



# a unit square (two triangles) used by the OBJ robustness tests below
_SQUARE = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n"


def _obj(tmp_path, data: bytes):
    path = tmp_path / "m.obj"
    path.write_bytes(data)
    return path


def test_obj_byte_order_mark_keeps_the_first_vertex(tmp_path):
    # before: "\ufeffv" was an unknown keyword, the first vertex was skipped and the faces
    # pointed one vertex further (or past the end)
    m = Mesh.from_obj(_obj(tmp_path, b"\xef\xbb\xbf" + _SQUARE))
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_obj_unknown_keywords_latin1_comments_and_continuations(tmp_path):
    data = (b"# caf\xe9 cr\xe9\xe9 par un logiciel\n"      # Latin-1, not UTF-8
            b"o pi\xe8ce\r\n"                            # a Latin-1 name, CRLF
            b"mtllib x.mtl\nusemtl m\nvp 0.5\ncstype bezier\nfoo 1 2 3\nvt 0 0\n"
            b"v 0 0 0 # origine \xe0\n"                 # a trailing comment
            b"v 1 0 0 1.0\n"                             # a weight
            b"v 1 1 0 0.5 0.5 0.5\n"                     # vertex colours
            b"v 0 1 \\\n 0\n"                            # a continued line
            b"f 1/1 2/1 3/1\nf -4 -2 -1 # fan\n")
    m = Mesh.from_obj(_obj(tmp_path, data))
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_obj_number_forms(tmp_path):
    # the forms of C's strtod that OBJ writers use; inf and nan are read, then refused
    data = b"v +1 -0. .5\nv 1e0 2E+1 -3.5e-1\nv 0 1 0\nf 1 2 3\n"
    m = Mesh.from_obj(_obj(tmp_path, data))
    np.testing.assert_array_equal(m.vertices, [[1, -0.0, 0.5], [1, 20, -0.35], [0, 1, 0]])
    with pytest.raises(ValueError, match=r"m\.obj:1: v line must hold finite numbers"):
        Mesh.from_obj(_obj(tmp_path, b"v -Infinity 0 0\n" + _SQUARE))


def test_obj_old_mac_line_ends(tmp_path):
    m = Mesh.from_obj(_obj(tmp_path, _SQUARE.replace(b"\n", b"\r")))
    assert m.faces.tolist() == [[0, 1, 2], [0, 2, 3]]


@pytest.mark.parametrize("data, line, match", [
    # a 20-digit index: OverflowError from numpy before
    (_SQUARE + b"f 1 2 12345678901234567890\n", 7,
     r"refers to vertex 12345678901234567890, but the file defines only 4 vertices"),
    (_SQUARE + b"f 1 2 5\n", 7, r"refers to vertex 5, but the file defines only 4"),
    (_SQUARE + b"f 1 2 -5\n", 7, r"counts back past the first vertex"),
    # the file cut off in the middle of its last record
    (_SQUARE + b"f 1 2", 7, r"f line must have >= 3 corners.*truncated"),
    (_SQUARE + b"f 1 2 3/", 7, None),  # cut inside the last corner: still a valid face
    (b"v 0 0 0\nv 1 0 0\nv 1 1", 3, r"v line must hold three numbers.*truncated"),
    (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nv 0 1", 5, r"three numbers.*truncated"),
    (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nv 0 1 1e", 5, r"three numbers.*truncated"),
    (b"v 0 0 0\nv 1 0 nan\nv 1 1 0\nf 1 2 3\n", 2, r"v line must hold finite numbers"),
    (b"v 0 0 0\nv1.0 0 0\nv 1 1 0\nf 1 2 3\n", 2, r"keyword 'v' must be followed by a space"),
    (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\xe9\n", 4, r"f line must hold vertex indices"),
    (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 1_0\n", 4, r"f line must hold vertex indices"),
    (b"v 0 0 0\nv 1 0 \xe9\nv 1 1 0\nf 1 2 3\n", 2, r"v line must hold three numbers"),
    (b"v 0 0 0\nv 1 0 0\nv 2 0 0\n\nf 1 2 3\n", 5, r"non-degenerate"),
    # before: skipped as unknown keywords, so the faces pointed at other vertices
    (b"v 0 0 0\nV 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\n", 2,
     r"keyword 'V' differs from the OBJ keyword 'v' only in case \(keywords are "
     r"case-sensitive\)"),
    (_SQUARE + b"F 1 2 3\n", 7, r"keyword 'F' differs from the OBJ keyword 'f' only in case"),
    (b"Usemtl m\n" + _SQUARE, 1, r"keyword 'Usemtl' differs from the OBJ keyword 'usemtl'"),
    # before: read by Python's float as 10.0, 1.0 and 1.0
    (b"v 0 0 0\nv 1_0 0 0\nv 1 1 0\nf 1 2 3\n", 2, r"v line must hold three numbers"),
    ("v 0 0 0\nv \u0661 0 0\nv 1 1 0\nf 1 2 3\n".encode(), 2, r"v line must hold three"),
    ("v 0 0 0\nv \uff11 0 0\nv 1 1 0\nf 1 2 3\n".encode(), 2, r"v line must hold three"),
], ids=["20-digit", "past-end", "back-past-start", "cut-face", "cut-corner", "cut-vertex",
        "cut-vertex-after-face", "cut-exponent", "nan", "glued", "latin1-index", "underscore",
        "latin1-coordinate", "degenerate", "uppercase-v", "uppercase-f", "mixed-case-usemtl",
        "underscore-coordinate", "arabic-indic-digit", "fullwidth-digit"])
def test_obj_damage_names_file_and_line(tmp_path, data, line, match):
    path = _obj(tmp_path, data)
    if match is None:
        assert Mesh.from_obj(path).faces.shape == (3, 3)
        return
    with pytest.raises(ValueError, match=match) as err:
        Mesh.from_obj(path)
    assert str(err.value).startswith(f"{path}:{line}: ")


def test_obj_binary_garbage_is_a_value_error(tmp_path):
    # a PNG renamed .obj: no v or f record, never a UnicodeDecodeError
    path = _obj(tmp_path, b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe\xfd")
    with pytest.raises(ValueError, match=r"m\.obj must contain at least one f line"):
        Mesh.from_obj(path)


def test_obj_missing_file_is_an_os_error(tmp_path):
    with pytest.raises(OSError, match="nope.obj"):
        Mesh.from_obj(tmp_path / "nope.obj")


def test_obj_fifo_refused(on_fifo):
    # opening a FIFO blocks until a writer appears: refused before it is opened
    with pytest.raises(ValueError, match=r"OBJ file '.*pipe.obj' must be a regular file, got "
                                         r"a FIFO \(named pipe\)"):
        on_fifo(Mesh.from_obj, "pipe.obj")

# -- triangles and cylinders ------------------------------------------------------------------

def test_bvh_triangles_match_brute_force(rng):
    tri = rng.uniform(-1, 1, (300, 1, 3)) + 0.2 * rng.normal(size=(300, 3, 3))
    bvh = BVH(np.full(300, TRIANGLE), tri.reshape(300, 9))
    o, d = random_rays(rng, 3000, -2, 2)
    t, prim, nrm = bvh.intersect(o, d)
    ref = brute_triangles(o, d, tri)
    assert 0.1 < np.isfinite(ref).mean() < 0.9  # a real mix of hits and misses
    np.testing.assert_array_equal(np.isfinite(t), np.isfinite(ref))
    hit = np.isfinite(ref)
    # both solve the same 3x3 system: agreement to ~1e2 eps of the distances (~4)
    np.testing.assert_allclose(t[hit], ref[hit], rtol=0, atol=1e-12)
    # the reported triangle contains the hit point and its normal faces the ray
    e = tri[prim[hit]]
    n = np.cross(e[:, 1] - e[:, 0], e[:, 2] - e[:, 0])
    n /= np.linalg.norm(n, axis=1)[:, None]
    np.testing.assert_allclose(np.abs(np.sum(n * nrm[hit], 1)), 1.0, rtol=0, atol=1e-12)
    assert np.all(np.sum(nrm[hit] * d[hit], 1) < 0)
    assert np.all(prim[~hit] == -1)


def test_bvh_cylinders_match_brute_force(rng):
    cyl = random_cylinders(rng, 40)
    tri = rng.uniform(-1, 1, (50, 1, 3)) + 0.2 * rng.normal(size=(50, 3, 3))
    pt = np.concatenate([np.full(50, TRIANGLE), np.full(40, CYLINDER)])
    bvh = BVH(pt, np.concatenate([tri.reshape(50, 9), cyl]))
    o, d = random_rays(rng, 3000, -2, 2)
    t, prim, nrm = bvh.intersect(o, d)
    ref = np.minimum(brute_triangles(o, d, tri), brute_cylinders(o, d, cyl))
    assert 0.1 < np.isfinite(ref).mean() < 0.95
    np.testing.assert_array_equal(np.isfinite(t), np.isfinite(ref))
    hit = np.isfinite(ref)
    np.testing.assert_allclose(t[hit], ref[hit], rtol=0, atol=1e-11)
    # a cylinder normal is radial: perpendicular to the axis and of length r from it
    c = hit & (prim >= 50)
    assert c.sum() > 100
    p = o[c] + t[c, None] * d[c]
    row = cyl[prim[c] - 50]
    across = np.where(row[:, 0] == 0, p[:, 1], p[:, 0]) - row[:, 1]
    radial = np.stack([np.where(row[:, 0] == 0, 0, across), np.where(row[:, 0] == 0, across, 0),
                       p[:, 2] - row[:, 2]], 1)
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), row[:, 3], rtol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(radial / row[:, 3:4] * nrm[c], 1)), 1.0,
                               rtol=0, atol=1e-9)


def test_bvh_periodic_wrap_matches_explicit_tiles(rng):
    # a bumpy triangle layer over a 2 x 1.5 period, poking out of the box on every side;
    # reference: brute force against explicit copies on a 9 x 9 block of periods
    lx, ly = 2.0, 1.5
    tri = np.column_stack([rng.uniform(-0.3, lx + 0.3, 60), rng.uniform(-0.3, ly + 0.3, 60),
                           rng.uniform(-0.2, 0.2, 60)])[:, None] + \
        0.25 * rng.normal(size=(60, 3, 3))
    cyl = np.array([[0, 0.4, 0.0, 0.15, 0.0, lx, 0, 0, 0], [1, 1.7, 0.1, 0.1, 0.0, ly, 0, 0, 0]])
    pt = np.concatenate([np.full(60, TRIANGLE), np.full(2, CYLINDER)])
    bvh = BVH(pt, np.concatenate([tri.reshape(60, 9), cyl]), period=(lx, ly))
    o = np.column_stack([rng.uniform(-3, 3, 800), rng.uniform(-3, 3, 800), np.full(800, 0.8)])
    d = rng.normal(size=(800, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.3
    d /= np.linalg.norm(d, axis=1)[:, None]
    st, t, prim, _ = bvh.intersect_periodic(o, d)
    tiles_t, tiles_c = [], []
    for kx in range(-4, 5):
        for ky in range(-4, 5):
            tiles_t.append(tri + np.array([kx * lx, ky * ly, 0.0]))
            c = cyl.copy()
            c[0, 1] += ky * ly
            c[0, 4:6] += kx * lx
            c[1, 1] += kx * lx
            c[1, 4:6] += ky * ly
            tiles_c.append(c)
    ref = np.minimum(brute_triangles(o, d, np.concatenate(tiles_t)),
                     brute_cylinders(o, d, np.concatenate(tiles_c)))
    # rays that reach the layer well inside the explicit block
    end = o + np.where(np.isfinite(ref), ref, 0)[:, None] * d
    inside = np.isfinite(ref) & (np.abs(end[:, 0]) < 7) & (np.abs(end[:, 1]) < 5)
    assert inside.sum() > 600
    assert np.all(st[inside] == 0)
    np.testing.assert_allclose(t[inside], ref[inside], rtol=0, atol=1e-10)


def test_bvh_periodic_rays_escape_and_fall_through():
    # one small triangle per period: upward rays escape, rays missing it are lost
    tri = np.array([[0.4, 0.4, 0.0, 0.6, 0.4, 0.0, 0.4, 0.6, 0.0]])
    bvh = BVH([TRIANGLE], tri, period=(1.0, 1.0))
    o = np.array([[0.45, 0.45, 1.0], [3.45, -6.55, 1.0], [0.1, 0.1, 1.0], [0.45, 0.45, 1.0]])
    d = np.array([[0, 0, -1.0], [0, 0, -1.0], [0, 0, -1.0], [0, 0, 1.0]])
    st, t, prim, nrm = bvh.intersect_periodic(o, d)
    assert st.tolist() == [0, 0, 2, 1] and prim.tolist()[:2] == [0, 0]
    np.testing.assert_allclose(t[:2], 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(nrm[:2], [[0, 0, 1], [0, 0, 1]], rtol=0, atol=1e-15)


# -- analytic primitives ----------------------------------------------------------------------

def test_spheres_match_brute_force(rng):
    sph = random_spheres(rng, 60)
    bvh = BVH(np.full(60, SPHERE), sph)
    o, d = random_rays(rng, 4000, -2, 2)
    t, prim, nrm = bvh.intersect(o, d)
    ref, outward = brute_spheres(o, d, sph)
    hit = np.isfinite(ref)
    assert 0.1 < hit.mean() < 0.9  # a real mix of hits and misses, some from inside
    np.testing.assert_array_equal(np.isfinite(t), hit)
    np.testing.assert_allclose(t[hit], ref[hit], rtol=0, atol=1e-10)
    np.testing.assert_allclose(nrm[hit], expected_normal(d[hit], outward[hit]), rtol=0,
                               atol=1e-9)
    # the reported sphere carries the hit point on its surface
    p = o[hit] + t[hit, None] * d[hit]
    np.testing.assert_allclose(np.linalg.norm(p - sph[prim[hit], :3], axis=1),
                               sph[prim[hit], 3], rtol=1e-10)


@pytest.mark.parametrize("caps", [0.0, 1.0])
def test_tubes_match_brute_force(rng, caps):
    tub = random_tubes(rng, 40, caps)
    tub[0, :6] = [3.0, 3.0, 0.0, 3.0, 3.0, 1.0]  # vertical, apart from the others
    bvh = BVH(np.full(40, TUBE), tub)
    o, d = random_rays(rng, 4000, -2, 2)
    # rays along the vertical axis, inside the vertical tube: they meet only its top cap
    d[:20] = [0.0, 0.0, -1.0]
    o[:20, 2] = 3.0
    o[:10, :2] = tub[0, :2] + rng.uniform(-0.03, 0.03, (10, 2))
    t, prim, nrm = bvh.intersect(o, d)
    ref, outward = brute_tubes(o, d, tub)
    hit = np.isfinite(ref)
    assert 0.2 < hit.mean() < 0.95
    np.testing.assert_array_equal(np.isfinite(t), hit)
    np.testing.assert_allclose(t[hit], ref[hit], rtol=0, atol=1e-10)
    np.testing.assert_allclose(nrm[hit], expected_normal(d[hit], outward[hit]), rtol=0,
                               atol=1e-9)
    if caps:  # the vertical rays above the vertical tube land on its top cap
        np.testing.assert_allclose(t[:10], 3.0 - tub[0, 5], rtol=0, atol=1e-14)
        np.testing.assert_array_equal(nrm[:10], np.broadcast_to([0.0, 0.0, 1.0], (10, 3)))
    else:
        assert np.all(prim[:10] != 0)


def test_rays_from_inside_find_the_far_wall_from_behind(rng):
    # one sphere and one capped tube (tilted); origins inside each, random directions
    sph = np.array([[0.3, -0.2, 0.1, 0.7, 0, 0, 0, 0, 0]])
    tub = np.array([[2.0, 0.0, -0.5, 2.4, 0.3, 1.2, 0.25, 1.0, 0]])
    bvh = BVH([SPHERE, TUBE], np.concatenate([sph, tub]))
    n = 2000
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    o_s = sph[0, :3] + 0.69 * u * rng.uniform(0, 1, (n, 1)) ** (1 / 3)
    s = rng.uniform(0.01, 0.99, n)
    axis = tub[0, 3:6] - tub[0, 0:3]
    side = np.cross(axis, u)
    side /= np.linalg.norm(side, axis=1)[:, None]
    o_t = tub[0, :3] + s[:, None] * axis + 0.24 * rng.uniform(0, 1, (n, 1)) * side
    o = np.concatenate([o_s, o_t])
    d = np.concatenate([u, rng.normal(size=(n, 3))])
    d /= np.linalg.norm(d, axis=1)[:, None]
    t, prim, nrm = bvh.intersect(o, d)
    ref_s, out_s = brute_spheres(o[:n], d[:n], sph)
    ref_t, out_t = brute_tubes(o[n:], d[n:], tub)
    np.testing.assert_array_equal(prim, np.repeat([0, 1], n))
    np.testing.assert_allclose(t, np.concatenate([ref_s, ref_t]), rtol=0, atol=1e-10)
    # the wall is met from inside: the normal facing the ray is the inward one
    np.testing.assert_allclose(nrm, -np.concatenate([out_s, out_t]), rtol=0, atol=1e-9)
    # ... and the walk reports front=False (outside rays: front=True)
    pb = BVH([SPHERE, TUBE], np.concatenate([sph, tub]), period=(4.0, 4.0))
    args = (4.0, 4.0, pb.lo[0, 2], pb.hi[0, 2], 1000, pb.lo, pb.hi, pb.link, pb.ptype, pb.pdata)
    for k in range(0, 2 * n, 97):
        st, th, *_, front = _periodic_hit(*o[k], *d[k], *args)
        assert st == 0 and not front and abs(th - t[k]) < 1e-10
    st, th, gx, gy, gz, _, front = _periodic_hit(0.3, -0.2, 3.0, 0.0, 0.0, -1.0, *args)
    assert st == 0 and front and abs(th - 2.2) < 1e-14 and (gx, gy, gz) == (0.0, 0.0, 1.0)


@pytest.mark.parametrize("winding", [1, -1])
def test_triangle_front_follows_winding(winding):
    # counter-clockwise seen from above: winding normal +z, the upper side is the front
    tri = np.array([[0.2, 0.2, 0.5, 0.8, 0.2, 0.5, 0.2, 0.8, 0.5]])
    if winding < 0:
        tri = tri[:, [0, 1, 2, 6, 7, 8, 3, 4, 5]]
    bvh = BVH([TRIANGLE], tri, period=(1.0, 1.0))
    args = (1.0, 1.0, bvh.lo[0, 2], bvh.hi[0, 2], 1000, bvh.lo, bvh.hi, bvh.link, bvh.ptype,
            bvh.pdata)
    down = _periodic_hit(0.3, 0.3, 1.0, 0.0, 0.0, -1.0, *args)
    up = _periodic_hit(0.3, 0.3, 0.0, 0.0, 0.0, 1.0, *args)
    assert down[0] == up[0] == 0 and down[2:5] == (0.0, 0.0, 1.0) and up[2:5] == (0, 0, -1.0)
    assert down[6] == (winding > 0) and up[6] == (winding < 0)


def test_bounds_are_exact(rng):
    # tube boxes: the ends extended by r sqrt(1 - a_k^2) per axis, reached by the rim circles
    tub = random_tubes(rng, 20, 1.0)
    lo, hi = _prim_bounds(np.full(20, TUBE), tub)
    ang = np.linspace(0, 2 * np.pi, 4001)
    for k, row in enumerate(tub):
        u = (row[3:6] - row[0:3]) / np.linalg.norm(row[3:6] - row[0:3])
        e1 = np.cross(u, [0.3, 0.5, 0.7])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        ring = row[6] * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
        pts = np.concatenate([row[0:3] + ring, row[3:6] + ring])
        # sampled every 2 pi / 4000: the extremes are missed by at most r (1 - cos) ~ 3e-7 r
        np.testing.assert_allclose(pts.min(0), lo[k], rtol=0, atol=1e-7)
        np.testing.assert_allclose(pts.max(0), hi[k], rtol=0, atol=1e-7)
        assert np.all(pts.min(0) >= lo[k] - 1e-15) and np.all(pts.max(0) <= hi[k] + 1e-15)


def test_periodic_wrap_matches_explicit_tiles(rng):
    # spheres and tilted tubes (some longer than a period) poking out of a 2 x 1.5 box on
    # every side; reference: brute force against explicit copies on a 9 x 9 block of periods
    lx, ly = 2.0, 1.5
    sph = np.zeros((12, 9))
    sph[:, 0] = rng.uniform(-0.2, lx + 0.2, 12)
    sph[:, 1] = rng.uniform(-0.2, ly + 0.2, 12)
    sph[:, 2] = rng.uniform(-0.2, 0.2, 12)
    sph[:, 3] = rng.uniform(0.1, 0.4, 12)
    tub = np.zeros((10, 9))
    tub[:, 0] = rng.uniform(-0.2, lx + 0.2, 10)
    tub[:, 1] = rng.uniform(-0.2, ly + 0.2, 10)
    tub[:, 2] = rng.uniform(-0.3, 0.0, 10)
    axis = rng.normal(size=(10, 3))
    axis[:, 2] = np.abs(axis[:, 2]) * 0.5
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    tub[:, 3:6] = tub[:, 0:3] + rng.uniform(0.3, 2.5, 10)[:, None] * axis
    tub[:, 6] = rng.uniform(0.05, 0.15, 10)
    tub[:, 7] = np.arange(10) % 2
    bvh = BVH(np.repeat([SPHERE, TUBE], [12, 10]), np.concatenate([sph, tub]),
              period=(lx, ly))
    o = np.column_stack([rng.uniform(-3, 3, 1500), rng.uniform(-3, 3, 1500),
                         np.full(1500, 1.5)])
    d = rng.normal(size=(1500, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.3
    d /= np.linalg.norm(d, axis=1)[:, None]
    st, t, prim, nrm = bvh.intersect_periodic(o, d)
    shifts = np.array([[kx * lx, ky * ly, 0.0] for kx in range(-4, 5) for ky in range(-4, 5)])
    tiles_s = np.concatenate([sph + np.r_[s, 0, 0, 0, 0, 0, 0] for s in shifts])
    tiles_t = np.concatenate([tub + np.r_[s, s, 0, 0, 0] for s in shifts])
    ref_s, n_s = brute_spheres(o, d, tiles_s)
    ref_t, n_t = brute_tubes(o, d, tiles_t)
    ref = np.minimum(ref_s, ref_t)
    outward = np.where((ref_s <= ref_t)[:, None], n_s, n_t)
    end = o + np.where(np.isfinite(ref), ref, 0)[:, None] * d
    inside = np.isfinite(ref) & (np.abs(end[:, 0]) < 7) & (np.abs(end[:, 1]) < 5)
    assert inside.sum() > 400
    assert np.all(st[inside] == 0)
    np.testing.assert_allclose(t[inside], ref[inside], rtol=0, atol=1e-10)
    np.testing.assert_allclose(nrm[inside], expected_normal(d[inside], outward[inside]),
                               rtol=0, atol=1e-9)
    # the primitive index is the input index of the wrapped original
    assert np.all((prim[inside] < 12) == (ref_s[inside] <= ref_t[inside]))


# -- the SAH build ----------------------------------------------------------------------------

def _mixed(rng):
    tri = (rng.uniform(-1, 1, (200, 1, 3)) + 0.2 * rng.normal(size=(200, 3, 3))).reshape(-1, 9)
    cyl = np.zeros((20, 9))
    cyl[:, 0] = rng.integers(0, 2, 20)
    cyl[:, 1:3] = rng.uniform(-1, 1, (20, 2))
    cyl[:, 3] = rng.uniform(0.05, 0.2, 20)
    cyl[:, 4] = rng.uniform(-1.5, 0, 20)
    cyl[:, 5] = cyl[:, 4] + 1.0
    pt = np.repeat([TRIANGLE, CYLINDER, SPHERE, TUBE], [200, 20, 30, 40])
    return pt, np.concatenate([tri, cyl, random_spheres(rng, 30), random_tubes(rng, 40, 1.0)])


def test_sah_and_median_builds_give_the_same_hits(rng):
    pt, pd = _mixed(rng)
    sah = BVH(pt, pd, build="sah")
    med = BVH(pt, pd, build="median")
    assert sah.link.shape != med.link.shape or np.any(sah.link != med.link)  # other trees
    o, d = random_rays(rng, 4000, -2, 2)
    t1, p1, n1 = sah.intersect(o, d)
    t2, p2, n2 = med.intersect(o, d)
    # the same primitive tests on the same rays: bit-identical results
    np.testing.assert_array_equal(t1, t2)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(n1, n2)
    assert 0.2 < np.isfinite(t1).mean() < 0.95
    # every primitive appears exactly once in the leaves of both
    for b in (sah, med):
        leaves = b.link[b.link[:, 1] > 0]
        cover = np.concatenate([np.arange(s, s + c) for s, c in leaves])
        np.testing.assert_array_equal(np.sort(cover), np.arange(pt.size))
        np.testing.assert_array_equal(np.sort(b.source), np.arange(pt.size))


def test_stack_depth_is_guaranteed_on_pathological_input():
    # a line of spheres shrinking geometrically towards x = 0: every SAH split cuts off the
    # few largest, so unconstrained SAH goes deeper than the traversal stack allows
    k = np.arange(1000)
    x = 1.2 ** -k
    sph = np.zeros((1000, 9))
    sph[:, 0] = x
    sph[:, 3] = 0.01 * x
    lo, hi = _prim_bounds(np.full(1000, SPHERE), sph)
    assert _build(lo, hi, "sah", max_depth=10_000)[4] > _STACK  # would overflow
    bvh = BVH(np.full(1000, SPHERE), sph)
    assert bvh.depth <= _STACK - 1
    # rays straight down onto every sphere from twice its radius, the deepest leaves included
    o = np.column_stack([x, np.zeros(1000), 2 * sph[:, 3]])
    d = np.broadcast_to([0.0, 0.0, -1.0], (1000, 3))
    t, prim, _ = bvh.intersect(o, d)
    np.testing.assert_array_equal(prim, k)
    np.testing.assert_allclose(t, sph[:, 3], rtol=1e-14)
    # many identical primitives: no split separates them, median halving keeps it shallow
    same = BVH(np.full(5000, SPHERE), np.tile(sph[:1], (5000, 1)))
    assert same.depth == 11  # ceil(log2(5000 / LEAF))
    t, prim, _ = same.intersect([[1.0, 0.0, 1.0]], [[0.0, 0.0, -1.0]])
    assert abs(t[0] - 0.99) < 1e-15 and 0 <= prim[0] < 5000


# -- bad input --------------------------------------------------------------------------------

def test_bvh_bad_input():
    with pytest.raises(ValueError, match=r"ptype must be TRIANGLE \(0\), .* got 7 at index 1"):
        BVH([SPHERE, 7], np.ones((2, 9)))
    with pytest.raises(ValueError, match=r"build must be one of \('sah', 'median'\), got 'x'"):
        BVH([SPHERE], np.ones((1, 9)), build="x")


def test_bvh_empty_scene_is_refused():
    with pytest.raises(ValueError, match=r"at least one primitive, got none"):
        BVH(np.zeros(0, np.int64), np.zeros((0, 9)))
