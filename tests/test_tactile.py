"""Tactile mapping: baseline, contact detection, feature size, stitching with given poses (on
the emulator's balloon-on-wall scene; the surfaces here are the scene's own, so the bounds are
those of the mapping, not of the reconstruction)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from skinmap.daemon.tactile import (ProbePose, ReliefMap, SampleGrid, capture_baseline, detect_contact, feature_size,
                                    read_poses_csv)
from skinmap.emulator import physics as ph
from skinmap.emulator.walls import BalloonOnWall, LetterRelief

N, PITCH = 8, 12.0
GRID = SampleGrid.for_array(N, N, PITCH, 2.0)
WALL = LetterRelief()


def _surface(shape: ph.Shape) -> tuple[np.ndarray, np.ndarray]:
    uv = GRID.uv
    return shape.position(uv), shape.normal(uv)


def _baseline():
    return capture_baseline([_surface(ph.SphereCap(80.0))])


def test_feature_size_of_a_disc_is_its_diameter():
    step = 0.5
    c = (np.arange(81) - 40) * step
    xx, yy = np.meshgrid(c, c)
    depth = np.clip(2.0 * (1.0 - (xx ** 2 + yy ** 2) / 20.0 ** 2), 0, None)  # half depth at r = 14.14
    assert feature_size(depth, step) == pytest.approx(2 * 20.0 / math.sqrt(2), abs=2 * step)
    assert feature_size(np.zeros((5, 5)), step) == 0.0


def test_no_press_no_contact_and_a_press_gives_its_depth_and_area():
    base = _baseline()
    assert detect_contact(_surface(ph.SphereCap(80.0))[0], base, GRID) is None
    flat = LetterRelief(height=1e-9)
    shape = BalloonOnWall(flat, (0.0, 0.0), 0.0, depth=3.0)
    c = detect_contact(_surface(shape)[0], base, GRID, min_depth_mm=0.05)
    assert c is not None
    assert c.peak_depth_mm == pytest.approx(3.0, abs=0.05)
    # the contact disc (r² ≈ 2Rδ) and the rim where the film is pushed in by more than 0.05 mm
    pushed = ph.SphereCap(80.0).position(GRID.uv)[:, 2] - _surface(shape)[0][:, 2]
    assert c.area_mm2 == pytest.approx(np.count_nonzero(pushed > 0.05) * GRID.step ** 2, rel=0.02)
    assert math.pi * 2 * 80.0 * 3.0 < c.area_mm2 < 1.25 * math.pi * 2 * 80.0 * 3.0


def test_a_frame_moved_rigidly_is_registered_onto_the_baseline():
    base = _baseline()
    pos = _surface(BalloonOnWall(WALL, (-30.0, 30.0), 15.0, depth=2.0))[0]
    th = math.radians(7.0)
    rot = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1.0]])
    moved = pos @ rot.T + np.array([3.0, -2.0, 1.5])
    a, b = detect_contact(pos, base, GRID), detect_contact(moved, base, GRID)
    assert np.array_equal(a.mask, b.mask)
    assert np.max(np.abs(a.depth - b.depth)) < 1e-6


def test_stitched_relief_error_below_0p15mm_and_coverage_above_90pct_with_given_poses():
    base = _baseline()
    relief = ReliefMap(size=120.0, step=1.0)
    rng = np.random.default_rng(3)
    for x in np.arange(-45.0, 46.0, 30.0):
        for y in np.arange(-45.0, 46.0, 30.0):
            pose = ProbePose(float(x), float(y), float(rng.uniform(-30, 30)), 5.0)
            c = detect_contact(_surface(BalloonOnWall(WALL, (pose.x_mm, pose.y_mm), pose.angle_deg, pose.depth_mm))[0],
                               base, GRID)
            assert c is not None
            relief.add(c, pose, GRID)
    h = relief.height()
    truth = WALL.height(relief.centres)
    touched = np.isfinite(h) & relief.wall_region()
    assert relief.coverage() >= 0.90
    assert float(np.mean(np.abs(h - truth)[touched])) <= 0.15
    conf = relief.confidence()
    assert np.all(conf[~np.isfinite(h)] == 0) and np.all((conf[touched] > 0) & (conf[touched] < 1))


def test_wrong_poses_are_seen_in_the_scatter():
    base = _baseline()
    good, bad = ReliefMap(), ReliefMap()
    for k, (x, y) in enumerate(((-30.0, 30.0), (-20.0, 30.0))):
        shape = BalloonOnWall(WALL, (x, y), 0.0, depth=5.0)
        c = detect_contact(_surface(shape)[0], base, GRID)
        good.add(c, ProbePose(x, y, 0.0, 5.0), GRID)
        bad.add(c, ProbePose(x + 8.0 * k, y, 0.0, 5.0), GRID)  # the second pose off by 8 mm
    assert np.nanmedian(bad.scatter()) > 3 * np.nanmedian(good.scatter())


def test_pose_csv_errors_name_the_column_and_line():
    poses = read_poses_csv("x_mm,y_mm,angle_deg,depth_mm\n1,2,3,4\n-5,6,7,8\n")
    assert poses[1] == ProbePose(-5.0, 6.0, 7.0, 8.0)
    with pytest.raises(ValueError, match="lacks the column"):
        read_poses_csv("x,y\n1,2\n")
    with pytest.raises(ValueError, match="line 3"):
        read_poses_csv("x_mm,y_mm,angle_deg,depth_mm\n1,2,3,4\n1,zz,3,4\n")
    with pytest.raises(ValueError, match="no rows"):
        read_poses_csv("x_mm,y_mm,angle_deg,depth_mm\n")


def test_baseline_refuses_nothing_and_mismatched_frames():
    with pytest.raises(ValueError, match="at least one"):
        capture_baseline([])
    a = _surface(ph.SphereCap(80.0))
    with pytest.raises(ValueError, match="differ"):
        capture_baseline([a, (a[0][:5], a[1][:5])])
