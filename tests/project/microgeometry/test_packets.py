"""_packets.py: the packet walk gives the bits of the ray-by-ray walk.

The reference is ``trace._trace_kernel``, which walks one ray at a time through
``_paths._intersect`` (itself checked against closed forms and an independent intersection
in test_paths.py and test_trace.py). Every output of every ray must be equal, bit for bit:
the packet walk runs the same operations in the same order, lane by lane, so any difference
is a fault. Surfaces cover power-of-two and other grid sides (the modulo without a
division), steep slopes (many bounces), flat cells (hits in the first step), lossy Fresnel
mirrors and diffuse facets (roulette), and the bounce and step caps; the lane width is
checked at 2, 4 and 8 in child processes, and the host's width with the other way of
gathering (gather instructions, as with AVX-512, or a load per lane).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from basis import simd
from project.microgeometry import Diffuse, GaussianSurface, Heightfield, Mirror
from project.microgeometry import _packets as pk
from project.microgeometry._paths import _alloc, incident_directions
from project.microgeometry.trace import _run

ROOT = Path(__file__).resolve().parents[3]


def _both(surface, ndirs=40, per=8, seed=3, start=5, **caps):
    dirs = incident_directions(ndirs, np.uint64(seed), 0, True)
    out = []
    for packets in (False, True):
        o = _alloc(ndirs * per)
        _run(surface, dirs, per, np.uint64(seed), start, o, packets=packets, **caps)
        out.append(o)
    return out


def _assert_same(a, b):
    for name, x, y in zip(("directions", "weights", "bounces", "absorbed", "lost"), a, b,
                          strict=True):
        assert np.array_equal(x, y), f"{name} differ in {np.sum(x != y)} entries"


def _random_field(ny, nx, slope, seed):
    rng = np.random.default_rng(seed)
    return Heightfield(slope * rng.standard_normal((ny, nx)), 0.5)


@pytest.mark.parametrize("surface", [
    GaussianSurface(1.0, 6.5, resolution=64, seed=1),  # 2^6 sides, six pyramid levels
    GaussianSurface(1.0, 2.0, resolution=32, seed=2),  # steep: multiple bounces
    _random_field(48, 40, 0.3, 4),  # 48 x 40 -> 24 x 20 -> 12 x 10 -> 6 x 5: not powers of 2
    _random_field(24, 36, 0.4, 5),
    _random_field(7, 9, 0.2, 6),  # odd sides: no level above the cells
    Heightfield(np.zeros((16, 16)), 1.0),  # flat: every cast ends in its first cell
], ids=["gauss64", "steep32", "48x40", "24x36", "7x9", "flat"])
def test_packets_give_the_bits_of_the_ray_walk(surface):
    _assert_same(*_both(surface))


@pytest.mark.parametrize("material", [Mirror(0.18, 3.42), Mirror(1.5, 0.0), Diffuse(0.3)],
                         ids=["metal", "glass-mirror", "diffuse"])
def test_packets_with_absorbing_facets(material):
    # Fresnel weights, diffuse bounces (random directions) and roulette (low weights)
    surface = GaussianSurface(1.0, 3.0, resolution=32, seed=3, material=material)
    a, b = _both(surface)
    _assert_same(a, b)
    assert np.all(a[3] > 0.0)  # every path lost energy to its facets


@pytest.mark.parametrize("caps", [{"max_bounces": 1}, {"max_steps": 3}, {"max_steps": 1}])
def test_packets_at_the_caps(caps):
    # the lost paths of both caps (a hit beyond the bounce cap, a cast cut off in its walk)
    a, b = _both(GaussianSurface(1.0, 2.0, resolution=32, seed=2), **caps)
    _assert_same(a, b)
    assert a[4].sum() > 0


def test_packets_are_independent_of_the_split():
    # one call of all rays vs the same rays in two calls (start offsets): the packets'
    # refill order differs, the paths must not
    surface = GaussianSurface(1.0, 4.0, resolution=32, seed=7)
    dirs = incident_directions(20, np.uint64(1), 0, True)
    whole = _alloc(160)
    _run(surface, dirs, 8, np.uint64(1), 0, whole)
    parts = [_alloc(80), _alloc(80)]
    _run(surface, dirs[:10], 8, np.uint64(1), 0, parts[0])
    _run(surface, dirs[10:], 8, np.uint64(1), 80, parts[1])
    _assert_same(whole, [np.concatenate([p[i] for p in parts]) for i in range(5)])


_CHILD = textwrap.dedent("""
    import numpy as np
    import basis.simd
    import project.microgeometry._packets as pk
    pk.LANES = {lanes}  # before anything compiles: the kernels read these at compile time
    basis.simd.GATHER = {gather}
    from project.microgeometry import GaussianSurface
    from project.microgeometry._paths import _alloc, incident_directions
    from project.microgeometry.trace import _run
    s = GaussianSurface(1.0, 3.0, resolution=48, seed=5)
    d = incident_directions(30, np.uint64(2), 0, True)
    out = []
    for packets in (False, True):
        o = _alloc(240)
        _run(s, d, 8, np.uint64(2), 0, o, packets=packets)
        out.append(o)
    assert all(np.array_equal(x, y) for x, y in zip(*out)), "lanes {lanes}: bits differ"
    print("ok", pk.LANES)
