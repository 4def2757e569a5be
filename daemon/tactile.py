"""Tactile mapping (pure functions): baseline, contacts, stitching.

A probe (e.g. a balloon with the sheet on it) is pressed against a wall many times.  Each
pressed surface is compared with the pre-contact baseline; where it is displaced inwards by
more than k·σ the sheet touches the wall.  Each contact's surface points, placed in the wall's
frame by the probe's pose, are stitched into one height map of the wall.

Surfaces here are samples on a regular material grid of the sheet (``SampleGrid``): positions
(K, 3) mm and normals, e.g. ``Surface.locate(grid.uv)`` of a reconstruction.

- **Baseline** (:func:`capture_baseline`): the mean of a few pre-contact frames and, per
  sample, the scatter σ between them (with a floor, so a noise-free baseline does not declare
  every tiny difference a contact).
- **Displacement** (:func:`displacement`): a pressed frame is first moved rigidly onto the
  baseline using the samples out of contact (the reconstruction's frame is anchored at the
  sheet's centre, which itself moves when pressed), starting from the sheet's rim and
  iterating as the contact is found; then
  d = (x − x₀)·n₀ along the baseline normal (negative: pressed in).
- **Contact** (:func:`detect_contact`): samples with −d > k·σ and −d > ``min_depth``; its area,
  indentation depth map, peak, and feature size L_r: the diameter of the largest circle inside
  the −6 dB (half peak depth) region around the peak.
- **Stitching** (:class:`ReliefMap`): with the probe pose (wall position and angle of the probe
  frame, and the press depth: the wall's base plane at z = −depth in the probe frame) each
  contact sample gives the wall height H = −depth − z at its wall point; the map keeps per cell
  the mean, the count and the scatter, hence coverage and a per-cell confidence.
- **Bending** (:func:`level_by_bending`): a contact registered by its rim is moved by the rigid
  motion that makes its free cells' deflection ℓ² times their change of bending, the rim's push
  the rim cannot show (:data:`PROBE_LENGTH_MM`, :func:`fit_probe_length`): what ``skinmap map``
  does with given poses.
- **Floor** (:func:`level_on_floor`): with a given pose, a contact registered by its rim is
  moved so that its lowest samples lie on the wall's base plane, where the data allows that the
  press touched it (a press pushes the rim in too; the base plane does not move with it).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from skinmap.reconstruction.linalg import exp_so3
from skinmap.strains import GAUGE_LENGTH_MM, cell_centres

__all__ = ["SampleGrid", "Baseline", "Contact", "ContactEvent", "ContactSegmenter", "ContactTracker", "ProbePose",
           "ReliefMap", "PoseEstimate",
           "capture_baseline", "displacement", "detect_contact", "feature_size", "read_poses_csv", "contact_points",
           "estimate_pose", "anchor_pose", "stitch_estimated", "FloorLevel", "level_on_floor", "PROBE_LENGTH_MM",
           "BendingLevel", "level_by_bending", "ProbeLengthFit", "fit_probe_length"]


@dataclass(frozen=True)
class SampleGrid:
    """A regular material grid over the sheet: ``shape`` (rows, cols) points ``step`` mm apart,
    centred on the sheet's centre."""

    shape: tuple[int, int]
    step: float

    @classmethod
    def for_array(cls, n: int, m: int, pitch: float, step: float = 2.0) -> "SampleGrid":
        """Covering the cell centres (the part the gauges see best)."""
        rows = int(math.floor((n - 1) * pitch / step)) + 1
        cols = int(math.floor((m - 1) * pitch / step)) + 1
        return cls((rows, cols), float(step))

    @property
    def uv(self) -> np.ndarray:
        r, c = self.shape
        u = (np.arange(c) - (c - 1) / 2) * self.step
        v = (np.arange(r) - (r - 1) / 2) * self.step
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu.ravel(), vv.ravel()], axis=1)


@dataclass(frozen=True)
class Baseline:
    positions: np.ndarray  # (K, 3) mm
    normals: np.ndarray  # (K, 3)
    sigma: np.ndarray  # (K,) mm, the scatter of the displacement between baseline frames
    bending: np.ndarray | None = None  # (N, M) 1/mm, the cells' mean bending (strains.cell_bending), if read


def capture_baseline(frames: list[tuple[np.ndarray, np.ndarray]], sigma_floor_mm: float = 0.01,
                     bending: list[np.ndarray] | None = None) -> Baseline:
    """Baseline from pre-contact frames [(positions (K, 3), normals (K, 3)), ...] and, if given,
    each frame's cell bending (:func:`skinmap.strains.cell_bending`, (N, M)); ValueError if
    there are none or they differ in size."""
    if not frames:
        raise ValueError("a baseline needs at least one pre-contact frame")
    k = frames[0][0].shape
    if any(p.shape != k or n.shape != k for p, n in frames):
        raise ValueError("baseline frames differ in their number of samples")
    mean_bending = None
    if bending is not None:
        if len(bending) != len(frames) or any(np.shape(b) != np.shape(bending[0]) or np.ndim(b) != 2 for b in bending):
            raise ValueError(f"{len(bending)} cell bending maps for {len(frames)} baseline frames "
                             "(one (N, M) map a frame)")
        mean_bending = np.mean(np.asarray(bending, dtype=float), axis=0)
    ref = frames[0][0]
    aligned = [_align(p, ref, np.ones(len(ref), bool))[0] for p, _ in frames]
    pos = np.mean(aligned, axis=0)
    nrm = np.mean([n for _, n in frames], axis=0)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    if len(frames) > 1:
        d = np.array([((p - pos) * nrm).sum(axis=1) for p in aligned])
        sigma = np.maximum(d.std(axis=0, ddof=1), sigma_floor_mm)
    else:
        sigma = np.full(len(pos), float(sigma_floor_mm))
    return Baseline(pos, nrm, sigma, mean_bending)


def _align(p: np.ndarray, q: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """p moved by the rigid motion that best maps p[use] onto q[use] (Kabsch); (moved, R, t)."""
    a, b = p[use], q[use]
    ac, bc = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ac).T @ (b - bc))
    d = np.sign(np.linalg.det(u @ vt))
    rot = (u * np.array([1.0, 1.0, d])) @ vt
    return (p - ac) @ rot + bc, rot, bc - ac @ rot


