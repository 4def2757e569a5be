"""The USTB/UFF probe example: angle convention and end-to-end run over loopback."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from skinmap.wire import messages as msg

_PATH = Path(__file__).resolve().parents[1] / "docs" / "examples" / "uff_probe.py"
_spec = importlib.util.spec_from_file_location("uff_probe", _PATH)
uff_probe = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(uff_probe)


def test_angles_follow_the_ustb_point_convention():
    rng = np.random.default_rng(3)
    n = rng.normal(size=(20, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.1
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    theta, phi = uff_probe.normal_angles(n)
    rebuilt = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(phi),
                               np.cos(theta) * np.cos(phi)])
    np.testing.assert_allclose(rebuilt, n, atol=1e-12)
    theta, phi = uff_probe.normal_angles([[0, 0, 1], [1, 0, 1], [0, 2, 2]])
    np.testing.assert_allclose(theta, [0, np.pi / 4, 0], atol=1e-12)
    np.testing.assert_allclose(phi, [0, 0, np.pi / 4], atol=1e-12)


def test_probe_geometry_from_message():
    pos = np.array([[0.001, 0.002, -0.003], [0.004, 0.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [np.sin(0.2), 0.0, np.cos(0.2)]])
    buf = msg.encode_elements(3, 0, 0, pos, nrm, np.zeros(2), np.array([1, 0]))
    geometry = uff_probe.probe_from_message(msg.decode_elements(buf), 0.002, 0.01)
    assert geometry.shape == (2, 7)
    np.testing.assert_array_equal(geometry[:, :3], pos)
    np.testing.assert_allclose(geometry[:, 3], [0.0, 0.2])
    np.testing.assert_array_equal(geometry[:, 5:], [[0.002, 0.01], [0.002, 0.01]])
    text = uff_probe.format_probe(geometry, np.array([True, False]))
    assert "(invalid)" in text.splitlines()[2] and "11.459" in text


def test_probe_geometry_errors():
    with pytest.raises(ValueError, match="zero"):
        uff_probe.normal_angles([[0, 0, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match="positions"):
        uff_probe.uff_probe_geometry(np.zeros((2, 2)), np.zeros((2, 2)), 1e-3, 1e-3)
    with pytest.raises(ValueError, match="width"):
        uff_probe.uff_probe_geometry(np.zeros((1, 3)), [[0, 0, 1]], 0.0, 1e-3)


def test_demo_runs_end_to_end_over_loopback(capsys):
    assert uff_probe.main(["--demo", "--device", "demo-probe"]) == 0
    out = capsys.readouterr().out
    assert "32 elements, 32 valid" in out
    assert "30.080" in out  # outermost element of the 40 mm cylinder: 21 mm arc -> 30.08 deg


def test_cli_reports_a_missing_daemon(capsys):
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert uff_probe.main(["--connect", f"tcp/127.0.0.1:{port}", "--timeout", "0.3"]) == 1
    assert "no info available" in capsys.readouterr().err