""")


@pytest.mark.parametrize("lanes, gather", [(n, simd.GATHER) for n in sorted({2, 8} - {pk.LANES})]
                         + [(pk.LANES, not simd.GATHER)])
def test_other_lane_widths_give_the_same_bits(lanes, gather, tmp_path):
    # a width other than the host's, or the host's with the other way of gathering (one
    # gather instruction, as with AVX-512, or a load per lane), compiled into an empty cache
    # in a child process
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", _CHILD.format(lanes=lanes, gather=gather)],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["ok", str(lanes)]


def test_lanes_is_the_vector_width():
    assert pk.LANES in (2, 4, 8)


_CROSS = textwrap.dedent("""
    import re
    import numba
    import numpy as np
    from project.microgeometry import _packets as pk
    from project.microgeometry._packets import walk_casts

    @numba.njit(cache=False)
    def walk(C, R, n, h, pyr, G):
        walk_casts(C, R, n, h, pyr, G)

    a2 = numba.float64[:, ::1]
    sig = (a2, a2, numba.int64, a2, numba.float32[::1], numba.float64[::1])
    walk.compile(sig)
    asm = walk.inspect_asm(sig)
    print(pk.LANES, *(len(re.findall(r"\\tv\\w+pd\\t[^\\n]*%" + r, asm)) for r in ("zmm", "ymm")),
          len(re.findall(r"\\tvgatherd", asm)))
""")


@pytest.mark.parametrize("cpu, features, lanes, reg, gathers", [
    ("skylake-avx512", "+avx512f,+avx512dq,+avx512vl,+avx512bw,+avx2,+avx,+fma,+sse4.2", 8,
     "zmm", 5),
    ("haswell", "+avx2,+avx,+fma,+sse4.2", 4, "ymm", 0),
])
def test_packet_step_at_the_width_of_the_target(tmp_path, cpu, features, lanes, reg, gathers):
    # compiled (never run) in a child process whose numba targets the named CPU: the packet
    # holds one register of doubles, and its arithmetic is on that register width; with
    # AVX-512 its five gathers (the pyramid's node, the cell's four corners) are gather
    # instructions
    import platform

    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("numba compiles for the host's architecture: x86-64 needs an x86-64 host")
    env = dict(os.environ, NUMBA_CPU_NAME=cpu, NUMBA_CPU_FEATURES=features,
               NUMBA_CACHE_DIR=str(tmp_path), PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", _CROSS], env=env, capture_output=True, text=True,
                       timeout=600)
    if r.returncode and "No available targets" in r.stderr:
        pytest.skip("this LLVM build has no x86 target")
    assert r.returncode == 0, r.stderr[-2000:]
    got, zmm, ymm, found = (int(x) for x in r.stdout.split())
    assert got == lanes
    assert found == gathers
    wide, other = (zmm, ymm) if reg == "zmm" else (ymm, zmm)
    assert wide > 100 and other < wide // 10, (zmm, ymm)
