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


def test_a_general_model_answer_leaves_no_graph_state():
    surf = Reconstructor(5, 5, graph_fit=False)(*_strains(ph.SphereCap(80.0)))
    assert surf.state == FrameState()


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
