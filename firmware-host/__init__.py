"""skinmap.emulator: the scanner-firmware emulator and the physics forward model.

- :mod:`skinmap.emulator.physics` — shapes and the Kirchhoff–Love gauge forward model (pure numpy).
"""
from __future__ import annotations

from skinmap.emulator.physics import (  # noqa: F401  (re-exported)
    Shape,
    cell_centres,
    gauge_strains,
    ground_truth,
    make_shape,
    parse_shape_spec,
)

__all__ = ["Shape", "cell_centres", "gauge_strains", "ground_truth", "make_shape", "parse_shape_spec"]
