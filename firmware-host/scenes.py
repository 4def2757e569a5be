"""Elastic scenes: the emulator's shapes with real mechanics behind them.

Every kinematic shape kind of :mod:`skinmap.emulator.physics` has an elastic form here, solved
with :mod:`skinmap.emulator.mechanics` and returned as a :class:`~skinmap.emulator.physics.Shape`,
so the gauges, the ground truth and the emulator use it unchanged:

| kind | elastic scene |
|---|---|
| `flat`, `cylinder`, `sphere`, `saddle`, `quadric`, `gaussian` (and sums) | the film laminated on a rigid mold of that height, sliding without friction (or with ``friction``), optionally pre-stretched in a frame (``prestretch``, ``prestretch_u``, ``prestretch_v``) |
| `membrane` | the film clamped on all four edges, indented by one or two rigid spherical fingertips (``finger_radius`` 8 mm) that press, release and slide |
| `balloon` | the film taped at its perimeter (``tape`` 5 mm) onto a pressurised balloon (``balloon_radius`` 80, wall ``tension`` 0.1 N/mm), indented by a rigid dome (``dome_radius`` 50, ``depth`` 7) or pressed against a wall relief (``indenter=1``: a ridge ``relief`` 4 mm high) |
| `palm` | the film laminated on a moving mold whose height morphs flat → cylinder → bump → saddle |

Time-varying scenes are solved at key frames over one cycle (each warm-started from the previous
one) and interpolated in time per node and per gauge by monotone cubic (PCHIP) interpolation, so
holds stay exactly still and a 5×5 moving scene streams at hundreds of scans per second.  Solves
are cached on disk by their parameters (``$SKINMAP_CACHE_DIR``, default
``~/.cache/skinmap/mechanics``).

Elastic-only parameters (all kinds): ``poisson`` (0.48), ``youngs`` (0.562 N/mm²),
``thickness`` (1 mm), ``bending`` (0.083 N·mm), ``mesh`` (1.5 mm), ``margin`` (half a pitch of
film beyond the outer cells), ``keyframes`` (time-varying scenes).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Literal, Mapping

import numpy as np
from scipy.interpolate import PchipInterpolator, RectBivariateSpline

from skinmap.emulator import mechanics as mc
from skinmap.emulator import physics as ph
from skinmap.strains import grid_size

__all__ = [
    "Mechanics",
    "SheetShape",
    "KeyframedSheet",
    "ELASTIC_PARAMETERS",
    "make_scene",
    "parse_scene_spec",
    "cache_directory",
]

Mechanics = Literal["kinematic", "elastic"]

# Bumped whenever a change of the mechanics changes solutions (invalidates the disk cache).
SOLVER_VERSION = 1

#: Parameters only the elastic form knows, with their defaults.
ELASTIC_PARAMETERS: dict[str, float | None] = {
    "poisson": 0.48,
    "youngs": 0.562,
    "thickness": 1.0,
    "bending": 0.083,
    "mesh": 1.5,
    "margin": None,
    "keyframes": None,
    # molds
    "prestretch": None,
    "prestretch_u": None,
    "prestretch_v": None,
    "friction": 0.0,
    # membrane
    "finger_radius": 8.0,
    # balloon
    "tension": 0.1,
    "tape": 5.0,
    "indenter": 0.0,
    "relief": 4.0,
    "relief_width": 15.0,
    "relief_angle": 0.0,
}

# Steepest mold slope a film may be laid on (a height field cannot wrap past 90°): 80°.
_MAX_SLOPE = math.tan(math.radians(80.0))
_MOLD_KINDS = ("flat", "cylinder", "sphere", "saddle", "quadric", "gaussian")
# A numerical anchor for the rotation of a film that only its centre pins (N/mm³ · Y/L²): small
# enough to change no strain by more than ~1e-6 of itself.
_ANCHOR = 1e-6


def cache_directory() -> Path:
    """Where solved scenes are kept: ``$SKINMAP_CACHE_DIR`` or ``~/.cache/skinmap/mechanics``."""
    env = os.environ.get("SKINMAP_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "skinmap" / "mechanics"


# --------------------------------------------------------------------------- shapes


class SheetShape(ph.Shape):
    """A solved sheet as a shape: the node positions (nv, nu, 3) on the material grid,
    interpolated by bicubic splines; normals from the splines' tangents."""

    def __init__(self, grid: mc.SheetGrid, positions: np.ndarray, label: str = "elastic sheet"):
        positions = np.asarray(positions, float)
        if positions.shape != (grid.nv, grid.nu, 3):
            raise ValueError(f"sheet positions must be {(grid.nv, grid.nu, 3)}, got {positions.shape}")
        self.grid = grid
        self.positions = positions
        self.label = label
        self._splines = [RectBivariateSpline(grid.v, grid.u, positions[..., c], kx=3, ky=3, s=0) for c in range(3)]

    def _eval(self, uv: np.ndarray, du: int, dv: int) -> np.ndarray:
        flat = uv.reshape(-1, 2)
        outside = (np.abs(flat[:, 0]) > self.grid.half_u + 1e-9) | (np.abs(flat[:, 1]) > self.grid.half_v + 1e-9)
        if outside.any():
            u, v = flat[np.flatnonzero(outside)[0]]
            raise ValueError(
                f"material point ({u:g}, {v:g}) mm lies outside the solved film "
                f"(±{self.grid.half_u:g} × ±{self.grid.half_v:g} mm): a larger film (margin, or the "
                "membrane's half_u/half_v) is needed for gauges or elements there")
        out = np.stack([s.ev(flat[:, 1], flat[:, 0], dx=dv, dy=du) for s in self._splines], axis=-1)
        return out.reshape(uv.shape[:-1] + (3,))

    def position(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        return self._eval(ph._as_uv(uv), 0, 0)

    def normal(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        uv = ph._as_uv(uv)
        return ph._normalise(np.cross(self._eval(uv, 1, 0), self._eval(uv, 0, 1)))

    def position_and_normal(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> tuple[np.ndarray, np.ndarray]:
        uv = ph._as_uv(uv)
        return self._eval(uv, 0, 0), ph._normalise(np.cross(self._eval(uv, 1, 0), self._eval(uv, 0, 1)))

    def layer_strains(self, centres, directions, offsets, gauge_length, t, samples, panels) -> np.ndarray:
        # the splines' curvature is piecewise linear between nodes: at least two quadrature panels
        # per node interval keep the readings within ~5e-8 of converged (one panel: ~4e-5)
        spans = 2 * math.ceil(gauge_length / min(self.grid.hu, self.grid.hv))
        return ph.quadrature_layer_strains(self, centres, directions, offsets, gauge_length, t, samples,
                                           max(panels, spans))

    def __repr__(self) -> str:
        return f"SheetShape({self.label}, {self.grid.nv}x{self.grid.nu} nodes)"


class _PeriodicPchip:
    """Monotone cubic interpolation of samples over one period, wrapped."""

    def __init__(self, times: np.ndarray, values: np.ndarray, period: float):
        self.t0 = float(times[0])
        self.period = float(period)
        t = np.concatenate([[times[-1] - period], times, [times[0] + period, times[1] + period]])
        v = np.concatenate([values[-1:], values, values[:2]], axis=0)
        self._p = PchipInterpolator(t, v, axis=0)

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        tt = self.t0 + np.mod(np.asarray(t, float) - self.t0, self.period)
        return self._p(tt)


class KeyframedSheet(ph.Shape):
    """A moving solved sheet: positions (K, nv, nu, 3) at key-frame times (K,) over one cycle
    of ``period`` s, interpolated in time per node by monotone cubics; gauge readings are computed
    exactly at every key frame (``key_frames``, each a :class:`SheetShape`) and interpolated the
    same way (no re-solve between frames)."""

    time_varying = True

    def __init__(self, grid: mc.SheetGrid, times: np.ndarray, positions: np.ndarray, period: float,
                 label: str = "elastic scene"):
        times = np.asarray(times, float)
        positions = np.asarray(positions, float)
        if positions.shape != (times.size, grid.nv, grid.nu, 3) or times.size < 2:
            raise ValueError(f"key frames must be (K >= 2, {grid.nv}, {grid.nu}, 3), got {positions.shape}")
        if np.any(np.diff(times) <= 0) or times[-1] - times[0] >= period:
            raise ValueError("key-frame times must increase within one period")
        self.grid = grid
        self.times = times
        self.positions = positions
        self.period = float(period)
        self.label = label
        self._nodes = _PeriodicPchip(times, positions, period)
        self.key_frames = [SheetShape(grid, p, f"{label} @ {t:g} s") for t, p in zip(times, positions)]
        self._tables: dict[tuple, _PeriodicPchip] = {}

    def frame(self, t: float) -> SheetShape:
        """The sheet at time ``t`` as a static shape."""
        return SheetShape(self.grid, self._nodes(float(t)), f"{self.label} @ {float(t):g} s")

    def _per_instant(self, uv: ph.ArrayLike, t: ph.ArrayLike, method: str):
        uv = ph._as_uv(uv)
        t = np.asarray(t, float)
        if t.ndim == 0:
            return getattr(self.frame(float(t)), method)(uv)
        t = ph._as_t(t, uv)
        flat_uv = uv.reshape(-1, 2)
        times, inverse = np.unique(t.reshape(-1), return_inverse=True)
        outs: tuple[np.ndarray, ...] | None = None
        for k, tk in enumerate(times):
            idx = np.flatnonzero(inverse == k)
            res = getattr(self.frame(float(tk)), method)(flat_uv[idx])
            res = res if isinstance(res, tuple) else (res,)
            if outs is None:
                outs = tuple(np.empty((flat_uv.shape[0], 3)) for _ in res)
            for o, r in zip(outs, res):
                o[idx] = r
        assert outs is not None
        shaped = tuple(o.reshape(uv.shape[:-1] + (3,)) for o in outs)
        return shaped if method == "position_and_normal" else shaped[0]

    def position(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        return self._per_instant(uv, t, "position")

    def normal(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> np.ndarray:
        return self._per_instant(uv, t, "normal")

    def position_and_normal(self, uv: ph.ArrayLike, t: ph.ArrayLike = 0.0) -> tuple[np.ndarray, np.ndarray]:
        return self._per_instant(uv, t, "position_and_normal")

    def layer_strains(self, centres, directions, offsets, gauge_length, t, samples, panels) -> np.ndarray:
        key = (centres.tobytes(), directions.tobytes(), offsets.tobytes(), float(gauge_length), samples, panels)
        table = self._tables.get(key)
        if table is None:
            frames = np.stack([
                f.layer_strains(centres, directions, offsets, gauge_length, np.asarray(0.0), samples, panels)
                for f in self.key_frames
            ])  # (K, L, G)
            table = self._tables[key] = _PeriodicPchip(self.times, frames, self.period)
        t = np.asarray(t, float)
        if t.ndim == 0:
            return table(float(t))
        # each gauge at its own instant: evaluate at the distinct instants, pick each gauge's
        times, inverse = np.unique(t, return_inverse=True)
        values = table(times)  # (T, L, G)
        return values[inverse, :, np.arange(t.size)].T

    def __repr__(self) -> str:
        return f"KeyframedSheet({self.label}, {self.times.size} key frames over {self.period:g} s)"


# --------------------------------------------------------------------------- scene solving


@dataclass(frozen=True)
class _Setup:
    """What every scene shares: the array, the film and its mesh."""

    n: int
    m: int
    pitch: float
    material: mc.SheetMaterial
    grid: mc.SheetGrid


def _mold_height(kind: str, params: Mapping[str, Any]) -> tuple[mc.HeightField, ph.Shape]:
    """The mold's height field and the kinematic shape of the same kind (the start)."""
    shape = ph.make_shape(kind, **params) if kind != "sum" else params["shape"]
    if isinstance(shape, ph.Flat):
        return mc.FlatHeight(), shape
    if isinstance(shape, ph.Cylinder):
        return mc.CylinderHeight(shape.radius, shape.axis_angle), shape
    if isinstance(shape, ph.SphereCap):
        return mc.SphereHeight(shape.radius), shape
    if isinstance(shape, ph.GraphShape):
        graph = shape
        return mc.FunctionHeight(lambda xy, t: graph.height_and_gradient(xy, np.zeros(xy.shape[0])), repr(graph)), shape
    raise ValueError(f"shape {kind!r} cannot be a mold")


def _on_mold(height: mc.HeightField, xy: np.ndarray, t: float = 0.0) -> np.ndarray:
    f, _, _ = height(xy.reshape(-1, 2), t)
    return np.concatenate([xy, f.reshape(xy.shape[:-1])[..., None]], axis=-1)


def _mold_problem(setup: _Setup, height: mc.HeightField, el: Mapping[str, Any], t: float = 0.0,
                  placement: Callable[[np.ndarray], np.ndarray] | None = None):
    """Problem and start of a film laminated on a mold.  ``placement`` maps material points to
    where a kinematic lay-up would put them in xy (the kind's own map; default the identity): the
    start, the friction's first-contact points and, with a pre-stretch, the frame that holds the
    edges (rollers: the u-edges' x, the v-edges' y) all follow it at the stretched coordinates."""
    grid = setup.grid
    uv = grid.uv()
    su, sv = el.get("prestretch_u"), el.get("prestretch_v")
    if el.get("prestretch") is not None:
        su = el["prestretch"] if su is None else su
        sv = el["prestretch"] if sv is None else sv
    stretched = uv * np.array([1.0 + float(su or 0.0), 1.0 + float(sv or 0.0)])
    ref = stretched if placement is None else placement(stretched)
    fixed = np.zeros((grid.nv, grid.nu, 3), bool)
    if su is not None:
        fixed[:, [0, -1], 0] = True
    if sv is not None:
        fixed[[0, -1], :, 1] = True
    anchor = _ANCHOR * setup.material.membrane_stiffness / max(grid.half_u, grid.half_v) ** 2
    friction = float(el.get("friction") or 0.0)
    # frictionless films keep their mean position: along the edges no frame holds, and turning
    # unless a frame holds both pairs of edges
    hold = () if friction else tuple(
        mode for mode, free in (("x", su is None), ("y", sv is None), ("turn", su is None or sv is None)) if free)
    problem = mc.SheetProblem(
        grid, setup.material, mold=height, fixed=fixed, foundation=max(friction, anchor if hold else 0.0),
        reference=ref, time=t, hold_rigid=hold,
    )
    _, slope, _ = height(ref.reshape(-1, 2), t)
    steepest = float(np.sqrt(np.max(np.sum(slope * slope, axis=-1))))
    if steepest > _MAX_SLOPE:
        raise ValueError(
            f"the film ({2 * grid.half_u:g} × {2 * grid.half_v:g} mm) reaches {math.degrees(math.atan(steepest)):.0f}° "
            f"of slope on this mold ({height!r}); a mold is a height field z = f(x, y), usable to "
            f"{math.degrees(math.atan(_MAX_SLOPE)):.0f}°: use a larger radius or a smaller array")
    return problem, _on_mold(height, ref, t)


def _solve_mold(setup: _Setup, kind: str, params: Mapping[str, Any], el: Mapping[str, Any]) -> np.ndarray:
    height, kinematic = _mold_height(kind, params)
    problem, x0 = _mold_problem(setup, height, el, placement=lambda q: kinematic.position(q)[..., :2])
    return mc.solve(problem, x0).positions


def _keyframe_times(period: float, count: int) -> np.ndarray:
    return np.arange(count) * (period / count)


def _solve_membrane(setup: _Setup, params: Mapping[str, Any], el: Mapping[str, Any]):
    kin = ph.FingertipMembrane(**params)
    grid = setup.grid
    mat = setup.material
    radius = float(el["finger_radius"]) + 0.5 * mat.thickness
    s = float(el.get("prestretch") or 0.0)
    fixed = np.zeros((grid.nv, grid.nu, 3), bool)
    fixed[[0, -1], :, :] = True
    fixed[:, [0, -1], :] = True
    x = grid.flat() * np.array([1.0 + s, 1.0 + s, 1.0])
    cycle = 2.0 * kin.period  # the press repeats every period, the slide every two
    count = int(el.get("keyframes") or 48)
    times = _keyframe_times(cycle, count)

    def finger(k: int) -> Callable[[float], np.ndarray]:
        def centre(t: float) -> np.ndarray:
            d, c = list(kin._fingers(np.asarray(t, float)))[k]
            return np.array([float(c[0]), float(c[1]), radius - float(d)])
        return centre

    contacts = [mc.SphereContact(finger(k), radius) for k in range(kin.fingers)]
    frames: list[np.ndarray] = []
    last: mc.Solution | None = None
    for t in times:
        problem = mc.SheetProblem(grid, mat, contacts=contacts, fixed=fixed, time=float(t))
        last = mc.solve(problem, _predict(frames, x), warm=last)
        frames.append(last.positions)
    return times, np.stack(frames), cycle


def _predict(frames: list[np.ndarray], start: np.ndarray) -> np.ndarray:
    """Warm start of the next key frame: the last one (the solver then moves any point a body
    now overlaps onto its surface).  Not extrapolated: after a release the extrapolation rises
    through the next fingertip and would start the film on the wrong side of it."""
    return frames[-1] if frames else start


class _Ridge:
    """A wall relief: a straight ridge of height ``height`` and width ``width`` (flat top,
    smooth flanks) at ``angle`` degrees from +u, hanging from a wall at z = top(t)."""

    def __init__(self, height: float, width: float, angle: float, top: Callable[[float], float]):
        self.height, self.width, self.top = height, width, top
        a = math.radians(angle)
        self._across = np.array([-math.sin(a), math.cos(a)])

    def height_and_gradient(self, xy: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        p = xy @ self._across / (0.5 * self.width)
        prof = np.exp(-p**4)
        dprof = -4.0 * p**3 * prof / (0.5 * self.width)
        z = self.top(t) - self.height * prof
        return z, (-self.height * dprof)[:, None] * self._across


def _balloon_contacts(kin: ph.BalloonDome, el: Mapping[str, Any], half: float) -> list[mc.GapField]:
    """The body pressed onto the balloon: a dome whose lowest point sits ``press_depth(t)`` below
    the apex, or a wall whose ridge's crest does."""
    if el.get("indenter"):
        relief = float(el["relief"])
        ridge = _Ridge(relief, float(el["relief_width"]), float(el["relief_angle"]),
                       lambda t: relief + half - float(kin.press_depth(t)))
        return [mc.WallContact(mc.FunctionHeight(ridge.height_and_gradient, "ridge wall"))]
    rd = kin.dome_radius + half
    return [mc.SphereContact(lambda t: np.array([0.0, 0.0, rd - float(kin.press_depth(t))]), rd)]


def _solve_balloon(setup: _Setup, params: Mapping[str, Any], el: Mapping[str, Any]):
    kin = ph.BalloonDome(**params)
    grid = setup.grid
    mat = setup.material
    rb = kin.balloon_radius
    # 1. the film laid on the inflated balloon (frictionless), 2. its perimeter taped there
    sphere = mc.SphereHeight(rb)
    cap = ph.SphereCap(rb)
    problem, x0 = _mold_problem(setup, sphere, {}, placement=lambda q: cap.position(q)[..., :2])
    x = mc.solve(problem, x0).positions
    uv = grid.uv()
    tape = float(el["tape"])
    taped = (np.abs(uv[..., 0]) >= grid.half_u - tape - 1e-9) | (np.abs(uv[..., 1]) >= grid.half_v - tape - 1e-9)
    fixed = np.repeat(taped[..., None], 3, axis=-1)
    balloon = mc.Balloon(float(el["tension"]), rb, (0.0, 0.0, -rb))
    half = 0.5 * mat.thickness
    contacts = _balloon_contacts(kin, el, half)
    if kin.time_varying:
        count = int(el.get("keyframes") or 32)
        times = _keyframe_times(kin.period, count)
        period = kin.period
    else:
        times, period = np.array([0.0]), math.inf
    if not kin.time_varying:  # press gradually to the full depth (a sudden one starts deep inside)
        ramp = [float(v) for v in np.linspace(0.0, kin.depth, 8)[1:-1]]
        for depth in ramp:
            stage = ph.BalloonDome(kin.balloon_radius, kin.dome_radius, depth, 0.0, kin.smoothing)
            staged = _balloon_contacts(stage, el, half)
            x = mc.solve(mc.SheetProblem(grid, mat, contacts=staged, fixed=fixed, balloon=balloon), x).positions
    frames: list[np.ndarray] = []
    last: mc.Solution | None = None
    for t in times:
        problem = mc.SheetProblem(grid, mat, contacts=contacts, fixed=fixed, balloon=balloon, time=float(t))
        last = mc.solve(problem, _predict(frames, x), warm=last)
        frames.append(last.positions)
    return times, np.stack(frames), period


def _palm_heights(params: Mapping[str, Any]) -> tuple[ph.PalmGesture, list[mc.HeightField]]:
    palm = ph.PalmGesture(**params)
    heights = [_mold_height("sum", {"shape": k})[0] for k in palm.keys]
    return palm, heights


class _MorphHeight:
    """Mold height between key shapes: each held, then blended by a C² smoothstep."""

    def __init__(self, palm: ph.PalmGesture, heights: list[mc.HeightField]):
        self.palm, self.heights = palm, heights

    def weights(self, t: float) -> tuple[int, int, float]:
        p = self.palm
        seg_len = p.hold + p.transition
        phase = float(np.mod(t, p.cycle))
        seg = int(phase // seg_len) % len(p.keys)
        x = (phase - seg * seg_len - p.hold) / p.transition
        w = float(ph._smoothstep(np.asarray(x))) if x > 0 else 0.0
        return seg, (seg + 1) % len(p.keys), w

    def __call__(self, xy: np.ndarray, t: float = 0.0):
        a, b, w = self.weights(t)
        fa = self.heights[a](xy, t)
        if w == 0.0:
            return fa
        fb = self.heights[b](xy, t)
        return tuple((1.0 - w) * va + w * vb for va, vb in zip(fa, fb))


def _solve_palm(setup: _Setup, params: Mapping[str, Any], el: Mapping[str, Any]):
    palm, heights = _palm_heights(params)
    morph = _MorphHeight(palm, heights)
    count = int(el.get("keyframes") or 8 * len(palm.keys))
    times = _keyframe_times(palm.cycle, count)
    x = None
    frames = []
    for t in times:
        problem, x0 = _mold_problem(setup, morph, el, float(t))
        if x is not None:  # warm: the last frame's film, dropped onto this frame's mold
            x0 = _on_mold(morph, x[..., :2], float(t))
        x = mc.solve(problem, x0).positions
        frames.append(x)
    return times, np.stack(frames), palm.cycle


def _material(el: Mapping[str, Any]) -> mc.SheetMaterial:
    return mc.SheetMaterial(youngs_modulus=float(el["youngs"]), thickness=float(el["thickness"]),
                            poisson=float(el["poisson"]), bending_stiffness=float(el["bending"]))


def _cache_key(kind: str, params: Mapping[str, Any], el: Mapping[str, Any], setup: _Setup) -> str:
    doc = {
        "version": SOLVER_VERSION, "kind": kind, "params": params, "elastic": el,
        "array": [setup.n, setup.m, setup.pitch], "grid": asdict(setup.grid),
    }
    text = json.dumps(doc, sort_keys=True, default=repr)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _load(path: Path) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, KeyError):
        return None  # absent or damaged: solve again


def _store(path: Path, **arrays: np.ndarray) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]  # numpy's stub: a key could be allow_pickle
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only or full disk only costs the next run a solve


_COMMON = {"poisson", "youngs", "thickness", "bending", "mesh"}
_FRAME = {"prestretch", "prestretch_u", "prestretch_v", "friction"}
#: Which elastic parameters each scene uses (any other is an error, not silently ignored).
APPLICABLE: dict[str, set[str]] = {
    "mold": _COMMON | {"margin"} | _FRAME,
    "membrane": _COMMON | {"keyframes", "finger_radius", "prestretch"},
    "balloon": _COMMON | {"margin", "keyframes", "tension", "tape", "indenter", "relief", "relief_width",
                          "relief_angle"},
    "palm": _COMMON | {"margin", "keyframes"} | _FRAME,
}


def _check_elastic(kind: str, given: Mapping[str, Any]) -> None:
    """Every elastic parameter given applies to this scene and has a sensible value."""
    scene = "mold" if kind in _MOLD_KINDS or kind == "sum" else kind
    extra = sorted(set(given) - APPLICABLE[scene])
    if extra:
        raise ValueError(f"elastic {kind!r}: {', '.join(extra)} do(es) not apply; it takes "
                         f"{', '.join(sorted(APPLICABLE[scene]))}")
    for name, value in given.items():
        if value is None:
            continue
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"elastic parameter {name} must be finite, got {value!r}")
        if name.startswith("prestretch") and not 0.0 <= v <= 0.5:
            raise ValueError(f"{name} must be a strain between 0 and 0.5, got {value!r}")
        if name in ("mesh", "finger_radius", "tension", "relief", "relief_width", "youngs", "thickness",
                    "bending") and v <= 0:
            raise ValueError(f"elastic parameter {name} must be > 0, got {value!r}")
        if name in ("friction", "tape", "margin") and v < 0:
            raise ValueError(f"elastic parameter {name} must be >= 0, got {value!r}")
        if name == "keyframes" and (v != int(v) or v < 2):
            raise ValueError(f"keyframes must be a whole number >= 2, got {value!r}")


def make_scene(kind: str, n: int, m: int, pitch: float = 12.0, *, cache: bool = True,
               cache_dir: str | os.PathLike[str] | None = None, **params: Any) -> ph.Shape:
    """The elastic form of a shape kind (see the module's table) for an N×M array at ``pitch``:
    a :class:`SheetShape` (static) or :class:`KeyframedSheet` (moving).  ``params`` are the
    kinematic kind's parameters plus the elastic ones in :data:`ELASTIC_PARAMETERS` that apply
    to the scene (:data:`APPLICABLE`).  Graph shapes summed with ``+`` come as
    ``kind="sum", shape=<GraphSum>``.  Raises ValueError naming a bad parameter, and
    :class:`~skinmap.emulator.mechanics.MechanicsError` when the film finds no equilibrium."""
    n, m = grid_size(n, m)
    pitch = ph._finite_positive("pitch", pitch)
    if kind not in ph.SHAPE_KINDS and kind != "sum":
        raise ValueError(f"unknown shape kind {kind!r}; known kinds: {', '.join(ph.SHAPE_KINDS)}")
    given = {k: params.pop(k) for k in list(params) if k in ELASTIC_PARAMETERS}
    _check_elastic(kind, given)
    el = {**ELASTIC_PARAMETERS, **given}
    if kind == "sum":
        if not isinstance(params.get("shape"), ph.GraphShape) or set(params) != {"shape"}:
            raise ValueError("kind 'sum' takes exactly shape=<a GraphShape>")
        key_params: dict[str, Any] = {"shape": repr(params["shape"])}
    else:
        ph.make_shape(kind, **params)  # the kinematic parameters' errors first, by name
        key_params = dict(params)
    margin = None if el["margin"] is None else float(el["margin"])
    material = _material(el)
    if kind == "membrane":
        kin = ph.FingertipMembrane(**params)
        grid = mc.SheetGrid(kin.half_u, kin.half_v, float(el["mesh"]))
    else:
        grid = mc.SheetGrid.for_array(n, m, pitch, float(el["mesh"]), margin)
    setup = _Setup(n, m, pitch, material, grid)
    solver: Callable[[], tuple[np.ndarray, np.ndarray, float]]
    if kind in _MOLD_KINDS or kind == "sum":
        solver = lambda: (np.array([0.0]), _solve_mold(setup, kind, params, el)[None], math.inf)
    elif kind == "membrane":
        solver = lambda: _solve_membrane(setup, params, el)
    elif kind == "balloon":
        solver = lambda: _solve_balloon(setup, params, el)
    else:
        solver = lambda: _solve_palm(setup, params, el)
    changed = {k: v for k, v in el.items() if v != ELASTIC_PARAMETERS[k]}
    label = f"elastic {kind} " + ",".join(f"{k}={v}" for k, v in sorted({**key_params, **changed}.items()))
    path = Path(cache_dir) if cache_dir is not None else cache_directory()
    path = path / f"{_cache_key(kind, key_params, el, setup)}.npz"
    data = _load(path) if cache else None
    if data is None:
        times, frames, period = solver()
        if cache:
            _store(path, times=times, frames=frames, period=np.array(period))
    else:
        times, frames, period = data["times"], data["frames"], float(data["period"])
    if times.size == 1:
        return SheetShape(grid, frames[0], label)
    return KeyframedSheet(grid, times, frames, period, label)


def parse_scene_spec(spec: str, mechanics: Mechanics, n: int, m: int, pitch: float = 12.0, **kw: Any) -> ph.Shape:
    """A shape spec (``kind[:key=value,...]``, graph shapes summed with ``+``) in either form:
    ``kinematic`` is :func:`skinmap.emulator.physics.parse_shape_spec`; ``elastic`` solves the
    scene (:func:`make_scene`; elastic parameters may follow the first term's)."""
    if mechanics not in ("kinematic", "elastic"):
        raise ValueError(f"mechanics must be 'kinematic' or 'elastic', got {mechanics!r}")
    terms = ph.split_shape_spec(spec)
    elastic = {k: v for _, params in terms for k, v in params.items() if k in ELASTIC_PARAMETERS}
    if mechanics == "kinematic":
        if elastic:
            raise ValueError(
                f"shape spec {spec!r}: {', '.join(sorted(elastic))} apply only to elastic mechanics "
                "(--mechanics elastic)")
        return ph.parse_shape_spec(spec)
    cleaned = [(kind, {k: v for k, v in p.items() if k not in ELASTIC_PARAMETERS}) for kind, p in terms]
    if len(cleaned) == 1:
        kind, params = cleaned[0]
        return make_scene(kind, n, m, pitch, **params, **elastic, **kw)
    shape = ph.GraphSum([ph.make_shape(k, **p) for k, p in cleaned])
    return make_scene("sum", n, m, pitch, shape=shape, **elastic, **kw)
