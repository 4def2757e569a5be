"""The gateway's parts behind their interfaces: the Notifier and its queued listeners (bounded,
drops counted), the log listener over an in-memory sink (a slow or failing disk), the in-memory
and null publishers, the rotation policy, and a whole Gateway fed by the emulator on a
pseudo-terminal publishing into memory and logging into memory (no Zenoh, no MCAP).
"""
from __future__ import annotations

import errno
import os
import threading

import numpy as np
import pytest
from conftest import explicit_elements, free_port, gateway_config, pty_emulator, wait_for

from skinmap.daemon.fanout import Event, Listener, Notifier, QueuedListener, RawFrame, Record, ScanReceived
from skinmap.daemon.gateway import Gateway
from skinmap.daemon.logsink import LogListener, LogStorageError, MemoryLogSink, NullLogSink
from skinmap.daemon.publisher import MemoryPublisher, MemoryPublishers, NullPublisher
from skinmap.daemon.rotation import RotationPolicy, final_name
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.physics import make_shape
from skinmap.protocol import decode_frame
from skinmap.wire import messages


class Recorder(Listener):
    def __init__(self) -> None:
        self.seen: list[Record] = []

    def on_record(self, record: Record) -> None:
        self.seen.append(record)


class Gated(QueuedListener):
    """Handles records only once `gate` is set; `entered` tells it holds one."""

    def __init__(self, maxsize: int, keep: str, drain: bool) -> None:
        super().__init__("test-gated", maxsize, keep=keep, drain=drain)  # type: ignore[arg-type]
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.handled: list[Record] = []

    def handle(self, record: Record) -> None:
        self.entered.set()
        self.gate.wait(30)
        self.handled.append(record)


def events(n: int, start: int = 0) -> list[Event]:
    return [Event(i, "info", f"event {i}") for i in range(start, start + n)]


def test_notifier_passes_every_record_to_every_listener_in_order():
    a, b = Recorder(), Recorder()
    notifier = Notifier([a])
    notifier.add_listener(b)
    for e in events(5):
        notifier.notify(e)
    notifier.remove_listener(a)
    notifier.notify(Event(99, "info", "only b"))
    assert [e.t_ns for e in a.seen] == [0, 1, 2, 3, 4]  # type: ignore[attr-defined]
    assert [e.t_ns for e in b.seen] == [0, 1, 2, 3, 4, 99]  # type: ignore[attr-defined]


@pytest.mark.parametrize("keep", ["newest", "oldest"])
def test_a_full_queue_counts_what_it_drops_and_keeps_the_configured_end(keep):
    listener = Gated(3, keep, drain=True)
    listener.start()
    listener.on_record(Event(-1, "info", "held"))
    assert listener.entered.wait(30)  # the thread holds record -1; the queue is empty
    for e in events(10):
        listener.on_record(e)  # returns at once though nothing is handled
    assert listener.dropped == 7
    listener.gate.set()
    listener.stop()
    kept = [r.t_ns for r in listener.handled]  # type: ignore[attr-defined]
    assert kept == ([-1, 7, 8, 9] if keep == "newest" else [-1, 0, 1, 2])


def test_a_listener_that_does_not_drain_ends_without_handling_the_rest():
    listener = Gated(5, "newest", drain=False)
    listener.start()
    listener.on_record(Event(-1, "info", "held"))
    assert listener.entered.wait(30)
    for e in events(3):
        listener.on_record(e)
    stopper = threading.Thread(target=listener.stop)
    stopper.start()
    listener.gate.set()
    stopper.join(30)
    assert [r.t_ns for r in listener.handled] == [-1]  # type: ignore[attr-defined]


