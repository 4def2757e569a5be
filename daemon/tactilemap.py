"""`skinmap map LOG.mcap`: a log's presses stitched into the touched wall's relief.

The log is replayed (its raw frames through the pipeline, with the calibration it was recorded
with); every processed surface is sampled on a material grid; the first ``baseline_frames`` are
the pre-contact baseline (start recording before the first press); a contact **event** is a run
of at least two frames in contact (ended by two free ones), represented by its frame of deepest
indentation; each event
is placed by its probe pose: from a CSV (columns x_mm, y_mm, angle_deg, depth_mm, one row a
press, in order), else from the pose the gateway's ``/contact`` messages carry (the one in force
when the contact began), else from the log's ``/pose`` topic (the latest pose received before
the event began), else from the ``[tactile] poses`` of the config it was recorded with; with
``estimate=True`` the poses are found by registering each contact against the map so far
(skinmap.daemon.tactile.stitch_estimated; a known first pose anchors the map, else the first
press's frame is the map's).  With given poses each contact, registered by its rim, is placed by
its free cells' bending (skinmap.daemon.tactile.level_by_bending, with the probe's stiffness
length: ``probe_length_mm``, else the log's ``[tactile] probe_length_mm``; ``reference="floor"``:
levelled on the wall's base plane where the press touched it, tactile.level_on_floor; ``"rim"``:
the rim alone); the summary says which.  ``fit_length=True``: the log's presses are of a flat
plate at the poses' depths, and the probe's stiffness length is fitted on them
(tactile.fit_probe_length) and used.  Outputs: a summary per contact, the relief map's
coverage, a PNG of the height map and its confidence, a PLY point cloud of the touched cells.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skinmap.daemon.tactile import (CELL_QUANTILE, CONTACT_RIM_MM, GAUGE_LENGTH_MM, PROBE_LENGTH_MM, Baseline,
                                    BendingLevel, Contact, ContactEvent, ContactSegmenter, FloorLevel, PoseEstimate,
                                    ProbeLengthFit, ProbePose, ReliefMap, SampleGrid,
                                    capture_baseline, detect_contact, fit_probe_length, level_by_bending,
                                    level_on_floor, read_poses_csv, stitch_estimated)

__all__ = ["MapReport", "contact_events", "map_log", "write_ply", "write_png"]


#: What ``skinmap map --estimate`` says of its poses.  A pressurised probe touches only the flat
#: parts of a relief (the floor, the strokes' tops) and spans its edges, which are what fix a
#: position; the rest of a contact is the film on the balloon, alike from press to press.  On the
#: emulator's balloon bench (docs/tactile.md) the placements that passed every check of
#: estimate_pose lay 7-110 mm (66 median) from their true places, and with the sheet's exact surfaces and
#: only its truly touching samples nothing could be placed at all; two presses' exact surfaces,
#: registered one onto the other from their true relative pose, move off it (none of 63 pairs
#: within 1 mm and 1°: ``bench/tactile.py --pairwise``).
UNVERIFIED_ESTIMATE = ("caution: poses estimated from the contacts' overlap are not verified. A pressurised probe "
                       "touches a relief's flat parts and spans its edges, so a contact's shape is mostly the probe's "
                       "own and can fit far from where it was pressed; give the poses (--poses, the /pose topic or "
                       "[tactile] poses) for a map to rely on")


@dataclass
class MapReport:
    frames: int = 0
    baseline_frames: int = 0
    events: list[Contact] = field(default_factory=list)
    relief: ReliefMap | None = None
    problems: list[str] = field(default_factory=list)
    pose_source: str = ""
    estimates: list[PoseEstimate] = field(default_factory=list)
    levels: list[FloorLevel | BendingLevel] = field(default_factory=list)
    probe_length_mm: float | None = None  # the stiffness length the contacts were placed with
    length_fit: ProbeLengthFit | None = None  # with fit_length: the fit on the plate's presses

    def format(self) -> str:
        lines = [f"{self.frames} surfaces, baseline of {self.baseline_frames}, {len(self.events)} contact events"
                 + (f", poses {self.pose_source}" if self.pose_source else "")]
        if self.length_fit is not None:
            f = self.length_fit
            lo, hi = f.indentation_mm
            lines.append(f"probe stiffness length fitted on {f.contacts} plate presses indenting {lo:.1f}-{hi:.1f} mm: "
                         f"{f.length_mm:.2f} mm (residual {f.residual_mm:.3f} mm rms; set [tactile] probe_length_mm = "
                         f"{f.length_mm:.2f}; a map whose presses indent much deeper than {hi:.1f} mm extrapolates it, "
                         "docs/tactile.md)"
                         + "".join(f"\n  left out: {s}" for s in f.skipped))
        elif self.probe_length_mm is not None:
            lines.append("contacts placed by their bending with the probe stiffness length "
                         f"{self.probe_length_mm:g} mm")
        for i, c in enumerate(self.events):
            s = c.summary()
            line = (f"  contact {i + 1}: area {s['area_mm2']:.0f} mm², peak depth {s['peak_depth_mm']:.2f} mm, "
                    f"feature size L_r {s['feature_size_mm']:.1f} mm")
            if i < len(self.estimates):
                e = self.estimates[i]
                line += (f"; pose x {e.pose.x_mm:.1f} y {e.pose.y_mm:.1f} mm, {e.pose.angle_deg:.1f}°, depth "
                         f"{e.pose.depth_mm:.2f} mm" + (f" (s.d. {e.sd_xy_mm:.2f} mm, {e.sd_angle_deg:.2f}°)"
                                                        if math.isfinite(e.sd_xy_mm) else f" ({e.reason})")
                         if e.pose is not None else f"; not placed: {e.reason}")
            if i < len(self.levels):
                lv = self.levels[i]
                if lv.reason:
                    line += f"; {lv.reason}"
                elif isinstance(lv, BendingLevel):
                    line += (f"; placed by its bending (moved {lv.offset_mm:+.2f} mm along z, {lv.cells} free cells, "
                             f"misfit {lv.residual_mm:.2f} mm rms)")
                    if lv.doubtful:
                        line += "; caution: the misfit is of the order of the move, which is not to be trusted"
                else:
                    line += (f"; levelled on the floor (moved {lv.offset_mm:.2f} mm off the wall, floor "
                             f"{lv.floor_area_mm2:.0f} mm²)")
            lines.append(line)
        doubtful = sum(isinstance(lv, BendingLevel) and lv.doubtful for lv in self.levels)
        if doubtful:
            lines.append(f"caution: {doubtful} of {len(self.levels)} contacts were moved by their bending with a "
                         "misfit of the order of the move (the cells round them do not read as a balloon pushed "
                         "in); their heights are not to be trusted")
        if self.relief is not None:
            h = self.relief.height()
            lines.append(f"relief map: coverage {100 * self.relief.coverage():.1f} % of the wall, heights "
                         f"{np.nanmin(h):.2f}…{np.nanmax(h):.2f} mm" if np.isfinite(h).any() else "relief map: empty")
        lines.extend(self.problems)
        return "\n".join(lines)


def contact_events(frames: list[np.ndarray], baseline_frames: int, grid: SampleGrid, k: float = 3.0,
                   min_depth_mm: float = 0.5, normals: list[np.ndarray] | None = None,
                   starts: list[int] | None = None, ends: list[int] | None = None,
                   bending: list[np.ndarray] | None = None,
                   baseline_out: list[Baseline] | None = None) -> tuple[list[Contact], int]:
    """(contact events, the number of baseline frames used) from sampled surfaces (K, 3);
    ``starts`` and ``ends``, if given, receive each event's first and last frame in contact
    (indices into ``frames``); ``bending``, if given, each frame's cell bending (the contacts
    keep its change from the baseline's); ``baseline_out``, if given, receives the baseline."""
    if len(frames) <= baseline_frames:
        raise ValueError(f"{len(frames)} surfaces: not more than the {baseline_frames} baseline frames asked for")
    if bending is not None and len(bending) != len(frames):
        raise ValueError(f"{len(bending)} cell bending maps for {len(frames)} surfaces")
    nrm = normals or [np.tile([0.0, 0.0, 1.0], (len(frames[0]), 1))] * len(frames)
    base = capture_baseline(list(zip(frames[:baseline_frames], nrm[:baseline_frames])),
                            bending=None if bending is None else bending[:baseline_frames])
    if baseline_out is not None:
        baseline_out[:] = [base]
    segmenter = ContactSegmenter()
    ended: list[ContactEvent] = []
    for i, pos in enumerate(frames[baseline_frames:], start=baseline_frames):
        event = segmenter.step(i, detect_contact(pos, base, grid, k, min_depth_mm,
                                                 bending=None if bending is None else bending[i]))
        if event is not None:
            ended.append(event)
    last_event = segmenter.finish()
    if last_event is not None:
        ended.append(last_event)
    if starts is not None:
        starts[:] = [e.first for e in ended]
    if ends is not None:
        ends[:] = [e.last for e in ended]
    return [e.contact for e in ended], baseline_frames


