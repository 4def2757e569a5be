"""The calibration procedure's poses as emulator scenes: the sheet flat, stretched in a frame,
or wrapped on a cylindrical mold along its rows or columns, each placed with a given error of
the mold's axis and of its centre.

    shape = mold_scene("cylinder", 5, 5, 12.0, radius=40.0, direction="rows", axis_error_deg=2.0)

Kinematic scenes are the closed-form maps (a stretched flat sheet, the isometric wrap);
elastic ones are solved films (skinmap.emulator.scenes: the biaxial pre-stretch frame, the film
laid frictionless on the cylinder).  A cylinder's strains do not change when the sheet lies off
its centre (the mold is uniform along and around its axis), so an off-centre placement only
moves the sheet: ``offset_mm`` is applied as that rigid motion, which the gauges cannot see.
"""
from __future__ import annotations

import math

import numpy as np

from skinmap.emulator import physics as ph

__all__ = ["StretchedFlat", "mold_scene"]


class StretchedFlat(ph.Shape):
    """The flat sheet stretched uniformly by ``stretch`` in both directions (held in a frame)."""

    def __init__(self, stretch: float = 0.05):
        self.stretch = float(stretch)
        if not (math.isfinite(self.stretch) and -0.5 < self.stretch < 1.0):
            raise ValueError(f"stretch must be in (-0.5, 1), got {stretch!r}")

    def position(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        uv = ph._as_uv(uv)
        return np.concatenate([(1.0 + self.stretch) * uv, np.zeros(uv.shape[:-1] + (1,))], axis=-1)

    def normal(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        uv = ph._as_uv(uv)
        return np.broadcast_to(np.array([0.0, 0.0, 1.0]), uv.shape[:-1] + (3,)).copy()


class _Moved(ph.Shape):
    """A shape moved rigidly by ``offset`` (mm, 3 components): the sheet off the mold's centre."""

    def __init__(self, shape: ph.Shape, offset: tuple[float, float, float]):
        self.shape = shape
        self.offset = np.asarray(offset, dtype=float)
        self.time_varying = shape.time_varying

    def position(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        return self.shape.position(uv, t) + self.offset

    def normal(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        return self.shape.normal(uv, t)

    def layer_strains(self, *args, **kwargs) -> np.ndarray:
        return self.shape.layer_strains(*args, **kwargs)


def mold_scene(kind: str, n: int, m: int, pitch: float = 12.0, *, radius: float = 0.0, direction: str = "rows",
               stretch: float = 0.0, axis_error_deg: float = 0.0, offset_mm: float = 0.0,
               mechanics: str = "kinematic") -> ph.Shape:
    """The scene of one calibration pose ('flat', 'stretch', 'cylinder', 'dome'); ValueError names a bad
    parameter."""
    if mechanics not in ("kinematic", "elastic"):
        raise ValueError(f"mechanics must be 'kinematic' or 'elastic', got {mechanics!r}")
    if kind == "flat":
        return ph.Flat()
    if kind == "stretch":
        if mechanics == "kinematic":
            return StretchedFlat(stretch)
        from skinmap.emulator.scenes import make_scene

        return make_scene("flat", n, m, pitch, prestretch=float(stretch))
    if kind == "dome":
        # a sphere cap; elastic: the film slides on it frictionless (a lubricated mold)
        if mechanics == "kinematic":
            return ph.SphereCap(radius)
        from skinmap.emulator.scenes import make_scene

        return make_scene("sphere", n, m, pitch, radius=float(radius))
    if kind != "cylinder":
        raise ValueError(f"mold kind must be 'flat', 'stretch', 'cylinder' or 'dome', got {kind!r}")
    if direction not in ("rows", "columns"):
        raise ValueError(f"a cylinder runs along 'rows' or 'columns', got {direction!r}")
    # axis_angle 0 puts the axis along v: the circumference follows u, the rows
    angle = (0.0 if direction == "rows" else 90.0) + float(axis_error_deg)
    if mechanics == "kinematic":
        shape: ph.Shape = ph.Cylinder(radius, axis_angle=angle)
    else:
        from skinmap.emulator.scenes import make_scene

        shape = make_scene("cylinder", n, m, pitch, radius=float(radius), axis_angle=angle)
    if offset_mm:
        th = math.radians(angle)
        shape = _Moved(shape, (offset_mm * math.sin(th), offset_mm * math.cos(th), 0.0))
    return shape