def test_a_slow_disk_never_blocks_the_notifying_thread_and_its_losses_are_counted():
    entered, release = threading.Event(), threading.Event()

    def slow(kind: str) -> None:
        entered.set()
        release.wait(30)

    sink = MemoryLogSink(before_write=slow)
    log = LogListener(sink, queue_size=4)
    other = Recorder()
    notifier = Notifier([other, log])
    log.start()
    notifier.notify(RawFrame(0, b"\x01\x00"))
    assert entered.wait(30)
    done = threading.Event()

    def notify_many() -> None:
        for i in range(1, 101):
            notifier.notify(RawFrame(i, bytes([i, 0])))
        done.set()

    threading.Thread(target=notify_many, daemon=True).start()
    assert done.wait(30), "notify() waited for the disk"
    assert len(other.seen) == 101  # the other listener got everything meanwhile
    assert log.dropped == 100 - 4
    release.set()
    log.stop()
    assert [t for _k, t, _v in sink.records] == [0, 1, 2, 3, 4]  # what was queued is written
    assert sink.closed


def test_storage_failure_sets_the_log_state_and_the_sink_brings_it_back():
    failing = {"on": True}

    def check(kind: str) -> None:
        if failing["on"]:
            raise LogStorageError("/logs", OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)), "writing to")

    sink = MemoryLogSink(before_write=check)
    log = LogListener(sink, queue_size=8)
    log.handle(Event(1, "error", "lost"))
    assert log.state == "error" and "No space left on device" in log.last_error
    assert sink.messages_lost == 1
    failing["on"] = False
    log.handle(Event(2, "info", "kept"))
    log.idle()
    assert log.state == "recording"
    assert sink.kinds("event") == [("info", "kept")]


def test_the_log_listener_takes_only_what_the_log_stores():
    log = LogListener(NullLogSink(), queue_size=2)
    assert log.accepts(RawFrame(0, b"\x00"))
    assert not log.accepts(ScanReceived(None, 0, 0))  # type: ignore[arg-type]


def test_memory_and_null_publishers_encode_like_the_zenoh_one_and_refuse_after_close():
    pub = MemoryPublisher("dev")
    with pytest.raises((TypeError, ValueError)):
        pub.publish_status({"device": "dev"})  # incomplete status: refused by the wire check
    with pytest.raises(TypeError, match="elements payload must be bytes"):
        pub.publish_elements("not bytes")  # type: ignore[arg-type]
    pub.publish_contact({"seq": 3, "contacts": []})
    assert pub.payloads("contact") == [b'{"seq":3,"contacts":[]}']
    pub.close()
    with pytest.raises(RuntimeError, match="closed"):
        pub.publish_strains(b"x")
    with pytest.raises((TypeError, ValueError)):
        NullPublisher().set_info({"device": "dev"})  # incomplete info


def test_rotation_policy_limits_and_names(tmp_path):
    policy = RotationPolicy("run", max_bytes=4096, max_seconds=2.0)
    assert not policy.due(4095, 1_999_999_999)
    assert policy.due(4096, 0) and policy.due(0, 2_000_000_000)
    t = 1_700_000_000 * 10**9
    first = policy.next_path(str(tmp_path), t)
    assert os.path.basename(first) == "run-20231114T221320Z-0001.mcap.active"
    open(final_name(policy.next_path(str(tmp_path), t)), "w").close()  # 0002 finished: taken
    assert policy.next_path(str(tmp_path), t).endswith("-0003.mcap.active")
    for bad in ({"basename": "a/b"}, {"max_bytes": 100}, {"max_seconds": 0}):
        with pytest.raises(ValueError):
            RotationPolicy(**bad)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# A whole gateway into memory

ELEMENT_UV = np.array([[-10.0, 0.0], [0.0, 0.0], [10.0, 5.0]])


@pytest.fixture
def emulator(tmp_path):
    with pty_emulator(tmp_path / "tty", ScannerSpec(n=4, m=4, scan_rate_hz=40.0, seed=3),
                      make_shape("cylinder", radius=50.0)) as emu:
        yield emu


def run_in_memory(cfg, **kwargs):
    gw = Gateway(cfg, **kwargs)
    runner = threading.Thread(target=gw.run, daemon=True)
    runner.start()
    return gw, runner


