"""make_session_config: loopback-only endpoints, multicast scouting always off by default."""

import json

import pytest

from skinmap.daemon.zenoh_io import check_loopback_endpoint, key_for, make_session_config


def _get(config, key):
    return json.loads(config.get_json(key))


def test_loopback_config_sets_endpoints_and_disables_scouting():
    config = make_session_config(["tcp/127.0.0.1:7447"], ["tcp/[::1]:7448", "tcp/localhost:7449"])
    assert _get(config, "mode") == "peer"
    assert _get(config, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(config, "connect/endpoints") == ["tcp/[::1]:7448", "tcp/localhost:7449"]
    assert _get(config, "scouting/multicast/enabled") is False
    assert _get(config, "scouting/gossip/enabled") is False


def test_empty_listen_replaces_the_all_interfaces_default():
    # zenoh's own default peer listener is tcp/[::]:0, i.e. every interface
    config = make_session_config([], ["tcp/127.0.0.1:7447"], mode="client")
    assert _get(config, "listen/endpoints") == []
    assert _get(config, "mode") == "client"


@pytest.mark.parametrize("endpoint", [
    "tcp/192.168.1.20:7447", "tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/10.0.0.1:7447",
    "udp/127.0.0.1:7447", "tls/127.0.0.1:7447", "tcp/example.com:7447", "tcp/127.0.0.2:7447",
    "127.0.0.1:7447", "tcp/127.0.0.1:", "tcp/127.0.0.1:70000", "tcp/127.0.0.1:abc",
])
def test_non_loopback_endpoints_are_refused_by_name(endpoint):
    with pytest.raises(ValueError) as err:
        make_session_config([endpoint], [])
    assert repr(endpoint) in str(err.value)
    with pytest.raises(ValueError):
        make_session_config([], [endpoint])


def test_port_zero_only_for_listening():
    assert check_loopback_endpoint("tcp/127.0.0.1:0", listen=True)
    with pytest.raises(ValueError, match="port"):
        check_loopback_endpoint("tcp/127.0.0.1:0")


def test_allow_non_loopback_accepts_any_endpoint_but_keeps_multicast_off():
    config = make_session_config(["tcp/0.0.0.0:7447"], ["tcp/192.168.1.20:7447"],
                                 allow_non_loopback=True)
    assert _get(config, "listen/endpoints") == ["tcp/0.0.0.0:7447"]
    assert _get(config, "scouting/multicast/enabled") is False


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="mode"):
        make_session_config([], [], mode="satellite")
    with pytest.raises(TypeError, match="listen"):
        make_session_config("tcp/127.0.0.1:7447", [])
    with pytest.raises(ValueError, match="device"):
        key_for("skinmap", "a/b", "elements")
    with pytest.raises(ValueError, match="prefix"):
        key_for("sk*", "dev", "elements")
    with pytest.raises(ValueError, match="kind"):
        key_for("skinmap", "dev", "pressure")
    assert key_for("lab/skinmap", "dev-1", "alive") == "lab/skinmap/dev-1/alive"


def test_config_file_endpoints_are_checked_and_multicast_forced_off(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "peer", listen: { endpoints: ["tcp/127.0.0.1:7500"] },'
                    ' connect: { endpoints: [] } }')
    config = make_session_config(config_file=path)
    assert _get(config, "listen/endpoints") == ["tcp/127.0.0.1:7500"]
    assert _get(config, "scouting/multicast/enabled") is False

    # a file that listens everywhere (or leaves zenoh's default) needs allow_non_loopback
    wide = tmp_path / "wide.json5"
    wide.write_text('{ mode: "peer" }')
    with pytest.raises(ValueError, match=r"tcp/\[::\]:0"):
        make_session_config(config_file=wide)
    assert make_session_config(config_file=wide, allow_non_loopback=True)
    # endpoints given explicitly replace the file's
    config = make_session_config(["tcp/127.0.0.1:7501"], config_file=wide)
    assert _get(config, "listen/endpoints") == ["tcp/127.0.0.1:7501"]


def test_config_file_may_enable_multicast_explicitly(tmp_path):
    path = tmp_path / "mc.json5"
    path.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7502"] },'
                    ' scouting: { multicast: { enabled: true } } }')
    assert _get(make_session_config(config_file=path), "scouting/multicast/enabled") is True
    path.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7502"] },'
                    ' scouting: { multicast: { enabled: false } } }')
    assert _get(make_session_config(config_file=path), "scouting/multicast/enabled") is False


def test_config_file_errors(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        make_session_config(config_file=tmp_path / "missing.json5")
    bad = tmp_path / "bad.json5"
    bad.write_text("{ this is not json5")
    with pytest.raises(ValueError, match="invalid Zenoh config"):
        make_session_config(config_file=bad)


def test_production_style_file_needs_allow_non_loopback(tmp_path):
    path = tmp_path / "prod.json5"
    path.write_text('{ mode: "peer", listen: { endpoints: ["tls/192.168.10.5:7447"] },'
                    ' connect: { endpoints: [] } }')
    with pytest.raises(ValueError, match="tls/192.168.10.5:7447"):
        make_session_config(config_file=path)
    config = make_session_config(config_file=path, allow_non_loopback=True)
    assert _get(config, "listen/endpoints") == ["tls/192.168.10.5:7447"]
    assert _get(config, "scouting/multicast/enabled") is False
