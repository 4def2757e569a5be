"""Sheets above 64 cells keep the height graph for the frames the general model misfits
(docs/reconstruction.md, "Larger sheets: the graph where the general model misfits"): a bump
sharper than the cells on 12×12 and 16×16, in the library and through skinmapd's pipeline (its
replay); what the larger fit needs (the banded linear start, the projection onto a basis finer
than the fine grid); and a graph answer read through its own derivatives, its mirror too (both
signs of a 45° saddle flagged)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import aligned_error
from scipy.linalg import lstsq

from skinmap.emulator import physics as ph
from skinmap.reconstruction import Reconstructor
from skinmap.reconstruction.engine import unit_data
from skinmap.reconstruction.graphfit import GraphFit, knots_per_pitch

PITCH, H, G = 12.0, 0.2, 10.0
NOISE = 0.0057e-2


@pytest.fixture(scope="module")
def sheets():
    return {n: (Reconstructor(n, n, PITCH, H, H, G), Reconstructor(n, n, PITCH, H, H, G, graph_fit=False))
            for n in (12, 16)}


@pytest.mark.parametrize("n, height, centre", [(12, 5.0, (21.0, -9.0)), (16, -5.0, (-40.0, 33.0))])
def test_a_sharp_bump_on_a_large_sheet_is_within_0_03_mm_noise_free_and_0_1_noisy_where_the_general_model_alone_is_beyond_0_15(
        sheets, n, height, centre):
    default, general = sheets[n]
    centres = ph.cell_centres(n, n, PITCH)
    shape = ph.GaussianBumps(height=height, fwhm=15.0, centre=centre)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    truth = shape.position(centres)
    alone = general(eu, el)
    assert alone.diagnostics.extra["chi2_per_gauge"] > 8.0  # the general model misfits: the rescue's cue
    assert aligned_error(alone.nodes, truth) > 0.15
    clean = default(eu, el)
    assert clean.diagnostics.extra["model"] == "graph"
    assert aligned_error(clean.nodes, truth) < 0.03
    # with the sensor's noise (which alone moves a 12×12 or 16×16 sheet by 0.03-0.05 mm)
    rng = np.random.default_rng(n)
    surf = default(eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape))
    assert surf.diagnostics.extra["model"] == "graph"
    assert aligned_error(surf.nodes, truth) < 0.1
    # the next frame, the bump moved by 0.5 mm, starts warm from this graph
    moved = ph.GaussianBumps(height=height, fwhm=15.0, centre=(centre[0] + 0.5, centre[1]))
    eu2, el2 = ph.gauge_strains(moved, n, n, PITCH, H, H, G)
    nxt = default(eu2 + rng.normal(0, NOISE, eu.shape), el2 + rng.normal(0, NOISE, el.shape), previous=surf)
    assert nxt.diagnostics.extra["graph_fit"] == "warm"
    assert aligned_error(nxt.nodes, moved.position(centres)) < 0.1


def test_sheets_above_144_cells_fit_the_graph_on_knots_every_half_pitch(sheets):
    """The rescue's cost is one band factorisation a warm frame, n·b² with n = (kN + 3)(kM + 3)
    unknowns for k knots a pitch: 12×12 keeps pitch/3 (1521 unknowns), 16×16 takes pitch/2 (1225,
    where pitch/3 had 2601), and a 16×16 sharp bump is still read within 0.03 mm noise-free
    (the parametrised test above)."""
    assert sheets[12][0]._graph_fit().size == (3 * 12 + 3) ** 2
    assert sheets[16][0]._graph_fit().size == (2 * 16 + 3) ** 2
    assert knots_per_pitch(12, 12) == 3 and knots_per_pitch(8, 19) == 2 and knots_per_pitch(5, 5) == 3


def test_a_smooth_large_sheet_the_general_model_fits_fits_no_graph(sheets):
    default, _ = sheets[16]
    for shape in (ph.Saddle(300.0, axis_angle=20.0), ph.SphereCap(-250.0), ph.GaussianBumps(height=3.0, fwhm=77.0)):
        eu, el = ph.gauge_strains(shape, 16, 16, PITCH, H, H, G)
        surf = default(eu, el)
        assert surf.diagnostics.extra["model"] == "general"
        assert "graph_fit" not in surf.diagnostics.extra  # no cold fit was tried


def test_the_banded_linear_start_is_the_least_squares_solution():
    """The linear start (small-slope turning rows J₀, prior P) solved on the band equals the dense
    least-squares solution of [J₀/σ; P^½] c = [Θ/σ; 0], a gauge left out included."""
    n = 5
    rec = Reconstructor(n, n, PITCH, H, H, G, graph_fit=True)
    fit = rec._graph_fit()
    assert isinstance(fit, GraphFit)
    shape = ph.GaussianBumps(height=2.0, fwhm=20.0, centre=(4.0, -3.0))
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    eu[0, 2, 3] = np.nan
    turning, _, valid = unit_data(eu, el, H, H, G)
    sigma_t = math.sqrt(2.0) * NOISE / (2 * H)
    got = fit._start(turning.ravel(), valid.ravel(), sigma_t)
    w = valid.ravel().astype(float) / sigma_t
    j = np.zeros((w.size, fit.size))
    np.add.at(j, (np.repeat(np.arange(w.size), fit.idx.shape[1]), fit.idx.ravel()), (fit._j0 * w[:, None]).ravel())
    prior = fit._prior_sparse.toarray()
    evals, evecs = np.linalg.eigh(prior)
    root = (evecs * np.sqrt(np.maximum(evals, 0.0))) @ evecs.T
    want = lstsq(np.vstack([j, root]), np.concatenate([w * np.where(valid.ravel(), turning.ravel(), 0.0),
                                                        np.zeros(fit.size)]))[0]
    assert np.abs(got - want).max() < 1e-6 * max(1.0, np.abs(want).max())


@pytest.mark.parametrize("n, bound", [(12, 0.03), (16, 0.04)])
def test_skinmapd_on_12x12_and_16x16_sheets_fits_a_sharp_bump_as_a_graph_within_0_03_and_0_04_mm_and_replays_it_from_the_block_start(
        n, bound):
    """The daemon's pipeline on 12×12 and 16×16 (graph_fit on, its default): a sharp bump sliding
    along the rows is answered by the graph (rescued: the general model misfits it) on every
    frame, within 0.03 mm of the truth on 12×12 and 0.04 mm on 16×16, whose graph has knots every
    pitch/2 (measured 0.016-0.033; the general model alone: 0.21 and 0.24 mm), and a log that
    starts at a block's first scan replays the same bits from the take-over of the restart chain
    on (the chains run for the rescue as for small sheets)."""
    from conftest import pipeline_sheet

    from skinmap.daemon.pipeline import GRAPH_ADOPT_SCANS, GRAPH_RESTART_SCANS, FramePipeline
    from skinmap.strains import Calibration

    geometry, element_uv, gf, r0 = pipeline_sheet(n, n, PITCH)
    start = 2 * GRAPH_RESTART_SCANS - 2
    count = GRAPH_ADOPT_SCANS + 5

    def shape(seq: int) -> ph.GaussianBumps:
        return ph.GaussianBumps(height=5.0, fwhm=15.0, centre=(-8.0 + 0.5 * (seq - start), 4.0))

    scans = {}
    for seq in range(start, start + count):
        eu, el = ph.gauge_strains(shape(seq), n, n, PITCH, H, H, G)
        scans[seq] = r0 * (1.0 + gf * np.stack([eu, el]))

    def run(seqs):
        pipe = FramePipeline(geometry, Calibration(gf, r0), element_uv, np.zeros(len(element_uv)))
        out = {seq: pipe.process(scans[seq], seq, 0, 0) for seq in seqs}
        return pipe, out

    pipe, live = run(range(start, start + count))
    assert pipe.reconstructor.graph_rescue and not pipe.reconstructor.graph_fit
    assert pipe._previous.diagnostics.extra["model"] == "graph"
    centres = ph.cell_centres(n, n, PITCH)
    for seq, frame in live.items():
        assert frame.surface.diagnostics.extra["model"] == "graph", seq
        assert aligned_error(frame.nodes_mm, shape(seq).position(centres)) < bound, seq
    block = start + 2
    _, replay = run(range(block, start + count))
    if n == 12:
        # above 256 cells skinmapd keeps the general model (no graph fit at all; the library
        # offers none there either, GRAPH_RESCUE_MAX_CELLS)
        big, big_uv, big_gf, big_r0 = pipeline_sheet(17, 17, PITCH)
        large = FramePipeline(big, Calibration(big_gf, big_r0), big_uv, np.zeros(len(big_uv)))
        assert not large.reconstructor.graph_rescue and not large.reconstructor.graph_fit
    for seq in range(block + GRAPH_ADOPT_SCANS, start + count):
        assert np.array_equal(live[seq].element_positions_mm, replay[seq].element_positions_mm), seq


def test_a_smooth_sheet_projected_onto_a_basis_finer_than_the_fine_grid_reads_its_own_gauges():
    """Above 8×8 the fine grid is coarser than the graph's knots (12×12: 25 nodes for 39
    B-splines a side): the projection of a surface's heights onto the basis (the general model's
    answer as the cold fit's start) must fill the B-splines between the nodes smoothly, so that a
    twisted quadric's own heights give back its gauges (the pseudo-inverse rippled between the
    nodes: its turning off by 6 times the signal)."""
    n = 12
    fit = Reconstructor(n, n, PITCH, H, H, G)._graph_fit()
    assert len(fit._fine_u) < fit.nbu  # the case in question
    shape = ph.Quadric(0.007, 0.004, -0.005)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    turning, stretch, _ = unit_data(eu, el, H, H, G)
    uu, vv = np.meshgrid(fit._fine_u, fit._fine_v)
    nodes = shape.position(np.stack([uu, vv], -1))
    model_turning, model_stretch = fit._model(fit.coeffs_from_positions(nodes), False)
    assert np.abs(model_turning - turning.ravel()).max() < 1e-3 * np.abs(turning).max()
    assert np.abs(model_stretch - stretch.ravel()).max() < 1e-3 * np.abs(stretch - 1.0).max()


def test_a_graph_answer_on_a_sheet_coarser_than_its_knots_reads_its_own_gauges():
    """A graph answer's surface takes the graph's own derivatives at the fine nodes: on 12×12
    (fine grid 6 mm, knots 4 mm) a noise-free sharp bump's answer reads its gauges within 2 per
    gauge at the posterior check (by the nodes' differences: 7.8, σ widened by it), and points
    between the nodes near the bump stay within 0.15 mm (0.21)."""
    n = 12
    rec = Reconstructor(n, n, PITCH, H, H, G)
    shape = ph.GaussianBumps(height=5.0, fwhm=15.0, centre=(7.0, -5.0))
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    surf = rec(eu, el)
    assert surf.diagnostics.extra["model"] == "graph"
    assert surf.diagnostics.extra["chi2_per_gauge"] < 2.0
    centres = ph.cell_centres(n, n, PITCH).reshape(-1, 2)
    uv = np.vstack([centres, np.random.default_rng(0).uniform(-30.0, 30.0, (300, 2))])
    got, truth = surf.locate(uv)[0], shape.position(uv)
    # the best rigid motion of the nodes onto the truth, then every point
    p, q = got[: len(centres)], truth[: len(centres)]
    u, _, vt = np.linalg.svd((p - p.mean(0)).T @ (q - q.mean(0)))
    rot = (u * np.array([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])) @ vt
    err = np.linalg.norm((got - p.mean(0)) @ rot + q.mean(0) - truth, axis=1)
    assert err[len(centres):].max() < 0.15


def test_both_signs_of_a_saddle_at_45_degrees_on_8x8_are_read_alike_and_flagged():
    """The graph's mirror is read through the same patches as the answer (the graph's own
    derivatives): a saddle at 45° and its mirror give identical strains, so every frame is
    flagged ambiguous (read one by the graph's derivatives and the other by the nodes'
    differences, one of these lost its flag)."""
    n = 8
    rec = Reconstructor(n, n, PITCH, H, H, G)
    shape = ph.Saddle(-150.0, axis_angle=45.0)
    eu, el = ph.gauge_strains(shape, n, n, PITCH, H, H, G)
    rng = np.random.default_rng(45)
    for _ in range(6):
        surf = rec(eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape))
        assert surf.diagnostics.extra["model"] == "graph"
        assert surf.mirror is not None


def test_a_large_graph_answers_node_sigma_from_the_band_factor_equals_the_dense_route(monkeypatch, sheets):
    """On 12×12 a graph answer's node σ comes from the band factor and the Jacobian by each gauge's own
    coefficients (|J y|, y = H⁻¹s):
    the same values as through the Jacobian and the dense triangle."""
    import skinmap.reconstruction.graphfit as graphfit

    default, _ = sheets[12]
    shape = ph.GaussianBumps(height=5.0, fwhm=15.0, centre=(9.0, 4.0))
    eu, el = ph.gauge_strains(shape, 12, 12, PITCH, H, H, G)
    rng = np.random.default_rng(7)
    eu, el = eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)
    uv = np.random.default_rng(1).uniform(-60.0, 60.0, (20, 2))
    banded = default(eu, el)
    assert banded.diagnostics.extra["model"] == "graph"
    # (σ is computed when first read: read it before the route changes)
    band_nodes, band_points = banded.node_sigma.copy(), banded.locate_sigma(uv)
    monkeypatch.setattr(graphfit, "_BAND_SIGMA_SIZE", 10 ** 9)
    dense = default(eu, el)
    assert np.allclose(band_nodes, dense.node_sigma, rtol=1e-9, atol=1e-12)
    assert np.allclose(band_points, dense.locate_sigma(uv), rtol=1e-9, atol=1e-12)
    assert band_nodes.max() > 0.0


def test_a_warm_graph_on_a_large_sheet_ends_where_a_recheck_finds_the_general_model_reads_the_gauges(sheets):
    """A graph begun on a sharp bump (12×12, 5 mm, FWHM 15 mm) is carried on by its warm start
    alone while the bump broadens frame by frame: at FWHM 45 mm, which the general model reads
    within the noise (χ² about 1 a gauge against 3000 at the start), the chain is still a graph.
    Asked to recheck (skinmapd every GRAPH_AUDIT_SCANS on these sheets), the reconstructor
    computes the general model's answer and, as it would not have tried the graph cold on that
    frame, answers with it; near the start, where the general model misfits, the graph stays."""
    default, _ = sheets[12]
    rng = np.random.default_rng(5)
    previous, early = None, None
    for fwhm in np.arange(15.0, 46.0, 1.5):
        eu, el = ph.gauge_strains(ph.GaussianBumps(height=5.0, fwhm=fwhm, centre=(21.0, -9.0)), 12, 12, PITCH, H, H, G)
        eu, el = eu + rng.normal(0, NOISE, eu.shape), el + rng.normal(0, NOISE, el.shape)
        if previous is not None and early is None:
            early = default(eu, el, previous=previous, graph_recheck=True)
        before = previous
        previous = default(eu, el, previous=previous)
    assert early is not None and early.diagnostics.extra["model"] == "graph"
    assert previous.diagnostics.extra["model"] == "graph", previous.diagnostics.extra.get("graph_fit")
    rechecked = default(eu, el, previous=before, graph_recheck=True)
    assert rechecked.diagnostics.extra["model"] == "general", rechecked.diagnostics.extra.get("graph_fit")
    assert "not needed" in rechecked.diagnostics.extra["graph_fit"]


def test_skinmapd_asks_a_larger_sheet_for_the_recheck_on_its_audit_scans_only():
    """FramePipeline passes ``graph_recheck`` on scans whose sample index is a multiple of
    GRAPH_AUDIT_SCANS, on sheets above AUDIT_MAX_CELLS (where the graph is a rescue), and never on
    smaller ones (audited by a catch-up chain instead)."""
    from conftest import pipeline_sheet

    from skinmap.daemon.pipeline import AUDIT_MAX_CELLS, GRAPH_AUDIT_SCANS, FramePipeline
    from skinmap.strains import Calibration

    for n in (12, 5):
        geometry, element_uv, gf, r0 = pipeline_sheet(n, n, PITCH)
        pipe = FramePipeline(geometry, Calibration(gf, r0), element_uv, np.zeros(len(element_uv)))
        real = pipe.reconstructor
        asked: dict[int, bool] = {}

        class Recording:
            graph_rescue = real.graph_rescue

            def __call__(self, eu, el, **kw):
                asked[seq] = bool(kw.get("graph_recheck", False))
                return real(eu, el, **kw)

            def __getattr__(self, name):
                return getattr(real, name)

        pipe.reconstructor = Recording()
        eu, el = ph.gauge_strains(ph.GaussianBumps(height=2.0, fwhm=40.0), n, n, PITCH, H, H, G)
        for seq in range(3 * GRAPH_AUDIT_SCANS - 2, 3 * GRAPH_AUDIT_SCANS + 2):
            pipe.process(r0 * (1.0 + gf * np.stack([eu, el])), seq, 20_000 * seq, 0)
        larger = n * n > AUDIT_MAX_CELLS
        assert asked == {seq: larger and seq % GRAPH_AUDIT_SCANS == 0 for seq in asked}, (n, asked)
        assert larger == any(asked.values())
