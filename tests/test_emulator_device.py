"""The emulated firmware as a pure state machine: every command, scheduling, faults."""
from __future__ import annotations

import numpy as np
import pytest

from skinmap import protocol as p
from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.electrical import ElectricalConfig
from skinmap.strains import gauge_strain
from skinmap.emulator.physics import gauge_strains, make_shape
from skinmap.protocol.framing import encode_body

IDEAL = ElectricalConfig.ideal()


class Host:
    """Talks to a Device and decodes its answers."""

    def __init__(self, device: Device):
        self.dev = device
        self.dec = p.StreamDecoder()
        self.seq = 0

    def send(self, msg, now: float) -> list[p.Frame]:
        frame = p.encode_frame(msg, self.seq)
        self.seq += 1
        return self.feed(self.dev.on_bytes(frame, now))

    def raw(self, data: bytes, now: float) -> list[p.Frame]:
        return self.feed(self.dev.on_bytes(data, now))

    def poll(self, now: float, **kw) -> list[p.Frame]:
        return self.feed(self.dev.poll(now, **kw))

    def feed(self, data: bytes) -> list[p.Frame]:
        frames = self.dec.feed(data)
        assert self.dec.garbage_bytes == 0, self.dec.last_error
        return frames


def make(n=5, m=5, shape=None, elec=IDEAL, rate=10.0, seed=1, t0=100.0):
    dev = Device(ScannerSpec(n=n, m=m, scan_rate_hz=rate, seed=seed, electrical=elec),
                 shape or make_shape("cylinder", radius=40.0), now_s=t0)
    host = Host(dev)
    boot = host.poll(t0)
    return dev, host, boot


def types(frames):
    return [f.msg_type.name for f in frames]


def only(frames, kind):
    return [f.msg for f in frames if f.msg_type == kind]


def test_boot_sends_delimiter_hello_seq0_then_status():
    dev, host, boot = make(n=4, m=6)
    raw = dev.poll  # nothing more is due at once
    assert types(boot) == ["HELLO", "STATUS"]
    assert boot[0].seq == 0 and boot[1].seq == 1
    hello = boot[0].msg
    assert (hello.n, hello.m) == (4, 6)
    assert hello.schema_hash == p.SCHEMA_HASH and hello.protocol_major == p.PROTOCOL_MAJOR
    assert hello.pitch_um == 12000 and hello.gauge_length_um == 10000
    assert (hello.h_upper_um, hello.h_lower_um) == (200, 200)
    assert hello.scan_rate_mhz == 10000
    assert hello.max_scan_rate_mhz == 4000 * 1000 // 8
    np.testing.assert_allclose(hello.gauge_factor(), dev.calibration.gauge_factor, atol=1e-12)
    np.testing.assert_allclose(hello.base_resistance_ohm(), dev.calibration.base_resistance_ohm, atol=1e-12)
    drive, sense = p.default_channel_map(4, 6)
    np.testing.assert_array_equal(hello.drive_line, drive)
    np.testing.assert_array_equal(hello.sense_channel, sense)
    status = boot[1].msg
    assert status.state == p.DeviceState.IDLE and status.scans_sent == 0
    # the wire starts with a delimiter that closes off line noise
    dev2 = Device(ScannerSpec(), make_shape("flat"), now_s=0.0)
    assert dev2.poll(0.0)[:1] == b"\x00"
    assert raw(100.5) == b""


def test_start_scans_on_schedule_with_incrementing_index():
    dev, host, _ = make(rate=10.0)
    frames = host.send(p.Start(request_id=7), 100.0)
    acks = only(frames, p.MsgType.ACK)
    assert acks == [p.Ack(7, int(p.MsgType.START), b"")]
    assert only(host.poll(100.099), p.MsgType.SCAN) == []  # the first scan is not complete yet
    scans = only(host.poll(100.1), p.MsgType.SCAN) + only(host.poll(100.55), p.MsgType.SCAN)
    assert [s.sample_index for s in scans] == [0, 1, 2, 3, 4]
    assert scans[0].flags & p.ScanFlag.FIRST_AFTER_START
    assert not any(s.flags & p.ScanFlag.FIRST_AFTER_START for s in scans[1:])
    steps = np.diff([s.timestamp_us for s in scans])
    np.testing.assert_array_equal(steps, 100_000)
    assert scans[0].timestamp_us == 0  # device clock counts from boot, START at boot time
    assert all(s.step_period_ns == 10_000_000 for s in scans)  # 10 steps of a 5x5 scan at 10/s
    assert all((s.n, s.m) == (5, 5) for s in scans)


