"""Config validation: every bad value is refused with a message naming key, value and rule."""
from pathlib import Path

import pytest

from skinmap.daemon.config import DEMO_CONFIG, ConfigError, load_config, parse_config

ROOT = Path(__file__).resolve().parents[1]


def test_demo_file_matches_embedded_default():
    assert (ROOT / "config" / "demo.toml").read_text() == DEMO_CONFIG
    cfg = load_config(ROOT / "config" / "demo.toml")
    assert cfg.device.port.startswith("socket://127.0.0.1:")
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in cfg.zenoh.listen)


def test_production_example_is_valid():
    cfg = load_config(ROOT / "config" / "production.toml")
    assert cfg.zenoh.allow_non_loopback
    assert cfg.device.port.startswith("/dev/")


def test_defaults_are_loopback():
    cfg = parse_config({})
    assert cfg.zenoh.listen == ("tcp/127.0.0.1:7447",)
    assert not cfg.zenoh.allow_non_loopback


@pytest.mark.parametrize(
    "doc, key, fragment",
    [
        ({"device": {"scan_rate_hz": -5}}, "device.scan_rate_hz", "> 0"),
        ({"device": {"scan_rate_hz": "fast"}}, "device.scan_rate_hz", "a number"),
        ({"device": {"baudrate": 9.5}}, "device.baudrate", "an integer"),
        ({"device": {"port": "COM3"}}, "device.port", "absolute"),
        ({"device": {"port": "socket://10.0.0.5:7600"}}, "device.port", "loopback"),
        ({"device": {"exclusive": "yes"}}, "device.exclusive", "true or false"),
        ({"device": {"speed": 1}}, "device.speed", "unknown"),
        ({"device": {"reconnect_min_s": 2.0, "reconnect_max_s": 1.0}}, "device.reconnect_max_s", "≥"),
        ({"output": {"rate_hz": float("nan")}}, "output.rate_hz", "number"),
        ({"elements": {"layout": "ring"}}, "elements.layout", "one of"),
        ({"elements": {"layout": "explicit"}}, "elements.explicit", "missing"),
        ({"elements": {"layout": "explicit", "explicit": [{"u_mm": 1}]}}, "elements.explicit[0].v_mm", "missing"),
        ({"elements": {"layout": "explicit", "explicit": [{"u_mm": 1, "v_mm": 2, "w": 3}]}}, "elements.explicit[0].w", "unknown"),
        ({"zenoh": {"listen": ["tcp/0.0.0.0:7447"]}}, "zenoh.listen", "non-loopback"),
        ({"zenoh": {"connect": ["tcp/192.168.1.4:7447"]}}, "zenoh.connect", "non-loopback"),
        ({"zenoh": {"listen": ["http://x"]}}, "zenoh.listen[0]", "endpoint"),
        ({"zenoh": {"prefix": "a/*"}}, "zenoh.prefix", "wildcards"),
        ({"zenoh": {"config_file": "/nonexistent/zenoh.json5"}}, "zenoh.config_file", "does not exist"),
        ({"log": {"compression": "gzip"}}, "log.compression", "one of"),
        ({"log": {"max_file_mb": 0}}, "log.max_file_mb", "> 0"),
        ({"bogus": {}}, "[bogus]", "unknown"),
        ({"log": 5}, "log", "table"),
        ({"reconstruction": {"convex_solver": "cvxpy"}}, "reconstruction.convex_solver", "one of"),
        ({"reconstruction": {"graph_fit": "yes"}}, "reconstruction.graph_fit", "true or false"),
        ({"reconstruction": {"poisson_ratio": 0.5}}, "reconstruction.poisson_ratio", "≤ 0.499"),
        ({"reconstruction": {"elastic_prior": 1}}, "reconstruction.elastic_prior", "true or false"),
        ({"reconstruction": {"twist_prior": "zero"}}, "reconstruction.twist_prior", "one of"),
        ({"reconstruction": {"gain_sd": 0.5}}, "reconstruction.gain_sd", "≤ 0.3"),
        ({"reconstruction": {"gain_sd": -0.01}}, "reconstruction.gain_sd", "≥ 0"),
    ],
)
def test_bad_values_name_key_and_rule(doc, key, fragment):
    with pytest.raises(ConfigError) as info:
        parse_config(doc)
    msg = str(info.value)
    assert key in msg and fragment in msg, msg


