"""SkinmapPublisher <-> SkinmapClient over loopback TCP with multicast scouting off."""

import multiprocessing
import threading
import time

import numpy as np
import pytest
from conftest import free_port, wait_until

from skinmap.wire import messages as msg
from skinmap.client import SkinmapClient
from skinmap.daemon.zenoh_io import SkinmapPublisher, make_session_config, open_session

DEVICE = "skin-test"


def elements_payload(seq, k=6):
    rng = np.random.default_rng(seq)
    pos = rng.normal(size=(k, 3)) * 0.01
    nrm = np.tile([0.0, 0.0, 1.0], (k, 1))
    return msg.encode_elements(seq, 1000 * seq, 10**18 + seq, pos, nrm, np.full(k, 1e-4),
                               np.full(k, msg.ElementFlag.VALID, np.uint8)), pos


INFO = {"device": DEVICE, "rows": 2, "cols": 3, "pitch_m": 0.012,
        "elements": {"count": 6, "width_m": 0.003, "height_m": 0.01},
        "calibration": {"gauge_factor": [1.24] * 20}, "versions": {"skinmap": "0.1.0"}}

STATUS = {"device": DEVICE, "host_time_ns": 5, "connected": True, "seq": 1,
          "scan_rate_hz": 20.0, "publish_rate_hz": 20.0, "frames_dropped": 0, "crc_errors": 0,
          "reconnects": 1, "solver_time_ms": 9.5, "log_state": "off"}


class Daemon:
    """The daemon's side: its publisher and endpoint (unpacks as the pair), and whether a
    subscriber has reached it, seen by a probe publisher on the same key in its session."""

    def __init__(self, publisher: SkinmapPublisher, endpoint: str, session) -> None:
        self.publisher, self.endpoint, self._session = publisher, endpoint, session
        self._probes: dict = {}

    def __iter__(self):
        return iter((self.publisher, self.endpoint))

    def subscribed(self, kind: str) -> bool:
        if kind not in self._probes:
            self._probes[kind] = self._session.declare_publisher(self.publisher.keys[kind])
        return bool(self._probes[kind].matching_status.matching)

    def close(self) -> None:
        for probe in self._probes.values():
            probe.undeclare()


