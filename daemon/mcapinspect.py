"""Inspection of skinmap MCAP logs: per-topic counts and rates, sequence gaps, time gaps,
warnings and errors logged, and how the file ended (`inspect`, used by `skinmap inspect`).
Reading is `skinmap.daemon.mcapread`'s (file order, cut files included).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from mcap.records import Attachment, Message, Metadata

from skinmap.daemon.foxglove_log import decode_protobuf
from skinmap.daemon.mcapread import (DEFAULT_MAX_RECORD_BYTES, FileOrderReader, LoggedMessage, ReadEnd,
                                     logged_message, skipped_lines)
from skinmap.daemon.mcapschema import LOG_LEVELS

__all__ = ["SequenceGap", "LogIssue", "TopicStats", "InspectReport", "inspect", "expected_rates"]

@dataclass(frozen=True)
class SequenceGap:
    topic: str
    after_seq: int
    next_seq: int
    missing: int  # messages missing at the expected step; 0 repeat, negative jump back
    t_ns: int
    expected_step: int = 1  # seq step between two messages of this topic when none is lost


@dataclass(frozen=True)
class LogIssue:
    t_ns: int
    source: str  # "/log" or "/status"
    level: str  # "WARNING", "ERROR", "FATAL"
    text: str


@dataclass
class TopicStats:
    topic: str
    schema_name: str
    message_encoding: str
    count: int = 0
    bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0
    time_gaps: list[tuple[int, int]] = field(default_factory=list)  # (from, to) log times
    out_of_order: int = 0
    expected_hz: float | None = None  # the topic's rate by the logged config (None: unknown)
    gap_threshold_s: float = 0.0  # the silence that counts as a gap on this topic

    @property
    def rate_hz(self) -> float:
        span = self.last_ns - self.first_ns
        return (self.count - 1) / (span * 1e-9) if self.count > 1 and span > 0 else 0.0


@dataclass
class InspectReport:
    path: str
    end: ReadEnd
    library: str
    topics: dict[str, TopicStats]
    sequence_gaps: list[SequenceGap]
    issues: list[LogIssue]
    metadata: dict[str, dict[str, str]]
    attachments: list[str]
    gap_threshold_s: float
    skipped: list[str] = field(default_factory=list)  # records refused as too large
    skipped_count: int = 0
    rates_source: str = ""  # where the expected rates come from

    @property
    def first_ns(self) -> int | None:
        return min((s.first_ns for s in self.topics.values()), default=None)

    @property
    def last_ns(self) -> int | None:
        return max((s.last_ns for s in self.topics.values()), default=None)

    def format(self, max_lines: int = 20) -> str:
        """The report: state, then what is wrong (errors and warnings from /log and /status,
        messages missing beyond the configured decimation, silences beyond each topic's own
        rate), then the topic table. At most `max_lines` lines of each kind are listed."""
        e = self.end
        state = "finished" if e.complete else f"NOT finished: {e.reason}"
        out = [f"{self.path}", f"  state: {state} ({e.valid_bytes} of {e.file_bytes} bytes "
               f"readable)", f"  writer: {self.library or '?'}"]
        if self.first_ns is not None and self.last_ns is not None:
            out.append(f"  span: {_utc(self.first_ns)} .. {_utc(self.last_ns)} "
                       f"({(self.last_ns - self.first_ns) * 1e-9:.3f} s)")
        t0 = self.first_ns or 0

        def capped(lines: list[str], what: str) -> list[str]:
            if len(lines) <= max_lines:
                return lines
            return lines[:max_lines] + [f"  ... and {len(lines) - max_lines} more {what}"]

        ranked = sorted(self.issues, key=lambda i: (-_LEVEL_RANK.get(i.level, 0), i.t_ns))
        out += capped([f"  {i.level} in {i.source} at t+{(i.t_ns - t0) * 1e-9:.3f} s: {i.text}"
                       for i in ranked], "warnings/errors")
        seq_lines = []
        for g in self.sequence_gaps:
            what = (f"{g.missing} missing" if g.missing > 0 else
                    "repeated" if g.missing == 0 else "jumped back: scanner restarted")
            step = f", expected step {g.expected_step}" if g.expected_step != 1 else ""
            seq_lines.append(f"  seq gap on {g.topic}: {g.after_seq} -> {g.next_seq} ({what}"
                             f"{step}) at t+{(g.t_ns - t0) * 1e-9:.3f} s")
        out += capped(seq_lines, "seq gaps")
        gap_lines = []
        for st in sorted(self.topics.values(), key=lambda st: st.topic):
            for a, b in st.time_gaps:
                gap_lines.append(f"  time gap on {st.topic}: {(b - a) * 1e-9:.3f} s after "
                                 f"t+{(a - t0) * 1e-9:.3f} s (threshold "
                                 f"{st.gap_threshold_s:.3g} s)")
            if st.out_of_order:
                gap_lines.append(f"  {st.topic}: {st.out_of_order} messages earlier than the "
                                 "one before")
        out += capped(gap_lines, "time gaps")
        if self.skipped_count:
            out.append(f"  {self.skipped_count} record(s) skipped unread:")
            out += skipped_lines(self.skipped, self.skipped_count, "    ")
        if not (self.sequence_gaps or self.issues or self.skipped_count or
                any(st.time_gaps or st.out_of_order for st in self.topics.values())):
            out.append("  no gaps, warnings or errors found")
        if self.rates_source:
            out.append(f"  expected rates: {self.rates_source}")
        if self.metadata:
            out.append("  metadata: " + ", ".join(sorted(self.metadata)))
        if self.attachments:
            out.append("  attachments: " + ", ".join(self.attachments))
        out.append(f"  {'topic':<18} {'count':>7} {'rate Hz':>9} {'expect':>7} {'bytes':>11}  "
                   "schema")
        for st in sorted(self.topics.values(), key=lambda st: st.topic):
            expect = "" if st.expected_hz is None else f"{st.expected_hz:g}"
            out.append(f"  {st.topic:<18} {st.count:>7} {st.rate_hz:>9.2f} {expect:>7} "
                       f"{st.bytes:>11}  {st.schema_name} ({st.message_encoding})")
        return "\n".join(out)


_LEVEL_RANK = {"FATAL": 5, "ERROR": 4, "WARNING": 3}


def _utc(t_ns: int) -> str:
    import datetime as dt

    return dt.datetime.fromtimestamp(t_ns / 1e9, dt.timezone.utc).isoformat(
        timespec="milliseconds").replace("+00:00", "Z")


_LEVEL_NAMES = {v: k for k, v in LOG_LEVELS.items()}
_BAD_STATES = {"error", "fault", "failed", "warning", "degraded", "fatal"}


def _status_issues(t_ns: int, status: Any) -> list[LogIssue]:
    """Warnings/errors a /status object reports: non-empty error/warning fields, a false
    health flag, or a state/level naming an error."""
    if not isinstance(status, dict):
        return []
    found = []
    for key, level in (("error", "ERROR"), ("errors", "ERROR"), ("last_error", "ERROR"),
                       ("warning", "WARNING"), ("warnings", "WARNING")):
        if status.get(key):
            found.append(LogIssue(t_ns, "/status", level, f"{key}: {status[key]}"))
    for key in ("healthy", "ok"):
        if status.get(key) is False:
            found.append(LogIssue(t_ns, "/status", "WARNING", f"{key} is false"))
    for key in ("state", "level"):
        value = status.get(key)
        if isinstance(value, str) and value.lower() in _BAD_STATES:
            level = "WARNING" if value.lower() in ("warning", "degraded") else "ERROR"
            found.append(LogIssue(t_ns, "/status", level, f"{key}: {value}"))
    return found


def inspect(path: str | os.PathLike[str], *, gap_threshold_s: float = 1.0,
            max_issues: int = 1000,
            max_record_bytes: int = DEFAULT_MAX_RECORD_BYTES) -> InspectReport:
    """Summarise a finished or cut log: per-topic counts, rates, first/last times, time gaps
    longer than `gap_threshold_s`, sequence gaps on topics that carry a frame seq, and
    warnings/errors from /log and /status (at most `max_issues` listed). Records over
    `max_record_bytes` are skipped and listed."""
    if not gap_threshold_s > 0:
        raise ValueError(f"gap_threshold_s must be > 0, got {gap_threshold_s!r}")
    reader = FileOrderReader(path, max_record_bytes=max_record_bytes)
    topics: dict[str, TopicStats] = {}
    times: dict[str, list[int]] = {}
    seqs: dict[str, list[tuple[int, int]]] = {}  # topic -> [(seq, log time)]
    issues: list[LogIssue] = []
    metadata: dict[str, dict[str, str]] = {}
    attachments: list[str] = []
    config_text: str | None = None
    for item in reader.items():
        rec = item.record
        if isinstance(rec, Metadata):
            metadata[rec.name] = rec.metadata
            continue
        if isinstance(rec, Attachment):
            attachments.append(rec.name)
            continue
        if not isinstance(rec, Message):
            continue
        m = logged_message(item)
        stats = topics.get(m.topic)
        if stats is None:
            stats = topics[m.topic] = TopicStats(m.topic, m.schema_name, m.message_encoding,
                                                 first_ns=m.log_time_ns, last_ns=m.log_time_ns)
        elif m.log_time_ns < stats.last_ns:
            stats.out_of_order += 1
        times.setdefault(m.topic, []).append(m.log_time_ns)
        stats.count += 1
        stats.bytes += len(m.data)
        stats.first_ns = min(stats.first_ns, m.log_time_ns)
        stats.last_ns = max(stats.last_ns, m.log_time_ns)
        if item.channel is not None and item.channel.metadata.get("sequence") == "frame":
            seqs.setdefault(m.topic, []).append((rec.sequence, m.log_time_ns))
        if m.topic == "/config" and config_text is None:
            config_text = _config_text(m.data)
        if len(issues) < max_issues:
            issues.extend(_message_issues(m))
    assert reader.end is not None
    rates, source = expected_rates(config_text)
    seq_gaps: list[SequenceGap] = []
    for topic, stats in topics.items():
        hz = rates.get(topic)
        stats.expected_hz = hz
        if topic in _EVENT_TOPICS:
            continue
        t = np.asarray(times[topic], dtype=np.int64)
        dt = np.diff(t)
        if hz:
            period_s = 1.0 / hz
        elif dt.size:
            period_s = float(np.median(dt)) * 1e-9  # unknown topic: its own typical interval
        else:
            period_s = 0.0
        # A silence counts when it is longer than the threshold and than 2.5 periods of the
        # topic's own rate: a 1 Hz topic is not "gapped" every second.
        stats.gap_threshold_s = max(gap_threshold_s, 2.5 * period_s)
        for k in np.flatnonzero(dt > stats.gap_threshold_s * 1e9):
            stats.time_gaps.append((int(t[k]), int(t[k + 1])))
        if topic in seqs:
            seq_gaps += _sequence_gaps(topic, seqs[topic], rates.get(("seq_step", topic)))
    seq_gaps.sort(key=lambda g: (g.t_ns, g.topic))
    return InspectReport(os.fspath(path), reader.end,
                         reader.header.library if reader.header else "", topics, seq_gaps,
                         issues[:max_issues], metadata, attachments, gap_threshold_s,
                         reader.skipped, reader.skipped_count, source)


_EVENT_TOPICS = {"/log", "/config"}


def _config_text(data: bytes) -> str | None:
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError):
        return None
    text = doc.get("config_text") if isinstance(doc, dict) else None
    return text if isinstance(text, str) else None


def expected_rates(config_text: str | None) -> tuple[dict[Any, float], str]:
    """Each topic's rate (Hz) and each seq topic's step under the logged config (the daemon's
    decimation): ({topic: hz, ("seq_step", topic): step}, where that came from). Without a
    usable config the rates are unknown and gaps are judged by each topic's own median."""
    if config_text is None:
        return {}, "unknown (no /config in the file): each topic judged by its own median"
    try:
        import tomllib

        from skinmap.daemon.config import ConfigError, parse_config

        cfg = parse_config(tomllib.loads(config_text), source="<logged config>",
                           text=config_text)
    except (ValueError, ConfigError, RecursionError) as exc:
        return {}, (f"unknown (the logged config does not parse: {exc}); each topic judged "
                    "by its own median")
    scan = float(cfg.device.scan_rate_hz)
    out_hz = min(float(cfg.output.rate_hz) or scan, scan)  # 0 = every scan
    surf_hz = min(float(cfg.log.surface_rate_hz) or out_hz, out_hz)
    status_hz = float(cfg.output.status_rate_hz)
    rates: dict[Any, float] = {"/raw": scan, "/status": status_hz}
    for topic in ("/elements", "/elements/poses", "/elements/plot", "/strains", "/strains/plot",
                  "/scene"):
        rates[topic] = out_hz
    for topic in ("/surface", "/surface/nodes", "/tf"):
        rates[topic] = surf_hz
    if out_hz < scan and cfg.output.lead_scans:  # (their seqs are not checked for gaps: a lead may be skipped)
        rates["/strains/lead"] = min(cfg.output.lead_scans * out_hz, scan - out_hz)
    for topic in ("/strains", "/strains/plot"):
        rates[("seq_step", topic)] = max(1, round(scan / out_hz))
    for topic in ("/surface", "/surface/nodes"):
        rates[("seq_step", topic)] = max(1, round(scan / surf_hz))
    return rates, (f"from the logged config: scans {scan:g} Hz, processed {out_hz:g} Hz (seq "
                   f"step {rates[('seq_step', '/strains')]}), logged surfaces {surf_hz:g} Hz "
                   f"(seq step {rates[('seq_step', '/surface')]}), status {status_hz:g} Hz")


