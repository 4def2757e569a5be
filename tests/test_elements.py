"""skinmap.elements: element positions, normals, uncertainty and flags on a located surface."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap.elements import (DEGRADED_SIGMA_MM, element_flags, element_layout, fit_inconsistent, held_flags,
                              locate_elements, prior_elements)
from skinmap.wire.messages import ElementFlag

VALID, EXTRAPOLATED, DEGRADED, STALE, AMBIGUOUS = (int(f) for f in (
    ElementFlag.VALID, ElementFlag.EXTRAPOLATED, ElementFlag.DEGRADED, ElementFlag.STALE, ElementFlag.AMBIGUOUS))


def cells(n: int = 3, m: int = 3, pitch: float = 10.0) -> np.ndarray:
    u = (np.arange(m) - (m - 1) / 2) * pitch
    v = (np.arange(n) - (n - 1) / 2) * pitch
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv], axis=-1)


class TiltedPlane:
    """z = 0.1 u, σ growing with |u|: positions, normals and σ known in closed form."""

    def locate(self, uv):
        uv = np.asarray(uv, float)
        pos = np.stack([uv[:, 0], uv[:, 1], 0.1 * uv[:, 0]], axis=1)
        n = np.array([-0.1, 0.0, 1.0]) / np.sqrt(1.01)
        return pos, np.broadcast_to(n, pos.shape).copy()

    def locate_sigma(self, uv):
        return 0.01 * np.abs(np.asarray(uv, float)[:, 0])


def test_layout_knows_neighbours_and_extrapolation():
    layout = element_layout([[0.0, 0.0], [25.0, 0.0], [-10.0, 10.0]], [0.0, 0.0, 0.0], cells(), 10.0)
    assert layout.count == 3 and list(layout.extrapolated) == [False, True, False]
    assert layout.neighbour_cells.shape == (3, 9) and layout.neighbour_cells[0].all()
    with pytest.raises(ValueError, match="2 element offsets for 3"):
        element_layout(np.zeros((3, 2)), [0.0, 0.0], cells(), 10.0)


def test_elements_are_located_and_moved_along_the_normal_by_their_offset():
    layout = element_layout([[0.0, 0.0], [10.0, -5.0]], [0.0, -2.0], cells(), 10.0)
    pos, nrm, sig = locate_elements(TiltedPlane(), layout)
    n = np.array([-0.1, 0.0, 1.0]) / np.sqrt(1.01)
    np.testing.assert_allclose(nrm, [n, n])
    np.testing.assert_allclose(pos[0], [0, 0, 0])
    np.testing.assert_allclose(pos[1], np.array([10.0, -5.0, 1.0]) - 2.0 * n)
    np.testing.assert_allclose(sig, [0.0, 0.1])
    empty = element_layout(np.zeros((0, 2)), np.zeros(0), cells(), 10.0)
    assert [a.shape for a in locate_elements(TiltedPlane(), empty)] == [(0, 3), (0, 3), (0,)]


def test_flags_from_uncertainty_gauges_ambiguity_and_misfit():
    layout = element_layout([[-10.0, -10.0], [10.0, 10.0], [14.0, 0.0]], np.zeros(3), cells(), 10.0)
    valid = np.ones((2, 2, 3, 3), bool)
    sigma = np.array([0.1, DEGRADED_SIGMA_MM * 2, 0.1])
    flags = element_flags(layout, sigma, valid, ambiguous=False, inconsistent=False)
    assert list(flags) == [VALID, VALID | DEGRADED, VALID | EXTRAPOLATED]
    # every gauge of the far corner cells gone: the element there rests on the prior alone
    valid[:, :, 2, 2] = False
    valid[:, :, 1, :] = False
    valid[:, :, :, 1:] = False
    flags = element_flags(layout, np.full(3, 0.1), valid, ambiguous=True, inconsistent=False)
    assert flags[0] == VALID | DEGRADED | AMBIGUOUS  # near a lost gauge, still measured
    assert flags[1] & VALID == 0 and flags[1] & DEGRADED
    flags = element_flags(layout, np.full(3, 0.1), np.ones((2, 2, 3, 3), bool), ambiguous=False, inconsistent=True)
    assert (flags & DEGRADED).all() and (flags & VALID).all()


def test_misfit_limit_grows_with_the_noise():
    assert not fit_inconsistent(0.004, 1e-4) and fit_inconsistent(0.006, 1e-4)
    assert not fit_inconsistent(0.006, 0.002) and fit_inconsistent(0.011, 0.002)


def test_prior_and_held_elements_are_stale():
    layout = element_layout([[1.0, 2.0]], [0.5], cells(), 10.0)
    pos, nrm, sig, flags = prior_elements(layout)
    np.testing.assert_allclose(pos, [[1.0, 2.0, 0.5]])
    np.testing.assert_allclose(nrm, [[0, 0, 1]])
    assert sig[0] >= 1e3 and list(flags) == [STALE]
    assert list(held_flags(np.array([VALID, VALID | DEGRADED], np.uint8))) == [VALID | STALE, VALID | DEGRADED | STALE]


def test_a_prepared_pipeline_gives_the_same_elements_and_a_continued_one_has_nothing_to_prepare():
    """FramePipeline.prepare() (skinmapd: at HELLO, before START) builds the reconstructor and
    fills its first-frame caches; the elements are those of an unprepared pipeline, and a
    pipeline that takes over its predecessor's reconstructor does no work again."""
    from skinmap.daemon.pipeline import ArrayGeometry, FramePipeline
    from skinmap.emulator import physics as ph
    from skinmap.strains import Calibration

    geometry = ArrayGeometry(5, 5, 12.0, 0.2, 0.2)
    gf, r0 = np.full((2, 2, 5, 5), 1.24), np.full((2, 2, 5, 5), 6.55)
    uv = np.array([[-18.0, 0.0], [0.0, 0.0], [6.0, 12.0]])

    def make() -> FramePipeline:
        return FramePipeline(geometry, Calibration(gf, r0), uv, np.zeros(len(uv)))

    eu, el = ph.gauge_strains(ph.make_shape("gaussian", height=3.0, fwhm=20.0), 5, 5, pitch=12.0)
    ohm = r0 * (1.0 + gf * np.stack([eu, el]))
    prepared, plain = make(), make()
    assert prepared.prepare() is True
    assert prepared.reconstructor._noise_responses  # the first frame's Monte Carlo is done
    a, b = prepared.process(ohm, 0, 0, 0), plain.process(ohm, 0, 0, 0)
    np.testing.assert_array_equal(a.element_positions_mm, b.element_positions_mm)
    np.testing.assert_array_equal(a.element_sigma_mm, b.element_sigma_mm)
    successor = make()
    successor.continue_from(prepared)
    assert successor.prepare() is False


