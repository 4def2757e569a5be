"""The `skinmap` tool against a live gateway and the log it wrote."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest
from conftest import WAIT_S, free_port, running_gateway, wait_until

from skinmap.daemon.cli import main as skinmap_main
from skinmap.emulator.device import ScannerSpec
from skinmap.emulator.emulator import Emulator
from skinmap.emulator.physics import make_shape
from skinmap.emulator.transport import PtyTransport

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def session_run(tmp_path_factory):
    """Run emulator → gateway for a few seconds; run echo/info meanwhile; keep the log."""
    tmp = tmp_path_factory.mktemp("cli")
    emu = Emulator(ScannerSpec(n=4, m=5, scan_rate_hz=30.0, seed=5), make_shape("cylinder", radius=40.0),
                   PtyTransport(link=tmp / "tty"))
    emu.start()
    zport = free_port()
    cfg_path = tmp / "skinmapd.toml"
    cfg_path.write_text(f"""
[device]
port = "{tmp / 'tty'}"
name = "cli"
scan_rate_hz = 30
[output]
rate_hz = 15
[zenoh]
listen = ["tcp/127.0.0.1:{zport}"]
[log]
directory = "logs"
[state]
directory = "state"
""")
    from skinmap.daemon.config import load_config

    cfg = load_config(cfg_path)
    outputs: dict[str, object] = {}
    try:
        with running_gateway(cfg) as gw:
            # 20 processed scans: a log with content; waited for, however long a loaded machine takes
            wait_until(lambda: gw.stats.results >= 20, 4 * WAIT_S)
            outputs["gateway_results"] = gw.stats.results
            outputs["info_rc"] = skinmap_main(["info", "--connect", f"tcp/127.0.0.1:{zport}", "--device", "cli", "--json"])
            outputs["echo_rc"] = skinmap_main(["echo", "--connect", f"tcp/127.0.0.1:{zport}", "--device", "cli", "--duration", "1.0"])
    finally:
        emu.stop()
    return tmp, cfg_path, outputs


def test_info_and_echo_talk_to_a_running_daemon(session_run, capsys):
    _tmp, _cfg, outputs = session_run
    assert outputs["gateway_results"] >= 20
    assert outputs["info_rc"] == 0 and outputs["echo_rc"] == 0


def test_inspect_lists_topics_and_draws_a_png(session_run, capsys, tmp_path):
    tmp, _cfg, _ = session_run
    log = next((tmp / "logs").glob("*.mcap"))
    png = tmp_path / "surface.png"
    assert skinmap_main(["inspect", str(log), "--png", str(png)]) == 0
    out = capsys.readouterr().out
    for topic in ("/raw", "/strains", "/elements", "/surface", "/status", "/config"):
        assert topic in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from skinmap.daemon.mcapsnapshot import render_surface_png

    snap = render_surface_png(log, None, tmp_path / "again.png")  # what the picture shows
    assert snap.sigma.shape == snap.nodes.shape[:2] and np.isfinite(snap.sigma).all()
    assert snap.elements is not None and snap.elements.count > 0 and snap.elements.valid.any()


def test_replay_reproduces_the_live_results(session_run, capsys):
    tmp, _cfg, _ = session_run
    log = next((tmp / "logs").glob("*.mcap"))
    assert skinmap_main(["replay", str(log), "--quiet"]) == 0
    assert "IDENTICAL" in capsys.readouterr().out


def test_recover_rewrites_a_cut_log(session_run, capsys, tmp_path):
    tmp, _cfg, _ = session_run
    log = next((tmp / "logs").glob("*.mcap"))
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap.active"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    out_path = tmp_path / "recovered.mcap"
    assert skinmap_main(["recover", str(cut), "-o", str(out_path)]) == 0
    assert "recovered" in capsys.readouterr().out
    # The recovered file is a finished MCAP that the regular reader accepts.
    from mcap.reader import make_reader

    with open(out_path, "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages()) > 0


def test_tare_from_log_refuses_a_bent_sheet_and_a_stored_tare_is_used(session_run, capsys):
    tmp, cfg_path, _ = session_run
    log = next((tmp / "logs").glob("*.mcap"))
    # the session's sheet lies on a 40 mm cylinder: no tare
    assert skinmap_main(["tare", "--config", str(cfg_path), "--from-log", str(log), "--scans", "10"]) == 1
    err = capsys.readouterr().err
    assert "not a tare" in err and "bent" in err and "nothing written" in err
    assert not list((tmp / "state").glob("tare-*.json"))

    from skinmap.strains import compute_tare, save_tare
    from skinmap.daemon.replay import resistances_from_log as scans_of

    serial, scans = scans_of(log, count=10)
    save_tare(tmp / "state", serial, compute_tare(np.stack(scans)), len(scans))
    tare_files = list((tmp / "state").glob("tare-*.json"))
    assert len(tare_files) == 1
    doc = json.loads(tare_files[0].read_text())
    assert doc["scans"] == 10 and doc["shape"] == [2, 2, 4, 5]
    assert all(v is None or 4.0 < v < 10.0 for v in doc["base_resistance_ohm"])

    from skinmap.daemon.config import load_config
    from skinmap.daemon.device_setup import calibration_for_hello
    from skinmap.daemon.mcapread import iter_messages_file_order
    from skinmap.protocol import Hello, StreamDecoder

    hello = None
    decoder = StreamDecoder()
    for m in iter_messages_file_order(log):
        if m.topic == "/raw":
            for f in decoder.feed(m.data):
                if isinstance(f.msg, Hello):
                    hello = f.msg
                    break
        if hello is not None:
            break
    cal = calibration_for_hello(hello, load_config(cfg_path))
    assert cal.source.startswith("tare")
    assert not np.allclose(cal.base_resistance, hello.base_resistance_ohm())


def test_bad_log_path_is_a_clear_error(capsys, tmp_path):
    assert skinmap_main(["inspect", str(tmp_path / "missing.mcap")]) == 1
    assert "missing.mcap" in capsys.readouterr().err


def test_healthy_log_inspects_clean_and_passes_the_doctor(session_run, capsys):
    """The gateway's own log: no false seq or time gaps at the configured decimation, and the
    MCAP doctor finds no error.  (On a busy machine the host clock may pass a scan by, 39 -> 42
    at step 2: a real gap the report must name; a false one is a step the decimation itself
    makes, or a silence shorter than two of the topic's own periods.)"""
    import os
    import subprocess
    import sys

    from skinmap.daemon.mcapinspect import inspect

    tmp, _cfg, _ = session_run
    log = next((tmp / "logs").glob("*.mcap"))
    assert skinmap_main(["inspect", str(log)]) == 0
    out = capsys.readouterr().out
    assert "processed 15 Hz (seq step 2)" in out
    report = inspect(log)
    strains = report.topics["/strains"]
    assert strains.expected_hz == 15 and strains.count > 10
    for gap in report.sequence_gaps:
        # a scan passed by, never the decimation's own step (a false gap on every message)
        assert gap.missing > 0 and gap.next_seq - gap.after_seq > gap.expected_step, (gap, out)
        if gap.topic == "/strains":
            assert gap.expected_step == 2, (gap, out)
    for st in report.topics.values():
        if st.expected_hz:
            assert st.gap_threshold_s >= 2.0 / st.expected_hz, (st.topic, st.gap_threshold_s, st.expected_hz)
        for a, b in st.time_gaps:
            assert (b - a) * 1e-9 > st.gap_threshold_s, (st.topic, a, b)
    doctor = os.path.join(os.path.dirname(sys.executable), "pymcap-cli")
    result = subprocess.run([doctor, "doctor", str(log), "--format", "jsonl"], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0 and '"severity":"error"' not in result.stdout, result.stdout[-2000:]


def test_replay_publish_announces_where_answers_info_and_echo_shows_no_false_latency(
        session_run, capsys):
    import threading

    from skinmap.client import SkinmapClient

    tmp, _cfg, _ = session_run
    log = next((tmp / "logs").glob("*.mcap"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rc: list[int] = []
    # at a quarter of the recorded speed the replay still publishes while echo's own session
    # starts, also on a loaded machine (at full speed a short log could end before it)
    replay = threading.Thread(target=lambda: rc.append(skinmap_main(
        ["replay", str(log), "--publish", "--listen", endpoint, "--speed", "0.25", "--quiet"])))
    replay.start()
    try:
        with SkinmapClient([endpoint], prefix="skinmap-replay", device="cli") as client:
            deadline = time.monotonic() + 30
            info = None
            while info is None and time.monotonic() < deadline:
                try:
                    info = client.info(timeout=1.0)
                except LookupError:
                    time.sleep(0.1)
            assert info is not None and info["source"] == f"replay of {log.name}"
            assert info["rows"] == 4 and info["cols"] == 5
        assert skinmap_main(["echo", "--connect", endpoint, "--prefix", "skinmap-replay",
                             "--device", "cli", "--duration", "1.0"]) == 0
    finally:
        replay.join(timeout=180)
    captured = capsys.readouterr()
    assert f"publishing on {endpoint} under 'skinmap-replay/cli'" in captured.err
    assert "latency is shown only for live data" in captured.err
    lines = [line for line in captured.out.splitlines() if line.startswith("seq")]
    assert lines and all("device t" in line and "latency" not in line for line in lines)
    assert rc == [0]


def test_the_demo_narrows_its_element_row_to_an_array_too_small_for_it():
    """The demo's 32-element row spans 46.5 mm: on 2×2 (cells 12 mm apart) it is narrowed to
    their span, on 5×5 and larger it stays (cmd_demo narrows its own config only, never one given
    with --config)."""
    import tomllib

    from skinmap.daemon.cli import _demo_elements_on_sheet
    from skinmap.daemon.config import DEMO_CONFIG, parse_config

    cfg = parse_config(tomllib.loads(DEMO_CONFIG), source="demo.toml", text=DEMO_CONFIG)
    assert (cfg.elements.cols - 1) * cfg.elements.pitch_u_mm > 12.0
    small = _demo_elements_on_sheet(cfg, "2x2")
    assert (small.elements.cols - 1) * small.elements.pitch_u_mm == pytest.approx(12.0)
    assert small.elements.cols == cfg.elements.cols and small.zenoh == cfg.zenoh
    for size in ("5x5", "16x16", "nonsense"):
        assert _demo_elements_on_sheet(cfg, size) is cfg
