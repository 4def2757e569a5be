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

from skinmap.daemon.cli import main as skinmap_main
from skinmap.daemon.mcapinspect import NotRegularFileError, inspect, iter_messages_file_order, recover
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
