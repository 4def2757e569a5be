"""Shape → elements: each mounted element's position, normal, uncertainty and validity flags on
a reconstructed surface. Pure functions on numpy arrays; the layout is fixed per sheet geometry.

Element coordinates are material coordinates (u, v) in mm on the flat sheet, in the cells'
frame (docs/architecture.md); ``offset_mm`` moves an element along the upper normal.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any, Protocol

import numpy as np

from skinmap.wire.messages import ElementFlag

__all__ = ["ElementLayout", "LocatableSurface", "element_layout", "locate_elements", "element_flags",
           "fit_inconsistent", "prior_elements", "held_flags", "DEGRADED_SIGMA_MM", "INCONSISTENT_RESIDUAL_RAD",
           "INCONSISTENT_RESIDUAL_SIGMAS", "UNKNOWN_SIGMA_MM"]

# An element whose 1-s.d. position uncertainty exceeds this is flagged DEGRADED.
DEGRADED_SIGMA_MM = 0.5
# Fit misfit (rad per gauge) above which a scan's strains are inconsistent with any one smooth
# sheet: every element is flagged DEGRADED. Legitimate shapes of the forward model stay below
# 1.7e-3 rad (8x8 and 16x16: palm, membrane, balloon, tight cylinders and spheres); independent
# random bends of ±2.5 rad per gauge give 0.006-0.016. The limit grows with the strain noise.
INCONSISTENT_RESIDUAL_RAD = 0.005
INCONSISTENT_RESIDUAL_SIGMAS = 5.0
# The uncertainty published where none is known (never NaN on the wire).
UNKNOWN_SIGMA_MM = 1e3


class LocatableSurface(Protocol):
    """What a reconstructed surface offers here: ``locate(uv)`` → (positions, normals[, σ]),
    optionally ``locate_sigma(uv)`` and ``mirror`` (skinmap.reconstruction.Surface)."""

    def locate(self, uv: np.ndarray) -> tuple[np.ndarray, ...]: ...


@dataclass(frozen=True)
class ElementLayout:
    """Where the elements sit on the sheet, and what of the sheet each one rests on."""

    uv_mm: np.ndarray  # (K, 2) material coordinates
    offset_mm: np.ndarray  # (K,) along the upper normal
    neighbour_cells: np.ndarray  # (K, N·M) bool: cells within 1.5 pitches (Chebyshev)
    extrapolated: np.ndarray  # (K,) bool: outside the cells' span
    # (K,) bool: on the sheet (within half a pitch beyond its outer cells, where a surface is
    # located); an element beyond is not located (a layout for a larger sheet)
    on_sheet: np.ndarray

    @property
    def count(self) -> int:
        return int(self.uv_mm.shape[0])

    @cached_property
    def all_on_sheet(self) -> bool:
        """Whether every element is on the sheet (the usual layout: nothing to fill in)."""
        return bool(self.on_sheet.all())

    @property
    def located_uv(self) -> np.ndarray:
        """(L, 2) the material coordinates of the elements on the sheet."""
        return self.uv_mm[self.on_sheet]

    def off_sheet_problem(self, n: int, m: int) -> str:
        """What is wrong with the layout on an N×M sheet ("" if every element is on it)."""
        off = int(np.count_nonzero(~self.on_sheet))
        if not off:
            return ""
        first = self.uv_mm[~self.on_sheet][0]
        return (f"{off} of {self.count} elements lie off the {n}x{m} sheet (the first at u = {first[0]:g}, "
                f"v = {first[1]:g} mm): not located, published on the flat sheet without VALID; check [elements]")


def element_layout(uv_mm: np.ndarray, offset_mm: np.ndarray, cell_uv_mm: np.ndarray, pitch_mm: float) -> ElementLayout:
    """The layout of elements at ``uv_mm`` (K, 2) with offsets (K,) on cells at ``cell_uv_mm``
    (N, M, 2) of pitch ``pitch_mm``."""
    uv = np.asarray(uv_mm, dtype=np.float64).reshape(-1, 2)
    offset = np.asarray(offset_mm, dtype=np.float64).reshape(-1)
    if offset.shape[0] != uv.shape[0]:
        raise ValueError(f"{offset.shape[0]} element offsets for {uv.shape[0]} element coordinates")
    cells = np.asarray(cell_uv_mm, dtype=np.float64).reshape(-1, 2)
    dist = np.abs(uv[:, None, :] - cells[None, :, :]).max(axis=2)
    half = np.abs(cells).max(axis=0) if cells.size else np.zeros(2)
    extrapolated = (np.abs(uv[:, 0]) > half[0] + 1e-9) | (np.abs(uv[:, 1]) > half[1] + 1e-9)
    edge = half + 0.5 * pitch_mm + 1e-9
    on_sheet = (np.abs(uv[:, 0]) <= edge[0]) & (np.abs(uv[:, 1]) <= edge[1])
    return ElementLayout(uv, offset, dist <= 1.5 * pitch_mm, extrapolated, on_sheet)


def locate_elements(surface: LocatableSurface, layout: ElementLayout,
                    sigma_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions (K, 3) mm, unit normals (K, 3), σ (K,) mm, NaN where the surface gives none).
    ``sigma_mm``: the σ of the elements on the sheet (``layout.located_uv``) where the caller
    read it already (skinmapd reads it with the cell centres').  An element off the sheet is not
    located: it stays where :func:`prior_elements` puts it, σ unknown."""
    k = layout.count
    if k == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    on = layout.on_sheet
    every = layout.all_on_sheet
    uv = layout.uv_mm if every else layout.uv_mm[on]
    if uv.shape[0] == 0:
        return prior_elements(layout)[:3]
    out = surface.locate(uv)
    p_on, n_on = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.float64)
    locate_sigma: Any = getattr(surface, "locate_sigma", None)
    if sigma_mm is not None:
        s_on = np.asarray(sigma_mm, dtype=np.float64)
    elif len(out) > 2:
        s_on = np.asarray(out[2], dtype=np.float64)
    elif locate_sigma is not None:
        s_on = np.asarray(locate_sigma(uv), dtype=np.float64)
    else:
        s_on = np.full(uv.shape[0], np.nan)
    if every:
        return p_on + layout.offset_mm[:, None] * n_on, n_on, s_on
    pos, nrm, sig, _ = prior_elements(layout)
    pos[on] = p_on + layout.offset_mm[on][:, None] * n_on
    nrm[on], sig[on] = n_on, s_on
    return pos, nrm, sig


