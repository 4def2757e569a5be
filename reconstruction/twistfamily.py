"""The answer's twist family: the one direction the gauges leave open (the sheet with its
constant twist moved, all else kept; docs/reconstruction.md, "Posterior check"), and what every
reading of that twist shares: the reach to another member (half the distance, as node_sigma's
term), spreads computed once, a candidate's diagnostics, the χ² test of two answers within the
noise, and whether two answers differ at all (mirror images).  Package-internal: used by
:mod:`.stretchtwist` and :mod:`.reconstructor`.
"""
from __future__ import annotations

import math
from typing import Callable, TypeVar

import numpy as np

from .linalg import aligned_distances
from .surface import Diagnostics, Surface

# Two mirror images are reported only where they differ by more than this many combined noise
# s.d. plus a floor (mm) somewhere; closer than that they are the same answer for any user.
MIRROR_SIGMAS, MIRROR_FLOOR_MM = 3.0, 0.02

_T = TypeVar("_T")


def _mean_twist_terms(product_fields, inner) -> tuple[float, float]:
    """(tm, base) over the cells' region for the fields (k_u, k_v, τ₀): the mean twist is
    m = tm + c for a constant c, and Gauss's equation mean(k_u k_v − (τ₀ + c)²) = K gives
    m² = base − K (mean((τ₀ − tm + m)²) = mean(τ₀²) − tm² + m²)."""
    k_u, k_v, tau0 = (np.asarray(f) for f in product_fields)
    tm = float(tau0[inner].mean())
    return tm, tm * tm - float((tau0[inner] ** 2).mean()) + float((k_u[inner] * k_v[inner]).mean())


def _with_twist(diag: Diagnostics, twist_constant: float) -> Diagnostics:
    """A copy of ``diag`` (its own ``extra``) for a candidate with another constant twist."""
    return Diagnostics(**{**diag.__dict__, "extra": dict(diag.extra), "twist_constant": twist_constant})


def _memo(fn):
    """``fn`` evaluated once, on first call."""
    box: list = []

    def once():
        if not box:
            box.append(fn())
        return box[0]

    return once


def _within_noise(chi_a: float, chi_b: float, dof: int, chi2_noise: float) -> bool:
    """Both χ² at most what the noise alone leaves in the general model's answers, plus two of
    its s.d. (``dof``·``chi2_noise``·(1 + 2√(2/dof))): their difference then proves nothing."""
    return max(chi_a, chi_b) <= dof * chi2_noise * (1.0 + 2.0 * math.sqrt(2.0 / max(dof, 1)))


def _with_reading_noise(rest: Callable[[], np.ndarray | None], positions_at, base_shift: float,
                        sd: float) -> np.ndarray | None:
    """``rest`` (a spread field or None) and the spread that a twist read with s.d. ``sd`` on
    ``positions_at``'s family causes, in quadrature."""
    other = rest()
    if sd <= 0.0 or positions_at is None:
        return other
    step = max(sd, 1e-7)
    response = positions_at(base_shift + step) - positions_at(base_shift - step)
    own = np.sqrt((response * response).sum(axis=2)) * (sd / (2.0 * step))
    return own if other is None else np.sqrt(own * own + other * other)


def _widened(positions_at, base_shift: float, shifts, rest: Callable[[], np.ndarray | None]):
    """A spread function: half the distance to the family members at ``shifts``, or ``rest``'s
    spread where that is larger (computed once, when first asked)."""

    def widened() -> np.ndarray:
        out = _half_reach(positions_at, base_shift, shifts)
        other = rest()
        return out if other is None else np.maximum(out, other)

    return _memo(widened)


def _larger(first: Callable[[], np.ndarray | None], second: Callable[[], np.ndarray | None]):
    """A spread function: the larger of two spreads node by node (either may be None, no
    spread), computed once, when first asked."""

    def larger() -> np.ndarray | None:
        a, b = first(), second()
        return b if a is None else a if b is None else np.maximum(a, b)

    return _memo(larger)


def _half_reach(positions_at, base_shift: float, shifts) -> np.ndarray:
    """Half the largest distance (fine grid, mm) from the sheet at ``base_shift`` on its twist
    family to the sheet at each of ``base_shift + shifts``: a twist the data leave open joins
    node_sigma so, and 3 s.d. then reach past it."""
    here = positions_at(base_shift)
    return 0.5 * np.max([np.linalg.norm(positions_at(base_shift + d) - here, axis=-1) for d in shifts], axis=0)


def _given(value: _T) -> Callable[[], _T]:
    """A function that returns ``value``."""
    return lambda: value


def _mirror_if_distinct(answer: Surface, candidate: Callable[[], Surface]) -> Surface | None:
    """``candidate()`` as the mirror image beside ``answer`` where the two differ
    (:func:`_differs`), else None (the posterior check decides it only when it is asked for)."""
    other = candidate()
    return other if _differs(answer, other) else None


def _differs(a: Surface, b: Surface) -> bool:
    """Two answers that differ by more than their noise anywhere, after the best rigid
    alignment (a rigid motion of the whole sheet is not a different shape)."""
    gap = aligned_distances(a.nodes.reshape(-1, 3), b.nodes.reshape(-1, 3))
    tol = MIRROR_SIGMAS * np.sqrt(2.0) * a.node_sigma.ravel() + MIRROR_FLOOR_MM
    return bool((gap > tol).any())
