"""The gateway's output: each processed scan encoded once as wire messages (skinmap.wire),
published at the configured rates and handed to the Notifier for the log; contacts with
[tactile] on. Runs on the processing thread.
"""
from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from skinmap.daemon.config import DaemonConfig
from skinmap.daemon.fanout import ContactRecord, Notifier, WireRecord
from skinmap.daemon.pacing import HostDecimator
from skinmap.daemon.pipeline import FramePipeline, FrameResult
from skinmap.daemon.publisher import NullPublisher, Publisher, PublisherFactory
from skinmap.wire import messages

if TYPE_CHECKING:
    from skinmap.daemon.tactile import ContactTracker

__all__ = ["OutputStats", "ResultOutput", "MAX_CLOUD_POINTS"]

log = logging.getLogger("skinmapd")

MAX_CLOUD_POINTS = 40_000  # the published dense cloud is thinned beyond this (32×32 at 20/pitch is 410k)


def _metres(mm: np.ndarray | None) -> np.ndarray | None:
    return None if mm is None else np.asarray(mm) / 1000.0


def encode_result_elements(r: FrameResult) -> bytes:
    """The elements message of one result (metres on the wire)."""
    return messages.encode_elements(
        r.seq & 0xFFFFFFFF, r.device_time_us, r.host_time_ns, r.element_positions_mm / 1000.0, r.element_normals,
        r.element_sigma_mm / 1000.0, r.element_flags, _metres(r.element_scatter_mm))


def encode_result_surface(r: FrameResult, cloud_mm: Any) -> bytes:
    """The surface message of one result with the dense cloud ``cloud_mm`` (P, 3) mm."""
    return messages.encode_surface(
        r.seq & 0xFFFFFFFF, r.device_time_us, r.host_time_ns, r.nodes_mm / 1000.0, r.normals,
        r.node_sigma_mm / 1000.0, np.asarray(cloud_mm).reshape(-1, 3) / 1000.0, scatter=_metres(r.node_scatter_mm))


def encode_result_strains(r: FrameResult) -> bytes:
    """The strains message of one result: the strains it was reconstructed from, and which
    gauges were usable."""
    gauge_flags = (r.gauge_valid[0].astype(np.uint8) * messages.GaugeFlag.UPPER_VALID) | (
        r.gauge_valid[1].astype(np.uint8) * messages.GaugeFlag.LOWER_VALID)
    return messages.encode_strains(r.seq & 0xFFFFFFFF, r.device_time_us, r.host_time_ns, np.nan_to_num(r.eps_upper),
                                   np.nan_to_num(r.eps_lower), gauge_flags)


@dataclass
class OutputStats:
    published: int = 0
    publish_errors: int = 0
    latencies_ms: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=256))
    publish_times: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=4096))


