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


# --- poses: the wire message, the config, the topic's assignment to events ---------------------


def test_pose_message_round_trips_and_malformed_ones_are_named():
    from skinmap.wire import messages as wire

    doc = wire.decode_pose(wire.encode_pose({"x_mm": 1.5, "y_mm": -2, "angle_deg": 30, "depth_mm": 3.0}))
    assert doc["x_mm"] == 1.5 and doc["schema"] == "skinmap.pose/1"
    with pytest.raises(wire.MessageError, match="missing field.*depth_mm"):
        wire.decode_pose(b'{"schema":"skinmap.pose/1","x_mm":1,"y_mm":2,"angle_deg":3}')
    with pytest.raises(wire.MessageError, match="'y_mm' must be"):
        wire.decode_pose(b'{"schema":"skinmap.pose/1","x_mm":1,"y_mm":"up","angle_deg":3,"depth_mm":1}')
    with pytest.raises(wire.MessageError, match="schema"):
        wire.decode_pose(b'{"schema":"skinmap.status/1","x_mm":1,"y_mm":2,"angle_deg":3,"depth_mm":1}')
    with pytest.raises(wire.MessageError, match="not valid JSON"):
        wire.decode_pose(b"x_mm=1")
    with pytest.raises(ValueError, match="finite"):
        wire.encode_pose({"x_mm": float("inf"), "y_mm": 0, "angle_deg": 0, "depth_mm": 1})


def test_docs_show_the_pose_messages_fields_and_key():
    import os

    from skinmap.wire import messages as wire

    text = open(os.path.join(os.path.dirname(__file__), "..", "docs", "zenoh.md"), encoding="utf-8").read()
    assert wire.json_table("pose") in text and "<prefix>-in/<device>/pose" in text


def test_pose_key_is_outside_the_space_the_gateway_guards():
    from skinmap.daemon.config import parse_config
    from skinmap.wire.keys import pose_key

    cfg = parse_config({"device": {"name": "dev"}, "zenoh": {"prefix": "lab/skinmap"}})
    key = pose_key("lab/skinmap", "dev")
    guard = cfg.guarded_key_expr()
    assert key == "lab/skinmap-in/dev/pose" and not key.startswith(guard[:-2])
    assert not key.startswith(parse_config({}).guarded_key_expr()[:-2])


def test_config_poses_round_trip_and_bad_rows_are_named():
    import tomllib

    from skinmap.daemon.config import ConfigError, config_to_toml, parse_config
    from skinmap.daemon.poses import poses_from_config

    cfg = parse_config(tomllib.loads("[tactile]\nposes = [[1, 2, 3, 4], [-5, 6.5, -7, 2]]\n"))
    assert poses_from_config(cfg.tactile.poses)[1] == ProbePose(-5.0, 6.5, -7.0, 2.0)
    assert parse_config(tomllib.loads(config_to_toml(cfg))).tactile == cfg.tactile
    with pytest.raises(ConfigError, match=r"tactile.poses\[1\].*4 numbers"):
        parse_config(tomllib.loads("[tactile]\nposes = [[1, 2, 3, 4], [1, 2]]\n"))
    with pytest.raises(ConfigError, match=r"tactile.poses\[0\]\[2\]"):
        parse_config(tomllib.loads("[tactile]\nposes = [[1, 2, 'a', 4]]\n"))


def test_topic_poses_go_to_the_next_event_and_a_missing_or_stray_one_is_named():
    from skinmap.daemon.poses import TimedPose, assign_poses

    a, b, c = ProbePose(1, 0, 0, 2), ProbePose(2, 0, 0, 2), ProbePose(3, 0, 0, 2)
    # b replaces a (moved again before pressing); c arrives during event 1, for event 2
    assert assign_poses([100, 200], [TimedPose(10, a), TimedPose(50, b), TimedPose(150, c)]) == [b, c]
    with pytest.raises(ValueError, match="event 2 .* no pose received on /pose since event 1"):
        assign_poses([100, 200], [TimedPose(10, a)])
    with pytest.raises(ValueError, match="event 1 .* before it"):
        assign_poses([100], [TimedPose(150, a)])
    with pytest.raises(ValueError, match="1 pose.* after the last contact event"):
        assign_poses([100], [TimedPose(10, a), TimedPose(300, b)])