def test_non_loopback_needs_explicit_opt_in():
    cfg = parse_config({"zenoh": {"listen": ["tcp/192.168.1.4:7447"], "allow_non_loopback": True}})
    assert cfg.zenoh.listen == ("tcp/192.168.1.4:7447",)


def test_unreadable_and_invalid_toml(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[device\nport=")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


def test_grid_layout_coordinates():
    cfg = parse_config({"elements": {"layout": "grid", "rows": 2, "cols": 3, "pitch_u_mm": 2, "pitch_v_mm": 4, "offset_mm": -0.5}})
    uv, off = cfg.elements.material_coordinates()
    assert uv == [(-2.0, -2.0), (0.0, -2.0), (2.0, -2.0), (-2.0, 2.0), (0.0, 2.0), (2.0, 2.0)]
    assert off == [-0.5] * 6


def test_relative_directories_resolve_against_config_file(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('[log]\ndirectory = "mylogs"\n')
    cfg = load_config(f)
    assert cfg.resolve(cfg.log.directory) == tmp_path / "mylogs"


def test_effective_config_round_trips_through_toml():
    import tomllib

    from skinmap.daemon.config import config_to_toml

    cfg = parse_config({
        "device": {"port": "/dev/skinmap0", "scan_rate_hz": 25},
        "elements": {"layout": "explicit", "explicit": [{"u_mm": 1.5, "v_mm": -2, "offset_mm": -0.3}, {"u_mm": 0, "v_mm": 0}]},
        "zenoh": {"listen": ["tcp/127.0.0.1:7555"], "prefix": "lab/skin"},
        "log": {"directory": "/tmp/x y \"z\""},
    })
    again = parse_config(tomllib.loads(config_to_toml(cfg)))
    for section in ("device", "reconstruction", "output", "elements", "zenoh", "log", "state"):
        assert getattr(again, section) == getattr(cfg, section), section


def test_tls_on_loopback_needs_the_same_opt_in_as_the_session():
    # make_session_config refuses anything but tcp on loopback by default; --check must agree.
    with pytest.raises(ConfigError, match="zenoh.listen"):
        parse_config({"zenoh": {"listen": ["tls/127.0.0.1:7447"]}})


def test_graph_fit_is_on_unless_turned_off():
    assert parse_config({}).reconstruction.graph_fit is True
    assert parse_config({"reconstruction": {"graph_fit": False}}).reconstruction.graph_fit is False


def test_check_verifies_the_files_and_folders_the_config_needs(tmp_path):
    """skinmapd --check: a Zenoh file naming missing TLS files and a log folder that cannot be
    created are errors (exit 2, each named); once they exist the same config is OK."""
    import subprocess
    import sys

    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the log folder's parent should be")
    zfile = tmp_path / "zenoh.json5"
    zfile.write_text('{ transport: { link: { tls: { root_ca_certificate: "%s", '
                     'listen_certificate: "%s", listen_private_key: "%s" } } } }'
                     % (tmp_path / "ca.pem", tmp_path / "gw.pem", tmp_path / "gw.key"))
    cfg = tmp_path / "gw.toml"
    cfg.write_text('[zenoh]\nlisten = ["tcp/127.0.0.1:7447"]\nconfig_file = "zenoh.json5"\n'
                   '[log]\ndirectory = "blocked/logs"\n')

    def check():
        return subprocess.run([sys.executable, "-m", "skinmap.daemon.service", "--config", str(cfg),
                               "--check"], capture_output=True, text=True, timeout=120)

    bad = check()
    assert bad.returncode == 2, bad.stdout + bad.stderr
    for name in ("ca.pem", "gw.pem", "gw.key", "log.directory"):
        assert name in bad.stderr, (name, bad.stderr)
    for name in ("ca.pem", "gw.pem", "gw.key"):
        (tmp_path / name).write_text("x")
    blocked.unlink()
    good = check()
    assert good.returncode == 0 and "OK" in good.stdout, good.stdout + good.stderr
    assert "does not exist yet; skinmapd creates it" in good.stdout
