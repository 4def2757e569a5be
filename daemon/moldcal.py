"""Per-gauge gauge factors and per-unit layer offsets from known poses (pure functions).

The sheet is put in poses whose layer strains are known in closed form:

- flat at rest (every strain 0; it is also the tare: base resistances),
- flat and stretched by a known s in a frame (every neutral-plane strain s, no bending),
- wrapped on cylinders of known radius R (+ convex, − concave) along the rows or the columns:
  a gauge whose direction makes the angle θ with the circumference reads, on its layer at signed
  offset h (+h_u upper, −h_l lower), h·cos²θ/R (to first order in h/R; the isometric wrap has no
  neutral-plane strain), plus a membrane strain of second order in the curvature that a real
  (elastic) film shows where the bending energy compresses it: q·(cos²θ/R)².

With the factory gauge factor GF_f of HELLO and the tared base resistance, a gauge reads
y = (GF/GF_f)·ε.  Per gauge the model is therefore linear in (a, a·h, a·q), a = GF/GF_f:

    y = a·s + (a·h)·t + (a·q)·t²,      t = cos²θ/R the normal curvature along the gauge,

fitted by least squares over the poses.  The mold's placement is not exact: the axis of each
cylinder pose may be off by a few degrees (θ unknown), fitted jointly by alternating the
per-gauge fit with a one-parameter fit per pose.  A cylinder's strains do not depend on where
along or across it the sheet lies, so an off-centre placement changes nothing to fit.

Without a stretched pose a and h are not separable (bending alone gives a·h); the fit then keeps
the nominal offsets and reports the offsets as not determined.

A dome (a sphere cap of known radius R, the film sliding on it: a lubricated mold) gives the
film's Poisson ratio ν, which the elastic prior of the reconstruction needs
(docs/reconstruction.md, "Elastic films").  A film loaded only along its normal has an Airy
stress function with ∇⁴φ = −E·K, and in plane stress tr ε = (1 − ν)·tr σ/E, so

    ∇²(ε_uu + ε_vv) = −(1 − ν)·K,     K = 1/R²,

whatever the sheet's outline: the trace of the stretch is −(1 − ν) r²/(4R²) plus a harmonic
function.  :func:`fit_poisson_ratio` fits c + b·r² + the harmonics up to fourth order (square
symmetry) to the units' stretch (each gauge's mean along its line only adds constants to these
terms), read with the calibrated gauges, and takes ν = 1 + 4R²b.  It is fitted after the gauges,
from the dome pose alone, which the gauge fit leaves out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Pose", "standard_poses", "MoldFit", "fit_mold_calibration", "pose_curvatures", "check_pose",
           "PoissonFit", "fit_poisson_ratio"]

#: The largest axis error the fit looks for (degrees); a placement worse than this is refused
#: by :func:`check_pose` before it gets here.
MAX_AXIS_ERROR_DEG = 20.0


@dataclass(frozen=True)
class Pose:
    """A calibration pose: ``kind`` 'flat', 'stretch', 'cylinder' or 'dome' (a sphere cap)."""

    kind: str
    radius_mm: float = 0.0  # cylinders, domes: + convex (upper layer in tension), − concave
    direction: str = ""  # cylinders: 'rows' (circumference along u) or 'columns' (along v)
    stretch: float = 0.0  # 'stretch': the frame's strain in both directions

    def __post_init__(self) -> None:
        if self.kind not in ("flat", "stretch", "cylinder", "dome"):
            raise ValueError(f"pose kind must be 'flat', 'stretch', 'cylinder' or 'dome', got {self.kind!r}")
        if self.kind == "dome" and not (math.isfinite(self.radius_mm) and abs(self.radius_mm) >= 20.0):
            raise ValueError(f"a dome pose needs a radius of at least 20 mm (signed), got {self.radius_mm!r}")
        if self.kind == "cylinder":
            if not (math.isfinite(self.radius_mm) and abs(self.radius_mm) >= 5.0):
                raise ValueError(f"a cylinder pose needs a radius of at least 5 mm (signed), got {self.radius_mm!r}")
            if self.direction not in ("rows", "columns"):
                raise ValueError(f"a cylinder pose runs along 'rows' or 'columns', got {self.direction!r}")
        if self.kind == "stretch" and not (math.isfinite(self.stretch) and 0.005 <= self.stretch <= 0.3):
            raise ValueError(f"a stretch pose needs a stretch of 0.005..0.3, got {self.stretch!r}")

    @property
    def title(self) -> str:
        if self.kind == "flat":
            return "flat sheet at rest"
        if self.kind == "stretch":
            return f"flat sheet stretched {100 * self.stretch:g} % in both directions"
        side = "convex" if self.radius_mm > 0 else "concave"
        if self.kind == "dome":
            return f"{side} dome (sphere) of radius {abs(self.radius_mm):g} mm, lubricated, the sheet centred on it"
        across = "u (the rows)" if self.direction == "rows" else "v (the columns)"
        return f"{side} cylinder of radius {abs(self.radius_mm):g} mm, its circumference along {across}"


def standard_poses(radii_mm: tuple[float, ...] = (40.0, 80.0), stretch: float = 0.05,
                   dome_mm: float = 0.0) -> list[Pose]:
    """Flat, stretched (if ``stretch``), then convex and concave cylinders of every radius along
    the rows and along the columns, then a convex dome of radius ``dome_mm`` (if given: the
    film's Poisson ratio)."""
    poses = [Pose("flat")]
    if stretch:
        poses.append(Pose("stretch", stretch=stretch))
    for direction in ("rows", "columns"):
        for r in radii_mm:
            for sign in (1.0, -1.0):
                poses.append(Pose("cylinder", radius_mm=sign * float(r), direction=direction))
    if dome_mm:
        poses.append(Pose("dome", radius_mm=float(dome_mm)))
    return poses


def pose_curvatures(pose: Pose, axis_error_deg: float = 0.0) -> tuple[float, float]:
    """Normal curvature (1/mm) along u and along v of a pose whose mold axis is off by
    ``axis_error_deg``."""
    if pose.kind != "cylinder":
        return 0.0, 0.0
    c2 = math.cos(math.radians(axis_error_deg)) ** 2
    k = 1.0 / pose.radius_mm
    return (k * c2, k * (1.0 - c2)) if pose.direction == "rows" else (k * (1.0 - c2), k * c2)


def _regressors(poses: list[Pose], errors_deg: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(P, 2 directions, 3) regressors (s, t, t²) of every pose for a u- and a v-gauge."""
    x = np.zeros((len(poses), 2, 3))
    for p, (pose, err) in enumerate(zip(poses, errors_deg)):
        ku, kv = pose_curvatures(pose, float(err))
        for d, k in enumerate((ku, kv)):
            x[p, d] = (pose.stretch if pose.kind == "stretch" else 0.0, k, k * k)
    return x


@dataclass
class MoldFit:
    """The fit's result; arrays shaped like the gauges (2 layers, 2 directions, N, M) or the
    units (2, N, M)."""

    gauge_factor: np.ndarray  # (2, 2, N, M)
    gauge_factor_sd: np.ndarray  # (2, 2, N, M) one s.d.
    h_upper_mm: np.ndarray  # (2, N, M)
    h_upper_sd_mm: np.ndarray
    h_lower_mm: np.ndarray
    h_lower_sd_mm: np.ndarray
    membrane_q_mm: np.ndarray  # (2, 2, N, M): the second-order stretch coefficient q
    residual_rms: np.ndarray  # (2, 2, N, M) strain: rms misfit of every gauge over the poses
    axis_error_deg: np.ndarray  # (P,) the fitted axis error of each pose (0 for flat ones)
    offsets_determined: bool
    method: str
    notes: list[str] = field(default_factory=list)


def _fit_gauges(y: np.ndarray, x: np.ndarray, sigma: float, with_stretch: bool,
                h_nominal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-gauge least squares.  y (P, 2, 2, N, M) readings; x (P, 2, 3) regressors.
    Returns (coef (3, 2, 2, N, M) = a, a·h, a·q; their s.d.; residual rms)."""
    p_count, _, _, n, m = y.shape
    coef = np.zeros((3, 2, 2, n, m))
    sd = np.zeros_like(coef)
    rms = np.zeros((2, 2, n, m))
    for d in range(2):
        xd = x[:, d, :] if with_stretch else x[:, d, 1:]
        cols = xd.shape[1]
        yd = y[:, :, d].reshape(p_count, -1)  # (P, layers·N·M)
        sol, *_ = np.linalg.lstsq(xd, yd, rcond=None)
        res = yd - xd @ sol
        dof = max(p_count - cols, 1)
        # the misfit's own level, but never below what the measurement noise alone gives
        s2 = np.maximum((res ** 2).sum(axis=0) / dof, sigma ** 2)
        cov = np.linalg.pinv(xd.T @ xd)
        err = np.sqrt(np.outer(np.diag(cov), s2))
        if with_stretch:
            coef[:, :, d] = sol.reshape(3, 2, n, m)
            sd[:, :, d] = err.reshape(3, 2, n, m)
        else:
            # a·h and a·q only; a follows from the nominal offset
            hn = h_nominal[:, d].reshape(-1)
            ah = sol[0]
            coef[0, :, d] = (ah / hn).reshape(2, n, m)
            coef[1, :, d] = ah.reshape(2, n, m)
            coef[2, :, d] = sol[1].reshape(2, n, m)
            sd[0, :, d] = (err[0] / np.abs(hn)).reshape(2, n, m)
            sd[1, :, d] = err[0].reshape(2, n, m)
            sd[2, :, d] = err[1].reshape(2, n, m)
        rms[:, d] = np.sqrt((res ** 2).mean(axis=0)).reshape(2, n, m)
    return coef, sd, rms


def _fit_axis_errors(y: np.ndarray, poses: list[Pose], coef: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Per cylinder pose, the axis error that best explains every gauge given their parameters
    (golden-section search on cos²θ over [cos² MAX, 1]; the sign of θ does not show)."""
    out = current.copy()
    lo = math.cos(math.radians(MAX_AXIS_ERROR_DEG)) ** 2
    for p, pose in enumerate(poses):
        if pose.kind != "cylinder":
            continue

        def misfit(c2: float) -> float:
            err = math.degrees(math.acos(math.sqrt(min(1.0, max(0.0, c2)))))
            ku, kv = pose_curvatures(pose, err)
            total = 0.0
            for d, k in enumerate((ku, kv)):
                pred = coef[1, :, d] * k + coef[2, :, d] * k * k
                total += float(np.nansum((y[p, :, d] - pred) ** 2))
            return total

        a, b = lo, 1.0
        g = (math.sqrt(5.0) - 1.0) / 2.0
        c, d = b - g * (b - a), a + g * (b - a)
        fc, fd = misfit(c), misfit(d)
        for _ in range(40):
            if fc < fd:
                b, d, fd = d, c, fc
                c = b - g * (b - a)
                fc = misfit(c)
            else:
                a, c, fc = c, d, fd
                d = a + g * (b - a)
                fd = misfit(d)
        best = 0.5 * (a + b)
        out[p] = math.degrees(math.acos(math.sqrt(min(1.0, best))))
    return out


def fit_mold_calibration(
    poses: list[Pose],
    readings: list[np.ndarray],
    factory_gauge_factor: np.ndarray,
    h_upper_mm: float,
    h_lower_mm: float,
    noise_sd: float = 1e-5,
    iterations: int = 4,
) -> MoldFit:
    """Fit gauge factors and layer offsets.

    ``readings``: per pose the mean strain (2, 2, N, M) computed with the factory gauge factors
    and the tared base resistances; ``noise_sd`` the s.d. of one such mean (strain).  A gauge with
    NaN in any pose gets NaN parameters.  ValueError names what cannot be fitted."""
    if len(poses) != len(readings) or not poses:
        raise ValueError(f"{len(poses)} poses but {len(readings)} readings")
    y = np.stack([np.asarray(r, dtype=float) for r in readings])
    gf0 = np.asarray(factory_gauge_factor, dtype=float)
    if y.shape[1:] != gf0.shape or gf0.ndim != 4:
        raise ValueError(f"readings shaped {y.shape[1:]} do not match the gauges {gf0.shape}")
    with_stretch = any(p.kind == "stretch" for p in poses)
    for d, name in ((0, "rows"), (1, "columns")):
        radii = {p.radius_mm for p in poses if p.kind == "cylinder" and p.direction == name}
        if len(radii) < 2:
            raise ValueError(f"the fit needs at least two cylinder poses along the {name} (different radii or "
                             f"signs); got {len(radii)}")
    _, _, n, m = gf0.shape
    h_nom = np.empty((2, 2, n, m))
    h_nom[0], h_nom[1] = h_upper_mm, -h_lower_mm
    bad = ~np.all(np.isfinite(y), axis=0)
    y = np.where(bad[None], 0.0, y)
    errors = np.zeros(len(poses))
    for _ in range(max(1, iterations)):
        x = _regressors(poses, errors, (n, m))
        coef, sd, rms = _fit_gauges(y, x, noise_sd, with_stretch, h_nom)
        errors = _fit_axis_errors(y, poses, coef, errors)
    x = _regressors(poses, errors, (n, m))
    coef, sd, rms = _fit_gauges(y, x, noise_sd, with_stretch, h_nom)
    a, ah, aq = coef
    with np.errstate(invalid="ignore", divide="ignore"):
        h = ah / a
        # first-order propagation of the s.d. of a and a·h into h = (a·h)/a
        h_sd = np.abs(h) * np.sqrt((sd[1] / ah) ** 2 + (sd[0] / a) ** 2)
        q = aq / a
    gf = gf0 * a
    gf_sd = gf0 * sd[0]
    notes = []
    if np.any(a <= 0):
        notes.append(f"{int(np.count_nonzero(a <= 0))} gauges fit a gauge factor <= 0 (kept at factory)")
    unusable = bad | ~(a > 0) | ~np.isfinite(a)
    gf = np.where(unusable, gf0, gf)
    gf_sd = np.where(unusable, np.nan, gf_sd)
    h = np.where(unusable, h_nom, h)
    h_sd = np.where(unusable, np.nan, h_sd)
    if not with_stretch:
        h, h_sd = h_nom.copy(), np.full_like(h_nom, np.nan)
        notes.append("no stretched pose: gauge factors assume the nominal layer offsets; offsets not determined")
    if bad.any():
        notes.append(f"{int(np.count_nonzero(bad))} gauges lacked data in some pose (factory values kept)")
    names = ", ".join(_short(p) for p in poses)
    return MoldFit(
        gauge_factor=gf, gauge_factor_sd=gf_sd,
        h_upper_mm=h[0], h_upper_sd_mm=h_sd[0], h_lower_mm=-h[1], h_lower_sd_mm=h_sd[1],
        membrane_q_mm=np.where(unusable, np.nan, q), residual_rms=np.where(bad, np.nan, rms),
        axis_error_deg=errors, offsets_determined=with_stretch,
        method=f"mold fit (linear per gauge, axis errors fitted per pose): {names}", notes=notes,
    )


#: The closed form's own error (small strain, the gauges' averaging along their lines), measured
#: on the emulator's solved films: 0.001–0.014 for ν 0.3–0.48; added to the fit's s.d.
POISSON_MODEL_SD = 0.01


@dataclass(frozen=True)
class PoissonFit:
    """The film's Poisson ratio from a dome pose."""

    poisson: float
    sd: float            # one s.d.: the fit's residuals and the closed form's own error
    residual_rms: float  # strain: the stretch trace's misfit to the model
    units: int


def fit_poisson_ratio(eps_upper: np.ndarray, eps_lower: np.ndarray, h_upper_mm: np.ndarray | float,
                      h_lower_mm: np.ndarray | float, pitch_mm: float, radius_mm: float) -> PoissonFit:
    """ν from calibrated strains (2, N, M) per layer on a dome of radius ``radius_mm`` (see the
    module's text).  ValueError says what cannot be fitted: too few units, or a ν outside
    [0, 0.5), which a film that slid on its mold cannot have (one that stuck to it reads high)."""
    from skinmap.reconstruction.airy import trace_laplacian
    from skinmap.reconstruction.decouple import decouple

    eu, el = np.asarray(eps_upper, float), np.asarray(eps_lower, float)
    if eu.shape != el.shape or eu.ndim != 3 or eu.shape[0] != 2:
        raise ValueError(f"strains must be (2, N, M) per layer, got {eu.shape} and {el.shape}")
    if not (math.isfinite(radius_mm) and abs(radius_mm) >= 20.0):
        raise ValueError(f"the dome's radius must be at least 20 mm, got {radius_mm!r}")
    hu, hl = np.broadcast_to(h_upper_mm, eu.shape), np.broadcast_to(h_lower_mm, eu.shape)
    eps_s = np.full(eu.shape, np.nan)
    for idx in np.ndindex(eu.shape):  # each unit its own calibrated offsets
        if np.isfinite(hu[idx]) and np.isfinite(hl[idx]):
            eps_s[idx] = float(decouple(eu[idx], el[idx], float(hu[idx]), float(hl[idx]))[1])
    fit = trace_laplacian(eps_s[0] + eps_s[1], pitch_mm)  # ValueError: too few units
    # ∇²tr = −(1 − ν)/R²
    scale = radius_mm ** 2
    nu = 1.0 + scale * fit.laplacian
    sd = math.hypot(scale * fit.sd, POISSON_MODEL_SD)
    if not 0.0 <= nu < 0.5:
        raise ValueError(f"the dome reads a Poisson ratio of {nu:.3f}, outside [0, 0.5): the film did not slide on "
                         "the mold (lubricate it) or the mold's radius is not the one given")
    return PoissonFit(nu, sd, fit.residual_rms, fit.units)


def _short(p: Pose) -> str:
    if p.kind == "flat":
        return "flat"
    if p.kind == "stretch":
        return f"stretch {100 * p.stretch:g} %"
    if p.kind == "dome":
        return f"dome {p.radius_mm:+g} mm"
    return f"cylinder {p.radius_mm:+g} mm {p.direction}"


def check_pose(pose: Pose, strains: np.ndarray, h_upper_mm: float, h_lower_mm: float) -> str:
    """Whether mean strains (2, 2, N, M), read with the factory calibration, look like the pose:
    '' if so, else what is wrong (for the user: what to correct).  Bounds are wide (gauge
    factors 15 % and offsets 10 % off are expected) but catch a wrong mold, side or direction."""
    eu, el = np.asarray(strains[0], float), np.asarray(strains[1], float)
    turn = (eu - el) / (h_upper_mm + h_lower_mm)  # (2, N, M) curvature per unit, 1/mm
    stretch = (eu * h_lower_mm + el * h_upper_mm) / (h_upper_mm + h_lower_mm)
    k_u, k_v = np.nanmedian(turn[0]), np.nanmedian(turn[1])
    s_med = float(np.nanmedian(stretch))
    if not np.isfinite(k_u) or not np.isfinite(k_v):
        return "no usable gauges"
    if pose.kind == "stretch":
        # a stretch read through gauge factors 15 % off looks like bending of up to ~0.3·s
        # between the layers: only the median unit is held to flatness
        bend = float(np.nanmedian(np.abs(eu - el)))
        if bend > 0.35 * pose.stretch + 4e-4:
            return f"the sheet is bent (the median unit turns as a radius of {(h_upper_mm + h_lower_mm) / bend:.0f} mm): lay it flat in the frame"
        if not 0.6 * pose.stretch <= s_med <= 1.5 * pose.stretch:
            return f"the sheet reads a stretch of {100 * s_med:.2f} %, not about {100 * pose.stretch:g} %"
        return ""
    if pose.kind == "flat":
        worst = float(np.nanmax(np.abs(turn)))
        if worst > 1.0 / 400.0:
            return (f"the sheet is bent (a unit turns as a radius of {1.0 / worst:.0f} mm; flat needs more than "
                    f"400 mm): lay it flat")
        if abs(s_med) > 2e-3:
            return f"the sheet is stretched ({100 * s_med:.2f} %): release it"
        return ""
    want = 1.0 / pose.radius_mm
    if pose.kind == "dome":
        flat_dirs = [name for name, k in (("u (the rows)", k_u), ("v (the columns)", k_v)) if abs(k) < 0.3 * abs(want)]
        if len(flat_dirs) == 1:
            return f"the sheet does not bend along {flat_dirs[0]}: that is a cylinder, not the dome"
        for name, k in (("u (the rows)", k_u), ("v (the columns)", k_v)):
            if k * want <= 0:
                return f"the sheet does not bend the dome's way along {name}: is it on the dome, this side up?"
            if not 0.6 <= k / want <= 1.6:
                return (f"the sheet bends as a radius of {1.0 / k:.0f} mm along {name}, not {pose.radius_mm:.0f} mm: "
                        "wrong mold or not lying on it")
        return ""
    along, across = (k_u, k_v) if pose.direction == "rows" else (k_v, k_u)
    if abs(along) < 0.3 * abs(want) and abs(across) > 0.5 * abs(want):
        return (f"the sheet bends along the other direction: turn it by 90° so that its {pose.direction} "
                f"follow the mold's circumference (the axis is off)")
    if along * want <= 0:
        side = "convex" if want > 0 else "concave"
        return f"the sheet bends the wrong way for a {side} mold (turn it over)"
    if not 0.6 <= along / want <= 1.6:
        return (f"the sheet bends as a radius of {1.0 / along:.0f} mm along the {pose.direction}, not "
                f"{pose.radius_mm:.0f} mm: wrong mold or not lying on it")
    if abs(across) > abs(along) * math.tan(math.radians(MAX_AXIS_ERROR_DEG)) ** 2 * 1.5 + 1.0 / 2000.0:
        return (f"the mold's axis is far off (across-turning {abs(across / along):.2f} of the along-turning): "
                f"align the sheet's {pose.direction} with the mold's circumference")
    return ""
