"""project.hdf5: every way an HDF5 file can take its data from elsewhere is refused, from the
metadata alone, naming the object; files without them pass."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from project.hdf5 import Indirection, check_self_contained


def _plugin_filtered(f, name, data):
    """A chunked dataset with filter 32015 (a plugin id), optional so that writing skips it."""
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk(data.shape)
    dcpl.set_filter(32015, h5py.h5z.FLAG_OPTIONAL)
    space = h5py.h5s.create_simple(data.shape)
    h5py.h5d.create(f.id, name.encode(), h5py.h5t.IEEE_F64LE, space, dcpl=dcpl)
    f[name][...] = data


def indirections(tmp_path):
    """(label, change, message) for each indirection h5py can write, applied to dataset 'x'.

    User-defined links (HDF5 link classes registered by a program) cannot be written with
    h5py; :func:`project.hdf5.check_links` refuses every link type other than hard, soft and
    external.
    """
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as g:
        g["x"] = np.arange(3.0) + 100
    raw = tmp_path / "raw.bin"
    raw.write_bytes((np.arange(3.0) + 200).tobytes())

    def replace(make):
        def change(f):
            del f["x"]
            make(f)
        return change

    def virtual(f):
        layout = h5py.VirtualLayout(shape=(3,), dtype="f8")
        layout[:] = h5py.VirtualSource(str(other), "x", shape=(3,))
        f.create_virtual_dataset("x", layout)

    return [
        ("soft link", replace(lambda f: f.__setitem__("x", h5py.SoftLink("/y"))),
         r"/x is a soft link to '/y'"),
        ("external link",
         replace(lambda f: f.__setitem__("x", h5py.ExternalLink(str(other), "/x"))),
         r"/x is an external link to '.*other\.h5':'/x'"),
        ("external link in a group",
         lambda f: f["g"].__setitem__("e", h5py.ExternalLink(str(other), "/")),
         r"/g/e is an external link"),
        ("virtual dataset", replace(virtual), r"/x is a virtual dataset"),
        ("external storage",
         replace(lambda f: f.create_dataset("x", shape=(3,), dtype="f8",
                                            external=[(str(raw), 0, 24)])),
         r"/x keeps its data in external file\(s\) \['.*raw\.bin'\]"),
        ("plugin filter", replace(lambda f: _plugin_filtered(f, "x", np.arange(3.0))),
         r"/x uses the HDF5 filter\(s\) \[32015\]"),
        ("object references",
         lambda f: f.create_dataset("r", data=f["y"].ref, dtype=h5py.ref_dtype),
         r"/r holds object references"),
        ("region references",
         lambda f: f.create_dataset("r", data=f["y"].regionref[0:1],
                                    dtype=h5py.regionref_dtype),
         r"/r holds region references"),
        ("reference attribute", lambda f: f["y"].attrs.__setitem__("r", f["x"].ref),
         r"the attribute /(y|alias)/@r holds object references"),
    ]


def _file(path):
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3.0)
        f["y"] = np.arange(3.0)
        f["g/h/z"] = np.zeros((2, 2))
        f["g/h/z"].attrs["note"] = "text"
        f.create_dataset("c", data=np.ones(4), compression="gzip", fletcher32=True)
        f["alias"] = f["y"]  # a second hard link: data in place
    return path


def test_plain_file_passes(tmp_path):
    with h5py.File(_file(tmp_path / "a.h5"), "r") as f:
        check_self_contained(f)
        with pytest.raises(Indirection, match=r"/c uses the HDF5 filter\(s\) \[1, 3\]"):
            check_self_contained(f, filters=frozenset())


@pytest.mark.parametrize("case", range(9))
def test_every_indirection_is_refused(tmp_path, case):
    label, change, match = indirections(tmp_path)[case]
    path = _file(tmp_path / "a.h5")
    with h5py.File(path, "r+") as f:
        change(f)
    with h5py.File(path, "r") as f, pytest.raises(Indirection, match=match):
        check_self_contained(f)


def test_hard_link_cycle_ends(tmp_path):
    path = _file(tmp_path / "a.h5")
    with h5py.File(path, "r+") as f:
        f["g/h/up"] = f["g"]  # a group that contains itself
    with h5py.File(path, "r") as f:
        check_self_contained(f)
