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
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["SampleGrid", "Baseline", "Contact", "ContactTracker", "ProbePose", "ReliefMap", "capture_baseline",
           "displacement", "detect_contact", "feature_size", "read_poses_csv"]


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


def capture_baseline(frames: list[tuple[np.ndarray, np.ndarray]], sigma_floor_mm: float = 0.01) -> Baseline:
    """Baseline from pre-contact frames [(positions (K, 3), normals (K, 3)), ...]; ValueError if
    there are none or they differ in size."""
    if not frames:
        raise ValueError("a baseline needs at least one pre-contact frame")
    k = frames[0][0].shape
    if any(p.shape != k or n.shape != k for p, n in frames):
        raise ValueError("baseline frames differ in their number of samples")
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
    return Baseline(pos, nrm, sigma)


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

    def summary(self) -> dict:
        return {"area_mm2": round(self.area_mm2, 3), "peak_depth_mm": round(self.peak_depth_mm, 4),
                "feature_size_mm": round(self.feature_size_mm, 3), "samples": int(self.mask.sum())}


def detect_contact(positions: np.ndarray, baseline: Baseline, grid: SampleGrid, k: float = 3.0,
                   min_depth_mm: float = 0.5) -> Contact | None:
    """The contact in one frame, or None if nothing is pressed in beyond k·σ."""
    d, moved, contact = displacement(positions, baseline, k, min_depth_mm)
    if not contact.any():
        return None
    depth = np.where(contact, -d, 0.0).reshape(grid.shape)
    mask = contact.reshape(grid.shape)
    return Contact(mask, depth, float(mask.sum() * grid.step ** 2), float(depth.max()),
                   feature_size(depth, grid.step), moved)


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


class ReliefMap:
    """The stitched wall: a grid of ``size`` × ``size`` mm at ``step`` mm centred on the origin."""

    def __init__(self, size: float = 120.0, step: float = 1.0, margin: float = 10.0) -> None:
        self.step = float(step)
        self.size = float(size)
        self.half = 0.5 * float(size) + float(margin)
        cells = int(round(2 * self.half / self.step))
        self.shape = (cells, cells)
        self._n = np.zeros(self.shape)
        self._sum = np.zeros(self.shape)
        self._sum2 = np.zeros(self.shape)
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
        the number of cells touched."""
        pos = contact.positions.reshape(*grid.shape, 3)
        mask = contact.mask.astype(float)
        if upsample > 1:
            pos = np.stack([ndimage.zoom(pos[..., i], upsample, order=1) for i in range(3)], axis=-1)
            mask = ndimage.zoom(mask, upsample, order=1)
        keep = mask >= 0.999
        pts = pos[keep]
        if not len(pts):
            return 0
        wall_xy = pose.to_wall(pts[:, :2])
        h = -pose.depth_mm - pts[:, 2]
        ij = np.floor((wall_xy + self.half) / self.step).astype(int)
        ok = np.all((ij >= 0) & (ij < self.shape[0]), axis=1)
        ij, h = ij[ok], h[ok]
        np.add.at(self._n, (ij[:, 1], ij[:, 0]), 1.0)
        np.add.at(self._sum, (ij[:, 1], ij[:, 0]), h)
        np.add.at(self._sum2, (ij[:, 1], ij[:, 0]), h * h)
        self.contacts += 1
        return int(len(np.unique(ij, axis=0)))

    @property
    def count(self) -> np.ndarray:
        return self._n.copy()

    def height(self) -> np.ndarray:
        """(rows, cols) mean wall height, NaN where never touched."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self._n > 0, self._sum / np.maximum(self._n, 1), np.nan)

    def scatter(self) -> np.ndarray:
        """(rows, cols) s.d. of the heights the contacts gave a cell (NaN with fewer than two)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self._sum / np.maximum(self._n, 1)
            var = np.maximum(self._sum2 / np.maximum(self._n, 1) - mean ** 2, 0.0) * self._n / np.maximum(self._n - 1, 1)
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
        return float(np.count_nonzero((self._n > 0) & region) / max(1, np.count_nonzero(region)))


class ContactTracker:
    """The gateway's contact state, frame by frame (explicit state, no I/O): the first
    ``baseline_frames`` surfaces become the baseline, every later one is compared with it.

    ``update(positions, normals)`` returns the `contact` message (a JSON-able dict): ``state``
    'baseline' (still collecting), 'free' or 'contact'; with a contact its area, peak depth,
    feature size L_r and the depth map on the sample grid (row-major, mm, 0 off contact)."""

    def __init__(self, grid: SampleGrid, baseline_frames: int = 10, k: float = 3.0, min_depth_mm: float = 0.5) -> None:
        if baseline_frames < 1:
            raise ValueError(f"baseline_frames must be >= 1, got {baseline_frames}")
        self.grid, self.baseline_frames, self.k, self.min_depth_mm = grid, int(baseline_frames), float(k), float(min_depth_mm)
        self._frames: list[tuple[np.ndarray, np.ndarray]] = []
        self.baseline: Baseline | None = None
        self.events = 0
        self._in_contact = False

    def reset(self) -> None:
        """Take a new baseline from the next frames (e.g. after the probe was re-inflated)."""
        self._frames, self.baseline, self._in_contact = [], None, False

    def update(self, positions: np.ndarray, normals: np.ndarray) -> dict:
        g = self.grid
        doc: dict = {"grid": {"rows": g.shape[0], "cols": g.shape[1], "step_mm": g.step}, "events": self.events}
        if self.baseline is None:
            self._frames.append((np.asarray(positions, float), np.asarray(normals, float)))
            if len(self._frames) >= self.baseline_frames:
                self.baseline = capture_baseline(self._frames)
                self._frames = []
            return {**doc, "state": "baseline", "baseline_frames": len(self._frames) if self.baseline is None
                    else self.baseline_frames}
        c = detect_contact(positions, self.baseline, g, self.k, self.min_depth_mm)
        if c is None:
            self._in_contact = False
            return {**doc, "state": "free"}
        if not self._in_contact:
            self.events += 1
            self._in_contact = True
        return {**doc, "events": self.events, "state": "contact", **c.summary(),
                "depth_mm": np.round(c.depth, 4).ravel().tolist()}