def test_a_contact_carries_the_pose_in_force_when_it_began():
    from skinmap.daemon.tactile import ContactTracker

    free = _surface(ph.SphereCap(80.0))
    pressed = _surface(BalloonOnWall(WALL, (-30.0, 30.0), 10.0, 2.0))
    a = {"x_mm": -30.0, "y_mm": 30.0, "angle_deg": 10.0, "depth_mm": 2.0}
    b = {"x_mm": 30.0, "y_mm": 30.0, "angle_deg": -15.0, "depth_mm": 2.0}
    tracker = ContactTracker(GRID, baseline_frames=1)
    assert tracker.update(*free, a)["state"] == "baseline"
    assert "pose" not in tracker.update(*free, a)  # free: no contact to place
    first = tracker.update(*pressed, a)
    assert first["state"] == "contact" and first["pose"] == a
    # one frame in contact is no press yet (it may straddle one's start); it would be the first
    assert first["events"] == 0 and first["press"] == 1
    # a pose received while pressed is for the next press
    second = tracker.update(*pressed, b)
    assert second["pose"] == a and second["events"] == 1
    # one free frame does not end the press: the next contact frame is still the first press
    assert tracker.update(*free, b)["state"] == "free"
    assert tracker.update(*pressed, b)["pose"] == a and tracker.events == 1
    # two free frames do
    tracker.update(*free, b)
    tracker.update(*free, b)
    third = tracker.update(*pressed, b)
    assert third["pose"] == b and third["press"] == 2 and tracker.events == 1
    assert tracker.update(*pressed, b)["events"] == 2
    # no pose ever received: the contact says nothing of one
    bare = ContactTracker(GRID, baseline_frames=1)
    bare.update(*free)
    assert bare.update(*pressed)["state"] == "contact" and "pose" not in bare.update(*pressed)


def test_the_live_tracker_and_the_map_count_the_same_presses():
    """One segmentation rule: over a run of frames with single-frame blips in and out of contact
    (scans straddling a press's start or end), the `contact` topic's count and ``skinmap map``'s
    events agree, and a blip neither makes nor splits a press."""
    from skinmap.daemon.tactile import ContactSegmenter, ContactTracker
    from skinmap.daemon.tactilemap import contact_events

    free = _surface(ph.SphereCap(80.0))
    pressed = _surface(BalloonOnWall(WALL, (-30.0, 30.0), 10.0, 2.0))
    # F free, P pressed: a blip, a press with a one-frame gap, a press to the end
    pattern = "FF" + "P" + "FFF" + "PPP" + "F" + "PP" + "FFFF" + "PPPP"
    frames = [free] + [pressed if ch == "P" else free for ch in pattern]
    tracker = ContactTracker(GRID, baseline_frames=1)
    counts = [tracker.update(*f)["events"] for f in frames]
    starts: list[int] = []
    ends: list[int] = []
    events, _ = contact_events([f[0] for f in frames], 1, GRID, normals=[f[1] for f in frames], starts=starts,
                               ends=ends)
    assert len(events) == counts[-1] == tracker.events == 2
    assert starts == [1 + pattern.index("PPP"), 1 + pattern.index("PPPP")]
    assert ends == [1 + pattern.index("PPPP") - 5, len(frames) - 1]
    with pytest.raises(ValueError, match="min_frames must be >= 1"):
        ContactSegmenter(0)
    # a new baseline drops a press in progress, not the presses counted
    tracker.reset()
    tracker.update(*free)  # the new baseline
    assert [tracker.update(*f)["events"] for f in (pressed, pressed)] == [2, 3]
    segmenter = ContactSegmenter()
    segmenter.step(0, events[0])
    segmenter.step(1, events[0])
    segmenter.abandon()
    assert segmenter.finish() is None and segmenter.events == 1 and segmenter.open_number is None


def test_contact_poses_take_the_first_pose_within_each_event_and_name_an_event_without():
    from skinmap.daemon.poses import TimedPose, contact_poses

    a, b = ProbePose(1, 0, 0, 2), ProbePose(2, 0, 0, 2)
    carried = [TimedPose(105, a), TimedPose(110, a), TimedPose(205, b)]
    assert contact_poses([100, 200], [150, 250], carried) == [a, b]
    with pytest.raises(ValueError, match=r"contact event 2 \(300…350 ns\) has no pose on the gateway's /contact"):
        contact_poses([100, 300], [150, 350], carried)


# --- poses estimated by registration -----------------------------------------------------------


def _press(x, y, angle, depth=3.0):
    return detect_contact(_surface(BalloonOnWall(WALL, (x, y), angle, depth))[0], _baseline(), GRID)


def test_registered_pose_within_0p5mm_and_1deg_of_the_truth_on_an_overlapping_press():
    from skinmap.daemon.tactile import estimate_pose

    first, second = ProbePose(-35.0, 30.0, 10.0, 3.0), ProbePose(-20.0, 30.0, -15.0, 3.0)
    relief = ReliefMap()
    relief.add(_press(first.x_mm, first.y_mm, first.angle_deg), first, GRID)
    est = estimate_pose(relief, _press(second.x_mm, second.y_mm, second.angle_deg), GRID, prior=first)
    assert est.pose is not None, est.reason
    assert math.hypot(est.pose.x_mm - second.x_mm, est.pose.y_mm - second.y_mm) <= 0.5
    assert abs(est.pose.angle_deg - second.angle_deg) <= 1.0 and abs(est.pose.depth_mm - 3.0) <= 0.1