def test_gateway_publishes_and_logs_into_memory(emulator, tmp_path):
    cfg = gateway_config(tmp_path, free_port(), tmp_path / "tty", "mem", 40, output={"status_rate_hz": 4},
                         elements=explicit_elements(ELEMENT_UV))
    publishers, sink = MemoryPublishers(), MemoryLogSink()
    gw, runner = run_in_memory(cfg, publishers=publishers, log_sink_factory=lambda c: sink)
    try:
        wait_for(lambda: publishers.opened and len(publishers.latest.payloads("elements")) >= 10, 60,
                 "10 elements messages")
        wait_for(lambda: publishers.latest.payloads("status"), 30, "a status message")
    finally:
        gw.stop()
        runner.join(30)
    pub = publishers.latest
    assert pub.device == "mem" and pub.closed
    assert pub.info is not None and pub.info["elements"]["count"] == len(ELEMENT_UV)
    published = [messages.decode_elements(p) for p in pub.payloads("elements")]
    seqs = [m.seq for m in published]
    assert seqs == sorted(set(seqs)) and all(m.positions.shape == (3, 3) for m in published)
    status = messages.decode_status(pub.payloads("status")[-1])
    assert status["device"] == "mem" and status["log_state"] == "recording"
    # The log holds what was published, strains of every processed scan, raw frames, config.
    logged = [messages.decode_elements(p).seq for p, _lat in sink.kinds("elements")]
    assert set(seqs) <= set(logged)
    assert [messages.decode_strains(p).seq for p in sink.kinds("strains")] == logged
    raws = sink.kinds("raw")
    assert raws and all(decode_frame(r[:-1]) is not None for r in raws[:5])
    text, calibration = sink.kinds("config")[0]
    assert "[device]" in text and "hello_frame_hex" in calibration
    assert sink.kinds("status") and sink.closed
    assert gw.stats.log_dropped == 0 and gw.stats.results >= len(logged)


def test_a_stuck_log_sink_stops_neither_publishing_nor_status_and_is_counted(emulator, tmp_path):
    release = threading.Event()
    cfg = gateway_config(tmp_path, free_port(), tmp_path / "tty", "stuck", 40, output={"status_rate_hz": 4},
                         log={"queue_size": 16})
    publishers = MemoryPublishers()
    sink = MemoryLogSink(before_write=lambda kind: release.wait(60))
    gw, runner = run_in_memory(cfg, publishers=publishers, log_sink_factory=lambda c: sink)
    try:
        wait_for(lambda: publishers.opened and len(publishers.latest.payloads("elements")) >= 40, 60,
                 "40 elements while the disk is stuck")
        wait_for(lambda: gw.status()["log_dropped"] > 0, 30, "log drops counted")
        st = gw.status()
        assert st["results"] >= 40 and st["log_dropped"] > 0
    finally:
        release.set()
        gw.stop()
        runner.join(30)
    assert not runner.is_alive()


def test_publishing_failures_are_counted_and_processing_goes_on(emulator, tmp_path):
    class Broken(MemoryPublisher):
        def send(self, kind: str, payload: bytes) -> None:
            if kind == "elements":
                raise RuntimeError("injected put failure")
            super().send(kind, payload)

    opened: list[Broken] = []

    def factory(device: str) -> Broken:
        opened.append(Broken(device))
        return opened[-1]

    cfg = gateway_config(tmp_path, free_port(), tmp_path / "tty", "broken", 40, output={"status_rate_hz": 4},
                         log={"enabled": False})
    gw, runner = run_in_memory(cfg, publishers=factory)
    try:
        wait_for(lambda: gw.stats.publish_errors >= 10, 60, "10 failed puts")
        wait_for(lambda: opened and opened[-1].payloads("status"), 30, "status still published")
        st = gw.status()
        assert st["results"] >= 10 and st["log_state"] == "off" and st["log_file"] == ""
    finally:
        gw.stop()
        runner.join(30)
    assert not runner.is_alive()


