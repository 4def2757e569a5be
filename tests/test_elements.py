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
    layout = element_layout([[-10.0, -10.0], [10.0, 10.0], [30.0, 0.0]], np.zeros(3), cells(), 10.0)
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