def displacement(positions: np.ndarray, baseline: Baseline, k: float = 3.0, min_depth_mm: float = 0.5,
                 iterations: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d (K,) mm along the baseline normal, the frame's aligned positions (K, 3), contact mask)."""
    p = np.asarray(positions, dtype=float)
    if p.shape != baseline.positions.shape:
        raise ValueError(f"a frame of {p.shape[0]} samples against a baseline of {baseline.positions.shape[0]}")
    # Start from the sheet's rim (a probe's sheet is taped there, and a press meets the middle
    # first); a start from every sample would let the pressed part pull the registration in.
    r = np.linalg.norm(baseline.positions[:, :2] - baseline.positions[:, :2].mean(axis=0), axis=1)
    free = r >= np.quantile(r, 0.75)
    for _ in range(max(1, iterations)):
        if free.sum() < 4:
            raise ValueError("fewer than 4 samples out of contact: the baseline frame cannot be registered")
        moved, _, _ = _align(p, baseline.positions, free)
        d = ((moved - baseline.positions) * baseline.normals).sum(axis=1)
        contact = (-d > k * baseline.sigma) & (-d > min_depth_mm)
        # register on what is clearly free: a margin around the contact keeps its rim out
        new_free = ~contact & (np.abs(d) <= max(k, 1.0) * baseline.sigma + min_depth_mm)
        if np.array_equal(new_free, free):
            break
        free = new_free if new_free.sum() >= 4 else free
    return d, moved, contact


def feature_size(depth: np.ndarray, step: float) -> float:
    """L_r (mm): the diameter of the largest circle inside the region around the peak where the
    depth is at least half the peak (−6 dB); 0 for no contact."""
    if not np.any(depth > 0):
        return 0.0
    peak = np.unravel_index(int(np.argmax(depth)), depth.shape)
    region, _ = ndimage.label(depth >= 0.5 * depth[peak])
    inside = region == region[peak]
    dist = ndimage.distance_transform_edt(np.pad(inside, 1))
    return float(2.0 * dist.max() * step)


@dataclass(frozen=True)
class Contact:
    mask: np.ndarray  # (rows, cols) samples in contact
    depth: np.ndarray  # (rows, cols) mm, indentation (−d) where in contact, 0 elsewhere
    area_mm2: float
    peak_depth_mm: float
    feature_size_mm: float  # L_r
    positions: np.ndarray  # (K, 3) the frame aligned onto the baseline
    sigma: np.ndarray | None = None  # (K,) mm, the frame's per-sample position uncertainty, if known
    # (N, M) 1/mm: the cells' bending (strains.cell_bending) less the baseline's, when both were read
    bending_change: np.ndarray | None = None

    def summary(self) -> dict:
        return {"area_mm2": round(self.area_mm2, 3), "peak_depth_mm": round(self.peak_depth_mm, 4),
                "feature_size_mm": round(self.feature_size_mm, 3), "samples": int(self.mask.sum())}


def detect_contact(positions: np.ndarray, baseline: Baseline, grid: SampleGrid, k: float = 3.0,
                   min_depth_mm: float = 0.5, sigma: np.ndarray | None = None,
                   bending: np.ndarray | None = None) -> Contact | None:
    """The contact in one frame, or None if nothing is pressed in beyond k·σ.  ``sigma`` (K,)
    mm: the frame's own per-sample uncertainty (e.g. ``Surface.locate_sigma``), kept as the
    stitching weight.  ``bending`` (N, M): the frame's cell bending
    (:func:`skinmap.strains.cell_bending`); with the baseline's, the contact keeps the change,
    which :func:`level_by_bending` reads."""
    d, moved, contact = displacement(positions, baseline, k, min_depth_mm)
    if not contact.any():
        return None
    change = None
    if bending is not None and baseline.bending is not None:
        if np.shape(bending) != baseline.bending.shape:
            raise ValueError(f"a cell bending map of shape {np.shape(bending)} against the baseline's "
                             f"{baseline.bending.shape}")
        change = np.asarray(bending, dtype=float) - baseline.bending
    depth = np.where(contact, -d, 0.0).reshape(grid.shape)
    mask = contact.reshape(grid.shape)
    return Contact(mask, depth, float(mask.sum() * grid.step ** 2), float(depth.max()),
                   feature_size(depth, grid.step), moved, None if sigma is None else np.asarray(sigma, float), change)


@dataclass(frozen=True)
class ContactEvent:
    """One press: its deepest frame's contact and its first and last frames in contact."""

    contact: Contact
    first: int
    last: int


class ContactSegmenter:
    """The one rule for where a contact event begins and ends, live (:class:`ContactTracker`,
    the `contact` topic's ``events``) and offline (``skinmap map``), so that the two count the
    same presses: an event is at least ``min_frames`` frames in contact and ends after
    ``min_frames`` free ones.  A frame whose scan straddles a press's start or end (each unit is
    read at its own TDM instant) thus neither splits a press nor makes one.  Explicit state: feed
    every frame's detection in order to :meth:`step`."""

    def __init__(self, min_frames: int = 2) -> None:
        if int(min_frames) < 1:
            raise ValueError(f"min_frames must be >= 1, got {min_frames!r}")
        self.min_frames = int(min_frames)
        self.events = 0  # events that have lasted min_frames frames in contact so far
        self._deepest: Contact | None = None  # the open event's deepest contact
        self._first = self._last = 0
        self._run = self._free = 0

    @property
    def open_since(self) -> int | None:
        """The first frame of the event in progress (not yet ended), or None."""
        return None if self._deepest is None else self._first

    @property
    def open_number(self) -> int | None:
        """The number (from 1) the event in progress has, or will have once it lasts
        ``min_frames`` frames; None when no event is in progress."""
        if self._deepest is None:
            return None
        return self.events if self._run >= self.min_frames else self.events + 1

    def step(self, index: int, contact: Contact | None) -> ContactEvent | None:
        """Frame ``index``'s detection (None: free); returns the event this frame ended, if any."""
        if contact is None:
            self._free += 1
            if self._deepest is not None and self._free >= self.min_frames:
                return self._close()
            return None
        self._free = 0
        if self._deepest is None:
            self._first = index
        self._last = index
        self._run += 1
        if self._run == self.min_frames:
            self.events += 1
        if self._deepest is None or contact.peak_depth_mm > self._deepest.peak_depth_mm:
            self._deepest = contact
        return None

    def finish(self) -> ContactEvent | None:
        """The event still open at the end of the frames, if it lasted long enough."""
        return None if self._deepest is None else self._close()

    def abandon(self) -> None:
        """Drop the event in progress without ending it (a new baseline is being taken: what
        follows is compared with another surface); the presses counted so far stay counted."""
        self._deepest, self._run, self._free = None, 0, 0

    def _close(self) -> ContactEvent | None:
        deepest, run = self._deepest, self._run
        self._deepest, self._run = None, 0
        if deepest is None or run < self.min_frames:
            return None
        return ContactEvent(deepest, self._first, self._last)


@dataclass(frozen=True)
class ProbePose:
    """Where the probe frame is on the wall: its origin at wall (x_mm, y_mm), turned by
    ``angle_deg``, the wall's base plane at z = −depth_mm in the probe frame."""

    x_mm: float
    y_mm: float
    angle_deg: float
    depth_mm: float

    def to_wall(self, xy: np.ndarray) -> np.ndarray:
        th = math.radians(self.angle_deg)
        c, s = math.cos(th), math.sin(th)
        return np.stack([self.x_mm + c * xy[..., 0] - s * xy[..., 1], self.y_mm + s * xy[..., 0] + c * xy[..., 1]], -1)


def read_poses_csv(text: str) -> list[ProbePose]:
    """Probe poses from CSV text with a header naming x_mm, y_mm, angle_deg, depth_mm (one row a
    press, in order); ValueError names the row and column that is wrong."""
    import csv
    import io

    rows = list(csv.DictReader(io.StringIO(text)))
    need = ("x_mm", "y_mm", "angle_deg", "depth_mm")
    if not rows:
        raise ValueError("the pose CSV has no rows")
    missing = [c for c in need if c not in rows[0]]
    if missing:
        raise ValueError(f"the pose CSV lacks the column(s) {', '.join(missing)} (it has {', '.join(rows[0])})")
    poses = []
    for i, row in enumerate(rows, start=2):
        try:
            vals = [float(row[c]) for c in need]
        except (TypeError, ValueError):
            raise ValueError(f"pose CSV line {i}: {', '.join(f'{c}={row.get(c)!r}' for c in need)} must be numbers") from None
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"pose CSV line {i}: values must be finite")
        poses.append(ProbePose(*vals))
    return poses


