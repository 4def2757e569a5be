"""ScannerLink held to PROTOCOL.md against a scanner that breaks it (the emulator's hostile modes).

Each test turns on one way a device can misbehave and checks what the link counts, names and
does: refusals with a clear message, duplicates and jumps that are not losses or reboots, scans
the device dropped itself, intact frames of unknown type, a rate that is always confirmed before
START, and a second host on a shared socket. Only counts, states and messages are asserted.
"""
from __future__ import annotations

import time

import pytest

from skinmap.daemon.config import DeviceConfig as LinkConfig
from skinmap.daemon.link import ScannerLink, serial_port_factory
from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.loopback import DeviceLoopback
from skinmap.emulator.physics import make_shape
from skinmap.emulator.transport import SharedTcpTransport
from skinmap.ports import PortFactory, ScannerPort
from skinmap.protocol import DeviceState, Start, StreamDecoder, encode_frame, step_period_ns

from conftest import wait_until
from test_link import CFG, Recorder, make_device


class ScanLog(Recorder):
    """Recorder that also keeps the step period of every scan passed on."""

    def __init__(self) -> None:
        super().__init__()
        self.periods: list[int] = []

    def link(self, cfg: LinkConfig, port_factory: PortFactory) -> ScannerLink:
        def on_scan(scan, frame, t):
            self.scans.append(scan.sample_index)
            self.periods.append(scan.step_period_ns)

        return ScannerLink(cfg, on_hello=self.hellos.append, on_scan=on_scan,
                           on_event=lambda level, text: self.events.append((level, text)),
                           port_factory=port_factory)



def texts(rec: Recorder, word: str) -> list[str]:
    return [t for _, t in rec.events if word in t]


def running(dev: Device, rec: Recorder, cfg: LinkConfig = CFG, loop: DeviceLoopback | None = None) -> ScannerLink:
    link = rec.link(cfg, (loop or DeviceLoopback(dev)).open)
    link.start()
    return link


# ---------------------------------------------------------------------------------------------
# handshake refusals


@pytest.mark.parametrize("length_um, expected", [(0, "gauge length 0 µm"), (20_000, "gauge length 20000 µm")])
def test_gauge_length_zero_or_longer_than_the_pitch_is_refused_at_the_handshake(length_um, expected):
    dev = make_device()
    dev.hostile.hello_gauge_length_um = length_um
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: link.stats.handshake_failures >= 1)
    finally:
        link.stop()
    assert expected in link.stats.last_error and "pitch 12000" in link.stats.last_error
    assert not rec.scans and not rec.hellos
    assert dev.state == DeviceState.IDLE


def _start_scanning(dev: Device) -> None:
    dev.on_bytes(encode_frame(Start(7), 0), time.monotonic())
    assert dev.state == DeviceState.SCANNING


def test_major_version_mismatch_stops_the_device_and_backs_off_beyond_the_reconnect_cap():
    dev = make_device()
    _start_scanning(dev)  # left streaming by a previous host
    dev.hostile.hello_protocol_major = 2
    rec = Recorder()
    cfg = LinkConfig(port="/dev/fake-scanner", scan_rate_hz=100.0, handshake_timeout_s=0.3,
                     reconnect_min_s=0.02, reconnect_max_s=0.05)
    link = running(dev, rec, cfg)
    backoffs: list[float] = []
    try:
        assert wait_until(lambda: (backoffs.append(link.stats.backoff_s) or link.stats.handshake_failures >= 4))
    finally:
        link.stop()
    assert "major versions differ" in link.stats.last_error and "protocol 2.0" in link.stats.last_error
    assert dev.state == DeviceState.IDLE  # STOP sent: the refused device does not stream on
    assert max(backoffs) > cfg.reconnect_max_s  # exponential, past the cap for vanished ports
    assert not rec.scans


