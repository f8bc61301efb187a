"""Scattered BRDF measurements: a validated, immutable set of (w_i, w_o, f) samples.

A gonioreflectometer measures a BRDF at a few thousand direction pairs, often at a handful
of incidence angles only; :class:`Measurements` holds such a set with its channels
(wavelengths or colours), weights and what the source states about isotropy, and provides
the operations a fit needs: subsets, channel selection and interpolation in wavelength, and
cross-validation folds that never put a direction pair and its twin on both sides of a
split. Readers of measurement files are in :mod:`project.measured.tables`.
"""

from __future__ import annotations

import operator
import os
import types
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from basis import to_angles
from basis.validation import choice

__all__ = ["FOLDS", "FOLD_GROUPINGS", "HORIZON_ATOL", "UNIT_ATOL", "Measurements", "pair_groups",
           "reciprocal_matches"]

#: Directions whose length differs from 1 by more than this are refused; others are
#: renormalised. Six printed decimals per component stay well inside it.
UNIT_ATOL = 1e-6
#: Directions at most this far below the horizon (z >= -HORIZON_ATOL) are put on it (z = 0,
#: renormalised): rounding of angles at exactly 90 degrees; anything lower is refused.
HORIZON_ATOL = 1e-9
#: Ways :meth:`Measurements.folds` groups samples.
FOLD_GROUPINGS = ("pairs", "incidence")
#: Folds of the default cross-validation (:meth:`Measurements.folds`, :func:`project.fit`).
FOLDS = 10
#: Directions (components) equal to this many decimals are the same direction.
DECIMALS = 9
#: Default angular tolerance (degrees) of the reciprocity count of :meth:`Measurements.describe`.
RECIPROCAL_TOL_DEG = 0.01


def _directions(d: ArrayLike, name: str) -> NDArray[np.float64]:
    """Return a (n, 3) float64 copy of unit vectors in the upper hemisphere (renormalised)."""
    try:
        a = np.array(d, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of floats with shape (n, 3), got "
                        f"{type(d).__name__}") from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got shape {a.shape}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} must be finite: {int(bad.sum())} of {len(a)} rows hold NaN or "
                         f"inf (first at row {i}: {a[i].tolist()})")
    norm = np.linalg.norm(a, axis=1)
    off = np.abs(norm - 1.0) > UNIT_ATOL
    if off.any():
        i = int(np.flatnonzero(off)[0])
        raise ValueError(f"{name} must be unit vectors (|norm - 1| <= {UNIT_ATOL:g}): "
                         f"{int(off.sum())} of {len(a)} rows are not (first at row {i}, "
                         f"norm {norm[i]:.9g})")
    a /= norm[:, None]
    below = a[:, 2] < -HORIZON_ATOL
    if below.any():
        i = int(np.flatnonzero(below)[0])
        raise ValueError(f"{name} must lie in the upper hemisphere z >= 0 (within "
                         f"{HORIZON_ATOL:g}): {int(below.sum())} of {len(a)} rows do not "
                         f"(first at row {i}, z = {a[i, 2]:.6g})")
    near = a[:, 2] < 0.0
    if near.any():
        a[near, 2] = 0.0
        a[near] /= np.linalg.norm(a[near], axis=1, keepdims=True)
    return a


def _readonly(a: NDArray) -> NDArray:
    a.flags.writeable = False
    return a


def _wavelength_name(nm: float) -> str:
    return f"{float(nm):g} nm"