def test_registration_refuses_when_the_overlap_cannot_decide():
    from skinmap.daemon.tactile import estimate_pose

    first = ProbePose(-35.0, 30.0, 10.0, 3.0)
    relief = ReliefMap()
    relief.add(_press(first.x_mm, first.y_mm, first.angle_deg), first, GRID)
    # a press 70 mm away shares nothing with the map
    far = estimate_pose(relief, _press(35.0, 30.0, 0.0), GRID, prior=first)
    assert far.pose is None and "cannot decide" in far.reason
    # a flat wall: every placement fits, none is fixed
    flat = LetterRelief(height=1e-6)
    base = _baseline()
    flat_map = ReliefMap()
    c0 = detect_contact(_surface(BalloonOnWall(flat, (0.0, 0.0), 0.0, 3.0))[0], base, GRID)
    flat_map.add(c0, ProbePose(0.0, 0.0, 0.0, 3.0), GRID)
    c1 = detect_contact(_surface(BalloonOnWall(flat, (8.0, 0.0), 0.0, 3.0))[0], base, GRID)
    est = estimate_pose(flat_map, c1, GRID, prior=ProbePose(0.0, 0.0, 0.0, 3.0))
    assert est.pose is None and "cannot decide" in est.reason


def test_bridging_membrane_stays_off_the_wall_between_strokes_and_never_passes_it():
    uv = GRID.uv
    follows = BalloonOnWall(WALL, (-30.0, 30.0), 10.0, 2.0)
    bridges = BalloonOnWall(WALL, (-30.0, 30.0), 10.0, 2.0, membrane_radius=40.0)
    zf, zb = follows.position(uv)[:, 2], bridges.position(uv)[:, 2]
    wall_z = follows.wall_z(follows.position(uv)[:, :2])
    # (the envelope is a cubic spline through a 1 mm raster of the wall: within 0.05 mm of it)
    assert np.all(zb <= zf + 0.05) and np.all(zb <= wall_z + 0.3)
    assert (zf - zb).max() > 1.0  # it spans over part of a 4 mm recess


def test_one_letter_spans_its_wall_with_strokes_still_15mm_wide():
    e = LetterRelief("E")
    assert e.height(np.array([0.0, 0.0])) == pytest.approx(4.0, abs=0.01)  # the middle bar
    assert e.height(np.array([0.0, 22.0])) == pytest.approx(0.0, abs=0.01)  # between the bars
    # the bars' centre lines at y = ±44 and 0: a stroke 15 mm wide across its flank's middle
    profile = e.height(np.stack([np.zeros(241), np.linspace(-60, 60, 241)], -1))
    assert np.count_nonzero(profile > 2.0) * 0.5 == pytest.approx(3 * 15.0, abs=1.5)
    assert np.abs(e._segs).max() > 40.0  # scaled to the wall, not to a quadrant
    with pytest.raises(ValueError, match="one letter or four"):
        LetterRelief("DU")


def test_membrane_solve_keeps_the_film_off_the_wall_and_in_equilibrium_where_free():
    from skinmap.emulator.walls import solve_membrane

    c = np.arange(-20.0, 20.5, 1.0)
    xx, yy = np.meshgrid(c, c)
    gap = np.where((np.abs(xx) <= 4) & (np.abs(yy) <= 4), -1.0, 5.0)  # a square punch 1 mm in
    w, held = solve_membrane(gap, np.zeros_like(gap), 1.0, 0.1, 0.0)
    assert np.all(w <= gap + 1e-9) and np.allclose(w[held], gap[held]) and held.any()
    lap = w[:-2, 1:-1] + w[2:, 1:-1] + w[1:-1, :-2] + w[1:-1, 2:] - 4 * w[1:-1, 1:-1]
    inner_free, inner_held = ~held[1:-1, 1:-1], held[1:-1, 1:-1]
    assert np.abs(lap[inner_free]).max() < 1e-9  # a tensioned film with no load: harmonic where free
    assert lap[inner_held].min() > -1e-9  # the wall only pushes (its reaction T·Δw ≥ 0)
    assert w[0].max() == 0.0 and -1.0 < w[held.any(axis=1)].min() + 1e-9


def test_pressed_membrane_touches_the_strokes_spans_beside_them_and_never_passes_the_wall():
    from skinmap.emulator.walls import Membrane

    wall = LetterRelief("E")
    mem = BalloonOnWall(wall, (0.0, 22.0), 0.0, 2.0, membrane=Membrane())
    follows = BalloonOnWall(wall, (0.0, 22.0), 0.0, 2.0)
    uv = SampleGrid.for_array(5, 5, 12.0, 1.0).uv
    x = mem.position(uv)
    assert np.all(x[:, 2] <= mem.wall_z(x[:, :2]) + 1e-6)
    gap = mem.clearance(x[:, :2])
    # the bars (wall y = 0 and 44) 22 mm either side of the apex: held on their tops where the
    # balloon reaches them (within 20 mm of the apex; farther out its sphere drops below them)
    on_top = (wall.height(mem.to_wall(x[:, :2])) > 3.99) & (np.hypot(x[:, 0], x[:, 1]) < 20.0)
    assert on_top.sum() > 20 and gap[on_top].max() < 0.05
    # follows touches the floor between the bars everywhere; the film stands off it by up to
    # what a span of radius T/p = 40 mm beside a 4 mm step allows
    near = np.hypot(x[:, 0], x[:, 1]) < 18.0  # where the balloon meets the base plane
    assert follows.clearance(follows.position(uv)[near, :2]).max() < 0.31
    assert 1.0 < gap[near].max() <= 4.0
    with pytest.raises(ValueError, match="not both"):
        BalloonOnWall(wall, membrane=Membrane(), membrane_radius=40.0)