def _sequence_gaps(topic: str, seq_times: list[tuple[int, int]],
                   expected: float | None) -> list[SequenceGap]:
    """Messages missing on a seq topic at the expected step (the config's decimation, or the
    topic's median step when the config is unknown). The decimation goes by host time, so a
    step of 4 or 6 where 5 is expected loses nothing: messages count as missing only when the
    step is nearer two or more expected steps than one."""
    seq = np.array([sq for sq, _ in seq_times], dtype=np.int64)
    steps = np.diff(seq) % 2**32
    if expected is None:
        forward = steps[(steps > 0) & (steps < 2**31)]
        expected = float(np.median(forward)) if forward.size else 1.0
    expected_step = max(1, int(round(expected)))
    gaps = []
    for k, step in enumerate(steps.tolist()):
        if step == 0:
            missing = 0
        elif step >= 2**31:
            missing = step - 2**32 - 1  # backwards: a restarted scanner
        else:
            missing = int(round(step / expected_step)) - 1
            if missing <= 0:
                continue
        gaps.append(SequenceGap(topic, int(seq[k]), int(seq[k + 1]), missing,
                                seq_times[k + 1][1], expected_step))
    return gaps


_MAX_ISSUE_TEXT = 500


def _clip(text: str) -> str:
    return text if len(text) <= _MAX_ISSUE_TEXT else text[:_MAX_ISSUE_TEXT] + "..."


