"""Least-squares fits with some data rows left out, from the all-valid fit alone.

A fit x = A⁻¹ Oᵀ d with A = OᵀO + P (data operator O, one row per unit; prior P) loses the
rows J of its missing units.  With Y_J = A⁻¹ O_Jᵀ and the hat matrix H = O A⁻¹ Oᵀ, the Woodbury
identity gives the fit without them, for data d that are zero on J, as

    x_J-out = x + Y_J M (O x)_J,        M = (I − H_JJ)⁻¹,

so an unseen validity mask costs a k × k inverse and k columns of the all-valid fit (k missing
units) instead of a new factorisation.  Y_J and H's columns are slices of the precomputed dense
maps on small grids, and one cached solve per unit on large ones.  The result is the exact
left-out fit: the data no longer enter, the prior fills the gap.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import cast

import numpy as np
import scipy.sparse as sp

from .linalg import FixedSolver

__all__ = ["LeaveOut", "woodbury_weights", "IllConditioned"]

# Beyond this condition number of I − H_JJ the remaining data and the prior no longer fix the
# fit (e.g. all units of one direction missing): the caller refactorises instead.
_MAX_CONDITION = 1e10


class IllConditioned(np.linalg.LinAlgError):
    """Leaving these units out leaves the fit (nearly) undetermined."""


def woodbury_weights(h_jj: np.ndarray) -> np.ndarray:
    """M = (I − H_JJ)⁻¹ for the hat matrix block of the missing units; raises
    :class:`IllConditioned` when the units cannot be left out without a new factorisation."""
    k = h_jj.shape[0]
    cap = np.eye(k) - h_jj
    cap = 0.5 * (cap + cap.T)  # symmetric by construction; remove rounding asymmetry
    try:
        inv = np.linalg.inv(cap)
    except np.linalg.LinAlgError:
        inv = None
    # 1-norm condition number from the inverse (cheaper than the spectrum for large k)
    cond = np.inf if inv is None else float(np.abs(cap).sum(axis=0).max() * np.abs(inv).sum(axis=0).max())
    if not cond <= _MAX_CONDITION:
        raise IllConditioned(f"leaving {k} unit(s) out leaves the fit undetermined (condition {cond:.3g})")
    return cast(np.ndarray, inv)  # not None: its condition is finite


class LeaveOut:
    """Columns of one all-valid least-squares fit, for leaving units out.

    Either ``hat`` (units × units, the dense hat matrix H of a small grid; the caller holds the
    dense data → field maps whose columns are the Y_J) or ``solver`` (the all-valid
    :class:`FixedSolver` of A) and ``obs`` (O, units × unknowns) for large grids, where the
    columns Y_j = A⁻¹ O_jᵀ and H e_j = O Y_j are solved per unit on first use and kept for the
    ``capacity`` most recently used units (at most ``budget`` new ones per call, see
    :meth:`affordable`).  Cache state changes only the time taken, never the
    numbers (each column is computed alone, whatever else is missing).
    """

    def __init__(
        self,
        *,
        hat: np.ndarray | None = None,
        solver: FixedSolver | None = None,
        obs: sp.csr_matrix | None = None,
        capacity: int = 256,
        budget: int = 24,
    ):
        if (hat is None) == (solver is None):
            raise ValueError("give either the dense hat matrix or a solver and its data operator")
        if solver is not None and obs is None:
            raise ValueError("a solver needs its data operator obs")
        self.hat = hat
        self.solver = solver
        self.obs = None if obs is None else sp.csr_matrix(obs)
        self.units: int = hat.shape[0] if hat is not None else cast(sp.csr_matrix, self.obs).shape[0]
        self.capacity = int(capacity)
        self.budget = min(int(budget), self.capacity)
        self._columns: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._weights: OrderedDict[bytes, np.ndarray] = OrderedDict()

    @property
    def dense(self) -> bool:
        return self.hat is not None

    def _fetch(self, missing: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """(Y_j, H e_j) of the given units, solving the uncached ones."""
        for j in dict.fromkeys(missing.tolist()):
            if j not in self._columns:
                # one unit at a time: a column's digits must not depend on which other units
                # happened to be solved with it (batched products may sum in another order)
                y = cast(FixedSolver, self.solver).solve(cast(sp.csr_matrix, self.obs)[j].toarray().ravel())
                self._columns[j] = (y, self.obs @ y)
        out = []
        for j in missing.tolist():
            self._columns.move_to_end(j)
            out.append(self._columns[j])
        while len(self._columns) > max(self.capacity, missing.size):
            self._columns.popitem(last=False)
        return out

    def affordable(self, missing: np.ndarray) -> bool:
        """Whether leaving these units out beats a new factorisation: always on small grids;
        on large ones while at most ``budget`` of them still need their columns solved (each
        is a solve with the all-valid factor; beyond that one factorisation of the mask is
        cheaper).  Depends on which units earlier calls left out, i.e. on the sequence of
        masks seen, never on time."""
        if self.dense:
            return True
        return sum(j not in self._columns for j in missing.tolist()) <= self.budget

    def solution_columns(self, missing: np.ndarray) -> np.ndarray:
        """Y_J = A⁻¹ O_Jᵀ, (unknowns, k) (large grids only)."""
        if self.dense:
            raise ValueError("dense leave-out: take Y_J from the dense field maps")
        if missing.size == 0:
            return np.zeros((cast(FixedSolver, self.solver).size, 0))
        return np.stack([c[0] for c in self._fetch(missing)], axis=1)

    def hat_columns(self, missing: np.ndarray) -> np.ndarray:
        """H[:, J], (units, k)."""
        if self.dense:
            return cast(np.ndarray, self.hat)[missing].T  # symmetric: a contiguous row gather
        if missing.size == 0:
            return np.zeros((self.units, 0))
        return np.stack([c[1] for c in self._fetch(missing)], axis=1)

    def weights(self, missing: np.ndarray) -> np.ndarray:
        """M = (I − H_JJ)⁻¹ for the missing units J (ascending indices), cached per set."""
        key = missing.tobytes()
        m = self._weights.get(key)
        if m is None:
            m = woodbury_weights(self.hat_columns(missing)[missing])
            self._weights[key] = m
            if len(self._weights) > 16:
                self._weights.popitem(last=False)
        else:
            self._weights.move_to_end(key)
        return m