def map_log(log: str | os.PathLike[str], poses_csv: str | os.PathLike[str] | None = None, *,
            estimate: bool = False, baseline_frames: int = 10, step_mm: float = 2.0, k: float = 3.0,
            min_depth_mm: float = 0.5, wall_size_mm: float = 120.0, cell_mm: float = 1.0,
            reference: str = "bending", probe_length_mm: float | None = None, fit_length: bool = False,
            cell_quantile: float = CELL_QUANTILE, rim_mm: float = CONTACT_RIM_MM) -> MapReport:
    """Replay the log and stitch its contact events with their poses (see the module); ValueError
    names what is wrong (no surfaces, too few baseline frames, no poses from any source, event
    and pose counts that differ, an event without a pose on the topic, a malformed pose)."""
    from skinmap.daemon.poses import assign_poses, contact_poses, poses_in_log
    from skinmap.daemon.replay import replay_log

    if reference not in ("bending", "floor", "rim"):
        raise ValueError(f"reference must be 'bending', 'floor' or 'rim', got {reference!r}")
    if fit_length and estimate:
        raise ValueError("fitting the probe's stiffness length needs the plate presses' given poses (their depths), "
                         "not estimated ones")
    if probe_length_mm is not None and not (math.isfinite(probe_length_mm) and probe_length_mm > 0):
        raise ValueError(f"the probe's stiffness length must be > 0 mm, got {probe_length_mm!r}")
    csv_poses = read_poses_csv(Path(poses_csv).read_text(encoding="utf-8")) if poses_csv is not None else None
    frames: list[np.ndarray] = []
    normals: list[np.ndarray] = []
    bending: list[np.ndarray] = []
    times: list[int] = []
    grid: SampleGrid | None = None  # from the first surface, with the sheet's pitch and gauge length (mm)
    pitch = gauge_length = math.nan

    def on_result(result) -> None:
        nonlocal grid, pitch, gauge_length
        if result.surface is None:
            return
        if grid is None:
            n, m = result.nodes_mm.shape[:2]
            pitch = float(result.surface.pitch)
            g = result.geometry
            gauge_length = GAUGE_LENGTH_MM if g is None else float(g.gauge_length_mm)
            grid = SampleGrid.for_array(n, m, pitch, step_mm)
        pos, nrm = result.surface.locate(grid.uv)
        frames.append(np.asarray(pos, dtype=float))
        normals.append(np.asarray(nrm, dtype=float))
        cells = result.cell_bending()
        bending.append(np.full(result.nodes_mm.shape[:2], np.nan) if cells is None else cells)
        times.append(int(result.host_time_ns))

    replay = replay_log(log, on_result=on_result)
    report = MapReport(frames=len(frames), problems=list(getattr(replay, "problems", []))[:5])
    if grid is None:
        raise ValueError(f"{log}: no surfaces could be replayed from its raw frames")
    starts: list[int] = []
    ends: list[int] = []
    based: list[Baseline] = []
    report.events, report.baseline_frames = contact_events(frames, baseline_frames, grid, k, min_depth_mm, normals,
                                                           starts, ends, bending, based)
    baseline = based[0]
    logged = poses_in_log(log)
    if logged.refused:
        raise ValueError(f"{log}: " + "; ".join(logged.refused[:3]))
    poses: list[ProbePose] | None
    if csv_poses is not None:
        poses, report.pose_source = csv_poses, f"from {poses_csv}"
    elif logged.contact:
        poses = contact_poses([times[i] for i in starts], [times[i] for i in ends], logged.contact)
        report.pose_source = f"from the gateway's /contact messages ({len(logged.contact)} with a pose)"
    elif logged.topic:
        poses = assign_poses([times[i] for i in starts], logged.topic)
        report.pose_source = f"from the log's /pose topic ({len(logged.topic)} received)"
    elif logged.config:
        poses, report.pose_source = logged.config, "from the log's [tactile] poses"
    else:
        poses = None
    relief = ReliefMap(wall_size_mm, cell_mm, rim_mm=rim_mm, quantile=cell_quantile)
    if estimate:
        if not report.events:
            raise ValueError(f"{log}: no contact events to register")
        first = poses[0] if poses else None
        report.estimates = stitch_estimated(report.events, grid, relief, first)
        placed = sum(e.pose is not None for e in report.estimates)
        report.pose_source = (f"estimated by registration ({placed} of {len(report.events)} placed; "
                              + (f"anchored by the first pose {report.pose_source})" if first else
                                 "the map in the first press's frame)"))
        report.problems.append(UNVERIFIED_ESTIMATE)
        report.relief = relief
        return report
    if poses is None:
        raise ValueError(f"{log}: no probe poses: give --poses CSV, or log them on the pose topic or in [tactile] "
                         "poses, or --estimate them from the overlap between contacts")
    if len(report.events) != len(poses):
        raise ValueError(f"{log}: {len(report.events)} contact events, but {len(poses)} poses "
                         f"{report.pose_source} (one pose a press, in order)")
    length = probe_length_mm if probe_length_mm is not None else logged.probe_length_mm or PROBE_LENGTH_MM
    if fit_length:
        report.length_fit = fit_probe_length(report.events, poses, baseline, grid, pitch,
                                             gauge_length_mm=gauge_length)
        length = report.length_fit.length_mm
    for c, pose in zip(report.events, poses):
        if reference == "bending":
            report.levels.append(level_by_bending(c, baseline, grid, pitch, length_mm=length,
                                                  gauge_length_mm=gauge_length))
            report.probe_length_mm = length
        elif reference == "floor":
            report.levels.append(level_on_floor(c, pose, grid))
        if report.levels:
            c = report.levels[-1].contact
        relief.add(c, pose, grid)
    report.relief = relief
    return report