def test_reboot_into_an_incompatible_protocol_stops_the_device():
    dev = make_device()
    rec = Recorder()
    loop = DeviceLoopback(dev)
    link = running(dev, rec, loop=loop)
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        dev.hostile.hello_protocol_major = 2
        loop.reboot()
        assert wait_until(lambda: link.stats.handshake_failures >= 1)
        with loop.lock:
            _start_scanning(dev)  # the new firmware starts by itself: the next refusal stops it again
        assert wait_until(lambda: link.stats.handshake_failures >= 2 and dev.state == DeviceState.IDLE)
    finally:
        link.stop()
    assert "major versions differ" in link.stats.last_error


# ---------------------------------------------------------------------------------------------
# the scan rate is always set and confirmed before START


def test_lost_boot_hello_still_gets_the_configured_rate_before_start():
    # boot default 20 scans/s, configured 100
    dev = Device(ScannerSpec(n=5, m=5, scan_rate_hz=20.0, seed=3), make_shape("flat"), now_s=time.monotonic())
    rec = ScanLog()
    loop = DeviceLoopback(dev)
    link = running(dev, rec, loop=loop)
    try:
        assert wait_until(lambda: len(rec.scans) >= 10)
        dev.hostile.lose_boot_hello = True
        loop.reboot()  # IDLE, at its boot rate, and the host was not told
        assert wait_until(lambda: link.stats.stalls >= 1)
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > n + 20)
    finally:
        link.stop()
    want = step_period_ns(100_000, 5, 5)
    assert set(rec.periods) == {want}
    assert dev.scan_rate_mhz == 100_000 and link.stats.applied_scan_rate_mhz == 100_000


def test_an_applied_rate_far_from_the_request_is_refused():
    dev = make_device()
    real = dev._apply_rate_mhz
    dev._apply_rate_mhz = lambda mhz: real(min(mhz, 10_000))  # firmware clamps silently to 10 scans/s
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: link.stats.handshake_failures >= 1)
    finally:
        link.stop()
    assert "applied 10 scans/s for the requested 100" in link.stats.last_error
    assert not rec.scans


# ---------------------------------------------------------------------------------------------
# sample-index accounting


@pytest.mark.slow
def test_repeated_sample_index_is_counted_and_reported_rate_limited_not_as_reboots():
    dev = make_device()
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        dev.hostile.repeat_sample_index = True
        assert wait_until(lambda: link.stats.scans_repeated_index >= 100)
        assert wait_until(lambda: link.stats.state == "stalled")
        error = link.stats.last_error
    finally:
        link.stop()
    s = link.stats
    assert s.reboots == 0 and s.scans_lost == 0
    assert "repeated" in error
    assert len(texts(rec, "repeated")) * 10 < s.scans_repeated_index  # rate-limited, not one per scan
    assert link.stats.decoder["scans_repeated_index"] == s.scans_repeated_index  # published


def test_implausible_index_jump_is_a_resync_not_a_loss():
    dev = make_device()
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        dev.hostile.index_jump = 0x7FFFFF00
        assert wait_until(lambda: link.stats.index_resyncs >= 1)
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > n + 10)
    finally:
        link.stop()
    assert link.stats.scans_lost == 0 and link.stats.reboots == 0
    assert rec.scans[-1] > 0x7FFFFF00
    assert any("resynchronised" in t for t in texts(rec, "scan index went"))


def test_scan_size_disagreeing_with_hello_is_counted_and_named():
    dev = make_device()
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        dev.hostile.scan_dims = (6, 6)
        assert wait_until(lambda: link.stats.state == "stalled" and link.stats.scans_wrong_size >= 50)
        error = link.stats.last_error
    finally:
        link.stop()
    assert "scan size 6×6 disagrees with HELLO 5×5" in error
    assert len(texts(rec, "scan size 6×6")) * 10 < link.stats.scans_wrong_size


