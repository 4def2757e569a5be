"""Bad configuration and bad bytes: fuzzing the config loader and the stream decoder, and
`skinmapd --config` refusing every invalid file without starting anything.

Each property test counts the inputs it tried and prints them ("FIGURE ...", run with -s);
the counts are asserted, so the figure in docs/reliability.md is what actually ran.
"""
from __future__ import annotations

import collections
import dataclasses
import re
import socket
import subprocess
import sys
import tempfile
import threading
import tomllib
from pathlib import Path

import pytest
from conftest import free_port
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from skinmap import protocol as p
from skinmap.daemon.config import DEMO_CONFIG, ConfigError, DaemonConfig, config_to_toml, load_config, parse_config
from skinmap.daemon.zenoh_io import make_session_config

CONFIG_EXAMPLES = 800
TOML_EXAMPLES = 400
DECODER_EXAMPLES = 300

# ---------------------------------------------------------------------------------------------
# Random configuration documents, built from the config dataclasses themselves.

SECTIONS = {f.name: f.type for f in dataclasses.fields(DaemonConfig) if f.name not in ("source", "text")}
_SECTION_CLASSES = {name: type(getattr(DaemonConfig(), name)) for name in SECTIONS}

ENDPOINTS = ["tcp/127.0.0.1:7447", "tcp/localhost:7447", "tcp/[::1]:7447", "tcp/0.0.0.0:7447",
             "tcp/[::]:7447", "tcp/192.168.1.4:7447", "tcp/example.com:7447", "tcp/127.0.0.1:0",
             "tcp/127.0.0.1:70000", "udp/127.0.0.1:7447", "http://x", "tcp/127.0.0.1", ""]
POOLS: dict[str, list] = {
    "port": ["/dev/ttyACM0", "socket://127.0.0.1:7600", "socket://10.0.0.5:7600", "socket://localhost:1",
             "loop://", "rfc2217://127.0.0.1:2217", "ftp://x", "COM3", "", " "],
    "layout": ["grid", "explicit", "none", "ring"],
    "mode": ["peer", "client", "router"],
    "compression": ["zstd", "lz4", "none", "gzip"],
    "prefix": ["skinmap", "lab/skinmap", "a/*", "", "a//b", "bad key"],
    "name": ["", "skin0", "bad name", "x" * 65],
    "basename": ["skinmap", "", "a/b", "x" * 65],
    "directory": ["logs", "/tmp/skinmap-fuzz-never-created", ""],
    "config_file": ["", "/nonexistent/zenoh.json5", "zenoh.json5"],
}

wild = st.one_of(
    st.booleans(), st.integers(), st.floats(), st.text(max_size=16),
    st.lists(st.one_of(st.integers(), st.text(max_size=8)), max_size=3),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=2),
    st.datetimes(), st.dates(), st.times(),
)


def _no_home_lookup(s: str) -> bool:
    # "~user/..." asks the password database; an unknown user is test_tilde_user_paths below.
    return not s.startswith("~")


def plausible(name: str, default):
    """Values near the valid range of a key: defaults, pools of good and bad strings, numbers
    around the limits."""
    if isinstance(default, bool):
        return st.booleans()
    if isinstance(default, int):
        return st.one_of(st.just(default), st.integers(-5, 3000), st.integers(2**31, 2**63))
    if isinstance(default, float):
        return st.one_of(st.just(default), st.floats(-10, 5000, allow_nan=False), st.integers(0, 100),
                         st.sampled_from([0.0, -0.0, float("nan"), float("inf"), 1e-300, 1e300]))
    if isinstance(default, tuple):
        if name == "explicit":
            return explicit_elements
        return st.lists(st.sampled_from(ENDPOINTS), max_size=3)
    if isinstance(default, str):
        return st.one_of(st.sampled_from(POOLS.get(name, [default])),
                         st.text(max_size=12).filter(_no_home_lookup))
    raise TypeError(f"no strategy for {name} = {default!r}")


element_key = st.sampled_from(["u_mm", "v_mm", "offset_mm", "w_mm"])
explicit_elements = st.one_of(
    st.lists(st.dictionaries(element_key, st.one_of(st.floats(-2000, 2000), st.integers(-5, 5), wild), max_size=4),
             max_size=4),
    wild,
)