def _message_issues(m: LoggedMessage) -> list[LogIssue]:
    if m.topic == "/log" and m.message_encoding == "protobuf":
        try:
            entry = decode_protobuf(m.schema_name, m.data)
        except Exception:  # noqa: BLE001 - protobuf raises its own DecodeError
            return [LogIssue(m.log_time_ns, m.topic, "ERROR", "message is not a valid "
                             f"{m.schema_name or 'protobuf'} record")]
        if entry.level >= LOG_LEVELS["WARNING"]:
            name = _LEVEL_NAMES.get(entry.level, str(entry.level))
            return [LogIssue(m.log_time_ns, "/log", name, _clip(f"[{entry.name}] {entry.message}"))]
        return []
    if m.topic not in ("/log", "/status") or m.message_encoding != "json":
        return []
    try:
        obj = json.loads(m.data)
        if m.topic == "/status":
            return [LogIssue(i.t_ns, i.source, i.level, _clip(i.text))
                    for i in _status_issues(m.log_time_ns, obj)]
        level = obj.get("level", 0) if isinstance(obj, dict) else 0
        if isinstance(level, int) and level >= LOG_LEVELS["WARNING"]:
            name = _LEVEL_NAMES.get(level, str(level))
            return [LogIssue(m.log_time_ns, "/log", name,
                             _clip(f"[{obj.get('name', '')}] {obj.get('message', '')}"))]
        return []
    except RecursionError:
        # json and str() recurse per nesting level: one such record must not end the report.
        return [LogIssue(m.log_time_ns, m.topic, "ERROR", f"unreadable record "
                         f"({len(m.data)} bytes): JSON nested too deeply to read")]
    except ValueError:
        return [LogIssue(m.log_time_ns, m.topic, "ERROR", "message is not valid JSON")]