@pytest.mark.slow
def test_scans_dropped_by_the_device_are_not_counted_as_link_loss():
    dev = make_device()
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        dev.hostile.drop_every = 4
        assert wait_until(lambda: link.stats.scans_dropped_by_device >= 20)
        dev.hostile.drop_every = 0
        time.sleep(0.1)
    finally:
        link.stop()
    assert link.stats.scans_lost == 0
    # Every flagged gap is a device drop; the device may drop more (a busy reader, the scans
    # before a re-handshake), never fewer.
    assert link.stats.scans_dropped_by_device <= dev.scans_dropped


def test_lost_start_ack_after_a_reboot_counts_one_reboot():
    dev = make_device()
    rec = Recorder()
    loop = DeviceLoopback(dev)
    link = running(dev, rec, loop=loop)
    try:
        assert wait_until(lambda: len(rec.scans) >= 20)
        dev.hostile.lose_start_acks = 1
        loop.reboot()
        assert wait_until(lambda: link.stats.reboots >= 1)
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) > n + 20)
    finally:
        link.stop()
    assert dev.hostile.lose_start_acks == 0  # the ACK was lost and the retry answered from memory
    assert link.stats.reboots == 1 and link.stats.index_resyncs == 0


# ---------------------------------------------------------------------------------------------
# frames


def test_vendor_frames_are_counted_as_unknown_not_as_damage_or_loss():
    dev = make_device()
    dev.hostile.vendor_frame_hz = 50
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: link.stats.unknown_frames >= 20)
    finally:
        link.stop()
    assert link.stats.frames_rejected == 0
    assert link.stats.decoder["seq_lost"] == 0 and link.stats.decoder["unknown_frames"] == link.stats.unknown_frames


def test_host_sequence_numbers_start_at_zero_on_every_open():
    dev = make_device()
    written: list[list[int]] = []

    class RecordingPort(ScannerPort):
        """Passes everything on; decodes what the host writes."""

        def __init__(self, inner: ScannerPort) -> None:
            super().__init__(inner.name)
            self.inner, self.decoder = inner, StreamDecoder()
            written.append([])

        def _send_internal(self, data: bytes) -> None:
            written[-1].extend(f.seq for f in self.decoder.feed(data))
            self.inner.send(data)

        def _recv_internal(self, timeout: float | None) -> bytes:
            return self.inner.recv(timeout)

        def _reset_input_internal(self) -> None:
            self.inner.reset_input()

        def _close_internal(self) -> None:
            self.inner.close()

    loop = DeviceLoopback(dev)
    rec = Recorder()
    link = rec.link(CFG, lambda: RecordingPort(loop.open()))
    link.start()
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        loop.unplug()
        loop.replug(power_cycle=False)  # the line glitched; the scanner kept its power
        assert wait_until(lambda: len(written) >= 2 and len(rec.scans) > 20)
    finally:
        link.stop()
    assert [w[0] for w in written[:2]] == [0, 0]
    assert written[0] == list(range(len(written[0])))


# ---------------------------------------------------------------------------------------------
# HELLO storms and a second host


@pytest.mark.slow
def test_hello_storm_without_reboot_costs_no_scans_and_is_unhealthy_while_it_lasts():
    dev = make_device()
    rec = Recorder()
    link = running(dev, rec)
    try:
        assert wait_until(lambda: len(rec.scans) >= 10)
        dev.hostile.hello_storm_hz = 50
        assert wait_until(lambda: link.stats.unsolicited_hellos >= 25)
        during = (link.streaming.is_set(), link.stats.state, link.stats.last_error)
        dev.hostile.hello_storm_hz = 0
        assert wait_until(lambda: link.streaming.is_set() and link.stats.state == "streaming")
    finally:
        link.stop()
    assert during[0] is False and during[1] == "contended" and "unsolicited HELLO" in during[2]
    assert link.stats.scans_lost == 0 and link.stats.reboots == 0 and link.stats.index_resyncs == 0
    # No restart: the index only grows, and what is missing the device dropped itself (a busy reader).
    assert all(b > a for a, b in zip(rec.scans, rec.scans[1:]))
    assert rec.scans[-1] - rec.scans[0] + 1 - len(rec.scans) == link.stats.scans_dropped_by_device