def write_ply(relief: ReliefMap, path: str | os.PathLike[str]) -> int:
    """ASCII PLY of the touched cells: x, y (wall frame, mm), z = height, and the confidence."""
    h = relief.height()
    conf = relief.confidence()
    c = relief.centres
    keep = np.isfinite(h)
    pts = np.column_stack([c[keep][:, 0], c[keep][:, 1], h[keep], conf[keep]])
    with open(path, "w", encoding="ascii") as f:
        f.write("ply\nformat ascii 1.0\ncomment skinmap stitched relief (wall frame, mm)\n")
        f.write(f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\n"
                "property float confidence\nend_header\n")
        np.savetxt(f, pts, fmt="%.4f")
    return int(len(pts))


def write_png(relief: ReliefMap, path: str | os.PathLike[str], truth: np.ndarray | None = None) -> None:
    """The height map and its confidence (and, if given, the true relief) side by side."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    panels = [("stitched height (mm)", relief.height(), "viridis"), ("confidence", relief.confidence(), "magma")]
    if truth is not None:
        panels.insert(0, ("true relief (mm)", truth, "viridis"))
    fig = Figure(figsize=(4.2 * len(panels), 4.0), dpi=100)
    FigureCanvasAgg(fig)
    ext = (-relief.half, relief.half, -relief.half, relief.half)
    for i, (title, img, cmap) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        # heights on their 1st–99th percentile: a few cells far off do not wash out the rest
        lim = np.nanpercentile(img, [1, 99]) if title.startswith("stitched") and np.isfinite(img).any() else (None, None)
        im = ax.imshow(img, origin="lower", extent=ext, cmap=cmap, vmin=lim[0], vmax=lim[1])
        ax.set_title(title)
        ax.set_xlabel("x (mm)")
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.tight_layout()
    fig.savefig(os.fspath(path), format="png")
