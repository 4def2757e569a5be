"""The graph fit's periodic cold restart (daemon/pipeline.py): begun beside the published frames
at a block's first scan, taken over GRAPH_ADOPT_SCANS later, the same bits on a worker thread and
in line, and a replay from the block's start agreeing from the take-over on; and the cold fits a
published frame needs, deferred to a catch-up chain (GRAPH_CATCH_UP_SCANS)."""
from __future__ import annotations

import threading

import numpy as np
import pytest
from conftest import pipeline_sheet

from skinmap.daemon.pipeline import (GRAPH_ADOPT_SCANS, GRAPH_AUDIT_SCANS, GRAPH_CATCH_UP_SCANS, GRAPH_RESTART_SCANS,
                                     GRAPH_SYNC_SCANS, FramePipeline, InlineBackground, WorkerBackground, graph_adopt,
                                     graph_audit, graph_restart)
from skinmap.emulator.physics import gauge_strains, make_shape
from skinmap.reconstruction.graphfit import WARM_LINEAR, GraphFit
from skinmap.strains import Calibration

N = M = 5
PITCH = 12.0
GEOMETRY, ELEMENT_UV, GF, R0 = pipeline_sheet(N, M, PITCH)
START = 3 * GRAPH_RESTART_SCANS - 3  # three scans before a block's start
COUNT = GRAPH_ADOPT_SCANS + 8


def scan(seq: int) -> np.ndarray:
    """A bump sliding along the rows, one step a scan: the warm start matters."""
    shape = make_shape("gaussian", height=4.0, fwhm=18.0, u0=-6.0 + 0.25 * (seq - START), v0=-4.0)
    eps_u, eps_l = gauge_strains(shape, N, M, pitch=PITCH)
    return R0 * (1.0 + GF * np.stack([eps_u, eps_l]))


SCANS = {seq: scan(seq) for seq in range(START, START + COUNT)}


def pipeline(**kw) -> FramePipeline:
    return FramePipeline(GEOMETRY, Calibration(GF, R0), ELEMENT_UV, np.zeros(len(ELEMENT_UV)), **kw)


def run(pipe: FramePipeline, seqs) -> dict[int, np.ndarray]:
    return {seq: pipe.process(SCANS[seq], seq, 0, 0).element_positions_mm for seq in seqs}


def test_restart_and_adoption_rules():
    assert graph_restart(None, 5) and graph_restart(63, 64) and graph_restart(60, 130)
    assert not graph_restart(64, 65) and not graph_restart(64, 127)
    assert not graph_adopt(64, 64 + GRAPH_ADOPT_SCANS - 1) and graph_adopt(64, 64 + GRAPH_ADOPT_SCANS)
    assert graph_adopt(64, 3)  # the sample index went back (a restarted scanner)
    assert GRAPH_SYNC_SCANS == GRAPH_RESTART_SCANS + GRAPH_ADOPT_SCANS


def test_audits_begin_only_where_a_replay_from_the_block_start_begins_them_too():
    # every GRAPH_AUDIT_SCANS, from the restart chain's take-over on, and done before the next
    # block's start
    begun = [seq for seq in range(0, 3 * GRAPH_RESTART_SCANS) if graph_audit(seq)]
    assert begun and all(seq % GRAPH_AUDIT_SCANS == 0 for seq in begun)
    within = {seq % GRAPH_RESTART_SCANS for seq in begun}
    assert min(within) >= GRAPH_ADOPT_SCANS and max(within) + GRAPH_CATCH_UP_SCANS < GRAPH_RESTART_SCANS


def test_an_audit_is_taken_over_only_where_it_fits_the_scan_with_the_lower_objective(monkeypatch):
    """The bump sliding over the rows: each audit begun after the take-over, and the look at the
    restart chain before it, is decided on the scan both chains fitted last, by the lower graph
    objective there."""
    import skinmap.daemon.pipeline as pipeline_module

    decided: list[tuple] = []
    lower = pipeline_module._lower_objective

    def spy(audit, audit_seq, published, published_seq):
        verdict = lower(audit, audit_seq, published, published_seq)
        decided.append((audit, audit_seq, published_seq, verdict,
                        audit.state.graph_objective < published.state.graph_objective))
        return verdict

    monkeypatch.setattr(pipeline_module, "_lower_objective", spy)
    pipe = pipeline()
    for seq in range(START, START + COUNT + 2 * GRAPH_AUDIT_SCANS):
        count = len(decided)
        pipe.process(SCANS.get(seq, scan(seq)), seq, 0, 0)
        if len(decided) > count:
            audit, audit_seq, published_seq, verdict, lower_there = decided[-1]
            assert audit_seq == published_seq == seq - 1
            assert verdict == lower_there
    assert len(decided) >= 2, "fewer audits than expected"