def _pressed_membrane(centre: tuple[float, float]):
    """A 5 x 5 sheet at 12 mm pressed 2 mm on the E wall (the solved film), its true surface
    and its contact registered by the rim."""
    from skinmap.emulator.walls import Membrane

    grid = SampleGrid.for_array(5, 5, 12.0, 2.0)
    free = ph.SphereCap(80.0)
    base = capture_baseline([(free.position(grid.uv), free.normal(grid.uv))])
    shape = BalloonOnWall(LetterRelief("E"), centre, 10.0, 2.0, membrane=Membrane())
    truth = shape.position(grid.uv)
    contact = detect_contact(truth, base, grid)
    assert contact is not None
    touch = contact.mask.ravel() & (shape.clearance(truth[:, :2]) < 0.05)
    return grid, shape, truth, contact, touch


def test_a_press_on_the_floor_is_levelled_to_within_0p25mm_of_its_true_place_from_more_than_0p5mm():
    from skinmap.daemon.tactile import level_on_floor

    grid, shape, truth, contact, touch = _pressed_membrane((45.0, 11.0))  # beside the E, on the floor
    pose = ProbePose(45.0, 11.0, 10.0, 2.0)
    by_rim = np.abs(contact.positions[touch, 2] - truth[touch, 2]).mean()
    lv = level_on_floor(contact, pose, grid)
    assert lv.reason == "" and lv.offset_mm > 0.3  # moved away from the wall: the rim was pushed in
    levelled = np.abs(lv.contact.positions[touch, 2] - truth[touch, 2]).mean()
    assert by_rim > 0.5 and levelled < 0.25


def test_a_press_that_touches_only_the_relief_stays_on_its_rim_and_says_why():
    from skinmap.daemon.tactile import level_on_floor

    grid, shape, truth, contact, touch = _pressed_membrane((0.0, 0.0))  # on the E's middle bar
    xy = truth[:, :2]
    assert not np.any((shape.clearance(xy) < 0.05) & (shape.wall.height(shape.to_wall(xy)) < 0.01))
    lv = level_on_floor(contact, ProbePose(0.0, 0.0, 10.0, 2.0), grid)
    assert "touched only the relief" in lv.reason and lv.offset_mm == 0.0
    assert np.array_equal(lv.contact.positions, contact.positions)


def test_floor_levelling_names_a_bad_parameter():
    from skinmap.daemon.tactile import level_on_floor

    c = detect_contact(_surface(BalloonOnWall(WALL, (-30.0, 30.0), 0.0, 3.0))[0], _baseline(), GRID)
    assert c is not None
    for kw, name in (({"quantile": 0.0}, "quantile"), ({"band_mm": -1.0}, "band_mm"),
                     ({"min_area_mm2": math.nan}, "min_area_mm2")):
        with pytest.raises(ValueError, match=name):
            level_on_floor(c, ProbePose(-30.0, 30.0, 0.0, 3.0), GRID, **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="depth"):
        level_on_floor(c, ProbePose(-30.0, 30.0, 0.0, math.inf), GRID)


def test_one_misplaced_press_does_not_move_the_cells_the_others_agree_on():
    """A cell's height is a quantile of the presses' readings (the median): three presses
    agree, a fourth comes in 1.5 mm off (its reconstruction or its level gone wrong); the mean
    of all samples would carry a quarter of that, the quantile none of it."""
    from dataclasses import replace

    pose = ProbePose(0.0, 0.0, 0.0, 3.0)
    good = _press(pose.x_mm, pose.y_mm, pose.angle_deg)
    off = replace(good, positions=good.positions + np.array([0.0, 0.0, 1.5]))
    relief, alone = ReliefMap(), ReliefMap()
    for c in (good, good, good, off):
        relief.add(c, pose, GRID)
    alone.add(good, pose, GRID)
    h, ref = relief.height(), alone.height()
    reached = np.isfinite(ref)
    assert reached.sum() > 100 and np.array_equal(np.isfinite(h), reached)
    assert np.max(np.abs(h - ref)[reached]) < 1e-9
    # the mean of the samples, which scatter() and confidence() still describe, is a quarter off
    assert np.nanmedian(relief.scatter()[reached]) > 0.5