def fit_inconsistent(residual_rad: float, turning_noise_rad: float) -> bool:
    """Whether a fit's misfit says no one smooth sheet explains the scan's strains."""
    return bool(residual_rad > max(INCONSISTENT_RESIDUAL_RAD, INCONSISTENT_RESIDUAL_SIGMAS * turning_noise_rad))


def element_flags(layout: ElementLayout, sigma_mm: np.ndarray, gauge_valid: np.ndarray, *, ambiguous: bool,
                  inconsistent: bool) -> np.ndarray:
    """(K,) uint8 ElementFlag bits of elements located with uncertainty ``sigma_mm`` on a scan
    whose usable gauges are ``gauge_valid`` (2, 2, N, M)."""
    flags = np.full(layout.count, int(ElementFlag.VALID), dtype=np.uint8)
    flags[layout.extrapolated] |= int(ElementFlag.EXTRAPOLATED)
    # (an element off the sheet is not located: no current estimate)
    flags[~layout.on_sheet] = int(ElementFlag.EXTRAPOLATED) | int(ElementFlag.DEGRADED)
    with np.errstate(invalid="ignore"):
        flags[np.asarray(sigma_mm) > DEGRADED_SIGMA_MM] |= int(ElementFlag.DEGRADED)
    valid = np.asarray(gauge_valid, dtype=bool)
    if not valid.all():
        # Elements near a gauge the scan could not use rest on the prior there.
        bad_cells = (~valid).any(axis=(0, 1)).ravel()
        flags[layout.neighbour_cells[:, bad_cells].any(axis=1)] |= int(ElementFlag.DEGRADED)
        # With no usable unit (both layers read) anywhere near, the position is the prior
        # alone, not a current estimate.
        measured_cells = (valid[0] & valid[1]).any(axis=0).ravel()
        unmeasured = ~layout.neighbour_cells[:, measured_cells].any(axis=1)
        flags[unmeasured] = (flags[unmeasured] & (0xFF ^ int(ElementFlag.VALID))) | int(ElementFlag.DEGRADED)
    if ambiguous:
        # the gauges cannot tell this shape from its mirror image (Surface.mirror)
        flags |= int(ElementFlag.AMBIGUOUS)
    if inconsistent:
        flags |= int(ElementFlag.DEGRADED)
    return flags


def held_flags(flags: np.ndarray) -> np.ndarray:
    """The flags of elements held from an earlier frame: STALE added."""
    return (np.asarray(flags) | int(ElementFlag.STALE)).astype(np.uint8)


def prior_elements(layout: ElementLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the elements are before any frame was located: on the flat sheet, normals +z,
    σ unknown, flagged STALE only (not VALID)."""
    k = layout.count
    pos = np.concatenate([layout.uv_mm, layout.offset_mm[:, None]], axis=1)
    nrm = np.broadcast_to([0.0, 0.0, 1.0], (k, 3)).copy()
    return pos, nrm, np.full(k, UNKNOWN_SIGMA_MM), np.full(k, int(ElementFlag.STALE), dtype=np.uint8)