def test_scan_values_are_the_forward_model():
    shape = make_shape("gaussian", height=4.0, fwhm=18.0, centre=(3.0, -2.0))
    dev, host, _ = make(shape=shape)
    host.send(p.Start(1), 100.0)
    scan = only(host.poll(100.1), p.MsgType.SCAN)[0]
    eps = gauge_strain(scan.resistances_ohm(), dev.calibration.gauge_factor, dev.calibration.base_resistance_ohm)
    eu, el = gauge_strains(shape, 5, 5)
    np.testing.assert_allclose(eps, np.stack([eu, el]), atol=3e-7)  # 1 µΩ quantum


def test_time_varying_shape_is_sampled_at_each_units_tdm_step():
    shape = make_shape("membrane", fingers=2, period=1.0)
    dev, host, _ = make(shape=shape, rate=5.0)
    host.send(p.Start(1), 100.0)
    scan = only(host.poll(100.45), p.MsgType.SCAN)[0]
    eps = gauge_strain(scan.resistances_ohm(), dev.calibration.gauge_factor, dev.calibration.base_resistance_ohm)
    times = p.unit_sample_times_us(scan.timestamp_us, scan.step_period_ns, dev.drive_line) * 1e-6
    # the device clock started at boot (t=100 s) together with the shape clock
    skewed = np.stack(gauge_strains(shape, 5, 5, t=times, samples=8, panels=1))
    np.testing.assert_allclose(eps, skewed, atol=3e-7)
    at_step0 = np.stack(gauge_strains(shape, 5, 5, t=times.min()))
    assert np.abs(eps - at_step0).max() > 1e-4  # the skew is real, not a snapshot


def test_start_retry_is_idempotent_and_start_while_scanning_does_not_restart():
    dev, host, _ = make()
    host.send(p.Start(7), 100.0)
    host.poll(100.35)
    again = host.send(p.Start(7), 100.36)  # retry: same request id
    assert only(again, p.MsgType.ACK) == [p.Ack(7, int(p.MsgType.START))]
    other = host.send(p.Start(8), 100.37)  # a new START while scanning: no effect
    assert only(other, p.MsgType.ACK) == [p.Ack(8, int(p.MsgType.START))]
    scans = only(host.poll(100.51), p.MsgType.SCAN)
    assert [s.sample_index for s in scans] == [3, 4]


def test_retry_answers_from_memory_without_executing_again():
    dev, host, _ = make()
    first = only(host.send(p.SetScanRate(3, 20_000), 100.0), p.MsgType.ACK)
    host.send(p.Start(4), 100.01)
    # a late retry of the SET_SCAN_RATE gets the remembered ACK, not NOT_ALLOWED_IN_STATE
    retry = host.send(p.SetScanRate(3, 20_000), 100.02)
    assert only(retry, p.MsgType.ACK) == first and not only(retry, p.MsgType.NAK)
    # a new request id is executed: NAK while scanning
    nak = only(host.send(p.SetScanRate(5, 20_000), 100.03), p.MsgType.NAK)
    assert nak == [p.Nak(5, int(p.MsgType.SET_SCAN_RATE), int(p.ErrorCode.NOT_ALLOWED_IN_STATE), 0)]
    # the memory holds the last 8 commands: after 8 more, request 3 is executed afresh
    for rid in range(10, 18):
        host.send(p.Ping(rid, b"x"), 100.04)
    again = host.send(p.SetScanRate(3, 20_000), 100.05)
    assert only(again, p.MsgType.NAK)[0].error == p.ErrorCode.NOT_ALLOWED_IN_STATE