def test_the_default_log_sink_follows_the_log_table(tmp_path):
    from skinmap.daemon.gateway import default_log_sink

    for fsync, policy in ((True, "chunk"), (False, "never")):
        cfg = gateway_config(tmp_path, free_port(), tmp_path / "tty", "cfg", 40,
                             log={"fsync": fsync, "basename": "run", "max_file_mb": 1})
        sink = default_log_sink(cfg)
        assert sink.fsync_policy == policy  # type: ignore[attr-defined]
        assert sink.rotation.basename == "run" and sink.rotation.max_bytes == 1024 * 1024  # type: ignore[attr-defined]
        sink.close()


def test_the_reconstruction_is_prepared_at_hello_and_the_first_pipeline_adopts_it(tmp_path):
    """The HELLO (link thread, before START) prepares a reconstructor for the new geometry, and
    the restart chains' own, so the first scans, and the first frame that takes a chain over, are
    not the slow ones; a second HELLO of the same geometry reuses the running ones."""
    from skinmap.daemon.device_setup import ScannerState
    from skinmap.emulator import physics as ph
    from skinmap.emulator.device import Device, ScannerSpec

    cfg = gateway_config(tmp_path, free_port(), "/dev/null", "prep", 20.0)
    hello = Device(ScannerSpec(n=5, m=5), ph.make_shape("flat")).hello()
    state = ScannerState(cfg)
    state.on_hello(hello)
    pipeline, new = state.ensure_pipeline()
    assert new and pipeline is not None
    rec = pipeline.reconstructor
    assert rec._noise_responses and rec._product_noise is not None  # done before any scan
    chains = pipeline._chain_reconstructor
    assert chains is not None and chains is not rec and chains._noise_responses  # not built by a chain's first step
    state.on_hello(hello)  # a reconnect: same geometry, the running reconstructors carry over
    again, new = state.ensure_pipeline()
    assert new and again is not None and again.reconstructor is rec and again._chain_reconstructor is chains


def test_the_elastic_prior_takes_poissons_ratio_from_the_config_else_the_calibration_else_says_why_it_is_off(tmp_path):
    import dataclasses

    from skinmap.daemon.device_setup import ScannerState, elastic_prior_for
    from skinmap.emulator import physics as ph
    from skinmap.emulator.device import Device, ScannerSpec
    from skinmap.strains import Calibration

    cfg = gateway_config(tmp_path, free_port(), "/dev/null", "elastic", 20.0)
    hello = Device(ScannerSpec(n=5, m=5), ph.make_shape("flat")).hello()
    cal = Calibration(hello.gauge_factor(), hello.base_resistance_ohm(), "factory")
    assert elastic_prior_for(cfg, cal, 25) == (None, "")  # off unless asked for
    on = dataclasses.replace(cfg, reconstruction=dataclasses.replace(cfg.reconstruction, elastic_prior=True))
    settings, problem = elastic_prior_for(on, cal, 25)
    assert settings is None and "calibrate --dome" in problem and "poisson_ratio" in problem
    measured = dataclasses.replace(cal, summary={"poisson_ratio": 0.47, "poisson_ratio_sd": 0.011})
    settings, problem = elastic_prior_for(on, measured, 25)
    assert problem == "" and settings.poisson == 0.47 and settings.poisson_sd == 0.011
    given = dataclasses.replace(on, reconstruction=dataclasses.replace(on.reconstruction, poisson_ratio=0.4))
    settings, _ = elastic_prior_for(given, measured, 25)
    assert settings.poisson == 0.4 and settings.poisson_sd == 0.02  # the config's value wins, with its s.d.
    settings, problem = elastic_prior_for(given, measured, 81)
    assert settings is None and "up to 64 cells" in problem
    state = ScannerState(on)
    state.on_hello(hello)
    pipeline, _ = state.ensure_pipeline()
    assert pipeline is not None and pipeline.elastic_prior is None and "calibrate --dome" in state.elastic_problem
    state = ScannerState(given)
    state.on_hello(hello)
    pipeline, _ = state.ensure_pipeline()
    assert pipeline is not None and pipeline.reconstructor.elastic_prior.poisson == 0.4 and state.elastic_problem == ""


