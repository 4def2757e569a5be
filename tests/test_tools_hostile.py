"""Hostile inputs for the log tools (inspect, replay, recover) and for the published data.

The crafted files come from bench/hostile_tools.py, which also measures what each costs.
Nothing here asserts a time or a memory figure: only what the tools report and that they return.
"""
from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import pytest
from conftest import free_port, wait_until

from skinmap.daemon.cli import main as skinmap_main
from skinmap.daemon.mcapinspect import inspect
from skinmap.daemon.mcapread import NotRegularFileError, iter_messages_file_order
from skinmap.daemon.mcaprecover import recover
from skinmap.daemon.replay import replay_log

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import hostile_tools as hostile  # noqa: E402

MiB = 1024 * 1024


def log_texts(path: Path) -> list[str]:
    return [i.text for i in inspect(path).issues if i.source == "/log"]


# ------------------------------------------------------------------------------------------
# decompression bombs and oversized records


def test_chunk_declaring_more_than_the_limit_is_skipped_and_the_rest_read(tmp_path):
    path = hostile.write_mcap(tmp_path / "bomb.mcap", [hostile.bomb_chunk(100 * MiB)])
    report = inspect(path)
    assert report.skipped_count == 1
    assert report.skipped[0].startswith("chunk record at offset ")
    assert "declares 100.0 MiB uncompressed, over the 64.0 MiB limit" in report.skipped[0]
    assert report.end.complete
    assert report.topics["/log"].count == 2  # the chunks before and after the bomb
    assert [t.split("] ")[1] for t in log_texts(path)] == ["before", "after"]
    assert "1 record(s) skipped unread" in report.format()


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_chunk_that_decompresses_past_its_declared_size_is_skipped(tmp_path, compression):
    path = hostile.write_mcap(tmp_path / "lie.mcap",
                              [hostile.bomb_chunk(32 * MiB, declared=1024, compression=compression)])
    report = inspect(path)
    assert report.skipped == [f"chunk record at offset {report.skipped[0].split()[4]} skipped: "
                              "decompresses to more than its declared 1024 bytes"]
    assert report.topics["/log"].count == 2


@pytest.mark.slow
def test_the_limit_is_configurable_from_the_command_line(tmp_path, capsys):
    path = hostile.write_mcap(tmp_path / "bomb.mcap", [hostile.bomb_chunk(4 * MiB)])
    assert inspect(path).skipped_count == 0  # under the default limit: read (4 MiB of zeros)
    assert skinmap_main(["inspect", str(path), "--max-record-mb", "1"]) == 0
    out = capsys.readouterr().out
    assert "declares 4.0 MiB uncompressed, over the 1.0 MiB limit" in out
    assert skinmap_main(["inspect", str(path), "--max-record-mb", "0"]) == 1
    assert "--max-record-mb must be between" in capsys.readouterr().err


def test_recover_and_replay_skip_the_bomb_and_keep_the_rest(tmp_path):
    path = hostile.write_mcap(tmp_path / "bomb.mcap", [hostile.bomb_chunk(100 * MiB)])
    rec = recover(path, tmp_path / "out.mcap")
    assert rec.topics == {"/log": 2} and rec.skipped_count == 1
    assert "record(s) not recovered (too large)" in rec.format()
    assert [t.split("] ")[1] for t in log_texts(tmp_path / "out.mcap")] == ["before", "after"]
    rep = replay_log(path)
    assert rep.problems == list(rec.skipped)
    assert "over the 64.0 MiB limit" in rep.format()


def test_oversized_attachment_record_is_skipped_unread(tmp_path):
    path = hostile.oversized_attachment(tmp_path / "big.mcap", 1024 * MiB)  # sparse
    report = inspect(path)
    assert report.skipped_count == 1
    assert "attachment record at offset" in report.skipped[0]
    assert "1024.0 MiB, over the 64.0 MiB limit" in report.skipped[0]
    assert report.attachments == [] and report.topics["/log"].count == 2 and report.end.complete


# ------------------------------------------------------------------------------------------
# not a regular file


