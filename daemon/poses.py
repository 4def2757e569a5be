"""Probe poses for tactile mapping: where they come from and which contact event each belongs to.

Sources, in the order ``skinmap map`` uses them: a CSV (``--poses``), the pose the gateway's
``/contact`` messages carry (the one in force when each contact began), the log's ``/pose``
topic (what the gateway received on ``skinmap.wire.keys.pose_key``), the ``[tactile] poses``
list of the config the log was recorded with.  Pure functions, except :func:`subscribe_poses` (the
gateway's Zenoh edge) and :func:`poses_in_log` (reads an MCAP file).

A pose from the topic belongs to the first contact event that begins after it was received
(the probe is placed, then pressed); an event with no pose received before it is an error,
and so is a pose that names nothing (a second pose before the same event replaces the first:
the probe was moved again before pressing).
"""
from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from skinmap.daemon.fanout import Event, PoseRecord, Record
from skinmap.daemon.tactile import ProbePose
from skinmap.wire import messages
from skinmap.wire.keys import pose_key

__all__ = ["TimedPose", "LoggedPoses", "pose_from_message", "poses_from_config", "poses_in_log", "assign_poses",
           "contact_poses", "subscribe_poses"]

log = logging.getLogger("skinmap.tactile")


@dataclass(frozen=True)
class TimedPose:
    t_ns: int  # host time it was received (the log time of `/pose`)
    pose: ProbePose


def pose_from_message(doc: dict[str, Any]) -> ProbePose:
    """A ProbePose from a decoded `pose` message (skinmap.wire.messages.decode_pose)."""
    return ProbePose(*(float(doc[name]) for name in messages.POSE_FIELDS))


def poses_from_config(rows: tuple[tuple[float, float, float, float], ...] | list) -> list[ProbePose]:
    """``[tactile] poses`` rows (validated by the config) as ProbePoses."""
    return [ProbePose(*map(float, row)) for row in rows]


@dataclass
class LoggedPoses:
    """What a log holds about poses: the `/pose` messages (with the ones refused, named), the
    poses the `/contact` messages carry (each contact frame's time and the pose in force when
    its contact began) and the `[tactile] poses` (and probe length) of its first config."""

    topic: list[TimedPose] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    config: list[ProbePose] = field(default_factory=list)
    contact: list[TimedPose] = field(default_factory=list)
    probe_length_mm: float | None = None  # the config's [tactile] probe_length_mm


def poses_in_log(path: str | os.PathLike[str]) -> LoggedPoses:
    """The poses an MCAP log carries (a malformed `/pose` message is named in ``refused``)."""
    import tomllib

    from skinmap.daemon.config import ConfigError, parse_config
    from skinmap.daemon.mcapread import iter_messages_file_order

    out = LoggedPoses()
    config_seen = False
    for m in iter_messages_file_order(os.fspath(path)):
        if m.topic == "/pose":
            try:
                out.topic.append(TimedPose(int(m.log_time_ns), pose_from_message(messages.decode_pose(m.data))))
            except (messages.MessageError, ValueError, TypeError) as exc:
                out.refused.append(f"/pose at {m.log_time_ns} ns: {exc}")
        elif m.topic == "/contact":
            try:
                doc = json.loads(m.data)
            except (ValueError, TypeError) as exc:
                out.refused.append(f"/contact at {m.log_time_ns} ns: not JSON: {exc}")
                continue
            if isinstance(doc, dict) and doc.get("state") == "contact" and "pose" in doc:
                try:
                    out.contact.append(TimedPose(int(doc.get("host_time_ns", m.log_time_ns)),
                                                 pose_from_message(messages.decode_pose(
                                                     json.dumps({"schema": messages.POSE_SCHEMA, **doc["pose"]}).encode()))))
                except (messages.MessageError, ValueError, TypeError, KeyError) as exc:
                    out.refused.append(f"/contact at {m.log_time_ns} ns: its pose: {exc}")
        elif m.topic == "/config" and not config_seen:
            config_seen = True
            try:
                text = json.loads(m.data)["config_text"]
                tactile = parse_config(tomllib.loads(text)).tactile
                out.config = poses_from_config(tactile.poses)
                out.probe_length_mm = tactile.probe_length_mm
            except (KeyError, ValueError, TypeError, ConfigError, tomllib.TOMLDecodeError) as exc:
                out.refused.append(f"/config: its [tactile] poses cannot be read: {exc}")
    return out


def assign_poses(event_starts_ns: list[int], timed: list[TimedPose]) -> list[ProbePose]:
    """The pose of each contact event: the latest pose received before the event began.
    ValueError names the first event without one, and a pose received after the last event
    began (nothing it could belong to: a log cut short, or a clock that jumped)."""
    timed = sorted(timed, key=lambda p: p.t_ns)
    out: list[ProbePose] = []
    for i, t in enumerate(event_starts_ns):
        since = event_starts_ns[i - 1] if i else None
        window = [p for p in timed if p.t_ns <= t and (since is None or p.t_ns > since)]
        if not window:
            raise ValueError(f"contact event {i + 1} (began at {t} ns) has no pose received on /pose "
                             f"{'before it' if since is None else f'since event {i} began'} "
                             f"({len(timed)} pose(s) in the log): the probe's pose must be put before each press")
        out.append(window[-1].pose)
    if timed and event_starts_ns and timed[-1].t_ns > event_starts_ns[-1]:
        late = sum(p.t_ns > event_starts_ns[-1] for p in timed)
        raise ValueError(f"{late} pose(s) on /pose received after the last contact event began "
                         f"({event_starts_ns[-1]} ns): a press without surfaces in the log, or poses out of order")
    return out


def contact_poses(event_starts_ns: list[int], event_ends_ns: list[int], carried: list[TimedPose]) -> list[ProbePose]:
    """The pose of each contact event from the gateway's `/contact` messages: the pose carried
    by the first contact message within the event (from its first frame to its last, host
    times).  ValueError names the first event no such message covers (the gateway was not
    told a pose before that press, or its contact was not seen live)."""
    carried = sorted(carried, key=lambda p: p.t_ns)
    out: list[ProbePose] = []
    for i, (t0, t1) in enumerate(zip(event_starts_ns, event_ends_ns)):
        inside = [p for p in carried if t0 <= p.t_ns <= t1]
        if not inside:
            raise ValueError(f"contact event {i + 1} ({t0}…{t1} ns) has no pose on the gateway's /contact messages "
                             f"({len(carried)} contact message(s) with a pose in the log)")
        out.append(inside[0].pose)
    return out


def subscribe_poses(session: Any, prefix: str, device: str, notify: Callable[[Record], None]) -> Any:
    """The gateway's pose input: subscribe to ``pose_key(prefix, device)``; every valid pose is
    handed on as a :class:`PoseRecord` (logged as `/pose`), a malformed one is refused with a
    warning naming the key and what is wrong (an :class:`Event`, logged too). Returns the
    subscriber (``undeclare()`` ends it)."""
    key = pose_key(prefix, device)

    def on_sample(sample: Any) -> None:
        t_ns = time.time_ns()
        try:
            doc = messages.decode_pose(sample.payload.to_bytes())
        except messages.MessageError as exc:
            text = f"pose on {key} refused: {exc}"
            log.warning("%s", text)
            notify(Event(t_ns, "warning", text))
            return
        notify(PoseRecord(t_ns, {name: float(doc[name]) for name in messages.POSE_FIELDS}))

    return session.declare_subscriber(key, on_sample)
