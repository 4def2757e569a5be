"""What skinmap's MCAP logs hold: the topics (`TOPICS`, one `TopicSpec` each: schema and
message encoding) and the payload codecs -- JSON bodies, `/log` entries, and a wire message's
Foxglove views (`wire_views`). No I/O: the writer is `skinmap.daemon.mcaplog`, the live bridge
serves the same views.
"""
from __future__ import annotations

import base64
import json
from dataclasses import dataclass, replace
from typing import Any, Mapping

import numpy as np

from skinmap.daemon import foxglove_log as fox
from skinmap.wire import messages

__all__ = ["TopicSpec", "TOPICS", "LOG_LEVELS", "LAYOUT_SCHEMA_ENCODING", "log_message", "topics_table",
           "device_topic", "wire_views", "to_json", "check_seq", "as_payload"]


# --------------------------------------------------------------------------------------------
# Topics. Binary payloads are the wire messages of skinmap.wire.messages, exactly as published;
# Foxglove views are the foxglove-sdk's protobuf messages (skinmap.daemon.foxglove_log).

LOG_LEVELS = {name: i for i, name in enumerate(fox.LOG_LEVEL_NAMES)}

RAW_LAYOUT = (
    "skinmap.cobs-frame: one scanner frame exactly as received on the serial port, "
    "COBS-encoded, including its 0x00 delimiter; see protocol/PROTOCOL.md. "
    "Replay writes these bytes back unchanged."
)


def _wire_layout(kind: str, what: str) -> bytes:
    header = messages.layout_table("header")
    body = messages.layout_table(kind)
    return (f"skinmap.{kind}/1: the {kind} message exactly as published on Zenoh ({what}; "
            "skinmap.wire.messages, little-endian, lengths in metres).\n\nCommon header:\n"
            f"{header}\n\n{kind}:\n{body}\n").encode()


LAYOUT_SCHEMA_ENCODING = "skinmap.layout-text"