def _finishes(target, timeout: float = 20.0) -> tuple[bool, BaseException | None]:
    outcome: list[BaseException | None] = []

    def run() -> None:
        try:
            target()
            outcome.append(None)
        except BaseException as exc:  # noqa: BLE001 - handed back to the test
            outcome.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout)
    return (not t.is_alive()), (outcome[0] if outcome else None)


@pytest.fixture
def not_files(tmp_path) -> dict[str, tuple[Path, str]]:
    fifo = tmp_path / "log.fifo"
    os.mkfifo(fifo)
    folder = tmp_path / "folder.mcap"
    folder.mkdir()
    return {"fifo": (fifo, "a FIFO (named pipe)"), "folder": (folder, "a folder"),
            "dev-zero": (Path("/dev/zero"), "a character device")}


@pytest.mark.parametrize("kind", ["fifo", "folder", "dev-zero"])
@pytest.mark.parametrize("tool", ["inspect", "recover", "replay", "messages"])
def test_non_regular_files_are_refused_at_once(tmp_path, not_files, kind, tool):
    path, what = not_files[kind]
    calls = {"inspect": lambda: inspect(path), "recover": lambda: recover(path, tmp_path / "out.mcap"),
             "replay": lambda: replay_log(path), "messages": lambda: list(iter_messages_file_order(path))}
    done, exc = _finishes(calls[tool])
    assert done, f"{tool} of {kind} did not return"
    assert isinstance(exc, NotRegularFileError), exc
    assert str(exc) == f"{path}: is {what}, not a regular MCAP log file"
    assert not (tmp_path / "out.mcap").exists() and not (tmp_path / "out.mcap.partial").exists()


def test_cli_names_a_fifo_in_one_line(tmp_path, not_files, capsys):
    path, _ = not_files["fifo"]
    done, _ = _finishes(lambda: skinmap_main(["recover", str(path), "-o", str(tmp_path / "o.mcap")]))
    assert done
    err = capsys.readouterr().err
    assert err == f"skinmap recover: {path}: is a FIFO (named pipe), not a regular MCAP log file\n"


# ------------------------------------------------------------------------------------------
# deeply nested JSON


def test_deeply_nested_json_is_one_unreadable_record_and_the_rest_is_inspected(tmp_path):
    path = hostile.nested_json_log(tmp_path / "nested.mcap", depth=100_000)
    report = inspect(path)
    unreadable = [i for i in report.issues if i.text.startswith("unreadable record")]
    assert [(i.source, i.level) for i in unreadable] == [("/status", "ERROR"), ("/log", "ERROR")]
    assert "JSON nested too deeply to read" in unreadable[0].text
    texts = [i.text for i in report.issues]
    assert "warnings: ['readable warning']" in texts and "healthy is false" in texts
    assert [t.split("] ")[1] for t in texts if t.startswith("[hostile]")] == ["before", "after"]
    assert report.topics["/status"].count == 2


# ------------------------------------------------------------------------------------------
# replay of a log with hostile /config records


