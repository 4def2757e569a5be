"""skinmap.ports: the ScannerPort contract on every implementation (in-memory pair, pyserial over
a pty and over socket://, the emulator's device loopback), and the loopback's frames decoded
by skinmap.protocol."""
from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest

from skinmap.emulator.device import Device, ScannerSpec
from skinmap.emulator.linkfaults import FaultyLink, LinkFaults
from skinmap.emulator.loopback import DeviceLoopback
from skinmap.emulator.physics import make_shape
from skinmap.ports import (RECV_CHUNK, PortClosed, PortError, PortOpenError, PortVanished, ScannerPort,
                           SerialScannerPort, memory_pair)
from skinmap.protocol import Ack, Hello, QueryInfo, Scan, SetScanRate, Start, StreamDecoder, encode_frame


def recv_until(port: ScannerPort, want: int, timeout_s: float = 5.0) -> bytes:
    got = bytearray()
    end = time.monotonic() + timeout_s
    while len(got) < want and time.monotonic() < end:
        got += port.recv(0.05)
    return bytes(got)


# ---------------------------------------------------------------------------------------------
# the in-memory pair


def test_memory_pair_carries_bytes_both_ways():
    a, b = memory_pair("t")
    a.send(b"hello")
    b.send(b"world")
    assert b.in_waiting == 5
    assert b.recv(1.0) == b"hello" and a.recv(1.0) == b"world"
    assert a.recv(0) == b"" and a.recv(0.02) == b""  # a timeout is no error


def test_memory_recv_returns_at_most_one_chunk():
    a, b = memory_pair()
    a.send(bytes(RECV_CHUNK + 10))
    assert len(b.recv(0)) == RECV_CHUNK and len(b.recv(0)) == 10


def test_recv_without_timeout_waits_for_bytes_from_another_thread():
    a, b = memory_pair()
    threading.Timer(0.05, a.send, args=(b"late",)).start()
    assert b.recv(None) == b"late"


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_a_bad_timeout_is_refused(bad):
    a, _ = memory_pair()
    with pytest.raises(ValueError, match="recv timeout"):
        a.recv(bad)


def test_closed_port_raises_port_closed_and_closing_again_is_harmless():
    a, b = memory_pair("c")
    a.close()
    a.close()
    assert a.closed
    for call in (lambda: a.send(b"x"), lambda: a.recv(0), a.reset_input):
        with pytest.raises(PortClosed, match="port c:0 is closed"):
            call()


def test_closing_one_end_makes_the_other_vanish_after_it_read_what_was_sent():
    a, b = memory_pair("v")
    a.send(b"last words")
    a.close()
    assert b.recv(1.0) == b"last words"
    with pytest.raises(PortVanished, match="other end closed") as exc:
        b.recv(1.0)
    assert not isinstance(exc.value, PortClosed) and isinstance(exc.value, PortError)
    assert isinstance(exc.value, OSError)
    with pytest.raises(PortVanished):
        b.send(b"anyone?")


def test_closing_while_another_thread_waits_wakes_it_with_port_closed():
    a, _b = memory_pair()
    errors: list[BaseException] = []

    def wait() -> None:
        try:
            a.recv(None)
        except PortError as exc:
            errors.append(exc)

    t = threading.Thread(target=wait)
    t.start()
    time.sleep(0.05)
    a.close()
    t.join(2.0)
    assert not t.is_alive() and len(errors) == 1 and isinstance(errors[0], PortClosed)


def test_reset_input_discards_what_was_not_read():
    a, b = memory_pair()
    a.send(b"stale")
    b.reset_input()
    a.send(b"fresh")
    assert b.recv(1.0) == b"fresh"


def test_context_manager_closes():
    a, b = memory_pair()
    with a as port:
        port.send(b"x")
    assert a.closed and b.recv(0) == b"x"
    with pytest.raises(PortVanished):
        b.recv(0)


# ---------------------------------------------------------------------------------------------
# pyserial


def test_serial_port_that_does_not_exist_is_an_open_error_naming_it(tmp_path):
    path = str(tmp_path / "ttyNONE")
    with pytest.raises(PortOpenError, match="ttyNONE"):
        SerialScannerPort(path)


def test_serial_port_over_a_pty_sends_receives_and_is_exclusive():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    try:
        with SerialScannerPort(path, exclusive=True) as port:
            with pytest.raises(PortOpenError, match="exclusively lock"):
                SerialScannerPort(path, exclusive=True)
            port.send(b"\x01\x02\x00")
            got = b""
            end = time.monotonic() + 2
            while len(got) < 3 and time.monotonic() < end:
                got += os.read(master, 16)
            assert got == b"\x01\x02\x00"
            os.write(master, b"from device")
            assert recv_until(port, 11) == b"from device"
            assert port.recv(0.02) == b""
        assert port.closed
    finally:
        os.close(master)
        os.close(slave)


