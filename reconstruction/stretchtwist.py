"""The stretch pattern's twist (docs/reconstruction.md, "Posterior check"): a film loaded along
its normal has the Gaussian curvature its stretch pattern says, and with the measured
curvatures that fixes the square of the constant twist the gauges leave open.  The steps here
read it (the free-edge membrane's reading, else the trace's interval), refine it on an answer's
own twist family, move an answer to it or leave the twists it allows open in σ, weigh the two
signs (the stretch of a saddle is even in its turn) and carry a held sheet's estimate to the
next frame.

:class:`StretchPatternTwist` holds them; :class:`~.reconstructor.Reconstructor` mixes it in,
and provides the geometry, the fields' noise and the models it reads (declared on the class).
"""
from __future__ import annotations

import hashlib
import math
from typing import Any, Callable, NamedTuple

import numpy as np

from .airy import airy_curvature_range, stretch_trace
from .engine import unit_data
from .forward import misfit, misfit_and_strains
from .grid import FineGrid
from .membrane import MembraneMaps, TwistReading, basis_curvature, membrane_maps, read_twist, stretch_residual
from .productnoise import turning_noise_estimate
from .surface import Surface
from .twistfamily import MIRROR_FLOOR_MM, _differs, _half_reach, _mean_twist_terms, _memo, _with_twist, _within_noise
from .uncertainty import DEFAULT_STRAIN_SIGMA

__all__ = ["StretchPatternTwist", "StretchTwist", "TWIST_PRIORS", "MOVE_SHARE", "SIGN_OWN_SHARE",
           "CARRIED_MOVE_SIGMAS", "OPEN_SIGMAS", "UNDECIDED_SHARE", "MEMBRANE_SIGN_RATIO", "SIGN_SIGMAS",
           "CONTESTED_SIGMAS", "PRODUCT_OPEN_SIGMAS", "NOISE_REACH_LEVEL", "DOME_SHARE"]

# Where the stretch pattern needs a twist, an answer whose mean twist is off the pattern's
# estimate by more than this share of it is modelled afresh at the estimate (the refined
# estimate scatters by 2-3 % from frame to frame with the sensor's noise).
MOVE_SHARE = 0.05
# Where both signs are modelled afresh, each is weighed at the twist its own family explains the
# stretch pattern best, modelled afresh there unless within this share of the twist it was
# modelled at: a sign weighed at a twist 5 % off its own (MOVE_SHARE) misread the stretch by
# more than the two signs differ (an 8×8 saddle of R 122 mm, ν 0.3: 4.6 times the wrong sign's
# misfit, and the wrong sign was taken), at 1 % by a twenty-fifth of that.
SIGN_OWN_SHARE = 0.01
# ... and an answer carrying the frame before's twist, by more than this many s.d. of the
# estimate's noise too (StretchPatternTwist._move_threshold).
CARRIED_MOVE_SIGMAS = 2.0
# The twists the stretch pattern leaves open reach past its refined estimate by this many s.d. of
# the estimate's noise (StretchPatternTwist._twist_left_open).
OPEN_SIGMAS = 2.0
# Where the stretch pattern allows no twist and the answer has none, a twist refined on the
# answer's family above this share of the interval's top is undecided, and joins node_sigma
# (below it, where the reading itself said a twist, the reading's twist joins it); where the
# reading needs a twist but its refined interval reaches none, a refined twist above this share
# of the reading's top decides the twist: the answer moves to it (StretchPatternTwist._stretch_twist).
UNDECIDED_SHARE = 1.0 / 3.0
#: What node_sigma takes of a twist the stretch pattern cannot tell from none, where the answer
#: has none (StretchPatternTwist._open_to_top): "open", the twists the reading allows; "none",
#: the sheet is known to carry none there.
TWIST_PRIORS = ("open", "none")
#: A sheet the product of whose mean curvatures (mean k_u · mean k_v) is at least this share of
#: its twist-free curvature product (c², _unread_twist) is a dome on the scale of the sheet (a
#: bump or a ridge on a flat sheet bends it both ways and its mean curvatures are about none):
#: where no reading explains its stretch, its twist is left open.
DOME_SHARE = 0.9
# The sign of a twist the stretch pattern needs is not told by it; an answer's own sign gives way
# to the other where that surface explains the pattern (through its own Gaussian curvature) with
# at most this share of the answer's misfit.
MEMBRANE_SIGN_RATIO = 0.5
# ... and only by more than the noise could make it: this many s.d. of the misfits' difference
# (see _sign_beyond_noise).
SIGN_SIGMAS = 2.0
# The reading's lower end in the square (TwistReading.low_square) within this many s.d. of the
# curvature product of none: the noise moves the pattern's decision from frame to frame (the
# 12×12 saddle of StretchTwist.contested: over 10 noisy frames that end scattered by 1.6 times the
# product's s.d. about none, and 4 of them cleared it)
CONTESTED_SIGMAS = 3.0
#: Where the trace's interval reads the twist, the twist the curvature product alone would be
#: is left open when the product lies beyond this many of its noise s.d. (below, it is the noise's).
PRODUCT_OPEN_SIGMAS = 3.0
#: The share of the stated noise that a frame's own turning noise (productnoise.
#: turning_noise_estimate) must reach before the gauges' veto of a twist the stretch pattern
#: moves to is weighed against the noise's reach (StretchPatternTwist._noise_reach, large sheets).
NOISE_REACH_LEVEL = 0.5


#: The twist's squares (times the reading's) that :meth:`StretchPatternTwist._refine_twist` weighs.
_REFINE_SQUARES = np.array([0.0, 0.5, 1.0, 1.5])
_REFINE_SQUARES.flags.writeable = False
# np.polyfit(_REFINE_SQUARES, ·, 2)'s scaled Vandermonde matrix, its column scales and rcond
# (fixed: built once, the same least-squares solve per frame)
_REFINE_LHS = np.vander(_REFINE_SQUARES, 3)
_REFINE_SCALE = np.sqrt((_REFINE_LHS * _REFINE_LHS).sum(axis=0))
_REFINE_LHS /= _REFINE_SCALE
_REFINE_RCOND = len(_REFINE_SQUARES) * np.finfo(float).eps
_REFINE_SCALE.flags.writeable = False
_REFINE_LHS.flags.writeable = False


