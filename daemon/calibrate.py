"""`skinmap calibrate` and `skinmap tare`: the guided procedure around the mold fit.

The procedure prompts for each pose (:func:`skinmap.daemon.moldcal.standard_poses`), waits until
the sheet is static, checks that the readings look like the pose (:func:`check_pose`), takes it,
and finally fits gauge factors and layer offsets and writes the tare and the calibration file.
Nothing is written unless every pose was taken and the fit succeeded.

Its edges are two small interfaces: a :class:`ScanFeed` (resistance scans from the scanner: the
serial link, or anything yielding arrays) and a placer (who puts the sheet in a pose: the user,
prompted on the terminal, or the in-process emulator).
"""
from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from skinmap.strains import gauge_strain
from skinmap.daemon.moldcal import MoldFit, PoissonFit, Pose, check_pose, fit_mold_calibration, fit_poisson_ratio

__all__ = ["CalibrationAborted", "ScanFeed", "LinkFeed", "PromptPlacer", "EmulatedPlacer", "CalibrationRun",
           "take_static", "run_calibration", "tare_problem", "STATIC_TOLERANCE"]

#: Largest change of any gauge's mean strain between the first and the last third of a window
#: for the sheet to count as static (the mean of 10 noisy scans moves by about 3e-5).
STATIC_TOLERANCE = 2e-4


class CalibrationAborted(RuntimeError):
    """The procedure cannot go on; the message says why and what to do."""


class ScanFeed(Protocol):
    def scans(self, count: int, timeout_s: float) -> list[np.ndarray]:
        """The next ``count`` resistance scans (2, 2, N, M) ohm, taken after this call."""


class LinkFeed:
    """Scans from the scanner over its serial link (skinmap.daemon.link.ScannerLink)."""

    def __init__(self, device_cfg: Any, on_event: Callable[[str, str], None] | None = None) -> None:
        from skinmap.daemon.link import ScannerLink

        self._q: queue.Queue[np.ndarray] = queue.Queue(maxsize=10000)
        self._hello = threading.Event()
        self.link = ScannerLink(device_cfg, on_hello=lambda h: self._hello.set(), on_scan=self._on_scan,
                                on_event=on_event or (lambda level, text: None))

    def _on_scan(self, scan: Any, _frame: Any, _t: int) -> None:
        try:
            self._q.put_nowait(scan.resistances_ohm())
        except queue.Full:
            pass

    def start(self, timeout_s: float = 10.0) -> Any:
        """Start the link; the scanner's HELLO (CalibrationAborted if none comes)."""
        self.link.start()
        if not self._hello.wait(timeout_s) or self.link.hello is None:
            self.link.stop()
            raise CalibrationAborted(f"no answer from the scanner at {self.link.cfg.port} within {timeout_s:g} s")
        return self.link.hello

    def stop(self) -> None:
        self.link.stop()

    def scans(self, count: int, timeout_s: float) -> list[np.ndarray]:
        while True:  # only scans taken after the call: the sheet may just have moved
            try:
                self._q.get_nowait()
            except queue.Empty:
                break
        out: list[np.ndarray] = []
        deadline = time.monotonic() + timeout_s
        while len(out) < count:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CalibrationAborted(f"only {len(out)} of {count} scans arrived within {timeout_s:g} s")
            try:
                out.append(self._q.get(timeout=left))
            except queue.Empty:
                continue
        return out


class PromptPlacer:
    """A person places the sheet: the instruction is printed, Enter confirms."""

    def __init__(self, ask: Callable[[str], str] = input, say: Callable[[str], None] = print) -> None:
        self.ask, self.say = ask, say

    def prepare(self, poses: list[Pose]) -> None:
        return None

    def place(self, pose: Pose, attempt: int) -> None:
        how = {
            "flat": "Lay the sheet flat on the table, nothing touching it.",
            "stretch": f"Clamp the sheet in the stretching frame at {100 * pose.stretch:g} % in both directions.",
        }.get(pose.kind, f"Lay the sheet on the {'convex' if pose.radius_mm > 0 else 'concave'} mold of radius "
                         f"{abs(pose.radius_mm):g} mm, its {pose.direction} around the circumference, upper side "
                         f"{'out' if pose.radius_mm > 0 else 'in'}; lift it off the previous mold first.")
        try:
            self.ask(f"  {how} Press Enter when it rests. ")
        except EOFError:
            raise CalibrationAborted("no answer on the terminal (stdin closed); nothing written") from None


