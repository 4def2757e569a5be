"""MCAP logger and reading tools: round trips, rotation, naming, cut files, storage errors,
inspection and the surface PNG."""

from __future__ import annotations

import errno
import json
import os
import random
import shutil
import struct
import subprocess
import sys

import numpy as np
import pytest
from conftest import CheckedFile
from mcap.reader import make_reader

from skinmap.daemon.mcapinspect import inspect
from skinmap.daemon.mcapread import NotMcapError, iter_messages_file_order
from skinmap.daemon.mcaprecover import recover
from skinmap.daemon.mcapsnapshot import render_surface_png
from skinmap.daemon.foxglove_log import decode_protobuf
from skinmap.daemon.mcaplog import LogStorageError, McapLogger
from skinmap.wire import messages as wire

T0 = 1_795_000_000_000_000_000  # 2026-11-18, a plausible wall-clock time in ns


class FakeClock:
    """Wall and monotonic clocks under test control."""

    def __init__(self) -> None:
        self.wall = T0
        self.mono = 0

    def advance(self, seconds: float) -> None:
        self.wall += int(seconds * 1e9)
        self.mono += int(seconds * 1e9)


def make_logger(directory, clock: FakeClock | None = None, **kw) -> McapLogger:
    clock = clock or FakeClock()
    return McapLogger(directory, clock=lambda: clock.wall, monotonic=lambda: clock.mono, **kw)