def test_reboot_storm_backs_off_with_a_clear_error():
    dev = make_device()
    rec = Recorder()
    loop = DeviceLoopback(dev)
    link = running(dev, rec, loop=loop)
    try:
        assert wait_until(lambda: len(rec.scans) >= 5)
        for _ in range(6):
            loop.reboot()
            assert wait_until(lambda: link.stats.state != "handshake")
            time.sleep(0.05)
        assert wait_until(lambda: link.stats.handshake_failures >= 1)
    finally:
        link.stop()
    assert any("rebooted 4 times within 10 s" in t for t in texts(rec, "HELLO storm"))


def test_a_port_lost_again_and_again_is_reported_unstable_while_it_streams():
    dev = make_device()
    loop = DeviceLoopback(dev)
    rec = Recorder()
    link = rec.link(CFG, loop.open)
    link.start()
    try:
        for _ in range(3):  # as when another host takes a socket:// port over in turn
            n = len(rec.scans)
            assert wait_until(lambda: len(rec.scans) >= n + 5)
            loop.unplug()
            loop.replug(power_cycle=False)
        n = len(rec.scans)
        assert wait_until(lambda: len(rec.scans) >= n + 5)
        during = (link.streaming.is_set(), link.stats.state, link.stats.last_error)
    finally:
        link.stop()
    assert during[0] is False and during[1] == "unstable", during
    assert "lost 3 times in the last 30 s" in during[2]


@pytest.mark.slow
def test_two_hosts_on_a_shared_socket_are_both_told_and_unhealthy():
    transport = SharedTcpTransport()
    emu = Emulator(ScannerSpec(n=5, m=5, scan_rate_hz=50.0, seed=4), make_shape("flat"), transport)
    emu.start()
    cfg = LinkConfig(port=transport.url, scan_rate_hz=50.0, handshake_timeout_s=1.0, stall_timeout_s=0.5,
                     reconnect_min_s=0.05, reconnect_max_s=0.2)
    links, recs = [], []
    try:
        for _ in range(2):
            rec = Recorder()
            link = rec.link(cfg, serial_port_factory(cfg))
            link.start()
            links.append(link)
            recs.append(rec)
            assert wait_until(lambda: len(rec.scans) >= 5 or link.stats.foreign_answers)
        assert wait_until(lambda: all(l.stats.foreign_answers >= 2 for l in links))
        samples = []
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            samples.append([(l.streaming.is_set(), l.stats.state) for l in links])
            time.sleep(0.05)
    finally:
        for link in links:
            link.stop()
        emu.stop()
    for i, link in enumerate(links):
        assert all(not s[i][0] for s in samples), [s[i] for s in samples]  # never reported healthy
        assert "another host is commanding the scanner" in link.stats.last_error


# ---------------------------------------------------------------------------------------------
# spec corners


def test_frame_ending_on_a_full_cobs_block_decodes_with_or_without_a_trailing_code_byte():
    from cobs import cobs

    from skinmap.protocol import Ping, decode_frame

    # header 01 00 00 14 | seq 01 01 | payload_len FA 00: its last zero is header byte 7; after
    # it come request id (2) + echo (248) + CRC (4) = 254 bytes, non-zero for a suitable fill.
    for fill in range(1, 256):
        frame = encode_frame(Ping(0x0101, bytes([fill]) * 248), 0x0101)
        raw = cobs.decode(frame[:-1])
        if 0 not in raw[8:]:
            break
    body = frame[:-1]
    assert len(raw) - 8 == 254 and body[-255] == 0xFF  # the last block is a full one, no code after it
    for wire in (frame, body + b"\x01\x00"):
        decoded = StreamDecoder().feed(wire)
        assert len(decoded) == 1 and decoded[0].msg == Ping(0x0101, bytes([fill]) * 248)
    assert decode_frame(body + b"\x01").msg.echo == bytes([fill]) * 248