def test_the_stretch_patterns_poisson_interval_is_any_elastomers_unless_the_config_or_calibration_gives_nu(tmp_path):
    import dataclasses

    from skinmap.daemon.device_setup import ScannerState, poisson_range_for
    from skinmap.emulator import physics as ph
    from skinmap.emulator.device import Device, ScannerSpec
    from skinmap.strains import Calibration

    cfg = gateway_config(tmp_path, free_port(), "/dev/null", "elastic", 20.0)
    hello = Device(ScannerSpec(n=5, m=5), ph.make_shape("flat")).hello()
    cal = Calibration(hello.gauge_factor(), hello.base_resistance_ohm(), "factory")
    assert poisson_range_for(cfg, cal) == (0.3, 0.5)
    measured = dataclasses.replace(cal, summary={"poisson_ratio": 0.47, "poisson_ratio_sd": 0.011})
    assert poisson_range_for(cfg, measured) == pytest.approx((0.448, 0.492))  # the prior need not be on
    given = dataclasses.replace(cfg, reconstruction=dataclasses.replace(cfg.reconstruction, poisson_ratio=0.49))
    assert poisson_range_for(given, measured) == pytest.approx((0.45, 0.5))  # the config's, capped at 0.5
    state = ScannerState(given)
    state.on_hello(hello)
    pipeline, _ = state.ensure_pipeline()
    assert pipeline is not None and pipeline.reconstructor.poisson_range == pytest.approx((0.45, 0.5))


def test_the_twist_prior_reaches_the_reconstructor_from_the_config(tmp_path):
    """[reconstruction] twist_prior (a twist the stretch cannot tell from none: "open" by default,
    "none" for a sheet known to carry none) is what the gateway's reconstructor takes."""
    import dataclasses

    from skinmap.daemon.device_setup import ScannerState
    from skinmap.emulator import physics as ph
    from skinmap.emulator.device import Device, ScannerSpec

    cfg = gateway_config(tmp_path, free_port(), "/dev/null", "elastic", 20.0)
    hello = Device(ScannerSpec(n=5, m=5), ph.make_shape("flat")).hello()
    for prior in ("open", "none"):
        given = dataclasses.replace(cfg, reconstruction=dataclasses.replace(cfg.reconstruction, twist_prior=prior))
        state = ScannerState(given)
        state.on_hello(hello)
        pipeline, _ = state.ensure_pipeline()
        assert pipeline is not None and pipeline.reconstructor.twist_prior == prior


def test_the_gain_sd_reaches_the_reconstructor_from_the_config(tmp_path):
    """[reconstruction] gain_sd (a gain error the gauges share, in σ: their hysteresis by
    default) is what the gateway's reconstructor takes."""
    import dataclasses

    from skinmap.daemon.device_setup import ScannerState
    from skinmap.emulator import physics as ph
    from skinmap.emulator.device import Device, ScannerSpec
    from skinmap.strains import SHARED_GAIN_SD

    cfg = gateway_config(tmp_path, free_port(), "/dev/null", "elastic", 20.0)
    assert cfg.reconstruction.gain_sd == SHARED_GAIN_SD
    hello = Device(ScannerSpec(n=5, m=5), ph.make_shape("flat")).hello()
    for gain in (0.0, 0.05):
        given = dataclasses.replace(cfg, reconstruction=dataclasses.replace(cfg.reconstruction, gain_sd=gain))
        state = ScannerState(given)
        state.on_hello(hello)
        pipeline, _ = state.ensure_pipeline()
        assert pipeline is not None and pipeline.reconstructor.gain_sd == gain


