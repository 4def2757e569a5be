"""What a frame leaves for the next one is explicit (Surface.state), and reconstruct()'s cache
is safe to use from several threads."""
from __future__ import annotations

import threading

import numpy as np

from skinmap.emulator import physics as ph
from skinmap.reconstruction import FrameState, Reconstructor, reconstruct

PITCH = 12.0


def _strains(shape, n=5):
    return ph.gauge_strains(shape, n, n, PITCH, 0.2, 0.2, 10.0)


def test_a_graph_answer_leaves_its_coefficients_and_a_warm_frame_starts_from_them():
    rec = Reconstructor(5, 5)
    first = rec(*_strains(ph.GaussianBumps(height=3.0, fwhm=20.0, centre=(2.0, 1.0))))
    assert first.diagnostics.extra["model"] == "graph"
    assert isinstance(first.state, FrameState) and first.state.graph is not None
    assert first.state.graph_before is None  # a cold frame has no frame before it
    moved = _strains(ph.GaussianBumps(height=3.0, fwhm=20.0, centre=(2.5, 1.0)))
    warm = rec(*moved, previous=first)
    assert warm.diagnostics.extra["graph_fit"] == "warm"
    cold = rec(*moved, previous=first, graph_warm=False)
    assert cold.diagnostics.extra["graph_fit"] != "warm"
    # a cold start ignores the state entirely: the same answer as with no previous frame
    assert np.array_equal(cold.nodes, rec(*moved).nodes)


def test_a_general_model_answer_leaves_no_graph_state_but_its_defect_correction():
    surf = Reconstructor(5, 5, graph_fit=False)(*_strains(ph.SphereCap(80.0)))
    assert (surf.state.graph, surf.state.graph_before, surf.state.position) == (None, None, None)
    assert surf.state.defect is not None and surf.state.defect.shape == (2, 2, 5, 5)
    assert np.isfinite(surf.state.defect).all() and np.isfinite(surf.state.defect_chi2)


def _noisy_frames(shape, count: int, seed: int = 3):
    eu, el = _strains(shape)
    rng = np.random.default_rng(seed)
    return [(eu + rng.normal(0, 5.7e-5, eu.shape), el + rng.normal(0, 5.7e-5, el.shape)) for _ in range(count)], shape


def test_a_held_sheet_starts_its_defect_correction_from_the_previous_frames_with_the_same_answer():
    # A sheet the general model answers (graph_fit off), held still under noise: each warm frame
    # takes one pass of the model where a cold one takes two or three (the first, then its
    # corrections)
    rec = Reconstructor(5, 5, graph_fit=False)
    frames, shape = _noisy_frames(ph.GaussianBumps(height=3.0, fwhm=18.0, centre=(4.0, -3.0)), 6)
    passes: list[int] = []
    general = rec._general

    def counted(*args, **kwargs):
        passes[-1] += 1
        return general(*args, **kwargs)

    rec._general = counted  # type: ignore[method-assign]
    truth = shape.position(ph.cell_centres(5, 5, PITCH))
    prev = None
    for eu, el in frames:
        passes.append(0)
        surf = rec(eu, el, previous=prev)
        cold = Reconstructor(5, 5, graph_fit=False)(eu, el)  # the same frame from no previous one
        assert cold.diagnostics.extra.get("defect_steps", 0) >= 1  # (it needs a correction)
        if prev is not None:
            assert surf.diagnostics.extra.get("defect_warm") is True
            assert passes[-1] == 1
            # the same answer within the noise's own scatter (0.01-0.02 mm on this sheet)
            assert np.abs(surf.nodes - cold.nodes).max() < 0.005
            assert abs(float(np.linalg.norm(surf.nodes - truth, axis=-1).mean())
                       - float(np.linalg.norm(cold.nodes - truth, axis=-1).mean())) < 0.005
        prev = surf
    # graph_warm=False: the frame starts from none, as a cold one
    again = rec(*frames[-1], previous=prev, graph_warm=False)
    assert "defect_warm" not in again.diagnostics.extra