class Measurements:
    """Scattered BRDF measurements: direction pairs, values per channel, weights, metadata.

    Parameters
    ----------
    wi, wo : (n, 3) array_like of float
        Unit vectors towards the light and towards the viewer, both pointing away from the
        surface (local frame, z the normal). Lengths within :data:`UNIT_ATOL` = 1e-6 of 1
        are renormalised; z down to -:data:`HORIZON_ATOL` = -1e-9 is put on the horizon.
    values : (n,) or (n, channels) array_like of float
        BRDF values f in 1/sr, as measured: finite, negative values allowed (measurement
        noise around 0; :meth:`describe` counts them). A 1-D array is one channel.
    weights : (n,) array_like of float, optional
        Finite, >= 0, not all 0 (default: ones), e.g. inverse variances.
    wavelengths : (channels,) array_like of float, optional
        Wavelength of each channel in nm, finite, > 0 and strictly increasing.
    channel_names : sequence of str, optional
        One per channel. Default: "450 nm" style names from ``wavelengths``, else
        ("R", "G", "B") for 3 channels, else "0", "1", ...
    isotropic : bool or None
        What the source states: True, False or None (unknown).
    name : str, optional
        Material name.
    source : str or os.PathLike, optional
        File the measurements came from.
    info : mapping, optional
        Further facts about the source (format, how it was detected, angle units, ...),
        JSON-able values; stored as a read-only mapping.

    Attributes
    ----------
    wi, wo : (n, 3) ndarray of float64, read-only
    values : (n, channels) ndarray of float64, read-only
    weights : (n,) ndarray of float64, read-only
    wavelengths : (channels,) ndarray of float64, read-only, or None
    channel_names : tuple of str
    channels : int
    isotropic : bool or None
    name : str or None
    source : pathlib.Path or None
    info : mapping (read-only)

    Notes
    -----
    The object is immutable (its arrays are read-only and its attributes cannot be set), so
    subsets (``meas[mask]``, :meth:`kfold`) can share nothing mutable with it. Subsets keep
    the weights as they are, even if those of the subset are all 0.

    Examples
    --------
    >>> from basis import from_angles
    >>> wi = from_angles(np.radians([30.0, 30.0, 60.0]), 0.0)
    >>> wo = from_angles(np.radians([0.0, 45.0, 45.0]), np.radians([0.0, 180.0, 90.0]))
    >>> meas = Measurements(wi, wo, [[0.2, 0.3, 0.4], [0.5, 0.6, 0.7], [-0.01, 0.1, 0.2]],
    ...                     name="demo")
    >>> meas
    Measurements(name='demo', samples=3, channels=3 (R, G, B), isotropic=None)
    >>> len(meas), meas.values.shape, meas.channel_names
    (3, (3, 3), ('R', 'G', 'B'))
    >>> meas[1:].values[:, 0].tolist()
    [0.5, -0.01]
    >>> meas.values[0, 0] = 1.0
    Traceback (most recent call last):
    ...
    ValueError: assignment destination is read-only
    """

    __slots__ = ("_wi", "_wo", "_values", "_weights", "_wavelengths", "_channel_names",
                 "_isotropic", "_name", "_source", "_info")

    def __init__(self, wi: ArrayLike, wo: ArrayLike, values: ArrayLike, *,
                 weights: ArrayLike | None = None, wavelengths: ArrayLike | None = None,
                 channel_names: Sequence[str] | None = None, isotropic: bool | None = None,
                 name: str | None = None, source: str | os.PathLike | None = None,
                 info: Mapping[str, Any] | None = None) -> None:
        a = _directions(wi, "wi")
        b = _directions(wo, "wo")
        n = a.shape[0]
        if b.shape != a.shape:
            raise ValueError(f"wo must have the shape of wi {a.shape}, got shape {b.shape}")
        v = _values(values, n)
        ch = v.shape[1]
        w = _weights(weights, n)
        wl = _wavelengths(wavelengths, ch)
        names = _channel_names(channel_names, ch, wl)
        if isotropic is not None and not isinstance(isotropic, (bool, np.bool_)):
            raise TypeError(f"isotropic must be True, False or None, got {isotropic!r}")
        if name is not None and not isinstance(name, str):
            raise TypeError(f"name must be a str or None, got {type(name).__name__}")
        if source is not None:
            try:
                source = Path(os.fspath(source))
            except TypeError:
                raise TypeError(f"source must be a str, os.PathLike or None, got "
                                f"{type(source).__name__}") from None
        if info is not None and not isinstance(info, Mapping):
            raise TypeError(f"info must be a mapping or None, got {type(info).__name__}")
        self._set(a, b, v, w, wl, names, None if isotropic is None else bool(isotropic),
                  name, source, dict(info or {}))

    def _set(self, wi: NDArray, wo: NDArray, values: NDArray, weights: NDArray,
             wavelengths: NDArray | None, names: tuple[str, ...], isotropic: bool | None,
             name: str | None, source: Path | None, info: dict[str, Any]) -> None:
        """Store validated parts (read-only)."""
        put = object.__setattr__
        put(self, "_wi", _readonly(wi))
        put(self, "_wo", _readonly(wo))
        put(self, "_values", _readonly(values))
        put(self, "_weights", _readonly(weights))
        put(self, "_wavelengths", None if wavelengths is None else _readonly(wavelengths))
        put(self, "_channel_names", names)
        put(self, "_isotropic", isotropic)
        put(self, "_name", name)
        put(self, "_source", source)
        put(self, "_info", types.MappingProxyType(info))

    def _derive(self, keep: Any = None, *, values: NDArray | None = None,
                wavelengths: NDArray | None = None,
                names: tuple[str, ...] | None = None) -> Measurements:
        """Return a new set with the metadata: rows ``keep`` and/or new (validated) channels."""
        out = object.__new__(Measurements)
        rows = slice(None) if keep is None else keep
        vals = self._values if values is None else values
        if names is None:
            wavelengths, names = self._wavelengths, self._channel_names
        out._set(np.array(self._wi[rows]), np.array(self._wo[rows]), np.array(vals[rows]),
                 np.array(self._weights[rows]),
                 None if wavelengths is None else np.array(wavelengths), names,
                 self._isotropic, self._name, self._source, dict(self._info))
        return out

    def __setattr__(self, key: str, value: object) -> None:
        raise AttributeError(f"Measurements is immutable: cannot set {key!r}; build a new "
                             "set (e.g. with select_channels or indexing)")

    def __delattr__(self, key: str) -> None:
        raise AttributeError(f"Measurements is immutable: cannot delete {key!r}")

    # -- attributes ----------------------------------------------------------------------------
    @property
    def wi(self) -> NDArray[np.float64]:
        """(n, 3) read-only unit vectors towards the light."""
        return self._wi.view()  # a view of a read-only array cannot be made writeable

    @property
    def wo(self) -> NDArray[np.float64]:
        """(n, 3) read-only unit vectors towards the viewer."""
        return self._wo.view()

    @property
    def values(self) -> NDArray[np.float64]:
        """(n, channels) read-only BRDF values in 1/sr."""
        return self._values.view()

    @property
    def weights(self) -> NDArray[np.float64]:
        """(n,) read-only weights >= 0."""
        return self._weights.view()

    @property
    def wavelengths(self) -> NDArray[np.float64] | None:
        """(channels,) read-only wavelengths in nm, or None."""
        return None if self._wavelengths is None else self._wavelengths.view()

    @property
    def channel_names(self) -> tuple[str, ...]:
        """One name per channel."""
        return self._channel_names

    @property
    def channels(self) -> int:
        """Number of value columns."""
        return int(self._values.shape[1])

    @property
    def isotropic(self) -> bool | None:
        """True / False as the source states, None if it does not say."""
        return self._isotropic

    @property
    def name(self) -> str | None:
        """Material name, or None."""
        return self._name

    @property
    def source(self) -> Path | None:
        """File the measurements came from, or None."""
        return self._source

    @property
    def info(self) -> Mapping[str, Any]:
        """Read-only facts about the source (format, angle units, ...)."""
        return self._info

    def __len__(self) -> int:
        return int(self._wi.shape[0])

    def __repr__(self) -> str:
        if self._wavelengths is not None and self.channels > 3:
            ch = (f"{self.channels} ({self._wavelengths[0]:g}-{self._wavelengths[-1]:g} "
                  "nm)")
        elif self.channels <= 3:
            ch = f"{self.channels} ({', '.join(self._channel_names)})"
        else:
            ch = str(self.channels)
        return (f"Measurements(name={self._name!r}, samples={len(self)}, channels={ch}, "
                f"isotropic={self._isotropic})")

    # -- subsets -------------------------------------------------------------------------------
    def __getitem__(self, key: object) -> Measurements:
        """Return the samples selected by a boolean mask, integer indices, a slice or an int.

        A scalar int gives a one-sample set. Metadata is kept.
        """
        n = len(self)
        if isinstance(key, slice):
            return self._derive(key)
        if isinstance(key, (bool, np.bool_)):
            raise TypeError("Measurements index must be an int, a slice, a boolean mask or an "
                            f"integer array, got {key!r}")
        if isinstance(key, (int, np.integer)):
            i = operator.index(key)
            if not -n <= i < n:
                raise IndexError(f"index {i} is out of range for {n} samples")
            return self._derive(slice(i % n, i % n + 1))
        try:
            k = np.asarray(key)
        except (TypeError, ValueError):
            k = np.asarray(None)
        if k.dtype == np.bool_:
            if k.shape != (n,):
                raise ValueError(f"boolean mask must have shape ({n},), got shape {k.shape}")
            return self._derive(k)
        if k.ndim == 1 and (k.dtype.kind in "iu" or k.size == 0):
            k = k.astype(np.int64)
            out = (k < -n) | (k >= n)
            if out.any():
                raise IndexError(f"index {int(k[out][0])} is out of range for {n} samples")
            return self._derive(k)
        raise TypeError("Measurements index must be an int, a slice, a (n,) boolean mask or a "
                        f"1-D integer array, got {type(key).__name__}"
                        + (f" of dtype {k.dtype} and shape {k.shape}"
                           if isinstance(key, np.ndarray | list) else ""))

    def angles(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Return theta_i, phi_i, theta_o, phi_o, each (n,), in radians.

        theta in [0, pi/2], phi in (-pi, pi] (:func:`basis.to_angles`; phi is 0 at the
        normal).

        Examples
        --------
        >>> from basis import from_angles
        >>> m = Measurements(from_angles(0.5, 0.0)[None], from_angles(0.25, -1.0)[None], [1.0])
        >>> [round(float(a[0]), 12) for a in m.angles()]
        [0.5, 0.0, 0.25, -1.0]
        """
        ti, pi = to_angles(self._wi)
        to, po = to_angles(self._wo)
        return ti, pi, to, po

    # -- channels ------------------------------------------------------------------------------
    def select_channels(self, channels: int | str | Sequence[int | str]) -> Measurements:
        """Return the set with only some channels, by index or by name, in the order given.

        Parameters
        ----------
        channels : int, str or sequence of int / str
            Channel indices (negative count from the end) or names. With wavelengths the
            selection must keep them strictly increasing.

        Returns
        -------
        Measurements

        Examples
        --------
        >>> from basis import from_angles
        >>> m = Measurements(from_angles([0.1, 0.2], 0.0), from_angles([0.3, 0.4], 1.0),
        ...                  [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
        >>> m.select_channels(["B", 0]).values.tolist(), m.select_channels(1).channel_names
        ([[3.0, 1.0], [6.0, 4.0]], ('G',))
        """
        items = [channels] if isinstance(channels, (str, int, np.integer)) else list(channels)
        if not items:
            raise ValueError("channels must name at least one channel, got none")
        idx = []
        for c in items:
            if isinstance(c, str):
                if c not in self._channel_names:
                    raise ValueError(f"channels must be indices or names among "
                                     f"{list(self._channel_names)}, got {c!r}")
                idx.append(self._channel_names.index(c))
                continue
            if isinstance(c, (bool, np.bool_)):
                raise TypeError(f"channels must be ints or names, got {c!r}")
            try:
                i = operator.index(c)  # type: ignore[arg-type]
            except TypeError:
                raise TypeError(f"channels must be ints or names, got {c!r}") from None
            if not -self.channels <= i < self.channels:
                raise ValueError(f"channel index must lie in [-{self.channels}, "
                                 f"{self.channels - 1}], got {i}")
            idx.append(i % self.channels)
        sel = np.array(idx, dtype=np.int64)
        wl = None
        if self._wavelengths is not None:
            wl = self._wavelengths[sel]
            if np.any(np.diff(wl) <= 0):
                raise ValueError("channels must keep the wavelengths strictly increasing, got "
                                 f"{wl.tolist()} nm")
        names = tuple(self._channel_names[i] for i in idx)
        return self._derive(values=self._values[:, sel], wavelengths=wl, names=names)

    def at_wavelengths(self, nm: float | ArrayLike) -> Measurements:
        """Return the set at other wavelengths, interpolated linearly between the measured ones.

        Parameters
        ----------
        nm : float or (m,) array_like of float
            Wavelengths in nm, strictly increasing, inside [min, max] of ``wavelengths``.

        Returns
        -------
        Measurements
            ``m`` channels named "<nm> nm". At a measured wavelength the value is copied
            exactly.

        Raises
        ------
        ValueError
            The set has no wavelengths, or ``nm`` lies outside their range (no
            extrapolation), or is not strictly increasing.

        Examples
        --------
        >>> from basis import from_angles
        >>> m = Measurements(from_angles([0.1], 0.0), from_angles([0.3], 1.0),
        ...                  [[1.0, 2.0, 4.0]], wavelengths=[400, 500, 600])
        >>> rgb = m.at_wavelengths([450, 500, 575])
        >>> rgb.values.tolist(), rgb.channel_names
        ([[1.5, 2.0, 3.5]], ('450 nm', '500 nm', '575 nm'))
        """
        if self._wavelengths is None:
            raise ValueError("at_wavelengths needs a set with wavelengths, got one with "
                             f"channels {list(self._channel_names)}")
        try:
            x = np.array(nm, dtype=np.float64).reshape(-1) if np.ndim(nm) <= 1 else None
        except (TypeError, ValueError):
            raise TypeError(f"nm must be a number or a 1-D array of numbers, got {nm!r}") \
                from None
        if x is None:
            raise ValueError(f"nm must be a number or a 1-D array, got shape {np.shape(nm)}")
        if x.size == 0 or not np.all(np.isfinite(x)) or np.any(np.diff(x) <= 0):
            raise ValueError(f"nm must be finite and strictly increasing, got {x.tolist()}")
        wl = self._wavelengths
        out = (x < wl[0]) | (x > wl[-1])
        if out.any():
            raise ValueError(f"nm must lie within the measured wavelengths [{wl[0]:g}, "
                             f"{wl[-1]:g}] nm (no extrapolation), got {x[out][0]:g}")
        j = np.clip(np.searchsorted(wl, x, side="right") - 1, 0, max(wl.size - 2, 0))
        vals = np.empty((len(self), x.size))
        for c, (xc, jc) in enumerate(zip(x, j, strict=True)):
            if wl.size == 1 or xc == wl[jc]:
                vals[:, c] = self._values[:, jc]
            elif xc == wl[jc + 1]:
                vals[:, c] = self._values[:, jc + 1]
            else:
                t = (xc - wl[jc]) / (wl[jc + 1] - wl[jc])
                vals[:, c] = (1.0 - t) * self._values[:, jc] + t * self._values[:, jc + 1]
        names = tuple(_wavelength_name(v) for v in x)
        return self._derive(values=vals, wavelengths=x, names=names)

    # -- cross-validation ----------------------------------------------------------------------
    def folds(self, k: int = FOLDS, *, seed: int = 0, by: str = "pairs",
              isotropic: bool | None = None) -> NDArray[np.int64]:
        """Return a fold index in [0, k) for each sample, keeping twins of a pair together.

        Parameters
        ----------
        k : int
            Number of folds, >= 2; fewer if there are fewer groups.
        seed : int
            Seed of the random order of the groups (deterministic for a given seed).
        by : {"pairs", "incidence"}
            ``"pairs"``: a group is a direction pair with its repeats and twins (see Notes).
            ``"incidence"``: a group is an incidence direction (theta_i alone for isotropic
            grouping), a leave-incidences-out split.
        isotropic : bool, optional
            Grouping for isotropic data or not; default ``self.isotropic``, and True (as
            :func:`project.fit` defaults) when that is unknown.

        Returns
        -------
        (n,) ndarray of int64

        Notes
        -----
        The groups are those :func:`project.fit` uses for its cross-validation: directions
        equal to 9 decimals are equal; a pair (w_i, w_o) is grouped with its repeats and its
        reciprocal (w_o, w_i), and for isotropic grouping with every pair of the same
        theta_i, theta_o and |phi_i - phi_o| up to exchange (same cos theta_i, cos theta_o
        and w_i . w_o). So a held-out fold never has a twin in training. The groups are
        put in a random order (``numpy.random.default_rng(seed)``), and each in turn goes to
        the fold with the fewest samples so far (the lowest index on ties): when every
        group is one sample this is the round-robin split of :func:`project.fit` (which
        uses k = 10, seed 0), and fold sizes differ by at most the largest group.

        Examples
        --------
        >>> from basis import from_angles
        >>> th = np.radians([10.0, 20.0, 30.0, 40.0])
        >>> m = Measurements(from_angles(th, 0.0), from_angles(th[::-1], 0.0), np.ones(4),
        ...                  isotropic=False)
        >>> f = m.folds(2)      # samples 0 and 3 are reciprocal, and 1 and 2
        >>> bool(f[0] == f[3]), bool(f[1] == f[2]), bool(f[0] != f[1])
        (True, True, True)
        """
        k = _fold_count(k)
        seed = operator.index(seed)
        by = choice(by, "by", FOLD_GROUPINGS)
        if isotropic is None:
            iso = True if self._isotropic is None else self._isotropic
        elif isinstance(isotropic, (bool, np.bool_)):
            iso = bool(isotropic)
        else:
            raise TypeError(f"isotropic must be True, False or None, got {isotropic!r}")
        group = pair_groups(self._wi, self._wo, iso, by)
        return _balanced_folds(group, k, seed)

    def kfold(self, k: int = FOLDS, *, seed: int = 0, by: str = "pairs",
              isotropic: bool | None = None) -> Iterator[tuple[Measurements, Measurements]]:
        """Yield (train, test) sets, one per fold of :meth:`folds` (same arguments).

        Examples
        --------
        >>> from basis import from_angles
        >>> th = np.radians(np.arange(10.0, 80.0, 10.0))
        >>> m = Measurements(from_angles(th, 0.0), from_angles(th, 2.0), np.ones(7))
        >>> [(len(train), len(test)) for train, test in m.kfold(3)]
        [(4, 3), (5, 2), (5, 2)]
        """
        f = self.folds(k, seed=seed, by=by, isotropic=isotropic)
        count = int(f.max()) + 1 if f.size else 0
        for j in range(count):
            test = f == j
            yield self._derive(~test), self._derive(test)

    # -- report --------------------------------------------------------------------------------
    def describe(self, *, tol_deg: float = RECIPROCAL_TOL_DEG) -> dict[str, Any]:
        """Return a JSON-able summary for a report.

        Parameters
        ----------
        tol_deg : float
            Angular tolerance (degrees, per direction) for counting reciprocal pairs.

        Returns
        -------
        dict
            ``name``, ``source``, ``samples``, ``channels``, ``channel_names``,
            ``wavelengths_nm`` ([min, max] or None), ``isotropic`` (as stated),
            ``incidence_directions`` (distinct w_i, to 9 decimals), ``theta_i_deg``
            (the distinct theta_i, degrees, rounded to 1e-6), ``theta_o_deg`` ([min, max]),
            ``phi_i_constant`` (whether every w_i off the normal has one phi_i, to 1e-6 deg),
            ``duplicate_pairs`` (samples repeating an earlier pair, to 9 decimals),
            ``reciprocal_pairs`` (samples with w_i != w_o whose swapped pair (w_o, w_i) is
            also measured within ``tol_deg``), ``reciprocal_pairs_isotropic`` (the same up to
            a rotation and mirroring about the normal, which isotropy makes equivalent),
            ``negative_values`` and ``negative_fraction`` (of all values),
            ``value_range`` (per channel [min, max], 1/sr), ``weights`` ([min, max]) and
            ``info``.

        Examples
        --------
        >>> from basis import from_angles
        >>> a, b = from_angles(0.3, 0.0), from_angles(0.6, 2.0)
        >>> m = Measurements([a, b, a], [b, a, b], [0.1, 0.2, -0.05])
        >>> d = m.describe()
        >>> d["samples"], d["duplicate_pairs"], d["reciprocal_pairs"], d["negative_values"]
        (3, 1, 3, 1)
        """
        tol = float(tol_deg)
        if not np.isfinite(tol) or tol < 0:
            raise ValueError(f"tol_deg must be finite and >= 0, got {tol_deg!r}")
        n = len(self)
        ti, pi, to, _ = self.angles()
        inc = np.unique(np.round(self._wi, DECIMALS), axis=0).shape[0] if n else 0
        pairs = np.concatenate([self._wi, self._wo], axis=1)
        dup = n - (np.unique(np.round(pairs, DECIMALS), axis=0).shape[0] if n else 0)
        off = ti > np.radians(1e-6)
        phis = np.degrees(pi[off])
        const = bool(phis.size == 0 or np.ptp(np.round(phis, 6) % 360.0) == 0.0 or
                     np.ptp(np.round(phis + 180.0, 6) % 360.0) == 0.0)
        vals = self._values
        neg = int(np.sum(vals < 0))
        wl = self._wavelengths
        return {
            "name": self._name,
            "source": None if self._source is None else str(self._source),
            "samples": n,
            "channels": self.channels,
            "channel_names": list(self._channel_names),
            "wavelengths_nm": None if wl is None else [float(wl[0]), float(wl[-1])],
            "isotropic": self._isotropic,
            "incidence_directions": int(inc),
            "theta_i_deg": np.unique(np.round(np.degrees(ti), 6)).tolist(),
            "theta_o_deg": [float(np.degrees(to.min())), float(np.degrees(to.max()))]
            if n else None,
            "phi_i_constant": const,
            "duplicate_pairs": int(dup),
            "reciprocal_pairs": _reciprocal_count(self._wi, self._wo, tol, False),
            "reciprocal_pairs_isotropic": _reciprocal_count(self._wi, self._wo, tol, True),
            "negative_values": neg,
            "negative_fraction": float(neg / vals.size) if vals.size else 0.0,
            "value_range": [[float(vals[:, c].min()), float(vals[:, c].max())]
                            for c in range(self.channels)] if n else [],
            "weights": [float(self._weights.min()), float(self._weights.max())] if n else None,
            "info": dict(self._info),
        }


# -- validation --------------------------------------------------------------------------------
def _values(values: ArrayLike, n: int) -> NDArray[np.float64]:
    try:
        v = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"values must be an array of floats, got {type(values).__name__}") \
            from None
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != n or v.shape[1] < 1:
        raise ValueError(f"values must have shape ({n},) or ({n}, channels >= 1) to match wi, "
                         f"got shape {np.shape(values)}")
    bad = ~np.isfinite(v)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ValueError(f"values must be finite: {int(bad.sum())} entries are NaN or inf "
                         f"(first at row {r}, channel {c})")
    return np.ascontiguousarray(v)


def _weights(weights: ArrayLike | None, n: int) -> NDArray[np.float64]:
    if weights is None:
        return np.ones(n)
    try:
        w = np.array(weights, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"weights must be an array of floats, got {type(weights).__name__}") \
            from None
    if w.shape != (n,):
        raise ValueError(f"weights must have shape ({n},) to match wi, got shape {w.shape}")
    bad = ~np.isfinite(w) | (w < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"weights must be finite and >= 0, got {float(w[i])!r} at row {i}")
    if n and not np.any(w > 0):
        raise ValueError("weights must not all be zero")
    return w


def _wavelengths(wavelengths: ArrayLike | None, channels: int) -> NDArray[np.float64] | None:
    if wavelengths is None:
        return None
    try:
        wl = np.array(wavelengths, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TypeError(f"wavelengths must be an array of floats, got "
                        f"{type(wavelengths).__name__}") from None
    if wl.size != channels or np.ndim(wavelengths) > 1:
        raise ValueError(f"wavelengths must have shape ({channels},), one per channel, got "
                         f"shape {np.shape(wavelengths)}")
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0) or np.any(np.diff(wl) <= 0):
        raise ValueError(f"wavelengths must be finite, > 0 and strictly increasing (nm), got "
                         f"{wl.tolist()}")
    return wl


def _channel_names(names: Sequence[str] | None, channels: int,
                   wl: NDArray | None) -> tuple[str, ...]:
    if names is None:
        if wl is not None:
            return tuple(_wavelength_name(x) for x in wl)
        return ("R", "G", "B") if channels == 3 else tuple(str(c) for c in range(channels))
    if isinstance(names, str):
        raise TypeError(f"channel_names must be a sequence of str, got the str {names!r}")
    out = tuple(names)
    if len(out) != channels:
        raise ValueError(f"channel_names must have one name per channel ({channels}), got "
                         f"{len(out)}")
    for x in out:
        if not isinstance(x, str):
            raise TypeError(f"channel_names must be str, got {x!r}")
    if len(set(out)) != len(out):
        raise ValueError(f"channel_names must be distinct, got {list(out)}")
    return out


def _fold_count(k: object) -> int:
    if isinstance(k, (bool, np.bool_)):
        raise TypeError(f"k must be an integer, got {k!r}")
    try:
        kk = operator.index(k)  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(f"k must be an integer, got {k!r}") from None
    if kk < 2:
        raise ValueError(f"k must be >= 2, got {kk}")
    return kk


# -- folds -------------------------------------------------------------------------------------
def _lex_greater(a: NDArray, b: NDArray) -> NDArray[np.bool_]:
    """Row-wise lexicographic a > b (rounded), for putting reciprocal pairs in one order."""
    a, b = np.round(a, DECIMALS), np.round(b, DECIMALS)
    out = np.zeros(a.shape[0], dtype=bool)
    undecided = np.ones(a.shape[0], dtype=bool)
    for k in range(a.shape[1]):
        out |= undecided & (a[:, k] > b[:, k])
        undecided &= a[:, k] == b[:, k]
    return out


def pair_groups(wi: NDArray, wo: NDArray, isotropic: bool, by: str) -> NDArray[np.int64]:
    """Group label of each sample pair: twins share one (see :meth:`Measurements.folds`).

    ``by="pairs"`` groups repeats, reciprocal pairs and (``isotropic``) pairs of equal
    cos theta_i, cos theta_o and w_i . w_o up to exchange; ``by="incidence"`` groups by
    incidence direction (its cosine when ``isotropic``). Cross-validation folds of
    :func:`project.fit` and :meth:`Measurements.folds` are unions of these groups.
    """
    n = wi.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if by == "incidence":
        key = wi[:, 2:] if isotropic else wi
    elif isotropic:
        zi, zo = wi[:, 2], wo[:, 2]
        key = np.stack([np.minimum(zi, zo), np.maximum(zi, zo),
                        np.einsum("ij,ij->i", wi, wo)], axis=1)
    else:
        swap = _lex_greater(wi, wo)
        key = np.where(swap[:, None], np.concatenate([wo, wi], axis=1),
                       np.concatenate([wi, wo], axis=1))
    return np.unique(np.round(key, DECIMALS), axis=0, return_inverse=True)[1].reshape(-1)


def _balanced_folds(group: NDArray, k: int, seed: int) -> NDArray[np.int64]:
    """Assign groups in a seeded random order, each to the fold with fewest samples so far."""
    if group.size == 0:
        return np.zeros(0, dtype=np.int64)
    count = int(group.max()) + 1
    k = min(k, count)
    sizes = np.bincount(group, minlength=count)
    order = np.random.default_rng(seed).permutation(count)
    fold_of = np.empty(count, dtype=np.int64)
    load = np.zeros(k, dtype=np.int64)
    for g in order:
        f = int(np.argmin(load))  # first minimum: round robin for groups of one sample
        fold_of[g] = f
        load[f] += sizes[g]
    return fold_of[group]


# -- reciprocity -------------------------------------------------------------------------------
def _canonical(wi: NDArray, wo: NDArray) -> NDArray:
    """(n, 6) pairs rotated about z so that phi_i = 0, mirrored so that wo_y >= 0."""
    r = np.hypot(wi[:, 0], wi[:, 1])
    c = np.where(r > 0, wi[:, 0] / np.where(r > 0, r, 1.0), 1.0)
    s = np.where(r > 0, wi[:, 1] / np.where(r > 0, r, 1.0), 0.0)
    a = np.stack([r, np.zeros_like(r), wi[:, 2]], axis=1)
    bx = c * wo[:, 0] + s * wo[:, 1]
    by = np.abs(-s * wo[:, 0] + c * wo[:, 1])
    b = np.stack([bx, by, wo[:, 2]], axis=1)
    if np.any(r == 0):  # w_i at the normal: phi_i undefined, rotate w_o to phi_o = 0
        z = r == 0
        b[z] = np.stack([np.hypot(wo[z, 0], wo[z, 1]), np.zeros(int(z.sum())), wo[z, 2]], axis=1)
    return np.concatenate([a, b], axis=1)


def reciprocal_matches(wi: NDArray, wo: NDArray, tol_deg: float,
                       isotropic: bool) -> NDArray[np.int64]:
    """Index pairs (i, j) such that sample j is the reciprocal of sample i within ``tol_deg``.

    Sample j matches sample i when its pair (w_i[j], w_o[j]) lies within ``tol_deg``
    (degrees, per direction) of the swapped pair (w_o[i], w_i[i]); with ``isotropic``, up
    to a rotation about the normal and a mirroring (both pairs compared in the canonical
    form phi_i = 0, w_o y >= 0). Self-matches (j == i: w_i = w_o, or theta_i = theta_o
    under isotropy) are included.

    Returns
    -------
    (m, 2) ndarray of int64
        Every matching (i, j), sorted by i and, for one i, by increasing distance (the
        larger of the two chord distances), so the first row of each i is its nearest twin.
    """
    n = wi.shape[0]
    if n == 0:
        return np.zeros((0, 2), dtype=np.int64)
    chord = 2.0 * np.sin(np.radians(tol_deg) / 2.0) + 1e-12
    if isotropic:
        pts, swapped = _canonical(wi, wo), _canonical(wo, wi)
    else:
        pts, swapped = np.concatenate([wi, wo], axis=1), np.concatenate([wo, wi], axis=1)
    tree = cKDTree(pts)
    # each direction within chord => the 6-vector within sqrt(2) chord: candidates, then check
    hits = tree.query_ball_point(swapped, r=np.sqrt(2.0) * chord)
    sizes = np.fromiter((len(h) for h in hits), dtype=np.int64, count=n)
    if not sizes.any():
        return np.zeros((0, 2), dtype=np.int64)
    i = np.repeat(np.arange(n, dtype=np.int64), sizes)
    j = np.fromiter((k for h in hits for k in h), dtype=np.int64, count=int(sizes.sum()))
    dist = np.maximum(np.linalg.norm(pts[j, :3] - swapped[i, :3], axis=1),
                      np.linalg.norm(pts[j, 3:] - swapped[i, 3:], axis=1))
    ok = dist <= chord
    i, j, dist = i[ok], j[ok], dist[ok]
    order = np.lexsort((j, dist, i))
    return np.stack([i[order], j[order]], axis=1)


def _reciprocal_count(wi: NDArray, wo: NDArray, tol_deg: float, isotropic: bool) -> int:
    """Count samples, w_i != w_o, whose swapped pair is measured (tolerance per direction)."""
    if wi.shape[0] == 0:
        return 0
    chord = 2.0 * np.sin(np.radians(tol_deg) / 2.0) + 1e-12
    same = np.linalg.norm(wi - wo, axis=1) <= chord
    i = reciprocal_matches(wi, wo, tol_deg, isotropic)[:, 0]
    return int(np.unique(i[~same[i]]).size)
