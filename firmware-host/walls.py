"""Tactile mapping scene: a balloon probe (the sheet laid on it) pressed against a cavity wall
that carries a relief of raised letters, moved and turned between presses.

    wall = LetterRelief()                                   # 'D', 'U', 'K', 'E' on 120 × 120 mm
    shape = BalloonOnWall(wall, centre=(-30, 30), angle_deg=20, depth=3.0)
    wall.height(xy)                                          # ground truth, mm

Frames.  Probe frame: the balloon's apex at the origin, its outward normal +z, the sheet's
centre on the apex (the sheet's sensor frame at rest).  Wall frame: the wall's base plane
z_w = 0, the relief rising from it towards the probe by H(x_w, y_w) ≥ 0.  A press puts the wall's
base plane at z = −depth in the probe frame (facing it, so wall height H sits at z = −depth − H)
with the probe frame's (x, y) at the wall's ``centre`` + R(angle)·(x, y).

Kinematic form: the sheet keeps its place on the balloon (geodesic polar map, as
:class:`~skinmap.emulator.physics.SphereCap`) and, where the balloon would pass through the wall,
is pushed back along −z onto it (a softplus of width ``smoothing`` rounds the contact's rim), as
:class:`~skinmap.emulator.physics.BalloonDome` does for a dome: a balloon soft enough to take the
wall's shape over the contact.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skinmap.emulator import physics as ph

__all__ = ["LetterRelief", "FlatPlate", "BalloonOnWall", "PressSequence", "LETTER_STROKES", "Membrane",
           "solve_membrane"]


def _arc(cx: float, cy: float, r: float, a0: float, a1: float, pieces: int = 8) -> list[tuple[float, float, float, float]]:
    a = np.radians(np.linspace(a0, a1, pieces + 1))
    x, y = cx + r * np.cos(a), cy + r * np.sin(a)
    return [(x[i], y[i], x[i + 1], y[i + 1]) for i in range(pieces)]


#: Stroke centre lines (x0, y0, x1, y1) of each letter in a box of ±25 mm about its centre.
LETTER_STROKES: dict[str, list[tuple[float, float, float, float]]] = {
    "D": [(-18, -22, -18, 22), (-18, 22, 0, 22), (-18, -22, 0, -22)] + _arc(0, 0, 22, 90, -90),
    "U": [(-18, 22, -18, -4), (18, 22, 18, -4)] + _arc(0, -4, 18, 180, 360),
    "K": [(-18, -22, -18, 22), (-12, 0, 18, 22), (-12, 0, 18, -22)],
    "E": [(-18, -22, -18, 22), (-18, 22, 18, 22), (-18, 0, 12, 0), (-18, -22, 18, -22)],
}


class LetterRelief:
    """Raised letters on a wall: strokes ``width`` wide (the smallest feature), ``height`` high,
    their flanks rising over ``edge`` mm (a smooth step).  Four letters: each centred in a
    quadrant of a ``size`` × ``size`` mm wall centred on the origin.  One letter: the letter
    alone spans the wall (its stroke centre lines scaled to ``size``, the strokes still ``width``
    wide), as in the paper's cavity, one wall a letter."""

    def __init__(self, letters: str = "DUKE", size: float = 120.0, width: float = 15.0, height: float = 4.0,
                 edge: float = 6.0):
        if len(letters) not in (1, 4) or any(c not in LETTER_STROKES for c in letters):
            raise ValueError(f"one letter or four out of {''.join(LETTER_STROKES)}, got {letters!r}")
        for name, v in (("size", size), ("width", width), ("height", height), ("edge", edge)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"relief {name} must be > 0 mm, got {v!r}")
        self.letters, self.size, self.width, self.relief, self.edge = letters, float(size), float(width), float(height), float(edge)
        q = size / 4.0
        centres = [(-q, q), (q, q), (-q, -q), (q, -q)] if len(letters) == 4 else [(0.0, 0.0)]
        # the letters' box is ±25 mm: a quadrant of 60 mm, or the whole wall for one letter
        scale = size / (120.0 if len(letters) == 4 else 60.0)
        segs = []
        for c, (cx, cy) in zip(letters, centres):
            segs += [(cx + scale * a, cy + scale * b, cx + scale * c2, cy + scale * d) for a, b, c2, d in LETTER_STROKES[c]]
        self._segs = np.asarray(segs, dtype=float)
        self._raster_step, self._raster_half = 0.5, 0.5 * self.size + 4.0
        self._coeffs: np.ndarray | None = None

    def distance(self, xy: np.ndarray) -> np.ndarray:
        """Distance (mm) of wall points (..., 2) to the nearest stroke centre line."""
        p = np.asarray(xy, dtype=float)[..., None, :]
        a, b = self._segs[:, :2], self._segs[:, 2:]
        ab = b - a
        t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
        d = np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)
        return d.min(axis=-1)

    def _exact_height(self, xy: np.ndarray) -> np.ndarray:
        x = np.clip((0.5 * self.width + 0.5 * self.edge - self.distance(xy)) / self.edge, 0.0, 1.0)
        return self.relief * x * x * (3.0 - 2.0 * x)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Relief height H (mm) at wall points (..., 2): ``height`` on a stroke, 0 off it, a
        smoothstep across the flank; 0 outside the wall's square.  Evaluated as a cubic spline
        through the exact profile on a 0.5 mm raster (the emulator evaluates it for every
        quadrature point of every gauge of every scan); that spline is the relief, truth included."""
        xy = np.asarray(xy, dtype=float)
        if self._coeffs is None:
            from scipy import ndimage

            c = -self._raster_half + self._raster_step * np.arange(int(round(2 * self._raster_half / self._raster_step)) + 1)
            xx, yy = np.meshgrid(c, c)
            self._coeffs = ndimage.spline_filter(self._exact_height(np.stack([xx, yy], -1)), order=3)
        from scipy import ndimage

        idx = (xy + self._raster_half) / self._raster_step
        flat = idx.reshape(-1, 2)
        h = ndimage.map_coordinates(self._coeffs, [flat[:, 1], flat[:, 0]], order=3, prefilter=False, mode="nearest")
        h = h.reshape(xy.shape[:-1])
        inside = np.all(np.abs(xy) <= 0.5 * self.size, axis=-1)
        return np.where(inside, h, 0.0)


class FlatPlate:
    """A flat wall (no relief), ``size`` mm square: the plate a probe is pressed on at known
    depths to fit its stiffness length (skinmap.daemon.tactile.fit_probe_length)."""

    relief = 0.0

    def __init__(self, size: float = 120.0) -> None:
        if not (math.isfinite(size) and size > 0):
            raise ValueError(f"plate size must be > 0 mm, got {size!r}")
        self.size = float(size)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """0 mm everywhere (the plate's base plane)."""
        return np.zeros(np.shape(xy)[:-1])


@dataclass(frozen=True)
class Membrane:
    """The pressed sheet as a tensioned, bending film on the balloon (docs/tactile.md).

    ``tension`` T (N/mm): the balloon's wall tension (docs/physics.md: 0.15 mm polyurethane at
    about 2.5 kPa, R 80 mm); the pressure is Laplace's p = 2T/R, so a free span curves no
    tighter than T/p = R/2.  ``bending`` D (N·mm): the sensor film's (docs/physics.md), which
    rounds what the wall would bend sharper over the length √(D/T) (0.9 mm).  ``stretch`` E·t
    (N/mm): the balloon wall's membrane stiffness (polyurethane, E ≈ 20 MPa, t 0.15 mm); a
    curved wall resists being pushed off its sphere by stretching around it, as a foundation of
    modulus E·t/R² (the shallow-shell analogy), so a push spreads over √(T·R²/(E·t)) ≈ 15 mm
    rather than over the whole balloon.  The solve is on a ``step`` mm grid out to ``half`` mm
    from the apex, where the balloon keeps its sphere."""

    tension: float = 0.1
    bending: float = 0.083
    stretch: float = 3.0
    step: float = 1.0
    half: float = 50.0

    def __post_init__(self) -> None:
        for name in ("tension", "bending", "stretch", "step", "half"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"membrane {name} must be > 0, got {v!r}")
        if self.half < 4 * self.step:
            raise ValueError(f"membrane half-width {self.half} mm is less than four grid steps of {self.step} mm")


def solve_membrane(gap: np.ndarray, load: np.ndarray, step: float, tension: float, bending: float,
                   foundation: float = 0.0, max_iterations: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """The deflection w (grid, mm) of a film under tension T and bending stiffness D from a
    reference shape (its equilibrium but for ``load``, N/mm², towards the wall), kept on the
    balloon's side by w ≤ ``gap`` (the wall minus the reference, mm), w = 0 on the grid's
    border: min ∫ T/2·|∇w|² + D/2·(Δw)² + k/2·w² − load·w subject to w ≤ gap (``foundation``
    k, N/mm³: what holds the film to its reference; small slopes; 5-point
    Laplacian, primal–dual active set).  Returns (w, the nodes held by the wall).  RuntimeError
    if the active set does not settle."""
    from scipy import sparse
    from scipy.sparse.linalg import splu

    gap = np.asarray(gap, dtype=float)
    if gap.ndim != 2 or gap.shape[0] != gap.shape[1] or gap.shape[0] < 5 or load.shape != gap.shape:
        raise ValueError(f"gap and load must be the same square grid of at least 5 nodes, got {gap.shape} and {load.shape}")
    n = gap.shape[0] - 2
    e = np.ones(n)
    lap1 = sparse.diags([-e[:-1], 2.0 * e, -e[:-1]], [-1, 0, 1]) / step ** 2
    eye = sparse.identity(n)
    lap = (sparse.kron(eye, lap1) + sparse.kron(lap1, eye)).tocsr()
    k = (tension * lap + bending * (lap @ lap) + foundation * sparse.identity(n * n)).tocsr()
    g = gap[1:-1, 1:-1].ravel()
    f = np.asarray(load, dtype=float)[1:-1, 1:-1].ravel()
    active = g <= 0.0  # start where the reference passes through the wall
    c = float(k.diagonal().mean())
    for _ in range(max_iterations):
        w = np.where(active, g, 0.0)
        free = ~active
        if free.any():
            kf = k[free]
            w[free] = splu(kf[:, free].tocsc()).solve(f[free] - kf[:, active] @ g[active])
        lam = f - k @ w  # the wall's reaction (≥ 0 where it holds the film)
        lam[free] = 0.0
        # nodes where the wall neither pushes nor is passed (both within rounding) stay free
        new = lam + c * (w - g) > 1e-9 * c
        if np.array_equal(new, active):
            break
        active = new
    else:
        raise RuntimeError(f"the membrane's contact did not settle in {max_iterations} iterations")
    out = np.zeros_like(gap)
    out[1:-1, 1:-1] = w.reshape(n, n)
    held = np.zeros(gap.shape, dtype=bool)
    held[1:-1, 1:-1] = active.reshape(n, n)
    return out, held


class BalloonOnWall(ph.Shape):
    """The sheet on a balloon of radius ``balloon_radius`` pressed ``depth`` mm against the wall
    (see the module's frames); ``depth`` ≤ 0 leaves the balloon free (the baseline).  With
    ``membrane_radius`` (mm; T/p, half the balloon's radius for its own wall tension) the sheet
    bridges what a pressurised membrane cannot follow (see ``_bridged_wall``); with
    ``membrane`` (:class:`Membrane`) it is solved as the pressed film (see ``_membrane``);
    without either, it takes the wall's shape exactly (a balloon infinitely soft)."""

    def __init__(self, wall: LetterRelief | FlatPlate, centre: tuple[float, float] = (0.0, 0.0),
                 angle_deg: float = 0.0, depth: float = 3.0, balloon_radius: float = 80.0, smoothing: float = 0.3,
                 membrane_radius: float | None = None, membrane: Membrane | None = None):
        self.wall = wall
        self.centre = (float(centre[0]), float(centre[1]))
        self.angle_deg = float(angle_deg)
        self.depth = float(depth)
        self.balloon_radius = float(balloon_radius)
        self.smoothing = float(smoothing)
        if not all(math.isfinite(v) for v in (*self.centre, self.angle_deg, self.depth)):
            raise ValueError("press centre, angle and depth must be finite")
        if not (self.balloon_radius > 0 and self.smoothing > 0):
            raise ValueError("balloon radius and smoothing must be > 0 mm")
        self._sphere = ph.SphereCap(self.balloon_radius)
        self.membrane_radius = membrane_radius
        self._envelope: np.ndarray | None = None
        if membrane_radius is not None:
            if not (math.isfinite(membrane_radius) and membrane_radius > 0):
                raise ValueError(f"membrane radius must be > 0 mm, got {membrane_radius!r}")
            self._envelope = self._bridged_wall(float(membrane_radius))
        if membrane is not None and membrane_radius is not None:
            raise ValueError("give a membrane radius (the bridging envelope) or a membrane (the solved film), not both")
        self.membrane = membrane
        self._deflection: np.ndarray | None = None
        self.held: np.ndarray | None = None  # the membrane grid's nodes the wall holds
        if membrane is not None:
            self._deflection, self.held = self._membrane(membrane)

    # the envelope's raster (probe frame): covers a sheet of up to 100 mm across
    _ENV_HALF, _ENV_STEP = 60.0, 1.0

    def _bridged_wall(self, rho: float) -> np.ndarray:
        """Spline coefficients of the wall as a pressurised membrane meets it: where the wall
        recedes (between raised strokes) the membrane spans over, curved no tighter than ρ
        (its tension over its pressure, T/p): the wall opened from the probe's side by a ball
        of radius ρ (erosion, then dilation, by the ball's cap)."""
        from scipy import ndimage

        c = -self._ENV_HALF + self._ENV_STEP * np.arange(int(round(2 * self._ENV_HALF / self._ENV_STEP)) + 1)
        xx, yy = np.meshgrid(c, c)
        w = self.wall_z(np.stack([xx, yy], -1))
        r = int(math.ceil(rho / self._ENV_STEP))
        d = np.arange(-r, r + 1) * self._ENV_STEP
        dx, dy = np.meshgrid(d, d)
        q = rho ** 2 - dx ** 2 - dy ** 2
        foot = q >= 0
        cap = np.where(foot, np.sqrt(np.maximum(q, 0.0)), 0.0)
        padded = np.pad(w, r, mode="edge")
        eroded = ndimage.grey_erosion(padded, footprint=foot, structure=cap, mode="nearest")
        opened = ndimage.grey_dilation(eroded, footprint=foot, structure=cap, mode="nearest")[r:-r, r:-r]
        return ndimage.spline_filter(np.minimum(opened, w), order=3)

    def _membrane(self, mem: Membrane) -> tuple[np.ndarray, np.ndarray]:
        """The film's deflection from the free balloon where the wall presses into it.  The free
        balloon is the film's equilibrium under p = 2T/R (a sphere), so the deflection w from it
        carries no load of its own: the wall pushes it in (w ≤ wall − sphere), tension, bending
        and the curved wall's stretch spread the push around the contact, and the balloon is on
        its sphere at the model's edge ``half`` mm from the apex.  Between raised
        strokes the film spans back towards the floor curved no tighter than T/p, its bends
        rounded over √(D/T) (solve_membrane).  Spline coefficients of w on the membrane's grid,
        and the nodes the wall holds."""
        from scipy import ndimage

        c = -mem.half + mem.step * np.arange(int(round(2 * mem.half / mem.step)) + 1)
        xx, yy = np.meshgrid(c, c)
        zs = self._sphere_z(np.stack([xx, yy], -1))
        gap = self.wall_z(np.stack([xx, yy], -1)) - zs
        w, held = solve_membrane(gap, np.zeros_like(gap), mem.step, mem.tension, mem.bending,
                                 mem.stretch / self.balloon_radius ** 2)
        return ndimage.spline_filter(w, order=3), held

    def _sphere_z(self, xy: np.ndarray) -> np.ndarray:
        r = self.balloon_radius
        return -(r - np.sqrt(np.maximum(r * r - (np.asarray(xy, dtype=float) ** 2).sum(-1), 0.0)))

    def deflection(self, xy: np.ndarray) -> np.ndarray:
        """The membrane's deflection w (mm, ≤ 0: pushed in) from the reference at probe (x, y)."""
        if self._deflection is None or self.membrane is None:
            return np.zeros(np.shape(xy)[:-1])
        from scipy import ndimage

        m = self.membrane
        xy = np.asarray(xy, dtype=float)
        idx = ((xy + m.half) / m.step).reshape(-1, 2)
        w = ndimage.map_coordinates(self._deflection, [idx[:, 1], idx[:, 0]], order=3, prefilter=False, mode="constant")
        return w.reshape(xy.shape[:-1])

    def clearance(self, xy: np.ndarray) -> np.ndarray:
        """How far (mm, along z) the sheet stands off the wall at probe (x, y): 0 where it
        touches (the ground truth of where the relief itself is felt)."""
        xy = np.asarray(xy, dtype=float)
        z = self.position_at_xy(xy, self._sphere_z(xy))
        return np.maximum(self.wall_z(xy) - z, 0.0)

    def position_at_xy(self, xy: np.ndarray, zs: np.ndarray) -> np.ndarray:
        """The sheet's height at probe (x, y) where the free balloon's height is ``zs``."""
        if self.membrane is not None:
            return np.minimum(zs + self.deflection(xy), self.wall_z(xy))
        s = self.smoothing
        return zs - s * np.logaddexp(0.0, (zs - self.sheet_wall_z(xy)) / s)

    def sheet_wall_z(self, xy: np.ndarray) -> np.ndarray:
        """Where the sheet meets the wall (probe frame): the wall itself, or with a membrane
        radius the wall as the membrane bridges it."""
        if self._envelope is None:
            return self.wall_z(xy)
        from scipy import ndimage

        xy = np.asarray(xy, dtype=float)
        idx = ((xy + self._ENV_HALF) / self._ENV_STEP).reshape(-1, 2)
        z = ndimage.map_coordinates(self._envelope, [idx[:, 1], idx[:, 0]], order=3, prefilter=False, mode="nearest")
        return z.reshape(xy.shape[:-1])

    def to_wall(self, xy: np.ndarray) -> np.ndarray:
        """Probe-frame (x, y) → wall (x_w, y_w)."""
        th = math.radians(self.angle_deg)
        c, s = math.cos(th), math.sin(th)
        xy = np.asarray(xy, dtype=float)
        return np.stack([self.centre[0] + c * xy[..., 0] - s * xy[..., 1],
                         self.centre[1] + s * xy[..., 0] + c * xy[..., 1]], axis=-1)

    def wall_z(self, xy: np.ndarray) -> np.ndarray:
        """The wall's surface in the probe frame at probe-frame (x, y)."""
        return -self.depth - self.wall.height(self.to_wall(xy))

    def position(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        x = self._sphere.position(ph._as_uv(uv))
        if self.depth <= -5.0 * self.smoothing - self.wall.relief:
            return x
        z = self.position_at_xy(x[..., :2], x[..., 2])
        return np.concatenate([x[..., :2], z[..., None]], axis=-1)

    def layer_strains(self, centres, directions, offsets, gauge_length, t, samples, panels) -> np.ndarray:
        # The pressed film is the solved deflection where it spans and the wall where the wall
        # holds it: its slope jumps where one meets the other (the film's bending rounds that
        # over √(D/T) ≈ 0.9 mm, finer than the solve's grid), and a quadrature's derivatives
        # read such a crease as a spike (one press of 64 read +75 % on both layers).
        if self.membrane is None:
            return super().layer_strains(centres, directions, offsets, gauge_length, t, samples, panels)
        return ph.creased_layer_strains(self, centres, directions, offsets, gauge_length, t)


class PressSequence(ph.Shape):
    """Presses one after the other: the free balloon for ``rest_s``, then press i (centre,
    angle, depth) held for ``hold_s``, the balloon free for ``gap_s`` between presses (moved and
    turned meanwhile), then free again.  ``presses``: [(x_mm, y_mm, angle_deg, depth_mm), ...].
    With ``membrane`` each press is the solved film (:class:`BalloonOnWall`'s ``membrane``: the
    rim pushed in too, as a real balloon's is), solved once here; without it the sheet takes the
    wall's shape exactly."""

    time_varying = True

    def __init__(self, wall: LetterRelief | FlatPlate, presses: list[tuple[float, float, float, float]],
                 rest_s: float = 1.0, hold_s: float = 1.0, gap_s: float = 0.5, balloon_radius: float = 80.0,
                 smoothing: float = 0.3, start_s: float = 0.0, membrane: Membrane | None = None):
        if not presses:
            raise ValueError("a press sequence needs at least one press")
        self.wall, self.rest_s, self.hold_s, self.gap_s = wall, float(rest_s), float(hold_s), float(gap_s)
        self.start_s = float(start_s)  # the shape clock's time at which the sequence begins
        self.presses = [BalloonOnWall(wall, (p[0], p[1]), p[2], p[3], balloon_radius, smoothing, membrane=membrane)
                        for p in presses]
        self._free = ph.SphereCap(balloon_radius)

    def press_at(self, t: np.ndarray) -> np.ndarray:
        """Index of the press held at each time (−1: none)."""
        t = np.asarray(t, dtype=float) - self.start_s - self.rest_s
        k = np.floor(t / (self.hold_s + self.gap_s)).astype(int)
        held = (t >= 0) & (t - k * (self.hold_s + self.gap_s) < self.hold_s) & (k < len(self.presses))
        return np.where(held, k, -1)

    @property
    def duration_s(self) -> float:
        return self.start_s + self.rest_s + len(self.presses) * (self.hold_s + self.gap_s)

    def position(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        uv = ph._as_uv(uv)
        t = np.broadcast_to(np.asarray(t, dtype=float), uv.shape[:-1])
        which = self.press_at(t)
        out = self._free.position(uv)
        for j in np.unique(which[which >= 0]):
            sel = which == j
            out[sel] = self.presses[int(j)].position(uv[sel])
        return out

    def layer_strains(self, centres, directions, offsets, gauge_length, t, samples, panels) -> np.ndarray:
        # each gauge read on the shape held at its own time, by that shape's own route (a solved
        # press reads its creases: BalloonOnWall.layer_strains)
        t = np.broadcast_to(np.asarray(t, dtype=float), (len(centres),))
        which = self.press_at(t)
        out = np.empty((len(offsets), len(centres)))
        for j in np.unique(which):
            sel = which == j
            shape: ph.Shape = self._free if j < 0 else self.presses[int(j)]
            out[:, sel] = shape.layer_strains(centres[sel], directions[sel], offsets, gauge_length, t[sel], samples,
                                              panels)
        return out
