"""Replay: re-run the live pipeline from a log's raw frames and compare with what was published.

The live daemon logs every received frame (`/raw`, bytes as received, stamped with the host
receive time), the config and calibration it used (`/config`), and the strains of every scan it
processed (`/strains`, carrying the scan's sample index; a lead scan's, reconstructed and not
published, as `/strains/lead`). Replay feeds the raw frames through the same decoder and
`FramePipeline`, processes exactly the scans the live run processed (its lead scans too: the
next scan's warm start), with the calibration in force at the time, and compares the element
messages byte for byte.
Cut (`.mcap.active`) files are read in file order up to the cut.  The graph fit is warm-started
from the scans before (pipeline.graph_restart), so in a file that starts mid-stream the scans
before the first restart chain begun in it is taken over (at most pipeline.GRAPH_SYNC_SCANS) may
differ from the live ones: they are counted as not comparable.

A damaged or hostile record (a /config that is not a config object, undecodable /strains or
/elements, a record over the reader's size limit) is named in the report's `problems`, one line
each, and the rest of the file is replayed: an unusable /config does not replace the one in
force before it, and scans with no usable config before them are counted, not replayed.
"""
from __future__ import annotations

import json
import os
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from skinmap.wire import messages
from skinmap.strains import Calibration
from skinmap.daemon.config import DaemonConfig, parse_config
from skinmap.daemon.mcapread import DEFAULT_MAX_RECORD_BYTES, iter_messages_file_order
from skinmap.daemon.output import encode_result_elements
from skinmap.daemon.pipeline import FramePipeline
from skinmap.protocol import Hello, Scan, StreamDecoder, decode_frame

__all__ = ["ReplayReport", "replay_log", "resistances_from_log"]


@dataclass
class ReplayReport:
    path: str
    raw_frames: int = 0
    scans: int = 0
    processed: int = 0
    leads: int = 0  # of the processed: lead scans (reconstructed, not published live)
    compared: int = 0
    identical_count: int = 0
    # scans that differ before the file's first restart of the graph fit is taken over (their
    # live fit was warm-started from scans before this file): not compared
    unsynced: int = 0
    mismatched: list[int] = field(default_factory=list)
    max_position_diff_m: float = 0.0
    published: int = 0
    published_as: str = ""  # <prefix>/<device> when republished
    seconds: float = 0.0
    end: str = ""
    results: list[messages.ElementsMessage] = field(default_factory=list)
    # one line per unusable record (bad /config, undecodable message, record over the size limit)
    problems: list[str] = field(default_factory=list)
    problem_count: int = 0
    # scans the live run processed for which the file holds no usable /config before them
    unconfigured: int = 0

    @property
    def identical(self) -> bool:
        return self.compared > 0 and not self.mismatched

    def format(self) -> str:
        verdict = "IDENTICAL" if self.identical else ("NOTHING TO COMPARE" if self.compared == 0 else "DIFFERENT")
        lines = [
            f"replay of {self.path}: {verdict}",
            f"  raw frames {self.raw_frames}, scans {self.scans}, processed {self.processed}"
            + (f" ({self.leads} lead scans)" if self.leads else "") + ", "
            f"compared {self.compared}, identical {self.identical_count}, mismatched {len(self.mismatched)}"
            + (f", not comparable {self.unsynced} (before the first graph-fit restart taken over; their live "
               f"fit was warm-started from scans before this file)" if self.unsynced else ""),
            f"  max element position difference {self.max_position_diff_m * 1e3:.3g} mm; "
            f"{self.processed / self.seconds if self.seconds > 0 else 0:.1f} scans/s replayed",
        ]
        if self.published:
            lines.append(f"  republished {self.published} element messages")
        if self.unconfigured:
            lines.append(f"  {self.unconfigured} processed scans not replayed: no usable /config before them")
        if self.mismatched:
            lines.append(f"  first mismatched seqs: {self.mismatched[:10]}")
        lines += [f"  {p}" for p in self.problems[:_PROBLEMS_SHOWN]]
        if self.problem_count > _PROBLEMS_SHOWN:
            lines.append(f"  ... and {self.problem_count - _PROBLEMS_SHOWN} more unusable records")
        if self.end:
            lines.append(f"  log end: {self.end}")
        return "\n".join(lines)


