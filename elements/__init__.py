"""skinmap.elements: shape → per-element positions, normals, uncertainty and flags (pure
functions; :mod:`~skinmap.elements.locate`)."""
from __future__ import annotations

from skinmap.elements.locate import (DEGRADED_SIGMA_MM, INCONSISTENT_RESIDUAL_RAD, INCONSISTENT_RESIDUAL_SIGMAS,
                                     UNKNOWN_SIGMA_MM, ElementLayout, LocatableSurface, element_flags,
                                     element_layout, fit_inconsistent, held_flags, locate_elements, prior_elements)

__all__ = ["DEGRADED_SIGMA_MM", "INCONSISTENT_RESIDUAL_RAD", "INCONSISTENT_RESIDUAL_SIGMAS", "UNKNOWN_SIGMA_MM",
           "ElementLayout", "LocatableSurface", "element_layout", "element_flags", "fit_inconsistent",
           "held_flags", "locate_elements", "prior_elements"]
