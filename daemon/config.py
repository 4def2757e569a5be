"""skinmapd configuration: TOML in, a validated frozen dataclass tree out.

Everything is checked before anything starts; the first problem found raises
`ConfigError` naming the key, the value and what is allowed. Unknown keys are errors too,
so a typo never silently falls back to a default.
"""
from __future__ import annotations

import json
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, get_args

from skinmap.strains import RESPONSE_TIME_S, SHARED_GAIN_SD

__all__ = [
    "ConfigError",
    "DaemonConfig",
    "DeviceConfig",
    "ElementSpec",
    "ElementsConfig",
    "LogConfig",
    "OutputConfig",
    "ReconstructionConfig",
    "StateConfig",
    "ZenohConfig",
    "load_config",
    "parse_config",
    "DEMO_CONFIG",
]


class ConfigError(ValueError):
    """A configuration value is missing, unknown or out of range."""


# ---------------------------------------------------------------------------------------------
# Options: each is one Literal, which the TOML's strings are checked against (_choice)

ConvexSolver = Literal["factorized", "clarabel"]
TwistSign = Literal["auto", "positive", "negative"]
TwistPrior = Literal["open", "none"]
ElementLayout = Literal["grid", "explicit", "none"]
ZenohMode = Literal["peer", "client"]
LogCompression = Literal["zstd", "lz4", "none"]

# Sections


@dataclass(frozen=True)
class DeviceConfig:
    port: str = "socket://127.0.0.1:7600"
    name: str = ""  # key-space name; empty = derived from the scanner's serial number
    baudrate: int = 3_000_000
    scan_rate_hz: float = 50.0
    handshake_timeout_s: float = 2.0
    stall_timeout_s: float = 1.0
    reconnect_min_s: float = 0.2
    reconnect_max_s: float = 1.0
    exclusive: bool = True
    max_cells: int = 1024


@dataclass(frozen=True)
class ReconstructionConfig:
    pitch_mm: float = 0.0  # 0 = as reported by the scanner
    h_upper_mm: float = 0.0  # 0 = as reported by the scanner
    h_lower_mm: float = 0.0
    strain_sigma: float = 5.7e-5  # strain-noise s.d. used for uncertainty estimates
    warm_start: bool = True
    # the general model's field fit: its closed form, or Clarabel with a Huber loss (docs/reconstruction.md,
    # "Solvers"); either way every frame is first screened for a gauge its neighbours contradict, the
    # robust fit of that screen solved by Clarabel ("Robust gauge screen")
    convex_solver: ConvexSolver = "factorized"
    # fit the sheet as a height graph to every gauge's turning and stretch first (sheets of up to
    # 64 cells; up to 144 where the general model misfits; larger ones keep the general model):
    # sharp bumps, see docs/reconstruction.md
    graph_fit: bool = True
    # the sign of a constant twist the gauges cannot observe (mirror-image shapes such as an
    # oblique cylinder): "auto" reports both (AMBIGUOUS), "positive"/"negative" fix it for a
    # sheet whose mounting is known (docs/reconstruction.md, "Mirror images")
    twist_sign: TwistSign = "auto"
    # a twist the stretch cannot tell from none where the answer has none (a dome: a sphere and a
    # dome turned off the grid read alike): "open" puts the twists the stretch allows into σ,
    # "none" is for a sheet known to carry none there (a balloon, a sphere, molds whose principal
    # axes lie along the rows and columns); the answers are the same (docs/reconstruction.md,
    # "A twist the stretch cannot tell from none")
    twist_prior: TwistPrior = "open"
    # the s.d. (relative) of a gain error every gauge shares, carried into σ: by default the
    # gauges' hysteresis (a loop 4.21 ± 0.70 % of the excursion high reads a sheet pressed and
    # held up to half of it low) and their relaxation (a held strain reads up to 3.5 % low), in
    # quadrature; more for gauges whose gauge factors are known less well, 0 to
    # leave it out (docs/reconstruction.md, "A gain the gauges share")
    gain_sd: float = SHARED_GAIN_SD
    # the gauges' response time (ms; the paper: below 170 ms): a sheet that moves is read up to a
    # third of it late (a first-order response at 95 %), so σ takes that lag times each point's
    # speed, read from the frames before; 0 leaves it out (docs/reconstruction.md, "A sheet that moves")
    response_time_ms: float = RESPONSE_TIME_S * 1e3
    # the full-position fit with the membrane-equilibrium prior after the default answer (sheets
    # of up to 64 cells, about a second of CPU per cold 5×5 frame: docs/reconstruction.md,
    # "Elastic films"); it needs the film's Poisson ratio
    elastic_prior: bool = False
    poisson_ratio: float = 0.0  # 0 = the calibration file's (`skinmap calibrate --dome R`)
    poisson_ratio_sd: float = 0.02  # with poisson_ratio set here: how well it is known