def contact_points(contact: Contact, grid: SampleGrid, upsample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A contact's surface points in the probe frame (P, 3), densified ×``upsample``
    bilinearly, and their weights (P,) (1, or 1/σ² normalised to a median of 1 when the
    contact carries per-sample σ)."""
    pos = contact.positions.reshape(*grid.shape, 3)
    mask = contact.mask.astype(float)
    sig = contact.sigma.reshape(grid.shape) if contact.sigma is not None else None
    if upsample > 1:
        pos = np.stack([ndimage.zoom(pos[..., i], upsample, order=1) for i in range(3)], axis=-1)
        mask = ndimage.zoom(mask, upsample, order=1)
        if sig is not None:
            sig = ndimage.zoom(sig, upsample, order=1)
    keep = mask >= 0.999
    if sig is None or not keep.any():
        return pos[keep], np.ones(int(keep.sum()))
    w = 1.0 / np.maximum(sig[keep], 1e-3) ** 2
    return pos[keep], w / np.median(w)


@dataclass(frozen=True)
class FloorLevel:
    """A contact levelled on the wall's base plane by :func:`level_on_floor`, or why not."""

    contact: Contact  # moved onto the floor plane, or as given (then ``reason`` says why)
    offset_mm: float  # how far it was moved away from the wall (0 when not levelled)
    floor_area_mm2: float  # the area of its samples found on the floor plane
    reason: str = ""  # why it stays registered by its rim ("" when levelled)


def level_on_floor(contact: Contact, pose: ProbePose, grid: SampleGrid, *, quantile: float = 0.05,
                   band_mm: float = 0.3, min_area_mm2: float = 40.0) -> FloorLevel:
    """Move a contact registered by its rim (:func:`displacement`) along z so that its lowest
    contact samples lie on the wall's base plane, z = −depth in the probe frame.

    Why: a press pushes the whole sheet in, its rim too, so a contact registered by its rim sits
    nearer the wall than it is, by how far the rim was pushed.  The wall's base plane is a
    reference that does not move with the press: the relief rises from it (H ≥ 0), so no part of
    the sheet lies beyond it, and the samples that touch the floor lie on it.  Their heights
    H = −depth − z are the lowest of the contact: the level of its lowest ``quantile``, then the
    median of the samples within ``band_mm`` of that level.

    It is used only when the data allows that the press touched the floor: the move must be away
    from the wall, since the rim is only ever pushed in (a press whose lowest samples stand above
    the floor plane touched only the relief, and placing them on the floor would pull the rim
    out), and those samples must cover ``min_area_mm2`` (a few stray samples are no patch).
    Otherwise the contact is returned as given, with the reason.
    Only the offset is fixed: the tilt of a small floor patch is not (the rim's tilt stays)."""
    if not (0.0 < quantile <= 0.5):
        raise ValueError(f"quantile must be in (0, 0.5], got {quantile!r}")
    if not (math.isfinite(band_mm) and band_mm > 0):
        raise ValueError(f"band_mm must be > 0, got {band_mm!r}")
    if not (math.isfinite(min_area_mm2) and min_area_mm2 >= 0):
        raise ValueError(f"min_area_mm2 must be >= 0, got {min_area_mm2!r}")
    if not math.isfinite(pose.depth_mm):
        raise ValueError(f"the pose's depth must be finite, got {pose.depth_mm!r}")
    mask = np.asarray(contact.mask, bool).ravel()
    if mask.size != len(contact.positions):
        raise ValueError(f"a contact mask of {mask.size} samples for {len(contact.positions)} positions")
    cell = grid.step ** 2
    if not mask.any():
        return FloorLevel(contact, 0.0, 0.0, "no samples in contact")
    h = -pose.depth_mm - contact.positions[mask, 2]
    low = float(np.quantile(h, quantile))
    on = np.abs(h - low) <= band_mm
    level = float(np.median(h[on]))
    area = float(on.sum() * cell)
    if area < min_area_mm2:
        return FloorLevel(contact, 0.0, area, f"its lowest samples cover {area:.0f} mm² (less than {min_area_mm2:.0f}): "
                                              "too few for a floor patch; registered by its rim")
    if level > 0.0:
        return FloorLevel(contact, 0.0, area, f"its lowest samples stand {level:.2f} mm off the floor plane: it touched "
                                              "only the relief (on the floor the rim would have been pulled out, and a "
                                              "press only pushes it in); registered by its rim")
    moved = contact.positions.copy()
    moved[:, 2] += level
    return FloorLevel(replace(contact, positions=moved), -level, area)


#: The probe's stiffness length ℓ (mm).  Outside a contact the balloon's wall, pushed off its
#: sphere by w (along its normal), carries the push by its tension T against the stiffness k of
#: its curved wall, T∇²w = k·w, so that w = ℓ²∇²w with ℓ = √(T/k): the push of the sheet's
#: rim, which the rim cannot see against the baseline, is written in its bending, which the
#: gauges read.  The paper's balloon (docs/physics.md): T 0.1 N/mm, k = E·t/R² = 3/80² N/mm³,
#: ℓ = 14.6 mm.  A probe's own is fitted by pressing a flat plate at known depths
#: (:func:`fit_probe_length`, ``skinmap map --fit-probe-length``).
PROBE_LENGTH_MM = 14.6

#: A contact's move is doubtful (:attr:`BendingLevel.doubtful`) when its free cells' misfit
#: reaches this share of it.  On the bench's letters the misfit is 0.12–0.19 mm median against
#: pushes of 1–2 mm; where a reconstruction is off round the contact (the emulator's kinematic
#: press) it is 1.6–2.1 mm against a wrongly read 1.9–2.1 mm (docs/tactile.md).  A misfit
#: below PUSH_DOUBT_FLOOR_MM is not doubtful whatever the move: the gauges' noise alone gives
#: about ℓ²·σ(Δκ), 0.06–0.08 mm a cell, so a light press's small move would otherwise be marked.
PUSH_DOUBT_RATIO, PUSH_DOUBT_FLOOR_MM = 0.5, 0.1

#: A cell is read as out of contact when its centre lies this far from every contact sample:
#: its gauges (10 mm) then end 1 mm short of the contact, whose crease they must not read.
FREE_CELL_MARGIN_MM = 6.0


@dataclass(frozen=True)
class BendingLevel:
    """A contact placed by its free cells' bending (:func:`level_by_bending`), or why not."""

    contact: Contact  # moved, or as given (then ``reason`` says why)
    offset_mm: float  # the move along z at the contact's samples, mean (negative: −z, into the balloon)
    cells: int  # the cells out of contact it read
    residual_mm: float  # rms, over those cells, of their deflection less ℓ²∇²w after the move
    reason: str = ""  # why it stays registered by its rim ("" when moved)

    @property
    def doubtful(self) -> bool:
        """Moved, but its free cells' misfit reaches :data:`PUSH_DOUBT_RATIO` of the move (and
        :data:`PUSH_DOUBT_FLOOR_MM`): the cells do not read as a balloon's wall pushed in, and the
        move is not to be trusted."""
        return not self.reason and self.residual_mm >= max(PUSH_DOUBT_RATIO * abs(self.offset_mm), PUSH_DOUBT_FLOOR_MM)


def _bending_system(contact: Contact, baseline: Baseline, grid: SampleGrid, pitch_mm: float,
                    margin_mm: float, gauge_length_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """At the contact's free cells: the rigid motion's effect on the normal deflection (C, 3 or
    1 columns: z offset, rotations about x and y), −Δ(κ_u + κ_v), and the deflection d as
    registered, each averaged over the cell's two gauges; or why the cells cannot decide."""
    if not (math.isfinite(gauge_length_mm) and gauge_length_mm >= 0):
        raise ValueError(f"gauge_length_mm must be >= 0, got {gauge_length_mm!r}")
    if contact.bending_change is None:
        return "no cell bending was read with it (the frame's or the baseline's layer strains)"
    change = np.asarray(contact.bending_change, dtype=float)
    n, m = change.shape
    centres_uv = cell_centres(n, m, pitch_mm).reshape(-1, 2)
    rows, cols = grid.shape
    # fractional sample indices of the cell centres (clamped onto the grid's outer samples)
    ij = np.stack([centres_uv[:, 1] / grid.step + (rows - 1) / 2, centres_uv[:, 0] / grid.step + (cols - 1) / 2])
    mask = np.asarray(contact.mask, bool).reshape(grid.shape)
    far = ndimage.distance_transform_edt(~mask) * grid.step
    free = (ndimage.map_coordinates(far, ij, order=1, mode="nearest") > margin_mm) & np.isfinite(change.ravel())
    cells = int(free.sum())
    if cells < 2:
        return (f"{cells} cell(s) lie {margin_mm:g} mm or more clear of the contact with usable gauges "
                "(2 needed): its rim's push cannot be read")

    # A gauge reads the curvature averaged along its length, so each cell's side of w = ℓ²∇²w is
    # averaged over the same two segments (measured on the emulator's exact pressed surfaces:
    # the push 0.068 mm mean off with the cell centre's deflection, 0.034 with the gauges' mean).
    along = np.linspace(-0.5, 0.5, 11) * gauge_length_mm
    zeros = np.zeros_like(along)
    offsets = np.concatenate([np.stack([along, zeros], 1), np.stack([zeros, along], 1)])  # (S, 2) as (u, v)
    points = centres_uv[free][:, None, :] + offsets[None]  # (C, S, 2)
    pij = np.stack([points[..., 1] / grid.step + (rows - 1) / 2, points[..., 0] / grid.step + (cols - 1) / 2])

    def at_gauges(field: np.ndarray) -> np.ndarray:
        """(C, S) the field at each free cell's gauge points."""
        return ndimage.map_coordinates(field.reshape(grid.shape), pij.reshape(2, -1), order=1,
                                       mode="nearest").reshape(points.shape[:2])

    p = np.stack([at_gauges(contact.positions[:, a]) for a in range(3)], axis=-1)
    nrm = np.stack([at_gauges(baseline.normals[:, a]) for a in range(3)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    d = at_gauges(((contact.positions - baseline.positions) * baseline.normals).sum(axis=1)).mean(axis=1)
    # a move by a ẑ + ω × p changes the normal deflection by a·n_z + ω·(p × n), averaged likewise
    cols3 = np.stack([nrm[..., 2], p[..., 1] * nrm[..., 2] - p[..., 2] * nrm[..., 1],
                      p[..., 2] * nrm[..., 0] - p[..., 0] * nrm[..., 2]], axis=-1).mean(axis=1)
    # a tilt wants cells spread round the contact; a few cells fix only the offset
    basis = cols3 if cells >= 6 else cols3[:, :1]
    return basis, -change.ravel()[free], d


def _moved(positions: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """positions moved by a ẑ + the rotation ω = (ω_x, ω_y, 0) about the probe frame's origin."""
    a, wx, wy = (list(motion) + [0.0, 0.0])[:3]
    return positions @ exp_so3(np.array([wx, wy, 0.0])).T + np.array([0.0, 0.0, a])


#: A free cell whose misfit exceeds this many robust s.d.s of the others' is left out of the fit
#: (its gauges read what the wall's equation does not hold for: a crease at the contact's edge,
#: a stroke's shoulder), down to the robust s.d.'s floor, ``_ROBUST_FLOOR_MM``.
_ROBUST_K, _ROBUST_FLOOR_MM = 3.0, 0.05


def _robust_motion(basis: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion fitted to the free cells, cells far off the rest left out and the fit
    taken again (at most three times; at least two cells kept, six for a tilt); (motion, the
    cells kept)."""
    keep = np.ones(len(target), bool)
    motion = np.zeros(3)
    for _ in range(4):
        cols = basis.shape[1] if keep.sum() >= 6 else 1
        motion, *_ = np.linalg.lstsq(basis[keep][:, :cols], target[keep], rcond=None)
        r = target - basis[:, :cols] @ motion
        scale = max(1.4826 * float(np.median(np.abs(r[keep]))), _ROBUST_FLOOR_MM)
        new = np.abs(r) <= _ROBUST_K * scale
        if new.sum() < 2 or np.array_equal(new, keep):
            break
        keep = new
    return motion, keep


def level_by_bending(contact: Contact, baseline: Baseline, grid: SampleGrid, pitch_mm: float, *,
                     length_mm: float = PROBE_LENGTH_MM, margin_mm: float = FREE_CELL_MARGIN_MM,
                     gauge_length_mm: float = GAUGE_LENGTH_MM) -> BendingLevel:
    """Move a contact registered by its rim (:func:`displacement`) by the rigid motion (an offset
    along z and a tilt) that makes its free cells' deflection from the baseline w = ℓ²∇²w.

    Why: a press pushes the whole balloon in, the sheet's rim too (1.3–1.6 mm on the emulator's
    letters), so a contact registered by its rim sits nearer the wall than it is.  The rim's
    push is not seen against the baseline, but its bending is: outside the contact the wall
    obeys T∇²w = k·w (:data:`PROBE_LENGTH_MM`), and ∇²w is the change of the cell's bending
    κ_u + κ_v, read by its gauges (−Δκ: a push in flattens the contact and curls the ring round
    it).  Cells whose gauges end clear of the contact (``margin_mm``) are read; six or more fix
    the offset and the tilt, two to five the offset alone; fewer leave the contact as given,
    with the reason.  ``length_mm``: ℓ, the probe's stiffness length; ``gauge_length_mm``: the
    gauges', over which each cell's deflection is averaged as its gauges average the bending."""
    if not (math.isfinite(length_mm) and length_mm > 0):
        raise ValueError(f"the probe's stiffness length must be > 0 mm, got {length_mm!r}")
    if not (math.isfinite(margin_mm) and margin_mm >= 0):
        raise ValueError(f"margin_mm must be >= 0, got {margin_mm!r}")
    system = _bending_system(contact, baseline, grid, pitch_mm, margin_mm, gauge_length_mm)
    if isinstance(system, str):
        return BendingLevel(contact, 0.0, 0, math.nan, system + "; registered by its rim")
    basis, lap, d = system
    target = length_mm ** 2 * lap - d
    motion, keep = _robust_motion(basis, target)
    moved = _moved(contact.positions, motion)
    mask = np.asarray(contact.mask, bool).ravel()
    offset = float((moved[mask, 2] - contact.positions[mask, 2]).mean()) if mask.any() else float(motion[0])
    residual = float(np.sqrt(np.mean((target[keep] - basis[keep][:, :len(motion)] @ motion) ** 2)))
    return BendingLevel(replace(contact, positions=moved), offset, int(keep.sum()), residual)


@dataclass(frozen=True)
class ProbeLengthFit:
    """The probe's stiffness length fitted on presses of a flat plate (:func:`fit_probe_length`)."""

    length_mm: float
    residual_mm: float  # rms, over the contacts' samples, of their height off the plate after levelling
    contacts: int  # the presses used
    skipped: list[str]  # the presses left out, each with why
    # (shallowest, deepest) peak indentation of the presses used, mm: the range ℓ was fitted over.
    # On reconstructed presses ℓ also takes in the reconstruction's error between a contact and
    # its free ring and the gauges' dead band, both of which change with the indentation (the
    # emulator's balloon: 11.5–17.7 mm fitted at one plate depth each, docs/tactile.md)
    indentation_mm: tuple[float, float] = (math.nan, math.nan)


def fit_probe_length(contacts: list[Contact], poses: list[ProbePose], baseline: Baseline, grid: SampleGrid,
                     pitch_mm: float, *, margin_mm: float = FREE_CELL_MARGIN_MM,
                     gauge_length_mm: float = GAUGE_LENGTH_MM) -> ProbeLengthFit:
    """ℓ from presses of a flat plate at known depths: the ℓ² with which :func:`level_by_bending`
    puts the contacts' samples on the plate, z = −depth, in the least-squares sense (it is
    linear in ℓ²).  The plate is the reference that does not move with the press; the depth is
    each pose's.  ValueError when the counts differ or no press has cells out of contact."""
    if len(contacts) != len(poses):
        raise ValueError(f"{len(contacts)} contacts but {len(poses)} poses (one pose a press)")
    g_all, r_all, skipped, used, peaks = [], [], [], 0, []
    for i, (c, pose) in enumerate(zip(contacts, poses)):
        system = _bending_system(c, baseline, grid, pitch_mm, margin_mm, gauge_length_mm)
        if isinstance(system, str):
            skipped.append(f"press {i + 1}: {system}")
            continue
        basis, lap, d = system
        mask = np.asarray(c.mask, bool).ravel()
        # the motion is linear in ℓ²: motion = ℓ²·P lap − P d, P the least-squares solve
        pinv = np.linalg.pinv(basis)
        m_lap, m_d = pinv @ lap, pinv @ d
        z = c.positions[mask, 2]
        g = _moved(c.positions[mask], m_lap)[:, 2] - z  # linear in the motion for small moves
        h = _moved(c.positions[mask], -m_d)[:, 2] - z
        g_all.append(g)
        r_all.append(-pose.depth_mm - z - h)
        peaks.append(c.peak_depth_mm)
        used += 1
    if not used:
        raise ValueError("no press had cells out of contact to read: " + "; ".join(skipped[:3]))
    g, r = np.concatenate(g_all), np.concatenate(r_all)
    l2 = float((g * r).sum() / (g * g).sum())
    if not l2 > 0:
        raise ValueError(f"the presses fit a stiffness length squared of {l2:.3g} mm², not > 0: the plate's presses "
                         "do not read as a balloon pushed in (was the plate flat, and were the depths right?)")
    return ProbeLengthFit(math.sqrt(l2), float(np.sqrt(np.mean((r - l2 * g) ** 2))), used, skipped,
                          (float(min(peaks)), float(max(peaks))))


#: Readings (one a contact) a relief-map cell keeps for its height: beyond this many the
#: oldest give way, so that a long log's map stays bounded (5 MB at the default 140² cells).
CELL_READINGS = 32
#: The quantile of a cell's readings that is its height: the median, of an even count the lower
#: middle reading (:meth:`ReliefMap.height`).  The wall is rigid, so a press reads a cell at the
#: wall's height where its film touched it and above it where the film spanned (held off by the
#: relief round it); of the two middle readings the lower is the nearer (the bench's
#: reconstructed letters, ℓ fitted on a plate: U 0.320 → 0.254 mm, E 0.292 → 0.262, D 0.224 →
#: 0.208, K 0.281 → 0.265 against the two middle readings' mean; docs/tactile.md).  The upper
#: third (2/3) took back the low reading of contacts levelled on the floor or registered by their
#: rim; contacts placed by their bending (level_by_bending) read the touched cells without that
#: bias, and the upper third then costs (E 0.302 mm with the median against 0.385, D 0.290
#: against 0.361, before cells far off the rest were left out).
#: One reading of four off either way moves nothing (the middle two agree).
CELL_QUANTILE = 0.5
#: A contact's outer ring of this width (mm) is left out of the map (0: none).  2 mm helped while
#: the emulator's gauges missed the creases where the wall takes over from the film (E 0.388 →
#: 0.351 mm, D 0.353 → 0.324 with the median); with the creases read it costs the map (levelled
#: as skinmap map does: E 0.782 → 0.884 mm, D 0.685 → 0.786, the four letters 1.483 → 1.485) and
#: its coverage (E 95.1 → 89.4 %, D 93.0 → 86.2 %, below the 90 % target), docs/tactile.md.
CONTACT_RIM_MM = 0.0


class ReliefMap:
    """The stitched wall: a grid of ``size`` × ``size`` mm at ``step`` mm centred on the origin.

    A cell's height is the ``quantile`` (:data:`CELL_QUANTILE`), over the contacts that reached
    it, of each contact's mean height there: a press whose reconstruction or placement went wrong does
    not drag the cells it shares with the others (each wall cell is met by several presses),
    where a mean over all samples would carry its error at its share.  A contact's outer
    ``rim_mm`` (:data:`CONTACT_RIM_MM`) is left out.  Each cell keeps its latest
    :data:`CELL_READINGS` readings; counts, weights and sums (``scatter``, ``confidence``) cover
    every sample."""

    def __init__(self, size: float = 120.0, step: float = 1.0, margin: float = 10.0,
                 rim_mm: float = CONTACT_RIM_MM, quantile: float = CELL_QUANTILE) -> None:
        if not (math.isfinite(rim_mm) and rim_mm >= 0):
            raise ValueError(f"rim_mm must be >= 0, got {rim_mm!r}")
        if not (0.0 <= quantile <= 1.0):
            raise ValueError(f"quantile must be in [0, 1], got {quantile!r}")
        self.rim_mm = float(rim_mm)
        self.quantile = float(quantile)
        self.step = float(step)
        self.size = float(size)
        self.half = 0.5 * float(size) + float(margin)
        cells = int(round(2 * self.half / self.step))
        self.shape = (cells, cells)
        self._n = np.zeros(self.shape)  # samples a cell got
        self._w = np.zeros(self.shape)  # their summed weight
        self._sum = np.zeros(self.shape)
        self._sum2 = np.zeros(self.shape)
        self._readings = np.full(self.shape + (CELL_READINGS,), np.nan)  # a ring per cell, one a contact
        self._k = np.zeros(self.shape, dtype=np.int64)  # contacts a cell got
        self._height: np.ndarray | None = None  # the heights, until the next contact
        self.contacts = 0

    @property
    def centres(self) -> np.ndarray:
        """(rows, cols, 2) wall coordinates of the cell centres (row 0 at the lowest y)."""
        c = -self.half + (np.arange(self.shape[0]) + 0.5) * self.step
        xx, yy = np.meshgrid(c, c)
        return np.stack([xx, yy], axis=-1)

    def add(self, contact: Contact, pose: ProbePose, grid: SampleGrid, upsample: int = 2) -> int:
        """Add one contact's samples (its aligned surface in the probe frame, densified by
        bilinear interpolation so that every map cell under the contact gets data); returns
        the number of cells touched.  The contact's outer ``rim_mm`` is left out."""
        rim = int(round(self.rim_mm / grid.step))
        if rim:
            mask = ndimage.binary_erosion(np.asarray(contact.mask, bool).reshape(grid.shape), iterations=rim)
            contact = replace(contact, mask=mask)
        pts, weight = contact_points(contact, grid, upsample)
        if not len(pts):
            return 0
        wall_xy = pose.to_wall(pts[:, :2])
        h = -pose.depth_mm - pts[:, 2]
        ij = np.floor((wall_xy + self.half) / self.step).astype(int)
        ok = np.all((ij >= 0) & (ij < self.shape[0]), axis=1)
        ij, h, w = ij[ok], h[ok], weight[ok]
        np.add.at(self._n, (ij[:, 1], ij[:, 0]), 1.0)
        np.add.at(self._w, (ij[:, 1], ij[:, 0]), w)
        np.add.at(self._sum, (ij[:, 1], ij[:, 0]), w * h)
        np.add.at(self._sum2, (ij[:, 1], ij[:, 0]), w * h * h)
        # this contact's own (weighted) mean height in every cell it reached: one reading each
        cells, inv = np.unique(ij[:, 1] * self.shape[1] + ij[:, 0], return_inverse=True)
        mean = np.bincount(inv, weights=w * h) / np.bincount(inv, weights=w)
        rows, cols = np.divmod(cells, self.shape[1])
        self._readings[rows, cols, self._k[rows, cols] % CELL_READINGS] = mean
        self._k[rows, cols] += 1
        self._height = None
        self.contacts += 1
        return int(len(cells))

    def clear(self) -> None:
        """Forget every contact (the grid stays)."""
        for a in (self._n, self._w, self._sum, self._sum2):
            a[:] = 0.0
        self._readings[:] = np.nan
        self._k[:] = 0
        self._height = None
        self.contacts = 0

    @property
    def count(self) -> np.ndarray:
        return self._n.copy()

    def height(self) -> np.ndarray:
        """(rows, cols) wall height: the map's ``quantile`` of the contacts' readings of a cell,
        the lower of the two readings about it (the median of an even count is the lower middle
        one: every reading is the wall's height or above it, where the film spanned), NaN where
        never touched."""
        if self._height is None:
            ordered = np.sort(self._readings, axis=-1)  # the NaN of unused slots sort last
            count = np.minimum(self._k, CELL_READINGS)[..., None]
            at = np.floor(self.quantile * np.maximum(count - 1, 0)).astype(np.int64)
            value = np.take_along_axis(ordered, at, axis=-1)[..., 0]
            self._height = np.where(count[..., 0] > 0, value, np.nan)
        return self._height.copy()

    def scatter(self) -> np.ndarray:
        """(rows, cols) s.d. of the heights the contacts gave a cell (NaN with fewer than two)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(self._w > 0, self._w, 1.0)
            mean = self._sum / w
            var = np.maximum(self._sum2 / w - mean ** 2, 0.0) * self._n / np.maximum(self._n - 1, 1)
        return np.where(self._n > 1, np.sqrt(var), np.nan)

    def confidence(self, sigma_mm: float = 0.1) -> np.ndarray:
        """(rows, cols) in [0, 1): 0 never touched; grows with the samples a cell got and falls
        with their disagreement (σ_mm: the scatter that counts as agreement)."""
        n = self._n
        sc = np.nan_to_num(self.scatter(), nan=0.0)
        return np.where(n > 0, (1.0 - 1.0 / (1.0 + n)) / (1.0 + (sc / sigma_mm) ** 2), 0.0)

    def wall_region(self) -> np.ndarray:
        """(rows, cols) the cells inside the wall's own square."""
        return np.all(np.abs(self.centres) <= 0.5 * self.size, axis=-1)

    def coverage(self, region: np.ndarray | None = None) -> float:
        """Share of the cells of ``region`` (default: the wall's own square) that were touched."""
        region = self.wall_region() if region is None else region
        return float(np.count_nonzero((self._n > 0) & region) / max(1, int(np.count_nonzero(region))))


class ContactTracker:
    """The gateway's contact state, frame by frame (explicit state, no I/O): the first
    ``baseline_frames`` surfaces become the baseline, every later one is compared with it.

    ``update(positions, normals, pose)`` returns the `contact` message (a JSON-able dict):
    ``state`` 'baseline' (still collecting), 'free' or 'contact' (this frame's detection);
    ``events``, the presses so far by :class:`ContactSegmenter`'s rule (the map's: a press counts
    once it has lasted two frames, and one free frame does not end it); with a contact ``press``,
    the number of the press it belongs to (``events + 1`` on a press's first frame), its area, peak
    depth, feature size L_r, the depth map on the sample grid (row-major, mm, 0 off contact) and,
    when a probe pose had been received (``pose``: the latest one, fields
    ``skinmap.wire.messages.POSE_FIELDS``), ``pose``: the one in force when the contact began.
    With ``pitch_mm`` and each frame's cell bending (``update(..., bending=)``), a contact also
    carries ``push_mm``: how far the press pushed the sheet in at the contact beyond what the
    rim shows (:func:`level_by_bending` with ``probe_length_mm``; the indentation from the free
    probe is about ``depth + push``), ``push_misfit_mm``, the free cells' rms misfit to the
    balloon wall's equation, and ``push_doubtful`` (:attr:`BendingLevel.doubtful`: the misfit of
    the order of the push, which is then not to be trusted), or ``push_unread`` saying why it
    could not be read.  ``pose`` is the one in force at the press's first frame in contact."""

    def __init__(self, grid: SampleGrid, baseline_frames: int = 10, k: float = 3.0, min_depth_mm: float = 0.5,
                 pitch_mm: float | None = None, probe_length_mm: float = PROBE_LENGTH_MM,
                 gauge_length_mm: float = GAUGE_LENGTH_MM) -> None:
        if baseline_frames < 1:
            raise ValueError(f"baseline_frames must be >= 1, got {baseline_frames}")
        if not (math.isfinite(probe_length_mm) and probe_length_mm > 0):
            raise ValueError(f"the probe's stiffness length must be > 0 mm, got {probe_length_mm!r}")
        self.grid, self.baseline_frames, self.k, self.min_depth_mm = grid, int(baseline_frames), float(k), float(min_depth_mm)
        self.pitch_mm, self.probe_length_mm = pitch_mm, float(probe_length_mm)
        self.gauge_length_mm = float(gauge_length_mm)
        self._frames: list[tuple[np.ndarray, np.ndarray]] = []
        self._bending: list[np.ndarray | None] = []
        self.baseline: Baseline | None = None
        self._presses = ContactSegmenter()
        self._frame = 0  # frames compared with the baseline
        self._event_pose: dict[str, float] | None = None

    @property
    def events(self) -> int:
        """Presses so far (:class:`ContactSegmenter`'s rule), counted across baselines."""
        return self._presses.events

    def reset(self) -> None:
        """Take a new baseline from the next frames (e.g. after the probe was re-inflated)."""
        self._frames, self._bending, self.baseline = [], [], None
        self._presses.abandon()

    def update(self, positions: np.ndarray, normals: np.ndarray, pose: Mapping[str, float] | None = None,
               bending: np.ndarray | None = None) -> dict:
        g = self.grid
        doc: dict = {"grid": {"rows": g.shape[0], "cols": g.shape[1], "step_mm": g.step}, "events": self.events}
        if self.baseline is None:
            self._frames.append((np.asarray(positions, float), np.asarray(normals, float)))
            self._bending.append(None if bending is None else np.asarray(bending, float))
            if len(self._frames) >= self.baseline_frames:
                read = [b for b in self._bending if b is not None]
                self.baseline = capture_baseline(self._frames, bending=read if len(read) == len(self._frames) else None)
                self._frames, self._bending = [], []
            return {**doc, "state": "baseline", "baseline_frames": len(self._frames) if self.baseline is None
                    else self.baseline_frames}
        c = detect_contact(positions, self.baseline, g, self.k, self.min_depth_mm, bending=bending)
        opened = self._presses.open_since
        self._presses.step(self._frame, c)
        self._frame += 1
        if c is None:
            return {**doc, "events": self.events, "state": "free"}
        if opened is None:
            # a pose received during the press belongs to the next press, not this one
            self._event_pose = None if pose is None else {k: float(v) for k, v in pose.items()}
        out = {**doc, "events": self.events, "press": self._presses.open_number, "state": "contact",
               **c.summary(), "depth_mm": np.round(c.depth, 4).ravel().tolist()}
        if self._event_pose is not None:
            out["pose"] = dict(self._event_pose)
        if self.pitch_mm is not None:
            placed = level_by_bending(c, self.baseline, g, self.pitch_mm, length_mm=self.probe_length_mm,
                                      gauge_length_mm=self.gauge_length_mm)
            if placed.reason:
                out["push_unread"] = placed.reason
            else:
                out["push_mm"] = round(-placed.offset_mm, 4)
                out["push_misfit_mm"] = round(placed.residual_mm, 4)
                out["push_doubtful"] = placed.doubtful
        return out


# ---------------------------------------------------------------------------------------------
# Poses estimated by registering each contact against the map so far


@dataclass(frozen=True)
class PoseEstimate:
    """A contact's pose found by registration, or why none was (``pose`` None, ``reason``)."""

    pose: ProbePose | None
    reason: str = ""
    overlap_cells: int = 0
    rms_mm: float = math.nan  # height residual over the overlap at the pose
    sd_xy_mm: float = math.nan  # 1-s.d. of the position along its worst direction (from the fit's conditioning)
    sd_angle_deg: float = math.nan


def anchor_pose(contact: Contact, grid: SampleGrid) -> ProbePose:
    """The pose that makes a first contact the map's frame: at the origin, unturned, the wall's
    base plane at the contact's least indented point."""
    pts, _ = contact_points(contact, grid)
    return ProbePose(0.0, 0.0, 0.0, float(np.min(-pts[:, 2])))


def _bin(xy: np.ndarray, h: np.ndarray, half: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean of h per cell of a (2·half/step)² grid centred on the origin, and the mask."""
    cells = int(round(2 * half / step))
    ij = np.floor((xy + half) / step).astype(int)
    ok = np.all((ij >= 0) & (ij < cells), axis=1)
    n = np.zeros((cells, cells))
    acc = np.zeros((cells, cells))
    np.add.at(n, (ij[ok, 1], ij[ok, 0]), 1.0)
    np.add.at(acc, (ij[ok, 1], ij[ok, 0]), h[ok])
    m = n > 0
    return np.where(m, acc / np.maximum(n, 1), 0.0), m


def _corr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Full cross-correlation c[t] = Σ_p a[p]·b[p + t] (t over every overlap)."""
    from scipy.signal import fftconvolve

    return fftconvolve(b, a[::-1, ::-1], mode="full")


def estimate_pose(relief: ReliefMap, contact: Contact, grid: SampleGrid, *, prior: ProbePose | None = None,
                  max_move_mm: float = 40.0, angle_range_deg: float = 70.0, angle_step_deg: float = 3.0, coarse_mm: float = 2.0, min_overlap: float = 0.3,
                  max_sd_mm: float = 0.5, max_sd_deg: float = 1.0, min_relief_mm: float = 0.3,
                  max_rms_mm: float = 0.5) -> PoseEstimate:
    """The pose (x, y, angle, depth) that best lays the contact's heights onto the map so far
    (least squares over the overlap, the depth solved in closed form), or a refusal saying why:
    too little overlap, an overlap without relief (heights that vary by less than
    ``min_relief_mm`` fix no position), an ill-conditioned fit (position s.d. beyond
    ``max_sd_mm`` or angle s.d. beyond ``max_sd_deg`` along the overlap's weakest direction,
    e.g. a straight stroke, which fixes nothing along itself), or two distinct poses fitting
    about equally well.

    Search: with a ``prior`` (e.g. the previous press's pose: the probe is moved a bounded
    step between presses) every angle within ±``angle_range_deg`` of its angle and every
    position within ``max_move_mm`` of it, without one every angle and position; angles at
    ``angle_step_deg``, shifts on a ``coarse_mm`` grid (masked correlations by FFT), then a
    local refinement on the map's cells."""
    pts, _ = contact_points(contact, grid)
    if len(pts) < 20:
        return PoseEstimate(None, f"a contact of {len(pts)} points is too small to register")
    hmap = relief.height()
    have = np.isfinite(hmap)
    if not have.any():
        return PoseEstimate(None, "the map is empty: nothing to register against")
    local_h = -pts[:, 2]  # = H + depth
    # coarse: the map and the turned contact on a coarse grid
    f = max(1, int(round(coarse_mm / relief.step)))
    cs = relief.step * f
    cells = relief.shape[0] // f
    hm = np.nan_to_num(hmap[:cells * f, :cells * f]).reshape(cells, f, cells, f)
    mm = have[:cells * f, :cells * f].reshape(cells, f, cells, f)
    cnt = mm.sum(axis=(1, 3))
    mb = cnt > 0.5 * f * f
    hb = np.where(mb, (hm * mm).sum(axis=(1, 3)) / np.maximum(cnt, 1), 0.0)
    reach = float(np.max(np.linalg.norm(pts[:, :2], axis=1))) + cs
    H, H2, Mh = hb * mb, hb * hb * mb, mb.astype(float)
    n_contact_min: float | None = None
    candidates = []  # (score, angle, x, y, overlap)
    a0, span = (prior.angle_deg, angle_range_deg) if prior is not None else (0.0, 180.0)
    for ang in a0 + np.arange(-span, span + 1e-9, angle_step_deg):
        th = math.radians(ang)
        c_, s_ = math.cos(th), math.sin(th)
        xy = np.stack([c_ * pts[:, 0] - s_ * pts[:, 1], s_ * pts[:, 0] + c_ * pts[:, 1]], -1)
        C, Mc = _bin(xy, local_h, reach, cs)
        Mcf = Mc.astype(float)
        nc = float(Mcf.sum())
        if n_contact_min is None:
            n_contact_min = min_overlap * nc
        n = _corr(Mcf, Mh)
        sc, sc2 = _corr(C * Mcf, Mh), _corr(C * C * Mcf, Mh)
        sh, sh2 = _corr(Mcf, H), _corr(Mcf, H2)
        sch = _corr(C * Mcf, H)
        ok = n >= max(n_contact_min, 10)
        nn = np.where(ok, n, 1.0)
        cov = sch / nn - sc * sh / nn ** 2
        vc = sc2 / nn - (sc / nn) ** 2
        vh = sh2 / nn - (sh / nn) ** 2
        good = ok & (vh > (0.25 * min_relief_mm) ** 2) & (vc > (0.25 * min_relief_mm) ** 2)
        score = np.where(good, cov / np.sqrt(np.maximum(vc * vh, 1e-12)), -np.inf)
        if prior is not None:
            ty = -relief.half + (np.arange(score.shape[0]) - (C.shape[0] - 1)) * cs + reach
            tx = -relief.half + (np.arange(score.shape[1]) - (C.shape[1] - 1)) * cs + reach
            near = np.hypot(tx[None, :] - prior.x_mm, ty[:, None] - prior.y_mm) <= max_move_mm
            score = np.where(near, score, -np.inf)
        # keep the best few peaks of this angle
        flat = np.argsort(score, axis=None)[-3:]
        for idx in flat:
            t = np.unravel_index(int(idx), score.shape)
            if not np.isfinite(score[t]):
                continue
            # full-correlation index → shift of the contact grid's origin on the map grid
            dy = t[0] - (C.shape[0] - 1)
            dx = t[1] - (C.shape[1] - 1)
            x = -relief.half + dx * cs + reach
            y = -relief.half + dy * cs + reach
            candidates.append((float(score[t]), float(ang), x, y, int(n[t])))
    if not candidates:
        return PoseEstimate(None, f"no placement overlaps the map by {100 * min_overlap:.0f} % of the contact "
                                  "with relief in it: the overlap cannot decide")
    candidates.sort(reverse=True)

    centres = relief.centres

    def residual(p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        x, y, ang = p
        pose = ProbePose(float(x), float(y), float(ang), 0.0)
        wxy = pose.to_wall(pts[:, :2])
        idx = (wxy + relief.half) / relief.step - 0.5
        inside = np.all((idx >= 0) & (idx <= relief.shape[0] - 1), axis=1)
        cover = ndimage.map_coordinates(have.astype(float), [idx[:, 1], idx[:, 0]], order=1, mode="constant")
        use = inside & (cover > 0.999)
        hh = ndimage.map_coordinates(np.nan_to_num(hmap), [idx[use, 1], idx[use, 0]], order=1)
        r = local_h[use] - hh
        return float(np.mean((r - r.mean()) ** 2)) if use.sum() > 10 else 1e6, use, hh, r

    gy, gx = np.gradient(np.nan_to_num(hmap), relief.step)

    def jacobian(p: np.ndarray, use: np.ndarray) -> np.ndarray:
        """∂H/∂x, ∂H/∂y, ∂H/∂θ (per radian) at the overlap points, and the depth column."""
        wxy = ProbePose(float(p[0]), float(p[1]), float(p[2]), 0.0).to_wall(pts[use, :2])
        idx = (wxy + relief.half) / relief.step - 0.5
        sx = ndimage.map_coordinates(gx, [idx[:, 1], idx[:, 0]], order=1)
        sy = ndimage.map_coordinates(gy, [idx[:, 1], idx[:, 0]], order=1)
        rx, ry = wxy[:, 0] - p[0], wxy[:, 1] - p[1]
        return np.column_stack([sx, sy, -ry * sx + rx * sy, -np.ones(len(sx))])

    def refine(cand: tuple) -> tuple[np.ndarray, float]:
        """Gauss–Newton on (x, y, θ, depth) from a coarse candidate (steps bounded to a cell)."""
        _s, ang, x, y, _n = cand
        p = np.array([x, y, ang], dtype=float)
        cost = residual(p)[0]
        for _ in range(30):
            cost, use, _hh, r = residual(p)
            if use.sum() <= 10:
                break
            jac = jacobian(p, use)
            step, *_ = np.linalg.lstsq(jac, r - 0.0, rcond=None)  # r = local_h − H ≈ J·δ + depth
            dx, dy, dth = step[:3]
            d = np.array([dx, dy, math.degrees(dth)])
            scale = min(1.0, cs / max(1e-9, math.hypot(dx, dy)), angle_step_deg / max(1e-9, abs(d[2])))
            trial = p + scale * d
            c_trial = residual(trial)[0]
            if c_trial > cost:
                trial = p + 0.25 * scale * d
                c_trial = residual(trial)[0]
                if c_trial > cost:
                    break
            p, converged = trial, math.hypot(*(scale * d[:2])) < 1e-3 and abs(scale * d[2]) < 1e-3
            cost = c_trial
            if converged:
                break
        return p, float(cost)

    best, best_cost = refine(candidates[0])
    # a rival: the best candidate that is a different placement (≥ 5 mm or ≥ 10° away)
    for cand in candidates[1:12]:
        if math.hypot(cand[2] - best[0], cand[3] - best[1]) >= 5.0 or abs(_wrap(cand[1] - best[2])) >= 10.0:
            p2, c2 = refine(cand)
            if math.hypot(p2[0] - best[0], p2[1] - best[1]) < 5.0 and abs(_wrap(p2[2] - best[2])) < 10.0:
                continue  # converged onto the same placement
            if c2 < best_cost:
                best, best_cost, p2, c2 = p2, c2, best, best_cost
            if c2 < 1.5 * best_cost + 0.0025:
                return PoseEstimate(None, f"two placements fit about equally (rms {math.sqrt(best_cost):.2f} and "
                                          f"{math.sqrt(c2):.2f} mm, {math.hypot(p2[0] - best[0], p2[1] - best[1]):.0f} mm "
                                          "apart): the overlap cannot decide")
            break
    cost, use, hh, r = residual(best)
    overlap = int(use.sum())
    if overlap < (n_contact_min or 0.0) * f * f or overlap < 20:
        return PoseEstimate(None, f"the overlap with the map is {overlap} points "
                                  f"({100 * overlap / len(pts):.0f} % of the contact): the overlap cannot decide",
                            overlap)
    if math.sqrt(cost) > max_rms_mm:
        return PoseEstimate(None, f"the best placement's heights differ from the map by {math.sqrt(cost):.2f} mm rms "
                                  f"(more than {max_rms_mm:g}): the contact matches the map nowhere it may be, "
                                  "the overlap cannot decide", overlap, math.sqrt(cost))
    if np.ptp(hh) < min_relief_mm:
        return PoseEstimate(None, f"the overlap's heights vary by {np.ptp(hh):.2f} mm only (a flat patch fixes no "
                                  "position): the overlap cannot decide", overlap)
    # conditioning: the map's slopes at the overlap points → the pose's covariance
    jac = jacobian(best, use)
    # the residuals are not white (a contact's rim and the map's binning err over a few mm):
    # count one independent sample per (3 mm)² of overlap, not one per point
    sigma = max(math.sqrt(cost), 0.05) * 3.0 / relief.step
    try:
        cov = sigma ** 2 * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return PoseEstimate(None, "the overlap's slopes do not fix the pose (singular fit): the overlap cannot decide",
                            overlap)
    sd_xy = float(math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)))
    sd_ang = float(math.degrees(math.sqrt(max(cov[2, 2], 0.0))))
    depth = float(np.mean(r))  # local_h − H = depth
    if not (sd_xy <= max_sd_mm and sd_ang <= max_sd_deg):
        return PoseEstimate(None, f"the fit is ill-conditioned (position s.d. {sd_xy:.2f} mm, angle s.d. {sd_ang:.2f}° "
                                  "along the overlap's weakest direction): the overlap cannot decide",
                            overlap, math.sqrt(cost), sd_xy, sd_ang)
    return PoseEstimate(ProbePose(float(best[0]), float(best[1]), float(_wrap(best[2])), depth), "", overlap,
                        math.sqrt(cost), sd_xy, sd_ang)


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def stitch_estimated(contacts: list[Contact], grid: SampleGrid, relief: ReliefMap, first: ProbePose | None = None,
                     sweeps: int = 2, **options: float) -> list[PoseEstimate]:
    """Stitch contacts whose poses are unknown: the first is placed by ``first`` (default
    :func:`anchor_pose`: the map is then in the first press's frame), each later one by
    :func:`estimate_pose` against the map so far; a refused one is tried again once the rest
    are in, and left out if it is still refused.  Each search starts from the nearest press in
    the sequence already placed (``max_move_mm`` and ``angle_range_deg`` bound the step).  Returns each contact's estimate (in order)."""
    if not contacts:
        return []
    # placed against a working map of whole contacts and each cell's median (the overlap a
    # registration needs: the rim left out and the upper quantile placed 5 of the bench's 64
    # presses instead of 13); ``relief``, the caller's map, is filled once the poses are known
    work = _registration_map(relief)
    out: list[PoseEstimate] = [PoseEstimate(None, "not tried")] * len(contacts)
    anchor = first or anchor_pose(contacts[0], grid)
    work.add(contacts[0], anchor, grid)
    out[0] = PoseEstimate(anchor, "the anchor")
    pending = list(range(1, len(contacts)))
    for _ in range(2):
        later = []
        for i in pending:
            # the prior: the nearest press in the sequence already placed (the probe moves a
            # bounded step between presses)
            placed = [j for j in range(len(contacts)) if out[j].pose is not None]
            near = min(placed, key=lambda j: abs(j - i))
            est = estimate_pose(work, contacts[i], grid, prior=out[near].pose, **options)
            out[i] = est
            if est.pose is None:
                later.append(i)
            else:
                work.add(contacts[i], est.pose, grid)
        if len(later) == len(pending):
            break
        pending = later
    # Errors of a chain of registrations add up: each placed contact is registered again,
    # near where it is, against the map of all the others (``sweeps`` times); the anchor stays.
    placed = [i for i in range(1, len(contacts)) if out[i].pose is not None]
    for _ in range(max(0, sweeps)):
        for i in placed:
            others = _registration_map(relief)
            for j in [0, *placed]:
                if j != i:
                    others.add(contacts[j], out[j].pose, grid)  # type: ignore[arg-type]
            est = estimate_pose(others, contacts[i], grid, prior=out[i].pose,
                                **{**options, "max_move_mm": 3.0, "angle_range_deg": 3.0})
            if est.pose is not None:
                out[i] = est
    relief.clear()
    for j in [0, *placed]:
        relief.add(contacts[j], out[j].pose, grid)  # type: ignore[arg-type]
    return out


def _registration_map(like: ReliefMap) -> ReliefMap:
    """An empty map of ``like``'s extent for registering contacts: whole contacts, each cell
    the median of its readings."""
    return ReliefMap(like.size, like.step, like.half - 0.5 * like.size, rim_mm=0.0, quantile=0.5)