@st.composite
def section_tables(draw, section: str) -> dict:
    cls = _SECTION_CLASSES[section]
    defaults = cls() if section != "elements" else dataclasses.replace(cls(), explicit=())
    names = [f.name for f in dataclasses.fields(cls)]
    chosen = draw(st.lists(st.sampled_from(names), unique=True, max_size=4))
    table = {}
    for name in chosen:
        table[name] = draw(st.one_of(plausible(name, getattr(defaults, name)), wild)
                           if draw(st.integers(0, 9)) == 0 else plausible(name, getattr(defaults, name)))
    if draw(st.integers(0, 19)) == 0:
        table[draw(st.text(min_size=1, max_size=8))] = draw(wild)
    return table


@st.composite
def documents(draw) -> dict:
    doc: dict = {}
    for section in draw(st.lists(st.sampled_from(sorted(SECTIONS)), unique=True, max_size=4)):
        doc[section] = draw(section_tables(section)) if draw(st.integers(0, 29)) else draw(wild)
    if draw(st.integers(0, 29)) == 0:
        doc[draw(st.text(min_size=1, max_size=8))] = {}
    return doc


def assert_names_a_key_of(doc: dict, message: str) -> None:
    """A ConfigError names a section or key the document has, or a key that one of the
    document's keys requires (a cross-check such as 'elements.explicit is missing')."""
    sections = list(doc)
    keys = [f"{s}.{k}" for s, table in doc.items() if isinstance(table, dict) for k in table]
    if any(f"config section '[{s}]'" in message for s in sections):
        return
    if any(f"config key '{k}{tail}" in message for k in keys for tail in ("'", "[", ".")):
        return
    if any(f"config key '{s}'" in message for s in sections):
        return  # the section itself, e.g. "must be a table"
    cross = any(f"config key '{s}." in message for s in sections) and (
        any(k in message for k in keys) or "is missing" in message)
    assert cross, f"error does not name a key of the document: {message}"


@pytest.mark.slow
def test_config_loader_fuzz_returns_a_config_or_names_the_key():
    seen: collections.Counter = collections.Counter()

    @settings(max_examples=CONFIG_EXAMPLES, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(doc=documents())
    @example(doc={"zenoh": {"listen": ["tcp/0.0.0.0:7447"], "allow_non_loopback": True}})
    @example(doc={"elements": {"explicit": [{"u_mm": 1.0, "v_mm": 2.0}]}})
    def check(doc: dict) -> None:
        seen["inputs"] += 1
        try:
            cfg = parse_config(doc, source="<fuzz>")
        except ConfigError as exc:
            seen["refused"] += 1
            assert_names_a_key_of(doc, str(exc))
            return
        seen["accepted"] += 1
        # A valid config is what the daemon logs; it must read back the same (control
        # characters in strings: test_control_characters_round_trip below).
        effective = config_to_toml(cfg)
        if any(ord(c) < 32 and c != "\n" for c in effective):
            return
        again = parse_config(tomllib.loads(effective), source="<fuzz>")
        for section in SECTIONS:
            assert getattr(again, section) == getattr(cfg, section), section

    check()
    print(f"FIGURE config fuzz: {seen['inputs']} documents tried, {seen['accepted']} accepted, "
          f"{seen['refused']} refused with the key named, 0 other exceptions")
    assert seen["inputs"] >= CONFIG_EXAMPLES
    assert seen["accepted"] >= CONFIG_EXAMPLES // 20 and seen["refused"] >= CONFIG_EXAMPLES // 4


@pytest.mark.slow
def test_config_file_fuzz_mutated_demo_config():
    """Random edits of the demo config text: load_config either loads it or raises ConfigError
    (invalid TOML included), never anything else."""
    seen: collections.Counter = collections.Counter()
    edits = st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 2),
                               st.text(max_size=4).filter(_no_home_lookup)), min_size=1, max_size=4)

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.toml"

        @settings(max_examples=TOML_EXAMPLES, deadline=None, database=None)
        @given(edits=edits)
        def check(edits) -> None:
            text = DEMO_CONFIG
            for where, kind, s in edits:
                i = int(where * len(text))
                text = {0: text[:i] + s + text[i:], 1: text[:i] + text[i + len(s) + 1:],
                        2: text[:i] + s + text[i + len(s):]}[kind]
            path.write_text(text, encoding="utf-8")
            seen["inputs"] += 1
            try:
                load_config(path)
                seen["accepted"] += 1
            except ConfigError as exc:
                seen["refused"] += 1
                assert str(exc)

        check()
    print(f"FIGURE config file fuzz: {seen['inputs']} mutated demo configs, {seen['accepted']} loaded, "
          f"{seen['refused']} refused with ConfigError")
    assert seen["inputs"] >= TOML_EXAMPLES and seen["refused"] > 0