@pytest.fixture(scope="module")
def bad_configs(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("hostile-config")
    real = hostile.record_real_log(tmp / "real")
    return {"real": real, **hostile.bad_config_copies(real, tmp)}


@pytest.mark.slow
def test_unusable_config_records_are_named_and_the_rest_replayed(bad_configs):
    clean = replay_log(bad_configs["real"])
    assert clean.identical and not clean.problems
    report = replay_log(bad_configs["list-inserted"])
    assert report.identical and report.compared == clean.compared
    assert len(report.problems) == 2
    first, second = report.problems
    assert first.startswith("unusable /config message #")
    assert first.endswith(": is a list, expected an object with config_text and calibration; "
                          "the config before it stays in force")
    assert second.endswith(": calibration is a list, expected an object; the config before it stays in force")


@pytest.mark.slow
@pytest.mark.parametrize("name, reason", [("only-list", "is a list, expected an object"),
                                          ("calibration-list", "calibration is a list, expected an object")])
def test_replay_without_a_usable_config_says_so_in_one_line(bad_configs, capsys, name, reason):
    report = replay_log(bad_configs[name])
    assert report.processed == 0 and report.unconfigured > 0
    assert len(report.problems) == 1 and reason in report.problems[0]
    assert skinmap_main(["replay", str(bad_configs[name]), "-q"]) == 1
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    lines = [line for line in captured.out.splitlines() if "unusable /config" in line]
    assert len(lines) == 1 and reason in lines[0]
    assert f"{report.unconfigured} processed scans not replayed: no usable /config before them" in captured.out


# ------------------------------------------------------------------------------------------
# forged data on the gateway's key space


def _demo_config(endpoint: str, **zenoh_keys):
    """The embedded demo config, listening on `endpoint` (loopback, free port)."""
    import dataclasses
    import tomllib

    from skinmap.daemon.config import DEMO_CONFIG, parse_config

    cfg = parse_config(tomllib.loads(DEMO_CONFIG), source="<demo>", text=DEMO_CONFIG)
    return dataclasses.replace(cfg, zenoh=dataclasses.replace(cfg.zenoh, listen=(endpoint,), **zenoh_keys))


def _elements(seq: int, k: int = 8, *, nan: bool = False) -> bytes:
    import numpy as np

    from skinmap.wire import messages as msg

    pos = np.full((k, 3), np.nan) if nan else np.arange(3 * k, dtype=np.float64).reshape(k, 3) * 1e-3
    return msg.encode_elements(seq, seq, 10**18 + seq, pos, np.tile([0.0, 0.0, 1.0], (k, 1)),
                               np.full(k, 1e-4), np.full(k, msg.ElementFlag.VALID, np.uint8))


class _ForgeryRun:
    """The gateway's Zenoh session (as skinmapd opens it from the config) publishing real
    elements, a watcher subscribing with a plain Zenoh session, and a foreign client-mode
    session on the same loopback endpoint putting forged elements and serving forged info."""

    def __init__(self, cfg) -> None:
        import zenoh

        from skinmap.daemon.service import open_zenoh
        from skinmap.daemon.zenoh_io import SkinmapPublisher, make_session_config

        self.endpoint = cfg.zenoh.listen[0]
        self._gateway_ctx = open_zenoh(cfg)
        self.gateway = self._gateway_ctx.__enter__()
        self.publisher = SkinmapPublisher(self.gateway, "skinmap", "demo")
        self.publisher.set_info({"device": "demo", "rows": 2, "cols": 2, "pitch_m": 0.01,
                                 "elements": {"count": 8}, "calibration": {}, "versions": {}})
        client_cfg = lambda: make_session_config([], [self.endpoint], mode="client")  # noqa: E731
        self.watcher = zenoh.open(client_cfg())
        self.forger = zenoh.open(client_cfg())
        self.seen = {"forged": 0, "real": 0}
        self.forged = _elements(7, nan=True)
        self._sub = self.watcher.declare_subscriber("skinmap/demo/elements", self._count)
        self._fake_info = self.forger.declare_queryable(
            "skinmap/demo/info", lambda q: q.reply("skinmap/demo/info", b'{"forged": true}'))
        self._fake_token = self.forger.liveliness().declare_token("skinmap/demo/forged-alive")

    def tokens(self) -> list[str]:
        return sorted(str(r.ok.key_expr) for r in self.watcher.liveliness().get("skinmap/demo/**", timeout=2.0)
                      if r.ok is not None)

    def _count(self, sample) -> None:
        self.seen["forged" if sample.payload.to_bytes() == self.forged else "real"] += 1

    def publish_until_seen(self, seq: int) -> bool:
        return wait_until(lambda: (self.publisher.publish_elements(_elements(seq)), self.seen["real"] > 0)[1])

    def forge(self, n: int) -> None:
        import time

        for _ in range(n):
            self.forger.put("skinmap/demo/elements", self.forged)
            time.sleep(0.002)
        self.forger.delete("skinmap/demo/elements")

    def close(self) -> None:
        self._fake_token.undeclare()
        self._fake_info.undeclare()
        self._sub.undeclare()
        self.forger.close()
        self.watcher.close()
        self.publisher.close()
        self._gateway_ctx.__exit__(None, None, None)


@pytest.mark.parametrize("guard", [True, False])
def test_foreign_puts_on_the_gateway_key_space_are_dropped_by_default(guard):
    """With the demo config a foreign session's forged elements never reach a subscriber; with
    `deny_remote_writes = false` they do (control case: the check can fail)."""
    import time

    cfg = _demo_config(f"tcp/127.0.0.1:{free_port()}", **({} if guard else {"deny_remote_writes": False}))
    assert cfg.guarded_key_expr() == ("skinmap/demo/**" if guard else None)
    run = _ForgeryRun(cfg)
    try:
        assert run.publish_until_seen(1), "the watcher never received the gateway's elements"
        # the forger's puts go where a subscriber is: wait until it knows of the watcher's
        probe = run.forger.declare_publisher("skinmap/demo/elements")
        assert wait_until(lambda: probe.matching_status.matching)
        probe.undeclare()
        run.forge(100)
        run.publisher.publish_elements(_elements(2))  # after the forged ones on the same links
        time.sleep(0.5)
        def info_replies() -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in run.watcher.get("skinmap/demo/info", timeout=2.0)
                    if r.ok is not None]

        replies = info_replies()
        if guard:
            assert run.seen["forged"] == 0
            assert len(replies) == 1 and b"forged" not in replies[0]  # the gateway's own info only
            assert run.tokens() == ["skinmap/demo/alive"]
        else:
            assert wait_until(lambda: run.seen["forged"] == 100)
            # (a loaded machine may answer the first query before the forged queryable is known)
            assert any(b"forged" in r for r in replies) or wait_until(
                lambda: any(b"forged" in r for r in info_replies()))
            assert run.tokens() == ["skinmap/demo/alive", "skinmap/demo/forged-alive"]
        assert run.seen["real"] >= 2
    finally:
        run.close()


