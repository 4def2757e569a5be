"""Hostile inputs for the log tools and the published data: what each one costs and what the
tool does with it. One line per scenario; it measures, it does not judge.

    .venv/bin/python bench/hostile_tools.py            # every scenario
    .venv/bin/python bench/hostile_tools.py bomb fifo  # only those whose name contains a word

Scenarios: MCAP decompression bombs and oversized records (inspect, replay, recover), a
/config that is a JSON list or has a list for its calibration (replay), deeply nested JSON in
/status and /log (inspect), a FIFO, a folder and /dev/zero given as the log (all three tools),
and forged puts on the gateway's key space from a foreign loopback Zenoh session.

Every log tool runs in its own process (`skinmap ...`), so its peak memory (ru_maxrss) and wall
time are its own. Zenoh sessions listen and connect on 127.0.0.1 only, multicast scouting off.

The file builders are also used by tests/test_tools_hostile.py.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, McapRecord, Message, Schema

REPO = Path(__file__).resolve().parents[1]
MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
MiB = 1024 * 1024


# ------------------------------------------------------------------------------------------
# MCAP files built from the library's low-level records


def record_bytes(records: Iterable[McapRecord]) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return builder.end()


def json_topic(channel_id: int, topic: str) -> list[McapRecord]:
    """Schema and channel records of a JSON topic (schema id = channel id)."""
    return [Schema(id=channel_id, name=topic.strip("/") or "x", encoding="jsonschema", data=b"{}"),
            Channel(id=channel_id, topic=topic, message_encoding="json", schema_id=channel_id, metadata={})]


def log_record(channel_id: int, t_ns: int, text: str, level: int = 4) -> Message:
    data = json.dumps({"timestamp": {"sec": t_ns // 10**9, "nsec": t_ns % 10**9}, "level": level,
                       "message": text, "name": "hostile", "file": "", "line": 0}).encode()
    return Message(channel_id=channel_id, log_time=t_ns, publish_time=t_ns, sequence=0, data=data)


def chunk_of(records: Iterable[McapRecord], compression: str = "zstd") -> Chunk:
    import zlib

    raw = record_bytes(records)
    if compression == "zstd":
        import zstandard

        data = zstandard.compress(raw)
    elif compression == "lz4":
        import lz4.frame

        data = lz4.frame.compress(raw)
    else:
        data = raw
    return Chunk(compression=compression, data=data, message_start_time=0, message_end_time=0,
                 uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw))


def zeros_compressed(n_bytes: int, compression: str) -> bytes:
    """`n_bytes` zero bytes compressed, built piecewise so the builder never holds them all."""
    piece = bytes(MiB)
    if compression == "zstd":
        import zstandard

        comp = zstandard.ZstdCompressor(level=19).compressobj()
    else:
        import lz4.frame

        comp = lz4.frame.LZ4FrameCompressor()
        head = comp.begin()
    out = [] if compression == "zstd" else [head]
    left = n_bytes
    while left > 0:
        step = min(left, MiB)
        out.append(comp.compress(piece[:step]))
        left -= step
    out.append(comp.flush())
    return b"".join(out)


def bomb_chunk(expands_to: int, declared: int | None = None, compression: str = "zstd") -> Chunk:
    """A chunk whose data decompresses to `expands_to` zero bytes and that declares `declared`
    uncompressed bytes (default: the truth)."""
    return Chunk(compression=compression, data=zeros_compressed(expands_to, compression),
                 message_start_time=0, message_end_time=0, uncompressed_crc=0,
                 uncompressed_size=expands_to if declared is None else declared)


def write_mcap(path: Path, middle: Iterable[McapRecord | bytes], *, t0_ns: int = 10**18) -> Path:
    """Header, a chunk with /log "before", `middle`, a chunk with /log "after", then the data end,
    an empty summary and the footer: a finished file whose records around `middle` are readable."""
    before = chunk_of([*json_topic(1, "/log"), log_record(1, t0_ns, "before")])
    after = chunk_of([*json_topic(1, "/log"), log_record(1, t0_ns + 10**9, "after")])
    with open(path, "wb") as f:
        f.write(MAGIC)
        f.write(record_bytes([Header(profile="", library="hostile_tools"), before]))
        for item in middle:
            f.write(item if isinstance(item, bytes) else record_bytes([item]))
        f.write(record_bytes([after, DataEnd(data_section_crc=0),
                              Footer(summary_start=0, summary_offset_start=0, summary_crc=0)]))
        f.write(MAGIC)
    return path


def oversized_attachment(path: Path, size: int) -> Path:
    """A finished file holding one attachment record of `size` bytes (sparse on disk)."""
    att = record_bytes([Attachment(create_time=0, log_time=0, name="big.bin",
                                   media_type="application/octet-stream", data=b"")])
    # Same record with its length and data-length fields set for `size` bytes of data.
    head_len = len(att) - 9  # body without data
    body_len = head_len + size
    with open(path, "wb") as f:
        f.write(MAGIC)
        f.write(record_bytes([Header(profile="", library="hostile_tools"),
                              chunk_of([*json_topic(1, "/log"), log_record(1, 10**18, "before")])]))
        f.write(att[:1] + body_len.to_bytes(8, "little"))
        body = bytearray(att[9:])
        # data length is the u64 just before the data (then the u32 CRC), i.e. the last 12 bytes
        body[-12:-4] = size.to_bytes(8, "little")
        f.write(body[:-4])
        f.seek(size, os.SEEK_CUR)  # the data: a hole, so the file costs no disk
        f.write(body[-4:])
        f.write(record_bytes([chunk_of([*json_topic(1, "/log"), log_record(1, 10**18 + 1, "after")]),
                              DataEnd(data_section_crc=0),
                              Footer(summary_start=0, summary_offset_start=0, summary_crc=0)]))
        f.write(MAGIC)
    return path


def nested_json_log(path: Path, depth: int = 100_000) -> Path:
    """A log with a /status and a /log message nested `depth` levels deep between readable ones."""
    deep = ("[" * depth + "]" * depth).encode()
    deep_log = ('{"level": 4, "message": ' + "[" * depth + "]" * depth + "}").encode()
    t = 10**18
    records: list[McapRecord] = [*json_topic(2, "/status")]
    records.append(Message(channel_id=2, log_time=t + 1, publish_time=t + 1, sequence=0, data=deep))
    records.append(Message(channel_id=2, log_time=t + 2, publish_time=t + 2, sequence=0,
                           data=b'{"healthy": false, "warnings": ["readable warning"]}'))
    records += [*json_topic(1, "/log"),
                Message(channel_id=1, log_time=t + 3, publish_time=t + 3, sequence=0, data=deep_log)]
    return write_mcap(path, [chunk_of(records)])


# ------------------------------------------------------------------------------------------
# a real log (emulator -> gateway, Zenoh off) and rewritten copies of it


def record_real_log(folder: Path, scans: int = 40) -> Path:
    """Run the emulator and an in-process gateway until `scans` shapes were made; the log file."""
    from skinmap.daemon.config import parse_config
    from skinmap.daemon.service import Gateway
    from skinmap.emulator.device import ScannerSpec
    from skinmap.emulator.emulator import Emulator
    from skinmap.emulator.physics import make_shape
    from skinmap.emulator.transport import PtyTransport

    folder.mkdir(parents=True, exist_ok=True)
    emu = Emulator(ScannerSpec(n=4, m=5, scan_rate_hz=30.0, seed=5), make_shape("cylinder", radius=40.0),
                   PtyTransport(link=folder / "tty"))
    emu.start()
    cfg = parse_config({"device": {"port": str(folder / "tty"), "name": "hostile", "scan_rate_hz": 30},
                        "output": {"rate_hz": 15}, "zenoh": {"enabled": False},
                        "log": {"directory": str(folder / "logs")}, "state": {"directory": str(folder / "state")}},
                       source="<hostile>")
    try:
        gw = Gateway(cfg)
        runner = threading.Thread(target=gw.run, daemon=True)
        runner.start()
        deadline = time.monotonic() + 60
        while gw.stats.results < scans and time.monotonic() < deadline:
            time.sleep(0.05)
        gw.stop()
        runner.join(timeout=20)
    finally:
        emu.stop()
    logs = sorted((folder / "logs").glob("*.mcap"))
    if not logs:
        raise RuntimeError(f"the gateway wrote no finished log in {folder / 'logs'}")
    return logs[0]


def rewrite_log(source: Path, out: Path, edit) -> Path:
    """Copy every message of `source` to `out` in file order; `edit(topic, data)` returns the list
    of payloads to write in its place (none drops it, several insert)."""
    from mcap.writer import Writer

    from skinmap.daemon.mcapread import FileOrderReader

    reader = FileOrderReader(source)
    with open(out, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="hostile_tools rewrite")
        ids: dict[int, int] = {}
        for item in reader.items():
            rec = item.record
            if not isinstance(rec, Message) or item.channel is None:
                continue
            ch = item.channel
            if ch.id not in ids:
                sid = 0
                if item.schema is not None:
                    sid = w.register_schema(item.schema.name, item.schema.encoding, item.schema.data)
                ids[ch.id] = w.register_channel(ch.topic, ch.message_encoding, sid, ch.metadata)
            for data in edit(ch.topic, rec.data):
                w.add_message(ids[ch.id], rec.log_time, data, rec.publish_time, rec.sequence)
        w.finish()
    return out


def bad_config_copies(real: Path, folder: Path) -> dict[str, Path]:
    """Copies of a real log with hostile /config records: 'list-inserted' (a JSON list and a
    config whose calibration is a list, right after the real one), 'only-list' (the only /config
    replaced by a list), 'calibration-list' (its calibration replaced by a list)."""
    def inserted(topic: str, data: bytes) -> list[bytes]:
        if topic != "/config":
            return [data]
        doc = json.loads(data)
        return [data, b"[1, 2, 3]", json.dumps({**doc, "calibration": [1, 2]}).encode()]

    def only_list(topic: str, data: bytes) -> list[bytes]:
        return [b"[1, 2, 3]"] if topic == "/config" else [data]

    def calibration_list(topic: str, data: bytes) -> list[bytes]:
        if topic != "/config":
            return [data]
        return [json.dumps({**json.loads(data), "calibration": [1, 2]}).encode()]

    return {name: rewrite_log(real, folder / f"{name}.mcap", edit)
            for name, edit in (("list-inserted", inserted), ("only-list", only_list),
                               ("calibration-list", calibration_list))}


# ------------------------------------------------------------------------------------------
# running the tools


# The tool's own peak RSS: VmHWM of its process, read at exit. (wait4's ru_maxrss would also
# count the RSS this script had when it forked the child.)
_PEAK_WRAPPER = """
import atexit, sys
def _peak():
    with open("/proc/self/status") as f:
        kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    sys.stderr.write(f"\\nHOSTILE_PEAK_KB {kb}\\n")