@dataclass(frozen=True)
class OutputConfig:
    rate_hz: float = 10.0  # 0 = every scan
    # scans reconstructed (not published) just before each one due at rate_hz, so that its warm
    # start is one scan old rather than several (docs/architecture.md, "Lead scans"); 0: none
    lead_scans: int = 1
    strains_rate_hz: float = 2.0
    status_rate_hz: float = 1.0
    surface_rate_hz: float = 10.0
    points_per_pitch: int = 20
    console: bool = False  # print a live status line (the demo turns it on)


@dataclass(frozen=True)
class ElementSpec:
    u_mm: float
    v_mm: float
    offset_mm: float = 0.0  # from the neutral plane along the upper normal; negative = toward the lower side


@dataclass(frozen=True)
class ElementsConfig:
    layout: ElementLayout = "grid"
    rows: int = 1
    cols: int = 16
    pitch_u_mm: float = 3.0
    pitch_v_mm: float = 3.0
    centre_u_mm: float = 0.0
    centre_v_mm: float = 0.0
    offset_mm: float = 0.0
    explicit: tuple[ElementSpec, ...] = ()

    def material_coordinates(self) -> tuple[list[tuple[float, float]], list[float]]:
        """Element (u, v) in mm and normal offsets, in publication order."""
        if self.layout == "explicit":
            return [(e.u_mm, e.v_mm) for e in self.explicit], [e.offset_mm for e in self.explicit]
        if self.layout == "none":
            return [], []
        uv = []
        for r in range(self.rows):
            for c in range(self.cols):
                uv.append(
                    (
                        self.centre_u_mm + (c - (self.cols - 1) / 2) * self.pitch_u_mm,
                        self.centre_v_mm + (r - (self.rows - 1) / 2) * self.pitch_v_mm,
                    )
                )
        return uv, [self.offset_mm] * len(uv)


@dataclass(frozen=True)
class ZenohConfig:
    prefix: str = "skinmap"
    mode: ZenohMode = "peer"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    allow_non_loopback: bool = False
    config_file: str = ""  # optional Zenoh JSON5 file (production: TLS, access control)
    enabled: bool = True
    # Zenoh access control: puts, deletes, queryables, liveliness tokens and replies that other
    # sessions send into the gateway's key space are dropped on arrival (subscribing and
    # querying stay open). A config_file with its own enabled access_control replaces this.
    deny_remote_writes: bool = True


@dataclass(frozen=True)
class LogConfig:
    enabled: bool = True
    directory: str = "logs"
    basename: str = "skinmap"
    max_file_mb: float = 256.0
    max_file_minutes: float = 60.0
    compression: LogCompression = "zstd"
    chunk_kb: int = 256
    fsync: bool = True
    queue_size: int = 4096
    surface_rate_hz: float = 1.0  # point clouds in the log (nodes replay from /raw)
    points_per_pitch: int = 8


@dataclass(frozen=True)
class StateConfig:
    directory: str = "state"