def test_guard_keeps_a_config_file_with_its_own_access_control():
    import json

    from skinmap.daemon.zenoh_io import make_session_config

    production = Path(__file__).resolve().parents[1] / "config" / "zenoh-production.json5"
    kept = make_session_config(config_file=production, allow_non_loopback=True, deny_remote_writes="skinmap/**")
    assert json.loads(kept.get_json("access_control/default_permission")) == "deny"
    added = make_session_config(["tcp/127.0.0.1:0"], deny_remote_writes="skinmap/demo/**")
    acl = json.loads(added.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "allow"
    assert acl["rules"][0]["key_exprs"] == ["skinmap/demo/**"] and acl["rules"][0]["flows"] == ["ingress"]
    assert json.loads(make_session_config([], []).get_json("access_control/enabled")) is False


def test_client_rejects_forged_elements_and_names_why():
    """Guard off, so forged puts arrive: SkinmapClient hands out only the real elements and
    counts and names every forged one it dropped."""
    from skinmap.client import SkinmapClient

    cfg = _demo_config(f"tcp/127.0.0.1:{free_port()}", deny_remote_writes=False)
    run = _ForgeryRun(cfg)
    try:
        with SkinmapClient([run.endpoint], device="demo", mode="client") as client:
            client.subscribe("elements")
            assert run.publish_until_seen(1)
            probe = run.forger.declare_publisher("skinmap/demo/elements")
            assert wait_until(lambda: probe.matching_status.matching)
            probe.undeclare()
            got = []
            seq = 10
            run.forge(5)
            while len(got) < 3 and seq < 200:
                run.publisher.publish_elements(_elements(seq))
                seq += 1
                try:
                    got.append(client.elements(timeout=0.2))
                except TimeoutError:
                    pass
            assert len(got) == 3 and all(m.valid.all() and m.positions[0, 2] == 0.002 for m in got)

            def drained() -> bool:
                try:
                    client.elements(timeout=0.05)
                except TimeoutError:
                    pass
                return client.rejected("elements") == 6

            assert wait_until(drained)  # 5 forged puts and the forged delete (an empty payload)
            reasons = client.rejections("elements")
            assert reasons[:5] == ["elements: element 0 is flagged VALID but its position, normal, "
                                   "uncertainty or scatter is not finite"] * 5
            assert reasons[5] == "truncated message: 0 bytes, header needs 32"
    finally:
        run.close()


def test_check_message_applies_the_layout_rules():
    import numpy as np

    from skinmap.wire import messages as msg
    from skinmap.client import RejectedMessage, check_message

    k = 4
    pos = np.zeros((k, 3))
    nrm = np.tile([0.0, 0.0, 1.0], (k, 1))
    sig = np.full(k, 1e-4)
    flags = np.full(k, msg.ElementFlag.VALID, np.uint8)

    def enc(p=pos, n=nrm, s=sig, f=flags, c=None):
        return msg.encode_elements(1, 2, 3, p, n, s, f, c)

    assert check_message("elements", enc()).count == k
    nan_clear = pos.copy()
    nan_clear[2] = np.nan
    cleared = flags.copy()
    cleared[2] = msg.ElementFlag.DEGRADED
    assert check_message("elements", enc(p=nan_clear, f=cleared)).count == k  # NaN allowed when not VALID
    # every flag the wire format defines is accepted: an ambiguous frame is no malformed one
    every_flag = np.full(k, sum(int(f) for f in msg.ElementFlag), np.uint8)
    assert check_message("elements", enc(f=every_flag)).count == k
    assert check_message("elements", enc(f=flags | msg.ElementFlag.AMBIGUOUS)).count == k
    cases = [(enc(p=nan_clear), "element 2 is flagged VALID but its position"),
             (enc(n=nrm * 2), "element 0 is flagged VALID but its normal is not a unit vector"),
             (enc(s=-sig), "element 0 has a negative uncertainty"),
             (enc(c=-sig), "element 0 has a negative uncertainty or scatter"),
             (enc(c=np.full(k, np.nan)), "element 0 is flagged VALID but its position, normal, uncertainty or scatter"),
             (enc(f=flags | 0x40), "element 0 has unknown flag bits 0x41")]
    for payload, reason in cases:
        with pytest.raises(RejectedMessage, match=reason):
            check_message("elements", payload)
    reserved = bytearray(enc())
    reserved[6] = 1
    with pytest.raises(RejectedMessage, match="reserved header bytes"):
        check_message("elements", bytes(reserved))
    with pytest.raises(msg.MessageError, match="counts imply"):
        good = bytearray(enc())
        good[32] = k + 1  # K disagrees with the header's length
        check_message("elements", bytes(good))
    up = np.zeros((2, 2, 2))
    up[0, 1, 1] = np.inf
    gf = np.full((2, 2, 2), msg.GaugeFlag.UPPER_VALID | msg.GaugeFlag.LOWER_VALID, np.uint8)
    with pytest.raises(RejectedMessage, match=r"upper gauge \[0, 1, 1\] is flagged valid but not finite"):
        check_message("strains", msg.encode_strains(1, 2, 3, up, np.zeros((2, 2, 2)), gf))
    nodes = np.zeros((2, 2, 3))
    nodes[1, 0, 2] = np.nan
    with pytest.raises(RejectedMessage, match="surface: a node is not finite"):
        check_message("surface", msg.encode_surface(1, 2, 3, nodes, np.tile([0.0, 0.0, 1.0], (2, 2, 1)),
                                                    np.zeros((2, 2))))


def test_the_documented_non_python_client_config_is_loopback_only_and_receives():
    """docs/examples/zenoh-client.json5, as docs/zenoh.md shows it, opens a client session that
    receives the daemon's elements (its endpoint swapped for a free loopback port)."""
    import json

    import zenoh

    from skinmap.daemon.zenoh_io import SkinmapPublisher, make_session_config, open_session

    example = Path(__file__).resolve().parents[1] / "docs" / "examples" / "zenoh-client.json5"
    text = example.read_text()
    assert text[text.index("{"):].strip() in (Path(__file__).resolve().parents[1] / "docs" / "zenoh.md").read_text()
    config = zenoh.Config.from_file(str(example))
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    got = []
    with open_session(make_session_config([endpoint], [], deny_remote_writes="skinmap/demo/**")) as daemon:
        publisher = SkinmapPublisher(daemon, "skinmap", "demo")
        with open_session(config) as session:
            sub = session.declare_subscriber("skinmap/demo/elements", lambda s: got.append(s.payload.to_bytes()))
            assert wait_until(lambda: (publisher.publish_elements(_elements(3)), bool(got))[1])
            sub.undeclare()
        publisher.close()
    assert got[0] == _elements(3)
