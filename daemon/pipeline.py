"""One scan in, one published result out: the data path's stages in order, resistances →
strains (skinmap.strains) → surface (skinmap.reconstruction) → element coordinates
(skinmap.elements).

`FramePipeline.process` is deterministic given the same sequence of scans, which is what lets
`skinmap replay` reproduce a live run bit for bit from the logged raw frames, whether the graph
fit's restart chains run on a worker (skinmapd) or in line (replay). It does no I/O.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import logging
import math
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Protocol

import numpy as np

from skinmap.elements import (UNKNOWN_SIGMA_MM, element_flags, element_layout, fit_inconsistent, held_flags,
                              locate_elements, prior_elements)
from skinmap.reconstruction.uncertainty import alignment_floor, response_lag_sigma
from skinmap.strains import (GAUGE_LENGTH_MM, RESPONSE_LAG_S, SHARED_GAIN_SD, Calibration, cell_bending,
                             cell_centres, reject_implausible_units, resistances_to_strains, to_nominal_offsets,
                             turning_noise_rad)

__all__ = ["ArrayGeometry", "FrameResult", "FramePipeline", "Background", "InlineBackground", "WorkerBackground",
           "GRAPH_RESTART_SCANS", "GRAPH_ADOPT_SCANS", "GRAPH_SYNC_SCANS", "GRAPH_CATCH_UP_SCANS", "GRAPH_AUDIT_SCANS",
           "AUDIT_MAX_CELLS", "MOTION_BASELINE_S", "MOTION_HORIZON_S", "graph_audit", "graph_restart",
           "graph_adopt"]

log = logging.getLogger("skinmapd")


@dataclass(frozen=True)
class ArrayGeometry:
    n: int
    m: int
    pitch_mm: float
    h_upper_mm: float
    h_lower_mm: float
    gauge_length_mm: float = GAUGE_LENGTH_MM

    def cell_uv(self) -> np.ndarray:
        """(N, M, 2) material coordinates of the cell centres (docs/architecture.md)."""
        return cell_centres(self.n, self.m, self.pitch_mm)


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
    # seconds per stage: strains, restart (the restart chain's part: handing it this scan, or
    # waiting for it when taken over), reconstruct, uncertainty (node σ), elements (located, σ)
    stage_s: dict[str, float] = field(default_factory=dict)
    # the part of node_sigma_mm / element_sigma_mm that repeated frames of a still sheet scatter
    # by (Surface.node_scatter_sigma); None: not known, the whole σ stands for it
    node_scatter_mm: np.ndarray | None = None  # (N, M)
    element_scatter_mm: np.ndarray | None = None  # (K,)
    # the array the strains were read on (their nominal offsets, the gauges' length), with a
    # reconstructed surface; None on a held frame
    geometry: ArrayGeometry | None = None

    def cell_bending(self) -> np.ndarray | None:
        """(N, M) 1/mm: each cell's bending κ_u + κ_v from its gauges (strains.cell_bending, at
        the nominal offsets), what tactile mapping reads to place a contact; None without the
        geometry.  Computed when asked, so frames nobody maps cost nothing."""
        g = self.geometry
        return None if g is None else cell_bending(self.eps_upper, self.eps_lower, g.h_upper_mm, g.h_lower_mm)


#: The graph fit's warm start depends on the frames before it.  So that a log replays bit for
#: bit, a fresh chain of fits is begun cold at the first processed scan of every block of this
#: many sample indices (``graph_restart``) and taken over by the published frames at the first
#: processed scan at least GRAPH_ADOPT_SCANS later (``graph_adopt``): from there on every result
#: depends only on the scans since the block's start.  The chain runs beside the published
#: frames (on a worker thread in skinmapd), so no published frame waits for the cold fit; replay
#: does the same work in line and gets the same bits.
GRAPH_RESTART_SCANS = 64
GRAPH_ADOPT_SCANS = 16
#: At most this many processed scans at the start of a log that begins mid-stream cannot be
#: compared by replay: those before the first chain begun in the file is taken over.
GRAPH_SYNC_SCANS = GRAPH_RESTART_SCANS + GRAPH_ADOPT_SCANS
#: A published frame that would need a cold graph fit (its warm fit failed, or the frame before
#: it has no graph to start from; the first frame, and one after a frame with too few usable
#: units to try a graph, fit cold themselves) is answered by the general model (``graph_cold=False``), and the cold fit of that
#: scan begins a catch-up chain on the background, fed the following scans as a restart chain is
#: and taken over at the first processed scan at least this many sample indices later (at 10 Hz
#: output of 50 scans/s: the next published frame).  The frames in between are the general
#: model's.  Taking it over does not begin a lineage of its own (``chain_origin`` is unchanged):
#: whether a frame defers depends on the frames before it, so a replay is in step with it only
#: where it already was.
GRAPH_CATCH_UP_SCANS = 4
#: Every this many sample indices a frame the warm chain answered begins an audit (sheets of up to
#: AUDIT_MAX_CELLS cells): a catch-up chain from the scan's cold fit, fed the following scans, and
#: at the catch-up scan taken over only where its graph fits that scan with the lower objective.  A
#: warm chain can settle in a basin of the graph fit a cold fit of the same scan leaves (its
#: Gauss-Newton step left short, so graphfit.WARM_UNSETTLED does not see it; its objective below
#: the basin test's yardstick): fingertips releasing a 5×5 membrane through the gauges' hysteresis.
#: On larger sheets, where the graph is a rescue for what the general model misfits, the same
#: scans recheck a warm graph (Reconstructor ``graph_recheck``): where the general model no longer
#: misfits, it answers and the chain of graphs ends (a 12×12 saddle held after a turn read through
#: lagging gauges stayed a graph 0.47 mm off, 1.2 times 3σ + 0.05 mm, until the next restart).
GRAPH_AUDIT_SCANS = 8
AUDIT_MAX_CELLS = 64
#: The largest sheet (cells) skinmapd fits as a height graph at all: on 12×12 and 16×16 a sharp
#: bump's graph answers keep 10 Hz output (emulated, 50 scans/s: 12×12 p99 82-176 ms, 0-1 output
#: dropped in 15-20 s; 16×16, on knots every pitch/2: solver 34-50 ms, p99 54 ms once started,
#: 5-6 outputs dropped in the first 3 s while the first restart chain builds its reconstructor).
#: On knots every pitch/3, 16×16 (13 ms a warm frame, 70 ms its node σ) fell to 8-9 Hz with 31
#: frames dropped in 20 s (docs/reconstruction.md, *Larger sheets*).
PIPELINE_GRAPH_MAX_CELLS = 256
#: How a sheet's speed is read for the gauges' response lag in σ (``response_lag_s``): from the
#: processed frame latest at least MOTION_BASELINE_S (device time) before this one, so that the
#: move between them stands above their noise (at 10 Hz output, the frame published before; with
#: every scan published, the third one back), and none older than MOTION_HORIZON_S (after a gap
#: or a reconnect the speed is not known, and the term is left out until it is).
MOTION_BASELINE_S = 0.06
MOTION_HORIZON_S = 0.5


@dataclass(frozen=True)
class _MotionSample:
    """What the response lag's speed is read from: one processed frame's points and scatter."""
    time_s: float
    nodes: np.ndarray  # (N·M, 3)
    node_scatter: np.ndarray | None  # (N·M,); None: not read (a lead scan)
    elements: np.ndarray  # (K, 3)
    element_scatter: np.ndarray | None  # (K,); None: not read


def graph_restart(previous_seq: int | None, seq: int) -> bool:
    """Whether the scan ``seq`` begins a block (a cold restart of the graph fit), given the last
    processed scan."""
    return previous_seq is None or seq // GRAPH_RESTART_SCANS != previous_seq // GRAPH_RESTART_SCANS


def graph_audit(seq: int) -> bool:
    """Whether the scan ``seq`` may begin an audit (GRAPH_AUDIT_SCANS): every GRAPH_AUDIT_SCANS
    sample indices, but not before the block's restart chain is taken over nor where the audit
    would still run at the next block's start, so that a replay from a block's start audits
    the same frames as the live run from the take-over on."""
    within = seq % GRAPH_RESTART_SCANS
    return (seq % GRAPH_AUDIT_SCANS == 0 and within >= GRAPH_ADOPT_SCANS
            and within + GRAPH_CATCH_UP_SCANS < GRAPH_RESTART_SCANS)


def graph_adopt(origin_seq: int, seq: int, after: int = GRAPH_ADOPT_SCANS) -> bool:
    """Whether the scan ``seq`` takes over the chain begun cold at scan ``origin_seq``, ``after``
    sample indices later (also when the sample index went back: waiting longer would not help)."""
    return seq < origin_seq or seq - origin_seq >= after


class Pending(Protocol):
    """A job handed to a `Background`; ``result()`` waits for it and returns its value or raises
    what it raised."""

    def result(self) -> Any: ...


class Background(Protocol):
    """Where the restart chains run; ``submit(fn)`` runs the jobs in the order given."""

    def submit(self, fn: Callable[[], Any]) -> Pending: ...


class _Done:
    def __init__(self, fn: Callable[[], Any]) -> None:
        self._error: Exception | None = None
        self._value: Any = None
        try:
            self._value = fn()
        except Exception as exc:  # noqa: BLE001 - raised again by result(), as a Future does
            self._error = exc

    def result(self) -> Any:
        if self._error is not None:
            raise self._error
        return self._value


class InlineBackground:
    """Runs each job at once on the caller's thread (replay, tests): the results of a worker, in
    the same order."""

    def submit(self, fn: Callable[[], Any]) -> Pending:
        return _Done(fn)


class _Job:
    """A job that runs once, on whichever thread claims it first: the worker, or one that asks for
    its result before the worker got to it."""

    def __init__(self, fn: Callable[[], Any]) -> None:
        self._fn: Callable[[], Any] | None = fn
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._value: Any = None
        self._error: BaseException | None = None

    def run_if_unclaimed(self) -> None:
        with self._lock:
            fn, self._fn = self._fn, None
        if fn is None:
            return
        try:
            self._value = fn()
        except BaseException as exc:  # noqa: BLE001 - raised again by result()
            self._error = exc
        finally:
            self._done.set()

    def result(self) -> Any:
        self.run_if_unclaimed()  # not started yet: run it here rather than wait for the worker
        self._done.wait()
        if self._error is not None:
            raise self._error
        return self._value


class WorkerBackground:
    """One worker thread at a lower scheduling priority (Linux: a thread's own nice value), so
    its jobs leave the CPU to the published frames; while the frames' thread says it is
    ``busy()``, the worker starts no job (a job already running goes on).  A job whose result is
    asked for before the worker started it runs on the asking thread instead, so a starved
    worker delays nobody by more than the job it is running.  ``close()`` ends the worker (jobs
    left run when asked for)."""

    NICE = 5
    BUSY_WAIT_S = 0.1  # the longest the worker holds back for a busy frames' thread

    def __init__(self, name: str = "skinmap-graph-restart") -> None:
        self._name = name
        self._jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._idle = threading.Event()
        self._idle.set()

    @contextlib.contextmanager
    def busy(self) -> Iterator[None]:
        """Around a frame's work on the frames' thread: no job starts meanwhile."""
        self._idle.clear()
        try:
            yield
        finally:
            self._idle.set()

    def submit(self, fn: Callable[[], Any]) -> Pending:
        job = _Job(fn)
        with self._lock:
            if not self._closed:
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
                    self._thread.start()
                self._jobs.put(job)
        return job

    def _run(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.NICE)
        except (AttributeError, OSError):  # not Linux, or not allowed: the same thread unniced
            pass
        while (job := self._jobs.get()) is not None:
            self._idle.wait(self.BUSY_WAIT_S)
            job.run_if_unclaimed()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self._thread is not None:
                self._jobs.put(None)


class _Chain:
    """Graph fits begun cold at scan ``origin`` and fed the scans the published frames get, on a
    reconstructor of their own (a Reconstructor fills caches and is not thread-safe), taken over
    ``adopt_after`` sample indices later.  Its steps run in order on the background, each after
    every job submitted before it (``after``: of any chain, as they share that reconstructor);
    ``last`` is its latest usable surface."""

    def __init__(self, origin: int, reconstructor: Any, element_uv: np.ndarray,
                 adopt_after: int = GRAPH_ADOPT_SCANS, audit: bool = False) -> None:
        self.origin = origin
        self.reconstructor = reconstructor
        self.element_uv = element_uv
        self.adopt_after = adopt_after
        # an audit of the published frames' warm chain (GRAPH_AUDIT_SCANS): taken over only where
        # its graph fits the same scan with the lower objective
        self.audit = audit
        # a restart chain is looked at once before its take-over (FramePipeline._peek)
        self.peeked = False
        self.last: Any = None
        self.last_seq: int | None = None
        self._pending: Pending | None = None

    def step(self, eps_u: np.ndarray, eps_l: np.ndarray, seq: int, kwargs: dict[str, Any]) -> None:
        if self.last is not None:
            kwargs = {**kwargs, "previous": self.last}
        surf = self.reconstructor(eps_u, eps_l, **kwargs)
        if _usable(surf, self.element_uv):  # the rule the published frames follow
            self.last, self.last_seq = surf, seq

    def submit(self, background: Background, fn: Callable[[], None], after: Pending | None = None) -> Pending:
        earlier = self._pending

        def run() -> None:
            if after is not None and after is not earlier:
                try:
                    after.result()  # another chain's step: never two on the reconstructor at once
                except Exception:  # noqa: BLE001 - that chain's failure is that chain's
                    pass
            if earlier is not None:
                earlier.result()  # a failed step fails the rest of the chain
            fn()

        self._pending = background.submit(run)
        return self._pending

    def wait(self) -> Any:
        """The chain's latest usable surface (None if none), once its steps are done; raises
        what a step raised."""
        if self._pending is not None:
            self._pending.result()
        return self.last


def _step(chain: _Chain, eps_u: np.ndarray, eps_l: np.ndarray, seq: int, kwargs: dict[str, Any]) -> Callable[[], None]:
    """The chain's step on this scan, as a job."""
    def run() -> None:
        chain.step(eps_u, eps_l, seq, kwargs)

    return run


def _warm_graph(surf: Any) -> bool:
    """Whether ``surf`` was answered by a warm graph fit (the frame before's, or its linear start's)."""
    how = getattr(getattr(surf, "diagnostics", None), "extra", {}).get("graph_fit")
    return isinstance(how, str) and how.startswith("warm") and getattr(surf.diagnostics, "extra", {}).get("model") == "graph"


def _lower_objective(audit: Any, audit_seq: int | None, published: Any, published_seq: int | None) -> bool:
    """Whether an audit chain's last surface fits the scan the published frames' chain last fitted
    with a lower graph objective (both graphs of the same scan; otherwise the published stands)."""
    if audit_seq is None or audit_seq != published_seq:
        return False
    mine = getattr(getattr(audit, "state", None), "graph_objective", math.inf)
    theirs = getattr(getattr(published, "state", None), "graph_objective", math.inf)
    return bool(mine < theirs)


def _with_yardstick(audit: Any, published: Any) -> Any:
    """The audit's surface, its chain's basin-test yardstick (FrameState.graph_reference) the
    published chain's where that is the higher: an audit moves the chain to a lower objective,
    and its own cold fit's yardstick refused warm fits the chain had kept (5×5 fingertips on a
    membrane: deferred frames doubled)."""
    state = getattr(audit, "state", None)
    theirs = getattr(getattr(published, "state", None), "graph_reference", math.inf)
    if state is None or not math.isfinite(theirs) or not theirs > state.graph_reference:
        return audit
    audit.state = dataclasses.replace(state, graph_reference=theirs)
    return audit


def _graph_tried(surf: Any) -> bool:
    """Whether ``surf`` is a frame on which the graph fit was tried (warm, cold or screened)."""
    return surf is not None and "graph_fit" in getattr(getattr(surf, "diagnostics", None), "extra", {})


def _usable(surf: Any, element_uv: np.ndarray) -> bool:
    """Whether a surface may be published and start the next frame: finite nodes and normals,
    and finite positions and normals at the elements."""
    if not (np.isfinite(surf.nodes).all() and np.isfinite(surf.normals).all()):
        return False
    if element_uv.shape[0] == 0:
        return True
    pos, nrm = surf.locate(element_uv)[:2]
    return bool(np.isfinite(pos).all() and np.isfinite(nrm).all())


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
        background: Background | None = None,
        defer_cold_fits: bool = True,
        elastic_prior: Any = None,
        poisson_range: tuple[float, float] = (0.3, 0.5),
        twist_prior: str = "open",
        gain_sd: float = SHARED_GAIN_SD,
        response_lag_s: float = RESPONSE_LAG_S,
    ) -> None:
        self.geometry = geometry
        self.calibration = calibration
        self.elements = element_layout(element_uv_mm, element_offset_mm, geometry.cell_uv(), geometry.pitch_mm)
        # (an element off the sheet, a layout for a larger one, is not located: status says so)
        self.elements_problem = self.elements.off_sheet_problem(geometry.n, geometry.m)
        self._sigma_uv = np.concatenate([geometry.cell_uv().reshape(-1, 2), self.elements.located_uv])
        self.strain_sigma = float(strain_sigma)
        self.warm_start = warm_start
        self.convex_solver = convex_solver
        self.graph_fit = bool(graph_fit)
        if twist_sign not in (None, 1, -1):
            raise ValueError(f"twist_sign must be None, +1 or -1, got {twist_sign!r}")
        self.twist_sign = twist_sign
        # PositionFitSettings of the elastic prior (docs/reconstruction.md, "Elastic films"), or None
        self.elastic_prior = elastic_prior
        # the film's Poisson ratio as an interval, for the stretch pattern's twist (any elastomer
        # unless the config or the calibration file gives ν)
        self.poisson_range = poisson_range
        # what node_sigma takes of a twist the stretch cannot tell from none (Reconstructor)
        self.twist_prior = twist_prior
        # the s.d. of a gain error the gauges share (their hysteresis and relaxation), carried into σ (Reconstructor)
        self.gain_sd = float(gain_sd)
        # the gauges' response lag bound (s), carried into σ where the sheet moves; 0 leaves it out
        if not (math.isfinite(response_lag_s) and response_lag_s >= 0.0):
            raise ValueError(f"response_lag_s must be a finite number >= 0, got {response_lag_s!r}")
        self.response_lag_s = float(response_lag_s)
        self._motion: list[_MotionSample] = []  # the frames within MOTION_HORIZON_S, oldest first
        self._previous: Any = None
        self._previous_seq: int | None = None
        self._last_good: FrameResult | None = None
        # Our own reconstructor (not the module-wide cache): its state (factorisations, the masks
        # it has seen) then depends only on the frames this pipeline processed, which is what
        # lets replay reproduce live results bit for bit. Built on first use (it is costly) unless
        # taken over from the pipeline this one replaces.
        self._reconstructor: Any = None
        # The restart chain (GRAPH_RESTART_SCANS): its own reconstructor, built on the background
        # at the first restart; the chain under way; where the current warm start's lineage began
        # cold (a block's first scan; None before the first restart seen).
        self.background: Background = background if background is not None else InlineBackground()
        self._chain_reconstructor: Any = None
        self._chain: _Chain | None = None
        self.chain_origin: int | None = None
        # Cold fits a published frame needs go to a catch-up chain (GRAPH_CATCH_UP_SCANS) unless
        # this is False (each such frame then fits cold itself); the chain under way; the last
        # job handed to the background (the chains' steps run one after another).
        self.defer_cold_fits = bool(defer_cold_fits)
        self._catch_up: _Chain | None = None
        self._chain_tail: Pending | None = None
        self._catch_up_failed = False  # the next frame then fits cold itself

    @property
    def element_uv(self) -> np.ndarray:
        """(K, 2) material coordinates of the elements, mm."""
        return self.elements.uv_mm

    @property
    def located_uv(self) -> np.ndarray:
        """(L, 2) material coordinates of the elements on the sheet (the ones located), mm."""
        return self.elements.located_uv

    @property
    def element_offset(self) -> np.ndarray:
        """(K,) offsets of the elements along the upper normal, mm."""
        return self.elements.offset_mm

    def set_calibration(self, calibration: Calibration) -> None:
        self.calibration = calibration

    @property
    def reconstructor(self) -> Any:
        """The reconstruction callable (a `Reconstructor` for this geometry, built on first use;
        replaceable, e.g. by tests)."""
        if self._reconstructor is None:
            self._reconstructor = self._new_reconstructor()
        return self._reconstructor

    @reconstructor.setter
    def reconstructor(self, value: Any) -> None:
        self._reconstructor = value

    def _new_reconstructor(self) -> Any:
        from skinmap.reconstruction import Reconstructor

        g = self.geometry
        # on: the reconstructor's own choice by size up to PIPELINE_GRAPH_MAX_CELLS (the graph first
        # up to 64 cells, where the general model misfits above), the general model alone above
        graph_fit = None if self.graph_fit and g.n * g.m <= PIPELINE_GRAPH_MAX_CELLS else False
        # the warm fits' basin test on (reconstructor.WARM_BASIN_RATIO): the chains' cold start every
        # 64 scans does not bound a warm chain's wander.  On the emulated palm gesture (every scan
        # through the pipeline, 400 scans, bench/pipeline_accuracy.py) an 8×8 sheet turning from a
        # bump into a saddle followed a warm graph to 2.6 times 3σ + 0.05 mm, 6 frames beyond;
        # 12×12 9 frames (2.5 times), 16×16 6 (3.9); with the test none, none and one (1.05).  A
        # refused warm fit leaves the frame to the general model (DEGRADED) until the catch-up
        # chain's cold fit takes over.  Its yardstick is the chain's last cold fit's: the audits
        # (GRAPH_AUDIT_SCANS) bound the wander the library's "lowest" yardstick catches, and with
        # that one the 5×5 palm deferred 8 → 44 of 400 frames, the two fingertips 15 → 48.
        return Reconstructor(g.n, g.m, g.pitch_mm, g.h_upper_mm, g.h_lower_mm, g.gauge_length_mm,
                             convex_solver=self.convex_solver, graph_fit=graph_fit, elastic_prior=self.elastic_prior,
                             poisson_range=self.poisson_range, twist_prior=self.twist_prior, gain_sd=self.gain_sd,
                             warm_basin_yardstick="cold")

    def _chain_reconstructor_built(self) -> Any:
        """The restart chains' reconstructor (on the background: built and prepared there)."""
        if self._chain_reconstructor is None:
            rec = self._new_reconstructor()
            rec.prepare(self.strain_sigma)
            self._chain_reconstructor = rec
        return self._chain_reconstructor

    def adopt_prepared(self, prepared: "FramePipeline") -> None:
        """Use the reconstructors ``prepared`` built (:meth:`prepare`; a pipeline of this geometry
        and these options) where this pipeline has none yet (taken over from its predecessor)."""
        if self._reconstructor is None:
            self._reconstructor = prepared._reconstructor
        if self._chain_reconstructor is None:
            self._chain_reconstructor = prepared._chain_reconstructor

    def prepare(self) -> bool:
        """Build the reconstructor and do its first frame's one-off work now (skinmapd: when the
        HELLO arrives, before the scanner is started), unless it was taken over from the pipeline
        this one replaces.  The restart chains' reconstructor is built and prepared too: built on
        the background at the first chain, the frame that takes that chain over waited for it
        (the emulated 5×5 palm, its first catch-up chain 3.8 s in: 86-105 ms).  Answers are
        unchanged.  True if there was work to do."""
        if self._reconstructor is not None:
            return False
        prepare = getattr(self.reconstructor, "prepare", None)
        if prepare is not None:
            prepare(self.strain_sigma)
        if self._chained():
            self._chain_reconstructor_built()
        return True

    def continue_from(self, earlier: "FramePipeline | None") -> None:
        """Take over the reconstructor and warm start of the pipeline this one replaces (after a
        reconnect or a new HELLO) when the geometry is the same."""
        if (earlier is not None and earlier.geometry == self.geometry and earlier.convex_solver == self.convex_solver
                and earlier.graph_fit == self.graph_fit and earlier.twist_sign == self.twist_sign
                and earlier.elastic_prior == self.elastic_prior and earlier.poisson_range == self.poisson_range
                and earlier.twist_prior == self.twist_prior and earlier.gain_sd == self.gain_sd):
            self._reconstructor = earlier._reconstructor
            self._previous = earlier._previous
            self._previous_seq = earlier._previous_seq
            self._chain_reconstructor = earlier._chain_reconstructor
            self._chain = earlier._chain
            self.chain_origin = earlier.chain_origin
            self._catch_up = earlier._catch_up
            self._chain_tail = earlier._chain_tail
            self._catch_up_failed = earlier._catch_up_failed
        if earlier is not None and earlier.geometry == self.geometry:
            # (the sheet's recent motion; a device whose clock restarted leaves none within reach)
            self._motion = list(earlier._motion)

    def process(self, resistance_ohm: np.ndarray, seq: int, device_time_us: int, host_time_ns: int,
                lead: bool = False) -> FrameResult:
        """One scan's resistances (4, N, M) Ω → its frame.  ``lead``: a lead scan (`[output]
        lead_scans`), reconstructed only so that the scan due after it starts warm one scan back,
        and never published: its chains are fed as any frame's and it becomes the next warm start,
        but its σ is not read (every σ UNKNOWN_SIGMA_MM, its elements flagged DEGRADED), and it
        is not held as the last good frame."""
        g = self.geometry
        t_start = time.perf_counter()
        eps_u, eps_l, valid = resistances_to_strains(resistance_ohm, self.calibration)
        cal = self.calibration
        if cal.h_upper_mm is not None and cal.h_lower_mm is not None:  # they come in pairs
            eps_u, eps_l = to_nominal_offsets(eps_u, eps_l, cal.h_upper_mm, cal.h_lower_mm, g.h_upper_mm, g.h_lower_mm)
        eps_u, eps_l, valid, implausible = reject_implausible_units(eps_u, eps_l, valid, g.gauge_length_mm,
                                                                    g.h_upper_mm, g.h_lower_mm)
        t0 = time.perf_counter()
        kwargs: dict[str, Any] = {"strain_sigma": self.strain_sigma}
        if self.twist_sign is not None:
            kwargs["twist_sign"] = self.twist_sign
        starts_cold = self._restart_chain(eps_u, eps_l, seq, kwargs)
        t_chain = time.perf_counter()
        chained = self._chained()
        previous = self._previous if self.warm_start else None
        call = dict(kwargs)
        if starts_cold:
            call["graph_warm"] = False
        if previous is not None:
            call["previous"] = previous
        if chained and self.defer_cold_fits and _graph_tried(previous) and not self._catch_up_failed:
            # (the first frame, with nothing before it, fits cold itself, and so does a frame
            # after one with too few usable units to try a graph: a stream's start or its
            # recovery from bad data is answered at once)
            call["graph_cold"] = False
        self._catch_up_failed = False
        if graph_audit(seq) and not self._audited and getattr(self.reconstructor, "graph_rescue", False):
            # a larger sheet's warm graph (a rescue) kept only while the general model still misfits
            call["graph_recheck"] = True
        surf = self.reconstructor(eps_u, eps_l, **call)
        t_rec = time.perf_counter()
        deferred = bool(getattr(getattr(surf, "diagnostics", None), "extra", {}).get("graph_deferred", False))
        if deferred:
            self._catch_up_chain(eps_u, eps_l, seq, kwargs, previous)
        elif chained and self.defer_cold_fits and graph_audit(seq) and _warm_graph(surf):
            self._audit_chain(eps_u, eps_l, seq, kwargs, previous)
        t_caught = time.perf_counter()
        nodes = np.asarray(surf.nodes, dtype=np.float64)
        normals = np.asarray(surf.normals, dtype=np.float64)
        locate_sigma = getattr(surf, "locate_sigma", None)
        read: tuple[np.ndarray, np.ndarray] | None = None
        if lead:
            # (the σ stage costs as much as the reconstruction itself; a lead's is never read)
            node_sigma = np.full(nodes.shape[:2], UNKNOWN_SIGMA_MM)
            node_scatter = node_sigma
            unknown = np.full(self.elements.count, UNKNOWN_SIGMA_MM)
            read = unknown, unknown
        elif locate_sigma is not None and self.elements.count and self.elements.on_sheet.any():
            # the cell centres' and the elements' σ in one reading each (the cell centres are
            # fine-grid nodes, read there exactly), and the scatter's part the same way
            cells = nodes.shape[0] * nodes.shape[1]
            sigma_all = np.asarray(locate_sigma(self._sigma_uv), dtype=np.float64)
            scatter_all = (np.asarray(locate_sigma(self._sigma_uv, scatter=True), dtype=np.float64)
                           if hasattr(surf, "node_scatter_sigma") else sigma_all)
            node_sigma = sigma_all[:cells].reshape(nodes.shape[:2])
            node_scatter = scatter_all[:cells].reshape(nodes.shape[:2])
            on = self.elements.on_sheet
            if self.elements.all_on_sheet:
                read = sigma_all[cells:], scatter_all[cells:]
            else:  # (the elements off the sheet: σ unknown)
                read = np.full(on.shape, UNKNOWN_SIGMA_MM), np.full(on.shape, UNKNOWN_SIGMA_MM)
                read[0][on], read[1][on] = sigma_all[cells:], scatter_all[cells:]
        else:
            node_sigma = np.asarray(surf.node_sigma, dtype=np.float64)
            node_scatter = np.asarray(getattr(surf, "node_scatter_sigma", node_sigma), dtype=np.float64)
        node_scatter = np.fmin(node_scatter, node_sigma)  # (a part of σ: never above it)
        t_sigma = time.perf_counter()
        located_sigma = (None if read is None else read[0] if self.elements.all_on_sheet
                         else read[0][self.elements.on_sheet])
        pos, nrm, sig = locate_elements(surf, self.elements, located_sigma)
        # (a surface that tells no σ by position, or no elements: the scatter is σ itself, never less)
        scatter = np.fmin(read[1], sig) if read is not None else sig
        lag_mm = 0.0
        if self.response_lag_s > 0.0 and lead:
            self._remember_motion(device_time_us * 1e-6, nodes, None, pos, None)
        elif self.response_lag_s > 0.0:
            node_sigma, sig, lag_mm = self._with_response_lag(device_time_us * 1e-6, nodes, node_scatter, node_sigma,
                                                              pos, scatter, sig)
        t_end = time.perf_counter()
        solve_s = t_end - t0
        stages = {"strains": t0 - t_start, "restart": (t_chain - t0) + (t_caught - t_rec), "reconstruct": t_rec - t_chain,
                  "uncertainty": t_sigma - t_caught, "elements": t_end - t_sigma}

        diagnostics = _diagnostics_dict(getattr(surf, "diagnostics", None))
        diagnostics["implausible_units"] = implausible
        if lag_mm > 0.0:
            diagnostics["response_lag_sigma_mm"] = round(lag_mm, 4)
        if deferred:
            diagnostics["graph_deferred"] = True  # answered by the general model; a catch-up chain fits it
        noise = turning_noise_rad(self.strain_sigma, g.gauge_length_mm, g.h_upper_mm, g.h_lower_mm)
        diagnostics["inconsistent"] = fit_inconsistent(diagnostics.get("residual", 0.0), noise)
        # a gauge the reconstruction's screen named and left out counts as unusable here too:
        # the elements near it rest on its neighbours alone
        usable = valid
        suspects = getattr(getattr(surf, "diagnostics", None), "extra", {}).get("suspect_gauges", ())
        if suspects:
            usable = valid.copy()
            for gauge in suspects:
                usable[("upper", "lower").index(gauge["layer"]), ("row", "column").index(gauge["direction"]),
                       gauge["row"], gauge["col"]] = False
        flags = element_flags(self.elements, sig, usable, ambiguous=getattr(surf, "mirror", None) is not None,
                              inconsistent=diagnostics["inconsistent"])
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
            node_sigma_mm=np.where(np.isfinite(node_sigma), node_sigma, UNKNOWN_SIGMA_MM),
            element_positions_mm=pos,
            element_normals=nrm,
            element_sigma_mm=np.where(np.isfinite(sig), sig, UNKNOWN_SIGMA_MM),
            element_flags=flags,
            solve_time_s=solve_s,
            diagnostics=diagnostics,
            surface=surf,
            stage_s=stages,
            node_scatter_mm=np.where(np.isfinite(node_scatter), node_scatter, UNKNOWN_SIGMA_MM),
            element_scatter_mm=np.where(np.isfinite(scatter), scatter, UNKNOWN_SIGMA_MM),
            geometry=g,
        )
        if not lead:
            self._last_good = result
        return result

    def _with_response_lag(self, time_s: float, nodes: np.ndarray, node_scatter: np.ndarray, node_sigma: np.ndarray,
                           pos: np.ndarray, scatter: np.ndarray, sig: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """node σ and element σ with the gauges' response lag taken in (in quadrature) where the
        sheet moves, and the largest lag term (mm; 0 where the speed is not known): each point's
        speed from the frame MOTION_BASELINE_S or more before (:func:`response_lag_sigma`), no point
        below the nodes' mean, the alignment floor (a reference placed by its best rigid fit moves
        every point by the mean of the nodes' errors).  This frame joins the history."""
        flat_nodes, flat_scatter = nodes.reshape(-1, 3), node_scatter.reshape(-1)
        before = [h for h in self._motion if MOTION_BASELINE_S <= time_s - h.time_s <= MOTION_HORIZON_S]
        largest = 0.0
        if before and before[-1].nodes.shape == flat_nodes.shape and before[-1].elements.shape == pos.shape:
            b = before[-1]
            dt = time_s - b.time_s
            # a lead scan's scatter was not read: the same sheet's a few scans later stands for it
            b_nodes = flat_scatter if b.node_scatter is None else b.node_scatter
            b_elements = scatter if b.element_scatter is None else b.element_scatter
            node_lag = response_lag_sigma(flat_nodes, b.nodes, dt, flat_scatter, b_nodes, self.response_lag_s)
            floor = alignment_floor(node_lag)
            node_lag = np.maximum(node_lag, floor).reshape(node_sigma.shape)
            element_lag = np.maximum(response_lag_sigma(pos, b.elements, dt, scatter, b_elements,
                                                        self.response_lag_s), floor)
            node_sigma = np.hypot(node_sigma, node_lag)
            sig = np.hypot(sig, element_lag)
            largest = float(np.max(node_lag)) if node_lag.size else 0.0
        self._remember_motion(time_s, nodes, node_scatter, pos, scatter)
        return node_sigma, sig, largest

    def _remember_motion(self, time_s: float, nodes: np.ndarray, node_scatter: np.ndarray | None, pos: np.ndarray,
                         scatter: np.ndarray | None) -> None:
        """This frame joins the motion history (its scatter None where it was not read: a lead
        scan), and frames beyond MOTION_HORIZON_S leave it."""
        history = [h for h in self._motion if 0.0 < time_s - h.time_s <= MOTION_HORIZON_S]
        flat_nodes = nodes.reshape(-1, 3)
        if np.isfinite(flat_nodes).all() and np.isfinite(pos).all():  # (a frame held for NaN is not one)
            history.append(_MotionSample(time_s, flat_nodes.copy(),
                                         None if node_scatter is None else np.array(node_scatter, dtype=float).reshape(-1),
                                         np.array(pos, dtype=float),
                                         None if scatter is None else np.array(scatter, dtype=float)))
        self._motion = history

    def _chained(self) -> bool:
        """Whether this pipeline runs the graph fit's chains (warm starts of a graph fit)."""
        rec = self.reconstructor
        return self.warm_start and bool(getattr(rec, "graph_fit", False) or getattr(rec, "graph_rescue", False))

    def _submit(self, chain: _Chain, fn: Callable[[], None]) -> None:
        self._chain_tail = chain.submit(self.background, fn, self._chain_tail)

    def _begin(self, chain: _Chain, eps_u: np.ndarray, eps_l: np.ndarray, seq: int, cold: dict[str, Any]) -> None:
        def begin() -> None:
            chain.reconstructor = self._chain_reconstructor_built()
            chain.step(eps_u, eps_l, seq, cold)

        self._submit(chain, begin)

    def _restart_chain(self, eps_u: np.ndarray, eps_l: np.ndarray, seq: int, kwargs: dict[str, Any]) -> bool:
        """The chains' part of a frame, before it is reconstructed (GRAPH_RESTART_SCANS,
        GRAPH_CATCH_UP_SCANS, GRAPH_AUDIT_SCANS): take over a chain that is due (a restart chain
        after a catch-up chain due at the same scan: it begins the lineage; an audit only where it
        fits the last scan with the lower objective), look at the restart chain before its
        take-over (:meth:`_peek`), begin a restart chain at a block's first scan, or feed the
        chains under way this scan.  True where this frame itself must start cold (a block's
        first scan with no graph to begin a chain from)."""
        if not self._chained():
            return False
        for restart in (False, True):
            chain = self._chain if restart else self._catch_up
            if chain is None or not graph_adopt(chain.origin, seq, chain.adopt_after):
                continue
            if restart:
                self._chain = None
            else:
                self._catch_up = None
            try:
                last = chain.wait()
            except Exception:  # noqa: BLE001 - a failed chain is dropped; the frames go on warm
                log.exception("the graph fit's %s chain from scan %s failed", "restart" if restart else "catch-up",
                              chain.origin)
                last = None
                self._catch_up_failed = not restart
            if last is not None and chain.audit:
                if not _lower_objective(last, chain.last_seq, self._previous, self._previous_seq):
                    last = None  # the published frames' chain stands
                else:
                    last = _with_yardstick(last, self._previous)
            if last is not None:
                self._previous, self._previous_seq = last, chain.last_seq
                if restart:
                    self.chain_origin = chain.origin
        self._peek(seq)
        previous = self._previous
        if self._previous_seq is not None and graph_restart(self._previous_seq, seq):
            # a catch-up chain under way began in the block before: a replay from here could not
            # repeat it
            self._catch_up = None
            if previous is None or getattr(previous.state, "graph", None) is None:
                # no graph to warm-start from: this frame starts cold by itself (nor does the
                # general model's defect correction start from the frame before's)
                self.chain_origin = seq
                return True
            self._chain = _Chain(seq, None, self.located_uv)
            self._begin(self._chain, eps_u, eps_l, seq, {**kwargs, "previous": previous, "graph_warm": False})
            return False
        for chain in (self._chain, self._catch_up):
            if chain is not None:
                self._submit(chain, _step(chain, eps_u, eps_l, seq, dict(kwargs)))
        return False

    @property
    def _audited(self) -> bool:
        """Whether this sheet's warm chain is audited (up to AUDIT_MAX_CELLS cells)."""
        return self.geometry.n * self.geometry.m <= AUDIT_MAX_CELLS

    def _peek(self, seq: int) -> None:
        """The restart chain under way, GRAPH_CATCH_UP_SCANS after its cold start, is an audit of
        the published frames (audits begin only after its take-over): where it fits the scan both
        fitted last with the lower objective, the published frames go on from a copy of its
        surface (the chain goes on, and is taken over as before; the frames until then may differ
        from a replay's, as they may anyway).  Like a take-over, it waits for the chain's steps so
        far."""
        chain = self._chain
        if (chain is None or chain.peeked or seq - chain.origin < GRAPH_CATCH_UP_SCANS
                or graph_adopt(chain.origin, seq, chain.adopt_after) or not self._audited):
            return
        chain.peeked = True
        try:
            last = chain.wait()
        except Exception:  # noqa: BLE001 - the chain's failure is reported at its take-over
            return
        if last is not None and _lower_objective(last, chain.last_seq, self._previous, self._previous_seq):
            self._previous = _with_yardstick(copy.copy(last), self._previous)
            self._previous_seq = chain.last_seq

    def _audit_chain(self, eps_u: np.ndarray, eps_l: np.ndarray, seq: int, kwargs: dict[str, Any],
                     previous: Any) -> None:
        """A published frame answered warm at an audit's scan (GRAPH_AUDIT_SCANS): begin an
        audit, a catch-up chain from this scan's cold fit taken over only where it ends on the
        lower objective (unless a chain is under way)."""
        if self._catch_up is None and self._audited:
            self._begin_catch_up(eps_u, eps_l, seq, kwargs, previous, audit=True)

    def _catch_up_chain(self, eps_u: np.ndarray, eps_l: np.ndarray, seq: int, kwargs: dict[str, Any],
                        previous: Any) -> None:
        """A published frame deferred its cold graph fit: begin a catch-up chain with it (unless
        one is under way: it will take the frames over, an audit then unconditionally)."""
        if self._catch_up is not None:
            self._catch_up.audit = False
            return
        self._begin_catch_up(eps_u, eps_l, seq, kwargs, previous, audit=False)

    def _begin_catch_up(self, eps_u: np.ndarray, eps_l: np.ndarray, seq: int, kwargs: dict[str, Any],
                        previous: Any, audit: bool) -> None:
        """Begin the catch-up chain (an audit, or a deferred frame's) from this scan's cold fit."""
        self._catch_up = _Chain(seq, None, self.located_uv, GRAPH_CATCH_UP_SCANS, audit=audit)
        cold = {**kwargs, "graph_warm": False}
        if previous is not None:
            cold["previous"] = previous
        self._begin(self._catch_up, eps_u, eps_l, seq, cold)

    def _stale(self, seq, device_time_us, host_time_ns, eps_u, eps_l, valid, solve_s) -> FrameResult:
        g = self.geometry
        if self._last_good is not None:
            prev = self._last_good
            nodes, normals, node_sigma = prev.nodes_mm, prev.normals, prev.node_sigma_mm
            pos, nrm, sig = prev.element_positions_mm, prev.element_normals, prev.element_sigma_mm
            flags = held_flags(prev.element_flags)
            scatters = (prev.node_scatter_mm, prev.element_scatter_mm)
        else:
            uv = g.cell_uv()
            nodes = np.concatenate([uv, np.zeros((g.n, g.m, 1))], axis=-1)
            normals = np.broadcast_to([0.0, 0.0, 1.0], nodes.shape).copy()
            node_sigma = np.full((g.n, g.m), UNKNOWN_SIGMA_MM)
            pos, nrm, sig, flags = prior_elements(self.elements)
            scatters = (None, None)
        return FrameResult(seq, device_time_us, host_time_ns, eps_u, eps_l, valid, nodes, normals, node_sigma,
                           pos, nrm, sig, flags, solve_s, {"status": "non-finite solution; held last good frame"}, None,
                           node_scatter_mm=scatters[0], element_scatter_mm=scatters[1])


def _diagnostics_dict(diag: Any) -> dict[str, Any]:
    if diag is None:
        return {}
    if isinstance(diag, dict):
        items = diag.items()
    else:
        items = getattr(diag, "__dict__", {}).items()
    return {k: v for k, v in items if isinstance(v, (int, float, str, bool))}