def _quadratic_fit(values: np.ndarray) -> np.ndarray:
    """np.polyfit(_REFINE_SQUARES, values, 2) (highest power first), the same numbers by its own
    steps with the fixed matrix built once."""
    return np.linalg.lstsq(_REFINE_LHS, values, _REFINE_RCOND)[0] / _REFINE_SCALE


def _sign_beyond_noise(own: np.ndarray, other: np.ndarray, noise_sd: float) -> bool:
    """Whether the other twist sign explains the stretch pattern (residuals ``other``) better than
    the answer's own (``own``) by more than noise of ``noise_sd`` per reading could: with
    residuals r = y − p of the same readings, |r₁|² − |r₂|² = 2 (y − (p₁ + p₂)/2)·(p₂ − p₁)
    moves with the noise by 2σ|p₂ − p₁| = 2σ|r₁ − r₂| (s.d.)."""
    gain = float(own @ own) - float(other @ other)
    return gain > 2.0 * SIGN_SIGMAS * noise_sd * float(np.linalg.norm(own - other))


class _SignCandidate(NamedTuple):
    """The answer modelled afresh with one twist sign (StretchPatternTwist._afresh_by_sign)."""

    chi2: float  # its misfit to the gauges
    sign: float
    surface: Surface
    family: Callable[[float], np.ndarray]  # shift of its twist constant → fine positions
    residual: np.ndarray  # the stretch pattern's residuals through its own Gaussian curvature (membrane readings)
    magnitude: float  # its twist's magnitude

    @property
    def rss(self) -> float:
        return float(self.residual @ self.residual)


class _LeftOpen(NamedTuple):
    """Twists the data leave open about an answer that stands (StretchPatternTwist._twist_left_open)."""

    ends: list[float]  # shifts on the answer's family to them (their spread joins node_sigma)
    #: they reach the reading's top with nothing refined (StretchPatternTwist._open_to_top): σ keeps
    #: what it took of the twist without the pattern (StretchTwist.keeps_rest)
    to_top: bool


def _shifts_to(magnitude: float, m0: float, sign: float, sign_open: bool) -> list[float]:
    """Shifts from the answer's twist ``m0`` to the twist of ``magnitude``, of either sign where
    none is told (``sign_open``), else of ``sign``."""
    return [m - m0 for m in ((sign * magnitude, -sign * magnitude) if sign_open else (sign * magnitude,))]


class StretchTwist(NamedTuple):
    """What the stretch pattern made of an answer's twist (StretchPatternTwist._stretch_twist)."""

    answer: Surface
    mirror: Surface | None
    shift: float  # where the answer sits on ``family``
    spread: Callable[[], np.ndarray | None]  # the twists the reading allows, as node_sigma's term
    chi2: float  # the answer's misfit to the gauges
    family: Callable[[float], np.ndarray]  # shift of the twist constant → fine positions
    noise_sd: float  # the s.d. of the reading's magnitude from the stretch noise alone (0: not known)
    #: shifts on ``family`` to the answer the other branch of the decision gives, where the
    #: noise takes one branch on some frames and the other on others (their way joins the
    #: scatter part of σ)
    contested: tuple[float, ...] = ()
    #: ``spread`` widens what σ took of the twist without the pattern (its noise, what the
    #: least-shear prior left open) instead of replacing it: an answer that stands where the
    #: reading leaves its twist open to its top, or where nothing reads the stretch of a dome
    keeps_rest: bool = False