@pytest.mark.parametrize("section, key", [("zenoh", "config_file"), ("log", "directory"), ("state", "directory")])
def test_tilde_user_paths_are_config_errors(section, key):
    with pytest.raises(ConfigError, match=f"{section}.{key}"):
        parse_config({section: {key: "~no-such-user-skinmap/x"}})


def test_control_characters_are_refused_and_quotes_round_trip():
    with pytest.raises(ConfigError, match="state.directory.*control characters"):
        parse_config({"state": {"directory": "state\x1f"}})
    with pytest.raises(ConfigError, match="device.port.*control characters"):
        parse_config({"device": {"port": "/dev/tty\x00S0"}})
    cfg = parse_config({"state": {"directory": 'st"ate\\ü'}})
    assert parse_config(tomllib.loads(config_to_toml(cfg))).state == cfg.state


# ---------------------------------------------------------------------------------------------
# Stream decoder fuzz, counted (tests/test_protocol_stream.py checks the same kinds of
# property without recording how many inputs ran).


def _some_frames(seed: int) -> bytes:
    scan = p.Scan(seed, 1000 * seed, 5000, [[[[6_500_000 + seed] * 3] * 2] * 2] * 2)
    return p.encode_frame(scan, seed % 65536) + p.encode_frame(p.Ack(seed, int(p.MsgType.PING), b"ok"), 1)


@pytest.mark.slow
def test_stream_decoder_fuzz_counted():
    seen: collections.Counter = collections.Counter()

    @settings(max_examples=DECODER_EXAMPLES, deadline=None, database=None)
    @given(prefix=st.binary(max_size=600), seed=st.integers(0, 10_000),
           flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 7)), max_size=4),
           cuts=st.lists(st.integers(1, 97), max_size=6))
    def check(prefix: bytes, seed: int, flips, cuts) -> None:
        data = bytearray(prefix + _some_frames(seed) + _some_frames(seed + 1))
        for where, bit in flips:
            data[int(where * len(data))] ^= 1 << bit
        decoder = p.StreamDecoder()
        frames, pos = [], 0
        for size in cuts + [len(data)]:
            frames += decoder.feed(bytes(data[pos:pos + size]))  # must never raise
            pos += size
        seen["inputs"] += 1
        seen["bytes"] += len(data)
        seen["frames"] += len(frames)
        assert decoder.bytes_in == len(data) and decoder.frames_ok == len(frames)
        for f in frames:  # whatever is passed on decodes again to the same message
            assert p.decode_frame(f.raw).seq == f.seq

    check()
    print(f"FIGURE stream decoder fuzz: {seen['inputs']} inputs, {seen['bytes']} bytes, "
          f"{seen['frames']} frames passed on, 0 exceptions")
    assert seen["inputs"] >= DECODER_EXAMPLES


# ---------------------------------------------------------------------------------------------
# skinmapd --config: every invalid file exits non-zero naming the key, with nothing started.

# name: (section, lines added to it, what the error must name); section None = the whole file.
BAD_CONFIGS = {
    "unknown section": ("bogus", "x = 1", "[bogus]"),
    "unknown key": ("device", "speed = 3", "device.speed"),
    "wrong type": ("device", 'scan_rate_hz = "fast"', "device.scan_rate_hz"),
    "out of range": ("output", "status_rate_hz = 0", "output.status_rate_hz"),
    "not loopback listen": ("zenoh", 'listen = ["tcp/0.0.0.0:{zport}"]', "zenoh.listen"),
    "not loopback connect": ("zenoh", 'connect = ["tcp/10.1.2.3:{zport}"]', "zenoh.connect"),
    "network serial port": ("device", 'port = "socket://10.0.0.5:7600"', "device.port"),
    "cross-check": ("device", "reconnect_min_s = 5\nreconnect_max_s = 1", "device.reconnect_max_s"),
    "explicit element": ("elements", 'layout = "explicit"\n[[elements.explicit]]\nu_mm = 1',
                         "elements.explicit[0].v_mm"),
    "compression": ("log", 'compression = "gzip"', "log.compression"),
    "zenoh file missing": ("zenoh", 'config_file = "nowhere.json5"', "zenoh.config_file"),
    "invalid TOML": (None, "[device\nport = ", "not valid TOML"),
}


