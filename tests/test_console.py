"""The live status console: a fixed panel on a terminal, one short line on a pipe."""
from __future__ import annotations

import io

import numpy as np

from skinmap.daemon.console import StatusConsole, shape_summary, status_line

STATUS = {"device": "demo", "link_state": "streaming", "seq": 1234, "scan_rate_hz": 50.0,
          "publish_rate_hz": 10.0, "solver_time_ms": 12.5, "latency_ms_p99": 80.0,
          "frames_dropped": 0, "crc_errors": 0, "reconnects": 0, "log_state": "recording",
          "warnings": ["2 scan(s) lost on the link in the last 10 s"]}


def test_a_pipe_gets_one_short_line_per_report():
    out = io.StringIO()
    shape = shape_summary(np.zeros((3, 3, 3)) + [0, 0, 1.5], np.array([[-20.0, 0, 1], [20, 0, 2]]))
    console = StatusConsole(out)
    assert not console.panel
    console.update(STATUS, shape)
    console.update(STATUS, shape)
    lines = out.getvalue().splitlines()
    assert len(lines) == 2 and all(len(line) <= 120 for line in lines)
    assert "seq 1234" in lines[0] and "WARN 1" in lines[0] and "+1.5" in lines[0]
    assert lines[0] == status_line(STATUS, shape)


def test_a_terminal_gets_a_panel_and_other_lines_print_above_it():
    out = io.StringIO()
    console = StatusConsole(out, force_panel=True)
    try:
        console.update(STATUS, shape_summary(None, None))
        print("[emulator] a line from the emulator")
        console.update({**STATUS, "seq": 1240}, {})
    finally:
        console.close()
    text = out.getvalue()
    assert "skinmapd demo" in text and "1240" in text and "lost on the link" in text
    assert "[emulator] a line from the emulator" in text
    assert text.index("[emulator]") < text.rindex("1240")  # above the last panel