def test_published_frames_never_wait_for_the_cold_restart():
    pipe = pipeline()
    rec = pipe.reconstructor
    calls: list[tuple[int, bool]] = []

    def spy(eu, el, **kw):
        calls.append(("previous" in kw, kw.get("graph_warm", True)))
        return rec(eu, el, **kw)

    spy.graph_fit = rec.graph_fit
    pipe.reconstructor = spy
    block = START + 3
    run(pipe, range(START, START + COUNT))
    # the first scan has nothing to start from; every later published frame is warm
    assert calls[0] == (False, True) and all(c == (True, True) for c in calls[1:]), calls
    # the chain began cold at the block's first scan on its own reconstructor, and was taken over
    assert pipe._chain_reconstructor is not None and pipe._chain_reconstructor is not rec
    assert pipe.chain_origin == block and pipe._chain is None


def test_replay_from_the_block_start_agrees_from_the_take_over_on():
    live = run(pipeline(), range(START, START + COUNT))
    block = START + 3
    replay = run(pipeline(), range(block, START + COUNT))  # a log that starts at the block
    adopted = block + GRAPH_ADOPT_SCANS
    for seq in range(adopted, START + COUNT):
        assert np.array_equal(live[seq], replay[seq]), seq
    # before the take-over the live frames are warm from the scans before the block (they may
    # differ in the last bits, but are the same sheet)
    for seq in range(block, adopted):
        assert np.allclose(live[seq], replay[seq], atol=0.05), seq