def test_stop_discards_the_scan_in_progress():
    dev, host, _ = make()
    host.send(p.Start(1), 100.0)
    frames = host.send(p.Stop(2), 100.25)
    assert types(frames)[-1] == "ACK" or "STATUS" in types(frames)
    assert [s.sample_index for s in only(frames, p.MsgType.SCAN)] == [0, 1]  # completed ones first
    ack_pos = types(frames).index("ACK")
    assert "SCAN" not in types(frames)[ack_pos:]
    assert only(host.poll(101.0), p.MsgType.SCAN) == []
    assert dev.state == p.DeviceState.IDLE
    assert only(host.send(p.Stop(3), 101.0), p.MsgType.ACK)  # STOP is allowed in any state


def test_set_scan_rate_arguments_and_applied_rate():
    dev, host, _ = make(rate=10.0)
    for rid, rate in ((1, 0), (2, dev.max_scan_rate_mhz + 1)):
        nak = only(host.send(p.SetScanRate(rid, rate), 100.0), p.MsgType.NAK)
        assert nak == [p.Nak(rid, int(p.MsgType.SET_SCAN_RATE), int(p.ErrorCode.BAD_ARGUMENT), 1)]
    ack = only(host.send(p.SetScanRate(3, 7_000), 100.0), p.MsgType.ACK)[0]
    assert ack.applied_scan_rate_mhz == 7_000
    ack = only(host.send(p.SetScanRate(4, 33_333), 100.0), p.MsgType.ACK)[0]
    period = p.step_period_ns(33_333, 5, 5)
    assert ack.applied_scan_rate_mhz == round(1e12 / (10 * period))
    host.send(p.Start(5), 100.0)
    scans = only(host.poll(100.2), p.MsgType.SCAN)
    assert len(scans) == 6 and scans[0].step_period_ns == period
    assert np.diff([s.timestamp_us for s in scans]).max() - 10 * period / 1000 < 1.0
    host.send(p.Stop(6), 100.2)
    hello = only(host.send(p.QueryInfo(7), 100.2), p.MsgType.HELLO)[0]
    assert hello.scan_rate_mhz == ack.applied_scan_rate_mhz


def test_query_info_acks_then_hello_and_ping_echoes():
    dev, host, _ = make()
    frames = host.send(p.QueryInfo(11), 100.0)
    assert types(frames) == ["ACK", "HELLO"]
    assert frames[0].msg == p.Ack(11, int(p.MsgType.QUERY_INFO))
    assert frames[1].seq == frames[0].seq + 1
    frames = host.send(p.Ping(12, bytes(range(255))), 100.0)
    assert frames[0].msg == p.Ack(12, int(p.MsgType.PING), bytes(range(255)))


def test_reset_acks_then_reboots_with_hello_seq0():
    dev, host, _ = make()
    host.send(p.Start(1), 100.0)
    host.poll(100.3)
    frames = host.send(p.Reset(2), 100.31)
    assert types(frames)[-2:] == ["ACK", "HELLO"]
    assert frames[-2].msg == p.Ack(2, int(p.MsgType.RESET))
    assert frames[-1].seq == 0
    assert dev.state == p.DeviceState.IDLE
    status = only(host.poll(100.32), p.MsgType.STATUS)[0]
    assert status.scans_sent == 0 and not status.fault_flags & p.FaultFlag.WATCHDOG_RESET
    assert only(host.poll(101.0), p.MsgType.SCAN) == []
    host.send(p.Start(1), 101.0)  # the answer memory is cleared at boot: executed again
    scans = only(host.poll(101.1), p.MsgType.SCAN)
    assert [s.sample_index for s in scans] == [0]
    assert abs(scans[0].timestamp_us - 690_000) <= 1  # device clock restarted at the reset


def _frame_with(msg_type: int, payload: bytes) -> bytes:
    return encode_body(msg_type, 0, payload)