def test_serial_port_over_socket_url_tells_a_hang_up_from_a_timeout():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    try:
        port = SerialScannerPort(f"socket://127.0.0.1:{server.getsockname()[1]}")
        conn, _ = server.accept()
        with port:
            conn.sendall(b"abc")
            assert recv_until(port, 3) == b"abc"
            assert port.recv(0.02) == b""  # silent device: no error
            port.send(b"xyz")
            assert conn.recv(16) == b"xyz"
            conn.close()
            with pytest.raises(PortVanished):
                port.recv(1.0)
    finally:
        server.close()


# ---------------------------------------------------------------------------------------------
# the emulator's device on an in-process line


def make_loopback(**kw) -> tuple[Device, DeviceLoopback]:
    dev = Device(ScannerSpec(n=5, m=5, scan_rate_hz=100.0, seed=3), make_shape("flat"), now_s=time.monotonic())
    return dev, DeviceLoopback(dev, **kw)


def frames_until(port: ScannerPort, decoder: StreamDecoder, done, timeout_s: float = 5.0) -> list:
    frames: list = []
    end = time.monotonic() + timeout_s
    while not done(frames) and time.monotonic() < end:
        frames += decoder.feed(port.recv(0.05))
    return frames


def test_loopback_gives_hello_then_scans_decoded_by_the_protocol():
    dev, loop = make_loopback()
    decoder = StreamDecoder()
    with loop.open() as port:
        boot = frames_until(port, decoder, lambda fs: any(isinstance(f.msg, Hello) for f in fs))
        hello = next(f for f in boot if isinstance(f.msg, Hello))
        assert hello.seq == 0 and (hello.msg.n, hello.msg.m) == (5, 5)
        assert hello.msg.serial_number == dev.serial_number
        port.send(encode_frame(SetScanRate(1, 100_000), 0) + encode_frame(Start(2), 1))
        frames = frames_until(port, decoder, lambda fs: sum(isinstance(f.msg, Scan) for f in fs) >= 5)
    acks = [f.msg for f in frames if isinstance(f.msg, Ack)]
    scans = [f.msg for f in frames if isinstance(f.msg, Scan)]
    assert [a.request_id for a in acks[:2]] == [1, 2]
    assert len(scans) >= 5 and all((s.n, s.m) == (5, 5) for s in scans)
    assert np.all(np.diff([s.sample_index for s in scans]) == 1)
    assert decoder.counters()["crc_errors"] == 0


def test_loopback_answers_a_query_at_once():
    _, loop = make_loopback()
    decoder = StreamDecoder()
    with loop.open() as port:
        frames_until(port, decoder, lambda fs: any(isinstance(f.msg, Hello) for f in fs))
        port.send(encode_frame(QueryInfo(9), 0))
        again = frames_until(port, decoder, lambda fs: any(isinstance(f.msg, Hello) for f in fs))
    assert any(isinstance(f.msg, Hello) and f.seq != 0 for f in again)  # an answer, not a reboot


def test_loopback_unplug_vanishes_refuses_opens_and_replug_boots_the_scanner():
    dev, loop = make_loopback()
    port = loop.open()
    with pytest.raises(PortOpenError, match="already open"):
        loop.open()
    boots = dev.boot_count
    loop.unplug()
    with pytest.raises(PortVanished, match="unplugged"):
        port.recv(1.0)
    with pytest.raises(PortVanished):
        port.send(b"\x00")
    with pytest.raises(PortOpenError, match="no scanner on the line"):
        loop.open()
    port.close()
    loop.replug()
    assert dev.boot_count == boots + 1
    with loop.open() as again:
        frames = frames_until(again, StreamDecoder(), lambda fs: any(isinstance(f.msg, Hello) for f in fs))
    assert any(isinstance(f.msg, Hello) and f.seq == 0 for f in frames)
    assert loop.opens == 2


def test_loopback_line_model_damages_the_devices_bytes():
    _, loop = make_loopback(line=FaultyLink(LinkFaults(bit_flip_rate=0.01), np.random.default_rng(1)).apply)
    decoder = StreamDecoder()
    with loop.open() as port:
        port.send(encode_frame(SetScanRate(1, 100_000), 0) + encode_frame(Start(2), 1))
        frames_until(port, decoder, lambda fs: decoder.counters()["crc_errors"] + decoder.counters()["cobs_errors"] >= 3)
    counters = decoder.counters()
    assert counters["crc_errors"] + counters["cobs_errors"] >= 3
