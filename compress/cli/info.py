"""``scatmodes info FILE``: what a saved representation, checkpoint or measurement file holds.

:func:`describe` returns a JSON-able dict, :func:`to_text` its human-readable form, and
:func:`run` prints one of them. Measurement files (a text table, CSV or a Cornell ``.brdf``
file, see :func:`project.measured.read_measurements`) are described by
:meth:`project.Measurements.describe`, RGL-EPFL ``.bsdf`` files by the header of
:func:`project.measured.read_rgl`, NVIDIA MDL ``.mbsdf`` files by
:func:`project.measured.read_mbsdf`. A representation (a file of :func:`compress.save`: a
coefficient matrix, a fitted model or a hybrid) is read in full with :func:`compress.load`,
so every check of :mod:`compress.store` applies and a damaged file is reported, not
described. A checkpoint of :func:`project.microgeometry.simulate` (``--checkpoint``) is
described from its attributes and scalar datasets; ``simulate --resume`` verifies it.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["describe", "run", "to_text"]

#: Pairs drawn to estimate the reciprocity of an RGL file (about 0.1 s; standard error ~1 %).
RECIPROCITY_PAIRS = 2**14


class _Damaged(ValueError):
    """A complete message about a damaged checkpoint."""


def run(path: str | os.PathLike, *, as_json: bool = False) -> int:
    """Print the description of ``path`` (text, or JSON with ``as_json``); return 0.

    Raises
    ------
    FileNotFoundError, IsADirectoryError, PermissionError
        The file is missing or cannot be read.
    ValueError
        It is not a scatmodes file or is damaged (the message says how).
    """
    d = describe(path)
    print(json.dumps(d, indent=2) if as_json else to_text(d))
    return 0


def describe(path: str | os.PathLike) -> dict[str, Any]:
    """Describe a file of :func:`compress.save`, a simulation checkpoint or measurements.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    dict
        JSON-able. Always ``path``, ``kind`` (``"representation"``, ``"checkpoint"``,
        ``"measurements"``, ``"rgl"`` or ``"mbsdf"``) and
        ``bytes_on_disk``. A representation adds ``content`` (``"coefficients"``, ``"model"``
        or ``"hybrid"``), ``schema_version``, ``library``, ``dtype``, ``stored_bytes`` (the
        numbers held, at the stored precision) and the description of the object: for a
        matrix ``basis``, ``basis_kind``, ``order``, ``size``, ``quantity``, ``channels``,
        ``scalar``, ``isotropic``, ``unique_coefficients``, ``nbytes`` (held in memory,
        :attr:`basis.CoefficientMatrix.nbytes`), ``info``; for a model
        ``family``, ``nparams``, ``channels``, ``params`` (name to shape), ``info``; for a
        hybrid ``lobe`` and ``residual`` (those two), ``nbytes`` and ``info``. A checkpoint adds
        ``format``, ``directions_done``, ``rays``, ``chunks``, ``seconds``, ``basis``,
        ``matrix_size``, ``surface``, ``incident``, ``targets``, ``chunk``, ``seeds``,
        ``energy`` (reflected, absorbed, lost) and ``sha256`` (whether the checkpoint carries
        a SHA-256 checksum of its content). A measurement file (any file that is neither
        HDF5 nor an RGL tensor file) has kind ``"measurements"`` and the keys of
        :meth:`project.Measurements.describe` (its ``info`` holds the format and how it was
        detected); an RGL ``.bsdf`` file kind ``"rgl"``, with ``name``, ``description``,
        ``channels``, ``channel_names``, ``wavelengths_nm``, ``isotropic``, ``jacobian``,
        ``reduction``, ``theta_i_nodes`` and ``phi_i_nodes``; an MDL ``.mbsdf`` file kind
        ``"mbsdf"``, with ``name``, ``channels``, ``resolution`` ([n_theta, n_phi]),
        ``negative_count``, ``min_value``, ``transmission`` (its resolution or null) and
        ``metadata`` (its lines). The measurement kinds add
        ``reciprocity``: :meth:`project.Reciprocity.describe` of :func:`project.reciprocity`
        without its ``source`` (``residual``, ``floor``, their ``*_stderr``, ``matched``,
        ``tol_deg``, ``bands``, ``channels``, ``samples``, ``note``; NaN as null), on
        :data:`RECIPROCITY_PAIRS` peak-resolving pairs for an RGL file and on the samples
        with a reciprocal twin for measurements; or ``{"error": message}`` when it cannot be
        estimated (e.g. values 0 everywhere).
    """
    from compress.store import file_kind, load

    p = Path(os.fspath(path))
    kind = file_kind(p)
    base = {"path": str(p), "bytes_on_disk": p.stat().st_size}
    if kind == "checkpoint":
        return {**base, "kind": kind, **_checkpoint(p)}
    if kind == "representation":
        obj = load(p)  # every check of compress.store; raises ValueError on anything else
        return {**base, "kind": kind, **_header(p), **_object(obj)}
    if kind == "rgl":
        return {**base, "kind": kind, **_rgl(p)}
    if kind == "mbsdf":
        return {**base, "kind": kind, **_mbsdf(p)}
    # a MERL .binary is described as the measurement table it is not: the reader says so
    return {**base, "kind": "measurements", **_measurements(p)}


# -- measurements -----------------------------------------------------------------------------
def _measurements(p: Path) -> dict[str, Any]:
    from project.measured import read_measurements

    try:
        meas = read_measurements(p)
    except ValueError as exc:
        raise ValueError(f"{str(p)!r} is not an HDF5 file (no HDF5 signature in its first "
                         f"bytes) and cannot be read as measurements: {exc}") from None
    return _plain({**meas.describe(), "reciprocity": _reciprocity(meas)})


def _reciprocity(source: Any) -> dict[str, Any]:
    """:func:`project.reciprocity` of a BRDF or measurements, as a JSON-able dict."""
    from project import reciprocity

    try:
        d = reciprocity(source, n=RECIPROCITY_PAIRS).describe()
    except ValueError as exc:  # e.g. values 0 everywhere: the relative residual is undefined
        return {"error": str(exc)}
    d.pop("source")
    return d


def _rgl(p: Path) -> dict[str, Any]:
    try:
        from project.measured import read_rgl
    except ImportError:  # pragma: no cover - the RGL reader is part of project.measured
        raise ValueError(f"{str(p)!r} is an RGL tensor file, which this installation cannot "
                         "read") from None
    brdf = read_rgl(p)
    wl = getattr(brdf, "wavelengths", None)
    fields = getattr(brdf, "fields", {})
    return _plain({
        "name": brdf.name, "description": getattr(brdf, "description", ""),
        "channels": int(brdf.channels),
        "channel_names": list(getattr(brdf, "channel_names", ())),
        "wavelengths_nm": None if wl is None else [float(wl[0]), float(wl[-1])],
        "isotropic": bool(brdf.isotropic), "jacobian": bool(getattr(brdf, "jacobian", False)),
        "reduction": int(getattr(brdf, "reduction", 1)),
        "theta_i_nodes": int(np.size(fields.get("theta_i", ()))),
        "phi_i_nodes": int(np.size(fields.get("phi_i", ()))),
        "reciprocity": _reciprocity(brdf),
    })


def _mbsdf(p: Path) -> dict[str, Any]:
    from project.measured import read_mbsdf

    brdf = read_mbsdf(p)
    info = brdf.info
    return _plain({
        "name": brdf.name, "channels": int(brdf.channels),
        "resolution": list(info["resolution"]), "negative_count": info["negative_count"],
        "min_value": info["min_value"],
        "transmission": None if info["transmission"] is None else list(info["transmission"]),
        "metadata": list(brdf.metadata), "reciprocity": _reciprocity(brdf),
    })


# -- representations --------------------------------------------------------------------------
def _header(p: Path) -> dict[str, Any]:
    """Header attributes and stored bytes of a file that compress.load has just accepted."""
    import h5py

    def text(v: Any) -> Any:
        return v.decode(errors="replace") if isinstance(v, bytes) else v

    stored = 0
    with h5py.File(p, "r") as f:
        a = f.attrs
        version = int(a["schema_version"])
        out = {"schema_version": version,
               "content": text(a.get("content", "coefficients")),
               "library": text(a.get("library", "unknown")),
               "dtype": text(a.get("dtype", "float64"))}

        def add(_name: str, obj: Any) -> None:
            nonlocal stored
            if isinstance(obj, h5py.Dataset):
                stored += obj.size * obj.dtype.itemsize

        f.visititems(add)
    out["stored_bytes"] = stored
    return out


def _object(obj: Any) -> dict[str, Any]:
    from basis import CoefficientMatrix
    from compress import Hybrid

    if isinstance(obj, Hybrid):
        return {"lobe": _model(obj.lobe), "residual": _matrix(obj.residual),
                "nbytes": int(obj.nbytes), "info": _plain(obj.info)}
    if isinstance(obj, CoefficientMatrix):
        return _matrix(obj)
    return _model(obj)


def _matrix(cm: Any) -> dict[str, Any]:
    from compress import unique_coefficients

    return {"basis": repr(cm.basis), "basis_kind": cm.basis.kind, "order": cm.basis.order,
            "size": cm.basis.size, "quantity": cm.quantity, "channels": cm.channels,
            "scalar": bool(cm.is_scalar), "isotropic": bool(cm.is_isotropic),
            "unique_coefficients": int(unique_coefficients(cm)), "nbytes": int(cm.nbytes),
            "info": _plain(cm.info)}


def _model(m: Any) -> dict[str, Any]:
    return {"family": m.family, "nparams": int(m.nparams), "channels": int(m.channels),
            "params": {k: list(np.shape(v)) for k, v in m.params.items()},
            "nbytes": int(m.nbytes), "info": _plain(m.info)}


# -- checkpoints ------------------------------------------------------------------------------
def _checkpoint(p: Path) -> dict[str, Any]:
    import h5py

    from project.hdf5 import Indirection, check_self_contained

    def damaged(what: str) -> ValueError:
        return _Damaged(f"{str(p)!r} is a damaged simulation checkpoint: {what}; run "
                          "simulate again without --resume")

    try:
        with h5py.File(p, "r") as f:
            try:  # links, virtual datasets, ...: the reads below would use other data
                check_self_contained(f)
            except Indirection as exc:
                raise _Damaged(f"{str(p)!r} is a simulation checkpoint that is refused: {exc}"
                               ) from None
            a = f.attrs

            def attr(name: str, kind: type) -> Any:
                v = a.get(name)
                v = v.decode(errors="replace") if isinstance(v, bytes) else v
                v = v.item() if isinstance(v, np.generic) else v
                if v is None or not isinstance(v, kind) or isinstance(v, bool):
                    raise damaged(f"attribute {name!r} is missing or not a "
                                  f"{kind.__name__} ({v!r})")
                return v

            def scalar(name: str, kind: type) -> Any:
                d = f.get(name)
                if not isinstance(d, h5py.Dataset) or d.shape != () or d.dtype.kind not in "iuf":
                    raise damaged(f"dataset {name!r} is missing or not a number")
                v = d[()].item()
                if not isinstance(v, kind) or not math.isfinite(v):
                    raise damaged(f"dataset {name!r} holds {v!r}")
                return v

            s = f.get("sum")
            if not isinstance(s, h5py.Dataset) or s.ndim != 2 or s.shape[0] != s.shape[1]:
                raise damaged("dataset 'sum' (the accumulated matrix) is missing or not square")
            seeds = a.get("meta_seeds")
            return {
                "format": attr("format", str),
                "directions_done": attr("directions_done", int),
                "rays": scalar("rays", int),
                "chunks": scalar("chunks", int),
                "seconds": float(scalar("seconds", int | float)),
                "basis": attr("meta_basis", str),
                "matrix_size": int(s.shape[0]),
                "surface": attr("meta_surface_repr", str),
                "incident": attr("meta_incident", str),
                "targets": attr("meta_targets", int),
                "chunk": attr("meta_chunk", int),
                "seeds": [int(x) for x in np.atleast_1d(seeds)] if seeds is not None else [],
                "energy": {k: float(scalar(k, int | float))
                           for k in ("reflected", "absorbed", "lost")},
                "sha256": "sha256" in a,
            }
    except _Damaged as exc:
        raise ValueError(str(exc)) from None
    except Exception as exc:  # noqa: BLE001 - h5py raises many types on damaged files
        raise damaged(f"{type(exc).__name__}: {' '.join(str(exc).split())}") from None


# -- text -------------------------------------------------------------------------------------
def to_text(d: dict[str, Any]) -> str:
    """Render a :func:`describe` dict as aligned ``key  value`` lines."""
    lines = []
    if d["kind"] == "measurements":
        return "\n".join(_measurement_lines(d))
    if d["kind"] == "rgl":
        wl = d["wavelengths_nm"]
        lines.append(f"{d['path']}: RGL-EPFL measured BRDF (tensor file), "
                     f"{d['bytes_on_disk']:,} bytes on disk")
        rows = [("name", d["name"]), ("description", _short(d["description"])),
                ("channels", f"{d['channels']} ({_short(d['channel_names'])})"
                 + ("" if wl is None else f", {wl[0]:g}-{wl[1]:g} nm")),
                ("isotropic", "yes" if d["isotropic"] else
                 f"no (azimuthal reduction {d['reduction']})"),
                ("incidence nodes", f"{d['theta_i_nodes']} theta_i x {d['phi_i_nodes']} phi_i"),
                ("jacobian", "yes" if d["jacobian"] else "no"),
                *_reciprocity_rows(d["reciprocity"])]
        return "\n".join(lines + _rows(rows))
    if d["kind"] == "mbsdf":
        n_theta, n_phi = d["resolution"]
        tr = d["transmission"]
        lines.append(f"{d['path']}: NVIDIA MDL measured BSDF (.mbsdf), "
                     f"{d['bytes_on_disk']:,} bytes on disk")
        rows = [("name", d["name"]),
                ("channels", f"{d['channels']} ({'RGB' if d['channels'] == 3 else 'scalar'})"),
                ("grid", f"{n_theta} theta_in x {n_theta} theta_out x {n_phi} delta_phi"),
                ("negative values", f"{d['negative_count']:,} (min {d['min_value']:.3g}; "
                                    "evaluated as 0)"),
                ("transmission", "none" if tr is None else
                 f"{tr[0]} x {tr[0]} x {tr[1]} (kept, not evaluated)"),
                ("metadata", _short(" | ".join(d["metadata"])) if d["metadata"] else "none"),
                *_reciprocity_rows(d["reciprocity"])]
        return "\n".join(lines + _rows(rows))
    if d["kind"] == "checkpoint":
        lines.append(f"{d['path']}: simulation checkpoint ({d['format']}), "
                     f"{d['bytes_on_disk']:,} bytes on disk")
        e = d["energy"]
        rows = [("directions done", d["directions_done"]),
                ("rays traced", f"{d['rays']:,} in {d['chunks']} chunk(s), "
                                f"{d['seconds']:.3g} s"),
                ("basis", f"{d['basis']} ({d['matrix_size']} functions)"),
                ("surface", d["surface"]), ("incident", d["incident"]),
                ("targets", d["targets"]), ("chunk", d["chunk"]),
                ("seeds", ", ".join(map(str, d["seeds"]))),
                ("energy", f"reflected {e['reflected']:.6g}, absorbed {e['absorbed']:.6g}, "
                           f"lost {e['lost']:.6g}"),
                ("sha256", "present (verified by simulate --resume)" if d["sha256"]
                 else "absent")]
        return "\n".join(lines + _rows(rows))
    lines.append(f"{d['path']}: scatmodes {d['content']} (schema {d['schema_version']}, "
                 f"written by {d['library']}), {d['bytes_on_disk']:,} bytes on disk, "
                 f"{d['stored_bytes']:,} bytes of {d['dtype']} numbers")
    if d["content"] == "hybrid":
        lines.append(f"hybrid: {d['nbytes']:,} bytes as float64 (lobe + residual)")
        lines += _rows(_info_rows(d["info"]), indent="  ")
        lines.append("lobe:")
        lines += _rows(_model_rows(d["lobe"]), indent="  ")
        lines.append("residual:")
        lines += _rows(_matrix_rows(d["residual"]), indent="  ")
    elif d["content"] == "model":
        lines += _rows(_model_rows(d))
    else:
        lines += _rows(_matrix_rows(d))
    return "\n".join(lines)


def _measurement_lines(d: dict[str, Any]) -> list[str]:
    info = d["info"]
    wl = d["wavelengths_nm"]
    iso = {True: "yes (as stated)", False: "no (as stated)", None: "not stated"}
    theta_i = d["theta_i_deg"]
    rng = d["value_range"]
    lo = min((r[0] for r in rng), default=float("nan"))
    hi = max((r[1] for r in rng), default=float("nan"))
    rows = [("name", d["name"]),
            ("format", f"{info.get('format')} ({info.get('format_detected')})"),
            ("samples", f"{d['samples']:,}"),
            ("channels", f"{d['channels']} ("
                         + (f"{wl[0]:g}-{wl[1]:g} nm" if wl else _short(d["channel_names"]))
                         + ")"),
            ("angles", f"{info.get('angles')} ({info.get('angles_from')})"),
            ("incidence directions", f"{d['incidence_directions']}; theta_i "
                                     f"{_short([round(t, 3) for t in theta_i])} deg"),
            ("theta_o", "none" if d["theta_o_deg"] is None else
             f"{d['theta_o_deg'][0]:.4g} to {d['theta_o_deg'][1]:.4g} deg"),
            ("phi_i constant", "yes" if d["phi_i_constant"] else "no"),
            ("isotropic", iso[d["isotropic"]]),
            ("duplicate pairs", d["duplicate_pairs"]),
            ("reciprocal pairs", f"{d['reciprocal_pairs']} "
                                 f"({d['reciprocal_pairs_isotropic']} up to isotropy)"),
            ("negative values", f"{d['negative_values']} ({100 * d['negative_fraction']:.3g} %)"),
            ("values", f"{lo:.6g} to {hi:.6g} 1/sr over all channels"),
            ("weights", "none" if d["weights"] is None else
             f"{d['weights'][0]:.6g} to {d['weights'][1]:.6g}"),
            *_reciprocity_rows(d["reciprocity"])]
    if info.get("description"):
        rows.insert(1, ("description", _short(info["description"])))
    return [f"{d['path']}: BRDF measurements, {d['bytes_on_disk']:,} bytes on disk",
            *_rows(rows)]


def _reciprocity_rows(r: dict[str, Any]) -> list[tuple[str, Any]]:
    """Rows for the reciprocity of a BRDF or measurements (see :func:`describe`)."""
    if "error" in r:
        return [("reciprocity", f"not estimated: {r['error']}")]
    if r["residual"] is None:
        return [("reciprocity", f"unknown: {r['note']}")]
    what = (f"{r['matched']:,} pairs, both orders" if r["tol_deg"] is None else
            f"{r['matched']:,} samples with a reciprocal twin within {r['tol_deg']:g} deg")
    se = r["residual_stderr"]
    rows = [("reciprocity", f"residual ||q - q^T|| / ||q|| = {r['residual']:.4g}"
                            + ("" if se is None else f" +- {se:.2g}")
                            + f", floor {r['floor']:.4g} (worst channel; {what})")]
    bands = r["bands"]
    if bands and all(b["share"] is not None for b in bands):
        rows.append(("antisymmetric energy", ", ".join(
            f"{b['theta_deg'][0]:g}-{b['theta_deg'][1]:g} deg {100 * b['share']:.3g} %"
            for b in bands) + " (by max(theta_i, theta_o))"))
        rows.append(("floor below", ", ".join(
            f"{b['theta_deg'][1]:g} deg " + ("n/a" if b["floor_below"] is None else
                                           f"{b['floor_below']:.3g}") for b in bands)))
    if r["note"]:
        rows.append(("reciprocity note", _short(r["note"])))
    return rows


def _matrix_rows(d: dict[str, Any]) -> list[tuple[str, Any]]:
    return [("basis", f"{d['basis']} (kind {d['basis_kind']}, order {d['order']}, "
                      f"{d['size']} functions)"),
            ("quantity", d["quantity"]),
            ("channels", f"{d['channels']}{' (scalar)' if d['scalar'] else ''}"),
            ("isotropic", "yes" if d["isotropic"] else "no (dense)"),
            ("coefficients", f"{d['unique_coefficients']:,} unique "
                             f"({8 * d['unique_coefficients']:,} bytes as float64; "
                             f"{d['nbytes']:,} bytes in memory)"),
            *_info_rows(d["info"])]


def _model_rows(d: dict[str, Any]) -> list[tuple[str, Any]]:
    shapes = ", ".join(f"{k} {tuple(v)}" for k, v in d["params"].items())
    return [("family", d["family"]),
            ("parameters", f"{d['nparams']} reals, {d['nbytes']:,} bytes as float64"),
            ("channels", d["channels"]), ("shapes", shapes), *_info_rows(d["info"])]


def _info_rows(info: dict[str, Any]) -> list[tuple[str, Any]]:
    return [(f"info.{k}", _short(v)) for k, v in info.items()]


def _rows(rows: list[tuple[str, Any]], indent: str = "") -> list[str]:
    width = max((len(k) for k, _ in rows), default=0)
    return [f"{indent}{k:<{width}}  {v}" for k, v in rows]


def _short(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list) and len(v) > 8:
        return f"[{', '.join(_short(x) for x in v[:8])}, ...] ({len(v)} values)"
    if isinstance(v, list):
        return f"[{', '.join(_short(x) for x in v)}]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_short(x)}" for k, x in list(v.items())[:8]) + (
            ", ...}" if len(v) > 8 else "}")
    text = str(v)
    return text if len(text) <= 120 else text[:117] + "..."


def _plain(v: Any) -> Any:
    """JSON-able copy of an info value: arrays and tuples as lists, nan/inf as strings."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return _plain(v.item())
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if v is None or isinstance(v, bool | int | float | str):
        return v
    return repr(v)