def test_published_scatter_is_the_surfaces_frame_to_frame_part_of_sigma_and_never_above_it():
    """The elements' and nodes' scatter (layout 2) are the surface's own
    (Surface.locate_sigma(uv, scatter=True), node_scatter_sigma): on an elastic saddle, whose σ
    holds the twist's interval, below σ; on the wire as given."""
    from skinmap.daemon.output import encode_result_elements
    from skinmap.daemon.pipeline import ArrayGeometry, FramePipeline
    from skinmap.emulator import physics as ph
    from skinmap.emulator.scenes import parse_scene_spec
    from skinmap.strains import Calibration
    from skinmap.wire.messages import decode_elements

    geometry = ArrayGeometry(5, 5, 12.0, 0.2, 0.2)
    gf, r0 = np.full((2, 2, 5, 5), 1.24), np.full((2, 2, 5, 5), 6.55)
    uv = np.array([[-18.0, 0.0], [0.0, 0.0], [6.0, 12.0], [24.0, -24.0]])
    pipeline = FramePipeline(geometry, Calibration(gf, r0), uv, np.zeros(len(uv)))
    shape = parse_scene_spec("saddle:radius=90,axis_angle=60", "elastic", 5, 5, 12.0)
    eu, el = ph.gauge_strains(shape, 5, 5, pitch=12.0)
    noise = np.random.default_rng(3).normal(0.0, 5.7e-5, (2,) + eu.shape)
    r = pipeline.process(r0 * (1.0 + gf * np.stack([eu + noise[0], el + noise[1]])), 7, 0, 0)
    surf = r.surface
    # (skinmapd reads the cell centres' and the elements' σ in one reading: the same values)
    np.testing.assert_array_equal(r.node_sigma_mm, surf.node_sigma)
    np.testing.assert_array_equal(r.element_sigma_mm, surf.locate_sigma(uv))
    np.testing.assert_allclose(r.element_scatter_mm, surf.locate_sigma(uv, scatter=True), rtol=1e-12)
    np.testing.assert_allclose(r.node_scatter_mm, surf.node_scatter_sigma, rtol=1e-12)
    assert (r.element_scatter_mm <= r.element_sigma_mm).all() and (r.node_scatter_mm <= r.node_sigma_mm).all()
    assert (r.node_scatter_mm < 0.9 * r.node_sigma_mm).any()  # the bias bounds are not scatter
    msg = decode_elements(encode_result_elements(r))
    assert msg.scatter is not None
    np.testing.assert_array_equal(msg.scatter, r.element_scatter_mm / 1000.0)