def config_text(scanner_port: int, zport: int, section: str | None, lines: str) -> str:
    """A good config (scanner and Zenoh on loopback, logs and state in the config's folder)
    with `lines` put into `section`, replacing the good key of the same name."""
    if section is None:
        return lines
    good = {
        "device": {"port": f'"socket://127.0.0.1:{scanner_port}"'},
        "zenoh": {"listen": f'["tcp/127.0.0.1:{zport}"]'},
        "log": {"directory": '"logs"'},
        "state": {"directory": '"state"'},
    }
    bad_keys = {line.split("=")[0].strip() for line in lines.splitlines() if "=" in line}
    out = []
    for name, table in good.items():
        out.append(f"[{name}]")
        out += [f"{k} = {v}" for k, v in table.items() if not (name == section and k in bad_keys)]
        if name == section:
            out.append(lines)
    if section not in good:
        out += [f"[{section}]", lines]
    return "\n".join(out) + "\n"


class ConnectionCounter:
    """A loopback listener standing in for the scanner: counts who connects."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.accepted = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
                self.accepted += 1
                conn.close()
            except OSError:
                pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


@pytest.mark.slow
def test_skinmapd_refuses_every_invalid_config_without_starting(tmp_path):
    scanner = ConnectionCounter()
    zport = free_port()
    runs = {}
    try:
        for name, (section, lines, _key) in BAD_CONFIGS.items():
            folder = tmp_path / name.replace(" ", "-")
            folder.mkdir()
            (folder / "skinmapd.toml").write_text(config_text(scanner.port, zport, section, lines.format(zport=zport)))
            runs[name] = (folder, subprocess.Popen(
                [sys.executable, "-m", "skinmap.daemon.service", "--config", str(folder / "skinmapd.toml")],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        # Control: the same file without the bad lines is valid, so each refusal is theirs.
        (tmp_path / "good.toml").write_text(config_text(scanner.port, zport, "device", ""))
        control = subprocess.run([sys.executable, "-m", "skinmap.daemon.service", "--config",
                                  str(tmp_path / "good.toml"), "--check"], capture_output=True, text=True, timeout=120)
        assert control.returncode == 0, control.stderr
        for name, (folder, proc) in runs.items():
            out, err = proc.communicate(timeout=120)
            key = BAD_CONFIGS[name][2]
            assert proc.returncode == 2, (name, proc.returncode, err)
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("skinmapd: ") and key in lines[0], (name, err)
            assert not (folder / "logs").exists() and not (folder / "state").exists(), name
            assert out == ""
    finally:
        for _folder, proc in runs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        scanner.close()
    assert scanner.accepted == 0, "a refused config must not open the scanner port"
    print(f"FIGURE config refusal: {len(BAD_CONFIGS)} invalid files, every one exit 2 naming the key, "
          f"no log/state folder, no scanner connection")


@pytest.mark.slow
def test_non_loopback_listen_is_only_accepted_when_the_config_says_so(tmp_path):
    cfg = tmp_path / "open.toml"
    cfg.write_text('[zenoh]\nlisten = ["tcp/0.0.0.0:7447"]\nallow_non_loopback = true\n')
    # --check only: this test never listens on anything but loopback.
    proc = subprocess.run([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg), "--check"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stderr


NON_LOOPBACK = ["tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/192.168.1.4:7447", "tcp/10.0.0.1:7447",
                "tcp/example.com:7447", "tcp/[fe80::1]:7447"]
LOOPBACK = ["tcp/127.0.0.1:7447", "tcp/localhost:7447", "tcp/[::1]:7447"]


@pytest.mark.parametrize("endpoint", NON_LOOPBACK)
@pytest.mark.parametrize("direction", ["listen", "connect"])
def test_non_loopback_refused_by_config_and_by_session_config(endpoint, direction):
    with pytest.raises(ConfigError) as info:
        parse_config({"zenoh": {direction: [endpoint]}})
    assert f"zenoh.{direction}" in str(info.value) and endpoint in str(info.value)
    assert "allow_non_loopback" in str(info.value)
    kwargs = {direction: [endpoint]}
    with pytest.raises(ValueError, match=re.escape(endpoint)):
        make_session_config(**kwargs)
    # Both accept it only when told explicitly (the session config is built, never opened).
    cfg = parse_config({"zenoh": {direction: [endpoint], "allow_non_loopback": True}})
    assert endpoint in getattr(cfg.zenoh, direction)
    make_session_config(**kwargs, allow_non_loopback=True)


@pytest.mark.parametrize("endpoint", LOOPBACK)
def test_loopback_accepted_by_config_and_by_session_config(endpoint):
    cfg = parse_config({"zenoh": {"listen": [endpoint]}})
    assert cfg.zenoh.listen == (endpoint,)
    conf = make_session_config(listen=[endpoint])
    assert endpoint in conf.get_json("listen/endpoints")
    assert conf.get_json("scouting/multicast/enabled") == "false"
