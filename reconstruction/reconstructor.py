"""The reconstructor: gauge strains of one frame → a :class:`~.surface.Surface`
(docs/reconstruction.md).  :class:`Reconstructor` holds one sensor geometry's fine grid, its
operators and their factorisations, and runs the steps per frame: the gauge screen
(:mod:`.robust`), the height-graph fit (:mod:`.graphfit`), the general model (:mod:`.engine`,
through the compiled :mod:`.kernels`), the posterior check (the mirror, the stretch pattern's
twist of :mod:`.stretchtwist`, the uncertainty of :mod:`.uncertainty`) and the opt-in elastic
prior (:mod:`.positionfit`).
:func:`reconstruct` keeps a small cache of reconstructors keyed by the geometry.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import threading
import time
from collections import OrderedDict
from functools import partial
from typing import Any, Callable, cast

import numpy as np
from threadpoolctl import ThreadpoolController

from skinmap.strains import GAUGE_LENGTH_MM

from .decouple import decouple
from .engine import (
    Metric,
    integrate_frames,
    least_shear_noise,
    least_shear_twists,
    least_shear_value,
    stretch_supports_curvature,
    metric_terms,
    integrate_positions,
    potential_curvatures,
    rotation_rates,
    solve_shear,
    solve_twist,
    stretch_variance,
    unit_data,
)
from .grid import FineGrid
from .graphfit import MAX_CELLS as GRAPH_FIT_MAX_CELLS
from .graphfit import AGREE_SIGMAS as GRAPH_AGREE_SIGMAS
from .graphfit import WARM_LINEAR, GraphFit, GraphResult, disagreement
from .graphsheet import SlopeNoise, free_part, graph_sheet_fields, slope_noise
from .productnoise import ProductNoise, measure_product_noise, pair_product, turning_noise_estimate
from .robust import GaugeScreen, Suspect, huber_potential
from .forward import GaugeLayout, Patches, misfit, misfit_and_strains, unit_box_mean
from .airy import airy_gaussian_curvature
from .membrane import MembraneMaps, TwistReading, membrane_maps
from .positionfit import ElasticFit, PositionFitSettings, start_from_surface
from .surface import Diagnostics, FrameState, Surface
from .stretchtwist import MEMBRANE_SIGN_RATIO, OPEN_SIGMAS, TWIST_PRIORS, StretchPatternTwist
from .twistfamily import (MIRROR_FLOOR_MM, MIRROR_SIGMAS, _given, _half_reach, _larger, _mean_twist_terms, _memo,
                          _mirror_if_distinct, _widened, _with_reading_noise, _with_twist, _within_noise)
from .uncertainty import (DEFAULT_GAIN_SD, DEFAULT_STRAIN_SIGMA, RESOLUTION_SHARE, SigmaField,
                          alignment_floor, fine_sigma, gain_sigma, graph_resolution_share, resolution_sigma, sigma_field,
                          stretch_noise_sd, with_gain)

__all__ = ["reconstruct", "decouple", "Reconstructor", "Surface", "FrameState", "Diagnostics", "DEFAULT_STRAIN_SIGMA",
           "DEFAULT_GAIN_SD",
           "GRAPH_FIT_MAX_CELLS", "GRAPH_AGREE_SIGMAS", "to_sensor_frame", "nodes_in_sensor_frame"]

# The least-shear twist replaces the model's own when it needs less than this share of the
# latter's shear; mirror-image minima within this factor of each other are one choice.
LEAST_SHEAR_GAIN, LEAST_SHEAR_TIE = 0.5, 1.2
# A least-shear twist taken with its square this many s.d. of the curvature product's noise or
# fewer from the untaken one's (the bar is 3) is taken by the noise: repeated frames may not
# take it, and the way back is part of the scatter σ.
MARGINAL_SIGMAS = 5.0
# A defect-correction pass is kept only if it lowers the χ² below this share of the last.
DEFECT_GAIN = 0.99
#: Where the noise alone leaves the general model above one χ² per gauge (24×24 and larger: its
#: nonlinear steps; `_noise_response`), a defect pass also reads the residual averaged over this
#: many units square, gauge by gauge kind (on noisy data always, on noise-free data where the raw
#: pass fails): the model's defect is smooth over the cells, the noise is not, and the raw
#: residual feeds the noise back into the model's input a second time.  Without it a noisy 32×32
#: sphere's pass failed on half the frames or more, which then kept the uncorrected model's own
#: error: a bias of the noise, 0.067 mm rms over the nodes against 0.011 with it
#: (docs/reconstruction.md, *Under noise on large sheets*).
DEFECT_SMOOTH_UNITS = 3
# Passes that take the constant twist below this share of what the uncorrected model read (or
# left open) leave that twist open (the passes refine a twist; losing most of it is no refinement:
# kinematic 12×12 and 16×16 saddles' passes move it by less, and their σ would double).
LOST_TWIST_SHARE = 0.5
# Posterior check (Reconstructor._posterior): a χ² difference below this many units (times the
# misfit's Birge ratio) does not tell two answers apart (2 s.d. of one parameter).
MIRROR_CHI2 = 4.0
MIRROR_SHARE = 0.5
# ... and a mirror image is said aloud (Surface.mirror, AMBIGUOUS) unless the gauges read it worse
# than the answer by this many units (3 s.d.): a wrong sign costs millimetres with a small σ.  At
# 2 s.d. a saddle turned by exactly 45° on 8×8 (R -147 mm; both signs give the same strains, and
# the two graph fits read them 0.029 and 0.048 per gauge) took the wrong sign unflagged, 7.8 mm
# off (1 of 16 reconstructions, 8 clean and 8 noisy; 5×5: 1 of 48).
MIRROR_FLAG_CHI2 = 9.0
# A frame's defect correction starts from the previous frame's where the strains changed by no
# more than this many times what two noise draws differ by (rms over the gauges): the sheet held
# still (Reconstructor._warm_general).
HELD_SIGMAS = 2.0
# ... on sheets of up to this many cells.  On larger ones a feature that moves by about the
# noise per gauge each frame passes that test, yet the correction it carries away no longer
# fits: a bump circling on 16×16 failed 15 of 24 such starts, each a pass spent (4.9 → 6.3 ms
# a frame); on 12×12 and smaller the test rejected the moving bump's frames, and held films
# gained (5×5 ×0.5–0.8, 12×12 saddles ×0.9).
WARM_DEFECT_MAX_CELLS = 144
#: Sheets above GRAPH_FIT_MAX_CELLS and up to this many cells fit the height graph cold only
#: where the general model's answer misfits the gauges by more than GRAPH_RESCUE_CHI2 times the
#: χ² per gauge the noise alone leaves in its answers (`_noise_response`, at least one), and warm
#: where the frame before was a graph.  Measured on the bench's kinematic classes at 12×12 and
#: 16×16 (noisy frames): a bump sharper than the cells 18-2700 per gauge, the general model then
#: 0.2-0.3 mm off; every other class at most 2.9.  (Twisted quadrics read 0.5-2.9, 0.17-0.34 mm
#: off from 1.5 up, and a threshold of 1.5 rescued them, but the timing table's broad bump on
#: 16×16 crossed it once and stayed on warm graph frames of 12-30 ms: docs/reconstruction.md.)
GRAPH_RESCUE_MAX_CELLS = 256
GRAPH_RESCUE_CHI2 = 8.0
#: A warm graph fit whose objective (data misfit and prior) is above this many times its chain's
#: yardstick (its last cold fit's objective, or the lowest since: WARM_BASIN_YARDSTICKS) is not
#: taken: it has followed another basin of the fit, one the chain carried from frame to frame
#: while a cold fit of the same data lands elsewhere (the modes the gauges pin least, beyond
#: their ends), and the frame fits cold instead (the library's default,
#: ``Reconstructor(warm_basin_ratio=...)``, and skinmapd's: its chains' cold restart every 64
#: scans does not bound the wander, daemon/pipeline.py).  Broad shapes moving on an ellipse over
#: 5×5, 100 noisy frames each warm from the one before (bench/reconstruction.py, *Warm chains*):
#: 0.051 / 0.153 / 0.087 mm mean with 74 / 75 / 58 frames beyond 3σ + 0.05 mm, now 0.010 /
#: 0.018 / 0.025 mm with 0 / 0 / 11 (each frame cold: 0.011 / 0.018 / 0.015, 0 / 0 / 2), 1-4
#: cold refits a chain; a sharp bump moving
#: over 12×12 and 16×16 never reaches it (docs/reconstruction.md, "Long warm chains").  The
#: objective at the optimum scatters with the noise (a 7×7 chain's cold fits 8.6–18.7), so a
#: ratio much below 2 refits on noise alone.
WARM_BASIN_RATIO = 2.0
#: A warm graph fit whose objective has climbed above this many times the lowest its chain
#: reached since its last cold fit or linear start (FrameState.graph_lowest), and by more than
#: WARM_CLIMB_SDS, while the basin test still passes it, descends the frame's linear start too,
#: and the lower objective answers (GraphFit.fit_warm).  Both are graphs: no frame is refused
#: for it, so a ratio below the basin test's costs a descent where the noise alone climbed, not
#: an answer.  Two fingertips on a 4×4 membrane every scan in skinmapd (whose yardstick is the
#: chain's last cold fit): a chain climbed from 21 to 362 while the cold fits of the same scans
#: stayed at 15-29 and its yardstick, a cold fit at the deepest press, stood at 483; one node
#: went 0.56 mm off with σ 0.08.  A bump circling over 8×8, 40 frames a turn, each warm from the
#: one before (the library's yardstick): corner nodes 0.34-0.48 mm off with σ 0.09-0.1 at 1.4-1.9
#: times the lowest, 5 frames beyond 3σ + 0.05 mm; with 1.5, none (docs/reconstruction.md, *A
#: warm chain that climbs*).
WARM_CLIMB_RATIO = 1.5
#: ... the s.d. of the noise's own part of the objective (half a χ² of 2 per unit, s.d.
#: √n_valid) it must also have climbed by: where the prior holds the objective low (the 5×5 palm
#: gesture's warm fits at 2-9), a few times the lowest is within the noise, and descending the
#: linear start there changed which frames were deferred (3-6 more of 400 every scan, 3 seeds).
WARM_CLIMB_SDS = 1.0
#: What a warm graph fit's objective is held against (``Reconstructor(warm_basin_yardstick=...)``):
#: "lowest", the lowest objective its chain has reached since its last cold fit (a chain that
#: leaves its basin climbs from there, while a cold fit that itself landed high lets it climb
#: twice as far: a broad dent whose chain began on a cold fit at objective 15.9, where the
#: frames' own cold fits sat at 1.4-5.5, climbed to 30 before it refitted, 0.12 mm off with σ
#: 0.04); "cold", the last cold fit's (skinmapd: its audits fit its chain's scans cold every
#: 8th scan and take over where lower, and a frame it refuses is deferred, DEGRADED, not
#: refitted in the frame; with "lowest" its 5×5 palm deferred 8 → 44 of 400 frames).
WARM_BASIN_YARDSTICKS = ("lowest", "cold")
# A constant twist that only the least-shear prior of a turned saddle gives (no stretch reading
# confirms it; none included) has its square uncertain by this share of the answer's mean
# Gaussian curvature (films with friction on 12 12×12 saddle molds: off by up to 0.42 of it;
# the prior was as far off in the square on large and small twists alike).
SHEAR_PRIOR_SHARE = 0.5
#: A sheet two cells across (N or M = 2) cannot read its constant twist at all: the gauges lie
#: along the rows and columns, which a twist leaves straight, and it reaches the data only
#: through the Gaussian curvature, which the stretch gives through its second differences
#: along both directions (Brioschi), and two cells have none across.  A 2×2 sheet on a saddle
#: turned 45° reads as flat, on a sphere as the cylinder at 45° (its stretch, alike at four
#: cells that lie alike about the centre, varies with neither).  With ``twist_prior`` "open"
#: (the default) every twist whose normal turns by up to this many radians along the sheet's
#: longer side, of either sign unless told, joins ``node_sigma`` (2 rad over a 2×2 sheet of
#: 12 mm pitch: 0.083 /mm, a saddle of R 12 mm at 45°).  Measured on the bench's kinematic
#: classes on 2×2, 3 noisy frames each, every frame within 3σ + 0.05 mm where 36 of 129 were
#: beyond (a 45° saddle 1.45 mm off with σ 0.008): docs/reconstruction.md, *A sheet two cells
#: across*.
UNREAD_TWIST_TURN = 2.0
# A χ² per gauge above this for both the model's own twist and the least-shear prior's: the data
# explain neither, so the prior has no answers it could choose among and the model's own stands
# (a sharp 5 mm bump on a noisy 16×16 sheet: 2400 and 4800 per gauge, the prior's twist 7.9 mm off).
GROSS_MISFIT = 100.0
# Data whose own turning noise (productnoise.turning_noise_estimate) is below this share of the
# stated read the constant twist against their own noise: a noise-free 16×16 cylinder 6.6° off
# the rows had its twist shrunk to a third by the stated noise's test, 0.75 mm off.  (The MAD
# estimate of a 5×5 sheet's 30 second differences scatters by about a fifth: a noisy frame
# reads below 0.3 about once in a thousand.)
QUIET_SHARE = 0.3
# The graph fit needs most units (a graph is judged by all of its gauges' misfit).
_GRAPH_MIN_UNITS = 0.8
ELASTIC_PRIOR_MAX_CELLS = 64  # the position fit's dense normal matrix grows as (N·M)²
# Seeded noisy flat frames that measure the general model's answer to noise (Reconstructor._noise_response).
RESPONSE_DRAWS, RESPONSE_SEED = 24, 20241201

#: The sensor frame's plane is the sheet's best-fit plane while that is well defined: its
#: normal's variance at most this share of the next direction's.  A sheet wrapped further
#: (a half tube of a circular section is 0.19, a 240° wrap 0.37, a closed tube 1) turns to the
#: centre's tangent plane by :data:`FRAME_PLANE_BLEND`, continuously.
FRAME_PLANE_OPEN = 0.3
FRAME_PLANE_BLEND = 0.2


def _positive(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
    return value


def default_subdivision(n: int, m: int) -> int:
    """Fine-grid intervals per pitch: 4 (3 mm at 12 mm pitch) resolves features down to the
    gauge length; arrays of more than 100 cells use 2 to keep the frame time within budget."""
    return 4 if n * m <= 100 else 2


def _noise_present(estimate: float, turning_sigma: float) -> float:
    """The turning noise the data carry (``estimate``, productnoise.turning_noise_estimate): the
    stated ``turning_sigma`` where too few units tell, at most twice it (more is a sharp
    feature's doing)."""
    return turning_sigma if not math.isfinite(estimate) else min(estimate, 2.0 * turning_sigma)


@dataclasses.dataclass(frozen=True)
class TwistLeftOpen:
    """What the data leave open about an answer's constant twist c0: each joins ``node_sigma``
    as a reach on the answer's family (:meth:`Reconstructor._twist_noise`), besides the noise
    through the curvature product."""

    #: a less-sheared twist within the noise that the model did not take (the shift to it,
    #: 1/mm): half the distance to it joins, so that 3 s.d. reach past it
    undecided: float = 0.0
    #: that twist is the curvature product's reading, which the answer did not take: reached
    #: past by OPEN_SIGMAS s.d. of the reading's own noise, in the square
    undecided_read: bool = False
    #: the twist's sign is within the noise and not told: half the distance to the mirror image
    #: (the twist −c0) joins (a cylinder turned 6° from the grid lines: the product's noise hid
    #: the sign of its 0.0015 /mm twist, and the default sign was 0.65 mm off with σ 0.054 mm)
    sign_open: bool = False
    #: the magnitude the curvature product allows where its noise shrank the twist taken
    #: (engine.solve_twist): half the distance to the twist of that magnitude, of either sign
    #: unless ``twist_sign`` tells it (the same cylinder where the shrunk twist was none: 0.87
    #: mm off, σ 0.058)
    open_twist: float = 0.0
    #: the sign the user told (±1), or None
    twist_sign: float | None = None
    #: a twist only a prior gave, nothing confirming it (1/mm²): half the distance to the twists
    #: whose squares lie that far either side of the answer's joins all of the above, of both
    #: signs unless ``twist_sign`` or ``prior_sign_told`` keeps the answer's
    prior_span: float = 0.0
    #: a mirror answer stands beside this one and covers the other sign
    prior_sign_told: bool = False


def _deferred(graph: GraphResult | None) -> GraphResult:
    """The record of a cold graph fit left to the caller (``graph_cold=False``)."""
    why = "no warm start" if graph is None else graph.how
    base = graph if graph is not None else GraphResult(False, np.zeros(0), math.inf, math.inf, 0, 0.0, math.inf, "",
                                                       math.inf)
    return base._replace(how=f"deferred: {why}")


class Reconstructor(StretchPatternTwist):
    """Reconstruction for one sensor geometry; holds the fine grid, its operators and their
    factorisations, so that each call only does per-frame work.  Not thread-safe: it fills its
    caches (per validity mask, per noise level) as frames come; use one per thread, or
    :func:`reconstruct`, which locks each of its cached instances.  What a frame leaves for the
    next is explicit: :attr:`Surface.state`, read when that surface is passed as ``previous``.

    Parameters
    ----------
    n, m : rows and columns of cells.
    pitch : cell pitch (mm).
    h_upper, h_lower : gauge offsets from the neutral plane (mm).
    gauge_length : gauge length (mm), at most the pitch.
    subdivision : fine-grid intervals per pitch (even, >= 2); default :func:`default_subdivision`.
    shear_passes : fixed-point passes of the shear estimate (0 keeps the material lines
        orthogonal, F = 0).
    frame_corrections : least-squares rotation corrections after the tree integration.
    kernels : "compiled" (default: the per-frame steps after the field fit as numba-compiled
        loops, :mod:`.kernels`, compiled or loaded from numba's cache here rather than in the
        first frame) or "numpy" (the reference implementation in :mod:`.engine`; also used when
        numba is not installed).  Both give the same surface to rounding.
    graph_fit : fit the sheet as a height graph to every gauge's turning and stretch first
        (step 0 in docs/reconstruction.md; its surface, and its own uncertainty, are used when
        it explains the data within the noise and, on a cold frame, agrees with the general
        model's surface within their combined uncertainty, else the general model's).  It
        resolves bumps sharper than a gauge (5 mm / FWHM 15 mm: 0.19 → 0.02 mm mean error) and
        twisted sheets pressed out of plane.  None (default): on for sheets of up to 64 cells
        (:data:`GRAPH_FIT_MAX_CELLS`; its unknowns grow as (3N + 3)(3M + 3)); above, up to
        :data:`GRAPH_RESCUE_MAX_CELLS`, tried only where the general model's answer misfits the
        gauges (:data:`GRAPH_RESCUE_CHI2`) or warm from a previous graph answer; True
        asks for it (an error above 64 cells), False for the general model alone.
    convex_solver : "factorized" (default: the least-squares field fit by its cached
        factorisation, the exact optimum) or "clarabel" (the same convex fit with a Huber loss
        on the turning data, threshold ``huber_sigmas`` noise s.d., solved by Clarabel each
        frame, 20-100 ms).  The fit interpolates the units' data, so residuals stay inside the
        Huber threshold and both give the same surface, even with a glitching gauge (see
        docs/reconstruction.md, "Solvers").
    least_shear : take the least-shear constant twist among those the data allow, as the prior
        for the one parameter the gauges leave open (docs/reconstruction.md, "Posterior check").
    defect_steps : passes of defect correction through the gauges' exact forward model on
        general-model answers that misfit (0: none).
    poisson_range : the film's Poisson ratio, as an interval (default 0.3-0.5, any elastomer;
        narrow it with a calibrated value).  Where the general model answers and the stretch
        pattern reads as one mean Gaussian curvature (Airy), the constant twist must give that
        curvature for some ratio in the interval; an answer that does not is moved to one that
        does, the interval's spread is part of ``node_sigma`` and a sign the gauges cannot tell
        leaves :attr:`Surface.mirror` set (docs/reconstruction.md, "The stretch pattern's
        twist").  None: off.
    warm_basin_ratio : a warm graph fit above this many times its chain's yardstick
        (``warm_basin_yardstick``) has followed another basin and the frame fits cold (default
        :data:`WARM_BASIN_RATIO`; None: off; skinmapd keeps it on, docs/reconstruction.md,
        "Long warm chains").
    warm_basin_yardstick : that yardstick: "lowest" (default), the lowest objective the chain
        has reached since its last cold fit; "cold", the last cold fit's (skinmapd, which
        audits its chain; :data:`WARM_BASIN_YARDSTICKS`).
    gauge_screen : screen every frame for a gauge its neighbours contradict (a gain off by tens
        of percent, still reading) before the fits (:class:`.robust.GaugeScreen`: a closed-form
        fit with redundancy, and a Huber fit by Clarabel when a gauge stands out); a gauge it
        names is left out as missing and reported in ``Surface.diagnostics.suspect_gauges``
        (docs/reconstruction.md, "Robust gauge screen").  On by default.
    twist_prior : what ``node_sigma`` takes of a twist the stretch pattern cannot tell from
        none, where the answer has none: "open" (default: the twists up to the reading's
        interval's top, of either sign not told, join it; the gauges read a dome's twist only
        through its Gaussian curvature, so a sphere and a dome turned off the grid read
        alike) or "none" (the sheet is known to carry no twist there: a balloon, a sphere,
        molds whose principal axes lie along the rows and columns; its σ then does not
        reach it).  On a sheet two cells across, which cannot read its twist at all, "open"
        also has σ reach every twist up to :data:`UNREAD_TWIST_TURN`.  Answers are the same
        either way (docs/reconstruction.md, "A twist the stretch cannot tell from none", "A
        sheet two cells across").
    gain_sd : the s.d. (relative) of a gain error every gauge shares, carried into
        ``node_sigma`` (not into its scatter part: it is the same on every frame of a held
        sheet).  Default :data:`DEFAULT_GAIN_SD`, the gauges' hysteresis (a loop 4.21 ± 0.70 %
        of the excursion high reads a sheet pressed and held up to half of it low) and their
        relaxation under a held strain (up to 3.5 % low), in quadrature; raise it
        for gauges whose gauge factors are known less well, 0 leaves it out
        (docs/reconstruction.md, "A gain the gauges share").
    """

    def __init__(
        self,
        n: int,
        m: int,
        pitch: float = 12.0,
        h_upper: float = 0.2,
        h_lower: float = 0.2,
        gauge_length: float = GAUGE_LENGTH_MM,
        subdivision: int | None = None,
        shear_passes: int = 2,
        frame_corrections: int = 1,
        convex_solver: str = "factorized",
        huber_sigmas: float = 4.0,
        kernels: str = "compiled",
        graph_fit: bool | None = None,
        least_shear: bool = True,
        defect_steps: int = 2,
        elastic_prior: PositionFitSettings | None = None,
        gauge_screen: bool = True,
        poisson_range: tuple[float, float] | None = (0.3, 0.5),
        warm_basin_ratio: float | None = WARM_BASIN_RATIO,
        warm_basin_yardstick: str = "lowest",
        twist_prior: str = "open",
        gain_sd: float = DEFAULT_GAIN_SD,
    ):
        self.least_shear = bool(least_shear)
        if (isinstance(gain_sd, bool) or not isinstance(gain_sd, (int, float)) or not math.isfinite(gain_sd)
                or not 0.0 <= gain_sd < 0.5):
            raise ValueError(f"gain_sd must be a number in [0, 0.5), got {gain_sd!r}")
        self.gain_sd = float(gain_sd)
        if twist_prior not in TWIST_PRIORS:
            raise ValueError(f"twist_prior must be one of {', '.join(TWIST_PRIORS)}, got {twist_prior!r}")
        self.twist_prior = twist_prior
        if warm_basin_ratio is not None and not (isinstance(warm_basin_ratio, (int, float))
                                                 and not isinstance(warm_basin_ratio, bool) and warm_basin_ratio > 1.0):
            raise ValueError(f"warm_basin_ratio must be a number > 1 or None, got {warm_basin_ratio!r}")
        self.warm_basin_ratio = math.inf if warm_basin_ratio is None else float(warm_basin_ratio)
        if warm_basin_yardstick not in WARM_BASIN_YARDSTICKS:
            raise ValueError(f"warm_basin_yardstick must be one of {', '.join(WARM_BASIN_YARDSTICKS)}, "
                             f"got {warm_basin_yardstick!r}")
        self.warm_basin_yardstick = warm_basin_yardstick
        if poisson_range is not None:
            try:
                lo, hi = (float(x) for x in poisson_range)
            except (TypeError, ValueError):
                raise ValueError(f"poisson_range must be (low, high) or None, got {poisson_range!r}") from None
            if not (0.0 <= lo <= hi < 0.5 + 1e-12):
                raise ValueError(f"poisson_range must satisfy 0 <= low <= high <= 0.5, got {poisson_range!r}")
            poisson_range = (lo, hi)
        self.poisson_range = poisson_range
        # the film's stretch per Gaussian curvature (:mod:`.membrane`), built at first use
        self._membrane: MembraneMaps | None = None
        if isinstance(defect_steps, bool) or int(defect_steps) != defect_steps or defect_steps < 0:
            raise ValueError(f"defect_steps must be an integer >= 0, got {defect_steps!r}")
        self.defect_steps = int(defect_steps)
        for name, val in (("n (rows)", n), ("m (columns)", m)):
            if isinstance(val, bool) or int(val) != val or int(val) < 2:
                raise ValueError(f"{name} must be an integer >= 2, got {val!r}")
        self.n, self.m = int(n), int(m)
        self.pitch = _positive("pitch", pitch)
        self.h_upper, self.h_lower = float(h_upper), float(h_lower)
        decouple(np.zeros(1), np.zeros(1), self.h_upper, self.h_lower)  # validates the offsets
        self.gauge_length = _positive("gauge_length", gauge_length)
        sub = default_subdivision(self.n, self.m) if subdivision is None else subdivision
        if isinstance(sub, bool) or int(sub) != sub:
            raise ValueError(f"subdivision must be an even integer >= 2, got {subdivision!r}")
        self.grid = FineGrid(self.n, self.m, self.pitch, self.gauge_length, sub=int(sub))
        for name, val in (("shear_passes", shear_passes), ("frame_corrections", frame_corrections)):
            if isinstance(val, bool) or int(val) != val or val < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {val!r}")
        self.shear_passes, self.frame_corrections = int(shear_passes), int(frame_corrections)
        if convex_solver not in ("factorized", "clarabel"):
            raise ValueError(f"convex_solver must be 'factorized' or 'clarabel', got {convex_solver!r}")
        self.convex_solver = convex_solver
        self.huber_sigmas = _positive("huber_sigmas", huber_sigmas)
        if not isinstance(gauge_screen, (bool, np.bool_)):
            raise ValueError(f"gauge_screen must be True or False, got {gauge_screen!r}")
        self._screen = GaugeScreen(self.n, self.m, self.h_upper, self.h_lower) if gauge_screen else None
        self.gauge_screen = bool(gauge_screen)
        if kernels not in ("compiled", "numpy"):
            raise ValueError(f"kernels must be 'compiled' or 'numpy', got {kernels!r}")
        self._compiled = None
        if kernels == "compiled":
            from . import kernels as compiled  # numba's import cost only where it is used

            if compiled.AVAILABLE:
                grid = self.grid
                a0, b0 = grid.centre
                self._band = compiled.laplacian_band(grid.incidence, a0 * grid.mf + b0, grid.laplacian.band)
                self._no_shear_target = np.zeros((grid.nf, grid.mf))
                compiled.warm_up(grid.spacing, a0, b0, self._band, self.shear_passes, self.frame_corrections)
                self._compiled = compiled
        self.kernels = "compiled" if self._compiled is not None else "numpy"
        graph_default = graph_fit is None
        if graph_fit is None:
            graph_fit = self.n * self.m <= GRAPH_FIT_MAX_CELLS
        if not isinstance(graph_fit, (bool, np.bool_)):
            raise ValueError(f"graph_fit must be True, False or None (by size), got {graph_fit!r}")
        if graph_fit and self.n * self.m > GRAPH_FIT_MAX_CELLS:
            raise ValueError(f"graph_fit is for sheets of up to {GRAPH_FIT_MAX_CELLS} cells "
                             f"(its unknowns grow as (3N + 3)(3M + 3)), got {self.n}x{self.m}")
        self._graph = None
        #: the graph fit kept for the frames the general model misfits (by default, 65 to 256 cells)
        self.graph_rescue = bool(graph_default and not graph_fit and self.n * self.m <= GRAPH_RESCUE_MAX_CELLS)
        if graph_fit or self.graph_rescue:
            self._graph = GraphFit(self.n, self.m, self.pitch, self.gauge_length, self.grid.u, self.grid.v,
                                   self.grid.inner, compiled=self._compiled)
        self.graph_fit = bool(graph_fit)
        if elastic_prior is not None and not isinstance(elastic_prior, PositionFitSettings):
            raise ValueError(f"elastic_prior must be a PositionFitSettings or None, got {type(elastic_prior).__name__}")
        if elastic_prior is not None and self.n * self.m > ELASTIC_PRIOR_MAX_CELLS:
            raise ValueError(f"elastic_prior is for sheets of up to {ELASTIC_PRIOR_MAX_CELLS} cells (its dense "
                             f"normal matrix grows as (N·M)²), got {self.n}x{self.m}")
        self.elastic_prior = elastic_prior
        self._position = (None if elastic_prior is None
                          else ElasticFit(self.n, self.m, self.pitch, self.gauge_length, elastic_prior))
        self._position_on_grid: Any = None  # the fit's basis on the fine grid, built at first use
        self._layout = GaugeLayout.build(self.n, self.m, self.pitch, self.gauge_length, self.h_upper, self.h_lower,
                                         compiled=self._compiled)
        self._half_diagonal2 = 0.25 * ((self.n * self.pitch) ** 2 + (self.m * self.pitch) ** 2)
        # the largest twist σ reaches on a sheet whose stretch cannot read it (UNREAD_TWIST_TURN)
        self._unread_twist_limit = (UNREAD_TWIST_TURN / (max(self.n, self.m) * self.pitch)
                                    if min(self.n, self.m) < 3 and twist_prior == "open" else 0.0)
        # the sheet's response |u·v| to a twist shift of one (/mm), where that limit is used
        self._twist_response = (np.abs(self.grid.v[:, None] * self.grid.u[None, :])
                                if self._unread_twist_limit > 0.0 else None)
        # what the turning noise makes of the mean curvature product, measured on first use
        # (all-valid field maps; a few dead units change it little)
        self._product_noise: ProductNoise | None = None
        # this frame's fields (k_u, k_v, τ₀) and their ProductNoise.cross_sd (_product_stats)
        self._product_cross: list[tuple[tuple, float]] = []
        self._least_shear_sd: float | None = None  # engine.least_shear_noise, on first use
        # the last measured data's fields, with their input (_measured_fields)
        self._measured_memo: tuple | None = None
        self._slope_noise_draws: SlopeNoise | None = None
        # the general model's scatter over the linear map's, per noise level (measured on first use)
        self._noise_responses: dict[float, tuple[float, float]] = {}
        self._shared_maps: dict[tuple[int, float], tuple[np.ndarray, np.ndarray]] = {}
        # BLAS thread limits for each call (the libraries' list is read once, here)
        self._blas = ThreadpoolController()
        self._blas_libraries = self._blas.select(user_api="blas").lib_controllers

    def _check_strains(self, name: str, eps) -> np.ndarray:
        eps = np.asarray(eps, dtype=float)
        if eps.shape != (2, self.n, self.m):
            raise ValueError(f"{name} must have shape (2, {self.n}, {self.m}) for this sensor, got {eps.shape}")
        if not ((eps > -1.0) & (eps < np.inf)).all():  # also false for NaN: look closer only then
            if np.isinf(eps).any():
                raise ValueError(f"{name} contains infinite strain; give NaN for a missing gauge")
            if (eps <= -1.0).any():
                raise ValueError(f"{name} contains strain <= -1 (a gauge compressed to zero length)")
        return eps

    def __call__(
        self,
        eps_upper,
        eps_lower,
        *,
        strain_sigma: float = DEFAULT_STRAIN_SIGMA,
        previous: Surface | None = None,
        twist_sign: float | None = None,
        graph_warm: bool = True,
        graph_cold: bool = True,
        graph_recheck: bool = False,
    ) -> Surface:
        """Reconstruct one frame.  NaN marks a missing gauge (its unit is dropped and filled by
        the smoothness prior; a mask not seen before leaves its units out of the all-valid fits
        instead of refactorising, see docs/reconstruction.md, "Missing units").  A constant twist can have two mirror-image solutions with
        identical strains (an oblique cylinder; a saddle turned by 45°): ``twist_sign`` (+1 or
        −1) picks one; by default the sign of ``previous`` (the last frame's surface) is kept,
        else +1.  Where the stretch pattern fixes the sign (a saddle turned off 0° and 45°) the
        data decide unless ``twist_sign`` is given.  ``graph_warm=False``: the graph fit starts
        cold although ``previous`` holds a graph, and the general model's defect correction from
        none, not from the previous frame's (a warm start depends on the frames before it;
        skinmapd restarts cold every 64 scans so that a log replays bit for bit from there).  A
        warm graph fit far above its chain's last cold fit's objective has followed another
        basin and the frame fits cold (:data:`WARM_BASIN_RATIO`); a chain that drifts slowly
        within the noise is not caught by that, so a caller chaining frames through ``previous``
        for long may still pass ``graph_warm=False`` now and then (docs/reconstruction.md, "Long
        warm chains").
        ``graph_cold=False``: a frame that would need a cold graph fit (no warm start, or the warm
        fit failed) and whose data the fit's screen does not rule out is answered by the general
        model (its first answer, no defect correction), with ``diagnostics.extra``
        ``graph_deferred`` True and ``graph_fit`` "deferred: ..." (why), its uncertainty widened
        by its resolution (uncertainty.resolution_sigma: a sheet that may be a graph may have
        features sharper than the gauges); the caller fits that frame cold elsewhere (skinmapd:
        on its restart worker, then warm-starts from it), so no frame pays for a cold fit.
        ``graph_recheck=True`` (sheets of 65 to 256 cells, where the graph is a rescue): a warm
        graph is kept only where the general model's answer still misfits the gauges as a cold
        frame's must for the graph to be tried (:data:`GRAPH_RESCUE_CHI2`), else the general
        model answers and the chain of graphs ends (a graph begun on a sharp or inconsistent frame
        is no longer carried on by its warm start alone; skinmapd asks every GRAPH_AUDIT_SCANS).

        BLAS runs on one thread during the call and when the surface's uncertainty is first
        read (this thread's problems are small: on a busy 2-core machine several BLAS threads
        made a 5×5 frame 5 times slower)."""
        with self._one_blas_thread_context():
            t0 = time.perf_counter()
            screened = self._screen_gauges(eps_upper, eps_lower, strain_sigma)
            if screened is not None and screened[0]:
                eps_upper, eps_lower = screened[2], screened[3]
            t_screen = time.perf_counter() - t0
            surf = self._reconstruct(eps_upper, eps_lower, strain_sigma, previous, twist_sign, graph_warm,
                                     graph_cold, graph_recheck)
        for answer in (surf, surf.mirror):
            if answer is not None and answer._fine_sigma_fn is not None:
                answer._fine_sigma_fn = sigma_field(answer._fine_sigma_fn).wrapped(self._one_blas_thread)
            if answer is not None and answer._scatter_sigma_fn is not None:
                answer._scatter_sigma_fn = sigma_field(answer._scatter_sigma_fn).wrapped(self._one_blas_thread)
            if answer is not None and screened is not None:
                _report_screen(answer.diagnostics, screened[0], screened[1], t_screen)
        return surf

    def _gain_map(self, positions: np.ndarray, stretch: np.ndarray, twist: float = 0.0) -> np.ndarray:
        """The fine-node σ of a gain error the gauges share (:func:`.uncertainty.gain_sigma`, the
        answer's constant ``twist`` taken apart), no less anywhere than its mean over the nodes:
        after a reference's best rigid fit the sheet's centre moves by the mean of the nodes'
        errors too (the alignment floor, as the noise's σ has it)."""
        sigma = gain_sigma(positions, self.grid.u, self.grid.v, stretch, self.pitch, self.gain_sd, twist)
        return np.maximum(sigma, alignment_floor(sigma[np.ix_(self.grid.node_rows, self.grid.node_cols)]))

    def _screen_gauges(self, eps_upper, eps_lower, strain_sigma):
        """The gauge screen's verdict on this frame, (suspects, what it did, the strains with the
        suspects set missing), or None when it is off or the input is for _reconstruct to refuse."""
        if self._screen is None:
            return None
        eu = self._check_strains("eps_upper", eps_upper)
        el = self._check_strains("eps_lower", eps_lower)
        try:
            sigma = float(strain_sigma)
        except (TypeError, ValueError):
            return None
        if not (math.isfinite(sigma) and sigma >= 0.0):
            return None
        # misfits below the sensor's noise mean nothing (as for the fits' own tests)
        suspects, info = self._screen.screen(eu, el, max(sigma, DEFAULT_STRAIN_SIGMA))
        if suspects:
            eu, el = eu.copy(), el.copy()
            for s in suspects:
                (eu if s.layer == 0 else el)[s.direction, s.row, s.col] = np.nan
        return suspects, info, eu, el

    def prepare(self, strain_sigma: float = DEFAULT_STRAIN_SIGMA) -> None:
        """Do now the one-off work the first frames would otherwise pay for: numba's kernels (done
        at construction), then the caches that a first frame read at this noise level fills, namely
        the all-valid fits, the noise's own curvature product and the general model's measured
        answer to noise (:meth:`_noise_response`, tens of milliseconds at 5×5, about a second at
        32×32), the uncertainty maps, the membrane's stretch maps (:mod:`.membrane`) and the
        slopes' noise draws (:func:`.graphsheet.slope_noise`).  A flat
        frame is reconstructed and its uncertainty read here; skinmapd calls this when a scanner's HELLO gives the geometry, so that its first
        published frames are not the slow ones."""
        flat = np.zeros((2, self.n, self.m))
        surf = self(flat, flat, strain_sigma=strain_sigma)
        centre = np.zeros((1, 2))
        _ = surf.node_sigma, surf.locate_sigma(centre)
        # and the same for a bent sheet: the graph fit and the posterior check's other branches
        bent = np.full((2, self.n, self.m), 1e-3)
        surf = self(bent, -bent, strain_sigma=strain_sigma, previous=surf)
        _ = surf.node_sigma, surf.locate_sigma(centre)
        # the membrane's stretch maps (0.15 s at 5×5, under a second on large sheets), which the
        # first elastic frame would otherwise build
        if self.poisson_range is not None and self._membrane is None:
            self._membrane = membrane_maps(self.grid)
        # the noise draws the graph sheet's twist is weighed against (tens of milliseconds)
        self._slope_noise()

    def _graph_fit(self) -> GraphFit:
        """The graph fit's operators (only called where the graph fit is on)."""
        assert self._graph is not None
        return self._graph

    def _one_blas_thread_context(self) -> contextlib.AbstractContextManager:
        """BLAS on one thread within the block; nothing to do where it runs on one already
        (skinmapd limits the process: a limit entered and left costs about 20 µs, a frame
        enters it several times)."""
        if all(lib.num_threads == 1 for lib in self._blas_libraries):
            return contextlib.nullcontext()
        return self._blas.limit(limits=1, user_api="blas")

    def _one_blas_thread(self, fn):
        """``fn`` run with BLAS on one thread."""
        def run(*args):
            with self._one_blas_thread_context():
                return fn(*args)

        return run

    def _reconstruct(self, eps_upper, eps_lower, strain_sigma, previous, twist_sign, graph_warm,
                     graph_cold: bool = True, graph_recheck: bool = False) -> Surface:
        t0 = time.perf_counter()
        self._product_cross.clear()  # (kept within a frame only)
        eu = self._check_strains("eps_upper", eps_upper)
        el = self._check_strains("eps_lower", eps_lower)
        strain_sigma = float(strain_sigma)
        if not math.isfinite(strain_sigma) or strain_sigma < 0:
            raise ValueError(f"strain_sigma must be a finite number >= 0, got {strain_sigma!r}")
        if previous is not None and not isinstance(previous, Surface):
            raise ValueError(f"previous must be a Surface from an earlier call, got {type(previous).__name__}")
        grid = self.grid
        units = unit_data(eu, el, self.h_upper, self.h_lower, self.gauge_length)  # (the steps below read them again)
        turning, stretch, valid = units
        if not (np.array_equal(np.isfinite(eu), valid) and np.array_equal(np.isfinite(el), valid)):
            # a unit with one gauge reading is missing (no fit uses a lone gauge), and so is its
            # lone gauge to every check against the gauges: what an answer predicts there is its
            # prior's fill, and on a saddle at 45° with three lone gauges on 8×8 their misfit,
            # 170-700 in χ², set the sign (11 mm off, unflagged) where the live units read both
            # alike (docs/reconstruction.md, "Missing units")
            eu, el = np.where(valid, eu, np.nan), np.where(valid, el, np.nan)
        n_valid = int(valid.sum())
        status = "solved" if n_valid == valid.size else f"solved with {valid.size - n_valid} missing unit(s)"
        if n_valid == 0:
            status = "no valid gauge: flat sheet assumed"
        if twist_sign is not None and twist_sign not in (1, -1, 1.0, -1.0):
            raise ValueError(f"twist_sign must be +1 or -1, got {twist_sign!r}")
        graph = None
        general = None
        warm = None
        deferred = False
        rescue = False  # a cold graph fit only if the general model's answer misfits (larger sheets)
        measured: list = []
        fresh_lowest = False  # (a warm chain's yardstick of its climb, WARM_CLIMB_RATIO)

        def data_fields() -> tuple:
            # the fields of the measured data, once a frame (the twist carried over and a warm
            # defect correction both read them)
            if not measured:
                measured.append(self._measured_fields(turning, stretch, valid))
            return measured[0]

        carried, reading = self._carried_twist(previous, twist_sign, turning, stretch, valid, strain_sigma,
                                               data_fields)
        graph_sigma: dict = {}

        def cold_fit(answer: tuple, starts: tuple) -> tuple[GraphResult, dict]:
            # the cold graph fit from ``starts`` (the general model's ``answer`` among them), held
            # to that answer by the agreement test; with the graph σ the test computed
            agree, sigma = self._agreement(answer, turning, valid, data, fit_sigma)
            return self._graph_fit().fit_cold(data, answer[0], twist_sign, agree, starts), sigma

        if self._graph is not None and n_valid >= _GRAPH_MIN_UNITS * valid.size:
            fit_sigma = max(strain_sigma, DEFAULT_STRAIN_SIGMA)  # misfits below the sensor's noise mean nothing
            sig_t = self._turning_sd(fit_sigma)
            sig_s = self._stretch_sd(fit_sigma)
            data = self._graph.prepare(turning, stretch, valid, sig_t, sig_s)
            state = previous.state if previous is not None and graph_warm else None
            linear_once: list = []  # the cold fit's linear start, computed once where asked for

            def linear_start() -> tuple[list, list[str]]:
                if not linear_once:
                    linear_once.append(self._graph_fit().cold_starts(data))
                return linear_once[0]

            warm = (state.graph, state.graph_before) if state is not None and state.graph is not None else None
            if warm is not None:
                assert state is not None
                climbed_over = max(WARM_CLIMB_RATIO * state.graph_lowest,
                                   state.graph_lowest + WARM_CLIMB_SDS * math.sqrt(n_valid))
                refused_over = self.warm_basin_ratio * state.graph_reference
                graph = self._graph.fit_warm(data, warm, twist_sign, linear_start, climbed_over, refused_over)
                # the frame's linear start descended beside the warm steps (unsettled, or climbed):
                # its best objective is the chain's lowest from here
                fresh_lowest = graph.accepted and (graph.how == WARM_LINEAR
                                                   or climbed_over < graph.objective <= refused_over)
                reference = state.graph_reference
                if graph.accepted and graph.objective > self.warm_basin_ratio * reference:
                    graph = graph._replace(accepted=False, how=(
                        f"warm: objective {graph.objective:.4g}, {graph.objective / reference:.3g} times the chain's "
                        "cold fit's (another basin)"))
                if graph.accepted:
                    why, _ = self._graph.warm_screen(graph.coeffs, data, linear_start())
                    if why:
                        graph = graph._replace(accepted=False, how=f"warm: {why}")
            if self.graph_rescue and (graph is None or not graph.accepted):
                # a larger sheet: the general model answers first, and the graph is fitted cold
                # only where that answer misfits the gauges (below)
                rescue = True
            linear = linear_start() if (graph is None or not graph.accepted) and not rescue else None
            ruled_out = self._graph.ruled_out(linear) if linear is not None else None
            if ruled_out is not None:
                # no graph can answer (the screen needs no start but the linear one): the general
                # model answers, as it would after the cold fit's own screen
                graph = ruled_out
            elif (graph is None or not graph.accepted) and not rescue:
                # cold: the general model first (a start for the fit, the surface an accepted
                # graph must agree with, and the answer if no graph fits or agrees)
                general = self._general(turning, stretch, valid, n_valid, strain_sigma, previous, twist_sign, (eu, el),
                                        carried, units)
                starts = self._graph.cold_starts(data, general[0], linear)
                if not graph_cold and not all(starts[1]):
                    # a cold fit to do, left to the caller: this frame is the general model's
                    graph = _deferred(graph)
                    deferred = True
                else:
                    graph, graph_sigma = cold_fit(general, starts)

        def general_answer(first, correct: bool) -> tuple:
            """The general model's answer: from the previous frame's correction where that holds,
            else from ``first`` (or a fresh pass) through the defect correction."""
            warm_general = None
            if first is None and correct and graph_warm:
                warm_general = self._warm_general(previous, eu, el, data_fields, units, n_valid, strain_sigma,
                                                  twist_sign, carried)
            if warm_general is not None:
                return warm_general
            if first is None:
                first = self._general(turning, stretch, valid, n_valid, strain_sigma, previous, twist_sign, (eu, el),
                                      carried, units)
            if correct:
                first = self._defect_correction(first, eu, el, valid, n_valid, strain_sigma, previous, twist_sign,
                                                carried, units)
            return first

        answered = None  # the general model's answer, where a rescue tried the graph after it

        def general_misfits(answer: tuple) -> bool:
            # the rescue's test: the general model's answer misreads the gauges beyond what its noise leaves
            chi_read = answer[3].get("forward_chi2")
            chi2_noise = self._noise_response(strain_sigma)[1]
            return chi_read is not None and chi_read[1] > GRAPH_RESCUE_CHI2 * chi2_noise * max(chi_read[2], 1)

        if (graph_recheck and self.graph_rescue and warm is not None and graph is not None and graph.accepted
                and not rescue):
            answered = general_answer(None, bool(n_valid and self.defect_steps))
            if not general_misfits(answered):
                graph = graph._replace(accepted=False, how=(
                    "warm: not needed, the general model reads the gauges within the rescue's bound"))
            else:
                answered = None
        if rescue:
            answered = general_answer(None, bool(n_valid and self.defect_steps))
            if general_misfits(answered):
                linear = linear_start()
                ruled_out = self._graph_fit().ruled_out(linear)
                if ruled_out is not None:
                    graph = ruled_out
                elif not graph_cold:
                    graph = _deferred(graph)
                    deferred = True
                else:
                    graph, graph_sigma = cold_fit(answered, self._graph_fit().cold_starts(data, answered[0], linear))
        left_out = True
        derivatives = None  # the answer's own ∂u, ∂v, ∂u∂v at the fine nodes (a graph's)
        if graph is not None and graph.accepted:
            pos, derivatives = self._graph_surface(graph.coeffs)
            twist_c = graph.twist
            convex_info = {"status": "not needed (graph fit)", "iterations": 0}
            iterations = graph.iterations
            fit = None
            positions_at = None
            if n_valid < valid.size:
                left_out = getattr(grid.field_maps(valid), "left_out", True)
        else:
            # (a deferred frame is the general model's first answer: its defect correction costs
            # as much as the cold fit it stands in for, and the posterior check widens its
            # uncertainty by the misfit left)
            correct = bool(n_valid and self.defect_steps and not deferred)
            general = answered if answered is not None else general_answer(general, correct)
            pos, twist_c, fit, convex_info, left_out, positions_at = general
            iterations = self.shear_passes + self.frame_corrections + convex_info["iterations"]
        if not np.isfinite(pos).all():
            # Only reachable with wildly inconsistent data; a surface must still come out.
            uu, vv = np.meshgrid(grid.u, grid.v)
            pos = np.stack([uu, vv, np.zeros_like(uu)], axis=-1)
            status = "numerical failure: flat sheet returned"
        # misfit of the fitted fields to the data, as turning angle per gauge (rad)
        if fit is None:
            assert graph is not None  # the graph answered
            residual = float(graph.turning_rms * self.gauge_length)
        else:
            fit = fit[valid.ravel()] if n_valid < valid.size else fit
            residual = math.sqrt(float(fit @ fit) / fit.size) * self.gauge_length if fit.size else 0.0
        if not math.isfinite(residual):
            residual = float("inf")
        h_u, h_l = self.h_upper, self.h_lower
        diag = Diagnostics(
            iterations=iterations,
            residual=residual,
            solve_time=0.0,
            status=status,
            twist_constant=twist_c,
            valid_units=n_valid,
            extra={"convex_solver": self.convex_solver, "convex_status": convex_info["status"], "kernels": self.kernels,
                   "model": "graph" if fit is None else "general"},
        )
        for key in ("least_shear_shift", "least_shear_stretch_rss", "least_shear_contested", "least_shear_marginal",
                    "undecided_twist", "open_twist",
                    "shear_prior_twist", "shear_prior_curvature", "defect_steps", "defect_smoothed", "defect_unsmoothed_chi2",
                    "defect_warm",
                    "graph_twist_sd", "product_ramp", "pair_product"):
            if key in convex_info:
                diag.extra[key] = convex_info[key]
        if graph is not None:
            diag.extra.update(graph_fit=graph.how, graph_steps=graph.iterations,
                              graph_chi2=(round(graph.chi2_turning, 4), round(graph.chi2_stretch, 4)))
            if math.isfinite(graph.agreement):
                diag.extra["graph_agreement"] = round(graph.agreement, 3)
            if deferred:
                diag.extra["graph_deferred"] = True
        def general_sigma() -> np.ndarray:
            return self._scaled(fine_sigma(grid, valid, turning, strain_sigma, h_u, h_l, left_out=left_out),
                                self._noise_response(strain_sigma)[0])

        surface_sigma: SigmaField
        if fit is None:  # the graph's own scatter; a missing unit's region as the general model has it
            assert graph is not None
            known = graph_sigma.get(graph.coeffs.tobytes())  # from the agreement test, at the fit's noise

            def graph_field() -> np.ndarray:
                assert graph is not None
                if known is not None:
                    sigma = known * (strain_sigma / fit_sigma)
                else:
                    sigma = self._graph_fit().fine_height_sigma(graph.coeffs, data, strain_sigma / fit_sigma, grid.centre)
                return sigma if n_valid == valid.size else np.maximum(sigma, general_sigma())

            # skinmapd reads the nodes and its elements' patches only: those alone, unless the
            # agreement test computed the whole field anyway
            graph_at = (None if known is not None else
                        self._graph_fit().height_sigma_at(graph.coeffs, data, strain_sigma / fit_sigma, grid.centre))

            def graph_nodes(flat: np.ndarray) -> np.ndarray:
                assert graph_at is not None
                sigma = graph_at(flat)
                return sigma if n_valid == valid.size else np.maximum(sigma, general_sigma().reshape(-1)[flat])

            surface_sigma = SigmaField(graph_field, None if graph_at is None else graph_nodes)
        elif deferred:
            # a frame a graph may fit (the screen passed): the sheet may have structure at the
            # gauge scale, which the general model cannot resolve, so its resolution is part of
            # its uncertainty (as in the agreement test a graph must pass)
            def deferred_sigma() -> np.ndarray:
                sig_turn = math.sqrt(2.0) * max(strain_sigma, DEFAULT_STRAIN_SIGMA) / (h_u + h_l)
                return np.sqrt(general_sigma() ** 2 + resolution_sigma(grid, valid, turning, sig_turn) ** 2)

            surface_sigma = SigmaField(deferred_sigma)
        else:
            surface_sigma = SigmaField(general_sigma)
        surf = self._surface(pos, surface_sigma, diag, derivatives)
        if deferred:
            surf._scatter_sigma_fn = SigmaField(general_sigma)
        if n_valid:
            def graph_mirror(sign: float) -> tuple[np.ndarray, bool, np.ndarray | None]:
                """The graph fitted again with the opposite twist sign, from the general model's
                answer with that sign (no agreement test: it is only weighed against the data),
                whether it is a graph (else the general model's answer with that sign), and the
                graph's own derivatives (read as the answer's are: both signs of a saddle at 45°
                read the same strains, and only the same reading shows it)."""
                general_m = self._general(turning, stretch, valid, n_valid, strain_sigma, None, sign, (eu, el),
                                          units=units)
                fit_m = self._graph_fit().fit_cold(data, general_m[0], sign)
                if fit_m.accepted:
                    pos_g, derivatives_g = self._graph_surface(fit_m.coeffs)
                    return pos_g, True, derivatives_g
                return general_m[0], False, None

            product_fields = convex_info.get("product_fields") if fit is not None else None
            twist_mean = cast("float | None", convex_info.get("twist_mean")) if fit is not None else None
            measured_fields = convex_info.get("measured_fields", product_fields) if fit is not None else None
            chi2_read = cast("tuple | None", convex_info.get("forward_chi2")) if fit is not None else None
            known = chi2_read[1:] if chi2_read is not None and chi2_read[0] is pos else None
            resolution_term: Callable[[], np.ndarray] | None = None
            if not deferred and grid.dense_maps:
                # the general model's fields misplace curvature that changes at the gauge scale,
                # and a graph fills it in between the gauges by its prior, less wrongly (a
                # deferred frame carries the whole term already)
                share = RESOLUTION_SHARE if fit is not None else graph_resolution_share(grid.n * grid.m)

                def resolution_field() -> np.ndarray:
                    sig_turn = math.sqrt(2.0) * max(strain_sigma, DEFAULT_STRAIN_SIGMA) / (h_u + h_l)
                    return share * resolution_sigma(grid, valid, turning, sig_turn)

                resolution_term = resolution_field

            surf = self._posterior(surf, eu, el, strain_sigma, positions_at, twist_sign, graph_mirror, turning, valid,
                                   product_fields, known, stretch if convex_info.get("graph_sheet") is None else None,
                                   twist_mean, measured_fields, reading, resolution_term, carried is not None)
        # the next frame's start: this graph and the one before it (a moving shape is predicted)
        earlier = warm[0] if graph is not None and graph.how == "warm" and warm is not None else None
        # (and the general model's defect correction, from which the next frame's starts)
        defect = cast("tuple[np.ndarray, float] | None", convex_info.get("defect")) if fit is not None else None
        # the yardstick of the chain's warm fits: its last cold fit's objective, or the lowest
        # since (WARM_BASIN_YARDSTICKS; a warm frame the linear start answered stays in the chain;
        # only the prediction from the graph before, in another basin, is dropped)
        chained = warm is not None and graph is not None and graph.how in ("warm", WARM_LINEAR)
        reference = (previous.state.graph_reference if chained and previous is not None
                     else graph.objective if graph is not None else math.inf)
        if chained and graph is not None and self.warm_basin_yardstick == "lowest":
            reference = min(reference, graph.objective)
        lowest = graph.objective if graph is not None else math.inf
        if chained and previous is not None and not fresh_lowest:
            lowest = min(previous.state.graph_lowest, lowest)
        surf.state = (FrameState(graph.coeffs, earlier, graph_reference=reference, graph_objective=graph.objective,
                                 graph_lowest=lowest)
                      if fit is None and graph is not None
                      else FrameState() if defect is None
                      else FrameState(defect=defect[0], defect_chi2=defect[1], strains=np.stack([eu, el])))
        if self._position is not None and n_valid:
            surf = self._elastic_prior(surf, turning, stretch, valid, strain_sigma, previous, (eu, el), twist_sign)
        diag.solve_time = time.perf_counter() - t0
        if self.gain_sd > 0.0:  # a gain the gauges share, from this frame's stretch (σ's term, read on demand)
            for answer in (surf, surf.mirror):
                if answer is not None and answer._fine_sigma_fn is not None:
                    answer._fine_sigma_fn = with_gain(answer._fine_sigma_fn,
                                                      partial(self._gain_map, answer._coeffs[..., 0, :], stretch,
                                                              answer.diagnostics.twist_constant))
        return surf


    def _scaled(self, base: np.ndarray, scale: float) -> np.ndarray:
        """``base * scale``, read-only and shared like ``base`` (one copy per map and scale)."""
        if scale == 1.0:
            return base
        return self._shared_map(base, scale, lambda b: b * scale)

    def _floored(self, base: np.ndarray, floor: float) -> np.ndarray:
        """``base`` raised to ``floor`` (the alignment floor of ``base`` itself, so one value per
        map), read-only and shared like ``base``."""
        return self._shared_map(base, -1.0, lambda b: np.maximum(b, floor))

    def _shared_map(self, base: np.ndarray, tag: float, make: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``make(base)``, made once per shared map ``base`` and ``tag`` (the last 16 kept)."""
        key = (id(base), tag)
        hit = self._shared_maps.get(key)
        if hit is None or hit[0] is not base:
            out = make(base)
            out.flags.writeable = False
            if len(self._shared_maps) >= 16:
                self._shared_maps.pop(next(iter(self._shared_maps)))
            hit = self._shared_maps[key] = (base, out)
        return hit[1]

    def _noise_response(self, strain_sigma: float) -> tuple[float, float]:
        """How the general model answers strain noise alone, measured once per noise level on
        :data:`RESPONSE_DRAWS` seeded noisy flat frames: (its root-mean-square node scatter over
        that of the linear map :func:`.uncertainty.fine_sigma`, the χ² per gauge its answers
        then leave at the posterior check's noise level).  The model integrates its fields along
        the rows and columns with least-squares frame corrections, which averages out part of
        the noise the linear map carries (flat 16×16: 0.58 of the map's scatter, 32×32: 0.28),
        and on large sheets its nonlinear steps leave the noise a χ² above one per gauge
        (32×32: 2-6): that much misfit is the noise's, not the model's."""
        if not strain_sigma > 0.0:
            return 1.0, 1.0
        key = float(strain_sigma)
        hit = self._noise_responses.get(key)
        if hit is not None:
            return hit
        grid = self.grid
        rng = np.random.default_rng(RESPONSE_SEED)
        shape = (2, self.n, self.m)
        rows, cols = grid.node_rows, grid.node_cols
        sigma_f = max(key, DEFAULT_STRAIN_SIGMA)
        nodes, chi2 = [], []
        for _ in range(RESPONSE_DRAWS):
            eu, el = rng.normal(0.0, key, shape), rng.normal(0.0, key, shape)
            turning, stretch, valid = unit_data(eu, el, self.h_upper, self.h_lower, self.gauge_length)
            pos = self._general(turning, stretch, valid, valid.size, key, None, None)[0]
            nodes.append(pos[rows[:, None], cols])
            chi, dof, _ = misfit(self._candidate(pos), self._layout, eu, el, sigma_f)
            chi2.append(chi / max(dof, 1))
        nodes_a = np.array(nodes)
        dev = nodes_a - nodes_a.mean(axis=0)
        # less the twist the noise leaves open on a flat sheet (the mode u·v): the twist's own
        # term carries it (engine.solve_twist's open twist, _twist_noise), so this ratio is the
        # integration's alone
        mode = np.outer(grid.v[rows], grid.u[cols])
        if (mode * mode).sum() > 0.0:
            dev[..., 2] -= np.multiply.outer(np.tensordot(dev[..., 2], mode, axes=2) / (mode * mode).sum(), mode)
        spread2 = (dev ** 2).sum(axis=3).mean(axis=0)
        linear = fine_sigma(grid, valid, np.zeros(shape), key, self.h_upper, self.h_lower)[rows[:, None], cols]
        keep = linear > 0.0
        ratio = math.sqrt(float(spread2[keep].sum()) / float((linear[keep] ** 2).sum())) if keep.any() else 1.0
        hit = (min(max(ratio, 0.25), 4.0) if math.isfinite(ratio) else 1.0, max(1.0, float(np.median(chi2))))
        if len(self._noise_responses) >= 4:
            self._noise_responses.pop(next(iter(self._noise_responses)))
        self._noise_responses[key] = hit
        return hit

    def _slope_noise(self) -> SlopeNoise:
        """The geometry's :class:`.graphsheet.SlopeNoise` (built on first use, or in prepare())."""
        if self._slope_noise_draws is None:
            valid = np.ones((2, self.n, self.m), dtype=bool)
            self._slope_noise_draws = slope_noise(self.grid, self.grid.field_maps(valid))
        return self._slope_noise_draws

    def _least_shear_noise(self) -> float:
        """The s.d. of the least-shear square of the twist per unit stretch noise
        (:func:`.engine.least_shear_noise`, measured on first use)."""
        if self._least_shear_sd is None:
            self._least_shear_sd = least_shear_noise(self.grid, self.grid.field_maps(np.ones((2, self.n, self.m), dtype=bool)))
        return self._least_shear_sd

    def _product_stats(self, k_u, k_v, tau0, turning_sigma: float) -> tuple[float, float]:
        """(bias, s.d.) of the mean curvature product k_u k_v − τ₀² over the cells' region
        that turning noise of s.d. ``turning_sigma`` (one unit, per length) causes, for these
        fields (:mod:`.productnoise`)."""
        if not turning_sigma > 0.0:
            return 0.0, 0.0
        grid = self.grid
        if self._product_noise is None:
            valid = np.ones((2, self.n, self.m), dtype=bool)
            self._product_noise = measure_product_noise(grid.field_maps(valid), valid, grid.inner)
        # (a frame asks for the same fields' statistics several times, at one or two noise
        # levels: the fields' part is kept, by the arrays' identity, until the next frame)
        for fields, cross in self._product_cross:
            if fields[0] is k_u and fields[1] is k_v and fields[2] is tau0:
                return self._product_noise.stats_at(cross, turning_sigma)
        tau0_c = np.asarray(tau0, dtype=float)
        cross = self._product_noise.cross_sd(np.asarray(k_u), np.asarray(k_v), tau0_c - tau0_c.sum() / tau0_c.size,
                                             grid.inner)
        if len(self._product_cross) >= 8:
            del self._product_cross[0]
        self._product_cross.append(((k_u, k_v, tau0), cross))
        return self._product_noise.stats_at(cross, turning_sigma)

    def _twist_noise(self, positions_at, base_shift: float, c0: float, product_sd, strain_sigma: float,
                     left: TwistLeftOpen = TwistLeftOpen(), twist_sd: float | None = None):
        """A function giving the fine-grid position s.d. (mm) that the turning noise causes
        through the constant twist, or None where there is none to speak of.  The twist comes
        from the mean curvature product k_u k_v, whose s.d. ``product_sd(strain σ)`` is measured
        through the model's field maps (:mod:`.productnoise`); c = √(product) then has the s.d. of that over
        2|c|, and the sheet's response to c is taken from the model itself (±5 % of c).  What
        the data leave open about the twist (``left``, :class:`TwistLeftOpen`) joins it as
        reaches on the answer's family (``positions_at``, the answer at ``base_shift``).
        ``twist_sd``: the twist's s.d. where it was read otherwise than from the product (the
        graph sheet's stretch pattern, ``graph_twist_sd``)."""
        if positions_at is None:
            return lambda: None
        twist_sign, sign_open, undecided = left.twist_sign, left.sign_open, left.undecided
        if left.prior_span > 0.0:
            rest = self._twist_noise(positions_at, base_shift, c0, product_sd, strain_sigma,
                                     dataclasses.replace(left, prior_span=0.0, prior_sign_told=False), twist_sd)
            # the squares c0² ± span, of the answer's sign where it is told or its mirror stands
            # beside it, else of either (the prior reads a square, not a sign: a saddle 18° off
            # the columns took 5.9·10⁻⁴ /mm of the default sign, unflagged, for −2.5·10⁻³)
            if twist_sign is not None:
                signs: tuple[float, ...] = (float(twist_sign),)
            elif left.prior_sign_told and c0 != 0.0:
                signs = (math.copysign(1.0, c0),)
            else:
                signs = (1.0, -1.0)
            ends = [s * math.sqrt(max(c0 * c0 + d, 0.0)) - c0 for s in signs for d in (left.prior_span, -left.prior_span)]
            return _widened(positions_at, base_shift, ends, rest)
        if left.open_twist > 0.0:
            targets = [s * left.open_twist - c0 for s in ((1.0, -1.0) if twist_sign is None else (twist_sign,))]
            rest = self._twist_noise(positions_at, base_shift, c0, product_sd, strain_sigma,
                                     TwistLeftOpen(undecided, left.undecided_read, sign_open), twist_sd)
            return _widened(positions_at, base_shift, targets, rest)
        # (a sign the noise leaves open reaches the mirror image as well: a 5×5 cylinder 5.6° off
        # the columns took the less-sheared twist of the default sign, 1.5 mm off at a corner,
        # its σ reaching back only to the product's shrunk twist)
        mirrored = (-2.0 * c0,) if sign_open else ()
        if undecided != 0.0 and not left.undecided_read:
            # (a twist taken from the least-shear prior carries its own noise too, which the
            # same turning data give it through the curvature product: a 12×12 cylinder of R 225
            # mm 9.7° off the rows took 9.1·10⁻⁴ /mm for 7.4·10⁻⁴ on 2 noisy frames of 150, 0.9
            # mm off at a corner, its σ reaching only back to the product's shrunk twist)
            own = self._twist_noise(positions_at, base_shift, c0, product_sd, strain_sigma, TwistLeftOpen(), twist_sd)
            return _widened(positions_at, base_shift, (undecided, *mirrored), own)
        if undecided != 0.0:
            # (past that twist by OPEN_SIGMAS s.d. of its own estimate, which the same product
            # gives: a cylinder of R 374 mm 8° off the columns on a noisy 32×32 sheet left its
            # 3.8·10⁻⁴ /mm twist undecided at 2.6·10⁻⁴ and was 1.14 × (3σ + 0.05) off at a corner)
            # (in the square, which the product reads: near zero the twist's own s.d. diverges)
            other = c0 + undecided
            sigma_product = product_sd(strain_sigma) if strain_sigma > 0.0 else 0.0
            beyond = math.copysign(math.sqrt(other * other + OPEN_SIGMAS * sigma_product), other) - other
            reach = undecided + math.copysign(abs(beyond), undecided)
            return _memo(lambda: _half_reach(positions_at, base_shift, (reach, *mirrored)))
        if abs(c0) * self._half_diagonal2 / 2.0 <= MIRROR_FLOOR_MM or strain_sigma == 0.0:
            return lambda: None
        if twist_sd is not None:
            sigma_c = twist_sd
        else:
            sigma_product = product_sd(strain_sigma)
            sigma_c = min(sigma_product / (2.0 * abs(c0)), math.sqrt(sigma_product))

        def spread() -> np.ndarray:
            step = 0.05 * abs(c0)
            response = positions_at(base_shift + step) - positions_at(base_shift - step)
            out = np.sqrt((response * response).sum(axis=2)) * (sigma_c / (2.0 * step))
            if sign_open:
                out = np.maximum(out, _half_reach(positions_at, base_shift, (-2.0 * c0,)))
            return out

        return _memo(spread)

    def _fresh(self, turning, stretch, valid, sigma_f: float, sign: float, strains, twist_mean: float):
        """The general model modelled afresh with the twist's ``sign`` and mean ``twist_mean``
        given (no previous frame), through its defect correction: a candidate to weigh."""
        n_valid = int(valid.sum())
        out = self._general(turning, stretch, valid, n_valid, sigma_f, None, sign, strains, twist_mean)
        if self.defect_steps:
            out = self._defect_correction(out, strains[0], strains[1], valid, n_valid, sigma_f, None, sign, twist_mean)
        return out

    def _defect_correction(self, general, eu, el, valid, n_valid: int, strain_sigma: float, previous, twist_sign,
                           twist_mean: float | None = None, units: tuple | None = None):
        """Carry the model through the gauges' exact forward model (:mod:`.forward`): the
        strains the answer would read are compared with those measured, the difference is added
        to the model's input and the model runs again (defect correction; its fixed point is an
        answer that reads exactly what was measured).  The model's own linearisations (small
        slopes in the potential, the first-order Gauss and Codazzi terms, chords) are then
        corrected where the data see them; what the data cannot see stays the prior's.  At
        most ``defect_steps`` passes, each kept only if it fits the measured strains better,
        and none once the answer fits within the noise.  The constant twist keeps its sign.
        Where the noise alone leaves the model above one χ² per gauge, a pass also reads the
        residual averaged over :data:`DEFECT_SMOOTH_UNITS` units square (on data that carry noise
        always, else where the raw pass fails) and takes it where it gains and keeps the constant
        twist (``defect_smoothed``: how many such passes; ``defect_unsmoothed_chi2``: the χ² per
        gauge the raw pass leaves, which σ widens by).
        The answer's info carries the correction its input had (2, 2, N, M) and its χ²
        (``defect``: where the next frame's starts, :meth:`_warm_general`).  ``units``: the unit
        data of (``eu``, ``el``) (:func:`.engine.unit_data`), where the caller has them."""
        sigma_f = max(strain_sigma, DEFAULT_STRAIN_SIGMA)
        layout = self._layout
        chi, dof, fu, fl = misfit_and_strains(self._candidate(general[0]), layout, eu, el, sigma_f)
        du, dl = eu, el
        kept = (du, dl)  # the input of the answer kept
        sign = twist_sign
        if sign is None and general[1] != 0.0:
            sign = math.copysign(1.0, general[1])
        first_twist, first_open = general[1], float(general[3].get("open_twist", 0.0))
        steps = 0
        smoothed = 0  # passes taken on the averaged residual (DEFECT_SMOOTH_UNITS)
        unsmoothed_chi2 = 0.0  # the χ² per gauge the raw pass left beside the first averaged one taken

        def corrected(cu: np.ndarray, cl: np.ndarray) -> tuple:
            # the model run on the corrected input (cu, cl), and its reading of the gauges
            # (np.maximum keeps a missing gauge's NaN)
            turning, stretch, _ = unit_data(np.maximum(cu, -0.99), np.maximum(cl, -0.99), self.h_upper, self.h_lower,
                                            self.gauge_length)
            trial = self._general(turning, stretch, valid, n_valid, strain_sigma, previous, sign, (eu, el), twist_mean,
                                  units)
            return (trial, *misfit_and_strains(self._candidate(trial[0]), layout, eu, el, sigma_f))

        # where the noise alone leaves the model above one χ² per gauge (large sheets) the raw
        # residual feeds the noise back in a second time: there its average over
        # DEFECT_SMOOTH_UNITS units is tried too, and preferred, where the data carry noise (their
        # own turning noise at least QUIET_SHARE of the stated), else only where the raw pass fails
        averaging = (self.defect_steps > 0 and chi > dof and n_valid > 0
                     and self._noise_response(strain_sigma)[1] > 1.0)
        noisy = False
        if averaging:
            sigma_t = self._turning_sd(strain_sigma)
            # the measured data's own turning noise, as the passes' field fit of them keeps it
            # (_measured: the passes read the same data again)
            shown = self._measured(*(units or unit_data(eu, el, self.h_upper, self.h_lower, self.gauge_length)))[1]
            noisy = sigma_t > 0.0 and _noise_present(shown, sigma_t) >= QUIET_SHARE * sigma_t
        for _ in range(self.defect_steps):
            if chi <= dof:
                break
            raw_u, raw_l = du + (eu - fu), dl + (el - fl)
            raw = corrected(raw_u, raw_l)
            raw_gains = bool(raw[1] < DEFECT_GAIN * chi and np.isfinite(raw[0][0]).all())
            on_average, left = False, chi
            if averaging and (noisy or not raw_gains):
                # the smooth part of the residual alone, taken only where it keeps the answer's
                # constant twist (it corrects the model's defect, it reads no twist: the gauges
                # cannot tell a twist from shear, and such passes took one onto a flat 32×32
                # sheet, 0.95 mm off, and lost a 5 % pre-stretched cylinder's, 12.5 mm off)
                avg_u = du + unit_box_mean(eu - fu, DEFECT_SMOOTH_UNITS)
                avg_l = dl + unit_box_mean(el - fl, DEFECT_SMOOTH_UNITS)
                averaged = corrected(avg_u, avg_l)
                keeps_twist = math.isclose(float(averaged[0][1]), float(general[1]), rel_tol=1e-3, abs_tol=1e-12)
                if averaged[1] < DEFECT_GAIN * chi and np.isfinite(averaged[0][0]).all() and keeps_twist:
                    on_average, left = True, (raw[1] if raw_gains else chi)
                elif not raw_gains:
                    break
            if on_average:
                du, dl = avg_u, avg_l
                trial, chi_t, _, fu_t, fl_t = averaged
            else:
                du, dl = raw_u, raw_l
                trial, chi_t, _, fu_t, fl_t = raw
            # a pass must gain clearly (1 %): a decision at the rounding level would make the
            # answer depend on how the arithmetic was ordered (replay needs the same bytes)
            # (a pass that overshoots is not taken again at half the correction: on an unseen
            # 16×16 kinematic saddle that read the gauges within the noise, 1.9 → 0.60 a gauge,
            # but an unseen elastic 16×16 saddle's least-shear answer, 1.25 → 0.71, then had the
            # gauges veto the stretch pattern's twist, and was 2.5 mm off for 0.08)
            if not (chi_t < DEFECT_GAIN * chi) or not np.isfinite(trial[0]).all():
                break
            # the fields' misfit stays that of the measured data (the consistency check's input)
            # (the stretch pattern is read with the measured data's fields: the corrected ones
            # carry the answer's own twist back into them)
            measured = general[3].get("measured_fields", general[3].get("product_fields"))
            info = {**trial[3], "defect_steps": steps + 1, "measured_fields": measured}
            if on_average and not smoothed:
                unsmoothed_chi2 = round(left / max(dof, 1), 3)  # what the raw pass leaves
            smoothed += on_average
            if smoothed:
                info.update(defect_smoothed=smoothed, defect_unsmoothed_chi2=unsmoothed_chi2)
            general = (trial[0], trial[1], general[2], info, trial[4], trial[5])
            chi, fu, fl = chi_t, fu_t, fl_t
            steps += 1
            kept = (du, dl)
        read = max(abs(first_twist), first_open)
        if steps and abs(general[1]) < LOST_TWIST_SHARE * read:
            # The gauges prefer the corrected answer, but they cannot tell a twist from shear (the
            # kinematic forward model): where the passes lost most of the twist the uncorrected
            # model read, or left open, it stays open (a 16×16 cylinder of R 300 mm 70° off the
            # rows, its product 10.8 s.d. beyond its noise, read its twist, and two passes took
            # it to none on one noisy frame of 150: 2.5 mm off with σ 0.070, 21.6 times the bound)
            general[3]["open_twist"] = max(float(general[3].get("open_twist", 0.0)), read)
        # the answer's χ² at the posterior check's noise level, read once
        general[3]["forward_chi2"] = (general[0], chi, dof)
        general[3]["defect"] = (np.stack([kept[0] - eu, kept[1] - el]), chi)
        return general

    def _warm_general(self, previous: Surface | None, eu, el, measured_fields: Callable[[], tuple], units: tuple,
                      n_valid: int, strain_sigma: float, twist_sign, twist_mean: float | None):
        """The general model through its defect correction from the previous frame's correction
        (``FrameState.defect``) instead of from none: a sheet that holds still needs nearly the
        same, and its first pass then lands where two passes from none would (a held 5×5 film:
        one pass of the model instead of two or three).  None where the previous frame left
        none, where the strains changed by more than the noise (:data:`HELD_SIGMAS`), where the
        previous answer misfit the gauges beyond the noise, or where this answer does (χ² above
        one per gauge: it would need passes): then the frame starts from none, as a cold one.
        ``units``: the unit data (turning, stretch, valid) of the measured (``eu``, ``el``)."""
        valid = units[2]
        state = previous.state if previous is not None else None
        if (self.n * self.m > WARM_DEFECT_MAX_CELLS or state is None or state.defect is None or state.strains is None
                or state.defect.shape != (2,) + eu.shape or state.strains.shape != (2,) + eu.shape):
            return None
        # Only a sheet that held still: a feature that moves carries its correction away with
        # it, and the previous one then adds misfit where the feature was (a bump circling on
        # 16×16 took two passes from it where it took none from none).  Held still: the strains
        # changed by no more than twice what two noise draws differ by (rms over the gauges).
        change = np.stack([eu, el]) - state.strains
        both = np.isfinite(change)
        sigma_f = max(strain_sigma, DEFAULT_STRAIN_SIGMA)
        if not both.any() or math.sqrt(float(np.mean(change[both] ** 2))) > HELD_SIGMAS * math.sqrt(2.0) * sigma_f:
            return None
        # ... and whose answer fitted the gauges within the noise (χ² at most one per gauge, where
        # the correction stops): a correction that left more misfit is no better a start than
        # none (32×32, whose general model leaves 2.6 a gauge under noise alone)
        if not state.defect_chi2 <= np.count_nonzero(np.isfinite(eu)) + np.count_nonzero(np.isfinite(el)):
            return None
        applied = np.nan_to_num(state.defect, nan=0.0)  # (a unit missing then has none)
        du, dl = eu + applied[0], el + applied[1]
        corrected_t, corrected_s, _ = unit_data(np.maximum(du, -0.99), np.maximum(dl, -0.99), self.h_upper,
                                                self.h_lower, self.gauge_length)
        trial = self._general(corrected_t, corrected_s, valid, n_valid, strain_sigma, previous, twist_sign, (eu, el),
                              twist_mean, units)
        if not np.isfinite(trial[0]).all():
            return None
        # the fields of the measured data, which the stretch pattern is read with (as the cold
        # passes keep them)
        trial[3]["measured_fields"] = measured_fields()
        # kept only where it needs no pass: its χ² at most one per gauge (where a pass from none
        # stops), or within the noise's own spread (3 s.d. of χ²) of the previous answer's, which
        # this frame's sheet held still from; else the frame starts from none, one pass spent
        chi, dof = misfit(self._candidate(trial[0]), self._layout, eu, el, sigma_f)[:2]
        if chi > max(dof, state.defect_chi2 + 3.0 * math.sqrt(2.0 * dof)):
            return None
        # (as _defect_correction leaves its answer: its χ², read once, and the correction it had)
        trial[3].update(forward_chi2=(trial[0], chi, dof), defect=(applied, chi), defect_warm=True)
        return trial

    def _elastic_prior(self, surf: Surface, turning, stretch, valid, strain_sigma: float,
                       previous: Surface | None, strains, twist_sign) -> Surface:
        """The full-position fit with the membrane-equilibrium prior (:mod:`.positionfit`), from the
        previous frame's answer, else from this frame's answer and its mirror image (or, when
        neither bends as the stretch pattern says, from the twist that does: :mod:`.airy`).  Its
        answer replaces ``surf`` when the prior holds (cost and χ² within their limits, mean
        Gaussian curvature within 3 s.d. of the pattern's), unless ``surf`` agrees with the
        pattern too and the two part by more than the fit's own σ: then ``surf`` stays with σ
        covering both.  Otherwise ``surf`` stays, saying why (docs/reconstruction.md)."""
        elastic = self._position
        assert elastic is not None and self.elastic_prior is not None
        pf = elastic.fine
        settings = self.elastic_prior
        fit_sigma = max(strain_sigma, DEFAULT_STRAIN_SIGMA)
        sig_t = self._turning_sd(fit_sigma)
        sig_s = self._stretch_sd(fit_sigma)
        data = (turning, stretch, valid, sig_t, sig_s)
        # the mean Gaussian curvature the stretch pattern implies (Airy): the check of every answer
        try:
            k_airy: float | None
            k_airy, k_sd = airy_gaussian_curvature(stretch, valid, self.pitch, settings.poisson, settings.poisson_sd)
        except ValueError:  # too few units measured
            k_airy, k_sd = None, 0.0

        def agrees(coeffs: np.ndarray, sds: float) -> bool:
            return k_airy is None or abs(pf.mean_gaussian_curvature(coeffs) - k_airy) <= sds * k_sd

        # the default model's answer bends as the stretch pattern says: it stays a rival reading
        images = {id(s): start_from_surface(pf, s) for s in (surf, surf.mirror) if s is not None}
        default_agrees = k_airy is not None and agrees(images[id(surf)], 3.0)
        warm = previous.state.position if previous is not None else None
        if warm is not None and warm.shape == (3, pf.nb):
            results = [elastic.warm(warm, *data)]
        else:
            starts = [s for s in (surf, surf.mirror) if s is not None]
            if k_airy is not None and not any(agrees(images[id(s)], 3.0) for s in starts):
                # neither image bends as the stretch pattern says: start where the twist makes it
                starts = self._airy_starts(turning, stretch, valid, strain_sigma, strains, twist_sign, k_airy) or starts
            results = [elastic.cold(s, *data) for s in starts]
        # the mirror image's fit replaces the answer only when the prior prefers it clearly
        if len(results) > 1 and results[0].cost > settings.mirror_cost_ratio * results[1].cost + 1e-9:
            results.reverse()
        best = results[0]
        diag = surf.diagnostics
        diag.extra.update(elastic_prior_cost=round(best.prior_cost, 4), elastic_chi2=round(best.chi2, 4),
                          elastic_steps=best.steps, elastic_status=best.status)
        if best.prior_cost > settings.max_prior_cost or best.chi2 > settings.max_chi2:
            diag.extra["elastic_prior"] = (f"not used: prior cost {best.prior_cost:.3g} (limit {settings.max_prior_cost:g}), "
                                           f"chi2 {best.chi2:.3g} (limit {settings.max_chi2:g}): the film is not "
                                           "loaded along its normal alone (friction, a sharp mold) or ν is off")
            return surf
        if not agrees(best.coeffs, 3.0):
            assert k_airy is not None
            diag.extra["elastic_prior"] = (f"not used: its mean Gaussian curvature {pf.mean_gaussian_curvature(best.coeffs):.3g}/mm² "
                                           f"disagrees with the stretch pattern's {k_airy:.3g} ± {k_sd:.2g} (Airy): "
                                           "the fit found another valley (noise) or the film is not loaded along its normal")
            return surf
        if k_airy is not None:
            diag.extra["airy_gaussian_curvature"] = (round(pf.mean_gaussian_curvature(best.coeffs), 9), round(k_airy, 9),
                                                     round(k_sd, 9))
        grid = self.grid
        if self._position_on_grid is None:
            vv, uu = np.meshgrid(grid.v, grid.u, indexing="ij")
            self._position_on_grid = pf.evaluator(uu.ravel(), vv.ravel())
        on_grid = self._position_on_grid

        def fine_positions(coeffs: np.ndarray) -> np.ndarray:
            return to_sensor_frame(grid, on_grid(coeffs)[0].reshape(grid.nf, grid.mf, 3))

        pos = fine_positions(best.coeffs)
        # Poisson's ratio is known to ±poisson_sd: the answer's first-order response to it
        spread = np.zeros((grid.nf, grid.mf))
        if settings.poisson_sd > 0:
            moved = best.coeffs + settings.poisson_sd * pf.poisson_response(best, *data)
            spread = np.linalg.norm(fine_positions(moved) - pos, axis=-1)
        base_sigma = surf._fine_sigma_fn
        misfit = math.sqrt(max(best.chi2, 1.0))
        if default_agrees:
            # Two models, each consistent with the gauges and with the stretch pattern's curvature:
            # where they part by more than the elastic answer's own uncertainty the data have not
            # decided (friction on a mold; a twist too small to change K), so the default answer
            # stays, its σ covering both readings.
            rival = np.linalg.norm(pos - surf._coeffs[..., 0, :], axis=-1)
            own = np.sqrt((misfit * base_sigma()) ** 2 + spread ** 2)
            parted = float(rival[grid.inner].mean())
            diag.extra["elastic_rival_mm"] = round(parted, 4)
            if parted > 3.0 * float(own[grid.inner].mean()):
                diag.extra["elastic_prior"] = (f"not decided: its answer and the default model's part by {parted:.3f} mm, "
                                               "both consistent with the gauges and the stretch pattern; the default "
                                               "is kept with σ covering both")
                default_sigma = surf._fine_sigma_fn
                undecided = self._surface(surf._coeffs[..., 0, :], lambda: np.maximum(default_sigma(), rival), diag)
                undecided.state, undecided.mirror = surf.state, surf.mirror
                undecided._scatter_sigma_fn = lambda: surf.scatter_sigma
                return undecided
            spread = np.maximum(spread, rival)

        def sigma() -> np.ndarray:
            return np.sqrt((misfit * base_sigma()) ** 2 + spread ** 2)

        def scatter() -> np.ndarray:
            # (ν's response is no scatter: the same every frame)
            return misfit * surf.scatter_sigma

        diag.extra["model"] = "position (equilibrium prior)"
        diag.extra["elastic_prior"] = "used"
        answer = self._surface(pos, sigma, diag)
        answer._scatter_sigma_fn = scatter
        answer.state = dataclasses.replace(surf.state, position=best.coeffs)
        if surf.mirror is not None and len(results) > 1:
            # the mirror stays when the prior cannot tell the two either (an isometric cylinder)
            other = results[1]
            diag.extra["elastic_mirror_cost"] = round(other.cost, 4)
            diag.extra["elastic_cost"] = round(best.cost, 4)
            if other.cost <= settings.mirror_cost_ratio * best.cost + 1e-9:
                answer.mirror = self._surface(fine_positions(other.coeffs), sigma, diag)
                answer.mirror._scatter_sigma_fn = scatter
            else:
                diag.extra["ambiguous"] = False
                diag.extra["mirror_resolved_by"] = (f"equilibrium prior: cost {best.cost:.3g} against the mirror "
                                                    f"image's {other.cost:.3g}")
        elif surf.mirror is not None:
            answer.mirror = surf.mirror
        return answer

    def _airy_starts(self, turning, stretch, valid, strain_sigma: float, strains, twist_sign,
                     k_airy: float) -> list[Surface]:
        """The general model's sheet with its constant twist set so that its mean Gaussian
        curvature is the stretch pattern's: both signs (mirror images) unless the sign is known;
        [] when no twist gets there (the curvature product alone is below it)."""
        n_valid = int(valid.sum())
        _, twist_c, _, info, _, positions_at = self._general(turning, stretch, valid, n_valid, strain_sigma, None,
                                                             twist_sign, strains)
        tm, base = _mean_twist_terms(info["product_fields"], self.grid.inner)
        disc = base - k_airy
        if disc < 0.0:
            return []
        signs = (1.0, -1.0) if twist_sign is None else (float(twist_sign),)
        return [self._surface(positions_at(-tm + sg * math.sqrt(disc) - twist_c), None, None) for sg in signs]

    def _graph_surface(self, coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A graph's fine positions in the sensor frame and its own derivatives there (∂u, ∂v,
        ∂u∂v: (3, nf, mf, 3)), for the surface's patches."""
        fit = self._graph_fit()
        base = fit.fine_positions(coeffs)
        rot, shift = sensor_frame(self.grid, base)
        return base @ rot.T - shift, fit.fine_derivatives(coeffs) @ rot.T

    def _surface(self, pos: np.ndarray, sigma, diag: Diagnostics | None,
                 derivatives: np.ndarray | None = None) -> Surface:
        # (diag None: a candidate weighed only against the gauges, never returned)
        grid = self.grid
        return Surface(pitch=self.pitch, fine_u=grid.u, fine_v=grid.v, fine_positions=pos,
                       node_index=(grid.node_rows, grid.node_cols), fine_sigma=sigma, diagnostics=cast(Diagnostics, diag),
                       compiled=self._compiled, fine_derivatives=derivatives)

    def _candidate(self, pos: np.ndarray) -> Surface | Patches:
        """Fine positions as the forward model reads them, for a candidate that is only weighed
        against the gauges: its patch data alone with the compiled kernels (a tenth of a
        :class:`Surface`'s cost, the same numbers), else a Surface."""
        if self._compiled is not None:
            return Patches(pos, self.grid.u, self.grid.v, self._compiled)
        return self._surface(pos, None, None)

    def _posterior(self, surf: Surface, eu, el, strain_sigma: float, positions_at, twist_sign, graph_mirror, turning,
                   valid, product_fields=None, known_chi2: tuple[float, int] | None = None,
                   stretch: np.ndarray | None = None, twist_mean: float | None = None,
                   measured_fields=None, reading: TwistReading | None = None,
                   resolution_term: Callable[[], np.ndarray] | None = None, carried: bool = False) -> Surface:
        """The posterior check (docs/reconstruction.md): the answer's own gauge readings
        against the measured ones (:mod:`.forward`), which

        - widens the uncertainty by the misfit (χ² per gauge above 1 is misfit the noise
          cannot explain: Birge's ratio);
        - carries the noise through the constant twist, which the model estimates from products
          of curvatures (Gauss's equation, the least-shear prior): its s.d. times the sheet's
          response to it is added to ``node_sigma`` (the linear map about the flat sheet
          cannot see it, and on an oblique cylinder it is most of the scatter);
        - tries the mirror image (the opposite constant twist): when it explains the data as
          well, the answer is ambiguous and :attr:`Surface.mirror` holds the other one; when it
          explains them clearly better, it becomes the answer;
        - with ``stretch`` (the general model answered, not as a graph pushed out of plane),
          holds the twist to the stretch pattern's Gaussian curvature (:meth:`_stretch_twist`);
        - adds ``resolution_term`` (a share of the model's resolution,
          :func:`.uncertainty.resolution_sigma`) in quadrature, not widened by the misfit (it is
          no noise).
        """
        diag = surf.diagnostics
        sigma_f = max(strain_sigma, DEFAULT_STRAIN_SIGMA)  # misfits below the sensor's noise mean nothing
        layout = self._layout
        product_fields_general = product_fields is not None
        if product_fields is None:  # a graph answered: the fields of the measured data
            product_fields = self.grid.field_maps(valid)(turning, np.ones(turning.shape))[:3]

        def product_sd(sigma_strain: float) -> float:
            return self._product_sd(product_fields, sigma_strain)

        chi0, dof = known_chi2 if known_chi2 is not None else misfit(surf, layout, eu, el, sigma_f)[:2]
        # Birge's ratio counts only misfit beyond what the noise alone leaves in the model that
        # answered (the general model's, measured; a graph's is one per gauge)
        chi2_noise = self._noise_response(strain_sigma)[1] if product_fields_general else 1.0
        birge = max(1.0, chi0 / max(dof, 1) / chi2_noise)
        # χ² differences of this size are what the data can still tell apart (2 s.d., scaled by
        # the misfit the model leaves)
        # nor can a difference below a share of the misfit the model leaves anyway: that misfit
        # is systematic, and two mirror images carry nearly the same
        tell = max(MIRROR_CHI2 * birge, MIRROR_SHARE * chi0)
        flag_tell = max(MIRROR_FLAG_CHI2 * birge, MIRROR_SHARE * chi0)
        c0 = diag.twist_constant
        base_shift = 0.0  # where the answer sits on positions_at's family
        info = {"chi2_per_gauge": round(chi0 / max(dof, 1), 3)}
        # the mirror image beside the answer, decided when first asked (:meth:`_stretch_twist`
        # mostly puts its own in its place: the two-answer test of this one is then not paid for)
        mirror_of: Callable[[], Surface | None] = _given(None)
        noise_sigma = sigma_field(surf._fine_sigma_fn)
        surf._fine_sigma_fn = noise_sigma
        # the part of it that repeated frames scatter by (a deferred frame's σ holds the
        # resolution term already)
        scatter_base = noise_sigma if surf._scatter_sigma_fn is None else sigma_field(surf._scatter_sigma_fn)
        # a twist c bends the far corners out of the untwisted shape by about c·ρ²/2 (ρ the
        # half-diagonal): below the mirror floor the two images are one answer; and a twist
        # within what the turning noise makes of the curvature product is no twist to mirror
        # (nor, alone, where the less-sheared twist was taken because it agreed with the
        # product's shrunk reading: its magnitude is read twice, its sign by nothing)
        agreed = bool(diag.extra.get("least_shear_contested")) and "least_shear_shift" in diag.extra
        if (abs(c0) * self._half_diagonal2 / 2.0 > MIRROR_FLOOR_MM and twist_sign is None
                and (abs(c0) > MIRROR_SIGMAS * math.sqrt(product_sd(sigma_f)) or agreed)):
            mirror_comparable = True  # the mirror is the same model's: its χ² may swap them
            derivatives_m = None
            if positions_at is not None:
                pos_m = positions_at(-2.0 * c0)
            else:  # a graph answered: its mirror is the graph refitted with the opposite sign
                # (where no graph of that sign fits, the general model's answer with it stands in:
                # its misfit is another model's, no evidence against the graph; an oblique trough
                # on 8×8 read 0.04 per gauge so against the graph's 0.11 and was taken, 1.0 mm
                # off with σ 0.016, where the graph of the other sign had 12 times its objective)
                pos_m, mirror_comparable, derivatives_m = graph_mirror(-math.copysign(1.0, c0))
            diag_m = _with_twist(diag, -c0)
            # (weighed against the gauges by its patch data alone, a graph's by its own
            # derivatives: it becomes a Surface only where it is kept, as the answer or the mirror)
            cand = _memo(partial(self._surface, pos_m, surf._fine_sigma_fn, diag_m, derivatives_m))
            chi_m, _, _ = misfit(cand() if derivatives_m is not None else self._candidate(pos_m), layout, eu, el,
                                 sigma_f)
            fresh_m = None
            if positions_at is not None and product_fields_general and chi_m - chi0 >= tell:
                # The family's reflection keeps the fields fitted to this twist's sign; on a large
                # sheet it misreads the gauges where the opposite sign modelled afresh reads them
                # exactly as well (a saddle at 45° on 12×12: 35 per gauge against 0.17 for both
                # signs; the default sign stood, 11 mm off, unflagged).  Before the mirror is
                # rejected it is modelled afresh.
                tm = twist_mean if twist_mean is not None else (
                    float(np.asarray(product_fields[2])[self.grid.inner].mean()) + c0)
                # (its defect correction matters: without it the mirror misread the gauges by 3-13
                # per gauge)
                s_m = stretch if stretch is not None else unit_data(eu, el, self.h_upper, self.h_lower,
                                                                    self.gauge_length)[1]
                fresh_m = self._fresh(turning, s_m, valid, sigma_f, -math.copysign(1.0, c0), (eu, el), -tm)
                cand_f = self._surface(fresh_m[0], surf._fine_sigma_fn, _with_twist(diag, fresh_m[1]))
                chi_f, _, _ = misfit(cand_f, layout, eu, el, sigma_f)
                info["mirror_afresh_chi2_per_gauge"] = round(chi_f / max(dof, 1), 3)
                if chi_f < chi_m:
                    cand, chi_m = _given(cand_f), chi_f
                else:
                    fresh_m = None
            info["mirror_chi2_per_gauge"] = round(chi_m / max(dof, 1), 3)
            # The general model's own misfit is systematic and as large as the noise's: where both
            # images read the gauges as well as the noise alone would (χ² within two s.d. of its
            # expectation), how their small misfits compare proves nothing (a saddle of R 284 mm
            # at 169° on 12×12: its mirror read 0.38 per gauge against the true sign's 0.92, and
            # was taken, 3.4 mm off).  A graph's misfit is the noise's alone: its χ² difference
            # is evidence however small both are.
            within_noise = product_fields_general and _within_noise(chi0, chi_m, dof, chi2_noise)
            # (a mirror modelled afresh is flagged, never taken: on large sheets the general
            # model's sign evidence is its own systematic misfit, and on one noise draw in 20 a
            # saddle at 49° on 16×16 read 2.2 per gauge with the right sign against 0.74 with
            # the wrong one, which was taken, 16.8 mm off, unflagged)
            # (nor is the family's mirror taken where the noise alone leaves the general model a
            # χ² above one per gauge (32×32: 2.6): there a noisy answer of the right sign that
            # its defect correction did not improve read 7.7 per gauge, its mirror 1.9, and the
            # mirror was taken, 17 mm off, unflagged; it is flagged instead)
            # (and where the general model's own answer reads the gauges beyond what the noise
            # leaves, its fit, not its sign, may be what the mirror beats: a noisy 16×16 saddle
            # of R 342 mm at 72° whose defect pass was not kept read 1.9 per gauge, its
            # reflection 0.87, while the wrong sign's best reads 0.67 and the right one's 0.71 on
            # the next draw; the reflection was taken, 8.0 mm off with σ 0.12, unflagged.  The
            # mirror is still taken, the answer kept beside it)
            fit_in_doubt = product_fields_general and not _within_noise(chi0, chi0, dof, chi2_noise)
            swapped = False
            if (chi_m < chi0 - tell and not within_noise and fresh_m is None and chi2_noise <= 1.0
                    and mirror_comparable):
                # the data prefer the mirror: it is the answer
                surf, cand, chi0, chi_m = cand(), _given(surf), chi_m, chi0
                diag = surf.diagnostics
                base_shift = -2.0 * c0
                info["mirror_swapped"] = True
                swapped = True
            if chi_m - chi0 < flag_tell or within_noise or (swapped and fit_in_doubt):
                mirror_of = _memo(partial(_mirror_if_distinct, surf, cand))
        pattern = None
        if stretch is not None and positions_at is not None and product_fields_general and self.poisson_range is not None:
            pattern = self._stretch_twist(surf, mirror_of, turning, stretch, valid, product_fields, positions_at,
                                          base_shift, twist_sign, eu, el, sigma_f, chi0, tell, info, twist_mean,
                                          measured_fields, reading, chi2_noise, carried)
        if pattern is not None:
            surf, mirror, base_shift, chi0, positions_at = (pattern.answer, pattern.mirror, pattern.shift, pattern.chi2,
                                                            pattern.family)
            diag = surf.diagnostics
        else:
            mirror = mirror_of()
        diag.extra.update(info)
        diag.extra["ambiguous"] = mirror is not None
        surf.mirror = mirror
        scale = math.sqrt(birge)
        unsmoothed = diag.extra.get("defect_unsmoothed_chi2")
        if unsmoothed is not None:
            # the averaged passes (DEFECT_SMOOTH_UNITS) fit the residual's smooth part, down to
            # below the noise's own χ²: the misfit the raw passes left stays the evidence σ is
            # widened by (without it a 32×32 twisted quadric's σ fell by half for the same error)
            scale = math.sqrt(max(birge, unsmoothed / chi2_noise))

        # no position is less certain than "somewhere on the sheet's own extent"
        ceiling = math.sqrt(self._half_diagonal2)

        # a twist whose sign the noise leaves open, not tried as a mirror above (within the
        # noise's own product) and not told: the answer's mirror image is as likely
        # (where the graph sheet read the twist and its sign from the stretch pattern, that
        # reading's own noise, not the product's: a noisy 16×16 saddle 1° off the rows, twist
        # 1.2·10⁻⁴ /mm, was 0.04-0.07 mm off with σ 0.8, its sign left open by the product.  Not
        # where the noise alone leaves the model above one per gauge (24×24 and larger): its
        # answers there are not the linear noise's, and a 32×32 twisted quadric's frames stood
        # beyond 3σ + 0.05 mm in the sensor frame on 2 of 4 noisy draws, σ 2.05 → 0.16 mm)
        graph_sd = (diag.extra.get("graph_twist_sd") if pattern is None and not info.get("mirror_swapped")
                    and chi2_noise <= 1.0 else None)
        sign_open = (twist_sign is None and mirror is None and graph_sd is None
                     and abs(c0) * self._half_diagonal2 / 2.0 > MIRROR_FLOOR_MM
                     and abs(c0) <= MIRROR_SIGMAS * math.sqrt(product_sd(sigma_f)))
        # The twist is the least-shear prior's of a turned saddle, and the stretch pattern
        # confirms nothing (neither reading explains it): a film on a mold shears otherwise, and
        # the prior's twist was 12-20 % off (a saddle of R 286 mm at 49° on 12×12 with friction
        # on its mold: 0.73 mm off with σ 0.048), or none for 1.3·10⁻³ /mm (R 284 mm at 169°:
        # 1.7 mm off with σ 0.05); the twists whose squares lie within SHEAR_PRIOR_SHARE of the
        # answer's mean Gaussian curvature join the spread.  (A reading that only bounds the
        # twist, the trace's interval from none upwards, confirms nothing either: a 5×5 saddle of
        # R 93 mm at 13.7° with friction read [0, 0.0082] /mm, took the prior's none for 0.0049
        # and was 1.0 mm off with σ 0.03)
        prior_only = "shear_prior_twist" in diag.extra and pattern is None
        prior_span = SHEAR_PRIOR_SHARE * abs(float(diag.extra.get("shear_prior_curvature", 0.0))) if prior_only else 0.0
        # (the constant's square moves with the product times the significance ramp's slope
        # where the ramp shrank it: a 5×5 cylinder 5.6° off the columns took its twist 0.74-0.9
        # of the way up the ramp on some noisy frames, where its slope is 2.5-2.8)
        ramp = float(diag.extra.get("product_ramp", 1.0))

        def square_sd(sigma_strain: float) -> float:
            return ramp * product_sd(sigma_strain)

        # where the cells' gauge pairs read the product (_pair_reading: large sheets), the twist
        # taken scatters by their s.d., not the fields' (a 32×32 cylinder at 68°: the fields'
        # 4.5·10⁻⁸ /mm², the pairs' 1.5·10⁻⁸; its twist scattered by 5-8·10⁻⁶ /mm over noisy
        # frames, where the fields' s.d. said 2.5-3.3·10⁻⁵ and the pairs' 1.0·10⁻⁵); node_sigma,
        # and what the data leave open about the twist, keep the fields' (a sharper reading
        # rules out none of it)
        pair = diag.extra.get("pair_product")
        pair_share = pair[2] / pair[3] if pair is not None and pair[3] > 0.0 else 1.0

        def scatter_square_sd(sigma_strain: float) -> float:
            return square_sd(sigma_strain) * pair_share

        twist = self._twist_noise(positions_at, base_shift, c0, square_sd, strain_sigma, TwistLeftOpen(
            undecided=diag.extra.get("undecided_twist", 0.0),
            undecided_read="least_shear_shift" not in diag.extra,
            sign_open=sign_open,
            open_twist=max(diag.extra.get("open_twist", 0.0), diag.extra.get("trace_open_twist", 0.0))
            if mirror is None else 0.0,
            twist_sign=None if twist_sign is None else float(twist_sign),
            prior_span=prior_span,
            prior_sign_told=mirror is not None), graph_sd)
        # the twist's own scatter: the noise through the curvature product, on the answer's own
        # family (the intervals and reaches above are the same every frame: no scatter, except
        # the way between the ramp's shrunk product twist and the least-shear one weighed
        # against it: the noise takes one on some frames, the other on others)
        # (and the stretch reading's own noise where it holds the twist)
        twist_scatter = self._twist_noise(positions_at, base_shift, diag.twist_constant, scatter_square_sd, strain_sigma,
                                          TwistLeftOpen(undecided=diag.extra.get("undecided_twist", 0.0)
                                                        if diag.extra.get("least_shear_contested")
                                                        or diag.extra.get("least_shear_marginal") else 0.0), graph_sd)
        if pattern is not None:
            if pattern.contested:
                # (where the noise flips the pattern's decision, frames land on either answer: a
                # 12×12 saddle of R 286 mm 6.7° off the columns moved to its twist on 11 noisy
                # frames of 20 and kept none on 9, 1.0 mm apart; its scatter was 4.7 times the
                # part of σ said to scatter)
                # (and node_sigma reaches the other answer too: never below the scatter's part)
                twist_scatter = _widened(positions_at, base_shift, list(pattern.contested), twist_scatter)
                twist = _widened(positions_at, base_shift, list(pattern.contested), pattern.spread)
            elif pattern.keeps_rest:
                twist = _larger(pattern.spread, twist)
            else:
                twist = pattern.spread
            twist_scatter = _memo(partial(_with_reading_noise, twist_scatter, positions_at, base_shift, pattern.noise_sd))

        if self._unread_twist_limit > 0.0:
            # a sheet two cells across: no datum reads its twist (UNREAD_TWIST_TURN)
            twist = _larger(_memo(partial(self._unread_twist_spread, diag.twist_constant, twist_sign)), twist)
            diag.extra["twist_unread_limit"] = round(self._unread_twist_limit, 6)

        resolution_known: list[np.ndarray | None] = []

        def resolution() -> np.ndarray | None:
            # the resolution term, once (None where it is zero)
            if not resolution_known:
                field = resolution_term() if resolution_term is not None else None
                resolution_known.append(field if field is not None and field.any() else None)
            return resolution_known[0]

        node_flat = (self.grid.node_rows[:, None] * self.grid.mf + self.grid.node_cols[None, :]).ravel()

        def combined(base_field: SigmaField, twist: Callable[[], np.ndarray | None], scale: float,
                     resolved: bool) -> SigmaField:
            # base_field scaled by ``scale`` (the misfit) and (unless ``resolved``) the resolution
            # term, in quadrature; unless ``resolved``, no less anywhere than their mean over the
            # nodes (ALIGNMENT_FLOOR); then the twist's spread in quadrature
            floor_known: list[float] = []

            def local_at(flat: np.ndarray) -> np.ndarray:
                out = base_field.at(flat) * scale
                unresolved = None if resolved else resolution()
                if unresolved is not None:
                    out = np.sqrt(out * out + unresolved.reshape(-1)[flat] ** 2)
                return out

            def floor() -> float:
                if not floor_known:
                    floor_known.append(0.0 if resolved else alignment_floor(local_at(node_flat)))
                return floor_known[0]

            def whole() -> np.ndarray:
                base = base_field()
                spread = twist()
                unresolved = None if resolved else resolution()
                if spread is None and unresolved is None and scale == 1.0 and float(base.max()) <= ceiling:
                    # the shared, read-only noise map (computed once per mask and noise), floored once
                    return base if resolved else self._floored(base, floor())
                out = base * scale
                if unresolved is not None:
                    out = np.sqrt(out * out + unresolved * unresolved)
                out = np.maximum(out, floor())
                if spread is not None:
                    out = np.sqrt(out * out + spread * spread)
                out = np.minimum(out, ceiling)
                out.flags.writeable = False
                return out

            def at(flat: np.ndarray) -> np.ndarray:
                # the same, node by node (the twist's spread and the resolution term are whole fields)
                out = np.maximum(local_at(flat), floor())
                spread = twist()
                if spread is not None:
                    out = np.sqrt(out * out + spread.reshape(-1)[flat] ** 2)
                return np.minimum(out, ceiling)

            return SigmaField(whole, at)

        surf._fine_sigma_fn = combined(noise_sigma, twist, scale, False)
        surf._scatter_sigma_fn = combined(scatter_base, twist_scatter, 1.0, True)
        if mirror is not None:
            mirror._fine_sigma_fn = surf._fine_sigma_fn
            mirror._scatter_sigma_fn = surf._scatter_sigma_fn
            mirror.diagnostics.extra.update(diag.extra)
            mirror.mirror = None
        return surf

    def _unread_twist_spread(self, c0: float, twist_sign: float | None) -> np.ndarray:
        """The fine-grid spread (mm) of the twists a sheet two cells across cannot read, from
        the answer's ``c0``: half the farthest reach to a twist within ±the limit
        (UNREAD_TWIST_TURN; of the sign told, from none), the sheet's response to a twist shift
        d being d·u·v in the sensor frame (zero mean and no slope over the cells: the frame's
        plane does not move)."""
        limit = self._unread_twist_limit
        ends = (0.0, float(twist_sign) * limit) if twist_sign is not None else (-limit, limit)
        reach = max(abs(e - c0) for e in ends)
        assert self._twist_response is not None
        out = 0.5 * reach * self._twist_response
        out.flags.writeable = False
        return out

    def _stretch_sd(self, sigma_f: float) -> float:
        """The noise s.d. of one unit's stretch reading for strain noise ``sigma_f`` on each layer."""
        return stretch_noise_sd(sigma_f, self.h_upper, self.h_lower)

    def _turning_sd(self, sigma_f: float) -> float:
        """The noise s.d. of one unit's turning per length (1/mm) for strain noise ``sigma_f`` on
        each layer: (ε_u − ε_l)/(h_u + h_l)."""
        return math.sqrt(2.0) * sigma_f / (self.h_upper + self.h_lower)

    def _pair_reading(self, k_u, k_v, tau0, turning, valid, measured, turning_sigma: float, present: float,
                      product_noise: tuple[float, float], info: dict) -> tuple[float, float]:
        """The (bias, s.d.) that :func:`.engine.solve_twist` reads the mean curvature product
        with: the fields' own (``product_noise``, its bias at the noise ``present``), or, where
        the cells' gauge pairs read the product k_u k_v more precisely
        (:func:`.productnoise.pair_product`) and agree with the fields' within three s.d. of the
        two, a bias that puts the product where the pairs read it, with the pairs' s.d. (the
        twist field's part of the product, mean τ₀², no gauge reads: the measured data's field
        fit gives it, debiased by its own noise, :meth:`.productnoise.ProductNoise.twist_stats`).  The
        s.d. is at the stated noise ``turning_sigma`` as the fields' is (solve_twist's
        ``quiet`` reads it against the noise the data show).  The pairs are read from the
        ``measured`` unit data where the pass's input is not the gauges' (:meth:`_measured_input`),
        and τ₀ with them: a defect pass's input (the measured
        data plus the model's correction) is no gauge's reading (a 32×32 cylinder at 30°: its
        pairs read 2.083·10⁻⁶ /mm², the corrected input's 2.151, 3.4 s.d. off).
        ``info["pair_product"]``: the two readings and s.d.s where the pairs' was taken."""
        noise = self._product_noise
        if noise is None or not turning_sigma > 0.0:
            return product_noise
        inner = self.grid.inner
        t0 = np.asarray(tau0, dtype=float)
        t0 = t0 - t0.sum() / t0.size
        fields = float((np.asarray(k_u)[inner] * np.asarray(k_v)[inner]).mean())
        twist2 = float((t0[inner] ** 2).mean())
        read_fields = fields - twist2 - product_noise[0]
        measured_t0, measured_present = t0, present
        if measured is not None:
            m_turning, m_stretch, m_valid = measured
            if not m_valid.any():
                return product_noise
            # a defect pass: its twist field, like its pairs, is the correction's as much as the
            # gauges' (the 32×32 cylinder's mean τ₀² read 3.8·10⁻⁸ below the noise's own bias, 7
            # s.d.): both come from the measured data
            measured_t0, measured_present = self._measured_twist(m_turning, m_stretch, m_valid, turning_sigma)
            turning, valid = m_turning, m_valid
        pair, pair_sd, cells = pair_product(turning, valid, turning_sigma)
        if cells < 0.5 * self.n * self.m:
            return product_noise
        twist_bias, twist_sd = noise.twist_stats(measured_t0, inner, turning_sigma)
        twist_bias *= (measured_present / turning_sigma) ** 2
        read_pairs = pair - float((measured_t0[inner] ** 2).mean()) + twist_bias
        sd = math.hypot(pair_sd, twist_sd)
        if not (sd < product_noise[1] and abs(read_pairs - read_fields) <= 3.0 * math.hypot(sd, product_noise[1])):
            return product_noise
        info["pair_product"] = (float(f"{read_pairs:.4g}"), float(f"{read_fields:.4g}"), float(f"{sd:.3g}"),
                                float(f"{product_noise[1]:.3g}"))
        return fields - twist2 - read_pairs, sd

    def _measured_fields(self, turning, stretch, valid) -> tuple:
        """The field fit's k_u, k_v, τ₀ of the measured unit data.  A frame asks for them more
        than once (the carried twist, the warm defect correction, each defect pass's
        :meth:`_pair_reading`): the last answer is kept with its input, compared by value (a
        caller may refill one buffer frame after frame), so a frame fits them once (about 1 ms
        at 32×32)."""
        return self._measured(turning, stretch, valid)[0][:3]

    def _measured(self, turning, stretch, valid) -> tuple:
        """((k_u, k_v, τ₀, λ_u, λ_v) of the measured unit data's field fit, the turning noise
        the data show), kept as :meth:`_measured_fields` says."""
        memo = self._measured_memo
        if (memo is not None and np.array_equal(memo[0], turning) and np.array_equal(memo[1], stretch)
                and np.array_equal(memo[2], valid)):
            return memo[3]
        fields = tuple(np.array(f, dtype=float) for f in self.grid.field_maps(valid)(turning, stretch)[:5])
        for f in fields:
            f.flags.writeable = False  # shared by every pass that asks: read-only
        out = (fields, turning_noise_estimate(turning, valid))
        self._measured_memo = (np.array(turning, copy=True), np.array(stretch, copy=True),
                               np.array(valid, copy=True), out)
        return out

    def _measured_stretch_variance(self, measured) -> float | None:
        """The measured stretch fields' variance over the cells' region where the pass's input is
        a defect pass's corrected input, not the gauges' (``measured``, :meth:`_measured_input`),
        else None: the developability test asks how the sheet stretches,
        and the correction's stretch is the model's misfit (a noisy 32×32 cylinder 8.3° off the
        rows: its gauges' stretch varied by 4·10⁻⁵, a pass's corrected input by 1.4–2.2·10⁻⁴,
        doubly curved by the test, and the pass dropped the twist the first had read, on 3
        frames of 12, 3.5 mm off)."""
        if measured is None or not measured[2].any():
            return None
        fields = self._measured(*measured)[0]
        return stretch_variance(self.grid, fields[3], fields[4])

    def _measured_input(self, turning, stretch, valid, strains, units: tuple | None = None) -> tuple | None:
        """The unit data (turning, stretch, valid) of the measured ``strains`` where the pass's
        input differs from them (a defect pass's corrected input), else None (no strains given,
        or the pass reads the gauges themselves).  ``units``: those unit data, where known."""
        if strains is None:
            return None
        if units is None:
            units = unit_data(strains[0], strains[1], self.h_upper, self.h_lower, self.gauge_length)
        m_turning, m_stretch, m_valid = units
        if (m_turning is turning and m_stretch is stretch and m_valid is valid) or (
                np.array_equal(m_turning, turning) and np.array_equal(m_stretch, stretch)
                and np.array_equal(m_valid, valid)):
            return None
        return m_turning, m_stretch, m_valid

    def _measured_twist(self, turning, stretch, valid, turning_sigma: float) -> tuple[np.ndarray, float]:
        """The measured data's twist field τ₀ (zero-mean over the fine grid) and the turning noise
        they carry (as :meth:`_general` reads it), for :meth:`_pair_reading`'s defect passes."""
        fields, estimate = self._measured(turning, stretch, valid)
        t0 = np.asarray(fields[2], dtype=float)
        t0 = t0 - t0.sum() / t0.size
        return t0, _noise_present(estimate, turning_sigma)

    def _product_sd(self, product_fields, sigma_f: float) -> float:
        """The s.d. of the mean curvature product k_u k_v − τ₀² of ``product_fields`` that strain
        noise ``sigma_f`` causes (:meth:`_product_stats`)."""
        k_u, k_v, tau0 = product_fields
        return self._product_stats(k_u, k_v, tau0, self._turning_sd(sigma_f))[1]

    def _agreement(self, general, turning, valid, data, fit_sigma):
        """The test an accepted graph must pass on a cold frame (graphfit.AGREE_SIGMAS): its
        surface and the general model's ``general`` agree, after the best rigid alignment, over
        most of the sheet within their combined uncertainty at the fit's noise level ``fit_sigma``
        (at least the sensor's): the general model's noise s.d., its resolution
        (uncertainty.resolution_sigma: what the turning pattern's structure at the gauge scale
        leaves open) and, only when those alone do not suffice, the graph's own s.d. (4-5 ms on
        5×5; kept in the returned dict, keyed by the coefficients, for the surface's
        node_sigma).  Returns (the test: coefficients → median distance in s.d., that dict)."""
        grid = self.grid
        pos, left_out = general[0], general[4]
        h_u, h_l = self.h_upper, self.h_lower
        sig_turn = math.sqrt(2.0) * fit_sigma / (h_u + h_l)
        # the general model's noise from the measured units (a missing unit's own share is
        # part of its resolution: unknown with the measured units' departures from the pattern)
        tol_sq = fine_sigma(grid, valid, turning, fit_sigma, h_u, h_l, left_out=left_out, missing_spread=0.0) ** 2
        tol_sq = tol_sq + resolution_sigma(grid, valid, turning, sig_turn) ** 2
        graph_sigma: dict = {}

        def agree(coeffs: np.ndarray) -> float:
            surface = self._graph_fit().fine_positions(coeffs)
            ratio = disagreement(surface, pos, np.sqrt(tol_sq))
            if ratio <= GRAPH_AGREE_SIGMAS:
                return ratio  # the graph's own scatter could only widen the tolerance
            sigma = self._graph_fit().fine_height_sigma(coeffs, data, 1.0, grid.centre)
            graph_sigma[coeffs.tobytes()] = sigma
            return disagreement(surface, pos, np.sqrt(tol_sq + sigma**2))

        return agree, graph_sigma

    def _general(self, turning, stretch, valid, n_valid, strain_sigma, previous, twist_sign, strains=None,
                 twist_mean: float | None = None, units: tuple | None = None):
        """Steps 1-5 of the model (any sheet): fields, twist, shear, frames, positions.
        ``twist_mean``: the mean twist over the cells (1/mm) given, not chosen (the stretch
        pattern's reading, :meth:`_stretch_twist`).  ``units``: the unit data of ``strains``
        (:func:`.engine.unit_data`), where the caller has them."""
        grid = self.grid
        left_out = True
        if n_valid:
            maps = grid.field_maps(valid)
            left_out = getattr(maps, "left_out", True)
            k_u, k_v, tau0, lam_u, lam_v, fit = maps(turning, stretch)
        else:  # nothing measured: the flat, unstretched sheet (no fit to build)
            k_u, k_v, tau0 = (np.zeros((grid.nf, grid.mf)) for _ in range(3))
            lam_u, lam_v = np.ones((grid.nf, grid.mf)), np.ones((grid.nf, grid.mf))
            fit = np.zeros(valid.size)
        convex_info = {"status": "factorized", "iterations": 0}
        if self.convex_solver == "clarabel":
            # turning per length = (ε_u − ε_l)/(h_u + h_l); floor for noise-free use
            sig_turn = max(np.sqrt(2.0) * strain_sigma / (self.h_upper + self.h_lower), 1e-6)
            z, convex_info = huber_potential(grid, turning, valid, self.huber_sigmas * sig_turn)
            convex_info["iterations"] = int(cast(int, convex_info["iterations"]))
            k_u, k_v, tau0 = potential_curvatures(grid, z)
            fit = np.concatenate([grid.average[0] @ k_u.ravel(), grid.average[1] @ k_v.ravel()]) - turning.ravel()
        sign, sign_known = 1.0, True
        if twist_sign is not None:
            sign = float(twist_sign)
        elif previous is not None and previous.diagnostics.twist_constant != 0.0:
            sign = math.copysign(1.0, previous.diagnostics.twist_constant)
        else:
            sign_known = False
        turning_sigma = self._turning_sd(strain_sigma)
        compiled = self._compiled
        if compiled is not None:
            k_u, k_v, lam_u, lam_v = compiled.as_field(k_u), compiled.as_field(k_v), compiled.as_field(lam_u), compiled.as_field(lam_v)
            metric_stack = compiled.metric_terms(grid.spacing, lam_u, lam_v)
        else:
            metric_stack = np.array(metric_terms(grid.spacing, lam_u, lam_v))
        stretch_sigma = self._stretch_sd(strain_sigma)
        product_noise = self._product_stats(k_u, k_v, tau0, turning_sigma)
        metric = Metric(*metric_stack)
        # the noise these data carry (too few units to tell: the stated; at most twice the
        # stated: more is a sharp feature's doing)
        present = _noise_present(turning_noise_estimate(turning, valid), turning_sigma) if n_valid else 0.0
        if product_noise[0] != 0.0:
            # the noise's own curvature product is no Gaussian curvature: the product the twist
            # is read from, and Brioschi's source for the shear (its F = 0 part and the base of
            # later passes), are taken without it
            product_noise = (product_noise[0] * (present / turning_sigma) ** 2, product_noise[1])
        # a positive product is read against the noise the data show where they are clearly
        # quieter than stated (engine.solve_twist's ``quiet``)
        quiet = present / turning_sigma if turning_sigma > 0.0 else 1.0
        if product_noise[0] != 0.0:
            assert self._product_noise is not None  # measured by _product_stats above
            debias = (present * present) * self._product_noise.bias_field * metric_stack[7]
            metric_stack = metric_stack.copy()
            metric_stack[6] -= debias
            metric_stack[8] -= debias
            metric = Metric(*metric_stack)
        # the product the twist is read from: the gauge pairs' where they read it more precisely
        # (the twist left open, and the least-shear prior below, keep the fields' noise: a
        # sharper reading takes more twists, it rules out none that noise leaves open)
        reading = product_noise
        measured = self._measured_input(turning, stretch, valid, strains, units)  # None unless a defect pass
        if product_noise[0] != 0.0:
            reading = self._pair_reading(k_u, k_v, tau0, turning, valid, measured, turning_sigma, present,
                                         product_noise, convex_info)
        # three s.d. of a least-shear square of the twist that the stretch noise causes through
        # Brioschi's source (on a 5×5 sheet six times the curvature product's: flat noisy frames
        # took twists of 4·10⁻⁴ /mm, 0.2 mm at the corners, when only the product's was counted)
        shear_noise = 3.0 * stretch_sigma * self._least_shear_noise()
        tau, twist_c, graph, open_twist, from_shear, product, ramp = solve_twist(
            grid, k_u, k_v, tau0, lam_u, lam_v, sign, turning_sigma, metric, stretch_sigma, sign_from_data=twist_sign is None,
            product_noise=reading, quiet=quiet if quiet < QUIET_SHARE else 1.0,
            open_spread=product_noise[1] if reading is not product_noise else None,
            stretch_dev2=self._measured_stretch_variance(measured),
            shear_noise=shear_noise,
        )
        convex_info["product_fields"] = (k_u, k_v, tau0)
        shear_graph = None
        if graph is not None:  # a sheet pushed out of plane: twist and shear from its slopes
            # (the noise the data carry: a defect pass's input carries more than the measured
            # data, its correction adding the residual's noise again; the all-valid maps' draws
            # stand for a frame with units missing too)
            level = present / turning_sigma if turning_sigma > 0.0 else 0.0
            # (the twist's own s.d. serves σ only where the noise alone leaves the model within
            # one per gauge, _posterior: not computed where that is known not to hold)
            known = self._noise_responses.get(float(strain_sigma))
            fields = graph_sheet_fields(grid, maps, turning, stretch, graph, (metric.e - 1.0, metric.g - 1.0),
                                        noise=self._slope_noise(), noise_sd=(present, level * stretch_sigma),
                                        want_twist_sd=known is None or known[1] <= 1.0)
            if fields is not None:
                (tau, shear_graph, twist_sd), twist_c = fields, graph.constant
                convex_info["graph_sheet"] = True
                if math.isfinite(twist_sd) and graph.slope_twist != 0.0:
                    # the twist and its sign read from the stretch pattern of the refined graph:
                    # its s.d. is the noise's through that reading (the frame model's twist per
                    # material length, as graph.constant), not the curvature product's
                    convex_info["graph_twist_sd"] = twist_sd * abs(graph.constant / graph.slope_twist)
        shift0 = 0.0
        undecided = 0.0  # a twist shift the data can neither confirm nor rule out (1/mm)
        curvature_supported = False  # the stretch varies as much as the own twist's curvature needs
        contested = False  # the least-shear twist weighed against the ramp's shrunk product twist
        marginal = False  # the least-shear twist taken by less than the noise could undo
        if twist_mean is not None:
            shift0 = twist_mean - float(tau[grid.inner].mean())
        elif shear_graph is None and self.least_shear:
            # the prior for the twist the gauges leave open: the least-shear sheet among those
            # the data allow, when it needs clearly less shear than the model's own pick
            tau_mean = float(tau.sum()) / tau.size
            options = least_shear_twists(grid, k_u, k_v, lam_u, lam_v, tau - tau_mean, metric)
            here = least_shear_value(grid, k_u, k_v, lam_u, lam_v, tau - tau_mean, metric, tau_mean)
            # a twist whose square the noise could produce is no evidence (three s.d. of the mean
            # curvature product, as solve_twist judges the Gauss equation's, and of the
            # least-shear square the stretch noise moves)
            product_bar = 3.0 * product_noise[1]
            noise = math.hypot(product_bar, shear_noise)
            options = [(c, val) for c, val in options if val < LEAST_SHEAR_GAIN * here]
            if sign_known:
                options = [opt for opt in options if opt[0] * sign > 0.0]
            within_noise = [opt for opt in options if abs(opt[0] ** 2 - tau_mean**2) <= noise]
            options = [opt for opt in options if abs(opt[0] ** 2 - tau_mean**2) > noise]
            if within_noise and not options:
                c_ls = within_noise[0][0]
                # (the least-shear twist where the product reads it too, within the product's
                # noise, and the ramp shrank or hid it: whether it is taken is the noise's to
                # decide, frame by frame; it is taken where the product is beyond its noise)
                contested = (open_twist > 0.0 and product > product_bar / 3.0 and abs(tau_mean) < abs(c_ls)
                             and abs(c_ls**2 - product) <= noise)
                if contested and product > product_bar and tau_mean != 0.0:
                    # the product's twist, beyond its noise but shrunk by its significance
                    # ramp, and the least-shear prior's, an independent reading, agree: the
                    # prior's is weighed as a choice (a noisy 12×12 cylinder of R 225 mm 9.7°
                    # off the rows, twist 7.4·10⁻⁴ /mm: the product read 3.3 s.d., shrunk to
                    # 2.2·10⁻⁴, 0.67 mm off; the prior said 6.3·10⁻⁴)
                    options = [within_noise[0]]
                else:
                    # a less-sheared twist the noise cannot rule out: kept as the answer's spread
                    undecided = c_ls - tau_mean
            if options and stretch_supports_curvature(grid, k_u, k_v, tau, lam_u, lam_v, stretch_sigma):
                # the stretch varies as much as the model's doubly curved sheet needs: it stands,
                # unless the stretch pattern itself says otherwise (below)
                if self.poisson_range is None or strains is None:
                    options = []
                else:
                    curvature_supported = True
            if options:  # mirror-image minima are one choice: the requested, kept or default (+) sign
                tied = [opt for opt in options if opt[1] <= LEAST_SHEAR_TIE * options[0][1] or sign_known]
                same_sign = [opt for opt in tied if opt[0] * sign > 0.0]
                options = same_sign if (same_sign or sign_known) else options
            if options:
                shift0 = options[0][0] - tau_mean
                # taken with its square within MARGINAL_SIGMAS s.d. of the product's noise from
                # the untaken twist's, two beyond the bar: another frame's noise leaves it
                marginal = abs(options[0][0] ** 2 - tau_mean**2) <= noise * MARGINAL_SIGMAS / 3.0

        family: dict[float, np.ndarray] = {}  # shifts asked for again (the answer, its mirror) are not recomputed

        def positions_at(shift: float) -> np.ndarray:
            """The sheet with its twist constant moved by ``shift`` (1/mm), all else kept: the
            one direction the gauges leave open (docs/reconstruction.md, "Posterior check").
            Read-only: a member may be asked for again."""
            key = float(shift + shift0)  # (the prior below may still move shift0)
            if key not in family:
                family[key] = member(key)
                family[key].flags.writeable = False
            return family[key]

        def member(shift: float) -> np.ndarray:
            twist = tau if shift == 0.0 else tau + shift
            if compiled is not None:
                # shear, rotation rates, frames, positions and the sensor frame in one call
                target = (compiled.as_field(shear_graph), True) if shear_graph is not None else (self._no_shear_target, False)
                return compiled.surface_positions(
                    grid.spacing, k_u, k_v, lam_u, lam_v, compiled.as_field(twist), metric_stack,
                    self.shear_passes, self.frame_corrections, self._band, *grid.centre, *target,
                    FRAME_PLANE_OPEN, FRAME_PLANE_BLEND,
                ).transpose(1, 2, 0)
            return to_sensor_frame(grid, self._positions(k_u, k_v, lam_u, lam_v, twist, metric, shear_graph))

        pos = positions_at(0.0)
        if shift0 != 0.0 and strains is not None and twist_mean is None:
            # the prior only chooses among answers the data cannot tell apart
            pos_own = positions_at(-shift0)
            sigma_f = max(strain_sigma, DEFAULT_STRAIN_SIGMA)
            chi_new, dof, _ = misfit(self._candidate(pos), self._layout, strains[0], strains[1], sigma_f)
            chi_own, _, _ = misfit(self._candidate(pos_own), self._layout, strains[0], strains[1], sigma_f)
            # (where the own twist's curvature has the stretch's support, the least-shear twist
            # is weighed by the stretch pattern below unless the gauges read it worse beyond the
            # noise: the family member keeps the fields fitted to the own twist, and within the
            # noise their preference for it proves nothing)
            if (chi_new > chi_own + MIRROR_CHI2 * max(1.0, chi_own / max(dof, 1))
                    and not (curvature_supported and _within_noise(chi_new, chi_own, dof, 1.0))
                    or min(chi_new, chi_own) > GROSS_MISFIT * max(dof, 1)):
                shift0, pos = 0.0, pos_own
            elif self.poisson_range is not None:
                # nor among those the film's stretch tells apart: through each one's own
                # Gaussian curvature (:mod:`.membrane`), the model's own twist explaining the
                # stretch pattern with half the misfit or less stands (a ridge of three bumps
                # along a diagonal: the least-shear twist put its corners 3.7 mm off)
                if self._membrane is None:
                    self._membrane = membrane_maps(grid)
                rss_new = self._stretch_rss(pos, stretch, valid)
                rss_own = self._stretch_rss(pos_own, stretch, valid)
                convex_info["least_shear_stretch_rss"] = (float(f"{rss_new:.4g}"), float(f"{rss_own:.4g}"))
                # (where the stretch varies as much as the own twist's curvature needs, that
                # twist stands unless the least-shear one explains the pattern with half its
                # misfit: a film pre-stretched 5 % on a 32×32 cylinder of R 407 mm at -43°
                # relaxes at its edges by about what the untwisted, doubly curved sheet needs,
                # and that sheet was kept, 12.5 mm mean off with σ 0.12 mm)
                if rss_own <= MEMBRANE_SIGN_RATIO * rss_new or (
                        curvature_supported and rss_new > MEMBRANE_SIGN_RATIO * rss_own):
                    shift0, pos = 0.0, pos_own
        # the answer's mean twist over the cells (the twist field is not τ₀ plus the constant
        # alone where the graph test or the metric scaling shaped it)
        convex_info["twist_mean"] = float(tau[grid.inner].mean()) + shift0
        if shift0 != 0.0:
            twist_c = twist_c + shift0
            convex_info["least_shear_shift"] = shift0
            # the curvature product's own twist, which the data could not rule out either (an
            # oblique cylinder, R 95 mm at -62°: the less-sheared twist taken was 5.6 % short,
            # 0.19 mm off at a corner with σ 0.023 mm)
            convex_info["undecided_twist"] = -shift0
        if undecided != 0.0 and shift0 == 0.0:
            convex_info["undecided_twist"] = undecided
        if contested and "undecided_twist" in convex_info:
            # taken on some noise draws and not on others: the way between is scatter too
            convex_info["least_shear_contested"] = True
        if marginal and shift0 != 0.0 and not contested:
            # (the same from the side that took it: a 5×5 cylinder of R 72 mm 5.6° off the columns
            # took a twist on 16 noisy draws of 30 and none on 14, 0.3 mm apart; the frames that
            # took it by this margin said a scatter of 0.04-0.05 mm)
            convex_info["least_shear_marginal"] = True
        if open_twist > 0.0 and shift0 == 0.0 and twist_mean is None and shear_graph is None:
            convex_info["open_twist"] = open_twist
        if ramp > 1.0 and shift0 == 0.0 and twist_mean is None and shear_graph is None:
            convex_info["product_ramp"] = ramp
        if from_shear and shift0 == 0.0 and twist_mean is None and shear_graph is None:
            convex_info["shear_prior_twist"] = twist_c
            # (the answer's mean Gaussian curvature, which scales how far the prior may be off)
            convex_info["shear_prior_curvature"] = product - twist_c * twist_c
        return pos, twist_c, fit, convex_info, left_out, positions_at

    def _positions(self, k_u, k_v, lam_u, lam_v, tau, metric: Metric, shear_graph: np.ndarray | None = None) -> np.ndarray:
        """The reference (numpy) steps from the twist to the positions: shear, rotation rates,
        frames, chords.  ``shear_graph``: a graph's shear F = z_u z_v, whose part a(u) + b(v)
        (which Brioschi's formula leaves free) replaces the least-norm one."""
        grid = self.grid
        if self.shear_passes:
            sin_gamma = solve_shear(grid, k_u, k_v, lam_u, lam_v, tau, self.shear_passes, metric)
        else:
            sin_gamma = np.zeros_like(k_u)
        if shear_graph is not None:
            f = sin_gamma * (lam_u * lam_v)
            f += free_part(shear_graph - f)
            sin_gamma = np.minimum(np.maximum(f / (lam_u * lam_v), -0.9), 0.9)
        rot_u, rot_v = rotation_rates(grid, k_u, k_v, lam_u, lam_v, tau, sin_gamma)
        frames = integrate_frames(grid, rot_u, rot_v, self.frame_corrections)
        return integrate_positions(grid, frames, rot_u, rot_v, lam_u, lam_v, sin_gamma)


def _report_screen(diag: Diagnostics, suspects: list[Suspect], info: dict, seconds: float) -> None:
    """The gauge screen's verdict in a surface's diagnostics."""
    diag.suspect_gauges = "; ".join(s.describe() for s in suspects)
    diag.extra["gauge_screen"] = info["screen"]
    if "screen_clarabel" in info:
        diag.extra["screen_clarabel"] = info["screen_clarabel"]
    if suspects:
        diag.extra["suspect_gauges"] = [
            {"name": s.name, "layer": ("upper", "lower")[s.layer], "direction": ("row", "column")[s.direction],
             "row": s.row, "col": s.col, "gain": round(s.gain, 3), "sigmas": round(s.residual_sigmas, 1)}
            for s in suspects]
    diag.solve_time += seconds


def nodes_in_sensor_frame(grid: FineGrid, position: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The cell-centre nodes (N, M, 3) of a reference surface, given as a map from material
    coordinates (K, 2) to positions (K, 3) such as an emulator shape's truth, put in the sensor
    frame by its one definition on ``grid``: what ``node_sigma`` describes, with no alignment."""
    uu, vv = np.meshgrid(grid.u, grid.v)
    fine = np.asarray(position(np.stack([uu.ravel(), vv.ravel()], axis=1))).reshape(grid.nf, grid.mf, 3)
    return to_sensor_frame(grid, fine)[np.ix_(grid.node_rows, grid.node_cols)]


def to_sensor_frame(grid: FineGrid, pos: np.ndarray) -> np.ndarray:
    """The sensor frame's one definition (docs/architecture.md), for any positions (nf, mf, 3)
    on ``grid`` (a reconstruction's, or a reference surface's to compare with it there): the
    centre node at the origin; +z the normal of the sheet's best-fit plane (least squares over
    every fine node: the cell centres alone jump from one plane to another on a sheet wrapped
    round a tube), towards the upper side; +x the rows' mean direction (the sum of their chords)
    in that plane.  The compiled kernel (kernels.surface_positions) takes the same steps.

    The whole sheet fixes the frame, not the centre's tangents: a slope read at one point turns
    the whole sheet with any error of the fields there (a bump beside the centre of a 5×5 film:
    0.25-0.52 mm mean error in the centre's tangent frame, 0.05 mm in this one; the error after
    the best rigid alignment 0.03-0.05).  A sheet wrapped so far that its plane is ill defined
    (:data:`FRAME_PLANE_OPEN`) takes the centre's tangent plane instead, blended continuously.
    Returns (nf, mf, 3), a view of a components-first array."""
    flat = pos.transpose(2, 0, 1).reshape(3, -1)  # a view where pos is one of components first
    rot, shift = sensor_frame(grid, pos)
    out = rot @ flat
    out -= shift[:, None]
    return out.reshape(3, grid.nf, grid.mf).transpose(1, 2, 0)


def sensor_frame(grid: FineGrid, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion :func:`to_sensor_frame` applies to ``pos``: (rot (3, 3), shift (3,)),
    x ↦ rot·x − shift (a vector, a derivative of the positions, turns by rot alone)."""
    a0, b0 = grid.centre
    flat = pos.transpose(2, 0, 1).reshape(3, -1)
    mean = flat.mean(axis=1)
    var, axes = np.linalg.eigh(flat @ flat.T - flat.shape[1] * np.outer(mean, mean))  # ascending
    nz = axes[:, 0]
    # the centre's tangents by the fourth-order differences the surface's patches use
    t_u = 8.0 * (pos[a0, b0 + 1] - pos[a0, b0 - 1]) - (pos[a0, b0 + 2] - pos[a0, b0 - 2])
    t_v = 8.0 * (pos[a0 + 1, b0] - pos[a0 - 1, b0]) - (pos[a0 + 2, b0] - pos[a0 - 2, b0])
    n_c = np.array(_cross3(t_u.tolist(), t_v.tolist()))
    n_c /= math.sqrt(n_c @ n_c)
    chord = pos[:, -1].sum(axis=0) - pos[:, 0].sum(axis=0)
    ratio = var[0] / var[1] if var[1] > 0.0 else 1.0
    if ratio > FRAME_PLANE_OPEN:  # a plane ill defined: towards the centre's tangent plane
        t = min((ratio - FRAME_PLANE_OPEN) / FRAME_PLANE_BLEND, 1.0)
        nz = (1.0 - t) * (nz if nz @ n_c >= 0.0 else -nz) + t * n_c
        nz /= math.sqrt(nz @ nz)
        chord = (1.0 - t) * chord / math.sqrt(chord @ chord) + t * t_u / math.sqrt(t_u @ t_u)
    elif nz @ n_c < 0.0:
        nz = -nz
    ex = chord - nz * (nz @ chord)
    ex /= math.sqrt(ex @ ex)
    rot = np.array([ex, _cross3(nz.tolist(), ex.tolist()), nz])  # rows: new axes in the old frame
    return rot, rot @ pos[a0, b0]


def _cross3(a, b) -> list[float]:
    """Cross product of two 3-vectors (np.cross costs more than the arithmetic here)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


# reconstruct()'s declared cache: one Reconstructor per geometry (least recently used first),
# each with its own lock, since a Reconstructor keeps per-mask caches and is not thread-safe;
# the cache itself is guarded by _CACHE_LOCK.
_CACHE: "OrderedDict[tuple, tuple[Reconstructor, threading.Lock]]" = OrderedDict()
_CACHE_SIZE = 8
_CACHE_LOCK = threading.Lock()


def reconstruct(
    eps_upper,
    eps_lower,
    pitch: float = 12.0,
    h_upper: float = 0.2,
    h_lower: float = 0.2,
    *,
    gauge_length: float = GAUGE_LENGTH_MM,
    strain_sigma: float = DEFAULT_STRAIN_SIGMA,
    previous: Surface | None = None,
    twist_sign: float | None = None,
    graph_fit: bool | None = None,
    twist_prior: str = "open",
    gain_sd: float = DEFAULT_GAIN_SD,
) -> Surface:
    """Reconstruct the sheet's surface from one frame of strains.

    ``eps_upper``, ``eps_lower``: (2, N, M) engineering strain; ``[0]`` row-direction (u) gauges,
    ``[1]`` column-direction (v) gauges; NaN for a missing gauge.  ``strain_sigma``: strain-noise
    s.d. of one gauge for the uncertainty estimate.  ``previous``: the last frame's surface (keeps
    the sign of an unobservable constant twist); ``twist_sign`` sets that sign explicitly (and
    overrides a sign the stretch pattern would fix).  ``graph_fit``: try the height-graph fit
    first (None, the default: on for sheets of up to 64 cells; see :class:`Reconstructor`).
    ``twist_prior``: "open" (default) or "none", and ``gain_sd``, as :class:`Reconstructor`
    takes them.  Geometry-dependent work is cached by (N, M, pitch, h_upper, h_lower,
    gauge_length, graph_fit, twist_prior, gain_sd).
    """
    eu = np.asarray(eps_upper, dtype=float)
    if eu.ndim != 3 or eu.shape[0] != 2:
        raise ValueError(f"eps_upper must have shape (2, N, M), got {eu.shape}")
    key = (eu.shape[1], eu.shape[2], float(pitch), float(h_upper), float(h_lower), float(gauge_length), graph_fit,
           twist_prior, gain_sd)
    with _CACHE_LOCK:
        entry = _CACHE.get(key)
        if entry is not None:
            _CACHE.move_to_end(key)
    if entry is None:
        # built outside the lock (a second or so on large sheets); a race builds it twice
        built = (Reconstructor(eu.shape[1], eu.shape[2], pitch, h_upper, h_lower, gauge_length, graph_fit=graph_fit,
                               twist_prior=twist_prior, gain_sd=gain_sd),
                 threading.Lock())
        with _CACHE_LOCK:
            entry = _CACHE.setdefault(key, built)
            if len(_CACHE) > _CACHE_SIZE:
                _CACHE.popitem(last=False)
    rec, lock = entry
    with lock:
        return rec(eu, eps_lower, strain_sigma=strain_sigma, previous=previous, twist_sign=twist_sign)
