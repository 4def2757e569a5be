"""One scan in, one published result out: strains → surface → element coordinates.

`FramePipeline.process` is deterministic given the same sequence of scans, which is what lets
`skinmap replay` reproduce a live run bit for bit from the logged raw frames. It does no I/O.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from skinmap.daemon.calibration import Calibration, resistances_to_strains, to_nominal_offsets
from skinmap.wire.messages import ElementFlag

__all__ = ["ArrayGeometry", "FrameResult", "FramePipeline", "OutputDecimator", "reject_implausible_units",
           "turning_noise_rad"]

# An element whose 1-s.d. position uncertainty exceeds this is flagged DEGRADED.
DEGRADED_SIGMA_MM = 0.5
# A sensing unit whose upper and lower strains imply that its gauge turns by more than half a
# circle (bend radius < L/π ≈ 3 mm for a 10 mm gauge) is not a film we can bend: both gauges
# are rejected as implausible (which of the pair is wrong cannot be told).
MAX_UNIT_TURNING_RAD = float(np.pi)
# Fit misfit (rad per gauge) above which a scan's strains are inconsistent with any one smooth
# sheet: every element is flagged DEGRADED. Legitimate shapes of the forward model stay below
# 1.7e-3 rad (8x8 and 16x16: palm, membrane, balloon, tight cylinders and spheres); independent
# random bends of ±2.5 rad per gauge give 0.006-0.016. The limit grows with the strain noise.
INCONSISTENT_RESIDUAL_RAD = 0.005
INCONSISTENT_RESIDUAL_SIGMAS = 5.0


@dataclass(frozen=True)
class ArrayGeometry:
    n: int
    m: int
    pitch_mm: float
    h_upper_mm: float
    h_lower_mm: float
    gauge_length_mm: float = 10.0

    def cell_uv(self) -> np.ndarray:
        """(N, M, 2) material coordinates of the cell centres (docs/architecture.md)."""
        u = (np.arange(self.m) - (self.m - 1) / 2) * self.pitch_mm
        v = (np.arange(self.n) - (self.n - 1) / 2) * self.pitch_mm
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)


@dataclass
class FrameResult:
    seq: int
    device_time_us: int
    host_time_ns: int
    eps_upper: np.ndarray  # (2, N, M), NaN where a gauge is unusable
    eps_lower: np.ndarray
    gauge_valid: np.ndarray  # (2, 2, N, M) bool
    nodes_mm: np.ndarray  # (N, M, 3)
    normals: np.ndarray  # (N, M, 3)
    node_sigma_mm: np.ndarray  # (N, M)
    element_positions_mm: np.ndarray  # (K, 3)
    element_normals: np.ndarray  # (K, 3)
    element_sigma_mm: np.ndarray  # (K,)
    element_flags: np.ndarray  # (K,) u8, ElementFlag bits
    solve_time_s: float
    diagnostics: dict[str, Any] = field(default_factory=dict)
    surface: Any = None  # the reconstruction's result object (points(), locate())


class OutputDecimator:
    """Chooses which scans to process from the DEVICE clock, so the choice replays identically.

    rate_hz = 0 passes every scan.
    """

    def __init__(self, rate_hz: float) -> None:
        self.period_us = 0 if rate_hz <= 0 else int(round(1e6 / rate_hz))
        self._next_due: int | None = None

    def due(self, device_time_us: int) -> bool:
        if self.period_us == 0:
            return True
        if self._next_due is None or device_time_us >= self._next_due + 4 * self.period_us or device_time_us < self._next_due - 4 * self.period_us:
            # First scan, a long gap or a device clock reset: restart the schedule here.
            self._next_due = device_time_us
        if device_time_us >= self._next_due:
            self._next_due += self.period_us
            return True
        return False


#: The graph fit's warm start depends on the frames before it, so the pipeline restarts it cold
#: at the first scan of every block of this many sample indices: a log replays bit for bit from
#: the first restart in it (``skinmap replay``), at the cost of one cold fit per block.
GRAPH_RESTART_SCANS = 64


def graph_restart(previous_seq: int | None, seq: int) -> bool:
    """Whether the scan ``seq`` starts the graph fit cold, given the last processed scan."""
    return previous_seq is None or seq // GRAPH_RESTART_SCANS != previous_seq // GRAPH_RESTART_SCANS


class FramePipeline:
    """Calibrated strains → reconstruction → element coordinates, with warm start."""

    def __init__(
        self,
        geometry: ArrayGeometry,
        calibration: Calibration,
        element_uv_mm: np.ndarray,
        element_offset_mm: np.ndarray,
        *,
        strain_sigma: float = 5.7e-5,
        warm_start: bool = True,
        convex_solver: str = "factorized",
        graph_fit: bool = True,
        twist_sign: int | None = None,
    ) -> None:
        self.geometry = geometry
        self.calibration = calibration
        self.element_uv = np.asarray(element_uv_mm, dtype=np.float64).reshape(-1, 2)
        self.element_offset = np.asarray(element_offset_mm, dtype=np.float64).reshape(-1)
        if self.element_offset.shape[0] != self.element_uv.shape[0]:
            raise ValueError("element offsets and element coordinates differ in count")
        self.strain_sigma = float(strain_sigma)
        self.warm_start = warm_start
        self.convex_solver = convex_solver
        self.graph_fit = bool(graph_fit)
        if twist_sign not in (None, 1, -1):
            raise ValueError(f"twist_sign must be None, +1 or -1, got {twist_sign!r}")
        self.twist_sign = twist_sign
        self._previous: Any = None
        self._previous_seq: int | None = None
        self._last_good: FrameResult | None = None
        # Our own reconstructor (not the module-wide cache): its state (factorisations, the masks
        # it has seen) then depends only on the frames this pipeline processed, which is what
        # lets replay reproduce live results bit for bit. Built on first use (it is costly) unless
        # taken over from the pipeline this one replaces.
        self._reconstructor: Any = None
        half_u = (geometry.m - 1) / 2 * geometry.pitch_mm
        half_v = (geometry.n - 1) / 2 * geometry.pitch_mm
        cells = geometry.cell_uv().reshape(-1, 2)
        dist = np.abs(self.element_uv[:, None, :] - cells[None, :, :]).max(axis=2)
        self._neighbour_cells = dist <= 1.5 * geometry.pitch_mm  # (K, N·M)
        self._extrapolated = (np.abs(self.element_uv[:, 0]) > half_u + 1e-9) | (np.abs(self.element_uv[:, 1]) > half_v + 1e-9)

    def set_calibration(self, calibration: Calibration) -> None:
        self.calibration = calibration

    @property
    def reconstructor(self) -> Any:
        """The reconstruction callable (a `Reconstructor` for this geometry, built on first use;
        replaceable, e.g. by tests)."""
        if self._reconstructor is None:
            from skinmap.reconstruction import GRAPH_FIT_MAX_CELLS, Reconstructor

            g = self.geometry
            # the graph fit is offered for small sheets only; larger ones keep the general model
            graph_fit = self.graph_fit and g.n * g.m <= GRAPH_FIT_MAX_CELLS
            self._reconstructor = Reconstructor(
                g.n, g.m, g.pitch_mm, g.h_upper_mm, g.h_lower_mm, g.gauge_length_mm, convex_solver=self.convex_solver,
                graph_fit=graph_fit,
            )
        return self._reconstructor

    @reconstructor.setter
    def reconstructor(self, value: Any) -> None:
        self._reconstructor = value

    def continue_from(self, earlier: "FramePipeline | None") -> None:
        """Take over the reconstructor and warm start of the pipeline this one replaces (after a
        reconnect or a new HELLO) when the geometry is the same."""
        if (earlier is not None and earlier.geometry == self.geometry and earlier.convex_solver == self.convex_solver
                and earlier.graph_fit == self.graph_fit and earlier.twist_sign == self.twist_sign):
            self._reconstructor = earlier._reconstructor
            self._previous = earlier._previous
            self._previous_seq = earlier._previous_seq

    def process(self, resistance_ohm: np.ndarray, seq: int, device_time_us: int, host_time_ns: int) -> FrameResult:
        g = self.geometry
        eps_u, eps_l, valid = resistances_to_strains(resistance_ohm, self.calibration)
        cal = self.calibration
        if cal.h_upper_mm is not None:
            eps_u, eps_l = to_nominal_offsets(eps_u, eps_l, cal.h_upper_mm, cal.h_lower_mm, g.h_upper_mm, g.h_lower_mm)
        eps_u, eps_l, valid, implausible = reject_implausible_units(eps_u, eps_l, valid, g)
        t0 = time.perf_counter()
        kwargs: dict[str, Any] = {"strain_sigma": self.strain_sigma}
        if self.twist_sign is not None:
            kwargs["twist_sign"] = self.twist_sign
        if self.warm_start and self._previous is not None:
            kwargs["previous"] = self._previous
            if graph_restart(self._previous_seq, seq) and getattr(self.reconstructor, "graph_fit", False):
                kwargs["graph_warm"] = False
        surf = self.reconstructor(eps_u, eps_l, **kwargs)
        nodes = np.asarray(surf.nodes, dtype=np.float64)
        normals = np.asarray(surf.normals, dtype=np.float64)
        node_sigma = np.asarray(surf.node_sigma, dtype=np.float64)
        pos, nrm, sig = _locate(surf, self.element_uv)
        pos = pos + self.element_offset[:, None] * nrm
        solve_s = time.perf_counter() - t0

        flags = np.full(self.element_uv.shape[0], int(ElementFlag.VALID), dtype=np.uint8)
        flags[self._extrapolated] |= int(ElementFlag.EXTRAPOLATED)
        flags[sig > DEGRADED_SIGMA_MM] |= int(ElementFlag.DEGRADED)
        if not valid.all():
            # Elements near a gauge the scan could not use rest on the prior there.
            bad_cells = (~valid).any(axis=(0, 1)).ravel()
            flags[self._neighbour_cells[:, bad_cells].any(axis=1)] |= int(ElementFlag.DEGRADED)
            # With no usable unit (both layers read) anywhere near, the position is the prior
            # alone, not a current estimate.
            measured_cells = (valid[0] & valid[1]).any(axis=0).ravel()
            unmeasured = ~self._neighbour_cells[:, measured_cells].any(axis=1)
            flags[unmeasured] = (flags[unmeasured] & (0xFF ^ int(ElementFlag.VALID))) | int(ElementFlag.DEGRADED)
        if getattr(surf, "mirror", None) is not None:
            # the gauges cannot tell this shape from its mirror image (Surface.mirror)
            flags |= int(ElementFlag.AMBIGUOUS)
        diagnostics = _diagnostics_dict(getattr(surf, "diagnostics", None))
        diagnostics["implausible_units"] = implausible
        residual = diagnostics.get("residual", 0.0)
        limit = max(INCONSISTENT_RESIDUAL_RAD,
                    INCONSISTENT_RESIDUAL_SIGMAS * turning_noise_rad(self.strain_sigma, g))
        diagnostics["inconsistent"] = bool(residual > limit)
        if diagnostics["inconsistent"]:
            flags |= int(ElementFlag.DEGRADED)
        finite = np.isfinite(nodes).all() and np.isfinite(normals).all() and np.isfinite(pos).all() and np.isfinite(nrm).all()
        if not finite:
            # Never publish NaN: hold the last good frame and say so.
            return self._stale(seq, device_time_us, host_time_ns, eps_u, eps_l, valid, solve_s)
        self._previous = surf
        self._previous_seq = seq
        result = FrameResult(
            seq=seq,
            device_time_us=device_time_us,
            host_time_ns=host_time_ns,
            eps_upper=eps_u,
            eps_lower=eps_l,
            gauge_valid=valid,
            nodes_mm=nodes,
            normals=normals,
            node_sigma_mm=np.where(np.isfinite(node_sigma), node_sigma, 1e3),
            element_positions_mm=pos,
            element_normals=nrm,
            element_sigma_mm=np.where(np.isfinite(sig), sig, 1e3),
            element_flags=flags,
            solve_time_s=solve_s,
            diagnostics=diagnostics,
            surface=surf,
        )
        self._last_good = result
        return result

    def _stale(self, seq, device_time_us, host_time_ns, eps_u, eps_l, valid, solve_s) -> FrameResult:
        g = self.geometry
        k = self.element_uv.shape[0]
        if self._last_good is not None:
            prev = self._last_good
            nodes, normals, node_sigma = prev.nodes_mm, prev.normals, prev.node_sigma_mm
            pos, nrm, sig = prev.element_positions_mm, prev.element_normals, prev.element_sigma_mm
            flags = (prev.element_flags | int(ElementFlag.STALE)).astype(np.uint8)
        else:
            uv = g.cell_uv()
            nodes = np.concatenate([uv, np.zeros((g.n, g.m, 1))], axis=-1)
            normals = np.broadcast_to([0.0, 0.0, 1.0], nodes.shape).copy()
            node_sigma = np.full((g.n, g.m), 1e3)
            pos = np.concatenate([self.element_uv, self.element_offset[:, None]], axis=1)
            nrm = np.broadcast_to([0.0, 0.0, 1.0], (k, 3)).copy()
            sig = np.full(k, 1e3)
            flags = np.full(k, int(ElementFlag.STALE), dtype=np.uint8)
        return FrameResult(seq, device_time_us, host_time_ns, eps_u, eps_l, valid, nodes, normals, node_sigma,
                           pos, nrm, sig, flags, solve_s, {"status": "non-finite solution; held last good frame"}, None)


def turning_noise_rad(strain_sigma: float, geometry: ArrayGeometry) -> float:
    """1-s.d. turning angle of one gauge due to strain noise: √2·σε·L / (h_u + h_l)."""
    return float(np.sqrt(2.0) * strain_sigma * geometry.gauge_length_mm / (geometry.h_upper_mm + geometry.h_lower_mm))


def reject_implausible_units(
    eps_upper: np.ndarray, eps_lower: np.ndarray, valid: np.ndarray, geometry: ArrayGeometry
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Mark both gauges of a unit unusable when together they imply an impossible bend.

    eps_* (2, N, M) with NaN for unusable gauges, valid (2, 2, N, M). Returns new arrays (the
    inputs are not modified) and the number of units rejected here.
    """
    turning = (eps_upper - eps_lower) * geometry.gauge_length_mm / (geometry.h_upper_mm + geometry.h_lower_mm)
    with np.errstate(invalid="ignore"):
        bad = valid[0] & valid[1] & ~(np.abs(turning) <= MAX_UNIT_TURNING_RAD)
    if not bad.any():
        return eps_upper, eps_lower, valid, 0
    valid = valid & ~bad[None]
    return np.where(bad, np.nan, eps_upper), np.where(bad, np.nan, eps_lower), valid, int(bad.sum())


def _locate(surf: Any, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if uv.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    out = surf.locate(uv)
    pos, nrm = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.float64)
    if len(out) > 2:
        sig = np.asarray(out[2], dtype=np.float64)
    elif hasattr(surf, "locate_sigma"):
        sig = np.asarray(surf.locate_sigma(uv), dtype=np.float64)
    else:
        sig = np.full(uv.shape[0], np.nan)
    return pos, nrm, sig


def _diagnostics_dict(diag: Any) -> dict[str, Any]:
    if diag is None:
        return {}
    if isinstance(diag, dict):
        items = diag.items()
    else:
        items = getattr(diag, "__dict__", {}).items()
    return {k: v for k, v in items if isinstance(v, (int, float, str, bool))}