# ---------------------------------------------------------------------------------------------
# Lead scans: reconstructed just before each scan due, not published


def test_the_host_decimator_names_the_scans_just_before_each_due_one_as_leads():
    from skinmap.daemon.pacing import HostDecimator

    t = np.arange(0, 4_000_000_000, 20_000_000)  # 50 scans/s for 4 s
    jitter = np.random.default_rng(3).integers(-3_000_000, 3_000_000, t.size)
    for lead_scans in (1, 2):
        d = HostDecimator(10.0)
        kinds = []
        for x in t + jitter:
            kinds.append("due" if d.due(int(x)) else "lead" if d.ahead(int(x), lead_scans * 20_000_000) else "")
        dues = [k for k, kind in enumerate(kinds) if kind == "due"]
        assert 39 <= len(dues) <= 41
        # every due scan but the first has its lead_scans scans before it as leads, and no other scan is one
        assert all(kinds[k - j] == "lead" for k in dues[1:] for j in range(1, lead_scans + 1))
        assert kinds.count("lead") == lead_scans * (len(dues) - 1)
    assert not any(HostDecimator(10.0).ahead(int(x), 0) for x in t)  # lead_scans = 0
    every = HostDecimator(0)
    assert all(every.due(int(x)) and not every.ahead(int(x), 20_000_000) for x in t)


def test_a_lead_scan_is_skipped_where_the_scan_due_already_waits():
    from types import SimpleNamespace

    from skinmap.daemon.processing import ProcessingListener

    processed: list[tuple[int, bool]] = []

    class Output:
        def publish(self, result, t_mono, pipeline):
            processed[-1] = (processed[-1][0], True)
            return True

    def scan(k: int) -> ScanReceived:
        s = SimpleNamespace(n=2, m=2, sample_index=k, timestamp_us=0, resistances_ohm=lambda: np.ones((4, 2, 2)))
        return ScanReceived(s, k, k * 20_000_000)  # type: ignore[arg-type]

    told_lead: list[int] = []

    def process(resistance, seq, _device_us, host_ns, lead=False):
        processed.append((seq, False))
        if lead:  # (its σ is not read)
            told_lead.append(seq)
        valid = np.ones((2, 2, 2, 2), bool)
        return SimpleNamespace(seq=seq, solve_time_s=0.0, host_time_ns=host_ns, device_time_us=0, gauge_valid=valid,
                               eps_upper=np.zeros((2, 2, 2)), eps_lower=np.zeros((2, 2, 2)))

    pipeline = SimpleNamespace(geometry=SimpleNamespace(n=2, m=2), process=process)
    scanner = SimpleNamespace(ensure_pipeline=lambda: (pipeline, False))
    notifier = Notifier()
    logged = []
    notifier.add_listener(type("Logged", (Listener,), {"on_record": lambda self, r: logged.append(r)})())
    p = ProcessingListener(10.0, scanner, Output(), notifier, on_new_pipeline=lambda _p: None,  # type: ignore[arg-type]
                           on_first_result=lambda: None, lead_scans=1, scan_rate_hz=50.0)
    for k in range(5):  # scan 0 due, 1-2 passed over, 3 a lead, 4 due (80 ms: within a quarter period)
        p.on_record(scan(k))
        if k in (0, 3, 4):
            p.handle(p._queue.get_nowait())  # the thread was free: each taken as it came
    assert processed == [(0, True), (3, False), (4, True)] and told_lead == [3]
    assert [r.kind for r in logged if getattr(r, "kind", "") == "lead"] == ["lead"] and p.leads == 1
    for k in range(5, 10):  # 8 a lead, 9 due: both queued before the thread is free
        p.on_record(scan(k))
    while p._queue.qsize():
        p.handle(p._queue.get_nowait())
    assert processed[3:] == [(9, True)] and p.leads_skipped == 1 and p.leads == 1