def test_a_cell_keeps_its_latest_readings_only():
    """A long log's map stays bounded: past CELL_READINGS contacts a cell's oldest readings give
    way, so the height follows the latest presses (here the wall moved 2 mm between sessions)."""
    from dataclasses import replace

    from skinmap.daemon.tactile import CELL_READINGS

    pose = ProbePose(0.0, 0.0, 0.0, 3.0)
    first = _press(pose.x_mm, pose.y_mm, pose.angle_deg)
    later = replace(first, positions=first.positions - np.array([0.0, 0.0, 2.0]))
    relief = ReliefMap()
    size = relief._readings.nbytes
    for _ in range(CELL_READINGS):
        relief.add(first, pose, GRID)
    before = relief.height()
    for _ in range(CELL_READINGS // 2 + 1):  # a majority of the kept readings
        relief.add(later, pose, GRID)
    after = relief.height()
    reached = np.isfinite(before)
    assert np.allclose((after - before)[reached], 2.0)
    assert relief._readings.nbytes == size and relief.contacts == CELL_READINGS + CELL_READINGS // 2 + 1


def test_a_cell_half_touched_half_spanned_reads_the_touching_presses_height_by_its_median():
    """The wall is rigid: a press reads a cell at the wall's height where its film touched it and
    above it (towards the probe) where the film spanned over it.  Two presses touch, two span
    1 mm above: the median, of an even count the lower middle reading (CELL_QUANTILE), is the
    touching presses' height, where the mean of the two middle readings would split the
    difference and the upper third would take the spanning presses' (docs/tactile.md).  With
    three spanning and one touching, the median is a spanning press's: the map says what most
    presses read, and the low reading alone does not decide."""
    from dataclasses import replace

    from skinmap.daemon.tactile import CELL_QUANTILE

    pose = ProbePose(0.0, 0.0, 0.0, 3.0)
    touch = _press(pose.x_mm, pose.y_mm, pose.angle_deg)
    span = replace(touch, positions=touch.positions - np.array([0.0, 0.0, 1.0]))  # 1 mm off the wall
    median, upper, alone, mostly_span = (ReliefMap(rim_mm=0.0), ReliefMap(rim_mm=0.0, quantile=2 / 3),
                                         ReliefMap(rim_mm=0.0), ReliefMap(rim_mm=0.0))
    for c in (span, touch, span, touch):
        median.add(c, pose, GRID)
        upper.add(c, pose, GRID)
    for c in (span, touch, span, span):
        mostly_span.add(c, pose, GRID)
    alone.add(touch, pose, GRID)
    reached = np.isfinite(alone.height())
    assert CELL_QUANTILE == 0.5 and reached.sum() > 100
    assert np.max(np.abs(median.height() - alone.height())[reached]) < 1e-9
    assert np.allclose((upper.height() - alone.height())[reached], 1.0)
    assert np.allclose((mostly_span.height() - alone.height())[reached], 1.0)


def test_a_contacts_rim_is_left_out_of_the_map():
    """With ``rim_mm`` 2 the contact's outer 2 mm (one sample ring at a 2 mm step), where the
    sheet leaves the wall, reaches no map cell; what remains lies inside what the whole contact
    reaches (the default, CONTACT_RIM_MM 0)."""
    pose = ProbePose(-30.0, 30.0, 10.0, 3.0)
    c = _press(pose.x_mm, pose.y_mm, pose.angle_deg)
    whole, inner = ReliefMap(), ReliefMap(rim_mm=2.0)
    n_whole, n_inner = whole.add(c, pose, GRID), inner.add(c, pose, GRID)
    assert 0 < n_inner < n_whole
    assert not np.any(np.isfinite(inner.height()) & ~np.isfinite(whole.height()))
    for kw, name in (({"rim_mm": -1.0}, "rim_mm"), ({"rim_mm": math.nan}, "rim_mm"), ({"quantile": 1.5}, "quantile")):
        with pytest.raises(ValueError, match=name):
            ReliefMap(**kw)  # type: ignore[arg-type]


def test_a_pressed_film_whose_slope_jumps_at_the_wall_reads_no_spike_on_its_gauges():
    """Where the wall takes over from the solved film their slopes differ (a crease finer than
    the solve's grid): the gauges read its turning, not a spike (one press of the bench's 64 on
    E read +75 % on both layers of one gauge through the quadrature's point derivatives)."""
    from skinmap.emulator.walls import Membrane

    rng = np.random.default_rng(0)
    angles = rng.uniform(-30, 30, 29)
    shape = BalloonOnWall(LetterRelief("E"), (-7.5, -7.5), float(angles[28]), 2.0,
                          membrane=Membrane(half=max(50.0, 0.5 * 5 * 12.0 * 2 ** 0.5 + 5.0)))
    eu, el = ph.gauge_strains(shape, 5, 5, 12.0, 0.2, 0.2, 10.0)
    # the crease there: the film's normal turns by 0.18 within 5 µm along the gauge (3, 2) along u
    x, normal = shape.position_and_normal(np.array([[4.4050, 12.0], [4.4100, 12.0]]))
    assert np.linalg.norm(normal[1] - normal[0]) > 0.1
    # a 2 mm press on a 4 mm relief stretches and bends the film by a few per cent, no more
    assert max(np.abs(eu).max(), np.abs(el).max()) < 0.1
    # the mean of the two layers is the stretch: below what the steepest flank would give
    assert np.abs(0.5 * (eu + el)).max() < 0.06


def _helmholtz_press(centre: tuple[float, float], length: float, plate_depth: float | None = None,
                     push: float = 2.0, contact_radius: float = 11.0):
    """A closed form of a press, independent of the emulator's membrane solve: a 5 x 5 sheet at
    12 mm on a sphere of R 80 mm whose free part is pushed in along its normal by
    w = −push·K0(r/ℓ)/K0(a/ℓ), r from ``centre`` (a solution of ∇²w = w/ℓ², the free wall's
    equation), and whose part within a = ``contact_radius`` is pressed further in (or, with
    ``plate_depth``, lies on the plate z = −depth).  Returns the grid, the baseline (with the
    sphere's cell bending 2/R), the true pressed samples, the frame as the sensor reports it
    (moved by an arbitrary rigid motion) and its cell bending (2/R − ∇²w at the cell's centre:
    point gauges, read with ``gauge_length_mm=0``)."""
    from scipy.special import k0

    grid = SampleGrid.for_array(5, 5, 12.0, 2.0)
    free = ph.SphereCap(80.0)
    uv = grid.uv
    b, nrm = free.position(uv), free.normal(uv)
    cells = ph.cell_centres(5, 5, 12.0).reshape(-1, 2)
    c = np.asarray(centre, float)

    def w_of(points_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.hypot(*(points_xy - c).T)
        outside = r >= contact_radius
        w = np.where(outside, -push * k0(np.maximum(r, contact_radius) / length) / k0(contact_radius / length),
                     -push - 0.01 * (contact_radius ** 2 - r ** 2))
        return w, outside

    w, _ = w_of(b[:, :2])
    truth = b + w[:, None] * nrm
    if plate_depth is not None:
        inside = np.hypot(*(b[:, :2] - c).T) < contact_radius
        truth[inside, 2] = -plate_depth
    # point gauges (gauge_length_mm=0 where this is read): each cell's bending change is w's
    # Laplacian at its centre, w/ℓ² where free (the closed form's own), 0.04 /mm inside
    w_cells, outside = w_of(free.position(cells)[:, :2])
    lap_cells = np.where(outside, w_cells / length ** 2, 0.04)
    bend0 = np.full((5, 5), 2.0 / 80.0)
    bend = bend0 - lap_cells.reshape(5, 5)
    # the sensor's own frame: turned 0.05 rad about a tilted axis and moved
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(0.05) * k + (1 - math.cos(0.05)) * k @ k
    reported = truth @ rot.T + np.array([1.0, -2.0, 3.0])
    base = capture_baseline([(b, nrm)], bending=[bend0])
    return grid, base, truth, reported, bend


@pytest.mark.parametrize("centre", [(0.0, 0.0), (7.0, -5.0)])
def test_a_contact_placed_by_its_free_cells_bending_lies_within_0p05mm_of_its_true_place_from_more_than_0p5mm(centre):
    from skinmap.daemon.tactile import level_by_bending

    grid, base, truth, reported, bend = _helmholtz_press(centre, 14.6)
    contact = detect_contact(reported, base, grid, bending=bend)
    assert contact is not None and contact.bending_change is not None
    m = contact.mask.ravel()
    by_rim = np.abs(contact.positions[m] - truth[m]).max(axis=1).mean()
    lv = level_by_bending(contact, base, grid, 12.0, length_mm=14.6, gauge_length_mm=0.0)
    assert lv.reason == "" and lv.cells >= 6
    placed = np.linalg.norm(lv.contact.positions[m] - truth[m], axis=1)
    assert by_rim > 0.5 and placed.mean() < 0.05 and placed.max() < 0.1
    assert lv.offset_mm < -0.3  # moved towards −z: the rim had been pushed in
    # with the wrong stiffness length the free cells disagree and the contact lands elsewhere
    wrong = level_by_bending(contact, base, grid, 12.0, length_mm=10.0, gauge_length_mm=0.0)
    assert np.linalg.norm(wrong.contact.positions[m] - truth[m], axis=1).mean() > 0.2
    assert lv.residual_mm < 0.1


def test_a_contact_without_cell_bending_or_free_cells_stays_on_its_rim_and_says_why():
    from skinmap.daemon.tactile import level_by_bending

    grid, base, _, reported, bend = _helmholtz_press((0.0, 0.0), 14.6)
    plain = detect_contact(reported, capture_baseline([(base.positions, base.normals)]), grid)
    assert plain is not None
    lv = level_by_bending(plain, base, grid, 12.0)
    assert "no cell bending" in lv.reason and lv.offset_mm == 0.0 and lv.contact is plain
    grid, base, _, reported, bend = _helmholtz_press((0.0, 0.0), 14.6, contact_radius=30.0)
    wide = detect_contact(reported, base, grid, bending=bend)
    assert wide is not None
    lv = level_by_bending(wide, base, grid, 12.0)
    assert "cannot be read" in lv.reason and np.array_equal(lv.contact.positions, wide.positions)
    for kw, name in (({"length_mm": 0.0}, "stiffness length"), ({"margin_mm": math.nan}, "margin_mm")):
        with pytest.raises(ValueError, match=name):
            level_by_bending(wide, base, grid, 12.0, **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="bending map"):
        detect_contact(reported, base, grid, bending=np.zeros((4, 4)))
    with pytest.raises(ValueError, match="baseline frames"):
        capture_baseline([(base.positions, base.normals)], bending=[])


def test_the_stiffness_length_fitted_on_plate_presses_is_within_3pct_of_the_true_one():
    from skinmap.daemon.tactile import fit_probe_length

    contacts, poses = [], []
    for depth, a in ((1.0, 9.0), (2.0, 11.0), (3.0, 13.0)):
        # the free wall meets the plate at the contact's edge: the sphere's sag there plus the push
        sag = 80.0 - math.sqrt(80.0 ** 2 - a ** 2)
        push = (depth - sag) * 80.0 / math.sqrt(80.0 ** 2 - a ** 2)
        grid, base, _, reported, bend = _helmholtz_press((0.0, 0.0), 12.0, plate_depth=depth, push=push,
                                                         contact_radius=a)
        c = detect_contact(reported, base, grid, bending=bend)
        assert c is not None
        contacts.append(c)
        poses.append(ProbePose(0.0, 0.0, 0.0, depth))
    fit = fit_probe_length(contacts, poses, base, grid, 12.0, gauge_length_mm=0.0)
    assert fit.contacts == 3 and not fit.skipped
    assert abs(fit.length_mm - 12.0) < 0.36
    # the range of indentation the length was fitted over (skinmap map prints it)
    peaks = [c.peak_depth_mm for c in contacts]
    assert fit.indentation_mm == (min(peaks), max(peaks)) and fit.indentation_mm[0] < fit.indentation_mm[1]
    with pytest.raises(ValueError, match="poses"):
        fit_probe_length(contacts, poses[:2], base, grid, 12.0)


def test_the_configs_probe_length_is_the_mappings_default_and_a_bad_one_is_named():
    from skinmap.daemon.config import ConfigError, TactileConfig, parse_config
    from skinmap.daemon.tactile import PROBE_LENGTH_MM

    assert TactileConfig().probe_length_mm == PROBE_LENGTH_MM
    assert parse_config({"tactile": {"probe_length_mm": 12.5}}).tactile.probe_length_mm == 12.5
    with pytest.raises(ConfigError, match="probe_length_mm"):
        parse_config({"tactile": {"probe_length_mm": 0}})


def test_the_gateways_contact_carries_the_push_read_from_the_bending_within_0p05mm():
    """ContactTracker with the sheet's pitch and each frame's cell bending: a contact carries
    ``push_mm``, how far the press pushed the sheet in beyond what its rim shows (the closed-form
    press of _helmholtz_press: its true value is known); without bending it says why not."""
    from skinmap.daemon.tactile import ContactTracker, displacement

    grid, base, truth, reported, bend = _helmholtz_press((4.0, 3.0), 14.6)
    tracker = ContactTracker(grid, baseline_frames=2, pitch_mm=12.0, gauge_length_mm=0.0)
    for _ in range(2):
        assert tracker.update(base.positions, base.normals, bending=base.bending)["state"] == "baseline"
    doc = tracker.update(reported, base.normals, bending=bend)
    assert doc["state"] == "contact"
    _, moved, mask = displacement(reported, tracker.baseline)
    true_push = float((moved[mask, 2] - truth[mask, 2]).mean())
    assert true_push > 0.5 and abs(doc["push_mm"] - true_push) < 0.05 and doc["push_misfit_mm"] < 0.05
    plain = ContactTracker(grid, baseline_frames=1, pitch_mm=12.0)
    plain.update(base.positions, base.normals)
    doc = plain.update(reported, base.normals)
    assert "push_mm" not in doc and "no cell bending" in doc["push_unread"]
    with pytest.raises(ValueError, match="stiffness length"):
        ContactTracker(grid, probe_length_mm=-1.0)


def test_cells_whose_gauges_read_a_contacts_crease_are_left_out_and_an_unpushed_rim_reads_no_push():
    """The emulator's kinematic press (the sheet pushed onto the wall, a 0.3 mm rounded crease,
    the balloon elsewhere untouched): no push beyond the rim, but the cells next to the contact
    read the crease (Δκ up to 0.03 /mm, ℓ²Δκ ≈ 7 mm); left out as far off the rest, the push
    read is the true one within 0.05 mm."""
    from skinmap.daemon.tactile import level_by_bending
    from skinmap.strains import cell_bending

    n = 8
    grid = SampleGrid.for_array(n, n, 12.0, 2.0)
    free = ph.SphereCap(80.0)

    def bending(shape: ph.Shape) -> np.ndarray:
        return cell_bending(*ph.gauge_strains(shape, n, n, 12.0, 0.2, 0.2, 10.0), 0.2, 0.2)

    base = capture_baseline([(free.position(grid.uv), free.normal(grid.uv))], bending=[bending(free)])
    shape = BalloonOnWall(WALL, (-30.0, 30.0), 10.0, 2.0)
    c = detect_contact(shape.position(grid.uv), base, grid, bending=bending(shape))
    assert c is not None and c.bending_change is not None and np.nanmax(c.bending_change) > 0.02
    lv = level_by_bending(c, base, grid, 12.0)
    m = c.mask.ravel()
    true_shift = float((shape.position(grid.uv)[m, 2] - c.positions[m, 2]).mean())
    assert lv.reason == "" and abs(lv.offset_mm - true_shift) < 0.05 and lv.residual_mm < 0.05


def test_map_refuses_a_stiffness_fit_on_estimated_poses_and_a_bad_length_before_reading_the_log(tmp_path):
    from skinmap.daemon.tactilemap import map_log

    missing = tmp_path / "never-read.mcap"
    with pytest.raises(ValueError, match="given poses"):
        map_log(missing, estimate=True, fit_length=True)
    with pytest.raises(ValueError, match="stiffness length must be > 0"):
        map_log(missing, probe_length_mm=-3.0)
    with pytest.raises(ValueError, match="reference must be"):
        map_log(missing, reference="shaft")


def test_a_move_whose_misfit_reaches_half_of_it_is_doubtful_and_the_map_summary_says_so():
    """BendingLevel.doubtful: moved, with the free cells' misfit at least PUSH_DOUBT_RATIO of the
    move and PUSH_DOUBT_FLOOR_MM; skinmap map's summary cautions on each such contact and counts
    them."""
    from skinmap.daemon.tactile import PUSH_DOUBT_RATIO, BendingLevel, level_by_bending
    from skinmap.daemon.tactilemap import MapReport

    grid, base, _, reported, bend = _helmholtz_press((0.0, 0.0), 14.6)
    c = detect_contact(reported, base, grid, bending=bend)
    assert c is not None
    good = level_by_bending(c, base, grid, 12.0, length_mm=14.6, gauge_length_mm=0.0)
    assert not good.doubtful and good.residual_mm < PUSH_DOUBT_RATIO * abs(good.offset_mm)
    bad = BendingLevel(c, -1.0, 8, 0.6)
    unread = BendingLevel(c, 0.0, 0, math.nan, "no cell bending was read with it")
    light = BendingLevel(c, -0.05, 8, 0.06)  # a light press: a noise-sized misfit is no doubt
    assert bad.doubtful and not unread.doubtful and not light.doubtful
    out = MapReport(frames=20, baseline_frames=10, events=[c, c, c], levels=[good, bad, unread]).format()
    lines = out.splitlines()
    assert "caution" not in lines[1] and "not to be trusted" in lines[2] and "no cell bending" in lines[3]
    assert "caution: 1 of 3 contacts" in out


def test_a_press_sequence_reads_each_gauge_on_the_shape_held_at_its_own_instant():
    """A scan that straddles a press's start reads some gauges on the free balloon and the rest
    on the solved press, each exactly as that shape alone reads it (a solved press by its own
    creased route)."""
    from skinmap.emulator.walls import FlatPlate, Membrane, PressSequence

    seq = PressSequence(FlatPlate(), [(3.0, -2.0, 10.0, 2.0)], rest_s=1.0, hold_s=1.0, membrane=Membrane(half=50.0))
    press, free = seq.presses[0], ph.SphereCap(80.0)
    assert press.membrane is not None
    centres = np.array([[0.0, 0.0], [12.0, 0.0], [-12.0, 12.0], [0.0, -12.0]])
    directions = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 1.0]])
    offsets = np.array([0.2, -0.2])
    t = np.array([0.5, 1.5, 0.99, 1.01])  # free, pressed, free, pressed
    got = seq.layer_strains(centres, directions, offsets, 10.0, t, 8, 4)
    on_press = press.layer_strains(centres, directions, offsets, 10.0, t, 8, 4)
    on_free = free.layer_strains(centres, directions, offsets, 10.0, t, 8, 4)
    pressed = seq.press_at(t) == 0
    assert pressed.tolist() == [False, True, False, True]
    np.testing.assert_allclose(got[:, pressed], on_press[:, pressed], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[:, ~pressed], on_free[:, ~pressed], rtol=0, atol=1e-12)
    assert np.abs(on_press - on_free)[:, pressed].max() > 1e-4  # the press reads otherwise