def one_blas_thread():
    """BLAS on one thread for the whole process, as skinmapd and replay set it (gateway.
    limit_blas_threads): otherwise the reconstructors' own per-call limits on two threads undo
    each other's (the limit is process-wide), and the last bits depend on the timing."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1)


def test_worker_thread_gives_the_bits_of_the_inline_run():
    worker = WorkerBackground()
    with one_blas_thread():
        try:
            threaded = run(pipeline(background=worker), range(START, START + COUNT))
        finally:
            worker.close()
        inline = run(pipeline(background=InlineBackground()), range(START, START + COUNT))
    for seq in threaded:
        assert np.array_equal(threaded[seq], inline[seq]), seq


def test_worker_runs_jobs_off_the_calling_thread_unless_asked_first():
    worker = WorkerBackground()
    here = threading.current_thread().name
    try:
        ran = threading.Event()
        seen: list[str] = []
        first = worker.submit(lambda: (seen.append(threading.current_thread().name), ran.set()))
        assert ran.wait(10.0)
        first.result()
        assert seen == [worker._name]
        # a worker held up: a job not yet started runs on the thread that asks for its result
        release = threading.Event()
        busy = worker.submit(lambda: release.wait(10.0))
        queued = worker.submit(lambda: threading.current_thread().name)
        assert queued.result() == here
        release.set()
        assert busy.result() is True
        failing = worker.submit(lambda: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            failing.result()
    finally:
        worker.close()


class _BrokenChain:
    """A chain reconstructor that fails every job."""
    graph_fit = True

    def __call__(self, *a, **kw):
        raise RuntimeError("chain reconstructor broke")


def test_a_failing_chain_is_dropped_and_the_frames_go_on(caplog):
    pipe = pipeline(defer_cold_fits=False)  # the published frames fit cold themselves: a restart chain begins

    pipe._chain_reconstructor = _BrokenChain()
    with caplog.at_level("ERROR", logger="skinmapd"):
        results = [pipe.process(SCANS[seq], seq, 0, 0) for seq in range(START, START + COUNT)]
    assert all(np.isfinite(r.element_positions_mm).all() for r in results)
    assert pipe._chain is None and pipe.chain_origin is None  # nothing taken over
    assert "restart chain" in caplog.text and "chain reconstructor broke" in caplog.text


@pytest.mark.parametrize("switch_at", [2, 8])
def test_a_new_pipeline_continues_the_chain(switch_at):
    """After a reconnect (same geometry) the new pipeline takes over the chain under way: the
    results are those of one pipeline throughout."""
    one = run(pipeline(), range(START, START + COUNT))
    first = pipeline()
    out = run(first, range(START, START + switch_at + 3))
    second = pipeline()
    second.continue_from(first)
    out.update(run(second, range(START + switch_at + 3, START + COUNT)))
    for seq in one:
        assert np.array_equal(one[seq], out[seq]), seq


def test_worker_starts_no_job_while_the_frames_thread_is_busy():
    worker = WorkerBackground()
    worker.BUSY_WAIT_S = 5.0
    started = threading.Event()
    try:
        worker.submit(lambda: None).result()  # the worker is up
        with worker.busy():
            job = worker.submit(started.set)
            assert not started.wait(0.3)  # held back while the frame is under way
        assert started.wait(5.0)  # and run once it is done
        job.result()
    finally:
        worker.close()


# A bump that jumps a pitch and a half between two scans: the warm fit from the scan before fails
JUMP_FROM, JUMP_AT, JUMP_COUNT = 200, 208, 16  # inside one block (192-255): no restart chain


def jump_scan(seq: int) -> np.ndarray:
    u0 = -6.0 + 0.25 * (seq - JUMP_FROM) if seq < JUMP_AT else 12.0 + 0.25 * (seq - JUMP_AT)
    shape = make_shape("gaussian", height=4.0, fwhm=18.0, u0=u0, v0=-4.0)
    eps_u, eps_l = gauge_strains(shape, N, M, pitch=PITCH)
    return R0 * (1.0 + GF * np.stack([eps_u, eps_l]))


JUMP_SCANS = {seq: jump_scan(seq) for seq in range(JUMP_FROM, JUMP_FROM + JUMP_COUNT)}


def run_jump(pipe: FramePipeline) -> dict:
    return {seq: pipe.process(JUMP_SCANS[seq], seq, 0, 0) for seq in JUMP_SCANS}


@pytest.fixture
def no_misread_refit(monkeypatch):
    """The jump's misreading warm fit is refitted in the frame from its linear start
    (graphfit.GraphFit._misread_refit); switched off, the frame needs a cold fit, which is what
    these tests follow."""
    monkeypatch.setattr(GraphFit, "_misread_refit", lambda self, *args: None)


@pytest.mark.usefixtures("no_misread_refit")
def test_a_frame_whose_warm_fit_fails_is_answered_without_a_cold_fit_in_the_frame():
    worker = WorkerBackground()
    try:
        pipe = pipeline(background=worker)
        graph = pipe.reconstructor._graph
        cold_fits: list[int] = []
        fit_cold = graph.fit_cold
        graph.fit_cold = lambda *a, **kw: (cold_fits.append(1), fit_cold(*a, **kw))[1]
        deferring = {JUMP_FROM: pipe.process(JUMP_SCANS[JUMP_FROM], JUMP_FROM, 0, 0)}
        assert cold_fits  # the first frame, with nothing before it, fits cold itself
        cold_fits.clear()
        deferring.update({seq: pipe.process(JUMP_SCANS[seq], seq, 0, 0) for seq in JUMP_SCANS if seq > JUMP_FROM})
    finally:
        worker.close()
    undeferred = run_jump(pipeline(defer_cold_fits=False))
    extra = {seq: r.surface.diagnostics.extra for seq, r in deferring.items()}
    # undeferred, the jump is fitted cold in the frame and a graph answers
    assert undeferred[JUMP_AT].surface.diagnostics.extra["graph_fit"] in ("linear", "general")
    # deferred: the published frames did no cold fit; the jump and the frames up to the take-over
    # are the general model's, saying so, and the frame after warm-starts from the chain's fit
    assert not cold_fits
    for seq in range(JUMP_AT, JUMP_AT + GRAPH_CATCH_UP_SCANS):
        assert extra[seq]["model"] == "general" and extra[seq]["graph_deferred"], (seq, extra[seq])
        assert extra[seq]["graph_fit"].startswith("deferred: "), extra[seq]
        assert deferring[seq].diagnostics["graph_deferred"] is True
    assert extra[JUMP_AT]["graph_fit"].startswith("deferred: warm: misfit")
    adopted = JUMP_AT + GRAPH_CATCH_UP_SCANS
    assert extra[adopted]["model"] == "graph" and extra[adopted]["graph_fit"] == "warm"
    # the deferred answers agree with the cold fit's within their own uncertainty
    for seq in range(JUMP_AT, adopted):
        gap = np.linalg.norm(deferring[seq].element_positions_mm - undeferred[seq].element_positions_mm, axis=1)
        assert (gap <= deferring[seq].element_sigma_mm).all(), (seq, gap, deferring[seq].element_sigma_mm)
    # from the take-over on, the frames are those of the run that fitted cold in the frame
    for seq in range(adopted, JUMP_FROM + JUMP_COUNT):
        assert np.allclose(deferring[seq].element_positions_mm, undeferred[seq].element_positions_mm,
                           atol=1e-6), seq


def test_a_jump_the_warm_steps_misread_is_answered_in_the_frame_from_its_linear_start():
    """The jump's four warm steps misread the gauges; the frame's linear start, descended in the
    frame (graphfit.GraphFit._misread_refit), answers it as a graph: no frame is deferred to a
    catch-up chain."""
    results = run_jump(pipeline())
    assert results[JUMP_AT].surface.diagnostics.extra["graph_fit"] == WARM_LINEAR
    assert not any(r.diagnostics.get("graph_deferred") for r in results.values())
    assert all(r.surface.diagnostics.extra["model"] == "graph" for r in results.values())


@pytest.mark.usefixtures("no_misread_refit")
def test_deferred_cold_fits_give_the_same_bits_on_the_worker_and_in_line():
    """Replay runs the catch-up chains in line: the same elements as the live worker's."""
    worker = WorkerBackground()
    with one_blas_thread():
        try:
            threaded = run_jump(pipeline(background=worker))
        finally:
            worker.close()
        inline = run_jump(pipeline(background=InlineBackground()))
    assert any(r.diagnostics.get("graph_deferred") for r in inline.values())
    for seq in threaded:
        assert np.array_equal(threaded[seq].element_positions_mm, inline[seq].element_positions_mm), seq
        assert np.array_equal(threaded[seq].element_sigma_mm, inline[seq].element_sigma_mm), seq
        assert np.array_equal(threaded[seq].node_sigma_mm, inline[seq].node_sigma_mm), seq