def test_naks_for_unknown_commands_bad_length_and_silence_for_damage():
    dev, host, _ = make()
    seen = host.raw(_frame_with(0x7F, b"\x34\x12\x00"), 100.0)
    assert only(seen, p.MsgType.NAK) == [p.Nak(0x1234, 0x7F, int(p.ErrorCode.UNKNOWN_COMMAND), 0)]
    ack_to_device = p.encode_frame(p.Ack(0x0506, int(p.MsgType.START)), 0)  # a device -> host type
    nak = only(host.raw(ack_to_device, 100.0), p.MsgType.NAK)[0]
    assert nak == p.Nak(0x0506, int(p.MsgType.ACK), int(p.ErrorCode.UNKNOWN_COMMAND), 0)
    # a HELLO does not even fit the 300-byte receive buffer: skipped and counted, no answer
    assert host.raw(p.encode_frame(dev.hello(), 0), 100.0) == []
    frames = host.raw(_frame_with(int(p.MsgType.START), b"\x05\x00\x00"), 100.0)
    assert only(frames, p.MsgType.NAK) == [p.Nak(5, int(p.MsgType.START), int(p.ErrorCode.BAD_LENGTH), 0)]
    seen += frames
    frames = host.raw(_frame_with(int(p.MsgType.STOP), b"\x09"), 100.0)
    assert only(frames, p.MsgType.NAK) == [p.Nak(0, int(p.MsgType.STOP), int(p.ErrorCode.BAD_LENGTH), 0)]
    seen += frames
    good = bytearray(p.encode_frame(p.Start(9), 0))
    good[3] ^= 0x40  # a flipped bit: CRC fails, no answer
    frames = host.raw(bytes(good), 100.0) + host.raw(b"\x13\x37\xde\xad\x00", 100.0)  # + garbage
    assert only(frames, p.MsgType.NAK) == only(frames, p.MsgType.ACK) == []
    seen += frames + host.poll(100.1)
    assert dev.state == p.DeviceState.IDLE
    assert dev.frames_rejected == 5  # HELLO, bad length x2, CRC, garbage (unknown types: answered)
    statuses = only(seen, p.MsgType.STATUS)  # rejected frames raise HOST_FRAME_ERRORS at once
    assert statuses and all(s.fault_flags & p.FaultFlag.HOST_FRAME_ERRORS for s in statuses)
    later = only(host.poll(101.2), p.MsgType.STATUS)[0]  # periodic: grew since the previous one
    assert later.frames_rejected == 5 and later.fault_flags & p.FaultFlag.HOST_FRAME_ERRORS
    quiet = only(host.poll(102.2), p.MsgType.STATUS)[0]  # nothing new since: the flag clears
    assert quiet.frames_rejected == 5 and not quiet.fault_flags & p.FaultFlag.HOST_FRAME_ERRORS


def test_commands_split_across_chunks_and_oversize_garbage():
    dev, host, _ = make()
    frame = p.encode_frame(p.Ping(3, b"abc"), 0)
    assert host.raw(frame[:4], 100.0) == []
    assert only(host.raw(frame[4:], 100.0), p.MsgType.ACK)[0].result == b"abc"
    host.raw(b"\x55" * 10_000, 100.0)  # no delimiter for 10 kB: dropped without buffering
    assert only(host.send(p.Ping(4, b"ok"), 100.0), p.MsgType.ACK) == []  # its tail ends at this 0x00
    assert only(host.send(p.Ping(5, b"ok"), 100.0), p.MsgType.ACK)[0].request_id == 5


def test_status_every_second_in_any_state():
    dev, host, boot = make()
    assert len(only(boot, p.MsgType.STATUS)) == 1
    stamps = []
    for k in range(1, 40):
        stamps += [s.timestamp_us for s in only(host.poll(100.0 + 0.1 * k), p.MsgType.STATUS)]
    assert len(stamps) == 3
    np.testing.assert_allclose(np.diff(stamps), 1_000_000, atol=60_000)