def read_all(path):
    """(topic, schema name, encoding, log time, data) with the regular time-ordered reader."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        return [(c.topic, s.name if s else "", c.message_encoding, m.log_time, m.data)
                for s, c, m in reader.iter_messages(log_time_order=False)]


def strains_payload(seq, up, lo):
    return wire.encode_strains(seq, 0, 0, up, lo, np.full(np.shape(up), 3, dtype=np.uint8))


def surface_payload(seq, nodes_mm, normals, points_mm=None):
    n, m = np.shape(nodes_mm)[:2]
    cloud = None if points_mm is None else np.asarray(points_mm) / 1000.0
    return wire.encode_surface(seq, 0, 0, np.asarray(nodes_mm) / 1000.0, normals,
                               np.full((n, m), 2e-5), cloud)


def elements_payload(seq, positions_mm):
    k = len(positions_mm)
    normals = np.tile([0.0, 0.0, 1.0], (k, 1))
    return wire.encode_elements(seq, 0, 0, np.asarray(positions_mm) / 1000.0, normals,
                                np.full(k, 1e-5), np.ones(k, dtype=np.uint8))


def files(directory, suffix):
    return sorted(str(p) for p in directory.iterdir() if p.name.endswith(suffix))


# --------------------------------------------------------------------------------------------
# round trips


def test_every_helper_round_trips(tmp_path):
    rng = np.random.default_rng(1)
    up, lo = rng.normal(size=(2, 3, 4)) * 1e-3, rng.normal(size=(2, 3, 4)) * 1e-3
    nodes, normals = rng.normal(size=(3, 4, 3)) * 10, rng.normal(size=(3, 4, 3))
    points = rng.normal(size=(25, 3)) * 20
    frame = bytes([5, 1, 2, 3, 4, 0])
    logger = make_logger(tmp_path, metadata={"device": "emulator", "grid": [3, 4]})
    logger.log_config(T0, "[scanner]\nport = 'x'\n", {"gf": np.full(4, 1.24), "r0": 6.55})
    logger.log_raw_frame(T0 + 1, frame)
    logger.log_strains(T0 + 2, strains_payload(7, up, lo))
    logger.log_surface(T0 + 3, surface_payload(7, nodes, normals, points))
    logger.log_elements(T0 + 4, elements_payload(7, points[:5]), latency_ms=12.5)
    logger.log_status(T0 + 5, {"state": "running", "rate_hz": 10.0})
    logger.log_event(T0 + 6, "warning", "scanner slow", name="serial")
    logger.write("/custom", T0 + 7, b"xyz", schema_name="my.Thing", schema_encoding="",
                 schema_data=b"", message_encoding="application/octet-stream")
    assert logger.current_path.endswith(".mcap.active")
    logger.close()
    (path,) = files(tmp_path, ".mcap")
    msgs = {m[0]: m for m in read_all(path)}
    assert set(msgs) == {"/config", "/raw", "/strains", "/strains/plot", "/surface",
                         "/surface/nodes", "/scene", "/tf", "/elements", "/elements/poses",
                         "/elements/plot", "/status", "/log", "/custom"}
    assert msgs["/raw"][4] == frame and msgs["/raw"][2] == "skinmap.cobs-frame"
    st = wire.decode_strains(msgs["/strains"][4])
    assert st.seq == 7 and np.array_equal(st.eps_upper, up) and np.array_equal(st.eps_lower, lo)
    plot = json.loads(msgs["/strains/plot"][4])
    np.testing.assert_allclose(plot["upper_row"], up[0].ravel(), rtol=1e-6)
    np.testing.assert_allclose(plot["lower_col"], lo[1].ravel(), rtol=1e-6)
    sf = wire.decode_surface(msgs["/surface/nodes"][4])
    assert sf.seq == 7 and np.array_equal(sf.nodes, nodes / 1000) and np.array_equal(sf.normals, normals)
    assert msgs["/surface"][1] == "foxglove.PointCloud" and msgs["/surface"][2] == "protobuf"
    cloud = decode_protobuf("foxglove.PointCloud", msgs["/surface"][4])
    assert (cloud.timestamp.seconds, cloud.timestamp.nanos) == ((T0 + 3) // 10**9, (T0 + 3) % 10**9)
    assert cloud.point_stride == 12 and [f.name for f in cloud.fields] == ["x", "y", "z"]
    np.testing.assert_allclose(np.frombuffer(cloud.data, "<f4").reshape(-1, 3) * 1e3, points,
                               rtol=1e-6, atol=1e-4)
    assert msgs["/elements"][4] == elements_payload(7, points[:5])
    assert msgs["/elements"][2] == "skinmap.elements/2"
    poses = decode_protobuf("foxglove.PosesInFrame", msgs["/elements/poses"][4])
    got = np.array([[p.position.x, p.position.y, p.position.z] for p in poses.poses]) * 1e3
    np.testing.assert_allclose(got, points[:5], rtol=1e-9, atol=1e-9)
    assert json.loads(msgs["/elements/plot"][4])["latency_ms"] == 12.5
    assert json.loads(msgs["/status"][4]) == {"state": "running", "rate_hz": 10.0}
    log = decode_protobuf("foxglove.Log", msgs["/log"][4])
    assert (log.level, log.message, log.name) == (3, "scanner slow", "serial")
    assert msgs["/custom"][1:] == ("my.Thing", "application/octet-stream", T0 + 7, b"xyz")
    config = json.loads(msgs["/config"][4])
    assert config["calibration"] == {"gf": [1.24] * 4, "r0": 6.55}
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        names = [a.name for a in reader.iter_attachments()]
    assert meta["skinmap.start"]["device"] == "emulator"
    assert meta["skinmap.start"]["grid"] == "[3,4]"
    assert meta["skinmap.config"]["config_text"].startswith("[scanner]")
    assert names == ["config.toml", "calibration.json"]
    # File-order reading of the finished file gives the same messages.
    it = iter_messages_file_order(path)
    assert [(m.topic, m.schema_name, m.message_encoding, m.log_time_ns, m.data)
            for m in it] == read_all(path)
    assert it.end.complete and it.end.valid_bytes == os.path.getsize(path)
    assert logger.messages_written == 15 and logger.files_finished == 1
    assert logger.bytes_written == os.path.getsize(path)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_temporary_name_then_final_name(tmp_path, compression):
    logger = make_logger(tmp_path, compression=compression)
    assert logger.current_path is None  # opened lazily
    logger.log_raw_frame(T0, b"\x01\x00")
    active = logger.current_path
    assert active.endswith(".mcap.active") and os.path.basename(active).startswith("skinmap-")
    assert files(tmp_path, ".mcap") == [] and files(tmp_path, ".mcap.active") == [active]
    logger.close()
    logger.close()  # idempotent
    assert logger.current_path is None
    assert files(tmp_path, ".mcap.active") == []
    assert files(tmp_path, ".mcap") == [active[: -len(".active")]]
    with pytest.raises(ValueError, match="closed"):
        logger.log_raw_frame(T0, b"\x01\x00")


# --------------------------------------------------------------------------------------------
# rotation


def test_rotation_by_size_keeps_every_file_standalone(tmp_path):
    logger = make_logger(tmp_path, max_bytes=64 * 1024, chunk_size=4096, compression="none")
    logger.log_config(T0, "rate = 10\n", {"gf": [1.2]})
    rng = np.random.default_rng(0)
    frames = [rng.bytes(300) for _ in range(600)]  # ~180 kB, incompressible anyway
    for i, frame in enumerate(frames):
        logger.log_raw_frame(T0 + i * 1_000_000, frame)
        logger.log_status(T0 + i * 1_000_000, {"i": i})
    logger.close()
    done = files(tmp_path, ".mcap")
    assert len(done) >= 3 and logger.files_finished == len(done)
    assert files(tmp_path, ".mcap.active") == []
    raw = []
    for path in done:
        assert os.path.getsize(path) <= 64 * 1024 + 8 * 1024  # plus the summary section
        msgs = read_all(path)  # each file is readable on its own
        topics = {m[0] for m in msgs}
        assert {"/raw", "/status", "/config"} <= topics
        with open(path, "rb") as f:
            meta = [m.name for m in make_reader(f).iter_metadata()]
        assert meta.count("skinmap.start") == 1 and meta.count("skinmap.config") == 1
        raw += [m[4] for m in msgs if m[0] == "/raw"]
    assert raw == frames
    assert logger.bytes_written == sum(os.path.getsize(p) for p in done)


def test_rotation_by_time_with_fake_clock(tmp_path):
    clock = FakeClock()
    logger = make_logger(tmp_path, clock, max_seconds=5.0)
    for i in range(12):
        logger.log_raw_frame(clock.wall, bytes([i + 1, 0]))
        clock.advance(1.0)
    logger.close()
    done = files(tmp_path, ".mcap")
    counts = [len(read_all(p)) for p in done]
    assert counts == [5, 5, 2]
    stamps = [os.path.basename(p).split("-")[1] for p in done]
    assert stamps == sorted(stamps) and len(set(stamps)) == 3  # UTC time of opening
    assert [os.path.basename(p).split("-")[2] for p in done] == [
        "0001.mcap", "0002.mcap", "0003.mcap"]


def test_old_chunk_is_closed_and_synced(tmp_path):
    clock = FakeClock()
    logger = make_logger(tmp_path, clock, max_chunk_age_s=0.5)
    logger.log_raw_frame(clock.wall, b"\x01\x00")
    logger.log_raw_frame(clock.wall, b"\x02\x00")
    assert logger.messages_flushed == 0
    clock.advance(0.6)
    logger.log_raw_frame(clock.wall, b"\x03\x00")
    assert logger.messages_flushed == 3  # chunk older than max_chunk_age_s was written
    copy = tmp_path / "copy.mcap.active"
    shutil.copy(logger.current_path, copy)  # what a crash right now would leave behind
    assert [m.data for m in iter_messages_file_order(copy)] == [b"\x01\x00", b"\x02\x00",
                                                                b"\x03\x00"]
    logger.log_raw_frame(clock.wall, b"\x04\x00")
    logger.flush()
    assert logger.messages_flushed == 4
    # Idle: tick() closes an old chunk, and finishes a file whose time is up.
    logger.log_raw_frame(clock.wall, b"\x05\x00")
    logger.tick()
    assert logger.messages_flushed == 4
    clock.advance(0.6)
    logger.tick()
    assert logger.messages_flushed == 5 and logger.files_finished == 0
    clock.advance(3600)
    logger.tick()
    assert logger.files_finished == 1 and logger.current_path is None
    logger.close()


# --------------------------------------------------------------------------------------------
# cut files


def _write_sample_log(directory, compression="zstd"):
    logger = make_logger(directory, chunk_size=1500, compression=compression)
    logger.log_config(T0, "a = 1\n", {"gf": [1.24, 1.3]})
    rng = np.random.default_rng(3)
    for i in range(60):
        t = T0 + i * 50_000_000
        logger.log_raw_frame(t, rng.bytes(40) + b"\x00")
        logger.log_strains(t, strains_payload(i, rng.normal(size=(2, 2, 3)),
                                              rng.normal(size=(2, 2, 3))))
        if i % 10 == 0:
            logger.log_event(t, "info", f"tick {i}")
    logger.close()
    (path,) = files(directory, ".mcap")
    return path


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_cut_at_random_offsets_yields_a_prefix(tmp_path, compression):
    path = _write_sample_log(tmp_path, compression)
    full = list(iter_messages_file_order(path))
    assert len(full) == 1 + 60 + 2 * 60 + 6
    data = open(path, "rb").read()
    rnd = random.Random(42)
    offsets = sorted({0, 1, 7, 8, 9, 20, len(data) - 1, len(data) - 8}
                     | {rnd.randrange(len(data)) for _ in range(40)})
    counts = []
    for cut in offsets:
        cut_path = tmp_path / f"cut{cut}.mcap.active"
        cut_path.write_bytes(data[:cut])
        it = iter_messages_file_order(cut_path)
        got = list(it)
        assert got == full[: len(got)], f"cut at {cut} is not a prefix"
        assert not it.end.complete and it.end.valid_bytes <= cut
        counts.append(len(got))
        if cut in (len(data) - 1, len(data) - 8):
            assert len(got) == len(full)  # only the summary/footer was lost
        out = tmp_path / f"rec{cut}.mcap"
        report = recover(cut_path, out)
        assert report.messages == len(got) and not report.end.complete
        assert [m[4] for m in read_all(out)] == [m.data for m in got]
    assert counts == sorted(counts) and counts[0] == 0 and 0 < counts[len(counts) // 2]


def test_zero_filled_tail_and_bad_chunk_are_not_fatal(tmp_path):
    path = _write_sample_log(tmp_path)
    full = list(iter_messages_file_order(path))
    data = open(path, "rb").read()
    half = tmp_path / "zeros.mcap.active"
    half.write_bytes(data[: len(data) // 2] + bytes(4096))  # power loss: zeros after the data
    it = iter_messages_file_order(half)
    got = list(it)
    assert 0 < len(got) < len(full) and got == full[: len(got)]
    assert "offset" in it.end.reason
    # Flip one byte inside the data section: reading stops before the damaged chunk.
    with open(path, "rb") as f:
        second = make_reader(f).get_summary().chunk_indexes[1]
    flipped = bytearray(data)
    flipped[second.chunk_start_offset + second.chunk_length - 10] ^= 0xFF
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(flipped))
    it = iter_messages_file_order(bad)
    got = list(it)
    assert got == full[: len(got)] and len(got) < len(full) and not it.end.complete
    assert "corrupt chunk record" in it.end.reason
    (tmp_path / "x.txt").write_bytes(b"hello world, not mcap")
    with pytest.raises(NotMcapError, match="not an MCAP file"):
        list(iter_messages_file_order(tmp_path / "x.txt"))


def test_recover_default_names(tmp_path):
    path = _write_sample_log(tmp_path)
    data = open(path, "rb").read()
    active = tmp_path / "skinmap-20261118T000000Z-0009.mcap.active"
    active.write_bytes(data[: len(data) * 2 // 3])
    report = recover(active)
    assert report.output == str(tmp_path / "skinmap-20261118T000000Z-0009.mcap")
    assert active.exists()  # the source is left alone
    again = recover(active)  # the finished name is taken now
    assert again.output.endswith("-0009.recovered.mcap")
    assert read_all(report.output) == read_all(again.output)
    assert report.attachments == 2 and report.metadata == 2
    assert report.topics["/raw"] == len([m for m in read_all(report.output) if m[0] == "/raw"])
    assert "recovered" in report.format()
    with pytest.raises(ValueError, match="overwrite"):
        recover(active, active)


# --------------------------------------------------------------------------------------------
# storage errors


class FullDisk(CheckedFile):
    """A raw file that accepts `budget` bytes, then fails like a full disk."""

    def __init__(self, path: str, budget: int):
        super().__init__(path, self._spend)
        self.budget = budget

    def _spend(self, n: int) -> None:
        if n > self.budget:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.budget -= n


def test_disk_full_raises_then_logging_resumes(tmp_path):
    clock = FakeClock()
    space = {"budget": 20_000}

    def opener(path):
        if space["budget"] is None:
            return open(path, "xb", buffering=0)
        return FullDisk(path, space["budget"])

    logger = make_logger(tmp_path, clock, chunk_size=1024, retry_interval_s=3.0,
                         open_file=opener)
    logger.log_config(clock.wall, "x = 1\n", {})
    rng = np.random.default_rng(5)
    frames = [struct.pack("<I", i) + rng.bytes(200) for i in range(400)]  # incompressible
    written = 0
    with pytest.raises(LogStorageError) as info:
        for frame in frames:
            logger.log_raw_frame(clock.wall, frame)
            written += 1
    err = info.value
    assert err.errno == errno.ENOSPC and err.path.endswith(".mcap.active")
    assert err.path in str(err) and "No space left" in str(err)
    assert not logger.healthy and logger.current_path is None
    cut = logger.abandoned_paths[0]
    # Within the retry interval: dropped quietly, counted.
    logger.log_raw_frame(clock.wall, b"dropped")
    assert logger.messages_dropped == 1
    # Still full at the retry: the retrying call raises again.
    clock.advance(3.5)
    space["budget"] = 10
    with pytest.raises(LogStorageError):
        logger.log_raw_frame(clock.wall, b"still full")
    # Space returns: the next retry opens a fresh file, config repeated.
    clock.advance(3.5)
    space["budget"] = None
    logger.log_raw_frame(clock.wall, b"after")
    assert logger.healthy and logger.current_path not in (None, cut)
    logger.close()
    # Nothing that reached the disk before the error is lost: the cut file holds a prefix.
    salvaged = [m.data for m in iter_messages_file_order(cut) if m.topic == "/raw"]
    assert salvaged == frames[: len(salvaged)] and len(salvaged) >= written - 10
    (resumed,) = [p for p in files(tmp_path, ".mcap")]
    msgs = read_all(resumed)
    assert [m[4] for m in msgs if m[0] == "/raw"] == [b"after"]
    assert any(m[0] == "/config" for m in msgs)


def test_missing_or_unwritable_folder(tmp_path):
    clock = FakeClock()
    missing = tmp_path / "logs"
    logger = make_logger(missing, clock, retry_interval_s=1.0)
    with pytest.raises(LogStorageError) as info:
        logger.log_raw_frame(clock.wall, b"\x01\x00")
    assert info.value.errno == errno.ENOENT and str(missing) in str(info.value)
    assert not logger.healthy
    missing.mkdir()
    clock.advance(1.5)
    logger.log_raw_frame(clock.wall, b"\x02\x00")
    assert logger.healthy
    logger.close()
    assert [m[4] for m in read_all(files(missing, ".mcap")[0])] == [b"\x02\x00"]

    # A folder that cannot exist (its parent is a file) — what a read-only mount looks like
    # to a root process that chmod cannot stop.
    blocker = tmp_path / "plainfile"
    blocker.write_text("x")
    logger = make_logger(blocker / "logs", clock)
    with pytest.raises(LogStorageError) as info:
        logger.log_status(clock.wall, {"a": 1})
    assert info.value.errno == errno.ENOTDIR and "plainfile" in str(info.value)
    logger.close()


def test_bad_input_is_rejected_clearly(tmp_path):
    with pytest.raises(ValueError, match="compression"):
        McapLogger(tmp_path, compression="gzip")
    with pytest.raises(ValueError, match="fsync"):
        McapLogger(tmp_path, fsync="sometimes")
    with pytest.raises(ValueError, match="max_bytes"):
        McapLogger(tmp_path, max_bytes=10)
    logger = make_logger(tmp_path)
    with pytest.raises(wire.MessageError, match="expected a strains message"):
        logger.log_strains(T0, elements_payload(1, np.zeros((2, 3))))
    with pytest.raises(wire.MessageError, match="truncated"):
        logger.log_surface(T0, surface_payload(1, np.zeros((2, 2, 3)), np.zeros((2, 2, 3)))[:-1])
    with pytest.raises(ValueError, match="NaN"):
        logger.log_surface(T0, surface_payload(1, np.full((2, 2, 3), np.nan), np.zeros((2, 2, 3))))
    with pytest.raises(TypeError, match="elements payload must be bytes"):
        logger.log_elements(T0, "text")
    with pytest.raises(ValueError, match="log level"):
        logger.log_event(T0, "loud", "x")
    with pytest.raises(ValueError, match="t_ns"):
        logger.log_raw_frame(-1, b"x")
    with pytest.raises(TypeError, match="raw frame must be bytes"):
        logger.log_raw_frame(T0, "text")
    with pytest.raises(ValueError, match="status is not JSON"):
        logger.log_status(T0, {"x": object()})
    with pytest.raises(ValueError, match="already logged"):
        logger.write("/raw", T0, b"x", schema_name="other", schema_encoding="",
                     schema_data=b"", message_encoding="x")
    logger.close()


# --------------------------------------------------------------------------------------------
# inspection and PNG


def _surface(t: float):
    u, v = np.meshgrid(np.linspace(-20, 20, 5), np.linspace(-15, 15, 4))
    z = 3.0 * np.exp(-(u**2 + v**2) / 200.0) * (1 + 0.1 * t)
    nodes = np.stack([u, v, z], axis=-1)
    normals = np.zeros_like(nodes)
    normals[..., 2] = 1.0
    return nodes, normals, nodes.reshape(-1, 3)


@pytest.mark.slow
def test_inspect_reports_counts_gaps_and_problems(tmp_path):
    clock = FakeClock()
    logger = make_logger(tmp_path, clock)
    seqs = [0, 1, 2, 3, 6, 7, 8]  # 4 and 5 lost
    for k, seq in enumerate(seqs):
        if k == 5:
            clock.advance(2.5)  # a stall
        nodes, normals, points = _surface(k)
        logger.log_surface(clock.wall, surface_payload(seq, nodes, normals, points))
        logger.log_strains(clock.wall, strains_payload(seq, np.zeros((2, 4, 5)), np.zeros((2, 4, 5))))
        clock.advance(0.1)
    logger.log_event(clock.wall, "error", "serial port vanished")
    logger.log_event(clock.wall, "info", "all fine")
    logger.log_status(clock.wall, {"state": "degraded", "errors": ["crc"]})
    logger.close()
    (path,) = files(tmp_path, ".mcap")
    report = inspect(path, gap_threshold_s=1.0)
    assert report.end.complete
    assert report.topics["/surface"].count == 7 and report.topics["/strains"].count == 7
    assert report.topics["/surface"].rate_hz == pytest.approx(6 / 3.1)
    assert sorted((g.topic, g.after_seq, g.next_seq, g.missing)
                  for g in report.sequence_gaps) == [
        ("/strains", 3, 6, 2), ("/strains/plot", 3, 6, 2), ("/surface", 3, 6, 2),
        ("/surface/nodes", 3, 6, 2)]
    assert report.topics["/surface"].time_gaps[0][1] - report.topics["/surface"].time_gaps[0][
        0] == pytest.approx(2.6e9)
    levels = sorted((i.source, i.level) for i in report.issues)
    assert levels == [("/log", "ERROR"), ("/status", "ERROR"), ("/status", "WARNING")]
    text = report.format()
    assert "serial port vanished" in text and "2 missing" in text and "time gap" in text
    assert "all fine" not in text

    out = tmp_path / "surface.png"
    snap = render_surface_png(path, 0.25, out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert snap.seq == 2 and snap.nodes.shape == (4, 5, 3) and snap.points.shape == (20, 3)
    last = render_surface_png(path, None, tmp_path / "last.png")
    assert last.seq == 8
    with pytest.raises(ValueError, match="t_s"):
        render_surface_png(path, float("nan"), out)


def test_inspect_and_png_on_a_cut_file(tmp_path):
    clock = FakeClock()
    logger = make_logger(tmp_path, clock, chunk_size=2000)
    for seq in range(30):
        nodes, normals, points = _surface(seq)
        logger.log_surface(clock.wall, surface_payload(seq, nodes, normals, points))
        clock.advance(0.1)
    cut = tmp_path / "cut.mcap.active"
    shutil.copy(logger.current_path, cut)
    logger.close()
    report = inspect(cut)
    assert not report.end.complete and "not finished" in report.format().lower()
    assert 0 < report.topics["/surface/nodes"].count <= 30
    assert report.sequence_gaps == []
    snap = render_surface_png(cut, 0.0, tmp_path / "cut.png")
    assert snap.seq == 0 and (tmp_path / "cut.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="no /surface"):
        empty = make_logger(tmp_path / "e", create_directory=True)
        empty.log_raw_frame(T0, b"\x01\x00")
        empty.close()
        render_surface_png(files(tmp_path / "e", ".mcap")[0], None, tmp_path / "n.png")


@pytest.mark.parametrize("policy", ["chunk", "close", "never"])
def test_fsync_policy(tmp_path, monkeypatch, policy):
    import skinmap.daemon.mcaplog as mcaplog

    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(mcaplog.os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    logger = make_logger(tmp_path, chunk_size=1024, fsync=policy)
    rng = np.random.default_rng(2)
    for i in range(40):
        logger.log_raw_frame(T0 + i, rng.bytes(300))
    during = len(synced)
    logger.close()
    with open(files(tmp_path, ".mcap")[0], "rb") as f:
        chunks = make_reader(f).get_summary().statistics.chunk_count
    if policy == "chunk":
        assert during >= chunks - 1 >= 5  # every emitted chunk, plus the file start
    elif policy == "close":
        assert during == 0 and len(synced) >= 1
    else:
        assert synced == []


# --------------------------------------------------------------------------------------------
# every file passes the MCAP doctor; the docs' topic table is the logger's


def doctor(path) -> subprocess.CompletedProcess:
    exe = os.path.join(os.path.dirname(sys.executable), "pymcap-cli")
    return subprocess.run([exe, "doctor", os.fspath(path), "--format", "jsonl"],
                          capture_output=True, text=True, timeout=120)


def test_every_kind_of_file_passes_the_mcap_doctor(tmp_path):
    clock = FakeClock()
    logger = make_logger(tmp_path, clock, chunk_size=4000, max_bytes=40_000)
    for seq in range(40):  # several rotations; a file with config, files without
        if seq == 0:
            logger.log_config(clock.wall, "a = 1\n", {"gf": [1.24]})
        nodes, normals, points = _surface(seq)
        logger.log_raw_frame(clock.wall, bytes([3, seq % 250 + 1, 7, 0]))
        logger.log_strains(clock.wall, strains_payload(seq, np.zeros((2, 4, 5)), np.zeros((2, 4, 5))))
        logger.log_elements(clock.wall, elements_payload(seq, points[:3]), latency_ms=1.0)
        logger.log_surface(clock.wall, surface_payload(seq, nodes, normals, points))
        logger.log_status(clock.wall, {"seq": seq})
        logger.log_event(clock.wall, "info", f"frame {seq}")
        clock.advance(0.1)
    logger.close()
    paths = files(tmp_path, ".mcap")
    assert len(paths) >= 2
    for path in paths:
        result = doctor(path)
        errors = [line for line in result.stdout.splitlines() if '"error"' in line]
        assert result.returncode == 0 and not errors, (path, result.stdout[-2000:], result.stderr[-500:])
    # A cut file is repaired by recover into one the doctor accepts too.
    logger = make_logger(tmp_path / "cut", clock, create_directory=True, chunk_size=2000)
    for seq in range(20):
        logger.log_strains(clock.wall, strains_payload(seq, np.zeros((2, 2, 2)), np.zeros((2, 2, 2))))
        clock.advance(0.1)
    cut = tmp_path / "cut" / "cut.mcap.active"
    shutil.copy(logger.current_path, cut)
    logger.close()
    recover(cut)
    fixed = [p for p in files(tmp_path / "cut", ".mcap") if "cut" in os.path.basename(p)]
    assert fixed, os.listdir(tmp_path / "cut")
    for path in fixed:
        assert doctor(path).returncode == 0, doctor(path).stdout[-2000:]


def test_docs_topic_table_is_the_loggers():
    from skinmap.daemon.mcapschema import topics_table

    doc = open(os.path.join(os.path.dirname(__file__), "..", "docs", "logging.md")).read()
    assert topics_table() in doc


def test_inspect_knows_the_configured_decimation_and_lists_real_warnings_first(tmp_path):
    """A healthy log decimated 50 -> 10 Hz with 1 Hz status and surfaces reports nothing; a
    real loss and a real stall are reported, after the logged errors."""
    from skinmap.daemon.config import DEMO_CONFIG

    clock = FakeClock()
    logger = make_logger(tmp_path, clock)
    logger.log_config(clock.wall, DEMO_CONFIG, {"gf": [1.24]})
    seq = 0
    for k in range(300):  # 30 s at 10 Hz, seq steps 4..6 (host-time decimation)
        seq += (5, 4, 6)[k % 3]
        if k == 200:
            seq += 10  # two processed scans lost
        if k == 250:
            clock.advance(4.0)  # the scanner stalled for 4 s
        logger.log_strains(clock.wall, strains_payload(seq, np.zeros((2, 2, 2)), np.zeros((2, 2, 2))))
        if k % 10 == 0:
            nodes, normals, points = _surface(k)
            logger.log_surface(clock.wall, surface_payload(seq, nodes, normals, points))
            logger.log_status(clock.wall, {"seq": seq})
        clock.advance(0.1)
    logger.log_event(clock.wall, "error", "serial port vanished")
    logger.close()
    (path,) = files(tmp_path, ".mcap")
    report = inspect(path)
    assert "processed 10 Hz (seq step 5)" in report.rates_source
    assert report.topics["/status"].expected_hz == 1 and report.topics["/strains"].expected_hz == 10
    strains_gaps = [(g.after_seq, g.missing) for g in report.sequence_gaps if g.topic == "/strains"]
    assert len(strains_gaps) == 1 and strains_gaps[0][1] == 2
    gapped = {t for t, s in report.topics.items() if s.time_gaps}
    assert gapped == set(report.topics) - {"/config", "/log"}  # the stall, seen on every topic
    assert all(len(s.time_gaps) == 1 for t, s in report.topics.items() if t in gapped)
    lines = report.format().splitlines()
    first_problem = next(i for i, line in enumerate(lines) if "gap" in line or "ERROR" in line)
    assert "ERROR in /log" in lines[first_problem] and "serial port vanished" in lines[first_problem]
    assert lines.index(next(line for line in lines if line.strip().startswith("topic"))) > first_problem
    # Without the config, each topic's own median step decides and says so.
    logger = make_logger(tmp_path / "nocfg", clock, create_directory=True)
    for k in range(50):
        logger.log_strains(clock.wall, strains_payload(5 * k, np.zeros((2, 2, 2)), np.zeros((2, 2, 2))))
        clock.advance(0.1)
    logger.close()
    report = inspect(files(tmp_path / "nocfg", ".mcap")[0])
    assert report.sequence_gaps == [] and "own median" in report.rates_source
