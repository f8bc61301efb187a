"""HDF5 files that hold their data in place: the check every HDF5 reader of the library runs.

HDF5 lets a file take its numbers from elsewhere, and h5py follows each of these ways
silently when a dataset is read:

1. soft links (another path of the same file),
2. external links (a path in another file),
3. user-defined links (a link class that HDF5 resolves through a registered callback),
4. virtual datasets (a mapping onto datasets of other files),
5. external raw storage (the dataset's bytes live in other, plain files),
6. filters that HDF5 loads from a plugin (a shared library found through
   ``HDF5_PLUGIN_PATH``; only the filters built into HDF5 and h5py are accepted),
7. object references stored in a dataset,
8. region references stored in a dataset,
9. references stored in an attribute.

A file of this library (:func:`compress.save`, the checkpoints of
:func:`project.microgeometry.simulate`) uses none of them, so a reader that finds one refuses
the file instead of reading another file's numbers. :func:`check_self_contained` walks every
group and dataset of an open file from its metadata alone (no numbers are read) and raises
:class:`Indirection` saying where and what; :func:`check_links` and :func:`check_dataset`
are its steps, for readers that walk a file themselves.
"""

from __future__ import annotations

from typing import Any

import h5py

__all__ = ["BUILTIN_FILTERS", "Indirection", "check_attributes", "check_dataset", "check_links",
           "check_self_contained"]

#: HDF5 filters built into HDF5 and h5py: no plugin is loaded to read them.
BUILTIN_FILTERS = frozenset({
    h5py.h5z.FILTER_DEFLATE, h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_FLETCHER32,
    h5py.h5z.FILTER_SZIP, h5py.h5z.FILTER_NBIT, h5py.h5z.FILTER_SCALEOFFSET,
    h5py.h5z.FILTER_LZF,
})
# a file of this library has a few dozen objects; a walk this long means a hostile file
_MAX_OBJECTS = 100_000


class Indirection(ValueError):
    """A file that takes data from elsewhere; the message says where and how (no file name)."""


def check_self_contained(f: h5py.Group, *,
                         filters: frozenset[int] | None = BUILTIN_FILTERS) -> None:
    """Refuse an open HDF5 file (or group) whose data are not all held in place.

    Parameters
    ----------
    f : h5py.File or h5py.Group
        Walked recursively along its hard links, each object once.
    filters : frozenset of int, optional
        HDF5 filter ids a dataset may use (default: :data:`BUILTIN_FILTERS`); None skips the
        check (the caller checks the filters itself).

    Raises
    ------
    Indirection
        At the first of the nine indirections of the module notes, naming the object's path.
        Also when the file has more than 100,000 objects.
    """
    seen: set[Any] = set()
    pending = [f]
    while pending:
        g = pending.pop()
        for key in check_links(g):
            obj = g[key]
            if obj.id in seen:
                continue
            seen.add(obj.id)
            if len(seen) > _MAX_OBJECTS:
                raise Indirection(f"{g.name} and its subgroups hold more than {_MAX_OBJECTS} "
                                  "objects, far more than a file of this library")
            check_attributes(obj)
            if isinstance(obj, h5py.Group):
                pending.append(obj)
            elif isinstance(obj, h5py.Dataset):
                check_dataset(obj, filters=filters)
    check_attributes(f)


def check_links(g: h5py.Group) -> list[str]:
    """Return the member names of ``g``, refusing soft, external and user-defined links."""
    names = list(g)
    for key in names:
        path = f"{g.name.rstrip('/')}/{key}"
        kind = g.id.links.get_info(key.encode()).type
        if kind == h5py.h5l.TYPE_HARD:
            continue
        if kind == h5py.h5l.TYPE_SOFT:
            link = g.get(key, getlink=True)
            raise Indirection(f"{path} is a soft link to {link.path!r}; the files of this "
                              "library hold their data in place and soft links are not "
                              "followed")
        if kind == h5py.h5l.TYPE_EXTERNAL:
            link = g.get(key, getlink=True)
            raise Indirection(f"{path} is an external link to {link.filename!r}:"
                              f"{link.path!r}; the files of this library are self-contained "
                              "and external links are not followed")
        raise Indirection(f"{path} is a user-defined link (HDF5 link class {int(kind)}); the "
                          "files of this library hold only hard links")
    return names


def check_dataset(d: h5py.Dataset, *,
                  filters: frozenset[int] | None = BUILTIN_FILTERS) -> None:
    """Refuse a virtual dataset, external raw storage, plugin filters and references."""
    path = d.name
    if d.is_virtual:
        raise Indirection(f"{path} is a virtual dataset (its data live in other datasets, "
                          "maybe other files); the files of this library are self-contained")
    plist = d.id.get_create_plist()
    if plist.get_external_count():
        raise Indirection(f"{path} keeps its data in external file(s) "
                          f"{[x[0] for x in d.external or []]!r}; the files of this library "
                          "are self-contained")
    if filters is not None:
        used = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
        other = [x for x in used if x not in filters]
        if other:
            raise Indirection(f"{path} uses the HDF5 filter(s) {other}, which this library "
                              "does not accept (HDF5 would load them from a plugin)")
    what = _reference(d.dtype)
    if what:
        raise Indirection(f"{path} holds {what} (pointers to other data); the files of "
                          "this library hold numbers")


def check_attributes(obj: Any) -> None:
    """Refuse attributes of ``obj`` that hold references to other objects."""
    for key in obj.attrs:
        what = _reference(obj.attrs.get_id(key).dtype)
        if what:
            raise Indirection(f"the attribute {obj.name.rstrip('/')}/@{key} holds {what} "
                              "(pointers to other data); the files of this library hold "
                              "numbers and text")


def _reference(dtype: Any) -> str:
    """'object references', 'region references' or '' for a (possibly compound) dtype."""
    ref = h5py.check_dtype(ref=dtype)
    if ref is h5py.Reference:
        return "object references"
    if ref is h5py.RegionReference:
        return "region references"
    if getattr(dtype, "fields", None):
        for sub, *_ in dtype.fields.values():
            what = _reference(sub)
            if what:
                return what
    base = getattr(dtype, "subdtype", None)
    if base is not None:
        return _reference(base[0])
    vlen = h5py.check_dtype(vlen=dtype)
    if vlen is not None and vlen not in (str, bytes):
        return _reference(vlen)
    return ""
