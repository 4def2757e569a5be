"""A sheet that moves, read by gauges that answer late: the gauges settle within 170 ms (the
sensor's paper), so a moving sheet is reconstructed where it was up to a third of that before,
and σ says so (skinmap.reconstruction.uncertainty.response_lag_sigma, FramePipeline's
``response_lag_s``, ``[reconstruction] response_time_ms``)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from skinmap.daemon.config import ConfigError, parse_config
from skinmap.daemon.device_setup import response_lag_for
from skinmap.daemon.pipeline import MOTION_HORIZON_S, ArrayGeometry, FramePipeline
from skinmap.emulator import physics as ph
from skinmap.reconstruction.uncertainty import response_lag_sigma
from skinmap.strains import RESPONSE_LAG_S, Calibration

N = M = 5
PITCH = 12.0
GEOMETRY = ArrayGeometry(N, M, PITCH, 0.2, 0.2)
ELEMENT_UV = np.array([[u, v] for v in (-12.0, 12.0) for u in (-18.0, 18.0)])
GF = np.full((2, 2, N, M), 1.24)
R0 = np.full((2, 2, N, M), 6.55)


def resistances(shape: ph.Shape) -> np.ndarray:
    eu, el = ph.gauge_strains(shape, N, M, pitch=PITCH)
    return R0 * (1.0 + GF * np.stack([eu, el]))


def pipeline(**kw) -> FramePipeline:
    return FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)), **kw)


def test_the_lag_sigma_of_points_moving_at_a_known_speed_is_that_speed_times_the_lag_over_root_3():
    """Points 0.1 s apart that moved 2 mm (20 mm/s) with no noise: the lag bound 57 ms puts them
    at most 1.13 mm behind, a bounded error whose s.d. is that over √3."""
    before = np.zeros((4, 3))
    now = before + np.array([0.0, 1.2, 1.6])  # |Δx| = 2 mm
    sigma = response_lag_sigma(now, before, 0.1, np.zeros(4), np.zeros(4), 0.057)
    np.testing.assert_allclose(sigma, 20.0 * 0.057 / math.sqrt(3.0), rtol=1e-12)


def test_the_lag_sigma_takes_the_frames_noise_out_of_their_difference():
    """A move no larger than the two frames' scatter is no evidence of motion (none); a larger one
    counts only its part beyond the noise: |Δx|² less both variances."""
    before = np.zeros((3, 3))
    now = np.array([[0.03, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.5]])
    scatter = np.full(3, 0.03)
    sigma = response_lag_sigma(now, before, 0.1, scatter, scatter, 0.057)
    assert sigma[0] == 0.0  # 0.03 mm against a noise of 0.042
    expected = math.sqrt(0.05**2 - 2 * 0.03**2) / 0.1 * 0.057 / math.sqrt(3.0)
    assert sigma[1] == pytest.approx(expected, rel=1e-12)
    assert sigma[2] == pytest.approx(math.sqrt(0.25 - 2 * 0.03**2) / 0.1 * 0.057 / math.sqrt(3.0), rel=1e-12)


def test_a_still_sheet_keeps_its_sigma_and_a_moving_one_gets_the_lag_in_it():
    """Through the pipeline, frames 20 ms apart by the device clock: a bump held still takes no
    lag term (its frames differ by nothing); the same bump growing by 1 mm in 100 ms takes it, at
    every node no less than the nodes' mean (the alignment floor) and most where the sheet moved,
    and the elements likewise; with the lag left out (0) σ is the reconstruction's alone."""
    def run(heights: list[float], lag: float) -> list:
        pipe = pipeline(response_lag_s=lag)
        return [pipe.process(resistances(ph.GaussianBumps(height=h, fwhm=20.0)), k, 20_000 * k, 0)
                for k, h in enumerate(heights)]

    still = run([3.0] * 6, RESPONSE_LAG_S)
    plain = run([3.0] * 6, 0.0)
    np.testing.assert_allclose(still[-1].node_sigma_mm, plain[-1].node_sigma_mm, rtol=1e-12)
    assert "response_lag_sigma_mm" not in still[-1].diagnostics

    growing = [3.0 + 0.2 * k for k in range(6)]  # 10 mm/s at the bump's top
    moving, unlagged = run(growing, RESPONSE_LAG_S), run(growing, 0.0)
    last, ref = moving[-1], unlagged[-1]
    extra = np.sqrt(np.maximum(last.node_sigma_mm**2 - ref.node_sigma_mm**2, 0.0))
    # the centre rose 0.6 mm in 60 ms in the sensor frame's terms (pinned there, the rim sinks): a
    # speed of about 10 mm/s somewhere on the sheet, a lag term of about 10 · 0.057/√3 ≈ 0.33 mm
    assert 0.1 < float(extra.max()) < 0.6
    assert float(np.min(extra)) > 0.0, "the alignment floor: no node without the lag term"
    assert last.diagnostics["response_lag_sigma_mm"] == pytest.approx(float(extra.max()), rel=0.01)
    assert np.all(last.element_sigma_mm > ref.element_sigma_mm)