@dataclass(frozen=True)
class TactileConfig:
    enabled: bool = False  # publish and log `contact` (docs/tactile.md)
    baseline_frames: int = 10  # processed surfaces after each (re)connect that make the baseline
    k: float = 3.0  # contact: pressed in beyond k·σ of the baseline
    min_depth_mm: float = 0.5  # … and beyond this (what a free probe's reconstruction wanders stays below)
    step_mm: float = 2.0  # material sampling of the sheet
    # the probe's stiffness length ℓ, mm: how `skinmap map` reads a contact's place from its free
    # cells' bending (tactile.level_by_bending; 14.6 the paper's balloon; `skinmap map
    # --fit-probe-length` fits a probe's own on presses of a flat plate)
    probe_length_mm: float = 14.6
    # known probe poses, one a press in order: (x_mm, y_mm, angle_deg, depth_mm) (docs/tactile.md)
    poses: tuple[tuple[float, float, float, float], ...] = ()


@dataclass(frozen=True)
class DaemonConfig:
    device: DeviceConfig = field(default_factory=DeviceConfig)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    elements: ElementsConfig = field(default_factory=ElementsConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    log: LogConfig = field(default_factory=LogConfig)
    state: StateConfig = field(default_factory=StateConfig)
    tactile: TactileConfig = field(default_factory=TactileConfig)
    source: str = "<defaults>"  # where the config came from
    text: str = ""  # the raw TOML, logged at start

    def guarded_key_expr(self) -> str | None:
        """The key expression other Zenoh sessions may not write into (None: not guarded):
        `<prefix>/<device>/**`, or all of `<prefix>/**` while the device name comes from the
        scanner's serial number and is not known before the session opens."""
        if not self.zenoh.deny_remote_writes:
            return None
        if self.device.name:
            return f"{self.zenoh.prefix}/{self.device.name}/**"
        return f"{self.zenoh.prefix}/**"

    def resolve(self, path: str) -> Path:
        """A relative directory in the config is relative to the config file's folder."""
        p = Path(path).expanduser()
        if p.is_absolute() or self.source.startswith("<"):
            return p
        return Path(self.source).parent / p


# ---------------------------------------------------------------------------------------------
# Validation helpers


def _fail(key: str, value: Any, allowed: str) -> ConfigError:
    return ConfigError(f"config key '{key}' = {value!r} is invalid: {allowed}")


def _number(lo: float, hi: float, *, integer: bool = False, lo_open: bool = False) -> Callable[[str, Any], Any]:
    def check(key: str, value: Any) -> Any:
        kind = "an integer" if integer else "a number"
        bound = f"{'>' if lo_open else '≥'} {lo:g} and ≤ {hi:g}"
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(key, value, f"must be {kind} {bound}")
        if integer and not isinstance(value, int):
            raise _fail(key, value, f"must be {kind} {bound}")
        if not math.isfinite(value) or value > hi or value < lo or (lo_open and value == lo):
            raise _fail(key, value, f"must be {kind} {bound}")
        return int(value) if integer else float(value)

    return check


def _boolean(key: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise _fail(key, value, "must be true or false")
    return value


def _choice(options_type: Any) -> Callable[[str, Any], str]:
    """A check that the value is one of the Literal type's strings."""
    options: tuple[str, ...] = get_args(options_type)

    def check(key: str, value: Any) -> str:
        if value not in options:
            raise _fail(key, value, "must be one of " + ", ".join(repr(o) for o in options))
        return value

    return check


def _no_control_characters(key: str, value: str) -> None:
    if any(ord(c) < 32 or ord(c) == 127 for c in value):
        raise _fail(key, value, "must not contain control characters")


def _string(pattern: str | None = None, what: str = "") -> Callable[[str, Any], str]:
    def check(key: str, value: Any) -> str:
        if not isinstance(value, str):
            raise _fail(key, value, "must be a string")
        _no_control_characters(key, value)
        if pattern is not None and not re.fullmatch(pattern, value):
            raise _fail(key, value, what or f"must match {pattern}")
        return value

    return check


_KEY_SEGMENT = r"[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*"


def _port(key: str, value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise _fail(key, value, "must be a serial device path (e.g. /dev/serial/by-id/…) or a pyserial URL")
    _no_control_characters(key, value)
    if "://" in value:
        scheme = value.split("://", 1)[0]
        if scheme not in ("socket", "loop", "rfc2217", "spy", "alt", "hwgrep"):
            raise _fail(key, value, "URL scheme must be one pyserial knows: socket://, loop://, rfc2217://, spy://, alt://, hwgrep://")
        if scheme in ("socket", "rfc2217"):
            host = value.split("://", 1)[1].split(":", 1)[0]
            if host not in ("127.0.0.1", "localhost", "[::1]", "::1"):
                raise _fail(key, value, "network serial ports are only allowed on loopback (127.0.0.1)")
    elif not value.startswith("/"):
        raise _fail(key, value, "must be an absolute device path or a pyserial URL")
    return value


def _endpoint(key: str, value: Any) -> str:
    if not isinstance(value, str) or not re.fullmatch(r"(tcp|udp|tls|quic)/.+:\d{1,5}", value):
        raise _fail(key, value, "must be a Zenoh endpoint like 'tcp/127.0.0.1:7447'")
    port = int(value.rsplit(":", 1)[1])
    if not 1 <= port <= 65535:
        raise _fail(key, value, "port must be 1..65535")
    return value


def _string_list(item: Callable[[str, Any], Any]) -> Callable[[str, Any], tuple]:
    def check(key: str, value: Any) -> tuple:
        if not isinstance(value, list):
            raise _fail(key, value, "must be a list")
        return tuple(item(f"{key}[{i}]", v) for i, v in enumerate(value))

    return check


_SCHEMA: dict[str, dict[str, Callable[[str, Any], Any]]] = {
    "device": {
        "port": _port,
        "name": _string(r"[A-Za-z0-9_\-]{0,64}", "must be 0–64 characters of letters, digits, '_' or '-'"),
        "baudrate": _number(1200, 20_000_000, integer=True),
        "scan_rate_hz": _number(0, 2000, lo_open=True),
        "handshake_timeout_s": _number(0.05, 60, lo_open=True),
        "stall_timeout_s": _number(0.05, 600),
        "reconnect_min_s": _number(0.01, 60),
        "reconnect_max_s": _number(0.01, 3600),
        "exclusive": _boolean,
        "max_cells": _number(4, 1024, integer=True),
    },
    "reconstruction": {
        "pitch_mm": _number(0, 100),
        "h_upper_mm": _number(0, 10),
        "h_lower_mm": _number(0, 10),
        "strain_sigma": _number(0, 0.01),
        "warm_start": _boolean,
        "convex_solver": _choice(ConvexSolver),
        "graph_fit": _boolean,
        "twist_sign": _choice(TwistSign),
        "twist_prior": _choice(TwistPrior),
        "gain_sd": _number(0, 0.3),
        "response_time_ms": _number(0, 2000),
        "elastic_prior": _boolean,
        "poisson_ratio": _number(0, 0.499),
        "poisson_ratio_sd": _number(0, 0.2),
    },
    "output": {
        "rate_hz": _number(0, 2000),
        "lead_scans": _number(0, 16, integer=True),
        "strains_rate_hz": _number(0, 2000),
        "status_rate_hz": _number(0.01, 100, lo_open=True),
        "surface_rate_hz": _number(0, 2000),
        "points_per_pitch": _number(1, 100, integer=True),
        "console": _boolean,
    },
    "elements": {
        "layout": _choice(ElementLayout),
        "rows": _number(1, 1024, integer=True),
        "cols": _number(1, 1024, integer=True),
        "pitch_u_mm": _number(0, 1000, lo_open=True),
        "pitch_v_mm": _number(0, 1000, lo_open=True),
        "centre_u_mm": _number(-1000, 1000),
        "centre_v_mm": _number(-1000, 1000),
        "offset_mm": _number(-50, 50),
    },
    "zenoh": {
        "prefix": _string(_KEY_SEGMENT, "must be a Zenoh key without wildcards, e.g. 'skinmap' or 'lab/skinmap'"),
        "mode": _choice(ZenohMode),
        "listen": _string_list(_endpoint),
        "connect": _string_list(_endpoint),
        "allow_non_loopback": _boolean,
        "config_file": _string(),
        "enabled": _boolean,
        "deny_remote_writes": _boolean,
    },
    "log": {
        "enabled": _boolean,
        "directory": _string(r".+", "must be a non-empty path"),
        "basename": _string(r"[A-Za-z0-9_\-]{1,64}", "must be 1–64 characters of letters, digits, '_' or '-'"),
        "max_file_mb": _number(0.01, 1_000_000, lo_open=True),
        "max_file_minutes": _number(0.01, 10_080, lo_open=True),
        "compression": _choice(LogCompression),
        "chunk_kb": _number(1, 65_536, integer=True),
        "fsync": _boolean,
        "queue_size": _number(16, 1_000_000, integer=True),
        "surface_rate_hz": _number(0, 2000),
        "points_per_pitch": _number(1, 100, integer=True),
    },
    "state": {"directory": _string(r".+", "must be a non-empty path")},
    "tactile": {
        "enabled": _boolean,
        "baseline_frames": _number(1, 10_000, integer=True),
        "k": _number(0.5, 100),
        "min_depth_mm": _number(0, 50),
        "step_mm": _number(0.25, 50),
        "probe_length_mm": _number(0.5, 1000),
        "poses": lambda key, value: _pose_rows(key, value),
    },
}

_SECTIONS = {
    "device": DeviceConfig,
    "reconstruction": ReconstructionConfig,
    "output": OutputConfig,
    "elements": ElementsConfig,
    "zenoh": ZenohConfig,
    "log": LogConfig,
    "state": StateConfig,
    "tactile": TactileConfig,
}


def _pose_rows(key: str, value: Any) -> tuple[tuple[float, float, float, float], ...]:
    """[tactile] poses: an array of [x_mm, y_mm, angle_deg, depth_mm] arrays of finite numbers."""
    if not isinstance(value, list):
        raise _fail(key, value, "must be an array of [x_mm, y_mm, angle_deg, depth_mm] arrays, one a press")
    rows = []
    for i, row in enumerate(value):
        if not isinstance(row, list) or len(row) != 4:
            raise _fail(f"{key}[{i}]", row, "must be [x_mm, y_mm, angle_deg, depth_mm] (4 numbers)")
        rows.append(tuple(_number(-1e6, 1e6)(f"{key}[{i}][{j}]", v) for j, v in enumerate(row)))
    return tuple(rows)


def _explicit_elements(value: Any, sheet_hint: str = "elements.explicit") -> tuple[ElementSpec, ...]:
    if not isinstance(value, list) or not value:
        raise _fail(sheet_hint, value, "must be a non-empty array of tables {u_mm, v_mm, offset_mm}")
    out = []
    for i, item in enumerate(value):
        key = f"{sheet_hint}[{i}]"
        if not isinstance(item, dict):
            raise _fail(key, item, "must be a table {u_mm, v_mm, offset_mm}")
        unknown = set(item) - {"u_mm", "v_mm", "offset_mm"}
        if unknown:
            raise _fail(f"{key}.{sorted(unknown)[0]}", item[sorted(unknown)[0]], "unknown key; allowed: u_mm, v_mm, offset_mm")
        for need in ("u_mm", "v_mm"):
            if need not in item:
                raise ConfigError(f"config key '{key}.{need}' is missing: every explicit element needs u_mm and v_mm")
        coord = _number(-1000, 1000)
        out.append(
            ElementSpec(
                u_mm=coord(f"{key}.u_mm", item["u_mm"]),
                v_mm=coord(f"{key}.v_mm", item["v_mm"]),
                offset_mm=_number(-50, 50)(f"{key}.offset_mm", item.get("offset_mm", 0.0)),
            )
        )
    return tuple(out)


def parse_config(data: dict[str, Any], *, source: str = "<dict>", text: str = "") -> DaemonConfig:
    """Validate a parsed TOML document; raise ConfigError on the first problem."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the configuration must be a TOML table")
    unknown = set(data) - set(_SECTIONS)
    if unknown:
        name = sorted(unknown)[0]
        raise ConfigError(f"config section '[{name}]' is unknown; allowed sections: {', '.join(_SECTIONS)}")
    sections: dict[str, Any] = {}
    for name, cls in _SECTIONS.items():
        raw = data.get(name, {})
        if not isinstance(raw, dict):
            raise _fail(name, raw, "must be a table")
        schema = _SCHEMA[name]
        values: dict[str, Any] = {}
        for key, value in raw.items():
            if name == "elements" and key == "explicit":
                values["explicit"] = _explicit_elements(value)
                continue
            if key not in schema:
                allowed = sorted(schema) + (["explicit"] if name == "elements" else [])
                raise ConfigError(f"config key '{name}.{key}' is unknown; allowed keys in [{name}]: {', '.join(allowed)}")
            values[key] = schema[key](f"{name}.{key}", value)
        sections[name] = cls(**values)

    cfg = DaemonConfig(**sections, source=source, text=text)
    _cross_checks(cfg)
    return cfg


def _cross_checks(cfg: DaemonConfig) -> None:
    d, z, e = cfg.device, cfg.zenoh, cfg.elements
    if d.reconnect_max_s < d.reconnect_min_s:
        raise _fail("device.reconnect_max_s", d.reconnect_max_s, f"must be ≥ device.reconnect_min_s ({d.reconnect_min_s:g})")
    if e.layout == "explicit" and not e.explicit:
        raise ConfigError("config key 'elements.explicit' is missing: layout = 'explicit' needs [[elements.explicit]] tables")
    if e.layout != "explicit" and e.explicit:
        raise _fail("elements.layout", e.layout, "must be 'explicit' when [[elements.explicit]] tables are given")
    if e.layout == "grid" and e.rows * e.cols > 65_536:
        raise _fail("elements.rows", e.rows, "rows × cols must be ≤ 65536")
    if z.enabled and not z.listen and not z.connect and not z.config_file:
        raise _fail("zenoh.listen", list(z.listen), "give at least one listen or connect endpoint (or zenoh.enabled = false)")
    if not z.allow_non_loopback:
        # The same rule the session itself applies, so `--check` and start-up never disagree.
        from skinmap.daemon.zenoh_io import check_loopback_endpoint

        for key, endpoints in (("zenoh.listen", z.listen), ("zenoh.connect", z.connect)):
            for ep in endpoints:
                try:
                    check_loopback_endpoint(ep, listen=key == "zenoh.listen")
                except ValueError as exc:
                    raise _fail(
                        key,
                        ep,
                        f"non-loopback endpoints are refused unless zenoh.allow_non_loopback = true "
                        f"(use tcp/127.0.0.1:PORT): {exc}",
                    ) from None
    for key, value in (("log.directory", cfg.log.directory), ("state.directory", cfg.state.directory),
                       ("zenoh.config_file", z.config_file)):
        try:
            Path(value).expanduser()
        except RuntimeError:
            raise _fail(key, value, "names a home directory ('~user') that does not exist") from None
    if z.config_file and not Path(cfg.resolve(z.config_file)).is_file():
        raise _fail("zenoh.config_file", z.config_file, "file does not exist")


def load_config(path: str | Path) -> DaemonConfig:
    """Read and validate a TOML config file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config file {str(p)!r}: {exc.strerror or exc}") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {str(p)!r} is not valid TOML: {exc}") from exc
    return parse_config(data, source=str(p), text=text)


# The embedded default: the emulator on loopback, logs and state in local folders.
DEMO_CONFIG = """\
# skinmapd demo: emulator on loopback TCP, Zenoh on loopback, logs in ./logs
[device]
port = "socket://127.0.0.1:7600"
name = "demo"
scan_rate_hz = 50

[output]
rate_hz = 10
console = true

[elements]
layout = "grid"
rows = 1
cols = 32
pitch_u_mm = 1.5
offset_mm = -0.3

[zenoh]
prefix = "skinmap"
listen = ["tcp/127.0.0.1:7447"]
# other sessions may subscribe and query, never put into skinmap/demo/**
deny_remote_writes = true

[log]
directory = "logs"

[state]
directory = "state"
"""


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        # JSON string escapes (\\ \" \n \u00XX) are valid TOML basic-string escapes.
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def config_to_toml(cfg: DaemonConfig) -> str:
    """The complete effective configuration as TOML (every key, defaults included).

    Logged at start so a log file carries exactly what produced it; parsing it back gives an
    equal configuration.
    """
    lines = [f"# effective skinmapd configuration (from {cfg.source})"]
    explicit: tuple[ElementSpec, ...] = ()
    for name in _SECTIONS:
        section = getattr(cfg, name)
        lines.append(f"\n[{name}]")
        for key in _SCHEMA[name]:
            lines.append(f"{key} = {_toml_value(getattr(section, key))}")
        if name == "elements":
            explicit = section.explicit
    for e in explicit:
        lines.append(f"\n[[elements.explicit]]\nu_mm = {e.u_mm!r}\nv_mm = {e.v_mm!r}\noffset_mm = {e.offset_mm!r}")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------
# What the config needs on this machine (skinmapd --check)

_TLS_FILE_KEYS = ("root_ca_certificate", "listen_private_key", "listen_certificate",
                  "connect_private_key", "connect_certificate")


def _writable_folder(path: Path) -> str | None:
    """None if `path` is a writable folder or can be created; else why not."""
    if path.exists():
        if not path.is_dir():
            return "exists but is not a folder"
        return None if os.access(path, os.W_OK | os.X_OK) else "is not writable by this user"
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        return f"does not exist, and {str(parent)!r} does not let this user create it"
    return None


def check_environment(cfg: DaemonConfig) -> list[tuple[str, str]]:
    """The files and folders the config needs, checked on this machine: (level, message)
    pairs, level 'error' (skinmapd would fail or lose data) or 'note'. TLS files named in
    the Zenoh config file are resolved as Zenoh does, from the working directory."""
    found: list[tuple[str, str]] = []
    if cfg.log.enabled:
        folder = Path(cfg.resolve(cfg.log.directory))
        problem = _writable_folder(folder)
        if problem:
            found.append(("error", f"log.directory {str(folder)!r} {problem}"))
        elif not folder.exists():
            found.append(("note", f"log.directory {str(folder)!r} does not exist yet; skinmapd "
                                  "creates it"))
    state = Path(cfg.resolve(cfg.state.directory))
    problem = _writable_folder(state)
    if problem:
        found.append(("error", f"state.directory {str(state)!r} {problem} (the tare is kept there)"))
    if cfg.zenoh.enabled and cfg.zenoh.config_file:
        found += _zenoh_file_needs(Path(cfg.resolve(cfg.zenoh.config_file)))
    port = cfg.device.port
    if not port.startswith(("socket://", "rfc2217://", "loop://")) and not Path(port).exists():
        found.append(("note", f"device.port {port!r} does not exist now; skinmapd waits for it "
                              "and opens it when it appears"))
    return found


def _zenoh_file_needs(path: Path) -> list[tuple[str, str]]:
    import zenoh

    try:
        zcfg = zenoh.Config.from_file(str(path))
        tls = json.loads(zcfg.get_json("transport/link/tls"))
    except Exception as exc:  # noqa: BLE001 - zenoh raises its own error type
        return [("error", f"zenoh.config_file {str(path)!r} cannot be read: {exc}")]
    found = []
    for key in _TLS_FILE_KEYS:
        value = (tls or {}).get(key)
        if not value:
            continue
        file = Path(value).expanduser()
        if not file.is_absolute():
            file = Path.cwd() / file
        if not file.is_file():
            found.append(("error", f"zenoh.config_file {str(path)!r}: transport/link/tls/{key} "
                                   f"{str(file)!r} does not exist"))
        elif not os.access(file, os.R_OK):
            found.append(("error", f"zenoh.config_file {str(path)!r}: transport/link/tls/{key} "
                                   f"{str(file)!r} is not readable by this user"))
    return found
