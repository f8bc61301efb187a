"""The names of the basis kinds, and the one factory that turns a name and an order into a basis.

Command line, studies and storage all speak this vocabulary (``Basis.kind``).
"""

from __future__ import annotations

from ._base import Basis
from .sh import HemiHarmonics, SphericalHarmonics
from .validation import choice
from .zernike import HemiZernike

__all__ = ["KINDS", "make_basis"]

#: Basis kinds: ``"zernike"`` (:class:`HemiZernike`), ``"harmonics"`` (:class:`HemiHarmonics`,
#: odd parity: the odd completion of Westin, Arvo & Torrance 1992, vanishing on the horizon),
#: ``"harmonics-even"`` (:class:`HemiHarmonics` with ``parity="even"``) and ``"sh"``
#: (:class:`SphericalHarmonics`, the whole sphere). ``make_basis(b.kind, b.order) == b`` for
#: every basis ``b``.
KINDS = ("zernike", "harmonics", "harmonics-even", "sh")


def make_basis(kind: str, order: int) -> Basis:
    """Return the basis named ``kind`` (one of :data:`KINDS`) at ``order``.

    Parameters
    ----------
    kind : {"zernike", "harmonics", "harmonics-even", "sh"}
        See :data:`KINDS`.
    order : int
        Highest degree, inclusive. The odd hemisphere harmonics have no function of degree
        0, so ``"harmonics"`` needs ``order >= 1``.

    Returns
    -------
    Basis

    Examples
    --------
    >>> make_basis("harmonics", 4), make_basis("zernike", 2).size
    (HemiHarmonics(4, parity='odd'), 6)
    """
    kind = choice(kind, "kind", KINDS)
    if kind == "zernike":
        return HemiZernike(order)
    if kind == "sh":
        return SphericalHarmonics(order)
    if kind == "harmonics" and isinstance(order, int) and order == 0:
        raise ValueError("order must be >= 1 for kind='harmonics' (the odd hemisphere "
                         "harmonics start at degree 1), got 0")
    return HemiHarmonics(order, parity="odd" if kind == "harmonics" else "even")