def test_the_lag_term_needs_a_frame_within_reach_by_the_device_clock():
    """Frames with no usable device time (all 0), or one after a gap longer than the horizon, or
    after the device clock restarted, have no speed to read: σ is the reconstruction's."""
    heights = [3.0, 3.5, 4.0]
    for times in ([0, 0, 0], [0, int(2e6 * MOTION_HORIZON_S), int(4e6 * MOTION_HORIZON_S)], [500_000, 100_000, 0]):
        pipe, plain = pipeline(), pipeline(response_lag_s=0.0)
        for k, (h, t) in enumerate(zip(heights, times)):
            a = pipe.process(resistances(ph.GaussianBumps(height=h, fwhm=20.0)), k, t, 0)
            b = plain.process(resistances(ph.GaussianBumps(height=h, fwhm=20.0)), k, t, 0)
        np.testing.assert_allclose(a.node_sigma_mm, b.node_sigma_mm, rtol=1e-12, err_msg=f"device times {times}")


def test_the_response_time_is_a_config_key_and_a_third_of_it_the_lag():
    assert response_lag_for(parse_config({})) == pytest.approx(RESPONSE_LAG_S)
    cfg = parse_config({"reconstruction": {"response_time_ms": 90}})
    assert cfg.reconstruction.response_time_ms == 90.0
    assert response_lag_for(cfg) == pytest.approx(0.030)
    assert response_lag_for(parse_config({"reconstruction": {"response_time_ms": 0}})) == 0.0
    with pytest.raises(ConfigError, match="response_time_ms"):
        parse_config({"reconstruction": {"response_time_ms": -5}})
    with pytest.raises(ValueError, match="response_lag_s"):
        pipeline(response_lag_s=float("nan"))


def test_the_demo_hands_the_gauges_response_and_relaxation_to_the_emulator(monkeypatch):
    """`skinmap demo --response-tau S --relaxation F` runs the emulator with those gauges (off by
    default: no such options are passed)."""
    from skinmap.daemon import cli, service

    seen: list[dict] = []
    monkeypatch.setattr(cli, "start_emulator", lambda port, **kw: seen.append(kw) or object())
    monkeypatch.setattr(cli, "stop_process", lambda proc: None)
    monkeypatch.setattr(service, "run_gateway", lambda cfg, **kw: 0)
    args = cli.build_parser().parse_args(["demo", "--response-tau", "0.057", "--relaxation", "0.035"])
    assert args.func(args) == 0
    assert seen[-1]["extra"] == ["--response-tau", "0.057", "--relaxation", "0.035"]
    args = cli.build_parser().parse_args(["demo"])
    assert args.func(args) == 0
    assert seen[-1]["extra"] == []


def test_the_device_info_tells_what_the_published_sigma_carries():
    """`info` (docs/zenoh.md) names the σ terms a remote user cannot see in the numbers: the
    strain noise, the shared gain, the response lag bound and the twist prior, as configured."""
    from skinmap.daemon.device_setup import device_info, pipeline_for_hello
    from skinmap.emulator.device import Device, ScannerSpec

    hello = Device(ScannerSpec(n=5, m=5), ph.make_shape("flat")).hello()
    for doc, lag in (({}, RESPONSE_LAG_S), ({"reconstruction": {"response_time_ms": 60, "gain_sd": 0.01}}, 0.02)):
        cfg = parse_config(doc)
        info = device_info("demo", hello, pipeline_for_hello(hello, cfg), cfg, source="live")
        assert info["uncertainty"]["response_lag_s"] == pytest.approx(lag)
        assert info["uncertainty"]["gain_sd"] == cfg.reconstruction.gain_sd
        assert info["uncertainty"]["strain_sigma"] == cfg.reconstruction.strain_sigma
        assert info["uncertainty"]["twist_prior"] == "open"


def test_a_lead_scan_read_without_sigma_is_still_the_baseline_of_the_lag_term():
    """A lead scan's σ is not read (FramePipeline.process(lead=True)), but it joins the motion
    history: here the lead is 100 ms before the scan due, the baseline the lag term reads the
    speed from, and the scan published before it is 600 ms back, beyond the 500 ms horizon
    (without the lead no speed could be read).  The due frame's σ is then that of a pipeline that read the
    lead's σ, to within the lead's scatter taken as the due frame's, and the lead itself reports
    every σ unknown, its elements DEGRADED."""
    from skinmap.elements.locate import UNKNOWN_SIGMA_MM
    from skinmap.wire.messages import ElementFlag

    heights = [3.0, 3.0, 3.3, 3.6]  # 3 mm/s at the top from the third scan on
    times = [0, 400_000, 900_000, 1_000_000]  # due, due, lead, due (µs)
    leads = [False, False, True, False]
    skipping, reading = pipeline(response_lag_s=RESPONSE_LAG_S), pipeline(response_lag_s=RESPONSE_LAG_S)
    for k, (h, t, lead) in enumerate(zip(heights, times, leads)):
        scan = resistances(ph.GaussianBumps(height=h, fwhm=20.0))
        a = skipping.process(scan, k, t, 0, lead=lead)
        b = reading.process(scan, k, t, 0)
        if lead:
            assert np.all(a.node_sigma_mm == UNKNOWN_SIGMA_MM) and np.all(a.element_sigma_mm == UNKNOWN_SIGMA_MM)
            assert np.all(a.element_flags & int(ElementFlag.DEGRADED))
            np.testing.assert_array_equal(a.nodes_mm, b.nodes_mm)
    np.testing.assert_array_equal(a.element_positions_mm, b.element_positions_mm)
    assert "response_lag_sigma_mm" in a.diagnostics, "the lead 100 ms back is the baseline"
    np.testing.assert_allclose(a.node_sigma_mm, b.node_sigma_mm, rtol=0.05)
    np.testing.assert_allclose(a.element_sigma_mm, b.element_sigma_mm, rtol=0.05)