def test_dead_and_saturated_gauges():
    dev, host, _ = make()
    dead = np.zeros((2, 2, 5, 5), bool)
    dead[0, 0, 2, 3] = True
    sat = np.zeros((2, 2, 5, 5), bool)
    sat[1, 1, 4, 0] = True
    dev.set_open(dead)
    dev.set_saturated(sat)
    status = only(host.poll(100.01), p.MsgType.STATUS)[0]  # fault change: immediate STATUS
    assert status.fault_flags & p.FaultFlag.GAUGE_OPEN and status.fault_flags & p.FaultFlag.GAUGE_SATURATED
    np.testing.assert_array_equal(status.open_gauges, dead)
    host.send(p.Start(1), 100.02)
    scan = only(host.poll(100.2), p.MsgType.SCAN)[0]
    assert scan.resistance_uohm[0, 0, 2, 3] == p.RES_OPEN
    assert scan.resistance_uohm[1, 1, 4, 0] == p.RES_SATURATED
    assert scan.flags & p.ScanFlag.OPEN_GAUGE and scan.flags & p.ScanFlag.SATURATED_GAUGE
    np.testing.assert_array_equal(scan.open_mask(), dead)
    with pytest.raises(ValueError, match="shape"):
        dev.set_open(np.zeros((2, 5, 5), bool))


def test_stall_drops_scans_and_flags_the_next_one():
    dev, host, _ = make()
    host.send(p.Start(1), 100.0)
    host.poll(100.25)
    dev.stall(100.25, 1.0)
    assert host.poll(100.8) == [] and host.send(p.Ping(2), 100.9) == []
    frames = host.poll(101.3)
    scans = only(frames, p.MsgType.SCAN)
    # the backlog beyond the scan buffer is lost, but sample_index counts every scan
    assert scans[-1].sample_index == 12
    assert scans[0].flags & p.ScanFlag.DROPPED_BEFORE
    status = only(frames, p.MsgType.STATUS)[0]
    assert status.scans_dropped == 13 - 2 - len(scans) and status.scans_dropped > 0
    assert status.fault_flags & p.FaultFlag.SCAN_BUFFER_OVERRUN


def test_busy_link_drops_whole_scans():
    dev, host, _ = make()
    host.send(p.Start(1), 100.0)
    host.poll(100.05, tx_ready=False)  # busy while nothing completes: nothing lost
    first = only(host.poll(100.1), p.MsgType.SCAN)
    assert [s.sample_index for s in first] == [0] and not first[0].flags & p.ScanFlag.DROPPED_BEFORE
    dev, host, _ = make()
    host.send(p.Start(1), 100.0)
    assert only(host.poll(100.35, tx_ready=False), p.MsgType.SCAN) == []
    scans = only(host.poll(100.45), p.MsgType.SCAN)
    assert [s.sample_index for s in scans] == [3]
    assert scans[0].flags & p.ScanFlag.DROPPED_BEFORE
    assert dev.scans_dropped == 3


def test_watchdog_reboot_restarts_sequence_and_reports_it():
    dev, host, _ = make()
    host.send(p.Start(1), 100.0)
    host.poll(100.3)
    dev.reboot(100.3)
    frames = host.poll(100.3)
    assert types(frames) == ["HELLO", "STATUS"] and frames[0].seq == 0
    assert frames[1].msg.fault_flags & p.FaultFlag.WATCHDOG_RESET
    assert frames[1].msg.state == p.DeviceState.IDLE


def test_adc_fault_enters_fault_state_and_refuses_start():
    dev, host, _ = make()
    dev.set_adc_fault(True)
    status = only(host.poll(100.0), p.MsgType.STATUS)[0]
    assert status.state == p.DeviceState.FAULT and status.fault_flags & p.FaultFlag.ADC_FAULT
    nak = only(host.send(p.Start(1), 100.0), p.MsgType.NAK)
    assert nak == [p.Nak(1, int(p.MsgType.START), int(p.ErrorCode.NOT_ALLOWED_IN_STATE), 0)]
    assert only(host.send(p.SetScanRate(2, 5000), 100.0), p.MsgType.ACK)  # allowed in FAULT
    dev.set_adc_fault(False)
    assert only(host.send(p.Start(3), 100.0), p.MsgType.ACK)