class ResultOutput:
    """Publishes and logs processed scans for the current device.

    `publishers` opens a device's Publisher by name (None: publish nothing); `use_device`
    switches to another device, closing the previous publisher."""

    def __init__(self, cfg: DaemonConfig, notifier: Notifier, publishers: PublisherFactory | None,
                 *, logging_on: bool) -> None:
        self.cfg = cfg
        self.notifier = notifier
        self.stats = OutputStats()
        self._factory: PublisherFactory = publishers or (lambda _device: NullPublisher())
        self.publisher: Publisher | None = None
        self.device = cfg.device.name or ""
        self._logging_on = logging_on
        self._surface = HostDecimator(cfg.output.surface_rate_hz)
        self._strains = HostDecimator(cfg.output.strains_rate_hz)
        self._log_surface = HostDecimator(cfg.log.surface_rate_hz)
        self._contact: ContactTracker | None = None  # rebuilt after every (re)connect
        # the latest probe pose received ([tactile]); set from the pose input's thread, read here
        # (a reference swap), kept across reconnects: the probe did not move because the link did
        self._pose: Mapping[str, float] | None = None

    def use_device(self, name: str, info: Callable[[], dict[str, Any]]) -> None:
        """Publish as `name` from now on; `info()` is its description."""
        if self.publisher is None or name != self.device:
            if self.publisher is not None:
                self.publisher.close()
            self.publisher = self._factory(name)
        self.device = name
        self._contact = None  # a new baseline after every (re)connect
        self.publisher.set_info(info())

    def note_pose(self, pose: Mapping[str, float]) -> None:
        """A probe pose was received: contacts that begin from now on are placed by it."""
        self._pose = dict(pose)

    def set_info(self, info: dict[str, Any]) -> None:
        if self.publisher is not None:
            self.publisher.set_info(info)

    def publish(self, r: FrameResult, t_mono: int, pipeline: FramePipeline) -> bool:
        """Publish one result and hand it to the log; False if publishing failed."""
        seq = r.seq & 0xFFFFFFFF
        elements = encode_result_elements(r)
        ok = True
        pub = self.publisher
        if pub is not None:
            # the element coordinates first: what a client waits for leaves before anything else
            try:
                pub.publish_elements(elements)
            except Exception as exc:  # noqa: BLE001 - a failed put must not stop processing
                self.stats.publish_errors += 1
                ok = False
                log.warning("publish failed: %s", exc)
        want_surface = self._surface.due(t_mono)
        want_strains = self._strains.due(t_mono)
        # The same strains message is published (at the strains rate) and logged (every scan).
        strains = encode_result_strains(r)
        if pub is not None and ok:
            try:
                if want_surface:
                    points = self._points(r, pipeline)
                    pub.publish_surface(encode_result_surface(r, points))
                if want_strains:
                    pub.publish_strains(strains)
                self.stats.published += 1
            except Exception as exc:  # noqa: BLE001 - a failed put must not stop processing
                self.stats.publish_errors += 1
                ok = False
                log.warning("publish failed: %s", exc)
        latency_ms = (time.time_ns() - r.host_time_ns) / 1e6
        self.stats.latencies_ms.append(latency_ms)
        self.stats.publish_times.append(time.monotonic())
        # Everything processed is logged (strains of every processed scan, so replay can pick
        # the same scans); surfaces at the log's surface rate.
        self.notifier.notify(WireRecord("strains", r.host_time_ns, strains))
        self.notifier.notify(WireRecord("elements", r.host_time_ns, elements, latency_ms))
        self._track_contact(r, pipeline)
        if self._logging_on and self._log_surface.due(t_mono):
            cloud = r.surface.points(per_pitch=self.cfg.log.points_per_pitch) if r.surface is not None else r.nodes_mm
            self.notifier.notify(WireRecord("surface", r.host_time_ns, encode_result_surface(r, cloud)))
        return ok

    def _track_contact(self, r: FrameResult, pipeline: FramePipeline) -> None:
        """With [tactile] on: the frame against the baseline, published and logged as `contact`."""
        tc = self.cfg.tactile
        if not tc.enabled or r.surface is None:
            return
        from skinmap.daemon.tactile import ContactTracker, SampleGrid

        g = pipeline.geometry
        grid = SampleGrid.for_array(g.n, g.m, g.pitch_mm, tc.step_mm)
        if self._contact is None or self._contact.grid != grid:
            self._contact = ContactTracker(grid, tc.baseline_frames, tc.k, tc.min_depth_mm, g.pitch_mm,
                                           tc.probe_length_mm, g.gauge_length_mm)
        pos, nrm = r.surface.locate(self._contact.grid.uv)
        doc = {"seq": int(r.seq), "host_time_ns": int(r.host_time_ns),
               **self._contact.update(pos, nrm, self._pose, r.cell_bending())}
        if self.publisher is not None:
            try:
                self.publisher.publish_contact(doc)
            except Exception as exc:  # noqa: BLE001 - a failed put must not stop processing
                self.stats.publish_errors += 1
                log.warning("publishing contact failed: %s", exc)
        self.notifier.notify(ContactRecord(r.host_time_ns, doc))

    def _points(self, r: FrameResult, pipeline: FramePipeline) -> np.ndarray:
        """The published dense cloud (mm), thinned to MAX_CLOUD_POINTS on large sheets."""
        if r.surface is None:
            return r.nodes_mm.reshape(-1, 3)
        g = pipeline.geometry
        per_pitch = max(1, min(self.cfg.output.points_per_pitch, int(MAX_CLOUD_POINTS ** 0.5 / max(g.n, g.m))))
        return np.asarray(r.surface.points(per_pitch=per_pitch)).reshape(-1, 3)

    def close(self) -> None:
        if self.publisher is not None:
            try:
                self.publisher.close()
            except Exception:  # noqa: BLE001 - closing at shutdown: nothing more to do
                pass