class EmulatedPlacer:
    """The in-process emulator places its sheet, with a placement error drawn for every pose: the
    mold's axis off by up to ``axis_error_deg`` and the sheet off the mold's centre by up to
    ``offset_mm``.  Between poses the sheet rests flat, as when lifted off one mold for the next."""

    def __init__(self, emulator: Any, mechanics: str = "kinematic", seed: int = 0, axis_error_deg: float = 3.0,
                 offset_mm: float = 5.0, rest_s: float = 0.2) -> None:
        self.emulator, self.mechanics = emulator, mechanics
        self.rng = np.random.default_rng([seed, 7])
        self.axis_error_deg, self.offset_mm, self.rest_s = axis_error_deg, offset_mm, rest_s
        self._scenes: dict[Pose, Any] = {}
        self.placements: list[tuple[float, float]] = []

    def prepare(self, poses: list[Pose]) -> None:
        """Draw every placement and build (solve) every scene before the scanner streams; poses
        already prepared keep theirs."""
        from skinmap.emulator.molds import mold_scene

        c = self.emulator.config
        for pose in poses:
            if pose in self._scenes:
                continue
            err = float(self.rng.uniform(-self.axis_error_deg, self.axis_error_deg))
            off = float(self.rng.uniform(-self.offset_mm, self.offset_mm))
            self._scenes[pose] = mold_scene(pose.kind, c.n, c.m, c.pitch_mm, radius=pose.radius_mm,
                                            direction=pose.direction or "rows", stretch=pose.stretch,
                                            axis_error_deg=err if pose.kind == "cylinder" else 0.0,
                                            offset_mm=off if pose.kind == "cylinder" else 0.0,
                                            mechanics=self.mechanics)
            self.placements.append((err, off))

    def place(self, pose: Pose, attempt: int) -> None:
        from skinmap.emulator.physics import Flat

        self.emulator.set_shape(Flat())
        time.sleep(self.rest_s)
        self.emulator.set_shape(self._scenes[pose])


