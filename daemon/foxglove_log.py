"""Foxglove views of skinmap data for MCAP logs and the live bridge (pure, no I/O).

Everything here is built with the official foxglove-sdk typed messages (protobuf); the schemas
come from the SDK (``Message.get_schema()``), not copies. skinmap's own plottable topics are
JSON with the JSON schemas defined here (status: generated from ``skinmap.wire.messages``).

- ``scene_sheet``: ``foxglove.SceneUpdate`` with the sheet as a triangle mesh of the cell-centre
  nodes, coloured by their 1-s.d. uncertainty σ, and a legend (text) giving the colour scale;
- ``scene_elements``: ``foxglove.SceneUpdate`` with one arrow per element along its normal,
  coloured by validity (green VALID, amber VALID with a caveat bit, red not VALID);
- ``element_poses``: ``foxglove.PosesInFrame`` (position and normal as the pose's +x axis);
- ``frame_transform``: ``foxglove.FrameTransform`` placing the sensor frame in ``world``;
- ``point_cloud``: ``foxglove.PointCloud`` of float32 x, y, z;
- ``log_entry``: ``foxglove.Log``;
- ``strains_plot`` / ``elements_plot``: JSON objects whose arrays the Plot panel can draw.

All lengths in metres: the inputs are the wire messages (metres).
"""

from __future__ import annotations

import json
from typing import Any, Mapping

import numpy as np
from foxglove import messages as fg

from skinmap.wire import messages as wire

FRAME_ID = "skinmap"
WORLD_FRAME_ID = "world"

# Five-stop viridis: enough for a legend readable by eye.
_VIRIDIS = np.array([[0.267, 0.005, 0.329], [0.229, 0.322, 0.546], [0.128, 0.567, 0.551],
                     [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]])
_VALID_RGB = (0.2, 0.8, 0.2)
_CAVEAT_RGB = (1.0, 0.7, 0.0)
_INVALID_RGB = (0.9, 0.1, 0.1)
_CAVEATS = int(wire.ElementFlag.EXTRAPOLATED | wire.ElementFlag.DEGRADED
               | wire.ElementFlag.STALE | wire.ElementFlag.AMBIGUOUS)

LOG_LEVEL_NAMES = ("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL")
_LOG_LEVELS = (fg.LogLevel.Unknown, fg.LogLevel.Debug, fg.LogLevel.Info, fg.LogLevel.Warning,
               fg.LogLevel.Error, fg.LogLevel.Fatal)


def timestamp(t_ns: int) -> fg.Timestamp:
    return fg.Timestamp(sec=int(t_ns) // 1_000_000_000, nsec=int(t_ns) % 1_000_000_000)


def viridis(values: np.ndarray, vmax: float) -> np.ndarray:
    """RGB (…, 3) for values scaled onto [0, vmax] (clipped; NaN maps to the low end)."""
    x = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64) / vmax), 0.0, 1.0)
    pos = x * (len(_VIRIDIS) - 1)
    lo = np.minimum(pos.astype(int), len(_VIRIDIS) - 2)
    frac = (pos - lo)[..., None]
    return _VIRIDIS[lo] * (1 - frac) + _VIRIDIS[lo + 1] * frac


def sigma_scale_m(sigma_m: np.ndarray) -> float:
    """Top of the σ colour scale: the largest finite σ rounded up to 1-2-5 steps, ≥ 1 µm."""
    finite = np.asarray(sigma_m)[np.isfinite(sigma_m)]
    top = max(float(finite.max()) if finite.size else 0.0, 1e-6)
    exp = 10.0 ** np.floor(np.log10(top))
    for step in (1, 2, 5, 10):
        if top <= step * exp * (1 + 1e-12):
            return float(step * exp)
    return float(10 * exp)


def _color(rgb: Any, a: float = 1.0) -> fg.Color:
    return fg.Color(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=a)