def test_a_moving_sheet_and_a_large_one_start_their_correction_from_none():
    # a bump moving 3 mm a frame: its strains change by more than the noise, and the correction
    # the frame before carried would misfit where the bump was
    rec = Reconstructor(5, 5, graph_fit=False)
    prev = None
    for k in range(4):
        eu, el = _strains(ph.GaussianBumps(height=3.0, fwhm=18.0, centre=(-6.0 + 3.0 * k, 2.0)))
        prev = rec(eu, el, previous=prev)
        assert "defect_warm" not in prev.diagnostics.extra
    # a held sheet of more than WARM_DEFECT_MAX_CELLS cells (13×13) starts from none as well
    big = Reconstructor(13, 13)
    eu, el = _strains(ph.SphereCap(400.0), 13)
    first = big(eu, el)
    assert first.state.defect is not None
    assert "defect_warm" not in big(eu, el, previous=first).diagnostics.extra


def test_a_previous_correction_that_no_longer_fits_is_not_used():
    # the shape moved (here: a correction that belongs to no shape at all, gauge by gauge 0.2 %
    # strain, which two passes cannot undo): the frame starts from none, and its answer is the
    # one it has without that correction
    import dataclasses

    rec = Reconstructor(5, 5, graph_fit=False)
    frames, _ = _noisy_frames(ph.SphereCap(70.0), 2)
    first = rec(*frames[0])
    assert first.state.defect is not None
    scrambled = np.random.default_rng(0).normal(0.0, 2e-3, first.state.defect.shape)
    wrong = dataclasses.replace(first.state, defect=first.state.defect + scrambled)
    first.state = wrong
    surf = rec(*frames[1], previous=first)
    assert "defect_warm" not in surf.diagnostics.extra
    first.state = dataclasses.replace(wrong, defect=None)
    assert np.array_equal(surf.nodes, rec(*frames[1], previous=first).nodes)


def test_reconstruct_from_several_threads_gives_the_sequential_answers():
    shapes = [ph.GaussianBumps(height=h, fwhm=20.0, centre=(1.0, -2.0)) for h in (1.0, 2.0, 3.0, 4.0)]
    frames = [_strains(s, 6) for s in shapes]
    want = [reconstruct(eu, el, PITCH).nodes for eu, el in frames]
    got: dict[int, np.ndarray] = {}
    errors: list[BaseException] = []

    def work(k: int) -> None:
        try:
            for _ in range(3):
                got[k] = reconstruct(*frames[k], PITCH).nodes
        except BaseException as exc:  # reported below, with the thread's own traceback lost
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(len(frames))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for k in range(len(frames)):
        assert np.array_equal(got[k], want[k])


def test_prepare_fills_the_first_frame_caches_and_changes_no_answer():
    """prepare() (skinmapd calls it at HELLO) does the first frame's one-off work; the frames
    after it are the same, bit for bit, as without it."""
    shape = ph.make_shape("gaussian", height=3.0, fwhm=20.0, centre=(3.0, -2.0))
    eu, el = ph.gauge_strains(shape, 5, 5, 12.0, 0.2, 0.2, 10.0)
    rng = np.random.default_rng(7)
    frames = [(eu + rng.normal(0, 5.7e-5, eu.shape), el + rng.normal(0, 5.7e-5, el.shape)) for _ in range(3)]
    prepared, fresh = Reconstructor(5, 5), Reconstructor(5, 5)
    prepared.prepare(5.7e-5)
    assert 5.7e-5 in prepared._noise_responses and prepared._product_noise is not None
    assert not fresh._noise_responses and fresh._product_noise is None
    prev_a = prev_b = None
    for e_u, e_l in frames:
        a = prepared(e_u, e_l, strain_sigma=5.7e-5, previous=prev_a)
        b = fresh(e_u, e_l, strain_sigma=5.7e-5, previous=prev_b)
        np.testing.assert_array_equal(a.nodes, b.nodes)
        np.testing.assert_array_equal(a.node_sigma, b.node_sigma)
        prev_a, prev_b = a, b