@pytest.fixture
def daemon():
    """A publisher session listening on a free loopback port, as skinmapd would hold it."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with open_session(make_session_config([endpoint], [])) as session:
        publisher = SkinmapPublisher(session, "skinmap", DEVICE)
        d = Daemon(publisher, endpoint, session)
        try:
            yield d
        finally:
            d.close()
            publisher.close()


def connect(endpoint, **kw):
    client = SkinmapClient([endpoint], prefix="skinmap", device=DEVICE, **kw)
    client.open()
    assert wait_until(lambda: client.session.info.peers_zid()), "client did not connect"
    return client


def test_subscriber_receives_elements_in_order(daemon):
    publisher, endpoint = daemon
    with connect(endpoint) as client:
        assert not daemon.subscribed("elements")
        client.subscribe("elements")
        assert wait_until(lambda: daemon.subscribed("elements"))
        sent = {}
        for seq in range(3):
            payload, pos = elements_payload(seq)
            sent[seq] = pos
            publisher.publish_elements(payload)
        for seq in range(3):
            got = client.elements(timeout=10.0)
            assert got.seq == seq
            np.testing.assert_array_equal(got.positions, sent[seq])
            assert got.valid.all()


def test_late_joiner_gets_latest_of_each_kind_at_once(daemon):
    publisher, endpoint = daemon
    for seq in range(5):
        publisher.publish_elements(elements_payload(seq)[0])
    nodes = np.zeros((2, 3, 3))
    publisher.publish_surface(msg.encode_surface(4, 0, 0, nodes, nodes, np.zeros((2, 3)),
                                                 np.ones((10, 3))))
    publisher.publish_strains(msg.encode_strains(4, 0, 0, np.zeros((2, 2, 3)),
                                                 np.zeros((2, 2, 3)), np.full((2, 2, 3), 3)))
    publisher.publish_status(STATUS)
    publisher.set_info(INFO)
    with connect(endpoint) as client:  # joins after everything was published
        assert client.latest("elements").seq == 4
        assert client.latest("surface").cloud.shape == (10, 3)
        assert client.latest("strains").valid_lower.all()
        assert client.status()["reconnects"] == 1
        info = client.info()
        assert info["rows"] == 2 and info["schema"] == msg.INFO_SCHEMA
        # one wildcard query returns every cached key
        keys = sorted(str(r.ok.key_expr) for r in client.session.get(f"skinmap/{DEVICE}/*",
                                                                     timeout=2.0) if r.ok)
        assert keys == [f"skinmap/{DEVICE}/{k}"
                        for k in ("elements", "info", "status", "strains", "surface")]


def test_latest_before_anything_published_is_a_clear_lookup_error(daemon):
    _, endpoint = daemon
    with connect(endpoint) as client:
        with pytest.raises(LookupError, match="surface"):
            client.latest("surface", timeout=0.5)
        with pytest.raises(ValueError, match="pressure"):
            client.latest("pressure")


def test_info_is_never_put(daemon):
    publisher, endpoint = daemon
    with connect(endpoint) as client:
        seen = []
        sub = client.session.declare_subscriber(f"skinmap/{DEVICE}/*",
                                                lambda s: seen.append(str(s.key_expr)))
        assert wait_until(lambda: daemon.subscribed("status"))
        publisher.set_info(INFO)
        assert client.info()["device"] == DEVICE
        publisher.publish_status(STATUS)  # proves the subscription is live
        assert wait_until(lambda: seen)
        sub.undeclare()
        assert seen == [f"skinmap/{DEVICE}/status"]


def test_liveliness_appears_and_disappears_on_close(daemon):
    publisher, endpoint = daemon
    with connect(endpoint) as client:
        assert client.alive()
        publisher.close()
        assert wait_until(lambda: not client.alive(timeout=0.5))
        with pytest.raises(RuntimeError, match="closed"):
            publisher.publish_elements(elements_payload(0)[0])


def test_iterator_and_callback_forms(daemon):
    publisher, endpoint = daemon
    with connect(endpoint) as client:
        got, done = [], threading.Event()

        def on_elements(m):
            got.append(m.seq)
            if len(got) == 3:
                done.set()

        client.on_elements(on_elements)
        client.subscribe("elements")
        assert wait_until(lambda: daemon.subscribed("elements"))
        for seq in range(3):
            publisher.publish_elements(elements_payload(seq)[0])
        assert done.wait(3.0) and got == [0, 1, 2]
        seqs = [m.seq for m in client.iter_elements(timeout=0.3)]
        assert seqs == [0, 1, 2]  # the iterator ends once nothing arrives within its timeout


def test_slow_reader_never_blocks_the_publisher(daemon):
    publisher, endpoint = daemon
    with connect(endpoint, queue_size=4) as client:
        client.subscribe("elements")
        assert wait_until(lambda: daemon.subscribed("elements"))
        payload = elements_payload(0, k=256)[0]
        published = 0
        deadline = time.monotonic() + 5.0
        # Nobody reads: the client's bounded queue drops the oldest. Zenoh itself may drop
        # under the burst too (congestion control DROP), so publish in bursts until the
        # client has had to discard some.
        while client.dropped("elements") == 0 and time.monotonic() < deadline:
            for _ in range(20):
                publisher.publish_elements(payload)
            published += 20
            time.sleep(0.01)
        assert client.dropped("elements") > 0, f"no drop after {published} messages"
        assert 0 < client.pending("elements") <= 4
        assert client.elements(timeout=10.0).count == 256


def test_publisher_rejects_bad_payloads(daemon):
    publisher, _ = daemon
    with pytest.raises(TypeError, match="elements payload"):
        publisher.publish_elements("not bytes")
    with pytest.raises(ValueError, match="crc_errors"):
        publisher.publish_status({k: v for k, v in STATUS.items() if k != "crc_errors"})
    with pytest.raises(ValueError, match="rows"):
        publisher.set_info({k: v for k, v in INFO.items() if k != "rows"})


def test_client_timeout_and_closed_errors():
    port = free_port()  # nobody listens here
    with SkinmapClient([f"tcp/127.0.0.1:{port}"], device=DEVICE) as client:
        with pytest.raises(TimeoutError, match="elements"):
            client.elements(timeout=0.2)
        assert client.alive(timeout=0.2) is False
    with pytest.raises(RuntimeError, match="not open"):
        client.elements()
    with pytest.raises(ValueError, match="not loopback"):
        SkinmapClient(["tcp/8.8.8.8:7447"])


def _publish_in_child(endpoint, ready, stop):
    with open_session(make_session_config([endpoint], [])) as session:
        with SkinmapPublisher(session, "skinmap", DEVICE) as publisher:
            publisher.publish_elements(elements_payload(11)[0])
            publisher.set_info(INFO)
            ready.set()
            stop.wait(10.0)


@pytest.mark.slow
def test_publisher_in_another_process():
    # a process forked after a session was opened cannot open one: use 'spawn'
    ctx = multiprocessing.get_context("spawn")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ready, stop = ctx.Event(), ctx.Event()
    child = ctx.Process(target=_publish_in_child, args=(endpoint, ready, stop))
    child.start()
    try:
        assert ready.wait(20.0)
        with connect(endpoint) as client:
            assert client.latest("elements").seq == 11
            assert client.alive()
            stop.set()
            child.join(10.0)
            assert child.exitcode == 0
            assert wait_until(lambda: not client.alive(timeout=0.5))
    finally:
        stop.set()
        child.join(5.0)
        if child.is_alive():
            child.kill()


def test_publish_methods_are_thread_safe(daemon):
    publisher, endpoint = daemon
    errors = []

    def worker(base):
        try:
            for i in range(50):
                publisher.publish_elements(elements_payload(base + i, k=2)[0])
                publisher.publish_status({**STATUS, "seq": base + i})
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(1000 * t,)) for t in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10.0)
    assert errors == []
    with connect(endpoint) as client:
        last = client.latest("elements").seq
        assert last % 1000 == 49  # the cache holds a complete, final message of some thread
        assert client.status()["seq"] % 1000 == 49


def test_samples_carry_the_documented_qos_and_encoding(daemon):
    import zenoh

    publisher, endpoint = daemon
    with connect(endpoint) as client:
        sub = client.session.declare_subscriber(f"skinmap/{DEVICE}/*",
                                                zenoh.handlers.FifoChannel(8))
        try:
            assert wait_until(lambda: daemon.subscribed("elements")
                              and daemon.subscribed("status"))
            publisher.publish_elements(elements_payload(1)[0])
            publisher.publish_status(STATUS)
            received = []
            # try_recv with a deadline: a lost sample fails the test instead of hanging it
            assert wait_until(lambda: received.append(sub.try_recv()) or
                              sum(x is not None for x in received) == 2)
            samples = {str(s.key_expr).rsplit("/", 1)[1]: s for s in received if s is not None}
        finally:
            sub.undeclare()
    elements, status = samples["elements"], samples["status"]
    assert elements.congestion_control == zenoh.CongestionControl.DROP and elements.express
    assert elements.priority == zenoh.Priority.DATA_HIGH
    assert str(elements.encoding) == "application/octet-stream;skinmap.elements/2"
    assert status.congestion_control == zenoh.CongestionControl.DROP and not status.express
    assert str(status.encoding) == "application/json;skinmap.status/1"