@dataclass(frozen=True)
class TopicSpec:
    """How one topic is stored: schema and message encoding, and whether it carries a seq."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    has_sequence: bool = False

    def channel_metadata(self) -> dict[str, str]:
        return {"sequence": "frame"} if self.has_sequence else {}


def _json_schema(schema: Mapping[str, Any]) -> bytes:
    return json.dumps(schema, separators=(",", ":")).encode()


def _foxglove(topic: str, key: str, has_sequence: bool = False) -> TopicSpec:
    schema = fox.SCHEMAS[key]
    return TopicSpec(topic, schema.name, schema.encoding, bytes(schema.data), "protobuf",
                     has_sequence)


TOPICS: dict[str, TopicSpec] = {
    spec.topic: spec
    for spec in (
        TopicSpec("/raw", "skinmap.CobsFrame", LAYOUT_SCHEMA_ENCODING, RAW_LAYOUT.encode(),
                  "skinmap.cobs-frame"),
        TopicSpec("/strains", "skinmap.Strains", LAYOUT_SCHEMA_ENCODING,
                  _wire_layout("strains", "every processed scan"), f"skinmap.strains/{messages.LAYOUT_VERSION}",
                  has_sequence=True),
        TopicSpec("/strains/lead", "skinmap.Strains", LAYOUT_SCHEMA_ENCODING,
                  _wire_layout("strains", "a lead scan: reconstructed just before a scan due, not published"),
                  f"skinmap.strains/{messages.LAYOUT_VERSION}", has_sequence=True),
        TopicSpec("/strains/plot", "skinmap.StrainsPlot", "jsonschema",
                  _json_schema(fox.STRAINS_PLOT_SCHEMA), "json", has_sequence=True),
        TopicSpec("/surface", "foxglove.PointCloud", "protobuf",
                  bytes(fox.SCHEMAS["cloud"].data), "protobuf", has_sequence=True),
        TopicSpec("/surface/nodes", "skinmap.Surface", LAYOUT_SCHEMA_ENCODING,
                  _wire_layout("surface", "nodes, normals, σ and the dense cloud"),
                  f"skinmap.surface/{messages.LAYOUT_VERSION}", has_sequence=True),
        TopicSpec("/elements", "skinmap.Elements", LAYOUT_SCHEMA_ENCODING,
                  _wire_layout("elements", "unchanged"), f"skinmap.elements/{messages.LAYOUT_VERSION}"),
        _foxglove("/elements/poses", "poses"),
        TopicSpec("/elements/plot", "skinmap.ElementsPlot", "jsonschema",
                  _json_schema(fox.ELEMENTS_PLOT_SCHEMA), "json"),
        _foxglove("/scene", "scene"),
        _foxglove("/tf", "tf"),
        TopicSpec("/contact", "skinmap.Contact", "jsonschema",
                  _json_schema({"title": "skinmap.Contact", "type": "object"}), "json"),
        TopicSpec("/pose", "skinmap.Pose", "jsonschema", _json_schema(messages.pose_json_schema()), "json"),
        TopicSpec("/status", "skinmap.Status", "jsonschema", _json_schema(fox.status_schema()),
                  "json"),
        _foxglove("/log", "log"),
        TopicSpec("/config", "skinmap.Config", "jsonschema",
                  _json_schema({
                      "title": "skinmap.Config",
                      "type": "object",
                      "properties": {
                          "config_text": {"type": "string"},
                          "calibration": {"type": "object"},
                          "logged_at_ns": {"type": "integer"},
                      },
                  }), "json"),
    )
}
TOPICS["/surface"] = _foxglove("/surface", "cloud", has_sequence=True)


def topics_table() -> str:
    """The markdown table of logged topics (docs/logging.md shows it; a test keeps them equal)."""
    lines = ["| topic | schema name (encoding) | message encoding |", "|---|---|---|"]
    for spec in TOPICS.values():
        lines.append(f"| `{spec.topic}` | `{spec.schema_name}` (`{spec.schema_encoding}`) | "
                     f"`{spec.message_encoding}` |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Pure payload helpers.


def check_seq(seq: int) -> int:
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or not 0 <= seq < 2**64:
        raise ValueError(f"seq must be an integer in [0, 2**64), got {seq!r}")
    return int(seq)


def _level_number(level: int | str) -> int:
    if isinstance(level, str):
        key = level.strip().upper()
        key = {"WARN": "WARNING", "CRITICAL": "FATAL"}.get(key, key)
        if key not in LOG_LEVELS:
            raise ValueError(f"unknown log level {level!r}; use one of {sorted(LOG_LEVELS)}")
        return LOG_LEVELS[key]
    if isinstance(level, (int, np.integer)) and not isinstance(level, bool):
        if 0 <= level <= 5:
            return int(level)
        # Python logging numbers (10 DEBUG .. 50 CRITICAL) map onto Foxglove's 1..5.
        if level in (10, 20, 30, 40, 50):
            return int(level) // 10
    raise ValueError(f"log level must be a name, 0..5 or a logging level, got {level!r}")


def log_message(t_ns: int, level: int | str, message: str, name: str = "skinmapd") -> bytes:
    """A foxglove.Log message (protobuf)."""
    return fox.log_entry(t_ns, _level_number(level), message, name)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (bytes, bytearray)):
        return base64.b64encode(bytes(value)).decode("ascii")
    raise TypeError(f"value of type {type(value).__name__} cannot be logged as JSON")


def to_json(value: Any, what: str) -> bytes:
    try:
        return json.dumps(value, default=_json_default, separators=(",", ":"),
                          allow_nan=True).encode()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} is not JSON-serialisable: {exc}") from None


def device_topic(topic: str, device: str | None = None) -> TopicSpec:
    """The spec of `topic`, under `/<device>` when several devices share a file or a server."""
    spec = TOPICS[topic]
    return spec if device is None else replace(spec, topic=f"/{device}{spec.topic}")


def wire_views(kind: str, payload: bytes, t_ns: int, device: str | None = None,
               latency_ms: float | None = None) -> list[tuple[TopicSpec, bytes, int | None, int]]:
    """A wire message and its Foxglove views as (topic spec, data, seq or None, time) —
    what the log stores and the live bridge serves. `kind` is elements, surface, strains or lead
    (a lead scan's strains, docs/logging.md);
    raises MessageError (bad layout) or ValueError (non-finite surface)."""
    frame = device or fox.FRAME_ID
    t = device_topic
    if kind == "lead":  # (not published: no plot)
        return [(t("/strains/lead", device), payload, messages.decode_strains(payload).seq, t_ns)]
    if kind == "strains":
        st = messages.decode_strains(payload)
        return [(t("/strains", device), payload, st.seq, t_ns),
                (t("/strains/plot", device), fox.strains_plot(st), st.seq, t_ns)]
    if kind == "surface":
        sf = messages.decode_surface(payload)
        if not (np.isfinite(sf.nodes).all() and np.isfinite(sf.cloud).all()):
            raise ValueError("surface nodes or cloud contain NaN or infinite values")
        points = sf.cloud if len(sf.cloud) else sf.nodes.reshape(-1, 3)
        cloud = fox.point_cloud(points, t_ns, frame)
        scene = fox.scene_sheet(sf, t_ns, frame)
        return [(t("/surface/nodes", device), payload, sf.seq, t_ns),
                (t("/surface", device), cloud, sf.seq, t_ns),
                (t("/tf", device), fox.frame_transform(t_ns, frame), None, t_ns),
                (t("/scene", device), scene, None, t_ns)]
    if kind == "elements":
        el = messages.decode_elements(payload)
        views = (fox.element_poses(el, t_ns, frame), fox.scene_elements(el, t_ns, frame),
                 fox.elements_plot(el, latency_ms))
        return [(t("/elements", device), payload, None, t_ns),
                (t("/elements/poses", device), views[0], None, t_ns),
                (t("/scene", device), views[1], None, t_ns),
                (t("/elements/plot", device), views[2], None, t_ns)]
    raise ValueError(f"unknown wire kind {kind!r}; expected elements, surface or strains")


def as_payload(kind: str, payload: Any) -> bytes:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise TypeError(f"{kind} payload must be bytes, got {type(payload).__name__}")
    return bytes(payload)
