"""Loopback-safe Zenoh session configuration, shared by the gateway, the client and the tools.

Multicast scouting and gossip are always off unless a Zenoh config file explicitly enables
multicast; every endpoint must be tcp on loopback unless non-loopback use is asked for.
"""

from __future__ import annotations

import ipaddress
import json
import re
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator

import zenoh

_MODES = ("peer", "client", "router")
_ENDPOINT = re.compile(r"^(?P<proto>[a-z0-9]+)/(?P<host>\[[^\]]*\]|[^:/\[\]]+):(?P<port>[^#?]*)"
                       r"(?P<rest>[#?].*)?$")
# Explicit `multicast: { ... enabled: true ... }` in a JSON5 file (quoted or bare keys).
_MULTICAST_ON = re.compile(r"""["']?multicast["']?\s*:\s*\{[^{}]*?["']?enabled["']?\s*:\s*true""")


def check_loopback_endpoint(endpoint: str, *, listen: bool = False) -> str:
    """Return ``endpoint`` if it is tcp on 127.0.0.1, [::1] or localhost with a valid port,
    else raise ValueError naming it."""
    if not isinstance(endpoint, str):
        raise TypeError(f"endpoint must be a string, got {type(endpoint).__name__}")
    match = _ENDPOINT.match(endpoint)
    if match is None:
        raise ValueError(f"endpoint {endpoint!r} is not of the form tcp/HOST:PORT")
    if match["proto"] != "tcp":
        raise ValueError(f"endpoint {endpoint!r}: only tcp is allowed on the loopback default")
    host = match["host"].strip("[]")
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host) in (ipaddress.ip_address("127.0.0.1"),
                                                      ipaddress.ip_address("::1"))
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"endpoint {endpoint!r} is not loopback (127.0.0.1, [::1] or "
                             f"localhost); pass allow_non_loopback=True to use it")
    port = match["port"]
    lowest = 0 if listen else 1
    if not port.isdigit() or not lowest <= int(port) <= 65535:
        raise ValueError(f"endpoint {endpoint!r} has an invalid port {port!r}")
    return endpoint


def _endpoint_list(name: str, endpoints: Iterable[str] | str) -> list[str]:
    if isinstance(endpoints, str):
        raise TypeError(f"{name} must be a list of endpoints, got the string {endpoints!r}")
    return list(endpoints)


def _file_endpoints(config: zenoh.Config, key: str, mode: str) -> list[str]:
    raw = json.loads(config.get_json(key))
    if isinstance(raw, dict):  # per-mode form: {"peer": [...], "router": [...]}
        raw = raw.get(mode)
    return list(raw or [])


def make_session_config(listen: Iterable[str] = (), connect: Iterable[str] = (), *,
                        allow_non_loopback: bool = False, mode: str = "peer",
                        config_file: str | Path | None = None,
                        deny_remote_writes: str | None = None) -> zenoh.Config:
    """Build a Zenoh config that talks only to the given endpoints.

    Multicast scouting and gossip are always switched off, except that a ``config_file``
    (production: TLS, access control) may explicitly enable multicast scouting. Every
    endpoint -- given here or found in the file -- must be tcp on loopback unless
    ``allow_non_loopback`` is True. ``listen``/``connect`` given here replace the file's.
    With ``deny_remote_writes`` (a key expression), other sessions' writes there are dropped
    by access control (``foreign_write_guard``), unless the file enables its own.
    """
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    listen = _endpoint_list("listen", listen)
    connect = _endpoint_list("connect", connect)
    if not allow_non_loopback:
        for e in listen:
            check_loopback_endpoint(e, listen=True)
        for e in connect:
            check_loopback_endpoint(e)

    multicast_in_file = False
    if config_file is not None:
        path = Path(config_file)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ValueError(f"cannot read Zenoh config file {str(path)!r}: {exc}") from None
        try:
            config = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise ValueError(f"invalid Zenoh config file {str(path)!r}: {exc}") from None
        multicast_in_file = (json.loads(config.get_json("scouting/multicast/enabled")) is True
                             and _MULTICAST_ON.search(text) is not None)
    else:
        config = zenoh.Config()

    config.insert_json5("mode", json.dumps(mode))
    # Always set listen explicitly: zenoh's default peer listener is tcp/[::]:0 (all interfaces).
    if listen or config_file is None:
        config.insert_json5("listen/endpoints", json.dumps(listen))
    if connect or config_file is None:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    if not allow_non_loopback:
        for e in _file_endpoints(config, "listen/endpoints", mode):
            check_loopback_endpoint(e, listen=True)
        for e in _file_endpoints(config, "connect/endpoints", mode):
            check_loopback_endpoint(e)
    if not multicast_in_file:
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("scouting/gossip/enabled", "false")
    if deny_remote_writes is not None and \
            json.loads(config.get_json("access_control/enabled")) is not True:
        config.insert_json5("access_control", json.dumps(foreign_write_guard(deny_remote_writes)))
    return config


def foreign_write_guard(key_expr: str) -> dict[str, Any]:
    """A Zenoh ``access_control`` block for a publishing session: what other sessions send
    into ``key_expr`` that would write there (put, delete, a queryable, a liveliness token, a
    reply) is dropped on arrival; subscribing, querying and everything else stay allowed.

    The subject has no attributes, so it matches every remote session on every link."""
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [{"id": "no-foreign-writes", "permission": "deny", "flows": ["ingress"],
                   "messages": ["put", "delete", "declare_queryable", "liveliness_token", "reply"],
                   "key_exprs": [key_expr]}],
        "subjects": [{"id": "every-remote-session"}],
        "policies": [{"rules": ["no-foreign-writes"], "subjects": ["every-remote-session"]}],
    }


class ZenohOpenError(OSError):
    """The Zenoh session could not be opened (an endpoint in use, unreachable, refused)."""


def _zerror_text(exc: Exception) -> str:
    """Zenoh's error message on one line, without its Rust source locations."""
    text = " ".join(str(exc).split())
    text = re.sub(r" at \S+\.rs:\d+\.?", "", text)
    listener = re.search(r"bound to (\S+?): \[[^\]]*?: ([^\[\]]+?)(?: \(os error \d+\))?\.?\]", text)
    if listener:
        return f"cannot listen on {listener[1]}: {listener[2]}"
    return text


@contextmanager
def open_session(config: zenoh.Config) -> Iterator[zenoh.Session]:
    """Open a session and always close it on exit; ZenohOpenError (one line naming the
    endpoint and the reason, e.g. "cannot listen on tcp/127.0.0.1:7447: Address already in
    use") if it cannot be opened.

    Closing explicitly matters: a process holding callback subscribers or queryables can hang
    at interpreter exit otherwise (atexit runs too late).
    """
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohOpenError(f"Zenoh: {_zerror_text(exc)}") from None
    try:
        yield session
    finally:
        session.close()