def _point(p: Any) -> fg.Point3:
    return fg.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _identity_pose(position: Any = (0.0, 0.0, 0.0)) -> fg.Pose:
    return fg.Pose(position=fg.Vector3(x=float(position[0]), y=float(position[1]),
                                       z=float(position[2])),
                   orientation=fg.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def quaternion_x_to(normals: np.ndarray) -> np.ndarray:
    """Unit quaternions (K, 4) as x, y, z, w rotating +x onto each unit normal (K, 3):
    Foxglove draws a pose as an arrow along its +x axis."""
    n = np.asarray(normals, dtype=np.float64)
    q = np.stack([np.zeros(len(n)), -n[:, 2], n[:, 1], 1.0 + n[:, 0]], axis=1)
    opposite = q[:, 3] < 1e-9  # n = -x: half a turn about z
    q[opposite] = (0.0, 0.0, 1.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _pose(position: Any, quat: Any) -> fg.Pose:
    return fg.Pose(position=fg.Vector3(x=float(position[0]), y=float(position[1]),
                                       z=float(position[2])),
                   orientation=fg.Quaternion(x=float(quat[0]), y=float(quat[1]),
                                             z=float(quat[2]), w=float(quat[3])))


def grid_triangles(n: int, m: int) -> np.ndarray:
    """Vertex indices (2·(N−1)·(M−1)·3,) of a row-major N×M node grid, two triangles a cell."""
    i, j = np.meshgrid(np.arange(n - 1), np.arange(m - 1), indexing="ij")
    a = (i * m + j).ravel()
    b, c, d = a + 1, a + m, a + m + 1
    return np.stack([a, b, d, a, d, c], axis=1).ravel()


def scene_sheet(surface: wire.SurfaceMessage, t_ns: int, frame_id: str = FRAME_ID) -> bytes:
    """SceneUpdate: entity ``sheet`` (mesh coloured by node σ) and ``sheet-legend``."""
    n, m = surface.shape
    nodes = surface.nodes.reshape(-1, 3)
    sigma = surface.uncertainty.reshape(-1)
    if not np.isfinite(nodes).all():
        raise ValueError("surface nodes contain NaN or infinite values")
    vmax = sigma_scale_m(sigma)
    rgb = viridis(sigma, vmax)
    stamp = timestamp(t_ns)
    triangles = []
    if n >= 2 and m >= 2:
        triangles.append(fg.TriangleListPrimitive(
            pose=_identity_pose(), points=[_point(p) for p in nodes],
            colors=[_color(c) for c in rgb], indices=[int(k) for k in grid_triangles(n, m)]))
    lines = [] if triangles else [fg.LinePrimitive(
        type=fg.LinePrimitiveLineType.LineStrip, pose=_identity_pose(), thickness=2.0,
        scale_invariant=True, points=[_point(p) for p in nodes],
        colors=[_color(c) for c in rgb])]
    lo, hi = nodes.min(axis=0), nodes.max(axis=0)
    stops = ", ".join(f"{name} {v * 1e6:.3g} µm" for name, v in
                      (("purple", 0.0), ("teal", vmax / 2), ("yellow", vmax)))
    legend = fg.TextPrimitive(pose=_identity_pose((lo[0], hi[1] + 0.005, hi[2])),
                              billboard=True, font_size=14.0, scale_invariant=True,
                              color=_color((1.0, 1.0, 1.0)),
                              text=f"node σ (1 s.d.): {stops}; seq {surface.seq}")
    return fg.SceneUpdate(entities=[
        fg.SceneEntity(timestamp=stamp, frame_id=frame_id, id="sheet", triangles=triangles,
                       lines=lines, metadata=[fg.KeyValuePair(key="sigma_max_m",
                                                              value=repr(vmax))]),
        fg.SceneEntity(timestamp=stamp, frame_id=frame_id, id="sheet-legend", texts=[legend]),
    ]).encode()


def element_colors(flags: np.ndarray) -> np.ndarray:
    """RGB (K, 3): green VALID, amber VALID with a caveat bit, red not VALID."""
    flags = np.asarray(flags, dtype=np.uint8)
    out = np.empty((len(flags), 3))
    out[:] = _INVALID_RGB
    valid = (flags & int(wire.ElementFlag.VALID)) != 0
    out[valid] = _VALID_RGB
    out[valid & ((flags & _CAVEATS) != 0)] = _CAVEAT_RGB
    return out


def _finite_elements(el: wire.ElementsMessage) -> np.ndarray:
    return np.isfinite(el.positions).all(axis=1) & np.isfinite(el.normals).all(axis=1) \
        & (np.linalg.norm(np.nan_to_num(el.normals), axis=1) > 0.5)


def scene_elements(el: wire.ElementsMessage, t_ns: int, frame_id: str = FRAME_ID,
                   arrow_m: float = 0.004) -> bytes:
    """SceneUpdate: entity ``elements``, one arrow per element with a finite pose."""
    keep = _finite_elements(el)
    quats = quaternion_x_to(np.where(keep[:, None], el.normals, (1.0, 0.0, 0.0)))
    colors = element_colors(el.flags)
    arrows = [fg.ArrowPrimitive(pose=_pose(el.positions[k], quats[k]), shaft_length=arrow_m * 0.7,
                                shaft_diameter=arrow_m * 0.08, head_length=arrow_m * 0.3,
                                head_diameter=arrow_m * 0.2, color=_color(colors[k]))
              for k in np.flatnonzero(keep)]
    return fg.SceneUpdate(entities=[fg.SceneEntity(
        timestamp=timestamp(t_ns), frame_id=frame_id, id="elements", arrows=arrows,
        metadata=[fg.KeyValuePair(key="seq", value=str(el.seq)),
                  fg.KeyValuePair(key="shown", value=f"{int(keep.sum())}/{el.count}")])]).encode()


def element_poses(el: wire.ElementsMessage, t_ns: int, frame_id: str = FRAME_ID) -> bytes:
    """PosesInFrame of the elements with a finite pose (others are left out)."""
    keep = _finite_elements(el)
    quats = quaternion_x_to(np.where(keep[:, None], el.normals, (1.0, 0.0, 0.0)))
    return fg.PosesInFrame(timestamp=timestamp(t_ns), frame_id=frame_id,
                           poses=[_pose(el.positions[k], quats[k])
                                  for k in np.flatnonzero(keep)]).encode()


def frame_transform(t_ns: int, frame_id: str = FRAME_ID, parent: str = WORLD_FRAME_ID) -> bytes:
    """The sensor frame placed at the origin of ``world`` (Foxglove needs a root frame)."""
    return fg.FrameTransform(timestamp=timestamp(t_ns), parent_frame_id=parent,
                             child_frame_id=frame_id,
                             translation=fg.Vector3(x=0.0, y=0.0, z=0.0),
                             rotation=fg.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)).encode()


def point_cloud(points_m: np.ndarray, t_ns: int, frame_id: str = FRAME_ID) -> bytes:
    """PointCloud of float32 x, y, z (metres)."""
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise ValueError("points contain NaN or infinite values")
    f32 = fg.PackedElementFieldNumericType.Float32
    return fg.PointCloud(timestamp=timestamp(t_ns), frame_id=frame_id, pose=_identity_pose(),
                         point_stride=12,
                         fields=[fg.PackedElementField(name=k, offset=4 * i, type=f32)
                                 for i, k in enumerate("xyz")],
                         data=pts.astype("<f4").tobytes()).encode()


def log_entry(t_ns: int, level: int, message: str, name: str) -> bytes:
    """foxglove.Log; ``level`` is Foxglove's 0..5."""
    return fg.Log(timestamp=timestamp(t_ns), level=_LOG_LEVELS[level], message=str(message),
                  name=str(name)).encode()


SCHEMAS = {
    "scene": fg.SceneUpdate.get_schema(),
    "poses": fg.PosesInFrame.get_schema(),
    "tf": fg.FrameTransform.get_schema(),
    "cloud": fg.PointCloud.get_schema(),
    "log": fg.Log.get_schema(),
}

# -------------------------------------------------------------------------------- plottable JSON

_NUMBER_ARRAY = {"type": "array", "items": {"type": ["number", "null"]}}
_INT_ARRAY = {"type": "array", "items": {"type": "integer"}}

STRAINS_PLOT_SCHEMA: dict[str, Any] = {
    "title": "skinmap.StrainsPlot",
    "description": "Per-gauge calibrated strains of one scan, flattened in C order over (i, j) "
                   "for each direction (row = along u/x, col = along v/y); null = not valid.",
    "type": "object",
    "properties": {
        "seq": {"type": "integer"}, "device_time_us": {"type": "integer"},
        "rows": {"type": "integer"}, "cols": {"type": "integer"},
        **{f"{layer}_{d}": {**_NUMBER_ARRAY, "description": f"{layer} gauge, {d} direction"}
           for layer in ("upper", "lower") for d in ("row", "col")},
    },
    "required": ["seq", "rows", "cols", "upper_row", "upper_col", "lower_row", "lower_col"],
}

ELEMENTS_PLOT_SCHEMA: dict[str, Any] = {
    "title": "skinmap.ElementsPlot",
    "description": "Per-element σ (1 s.d., µm) and flags of one scan, and the frame's latency "
                   "(host receive to publish, ms).",
    "type": "object",
    "properties": {
        "seq": {"type": "integer"}, "device_time_us": {"type": "integer"},
        "latency_ms": {"type": ["number", "null"]},
        "valid_count": {"type": "integer"},
        "sigma_um": {**_NUMBER_ARRAY, "description": "per element, null where not finite"},
        "scatter_um": {**_NUMBER_ARRAY, "description": "the part of σ that repeated frames of a still "
                                                       "sheet scatter by, per element (absent in logs of layout 1)"},
        "flags": {**_INT_ARRAY, "description": "ElementFlag bits per element"},
        "valid": {**_INT_ARRAY, "description": "1 where the VALID bit is set"},
    },
    "required": ["seq", "sigma_um", "flags", "valid"],
}

_JSON_TYPES = {str: "string", int: "integer", float: "number", bool: "boolean", dict: "object"}


def status_schema() -> dict[str, Any]:
    """JSON schema of the status object, generated from ``skinmap.wire.messages.STATUS_FIELDS``
    (extra fields are allowed, as on the wire)."""
    props = {name: {"type": sorted({_JSON_TYPES[t] for t in types}), "description": doc}
             for name, (types, doc) in wire.STATUS_FIELDS.items()}
    return {"title": "skinmap.Status", "type": "object", "properties": props,
            "required": list(wire.STATUS_FIELDS), "additionalProperties": True}


def _nullable(values: np.ndarray, scale: float = 1.0) -> list[float | None]:
    # 7 significant digits: far below the gauges' noise, and a third of the JSON size.
    return [float(f"{v * scale:.7g}") if np.isfinite(v) else None
            for v in np.asarray(values, dtype=np.float64).ravel()]


def strains_plot(st: wire.StrainsMessage) -> bytes:
    n, m = st.eps_upper.shape[1:]
    body: dict[str, Any] = {"seq": st.seq, "device_time_us": st.device_time_us, "rows": n,
                            "cols": m}
    for layer, eps, valid in (("upper", st.eps_upper, st.valid_upper),
                              ("lower", st.eps_lower, st.valid_lower)):
        for k, d in enumerate(("row", "col")):
            body[f"{layer}_{d}"] = _nullable(np.where(valid[k], eps[k], np.nan))
    return json.dumps(body, separators=(",", ":")).encode()


def elements_plot(el: wire.ElementsMessage, latency_ms: float | None = None) -> bytes:
    valid = el.valid
    body = {"seq": el.seq, "device_time_us": el.device_time_us,
            "latency_ms": None if latency_ms is None or not np.isfinite(latency_ms)
            else round(float(latency_ms), 3),
            "valid_count": int(valid.sum()), "sigma_um": _nullable(el.uncertainty, 1e6),
            "flags": [int(f) for f in el.flags], "valid": [int(v) for v in valid]}
    if el.scatter is not None:
        body["scatter_um"] = _nullable(el.scatter, 1e6)
    return json.dumps(body, separators=(",", ":")).encode()


def json_schema_bytes(schema: Mapping[str, Any]) -> bytes:
    return json.dumps(schema, separators=(",", ":")).encode()


_DECODERS: dict[str, Any] = {}


def decode_protobuf(schema_name: str, data: bytes) -> Any:
    """Decode a Foxglove protobuf message this module writes (``foxglove.Log``, …) into a
    protobuf object, with the SDK's own schema (mcap-protobuf-support)."""
    decoder: Any = _DECODERS.get(schema_name)
    if decoder is None:
        from mcap.records import Schema
        from mcap_protobuf.decoder import DecoderFactory

        known = {s.name: s for s in SCHEMAS.values()}
        if schema_name not in known:
            raise ValueError(f"unknown Foxglove schema {schema_name!r}; expected one of "
                             f"{sorted(known)}")
        sdk = known[schema_name]
        schema = Schema(id=1, name=sdk.name, encoding=sdk.encoding, data=bytes(sdk.data))
        decoder = _DECODERS[schema_name] = DecoderFactory().decoder_for("protobuf", schema)
    return decoder(bytes(data))