_PROBLEMS_SHOWN = 10
_PROBLEMS_KEPT = 1000


def _calibration_from_doc(doc: dict[str, Any]) -> Calibration:
    shape = tuple(doc["shape"])
    offsets: list[np.ndarray | None] = [None, None]
    if "h_upper_mm" in doc or "h_lower_mm" in doc:
        offsets = [np.asarray(doc[k], dtype=np.float64).reshape(shape[1:]) for k in ("h_upper_mm", "h_lower_mm")]
    return Calibration(np.asarray(doc["gauge_factor"], dtype=np.float64).reshape(shape),
                       np.asarray(doc["r0_ohm"], dtype=np.float64).reshape(shape), doc.get("source", "logged"),
                       offsets[0], offsets[1], doc.get("fit") if isinstance(doc.get("fit"), dict) else None)


def _type_name(value: Any) -> str:
    return {list: "a list", dict: "an object", str: "a string", type(None): "null"}.get(type(value), type(value).__name__)


def _config_doc(data: bytes) -> tuple[str, dict]:
    """(config text, calibration) of a /config message; ValueError naming what is unusable."""
    try:
        doc = json.loads(data)
    except RecursionError:
        raise ValueError("JSON nested too deeply to read") from None
    except ValueError as exc:
        raise ValueError(f"not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"is {_type_name(doc)}, expected an object with config_text and calibration")
    text = doc.get("config_text", doc.get("config", ""))
    calibration = doc.get("calibration", {})
    if not isinstance(text, str):
        raise ValueError(f"config_text is {_type_name(text)}, expected a string")
    if not isinstance(calibration, dict):
        raise ValueError(f"calibration is {_type_name(calibration)}, expected an object")
    try:
        _config_from_text(text)
    except ValueError as exc:  # TOML and config errors are ValueErrors
        raise ValueError(f"config_text is not a usable config: {exc}") from None
    try:
        _calibration_from_doc(calibration)
    except (KeyError, TypeError, ValueError) as exc:
        what = f"lacks {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ValueError(f"calibration is not usable: {what}") from None
    hello_hex = calibration.get("hello_frame_hex")
    if hello_hex is not None:
        try:
            if not isinstance(decode_frame(bytes.fromhex(hello_hex)).msg, Hello):
                raise ValueError("not a HELLO frame")
        except (TypeError, ValueError) as exc:
            raise ValueError(f"calibration.hello_frame_hex is not a HELLO frame: {exc}") from None
    return text, calibration


def _problem(report: ReplayReport, line: str) -> None:
    report.problem_count += 1
    if len(report.problems) < _PROBLEMS_KEPT:
        report.problems.append(line)


def _first_pass(path: str, report: ReplayReport, max_record_bytes: int
                ) -> tuple[dict[int, bytes], dict[int, tuple[str, dict]], set[int], int]:
    """Logged elements by seq, the config in force for each processed seq, the lead scans' seqs,
    raw frame count.  Unusable records are named in `report.problems`."""
    elements: dict[int, bytes] = {}
    leads: set[int] = set()
    config_for_seq: dict[int, tuple[str, dict]] = {}
    current: tuple[str, dict] | None = None
    raw = 0
    reader = iter_messages_file_order(path, max_record_bytes=max_record_bytes)
    for index, m in enumerate(reader):
        where = f"{m.topic} message #{index} (log time {m.log_time_ns})"
        if m.topic == "/raw":
            raw += 1
        elif m.topic == "/config":
            try:
                current = _config_doc(m.data)
            except ValueError as exc:
                keep = "; the config before it stays in force" if current is not None else ""
                _problem(report, f"unusable {where}: {exc}{keep}")
        elif m.topic in ("/strains", "/strains/lead"):
            try:
                seq = messages.decode_strains(m.data).seq
            except (ValueError, RecursionError) as exc:
                _problem(report, f"unusable {where}: {exc}")
                continue
            if current is None:
                report.unconfigured += 1
            else:
                config_for_seq[seq] = current
                if m.topic == "/strains/lead":
                    leads.add(seq)
                else:
                    leads.discard(seq)
        elif m.topic == "/elements":
            try:
                elements[messages.decode_header(m.data).seq] = bytes(m.data)
            except messages.MessageError as exc:
                _problem(report, f"unusable {where}: {exc}")
    for line in reader.skipped:
        _problem(report, line)
    report.problem_count += reader.skipped_count - len(reader.skipped)
    return elements, config_for_seq, leads, raw


def replay_log(path: str | os.PathLike[str], *, session: Any = None, prefix: str = "skinmap-replay", speed: float = 0.0,
               progress: bool = False, keep_results: bool = False,
               max_record_bytes: int = DEFAULT_MAX_RECORD_BYTES,
               on_result: Any = None, on_publish: Callable[[str], None] | None = None) -> ReplayReport:
    """Re-run the pipeline over a log; optionally republish on `session` at `speed` (0 = max),
    with `info` answered (its `source` names the log). `on_publish("<prefix>/<device>")` is
    called once the device name is known. Records over `max_record_bytes` are skipped and
    named in the report's `problems`. `on_result(result)` is called with every processed scan's
    FrameResult (its surface included)."""
    from skinmap.daemon.gateway import limit_blas_threads

    limit_blas_threads()  # as the live daemon: the summation order, hence the last bit, depends on it
    path = str(path)
    report = ReplayReport(path)
    logged, config_for_seq, leads, n_raw = _first_pass(path, report, max_record_bytes)
    decoder = StreamDecoder()
    pipeline: FramePipeline | None = None
    earlier: FramePipeline | None = None
    hello: Hello | None = None
    active_config: tuple[str, dict] | None = None
    publisher = None
    # The graph fit is warm-started (pipeline.graph_restart): until the first restart chain
    # begun in this file is taken over, a scan of a file that starts mid-stream may differ from
    # the live one.
    synced = False
    scans_seen = False
    t_start = time.perf_counter()
    first_log_ns: int | None = None
    try:
        reader = iter_messages_file_order(path, max_record_bytes=max_record_bytes)
        for m in reader:
            if m.topic == "/config" and hello is None:
                try:
                    hex_hello = _config_doc(m.data)[1].get("hello_frame_hex")
                except ValueError:
                    continue  # named by the first pass
                if hex_hello:
                    first = decode_frame(bytes.fromhex(hex_hello)).msg  # file starts mid-stream
                    hello = first if isinstance(first, Hello) else hello
                continue
            if m.topic != "/raw":
                continue
            report.raw_frames += 1
            if progress and (report.raw_frames % 200 == 0 or report.raw_frames == n_raw):
                _progress(report.raw_frames, n_raw)
            for frame in decoder.feed(m.data):
                if isinstance(frame.msg, Hello):
                    hello = frame.msg
                    if pipeline is not None:
                        earlier = pipeline
                    pipeline = None
                    synced = synced or not scans_seen  # the stream starts in this file
                    continue
                if not isinstance(frame.msg, Scan) or hello is None:
                    continue
                scan = frame.msg
                report.scans += 1
                scans_seen = True
                seq = scan.sample_index & 0xFFFFFFFF
                cfg_entry = config_for_seq.get(seq)
                if cfg_entry is None:
                    continue  # the live run did not process this scan
                if pipeline is None or cfg_entry is not active_config:
                    cfg = _config_from_text(cfg_entry[0])
                    if pipeline is None:
                        from skinmap.daemon.device_setup import pipeline_for_hello

                        pipeline = pipeline_for_hello(hello, cfg)
                        pipeline.continue_from(earlier)  # as the live daemon does after a new HELLO
                    pipeline.set_calibration(_calibration_from_doc(cfg_entry[1]))
                    active_config = cfg_entry
                result = pipeline.process(scan.resistances_ohm(), seq, scan.timestamp_us, m.log_time_ns,
                                          lead=seq in leads)
                synced = synced or pipeline.chain_origin is not None
                report.processed += 1
                if seq in leads:  # the next scan's warm start; nothing was published
                    report.leads += 1
                    continue
                if on_result is not None:
                    on_result(result)
                payload = encode_result_elements(result)
                if keep_results:
                    report.results.append(messages.decode_elements(payload))
                live = logged.get(seq)
                if live is not None and live != payload and _older_layout_alike(live, payload):
                    live = payload  # a log of an earlier layout: the fields it has are the same bytes
                if live is not None and live != payload and not synced and getattr(pipeline.reconstructor, "graph_fit", False):
                    report.unsynced += 1
                elif live is not None:
                    report.compared += 1
                    if live == payload:
                        report.identical_count += 1
                    else:
                        report.mismatched.append(seq)
                        a, b = messages.decode_elements(live), messages.decode_elements(payload)
                        if a.positions.shape == b.positions.shape:
                            report.max_position_diff_m = max(report.max_position_diff_m,
                                                             float(np.nanmax(np.abs(a.positions - b.positions), initial=0.0)))
                if session is not None:
                    if publisher is None:
                        from skinmap.daemon.device_setup import device_info, device_name
                        from skinmap.daemon.zenoh_io import SkinmapPublisher

                        replay_cfg = _config_from_text(cfg_entry[0])
                        device = device_name(hello, replay_cfg)
                        publisher = SkinmapPublisher(session, prefix, device)
                        # `info` answers as the live daemon did; `source` tells clients the
                        # host times are the recorded ones.
                        publisher.set_info(device_info(device, hello, pipeline, replay_cfg,
                                                       source=f"replay of {os.path.basename(path)}"))
                        report.published_as = f"{prefix}/{device}"
                        if on_publish is not None:
                            on_publish(report.published_as)
                    if speed > 0:
                        if first_log_ns is None:
                            first_log_ns, t_wall0 = m.log_time_ns, time.perf_counter()
                        due = t_wall0 + (m.log_time_ns - first_log_ns) / 1e9 / speed
                        delay = due - time.perf_counter()
                        if delay > 0:
                            time.sleep(delay)
                    publisher.publish_elements(payload)
                    report.published += 1
        end = reader.end
        if end is not None and not end.complete:
            report.end = f"cut file: {end.reason} (read {end.valid_bytes} of {end.file_bytes} bytes)"
    finally:
        if publisher is not None:
            publisher.close()
        if progress:
            print(file=sys.stderr)
    report.seconds = time.perf_counter() - t_start
    return report


_config_cache: dict[str, DaemonConfig] = {}
_CONFIG_CACHE_SIZE = 64


def _config_from_text(text: str) -> DaemonConfig:
    cfg = _config_cache.get(text)
    if cfg is None:
        cfg = parse_config(tomllib.loads(text) if text else {}, source="<log>", text=text)
        if len(_config_cache) >= _CONFIG_CACHE_SIZE:
            _config_cache.clear()  # a file of many distinct /config texts must not grow it for ever
        _config_cache[text] = cfg
    return cfg


def _progress(done: int, total: int) -> None:
    total = max(total, 1)
    width = 40
    filled = int(width * done / total)
    sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {100 * done / total:5.1f}% {done}/{total} frames")
    sys.stderr.flush()


def resistances_from_log(path: str | Path, *, start_s: float = 0.0, count: int = 50) -> tuple[str, list[np.ndarray]]:
    """Resistance scans from a log's raw frames, starting `start_s` after its first frame."""
    decoder = StreamDecoder()
    serial = "unknown"
    scans: list[np.ndarray] = []
    t0: int | None = None
    for m in iter_messages_file_order(str(path)):
        if m.topic != "/raw":
            continue
        t0 = m.log_time_ns if t0 is None else t0
        for frame in decoder.feed(m.data):
            if isinstance(frame.msg, Hello):
                serial = frame.msg.serial_number
            elif isinstance(frame.msg, Scan) and (m.log_time_ns - t0) / 1e9 >= start_s:
                scans.append(frame.msg.resistances_ohm())
                if len(scans) >= count:
                    return serial, scans
    return serial, scans


def _older_layout_alike(live: bytes, payload: bytes) -> bool:
    """Whether ``live``, an elements message of an earlier layout (without the scatter array),
    holds the same bytes as ``payload`` in every field it has."""
    try:
        if messages.decode_header(live).version != 1:
            return False  # a log of this layout is compared byte for byte
        a, b = messages.decode_elements(live), messages.decode_elements(payload)
    except messages.MessageError:
        return False
    return (a.seq, a.device_time_us, a.host_time_ns) == (b.seq, b.device_time_us, b.host_time_ns) and all(
        x.tobytes() == y.tobytes() for x, y in ((a.positions, b.positions), (a.normals, b.normals),
                                                (a.uncertainty, b.uncertainty), (a.flags, b.flags)))