atexit.register(_peak)
from skinmap.daemon.cli import main
sys.exit(main(sys.argv[1:]))
"""


def run_tool_rss(args: list[str], timeout: float = 120.0) -> dict[str, Any]:
    """`skinmap ARGS` in its own process: exit code, wall time, its own peak RSS, output."""
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-c", _PEAK_WRAPPER, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    try:
        out, err = proc.communicate(timeout=timeout)
        timed_out = False
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        timed_out = True
    wall = time.monotonic() - t0
    peak = [int(line.split()[1]) for line in err.splitlines() if line.startswith("HOSTILE_PEAK_KB")]
    err = "\n".join(line for line in err.splitlines() if not line.startswith("HOSTILE_PEAK_KB"))
    result = {"rc": proc.returncode, "wall_s": wall, "out": out, "err": err, "timed_out": timed_out}
    if peak:
        result["rss_mib"] = peak[0] / 1024
    return result


def summary(result: dict[str, Any], grep: str = "") -> str:
    text = (result["out"] + result["err"]).strip().splitlines()
    traceback = any(line.startswith("Traceback") for line in text)
    pick = [line.strip() for line in text if grep and grep in line][:2] or text[-1:]
    what = "TIMED OUT (killed)" if result["timed_out"] else f"rc {result['rc']}"
    rss = f", peak {result['rss_mib']:.0f} MiB" if "rss_mib" in result else ""
    return (f"{what}, {result['wall_s']:.2f} s{rss}{', TRACEBACK' if traceback else ''}: "
            + " | ".join(p[:160] for p in pick))


# ------------------------------------------------------------------------------------------
# scenarios


def scenario_bombs(tmp: Path) -> None:
    files = {
        "bomb: zstd chunk declaring and holding 2 GiB of zeros": write_mcap(
            tmp / "bomb-2g.mcap", [bomb_chunk(2048 * MiB)]),
        "bomb: zstd chunk declaring 1 KiB, holding 1 GiB": write_mcap(
            tmp / "bomb-lie-zstd.mcap", [bomb_chunk(1024 * MiB, declared=1024)]),
        "bomb: lz4 chunk declaring 1 KiB, holding 256 MiB": write_mcap(
            tmp / "bomb-lie-lz4.mcap", [bomb_chunk(256 * MiB, declared=1024, compression="lz4")]),
        "bomb: attachment record of 1 GiB (sparse file)": oversized_attachment(tmp / "big-attachment.mcap", 1024 * MiB),
    }
    for name, path in files.items():
        size = path.stat().st_size
        label = f"{size / 1024:.1f} KB" if size < 100 * MiB else f"{size / MiB:.0f} MiB apparent"
        for tool in ("inspect", "recover", "replay"):
            args = [tool, str(path)] + (["-o", str(tmp / "out.mcap")] if tool == "recover" else []) + \
                (["-q"] if tool == "replay" else [])
            r = run_tool_rss(args)
            print(f"{name} ({label}), {tool}: {summary(r, 'skipped')}", flush=True)


def scenario_bad_config(tmp: Path) -> None:
    real = record_real_log(tmp / "real")
    for name, path in bad_config_copies(real, tmp).items():
        r = run_tool_rss(["replay", str(path), "-q"])
        print(f"bad /config ({name}), replay: {summary(r, 'unusable')} | "
              f"{next((line.strip() for line in r['out'].splitlines() if 'replay of' in line), '')}", flush=True)


def scenario_nested(tmp: Path) -> None:
    path = nested_json_log(tmp / "nested.mcap")
    r = run_tool_rss(["inspect", str(path)])
    print(f"nested JSON 100000 deep in /status and /log, inspect: {summary(r, 'unreadable')} | "
          f"readable warning {'reported' if 'readable warning' in r['out'] else 'NOT reported'}", flush=True)


def scenario_not_files(tmp: Path) -> None:
    fifo = tmp / "log.fifo"
    os.mkfifo(fifo)
    folder = tmp / "a-folder.mcap"
    folder.mkdir()
    for label, path in (("FIFO", fifo), ("folder", folder), ("/dev/zero", Path("/dev/zero"))):
        for tool in ("inspect", "replay", "recover"):
            args = [tool, str(path)] + (["-o", str(tmp / "out2.mcap")] if tool == "recover" else [])
            r = run_tool_rss(args, timeout=15.0)
            print(f"{label} as the log, {tool}: {summary(r)}", flush=True)


def scenario_forged_puts(tmp: Path) -> None:
    """A gateway (emulator, default Zenoh settings) and a foreign client session putting forged
    elements on its key: what a raw subscriber and SkinmapClient receive, with the gateway's
    foreign-write guard on (the default) and off."""
    import zenoh

    from skinmap.wire import messages
    from skinmap.client import SkinmapClient
    from skinmap.daemon.config import parse_config
    from skinmap.daemon.service import Gateway, open_zenoh, zenoh_publishers
    from skinmap.daemon.zenoh_io import make_session_config
    from skinmap.emulator.device import ScannerSpec
    from skinmap.emulator.emulator import Emulator
    from skinmap.emulator.physics import make_shape
    from skinmap.emulator.transport import PtyTransport

    sys.path.insert(0, str(REPO / "tests"))
    from conftest import free_port

    k = 16  # the default element grid: 1 x 16 at 3 mm
    forged = messages.encode_elements(7, 0, time.time_ns(), np.full((k, 3), np.nan), np.tile([0.0, 0.0, 1.0], (k, 1)),
                                      np.full(k, 1e-4), np.full(k, messages.ElementFlag.VALID, np.uint8))
    for guard in (True, False):
        folder = tmp / f"forge-{guard}"
        folder.mkdir()
        emu = Emulator(ScannerSpec(n=4, m=5, scan_rate_hz=30.0, seed=5), make_shape("cylinder", radius=40.0),
                       PtyTransport(link=folder / "tty"))
        emu.start()
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        cfg = parse_config({"device": {"port": str(folder / "tty"), "name": "demo", "scan_rate_hz": 30},
                            "elements": {"cols": k}, "output": {"rate_hz": 15},
                            "zenoh": {"listen": [endpoint], "deny_remote_writes": guard},
                            "log": {"enabled": False}, "state": {"directory": str(folder / "state")}},
                           source="<hostile>")
        try:
            with open_zenoh(cfg) as session:
                gw = Gateway(cfg, publishers=zenoh_publishers(cfg, session))
                runner = threading.Thread(target=gw.run, daemon=True)
                runner.start()
                raw = {"forged": 0, "real": 0}
                with zenoh.open(make_session_config([], [endpoint], mode="client")) as watcher, \
                        zenoh.open(make_session_config([], [endpoint], mode="client")) as forger, \
                        SkinmapClient([endpoint], device="demo", mode="client") as client:
                    watcher.declare_subscriber(
                        "skinmap/demo/elements",
                        lambda s: raw.__setitem__("forged" if s.payload.to_bytes() == forged else "real",
                                                  raw["forged" if s.payload.to_bytes() == forged else "real"] + 1))
                    client.subscribe("elements")
                    time.sleep(1.0)
                    got_ok = 0
                    stop = threading.Event()

                    def read() -> None:
                        nonlocal got_ok
                        while not stop.is_set():
                            try:
                                client.elements(timeout=0.2)
                                got_ok += 1
                            except TimeoutError:
                                pass

                    reader = threading.Thread(target=read)
                    reader.start()
                    n = 470
                    for _ in range(n):
                        forger.put("skinmap/demo/elements", forged)
                        time.sleep(0.004)
                    time.sleep(1.0)
                    stop.set()
                    reader.join()
                    rejected = client.rejected("elements")
                    reasons = client.rejections("elements")[:1]
                gw.stop()
                runner.join(timeout=20)
        finally:
            emu.stop()
        state = "on (default)" if guard else "off (deny_remote_writes = false)"
        print(f"forged puts, {n} NaN elements flagged VALID from a foreign client session, guard {state}: "
              f"a raw subscriber received {raw['forged']} forged and {raw['real']} real; SkinmapClient "
              f"returned {got_ok}, rejected {rejected}" + (f" ({reasons[0]})" if reasons else ""), flush=True)


SCENARIOS = {"bomb": scenario_bombs, "config": scenario_bad_config, "nested": scenario_nested,
             "fifo": scenario_not_files, "forged": scenario_forged_puts}


def main(argv: list[str]) -> int:
    chosen = [name for name in SCENARIOS if not argv or any(word in name for word in argv)]
    with tempfile.TemporaryDirectory(prefix="skinmap-hostile-") as tmp:
        for name in chosen:
            folder = Path(tmp) / name
            folder.mkdir()
            SCENARIOS[name](folder)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