@pytest.mark.usefixtures("no_misread_refit")
def test_a_failed_catch_up_chain_lets_the_next_frame_fit_cold_itself(caplog):
    pipe = pipeline()

    pipe._chain_reconstructor = _BrokenChain()
    with caplog.at_level("ERROR", logger="skinmapd"):
        results = run_jump(pipe)
    assert "catch-up chain from scan" in caplog.text
    models = {seq: r.surface.diagnostics.extra["model"] for seq, r in results.items()}
    # the jump defers; the chain fails at its take-over, where the frame fits cold itself
    assert results[JUMP_AT].diagnostics["graph_deferred"]
    taken = JUMP_AT + GRAPH_CATCH_UP_SCANS
    assert models[taken] == "graph" and results[taken].surface.diagnostics.extra["graph_fit"] in ("linear", "general")
    assert all(np.isfinite(r.element_positions_mm).all() for r in results.values())


def test_a_sheet_the_general_model_answers_replays_bit_for_bit_from_the_block_start():
    # a sheet laid on a dome (no graph: the screen rules it out) breathing slowly: each warm
    # frame's defect correction starts from the frame before's; the block's first scan starts
    # from none, so a log that starts there replays the same bits from its first frame
    def dome(seq: int) -> np.ndarray:
        shape = make_shape("sphere", radius=70.0 + 0.5 * (seq - START))
        eps_u, eps_l = gauge_strains(shape, N, M, pitch=PITCH)
        return R0 * (1.0 + GF * np.stack([eps_u, eps_l]))

    scans = {seq: dome(seq) for seq in range(START, START + 8)}
    block = START + 3

    def run_dome(pipe: FramePipeline, seqs) -> dict[int, np.ndarray]:
        return {seq: pipe.process(scans[seq], seq, 0, 0).element_positions_mm for seq in seqs}

    live_pipe = pipeline()
    live = run_dome(live_pipe, range(START, START + 8))
    assert live_pipe._previous.diagnostics.extra["model"] == "general"
    assert live_pipe._previous.diagnostics.extra.get("defect_warm") is True  # (a warm frame's start)
    replay = run_dome(pipeline(), range(block, START + 8))
    for seq in range(block, START + 8):
        assert np.array_equal(live[seq], replay[seq]), seq


def test_a_lead_scan_whose_sigma_is_not_read_leaves_every_published_frame_the_same_bits():
    """Lead scans (every fourth scan due, the one before it a lead) processed with lead=True
    skip their σ stage only: the frames due after them, their positions, σ and flags, are the
    bits of a run that read every lead's σ (the chains and the warm start are fed the same)."""
    with one_blas_thread():
        skipping, reading = pipeline(), pipeline()
        for seq in range(START, START + COUNT):
            lead = seq % 4 == 3
            if seq % 4 not in (0, 3):
                continue
            a = skipping.process(SCANS[seq], seq, 0, 0, lead=lead)
            b = reading.process(SCANS[seq], seq, 0, 0)
            if lead:
                assert not np.array_equal(a.element_sigma_mm, b.element_sigma_mm)
                continue
            for field in ("nodes_mm", "node_sigma_mm", "element_positions_mm", "element_sigma_mm", "element_flags"):
                assert np.array_equal(getattr(a, field), getattr(b, field)), (seq, field)