class SheetOf3x3(TiltedPlane):
    """The tilted plane, refusing (as a Surface does) any point beyond half a pitch outside the
    outer cells of a 3×3 sheet of 10 mm pitch."""

    def locate(self, uv):
        if (np.abs(np.asarray(uv, float)) > 15.0).any():
            raise ValueError("off the sheet")
        return super().locate(uv)


def test_an_element_off_the_sheet_is_not_located_and_says_so():
    """A layout made for a larger sheet: the elements on this one are located as before; one
    beyond its edge stays on the flat sheet, σ unknown, without VALID, and the layout names it."""
    uv = np.array([[-12.0, 3.0], [14.9, -15.0], [15.2, 0.0], [0.0, -40.0]])
    layout = element_layout(uv, np.zeros(4), cells(), 10.0)
    assert layout.on_sheet.tolist() == [True, True, False, False]
    np.testing.assert_array_equal(layout.located_uv, uv[:2])
    problem = layout.off_sheet_problem(3, 3)
    assert "2 of 4 elements lie off the 3x3 sheet" in problem and "u = 15.2" in problem
    assert element_layout(uv[:2], np.zeros(2), cells(), 10.0).off_sheet_problem(3, 3) == ""
    pos, nrm, sig = locate_elements(SheetOf3x3(), layout)
    np.testing.assert_allclose(pos[:2], SheetOf3x3().locate(uv[:2])[0])
    np.testing.assert_allclose(sig[:2], [0.12, 0.149])
    prior_pos, prior_nrm, prior_sig, _ = prior_elements(layout)
    np.testing.assert_array_equal(pos[2:], prior_pos[2:])
    np.testing.assert_array_equal(nrm[2:], prior_nrm[2:])
    assert (sig[2:] == prior_sig[2:]).all() and np.isfinite(pos).all()
    flags = element_flags(layout, sig, np.ones((2, 2, 3, 3), bool), ambiguous=False, inconsistent=False)
    assert [bool(f & VALID) for f in flags] == [True, True, False, False]
    assert (flags[2:] & DEGRADED).all() and (flags[2:] & EXTRAPOLATED).all()


def test_skinmapd_publishes_a_sheet_whose_layout_reaches_beyond_it_and_warns_once(tmp_path, caplog):
    """The demo's 32-element row (46.5 mm) on a 2×2 scanner (24 mm): every scan is processed
    (it failed on every one), the elements on the sheet located, the others flagged, and the
    status names the layout's problem."""
    from conftest import free_port, gateway_config

    from skinmap.daemon.device_setup import ScannerState
    from skinmap.emulator import physics as ph
    from skinmap.emulator.device import Device, ScannerSpec

    cfg = gateway_config(tmp_path, free_port(), "/dev/null", "offsheet", 20.0,
                         elements={"layout": "grid", "rows": 1, "cols": 32, "pitch_u_mm": 1.5})
    device = Device(ScannerSpec(n=2, m=2), ph.make_shape("cylinder", radius=40.0))
    state = ScannerState(cfg)
    state.on_hello(device.hello())
    with caplog.at_level("WARNING", logger="skinmapd"):
        pipeline, _ = state.ensure_pipeline()
    assert pipeline is not None and pipeline.elements.count == 32
    assert "16 of 32 elements lie off the 2x2 sheet" in state.elements_problem
    assert caplog.text.count("lie off the 2x2 sheet") == 1
    eu, el = ph.gauge_strains(ph.make_shape("cylinder", radius=40.0), 2, 2, pitch=12.0)
    gf, r0 = pipeline.calibration.gauge_factor, pipeline.calibration.base_resistance
    result = pipeline.process(r0 * (1.0 + gf * np.stack([eu, el])), 0, 0, 0)
    on = pipeline.elements.on_sheet
    assert (result.element_flags[on] & VALID).all() and not (result.element_flags[~on] & VALID).any()
    assert np.isfinite(result.element_positions_mm).all() and "non-finite" not in result.diagnostics.get("status", "")