def motion(strains: np.ndarray) -> float:
    """Largest change of a gauge's mean strain from the first to the last third of a window."""
    k = max(1, strains.shape[0] // 3)
    with np.errstate(invalid="ignore"):
        d = np.abs(np.nanmean(strains[:k], axis=0) - np.nanmean(strains[-k:], axis=0))
    return float(np.nanmax(d)) if np.isfinite(d).any() else float("inf")


def take_static(feed: ScanFeed, gauge_factor: np.ndarray, base_resistance: np.ndarray, window: int,
                timeout_s: float, say: Callable[[str], None] = print) -> tuple[np.ndarray, np.ndarray]:
    """Windows of ``window`` scans until one is static; (its scans (K, 2, 2, N, M) ohm, their
    strains).  CalibrationAborted when the sheet does not come to rest within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    worst = float("inf")
    while time.monotonic() < deadline:
        scans = np.stack(feed.scans(window, max(1.0, deadline - time.monotonic() + 5.0)))
        eps = gauge_strain(scans, gauge_factor, base_resistance)
        worst = motion(eps)
        if worst <= STATIC_TOLERANCE:
            return scans, eps
        say(f"  the sheet is moving (a gauge changed by {worst:.1e} strain within the window); waiting for it to rest")
    raise CalibrationAborted(f"the sheet did not come to rest within {timeout_s:g} s (a gauge still changed by "
                             f"{worst:.1e} strain, the limit is {STATIC_TOLERANCE:.0e}); nothing written")


def tare_problem(scans: np.ndarray, gauge_factor: np.ndarray, base_resistance: np.ndarray,
                 h_upper_mm: float, h_lower_mm: float) -> str:
    """Why these scans are no tare ('' if they are one): the sheet moved, or it is not flat."""
    eps = gauge_strain(scans, gauge_factor, base_resistance)
    moved = motion(eps)
    if moved > STATIC_TOLERANCE:
        return (f"the sheet is moving (a gauge changed by {moved:.1e} strain over the scans, the limit is "
                f"{STATIC_TOLERANCE:.0e}); let it rest flat and try again")
    with np.errstate(invalid="ignore"):
        problem = check_pose(Pose("flat"), np.nanmean(eps, axis=0), h_upper_mm, h_lower_mm)
    return f"{problem} and try again" if problem else ""


@dataclass
class CalibrationRun:
    """What a finished procedure found and wrote."""

    fit: MoldFit
    tare_ohm: np.ndarray
    tare_file: Path | None
    calibration_file: Path | None
    duration_s: float
    poses: list[dict] = field(default_factory=list)
    poisson: PoissonFit | None = None  # with a dome pose: the film's Poisson ratio


def run_calibration(feed: ScanFeed, placer: Any, poses: list[Pose], hello: Any, *, state_dir: Path | None,
                    h_upper_mm: float, h_lower_mm: float, window: int = 30, timeout_s: float = 30.0,
                    attempts: int = 3, say: Callable[[str], None] = print) -> CalibrationRun:
    """The whole procedure; writes the tare and the calibration file into ``state_dir`` (None:
    nothing written)."""
    from skinmap.strains import compute_tare, save_calibration, save_tare

    if not poses or poses[0].kind != "flat":
        raise ValueError("the procedure starts with the flat pose (it is the tare)")
    t0 = time.monotonic()
    gf0 = np.asarray(hello.gauge_factor(), dtype=float)
    r0 = np.asarray(hello.base_resistance_ohm(), dtype=float)
    placer.prepare(poses)
    readings: list[np.ndarray] = []
    taken: list[dict] = []
    noise: list[float] = []
    tare = r0
    for i, pose in enumerate(poses):
        say(f"[{i + 1}/{len(poses)}] {pose.title}")
        for attempt in range(attempts):
            placer.place(pose, attempt)
            scans, eps = take_static(feed, gf0, tare, window, timeout_s, say)
            if pose.kind == "flat":
                tare = compute_tare(scans)
                eps = gauge_strain(scans, gf0, tare)
            with np.errstate(invalid="ignore"):
                mean = np.nanmean(eps, axis=0)
            problem = check_pose(pose, mean, h_upper_mm, h_lower_mm)
            if not problem:
                break
            say(f"  not taken: {problem}")
        else:
            raise CalibrationAborted(f"pose {i + 1} ({pose.title}) was not taken after {attempts} attempts; "
                                     "nothing written")
        with np.errstate(invalid="ignore"):
            noise.append(float(np.nanmedian(np.nanstd(eps, axis=0))) / np.sqrt(eps.shape[0]))
        readings.append(mean)
        taken.append({"pose": pose.title, "kind": pose.kind, "radius_mm": pose.radius_mm, "direction": pose.direction,
                      "stretch": pose.stretch, "scans": int(eps.shape[0]), "motion_strain": motion(eps)})
        say(f"  taken ({eps.shape[0]} scans, still within {motion(eps):.1e} strain)")
    # the gauges from the flat, stretched and cylinder poses; a dome gives the film's Poisson ratio
    gauge_idx = [i for i, p in enumerate(poses) if p.kind != "dome"]
    fit = fit_mold_calibration([poses[i] for i in gauge_idx], [readings[i] for i in gauge_idx], gf0, h_upper_mm,
                               h_lower_mm, noise_sd=max(float(np.median(noise)), 1e-7))
    for i, err in zip(gauge_idx, fit.axis_error_deg):
        taken[i]["axis_error_deg_fitted"] = round(float(err), 3)
    poisson = None
    for i, pose in enumerate(poses):
        if pose.kind != "dome":
            continue
        strain = readings[i] * gf0 / fit.gauge_factor  # read again with the fitted gauge factors
        try:
            poisson = fit_poisson_ratio(strain[0], strain[1], fit.h_upper_mm, fit.h_lower_mm, hello.pitch_um / 1000.0,
                                        pose.radius_mm)
        except ValueError as exc:
            raise CalibrationAborted(f"pose {i + 1} ({pose.title}): {exc}; nothing written") from None
        taken[i]["poisson_ratio"] = round(poisson.poisson, 4)
        say(f"  Poisson's ratio {poisson.poisson:.3f} ± {poisson.sd:.3f} ({poisson.units} units)")
    duration = time.monotonic() - t0
    tare_file = cal_file = None
    if state_dir is not None:
        serial = hello.serial_number
        tare_file = save_tare(state_dir, serial, tare, window)
        cal_file = save_calibration(
            state_dir, serial, gauge_factor=fit.gauge_factor, gauge_factor_sd=fit.gauge_factor_sd,
            h_upper_mm=fit.h_upper_mm, h_upper_sd_mm=fit.h_upper_sd_mm, h_lower_mm=fit.h_lower_mm,
            h_lower_sd_mm=fit.h_lower_sd_mm, residual_rms=fit.residual_rms, method=fit.method,
            offsets_determined=fit.offsets_determined, poses=taken, duration_s=duration, notes=fit.notes,
            poisson=None if poisson is None else (poisson.poisson, poisson.sd))
    return CalibrationRun(fit, tare, tare_file, cal_file, duration, taken, poisson)


def summarise(fit: MoldFit, factory_gauge_factor: np.ndarray) -> list[str]:
    """Lines for the user: how far the gauges were from their factory values, and how sure the
    fit is of each kind of parameter."""
    rel = fit.gauge_factor / factory_gauge_factor - 1.0
    lines = [
        f"gauge factors: {np.count_nonzero(np.isfinite(fit.gauge_factor_sd))} gauges fitted, "
        f"{100 * np.sqrt(np.nanmean(rel ** 2)):.1f} % rms from the factory values (largest {100 * np.nanmax(np.abs(rel)):.1f} %); "
        f"s.d. of each {100 * np.nanmedian(fit.gauge_factor_sd / fit.gauge_factor):.2f} % (median)",
        f"residual per gauge: {np.nanmedian(fit.residual_rms):.1e} strain rms (median), {np.nanmax(fit.residual_rms):.1e} largest",
    ]
    if fit.offsets_determined:
        for name, h, sd in (("h_upper", fit.h_upper_mm, fit.h_upper_sd_mm), ("h_lower", fit.h_lower_mm, fit.h_lower_sd_mm)):
            lines.append(f"{name}: {np.nanmin(h):.4f}…{np.nanmax(h):.4f} mm over the units, s.d. of each "
                         f"{np.nanmedian(sd):.4f} mm (median)")
    cyl = [e for e in fit.axis_error_deg if e]
    if cyl:
        lines.append(f"mold axis errors fitted: up to {max(cyl):.1f}°")
    lines.extend(fit.notes)
    return lines