class StretchPatternTwist:
    """The stretch pattern's twist, as steps of the reconstructor's posterior check (mixed into
    :class:`~.reconstructor.Reconstructor`).  What they read of their host is declared here."""

    grid: FineGrid
    pitch: float
    h_upper: float
    h_lower: float
    gauge_length: float
    #: ν's interval for the stretch pattern's readings (None: they are not taken)
    poisson_range: tuple[float, float] | None
    #: what node_sigma takes of a twist the reading cannot tell from none (TWIST_PRIORS)
    twist_prior: str
    _membrane: MembraneMaps | None  # the membrane's maps, made on first use
    _compiled: Any  # the compiled kernels, or None
    _half_diagonal2: float  # the sheet's squared half-diagonal (mm²)
    _layout: Any  # the gauges' layout for the forward model
    _fresh: Callable[..., Any]  # the general model afresh at a given sign and twist
    _surface: Callable[..., Surface]
    _candidate: Callable[..., Any]
    _product_sd: Callable[..., float]
    _stretch_sd: Callable[[float], float]
    _turning_sd: Callable[[float], float]

    def _twist_reading(self, stretch, valid, product_fields, sigma_f: float) -> TwistReading | None:
        """What the stretch pattern says of the mean twist's magnitude (docs/reconstruction.md):
        the free-edge membrane's reading (:func:`.membrane.read_twist`: the twist and ν together)
        where it explains the pattern, else the trace's (:func:`.airy.airy_curvature_range`: any
        outline and edge load, ν anywhere in the Poisson interval; its middle is the estimate).
        None where neither says anything."""
        assert self.poisson_range is not None
        stretch_sd = self._stretch_sd(sigma_f)
        k_u, k_v, tau0 = product_fields
        if self._membrane is None:
            self._membrane = membrane_maps(self.grid)
        # Both readings are linear in the strain: their relation between the pattern and K holds
        # to first order, so their interval widens by the sheet's own strain level (a film
        # pre-stretched 5 % on a cylinder at -38°: the trace read 0.00714-0.00749 /mm for a
        # twist of 0.00693)
        strain = stretch[valid]
        level = float(np.mean(np.abs(strain - 1.0))) if strain.size else 0.0
        reading = read_twist(self._membrane, stretch, valid, k_u, k_v, tau0, self.grid.inner, self.poisson_range,
                             stretch_sd, self._compiled)
        if reading is not None:
            shrink = max(1.0 - level, 0.0)
            return reading._replace(low=reading.low * shrink, high=reading.high * (1.0 + level),
                                    low_square=reading.low_square * (shrink * shrink if reading.low_square > 0.0 else 1.0))
        bounds = airy_curvature_range(stretch, valid, self.pitch, *self.poisson_range,
                                      noise_sd=math.sqrt(2.0) * stretch_sd)  # a trace: two readings
        if bounds is None:
            return None
        _, base = _mean_twist_terms(product_fields, self.grid.inner)
        lo, hi = max(base - bounds[1], 0.0), base - bounds[0]
        if hi <= 0.0:
            return None  # no twist gets there: the curvature product alone is below the pattern's K
        m_lo, m_hi = math.sqrt(lo) * max(1.0 - level, 0.0), math.sqrt(hi) * (1.0 + level)
        return TwistReading(0.5 * (m_lo + m_hi), m_lo, m_hi, math.nan, math.nan, "trace")

    def _carried_twist(self, previous: Surface | None, twist_sign, turning, stretch, valid,
                       strain_sigma: float, measured_fields: Callable[[], tuple]) -> tuple[float | None, TwistReading | None]:
        """The mean twist (signed, 1/mm) the stretch pattern gave the frame before, where
        ``twist_sign`` does not contradict its sign and this frame's stretch still needs a twist
        (the membrane's reading of this frame excludes zero and holds the last estimate, within
        a quarter): this frame's general model starts there, so a shape that holds still is not
        modelled afresh every frame.  None otherwise (a sphere after a saddle goes back to the
        least-shear prior).  Also returns the reading, which the posterior check then takes as
        its own (the same data, the same fields)."""
        if previous is None or self.poisson_range is None or not valid.any():
            return None, None
        estimate = previous.diagnostics.extra.get("stretch_estimate")
        if estimate is None or (twist_sign is not None and float(estimate[0]) != float(twist_sign)):
            return None, None
        fields = measured_fields()
        reading = self._twist_reading(stretch, valid, fields, max(strain_sigma, DEFAULT_STRAIN_SIGMA))
        # (an interval reaching none carries the estimate too where the reading itself still
        # says a twist, above half its top: a held 12×12 saddle of R 286 mm at 83° otherwise
        # went between its twist and none frame by frame, 0.05 and 1.0 mm off; spheres read
        # 0.15-0.45 of their top)
        says_twist = reading is not None and (reading.low > 0.0 or reading.twist > 0.5 * reading.high)
        if (reading is None or reading.source != "membrane" or not says_twist
                or not 0.75 * reading.low <= estimate[1] <= 1.25 * reading.high):
            return None, reading
        return float(estimate[0]) * float(estimate[1]), reading

    def _stretch_residual(self, positions: np.ndarray, stretch, valid) -> np.ndarray:
        """The stretch pattern's residuals through a surface's own Gaussian curvature (fine-grid
        positions), :func:`.membrane.stretch_residual` at the best ν of the Poisson interval."""
        assert self.poisson_range is not None and self._membrane is not None
        maps = self._membrane
        if self._compiled is None:
            return stretch_residual(maps, basis_curvature(maps, positions, self.grid.spacing), stretch, valid,
                                    self.poisson_range)[0]
        # the same steps compiled: a frame weighs up to seven members of its twist family
        k_basis = np.empty(maps.rows.size * maps.cols.size)
        self._compiled.basis_curvature(positions, maps.rows, maps.cols, self.grid.spacing, k_basis)
        ok = np.ascontiguousarray(valid, dtype=bool).reshape(-1)
        r = np.empty(int(np.count_nonzero(ok)))
        self._compiled.stretch_residual(maps.ab, k_basis, np.ascontiguousarray(stretch, dtype=float).reshape(-1), ok,
                                        *self.poisson_range, r)
        return r

    def _stretch_rss(self, positions: np.ndarray, stretch, valid) -> float:
        """The stretch pattern's misfit (sum of squares) through a surface's own Gaussian curvature."""
        r = self._stretch_residual(positions, stretch, valid)
        return float(r @ r)

    def _refine_twist(self, at_magnitude, reading: TwistReading, stretch, valid) -> float:
        """The mean twist's magnitude that best explains the stretch pattern through the
        surfaces' own Gaussian curvature (:func:`.membrane.stretch_misfit`): ``at_magnitude``
        (magnitude → fine positions, a twist family) at 0, ½, 1 and 1½ times the reading's
        square, a quadratic in the square through their misfits (K is linear in it), its minimum
        held within [0, 2] times the reading's square."""
        t_read = reading.twist ** 2
        squares = _REFINE_SQUARES
        rss = [self._stretch_rss(at_magnitude(math.sqrt(t * t_read)), stretch, valid) for t in squares]
        a2, a1, _ = _quadratic_fit(np.array(rss))
        if a2 > 0.0 and math.isfinite(a2):
            best = min(max(-a1 / (2.0 * a2), 0.0), 2.0)
        else:
            best = float(squares[int(np.argmin(rss))])
        return math.sqrt(best * t_read)

    def _stretch_twist(self, surf: Surface, mirror: Callable[[], Surface | None], turning, stretch, valid,
                       product_fields, positions_at, base_shift: float, twist_sign, eu, el, sigma_f: float, chi0: float,
                       tell: float, info: dict, twist_mean: float | None = None, measured_fields=None,
                       reading: TwistReading | None = None, chi2_noise: float = 1.0,
                       carried: bool = False) -> StretchTwist | None:
        """The stretch pattern's twist (docs/reconstruction.md): a film loaded along its normal
        has the Gaussian curvature its stretch pattern says, and with the measured curvatures
        k_u, k_v that fixes the square of the mean twist: mean(k_u k_v − τ²) = K
        (:meth:`_twist_reading`: the free-edge membrane's reading, else the trace's interval).
        Where the interval allows no twist and the answer has none, the answer stands (the
        least-shear prior decides) and, unless something refines the reading, the twists it
        allows join σ (:meth:`_open_to_top`).  Else the membrane's reading is refined on the
        answer's own family with each member's exact Gaussian curvature
        (:meth:`_refine_twist`); an answer off the estimate is modelled afresh there.  The sign
        is not read from the stretch: of the two signs the one whose surface explains the stretch
        pattern better is the answer (by twice the misfit, for an answer that had a sign of its
        own), the other the mirror unless
        the gauges reject it (χ² worse by ``tell`` and by the answer's own misfit: the forward
        model is kinematic, the film is not); the interval's ends are the twist's spread in
        ``node_sigma``.  ``twist_mean``: the answer's mean twist over the cells (at zero shift
        of ``positions_at``); ``measured_fields``: the fields of the measured data (the reading's
        input); ``reading``: the reading, where it was taken already; ``chi2_noise``: the χ² per
        gauge the noise alone leaves in the general model's answers (the posterior check's):
        where both signs read the gauges within it, their χ² difference rejects neither.
        ``mirror``: the mirror image the posterior check found beside the answer, as a function
        (decided when called; not called where this step puts its own in its place).  Returns
        None where the pattern says nothing, else a :class:`StretchTwist`."""
        fields_read = product_fields if measured_fields is None else measured_fields  # the reading's input
        if reading is None:
            reading = self._twist_reading(stretch, valid, fields_read, sigma_f)
        c0 = surf.diagnostics.twist_constant
        if twist_mean is None:
            twist_mean = float(np.asarray(product_fields[2])[self.grid.inner].mean()) + c0 - base_shift
        m0 = twist_mean + base_shift  # the answer's (a swapped mirror sits at base_shift on the family)
        if reading is None:
            return self._unread_twist(surf, mirror(), m0, base_shift, positions_at, twist_sign, stretch, valid,
                                      fields_read, sigma_f, chi0, info)
        m_lo, m_hi, magnitude = reading.low, reading.high, reading.twist
        # a twist below the mirror floor bends nothing the elements would see
        if m_hi * self._half_diagonal2 / 2.0 <= MIRROR_FLOOR_MM:
            return None
        info["stretch_twist"] = (round(m0, 7), round(m_lo, 7), round(m_hi, 7))
        info["stretch_reading"] = (reading.source, round(reading.poisson, 3), round(reading.residual, 3), round(reading.twist, 7))
        sign = float(twist_sign) if twist_sign is not None else (math.copysign(1.0, m0) if m0 != 0.0 else 1.0)
        sign_open = twist_sign is None

        def within(low: float, high: float) -> bool:
            return low <= abs(m0) <= high and (sign_open or m0 * sign >= 0.0)

        membrane = reading.source == "membrane"
        decided = False  # a twist the refined reading gives where its interval allows none too
        stretch_sd = self._stretch_sd(sigma_f)

        def about(magnitude: float) -> tuple[float, float]:
            # the reading's width (in the twist's square) kept about a refined magnitude
            half = 0.5 * (reading.high ** 2 - reading.low ** 2)
            return math.sqrt(max(magnitude ** 2 - half, 0.0)), math.sqrt(magnitude ** 2 + half)

        if within(m_lo, m_hi) and m_lo <= 0.0:
            # The pattern allows no twist too (a sphere): the answer stands, unless the data have
            # not decided between none and the refined reading's twist (:meth:`_twist_left_open`)
            left = self._twist_left_open(reading, m0, sign, sign_open, base_shift, positions_at, stretch, valid,
                                         fields_read, carried, info, sigma_f)
            if left is None:
                return None
            if isinstance(left, _LeftOpen):
                # the answer stays; where the reading's interval reaches none by less than the
                # noise reaches, other frames clear it and move to the refined twist
                ends = left.ends
                # (a reading left open without its refinement moves no frame: nothing flips)
                flips = "stretch_twist_refined" in info and self._flip_within_noise(reading, fields_read, sigma_f)
                refined = float(info["stretch_twist_refined"][0]) if flips else 0.0
                if flips:
                    info["stretch_twist_contested"] = True
                return StretchTwist(surf, mirror(), base_shift,
                                    _memo(lambda: _half_reach(positions_at, base_shift, ends)), chi0, positions_at, 0.0,
                                    (sign * refined - m0,) if flips else (), left.to_top)
            magnitude, decided = left, True
            m_lo, m_hi = about(magnitude)
        elif membrane:
            # The reading's K is k_u k_v − τ² of the fields, a few percent off the surface's own
            # (the metric, the slopes): the twist's square is read again on the answer's family
            # with each member's exact Gaussian curvature, the reading's width kept about it.
            # (Refined to where zero twist is allowed too, the answer stays, but the data have not
            # decided: the twists up to the interval's top join its σ below.)
            magnitude = self._refine_twist(lambda m: positions_at(base_shift + sign * m - m0), reading, stretch, valid)
            m_lo, m_hi = about(magnitude)
            info["stretch_twist_refined"] = (round(magnitude, 7), round(m_lo, 7), round(m_hi, 7))
            # Refined to where zero twist is allowed too, but above UNDECIDED_SHARE of the
            # reading's top (a saddle of R 286 mm 7° off the grid lines on a 12×12 sheet refined
            # to 0.69-0.84 of its 0.81·10⁻³/mm, while the least-shear answer kept none and was
            # 1.0 mm off): the twist is decided, the answer moves to it below (both signs, the
            # other the mirror unless the gauges reject it)
            decided = magnitude > UNDECIDED_SHARE * reading.high
        shift, chi = base_shift, chi0
        other: tuple[Surface, float, int] | None = None  # the other sign's candidate, its χ² and gauges counted
        contested: tuple[float, ...] = ()  # shifts to the answer the decision's other branch gives
        # Where the membrane's reading needs a twist, the least-shear prior has no say: an answer
        # off its estimate by more than MOVE_SHARE moves to it (within the interval too; the
        # trace's interval has no estimate, only ends)
        off = membrane and (m_lo > 0.0 or decided) and abs(abs(m0) - magnitude) > self._move_threshold(
            magnitude, reading, product_fields, sigma_f, carried)
        signs = (sign, -sign) if sign_open else (sign,)
        if membrane and sign_open and m_lo > 0.0 and not off and within(m_lo, m_hi):
            # The answer's twist is the pattern's; its sign is the model's.  Its mirror image on
            # its family is tried against the stretch pattern as well: a mirror that explains the
            # stretch with half the answer's misfit is modelled afresh as the answer.
            r_here = self._stretch_residual(positions_at(shift), stretch, valid)
            r_flipped = self._stretch_residual(positions_at(shift - 2.0 * m0), stretch, valid)
            here, flipped = float(r_here @ r_here), float(r_flipped @ r_flipped)
            info["stretch_sign_rss"] = (float(f"{here:.4g}"), float(f"{flipped:.4g}"))
            if flipped <= MEMBRANE_SIGN_RATIO * here and _sign_beyond_noise(r_here, r_flipped, stretch_sd):
                # (a carried sign is weighed again against the other, each modelled afresh at
                # its own twist: the mirror on a family whose fields were fitted to the carried
                # twist is no model of the other sign where that twist lags a sheet that changes
                # shape (a 5×5 saddle at 60° whose radius grew 0.5 % a frame, 90 to 110 mm:
                # 10 sign changes in 40 frames, each 3.6 mm off, flagged; now none))
                off, signs = True, ((sign, -sign) if carried else (-sign,))
        if off or not within(m_lo, m_hi):
            # modelled afresh at the reading's twist (the family above keeps the fields the defect
            # correction fitted to the old twist), both signs where none is given
            cands, dof = self._afresh_by_sign(signs, magnitude, reading, surf, turning, stretch, valid, sigma_f, eu, el,
                                              refined_sign=sign)
            if len(cands) > 1:
                if membrane:
                    # the sign whose surface explains the stretch pattern better (it was the right
                    # one in 10 of 11 turned elastic saddles measured, the kinematic χ² in none)
                    info["stretch_sign_rss"] = (float(f"{cands[0].rss:.4g}"), float(f"{cands[1].rss:.4g}"))
                    # (an answer that carries the frame before's sign keeps it unless the other
                    # explains the pattern with MEMBRANE_SIGN_RATIO of its misfit, as a mirror on
                    # the family must: a held 12×12 saddle flipped to the wrong sign on a frame
                    # whose twist was read afresh, and kept it)
                    # (and only by more than the noise could make the difference: a 5×5 ν 0.3
                    # saddle of R 150-272 mm at 35-55°, whose sign the pattern does not tell,
                    # took the wrong one on a difference of a third of the noise's s.d.)
                    if (cands[1].rss < (MEMBRANE_SIGN_RATIO if carried else 1.0) * cands[0].rss
                            and _sign_beyond_noise(cands[0].residual, cands[1].residual, stretch_sd)):
                        cands.reverse()
                elif cands[1].chi2 < cands[0].chi2 - (0.0 if abs(m0) <= 0.5 * m_lo else tell):
                    # the trace: the answer's own sign stands where it has a twist of the
                    # interval's order unless the other reads the gauges clearly better
                    cands.reverse()
            chi_t, sg, cand, family, _, own = cands[0]
            if own != magnitude:  # the winner's own twist: the reading's width kept about it
                magnitude = own
                m_lo, m_hi = about(magnitude)
                info["stretch_twist_refined"] = (round(magnitude, 7), round(m_lo, 7), round(m_hi, 7))
            if chi_t > chi0 + max(tell, 0.5 * chi0) and not self._fits_within_present_noise(
                    chi0, chi_t, dof, chi2_noise, turning, valid, sigma_f) and not (
                    chi2_noise > 1.0 and chi_t <= self._noise_reach(cands[0], eu, el, turning, valid, sigma_f, info)):
                # the gauges reject the pattern's twist (the film is not what the model of the
                # stretch assumes): the answer stays, its σ reaching to the pattern's reading
                info["stretch_twist_rejected"] = round(chi_t / max(dof, 1), 3)
                gap = np.linalg.norm(cand._coeffs[..., 0, :] - surf._coeffs[..., 0, :], axis=-1)
                return StretchTwist(surf, mirror(), base_shift, _memo(lambda: 0.5 * gap), chi0, positions_at, 0.0)
            info["stretch_twist_moved"] = round(sg * magnitude - m0, 7)
            if len(cands) > 1:
                other = (cands[1].surface, cands[1].chi2, dof)
            if membrane and within(0.0, reading.high) and self._flip_within_noise(reading, fields_read, sigma_f):
                # moved on a reading whose interval cleared none by less than the noise reaches:
                # on other frames it reaches none, and the answer stays
                contested = (m0 - sg * magnitude,)
                info["stretch_twist_contested"] = True
            sign = sg
            surf, chi, shift, m0 = cand, chi_t, 0.0, sg * magnitude
            positions_at = family
        if membrane and (m_lo > 0.0 or decided):
            # where the next frame's general model starts (:meth:`_carried_twist`)
            info["stretch_estimate"] = (sign, round(abs(m0), 7))

        def spread() -> np.ndarray:
            # the twists the reading allows: 3 s.d. reach past the farther end; of either sign
            # where the reading allows none too and nothing tells the sign (no mirror is tried
            # below: a stretch is even in the twist).  A 5×5 film pre-stretched 5 % on a dome
            # turned 27° off the rows (k_uv 0.005 /mm) was moved from the general model's twist, beyond the
            # trace's interval [0, 0.0069], to its middle with the model's sign, the wrong one:
            # 1.5 mm off with σ 0.55, 1.58 times 3σ + 0.05 mm; now σ 1.31, 0.88 times
            ends = [sign * m - m0 for m in (m_lo, m_hi)]
            if sign_open and m_lo <= 0.0 and not decided:
                ends.append(-sign * m_hi - m0)
            return _half_reach(positions_at, shift, ends)

        if sign_open and (m_lo > 0.0 or decided):
            # The pattern needs a twist whose sign nothing tells (the stretch of a saddle is even
            # in its turn; which sign's surface fits it better was wrong once in 11): the other
            # sign is the mirror unless the gauges reject it.
            kept = self._pattern_mirror(surf, other, positions_at, shift, sign, m0, eu, el, sigma_f, chi, tell,
                                        chi2_noise, info)
        else:
            kept = mirror()
        noise_sd = reading.noise_sd if membrane and math.isfinite(reading.noise_sd) else 0.0
        return StretchTwist(surf, kept, shift, _memo(spread), chi, positions_at, noise_sd, contested)

    def _move_threshold(self, magnitude: float, reading: TwistReading, product_fields, sigma_f: float,
                        carried: bool) -> float:
        """How far (1/mm) an answer's mean twist may lie from the stretch pattern's refined
        estimate ``magnitude`` before it is modelled afresh there: MOVE_SHARE of it; for an answer
        that carries the frame before's twist, also CARRIED_MOVE_SIGMAS s.d. of the estimate's own
        noise (the curvature product's over 2|c|, with the reading's): two estimates of a still
        sheet differ by that much, and moving on it bought nothing (a held 12×12 saddle of R 260
        mm at 8°, whose estimate scatters by 5 %: half its frames were modelled afresh, 21 ms
        against 8, the errors alike)."""
        share = MOVE_SHARE * magnitude
        if not carried or magnitude <= 0.0:
            return share
        return max(share, CARRIED_MOVE_SIGMAS * self._estimate_sd(magnitude, reading, product_fields, sigma_f))

    def _flip_within_noise(self, reading: TwistReading, fields, sigma_f: float) -> bool:
        """Whether the noise could move the reading's lower end across none (so that frames of
        the same sheet take the pattern's twist on some and leave it open on others): its square
        before clipping within CONTESTED_SIGMAS s.d. of the mean curvature product of ``fields``
        (the twist's square is read as that product less the pattern's K)."""
        low_square = reading.low_square
        return math.isfinite(low_square) and abs(low_square) <= CONTESTED_SIGMAS * self._product_sd(fields, sigma_f)

    def _estimate_sd(self, magnitude: float, reading: TwistReading, product_fields, sigma_f: float) -> float:
        """The s.d. (1/mm) of a refined twist estimate ``magnitude`` from the noise: the mean
        curvature product's (its s.d. over 2|c|, :meth:`_product_stats`) with the reading's own."""
        reading_sd = reading.noise_sd if math.isfinite(reading.noise_sd) else 0.0
        return math.hypot(self._product_sd(product_fields, sigma_f) / (2.0 * magnitude), reading_sd)

    def _twist_left_open(self, reading: TwistReading, m0: float, sign: float, sign_open: bool, base_shift: float,
                         positions_at, stretch, valid, fields, carried: bool, info: dict,
                         sigma_f: float) -> _LeftOpen | float | None:
        """Where the stretch pattern's interval allows no twist too and the answer's twist lies in
        it: None where the answer stands as it is; else the shifts on ``positions_at``'s family
        whose twists the data leave open (their spread joins node_sigma); or, for an answer that
        carries the frame before's twist which the refinement confirms, the decided magnitude.
        A trace's interval gives None, and ``info["trace_open_twist"]`` where it holds the twist
        the curvature product alone would be (joined to σ as the product's open twist).

        The membrane's reading, refined on the answer's own family, may still say a twist: the
        data have not decided between none and that one, and the twists up to it, of either sign
        the data leave open, join node_sigma.  A refined twist below UNDECIDED_SHARE of the
        interval's top is the interval's own noise (a ν 0.3 saddle turned 6° from the grid
        refines to 0.54-0.56 of it, its true twist 0.7; noisy spheres to 0-0.18)."""
        m_hi = reading.high
        base = _mean_twist_terms(fields, self.grid.inner)[1]
        saddle_like = base < 0.0
        if reading.source != "membrane":
            # The trace's interval reads no ν and no sign: where it allows none and also the
            # twist the curvature product alone would be (a developable sheet: K = 0), beyond the
            # product's noise, the stretch has not decided between them either, and that twist
            # joins σ (a 12×12 film pre-stretched 5 % on a cylinder of R 179 mm 6.8° off the
            # columns: its stretch varies with the pre-stretch as a doubly curved sheet's would,
            # no twist was taken or left open on one noisy frame of 150, 0.98 mm off with σ 0.063,
            # 9.5 times the bound)
            # (`extra["trace_open_twist"]`, reached as the product's open twist is, _posterior)
            product_twist = math.sqrt(base) if base > 0.0 else 0.0
            if (base > PRODUCT_OPEN_SIGMAS * self._product_sd(fields, sigma_f) and product_twist <= m_hi
                    and abs(product_twist - abs(m0)) * self._half_diagonal2 / 2.0 > MIRROR_FLOOR_MM):
                info["trace_open_twist"] = round(product_twist, 7)
            return self._open_to_top(m_hi, m0, sign, sign_open, info)
        if reading.twist <= 0.5 * m_hi and not saddle_like:
            # (the reading itself below half the interval's top: spheres read 0.15-0.45 of
            # it, that saddle 0.70; the refinement would double a warm sphere frame's cost.
            # A sheet whose curvature product is negative, as a saddle's near the grid lines,
            # has nothing but the stretch to tell its twist: it is refined whatever the
            # reading (a 12×12 saddle of R 286 mm at 83° read 0.22 of the top on one draw in
            # 20, its twist 0.84 of it: 1.0 mm off with σ 0.050, 10.9 times the bound))
            return self._open_to_top(m_hi, m0, sign, sign_open, info)
        mag = self._refine_twist(lambda m: positions_at(base_shift + sign * m - m0), reading, stretch, valid)
        info["stretch_twist_refined"] = (round(mag, 7), 0.0, round(mag, 7))
        refined = mag
        if mag <= UNDECIDED_SHARE * m_hi:
            # The refinement finds no twist where the reading itself said one: two readings
            # of the same pattern disagree, so the twists up to the reading's stay open (a
            # 16×16 saddle of R 293 mm 1° off the grid lines read 0.58 of the top, refined to
            # none, and was 0.28 mm off with σ 0.06); up to the larger of the two
            mag = max(mag, reading.twist)
        if mag * self._half_diagonal2 / 2.0 <= MIRROR_FLOOR_MM:
            return None
        # (the answer stays: moved to the refined twist, a noisy 5×5 sphere and an aligned
        # saddle went 0.3 mm off, refined to 0.4-0.5 of the top)
        if not (carried and m0 != 0.0 and abs(abs(m0) - refined) <= 0.25 * abs(m0)):
            # the twists left open reach past the estimate by OPEN_SIGMAS s.d. of its own noise (a
            # held 12×12 saddle of R 286 mm at 83°, twist 0.0008 /mm, refined on the untwisted
            # answer's family to 0.00046 on one frame in 40: 1.05 mm off, 1.21 times 3σ + 0.05 mm)
            mag += OPEN_SIGMAS * self._estimate_sd(mag, reading, fields, sigma_f)
            return _LeftOpen(_shifts_to(mag, m0, sign, sign_open), False)
        # The answer carries the frame before's twist (:meth:`_carried_twist`) and the
        # refinement confirms it: decided, and its sign kept unless the stretch clearly prefers
        # the other (a held 12×12 saddle of R 286 mm at 83° went between its twist and none frame
        # by frame, 0.05 and 1.0 mm off)
        return mag

    def _unread_twist(self, surf: Surface, mirror: Surface | None, m0: float, base_shift: float, positions_at,
                      twist_sign, stretch, valid, fields, sigma_f: float, chi0: float,
                      info: dict) -> StretchTwist | None:
        """Where the stretch has a pattern (its trace spread beyond 3 s.d. of its noise) that
        neither reading explains (friction on a dome, a bump on one) on a sheet that is a dome on
        its own scale: nothing tells its twist between none and the one that would leave it no
        Gaussian curvature (c² = mean k_u k_v − the spread of τ₀, a developable sheet's), and
        both ends, of either sign where none is told and no mirror stands beside the answer,
        join node_sigma (``extra["stretch_unread_twist"]``: c).  A dome on its own scale: the
        product of the mean curvatures at least DOME_SHARE of c², and c² beyond its noise.  None
        otherwise, and with ``twist_prior`` "none": a pattern within its noise says K is about
        none, which the least-shear prior takes (a cylinder); a bump or a ridge on a flat sheet
        bends it both ways, its mean curvatures about none, and has flat cells, whose stretch
        the prior reads right (reached there, 12×12 and 16×16 bumps' σ went 0.36-0.59 → 1.2-2.5
        mm for errors of 0.04-0.10).  A 5×5 film on a dome k_uu = 0.010, k_uv = 0.003, k_vv =
        0.006 /mm with a 2 mm bump on it was 0.60 mm off with σ 0.28 (2.2 times 3σ + 0.05 mm); a
        12×12 film with friction 10⁻³ on a dome k_uu = 0.0052, k_uv = 0.0008, k_vv = 0.0033 /mm
        0.97 mm off with σ 0.06 (9.5-10 times)."""
        if self.twist_prior == "none":
            return None
        k_u, k_v, _ = (np.asarray(f)[self.grid.inner] for f in fields)
        base = _mean_twist_terms(fields, self.grid.inner)[1]
        if not float(np.mean(k_u)) * float(np.mean(k_v)) >= DOME_SHARE * base:
            return None
        if not base > PRODUCT_OPEN_SIGMAS * self._product_sd(fields, sigma_f):
            return None
        # (the trace's own test of a pattern, airy_curvature_range's)
        trace = stretch_trace(stretch, valid)
        noise = 3.0 * math.sqrt(2.0) * self._stretch_sd(sigma_f)
        if not np.isfinite(trace).any() or not float(np.nanstd(trace)) > noise:
            return None
        top = math.sqrt(base)
        if top * self._half_diagonal2 / 2.0 <= MIRROR_FLOOR_MM:
            return None
        info["stretch_unread_twist"] = round(top, 7)
        sign = float(twist_sign) if twist_sign is not None else (math.copysign(1.0, m0) if m0 != 0.0 else 1.0)
        signs = (sign, -sign) if twist_sign is None and mirror is None else (sign,)
        ends = [m - m0 for m in (0.0, *(sg * top for sg in signs))]
        return StretchTwist(surf, mirror, base_shift, _memo(lambda: _half_reach(positions_at, base_shift, ends)), chi0,
                            positions_at, 0.0, keeps_rest=True)

    def _open_to_top(self, m_hi: float, m0: float, sign: float, sign_open: bool, info: dict) -> _LeftOpen | None:
        """The shifts to the twists a reading leaves open where the answer stands and nothing
        refines it: to the interval's top, of either sign where none is told (None with
        ``twist_prior`` "none": the sheet is known to carry none).  A dome's twist is read
        only through its Gaussian curvature (k_u k_v − τ²), and the reading does not tell a
        twist up to its top from none: on a 5×5 film on a mold, a dome k_uu = k_vv = 0.0143 /mm
        with k_uv = 0.002 (principal axes at 45°) read 0.00147 of a top of 0.00353, a sphere of
        R 70 mm 0.00135 of 0.00377, and the answer kept none, 0.34 mm off with σ 0.06."""
        if self.twist_prior == "none":
            return None
        info["stretch_twist_open"] = round(m_hi, 7)
        return _LeftOpen(_shifts_to(m_hi, m0, sign, sign_open), True)

    def _afresh_by_sign(self, signs, magnitude: float, reading: TwistReading, surf: Surface, turning, stretch, valid,
                        sigma_f: float, eu, el, refined_sign: float) -> tuple[list["_SignCandidate"], int]:
        """The answer modelled afresh at the reading's twist ``magnitude`` with each of ``signs``
        (the family of the answer keeps the fields the defect correction fitted to the old
        twist): one :class:`_SignCandidate` per sign, and the gauges counted.  ``refined_sign``:
        the sign of the family a membrane reading's ``magnitude`` was refined on; a sign other
        than it, or either of two, is refined on its own family."""
        membrane = reading.source == "membrane"
        cands: list[_SignCandidate] = []
        dof = 0
        for sg in signs:
            fresh, own = self._fresh(turning, stretch, valid, sigma_f, sg, (eu, el), sg * magnitude), magnitude
            if membrane and (len(signs) > 1 or sg != refined_sign):
                # Each sign is weighed at the twist its own family explains best: the refined
                # magnitude above was read on the answer's family, whose sign may be the wrong
                # one, and the two signs prefer different magnitudes (a saddle R 74 mm at 32°:
                # at 0.0120 /mm, the wrong sign's best, it read the stretch 5 times better
                # than the right one; at 0.0114, the right sign's, 15 times worse).
                family_sg = fresh[5]
                own = self._refine_twist(lambda m: family_sg(sg * (m - magnitude)), reading, stretch, valid)
                if abs(own - magnitude) > SIGN_OWN_SHARE * magnitude:
                    fresh = self._fresh(turning, stretch, valid, sigma_f, sg, (eu, el), sg * own)
                else:
                    own = magnitude
            cand = self._surface(fresh[0], surf._fine_sigma_fn, _with_twist(surf.diagnostics, fresh[1]))
            residual = self._stretch_residual(fresh[0], stretch, valid) if membrane else np.zeros(0)
            chi_c, dof = misfit(cand, self._layout, eu, el, sigma_f)[:2]
            cands.append(_SignCandidate(chi_c, sg, cand, fresh[5], residual, own))
        return cands, dof

    def _fits_within_present_noise(self, chi_a: float, chi_b: float, dof: int, chi2_noise: float, turning, valid,
                                   sigma_f: float) -> bool:
        """Whether both answers read the gauges within what the noise the data carry leaves
        (:func:`_within_noise` at the χ² of that noise: the stated one's, scaled by the square of
        the data's own turning noise over the stated, at most 1): then their χ² difference rejects
        neither.  A 12×12 saddle on a mold, R 221 mm at 39°, read 0.58 per gauge at the
        least-shear twist after two defect passes and 0.99 at the stretch pattern's (0.003534
        and 0.00419 /mm): the veto kept the first, 0.83 mm off, on one noisy frame in 20 (the
        other 19, whose defect passes left the first at 1.8, moved, 0.03 mm off).  Quieter data
        than stated keep the veto (their χ² differences mean what they say)."""
        level = self._present_noise_level(turning, valid, sigma_f)
        return _within_noise(chi_a, chi_b, dof, chi2_noise * level * level)

    def _present_noise_level(self, turning, valid, sigma_f: float) -> float:
        """The turning noise the data carry (:func:`.productnoise.turning_noise_estimate`) over
        the stated strain noise ``sigma_f``'s, at most 1 (1 where it cannot be estimated)."""
        present = turning_noise_estimate(turning, valid)
        return min(present / self._turning_sd(sigma_f), 1.0) if math.isfinite(present) else 1.0

    def _noise_reach(self, cand: "_SignCandidate", eu, el, turning, valid, sigma_f: float, info: dict) -> float:
        """The χ² (over the gauges counted) up to which strain noise alone reaches in an answer
        modelled afresh at ``cand``'s sign and twist, measured on the candidate's own forward
        strains plus one noise draw (seeded by the frame's strains: replay gives the same bytes;
        ``turning``, ``valid``: the frame's own units, whose noise sets the draw's),
        plus two of the χ² distribution's s.d.  Where the general model's answers leave the noise
        a χ² above one per gauge (large sheets), the noise's misfit grows with how far the
        held twist lies from what the noisy fields' own least-shear twist would be, so a χ²
        difference of a few per gauge between two twists proves nothing: a 32×32 saddle of
        R 431 mm at 150° read 2.1 per gauge at the wrong sign's least-shear twist and 5.5 at
        the right sign's (0.24 mm off), while the right one's own strains with another noise draw
        read 8.5-12.8 at its twist, and 0.33 without noise.  0 (the veto stands) where the
        frame's own turning noise is below NOISE_REACH_LEVEL of the stated."""
        # Only where the data carry the noise they are told of (its estimate from the data at
        # least NOISE_REACH_LEVEL of the stated): quieter data keep the gauges' veto, whose χ²
        # differences then mean what they say (a clean 32×32 sphere cap told the sensor's noise
        # was moved to a trace's twist, 7 mm off, with the veto lifted)
        level = self._present_noise_level(turning, valid, sigma_f)
        if level < NOISE_REACH_LEVEL:
            info["noise_reach_chi2_per_gauge"] = (None, round(level, 3))
            return 0.0
        _, dof, fu, fl = misfit_and_strains(cand.surface, self._layout, eu, el, sigma_f)
        seed = int.from_bytes(hashlib.blake2b(np.ascontiguousarray(eu).tobytes(), digest_size=8).digest(), "little")
        rng = np.random.default_rng(seed)
        sd = level * sigma_f
        nu = np.where(np.isnan(eu), np.nan, fu + rng.normal(0.0, sd, fu.shape))
        nl = np.where(np.isnan(el), np.nan, fl + rng.normal(0.0, sd, fl.shape))
        sim_turning, sim_stretch, sim_valid = unit_data(nu, nl, self.h_upper, self.h_lower, self.gauge_length)
        twist = float(cand.sign) * float(cand.magnitude)
        sim = self._fresh(sim_turning, sim_stretch, sim_valid & valid, sigma_f, cand.sign, (nu, nl), twist)
        chi_s, dof_s, _ = misfit(self._candidate(sim[0]), self._layout, nu, nl, sigma_f)
        per_gauge = chi_s / max(dof_s, 1)
        info["noise_reach_chi2_per_gauge"] = (round(per_gauge, 3), round(level, 3))
        return dof * per_gauge * (1.0 + 2.0 * math.sqrt(2.0 / max(dof, 1)))

    def _pattern_mirror(self, surf: Surface, other, positions_at, shift: float, sign: float, m0: float, eu, el,
                        sigma_f: float, chi: float, tell: float, chi2_noise: float, info: dict) -> Surface | None:
        """The other sign of a twist the stretch pattern needs (``other``: the other sign modelled
        afresh, (surface, χ², gauges counted), else its mirror on the answer's family), unless the
        gauges reject it or it is the answer's own surface."""
        if other is None:
            target = -sign * abs(m0)
            cand = self._surface(positions_at(shift + target - m0), surf._fine_sigma_fn,
                                 _with_twist(surf.diagnostics, surf.diagnostics.twist_constant + target - m0))
            chi_m, dof = misfit(cand, self._layout, eu, el, sigma_f)[:2]
        else:
            cand, chi_m, dof = other
        info["mirror_chi2_per_gauge"] = round(chi_m / max(dof, 1), 3)
        # as in the posterior check: where both signs read the gauges as well as the noise
        # alone would, the kinematic forward model's preference proves nothing (a saddle on a
        # mold with friction, R 85 mm at 54°: the wrong sign read 0.10 per gauge, the right
        # one 0.43, and the answer was 4.4 mm off with nothing said)
        if (chi_m <= chi + max(tell, chi) or _within_noise(chi, chi_m, dof, chi2_noise)) and _differs(surf, cand):
            return cand
        return None