def test_same_seed_same_bytes_different_seed_different_calibration():
    def run(seed):
        dev = Device(ScannerSpec(seed=seed, electrical=ElectricalConfig()), make_shape("palm"), now_s=0.0)
        out = dev.poll(0.0) + dev.on_bytes(p.encode_frame(p.Start(1), 0), 0.0)
        return out + b"".join(dev.poll(0.1 * k) for k in range(1, 12))

    assert run(3) == run(3)
    assert run(3) != run(4)


def test_ground_truth_of_sent_scans():
    shape = make_shape("membrane", period=1.0)
    dev, host, _ = make(shape=shape)
    host.send(p.Start(1), 100.0)
    scans = only(host.poll(100.5), p.MsgType.SCAN)
    gt = dev.ground_truth(scans[2].sample_index, element_uv=[[0.0, 0.0]])
    t = scans[2].timestamp_us * 1e-6  # device and shape clocks both started at t0 here
    np.testing.assert_allclose(gt.nodes, shape.position(gt.nodes[..., :2] * 0 + _centres(), t), atol=1e-9)
    assert gt.element_positions.shape == (1, 3)
    with pytest.raises(KeyError, match="no record"):
        dev.ground_truth(99)


def _centres():
    from skinmap.emulator.physics import cell_centres

    return cell_centres(5, 5, 12.0)


def test_config_errors_are_named():
    with pytest.raises(ValueError, match="ScannerSpec.n"):
        ScannerSpec(n=1)
    with pytest.raises(ValueError, match="ScannerSpec.m"):
        ScannerSpec(m=33)
    with pytest.raises(ValueError, match="exceeds the maximum"):
        ScannerSpec(n=32, m=32, scan_rate_hz=100.0)
    with pytest.raises(ValueError, match="serial_number"):
        ScannerSpec(serial_number="x" * 17)


@pytest.mark.parametrize("n, m", [(2, 2), (7, 3), (3, 7), (32, 32)])
def test_any_size_from_2x2_to_32x32(n, m):
    shape = make_shape("cylinder", radius=60.0, axis_angle=30.0)
    dev, host, boot = make(n=n, m=m, shape=shape, rate=5.0)
    hello = only(boot, p.MsgType.HELLO)[0]
    assert (hello.n, hello.m) == (n, m)
    host.send(p.Start(1), 100.0)
    scan = only(host.poll(100.2), p.MsgType.SCAN)[0]
    assert scan.resistance_uohm.shape == (2, 2, n, m)
    assert scan.step_period_ns == round(1e12 / (5000 * 2 * min(n, m)))
    eps = gauge_strain(scan.resistances_ohm(), dev.calibration.gauge_factor, dev.calibration.base_resistance_ohm)
    np.testing.assert_allclose(eps, np.stack(gauge_strains(shape, n, m)), atol=3e-7)


from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=150, deadline=None)
@given(chunks=st.lists(st.binary(max_size=400), max_size=6), seed=st.integers(0, 3))
def test_arbitrary_host_bytes_never_break_the_firmware(chunks, seed):
    dev = Device(ScannerSpec(n=2, m=3, seed=seed, electrical=IDEAL), make_shape("flat"), now_s=0.0)
    dec = p.StreamDecoder()
    dec.feed(dev.poll(0.0))
    valid = p.encode_frame(p.Ping(77, b"alive"), 0)
    for k, chunk in enumerate(chunks):
        dec.feed(dev.on_bytes(chunk, 0.01 * k))
    # whatever came before, a delimiter then a valid command is answered
    frames = dec.feed(dev.on_bytes(b"\x00" + valid, 1.0))
    assert any(f.msg_type == p.MsgType.ACK and f.msg.request_id == 77 for f in frames)
    assert dec.crc_errors == dec.cobs_errors == 0  # the device's own output is always clean
