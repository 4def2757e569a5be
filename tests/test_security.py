"""Security of the Zenoh edge: access control, TLS and mutual TLS, loopback-only defaults.

Every session here listens or connects on 127.0.0.1 with a free port and multicast scouting off.
Certificates are made with the ``openssl`` command line into a temporary folder: one CA, the
daemon's certificate, an allowed client (CN ``skinmap-client``), a client of the same CA whose
CN is not in the policy (``intruder``), and a client of another CA that reuses an allowed CN.

The access-control tests load ``config/zenoh-production.json5`` itself; only its certificate
paths are pointed at the temporary certificates and its listen endpoint is replaced by a
loopback one.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from conftest import free_port, python_for_other_users, wait_until

from skinmap.wire import messages as msg
from skinmap.client import SkinmapClient
from skinmap.daemon.zenoh_io import SkinmapPublisher, make_session_config, open_session

REPO = Path(__file__).resolve().parents[1]
PRODUCTION = REPO / "config" / "zenoh-production.json5"
PRODUCTION_CERT_DIR = "/etc/skinmap/tls/"
DEVICE = "skin-sec"
ALLOWED_CN = "skinmap-client"  # listed in the production policy's cert_common_names

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None,
                                reason="the openssl command line is needed to make certificates")


# ---------------------------------------------------------------------------------------------
# certificates


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def make_ca(folder: Path, name: str) -> None:
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
             "-keyout", f"{name}.key", "-out", f"{name}.pem", "-subj", f"/CN={name}",
             "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=folder)


def make_leaf(folder: Path, ca: str, name: str, cn: str) -> None:
    """A certificate for 127.0.0.1/localhost, usable as TLS server and client, signed by ``ca``."""
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key",
             "-out", f"{name}.csr", "-subj", f"/CN={cn}", cwd=folder)
    (folder / f"{name}.ext").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n"
                                        "basicConstraints=CA:FALSE\n"
                                        "extendedKeyUsage=serverAuth,clientAuth\n")
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
             "-CAcreateserial", "-days", "2", "-out", f"{name}.pem",
             "-extfile", f"{name}.ext", cwd=folder)


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("tls")
    make_ca(folder, "ca")
    make_leaf(folder, "ca", "skinmapd", "skinmapd")
    make_leaf(folder, "ca", "client", ALLOWED_CN)
    make_leaf(folder, "ca", "intruder", "intruder")
    make_ca(folder, "rogue-ca")
    make_leaf(folder, "rogue-ca", "forged", ALLOWED_CN)  # allowed CN, wrong CA
    return folder


# ---------------------------------------------------------------------------------------------
# session configs


def production_copy(pki: Path, tmp_path: Path) -> Path:
    """The production file with its certificate paths pointed at the test certificates."""
    text = PRODUCTION.read_text(encoding="utf-8")
    assert PRODUCTION_CERT_DIR in text
    text = (text.replace(PRODUCTION_CERT_DIR + "skinmapd.key", str(pki / "skinmapd.key"))
                .replace(PRODUCTION_CERT_DIR + "skinmapd.pem", str(pki / "skinmapd.pem"))
                .replace(PRODUCTION_CERT_DIR + "ca.pem", str(pki / "ca.pem")))
    assert PRODUCTION_CERT_DIR not in text, "production file names a certificate the test lacks"
    path = tmp_path / "zenoh-daemon.json5"
    path.write_text(text, encoding="utf-8")
    return path


def client_file(tmp_path: Path, root_ca: Path, cert: str | None, pki: Path) -> Path:
    """A client's Zenoh file: trust ``root_ca``; present ``cert`` (mutual TLS) when given."""
    tls: dict = {"root_ca_certificate": str(root_ca), "verify_name_on_connect": True}
    if cert is not None:
        tls.update(enable_mtls=True, connect_private_key=str(pki / f"{cert}.key"),
                   connect_certificate=str(pki / f"{cert}.pem"))
    path = tmp_path / f"zenoh-client-{cert or 'nocert'}-{root_ca.stem}.json5"
    path.write_text(json.dumps({"mode": "peer", "transport": {"link": {"tls": tls}}}))
    return path


def daemon_config(config_file: Path, endpoint: str) -> zenoh.Config:
    # tls/ endpoints are for the network, so make_session_config wants the explicit opt-in even
    # on 127.0.0.1; the endpoint used here is still loopback.
    assert endpoint.startswith("tls/127.0.0.1:")
    return make_session_config([endpoint], [], allow_non_loopback=True, config_file=config_file)


def server_only_tls_file(pki: Path, tmp_path: Path) -> Path:
    path = tmp_path / "zenoh-server-tls.json5"
    path.write_text(json.dumps({"transport": {"link": {"tls": {
        "listen_private_key": str(pki / "skinmapd.key"),
        "listen_certificate": str(pki / "skinmapd.pem"),
        "enable_mtls": False}}}}))
    return path


def open_client(endpoint: str, config_file: Path) -> SkinmapClient:
    assert endpoint.startswith("tls/127.0.0.1:")
    client = SkinmapClient([endpoint], prefix="skinmap", device=DEVICE, allow_non_loopback=True,
                           config_file=config_file)
    return client.open()


def connected(client: SkinmapClient, timeout: float = 5.0) -> bool:
    return wait_until(lambda: bool(client.session.info.peers_zid()), timeout)


def elements_payload(seq: int) -> bytes:
    k = 4
    pos = np.arange(3 * k, dtype=np.float64).reshape(k, 3) * 1e-3 + seq
    return msg.encode_elements(seq, 1000 * seq, 10**18 + seq, pos, np.tile([0.0, 0.0, 1.0], (k, 1)),
                               np.full(k, 1e-4), np.full(k, msg.ElementFlag.VALID, np.uint8))


INFO = {"device": DEVICE, "rows": 2, "cols": 2, "pitch_m": 0.012,
        "elements": {"count": 4, "width_m": 0.003, "height_m": 0.01},
        "calibration": {"gauge_factor": [1.24] * 16}, "versions": {"skinmap": "test"}}


class DaemonSide:
    """A publisher session as skinmapd holds it, plus subscribers on the daemon's own session
    that record every remote write into the skinmap key space and outside it."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.publisher = SkinmapPublisher(session, "skinmap", DEVICE)
        self.publisher.set_info(INFO)
        self.received: list[tuple[str, str, bytes]] = []
        self._subs = [session.declare_subscriber(k, self._record)
                      for k in ("skinmap/**", "other/**")]

    def _record(self, sample: zenoh.Sample) -> None:
        self.received.append((str(sample.key_expr), str(sample.kind), sample.payload.to_bytes()))

    def remote_writes(self) -> list[tuple[str, str, bytes]]:
        # the daemon's own puts reach its own subscriber locally; count only the client's
        return [r for r in self.received if not r[2].startswith(b"SKMP")]

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.publisher.close()


def receives(publisher: SkinmapPublisher, client: SkinmapClient, seq: int,
             timeout: float = 5.0) -> bool:
    """Publish elements ``seq`` every 0.1 s until the client gets it (True) or ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        publisher.publish_elements(elements_payload(seq))
        try:
            if client.elements(timeout=0.1).seq == seq:
                return True
        except TimeoutError:
            pass
        except msg.MessageError:  # the client's own forged put, delivered to itself locally
            pass
    return False


def attempt_writes(client: SkinmapClient) -> None:
    s = client.session
    s.put(f"skinmap/{DEVICE}/elements", b"forged elements")
    s.put(f"skinmap/{DEVICE}/status", b'{"healthy": true}')
    s.delete(f"skinmap/{DEVICE}/elements")
    s.put("skinmap/other-device/elements", b"forged elements")
    s.put("other/key", b"outside the key space")


def announce_daemon_subscribers(config: zenoh.Config) -> None:
    """Add to the production ACL one rule letting the daemon announce its subscribers to
    clients: clients then know where a put would go, so only the ingress `put`/`delete` denial
    can stop it."""
    rules = json.loads(config.get_json("access_control/rules"))
    rules.append({"id": "announce-daemon-subscribers", "permission": "allow", "flows": ["egress"],
                  "messages": ["declare_subscriber"], "key_exprs": ["skinmap/**", "other/**"]})
    policies = json.loads(config.get_json("access_control/policies"))
    policies[0]["rules"].append("announce-daemon-subscribers")
    config.insert_json5("access_control/rules", json.dumps(rules))
    config.insert_json5("access_control/policies", json.dumps(policies))


# ---------------------------------------------------------------------------------------------
# the production example file


def test_production_file_loads_with_mtls_and_default_deny_access_control():
    config = zenoh.Config.from_file(str(PRODUCTION))
    tls = json.loads(config.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True
    assert tls["root_ca_certificate"] and tls["listen_certificate"] and tls["listen_private_key"]
    acl = json.loads(config.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    # nothing lets a remote write into the key space: the only ingress messages allowed are
    # subscriptions and queries
    ingress = {m for r in acl["rules"] if r["permission"] == "allow"
               and "ingress" in r.get("flows", ["ingress", "egress"]) for m in r["messages"]}
    assert ingress and not ingress & {"put", "delete", "declare_queryable", "liveliness_token",
                                      "reply"}
    assert all(e.startswith("tls/") for e in json.loads(config.get_json("listen/endpoints")))
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False


def test_production_file_needs_the_explicit_non_loopback_opt_in():
    with pytest.raises(ValueError, match=r"tls/192\.0\.2\.10:7447"):
        make_session_config(config_file=PRODUCTION)
    config = make_session_config(config_file=PRODUCTION, allow_non_loopback=True)
    assert json.loads(config.get_json("listen/endpoints")) == ["tls/192.0.2.10:7447"]
    assert json.loads(config.get_json("access_control/enabled")) is True
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False


@pytest.mark.parametrize("endpoint", ["tcp/0.0.0.0:7447", "tcp/[::]:7447", "tcp/192.0.2.10:7447",
                                      "tls/192.0.2.10:7447", "tls/127.0.0.1:7447",
                                      "quic/127.0.0.1:7447"])
def test_make_session_config_refuses_non_loopback_unless_allowed(endpoint):
    for listen, connect in (([endpoint], []), ([], [endpoint])):
        with pytest.raises(ValueError) as err:
            make_session_config(listen, connect)
        assert repr(endpoint) in str(err.value)
        config = make_session_config(listen, connect, allow_non_loopback=True)
        assert endpoint in json.loads(config.get_json("listen/endpoints")) + json.loads(
            config.get_json("connect/endpoints"))


# ---------------------------------------------------------------------------------------------
# access control (production policy, mutual TLS on loopback)


@pytest.mark.slow
def test_allowed_client_reads_everything_but_cannot_write(pki, tmp_path):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    with open_session(daemon_config(production_copy(pki, tmp_path), endpoint)) as session:
        daemon = DaemonSide(session)
        try:
            daemon.publisher.publish_elements(elements_payload(1))
            with open_client(endpoint, client_file(tmp_path, pki / "ca.pem", "client", pki)) as client:
                assert connected(client), "allowed client did not connect over mutual TLS"
                # liveliness and queries (late joiner: latest value, info)
                assert wait_until(client.alive)
                assert client.latest("elements", timeout=3.0).seq == 1
                assert client.info(timeout=3.0)["device"] == DEVICE
                live = []
                watcher = client.session.liveliness().declare_subscriber(
                    "skinmap/**", lambda s: live.append((str(s.key_expr), str(s.kind))),
                    history=True)
                assert wait_until(lambda: live)
                assert live[0] == (f"skinmap/{DEVICE}/alive", "SampleKind.PUT")
                watcher.undeclare()
                # subscription
                # subscription (the daemon's own subscriber already matches, so publish until
                # the client's subscription has propagated)
                client.subscribe("elements")
                assert receives(daemon.publisher, client, seq=2)

                attempt_writes(client)
                # a put that followed the forged ones on the same link proves they had their chance
                time.sleep(0.5)
                assert receives(daemon.publisher, client, seq=3)
                time.sleep(0.3)
                assert daemon.remote_writes() == []
        finally:
            daemon.close()


@pytest.mark.slow
@pytest.mark.parametrize("acl_enabled", [True, False])
def test_ingress_put_and_delete_are_denied_even_to_a_declared_subscriber(pki, tmp_path, acl_enabled):
    """With the daemon's subscribers announced to the client, the client does send its puts;
    the access control drops them on arrival. Without access control they do arrive (control
    case: the check can fail)."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    config = daemon_config(production_copy(pki, tmp_path), endpoint)
    announce_daemon_subscribers(config)
    if not acl_enabled:
        config.insert_json5("access_control/enabled", "false")
    with open_session(config) as session:
        daemon = DaemonSide(session)
        try:
            with open_client(endpoint, client_file(tmp_path, pki / "ca.pem", "client", pki)) as client:
                assert connected(client)
                probe = client.session.declare_publisher(f"skinmap/{DEVICE}/elements")
                assert wait_until(lambda: probe.matching_status.matching), \
                    "the daemon's subscriber was not announced to the client"
                probe.undeclare()
                attempt_writes(client)
                if acl_enabled:
                    time.sleep(1.0)
                    assert daemon.remote_writes() == []
                else:
                    assert wait_until(lambda: len(daemon.remote_writes()) == 5)
                    keys = sorted(k for k, _, _ in daemon.remote_writes())
                    assert keys == ["other/key", "skinmap/other-device/elements",
                                    f"skinmap/{DEVICE}/elements", f"skinmap/{DEVICE}/elements",
                                    f"skinmap/{DEVICE}/status"]
        finally:
            daemon.close()


@pytest.mark.slow
def test_certificate_outside_the_policy_connects_but_sees_nothing(pki, tmp_path):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    with open_session(daemon_config(production_copy(pki, tmp_path), endpoint)) as session:
        daemon = DaemonSide(session)
        try:
            daemon.publisher.publish_elements(elements_payload(1))
            with open_client(endpoint, client_file(tmp_path, pki / "ca.pem", "intruder", pki)) as client:
                assert connected(client), "a CA-signed certificate should pass the TLS handshake"
                assert not client.alive(timeout=1.0)
                with pytest.raises(LookupError):
                    client.latest("elements", timeout=1.0)
                client.subscribe("elements")
                assert not receives(daemon.publisher, client, seq=2, timeout=1.5)
                attempt_writes(client)
                time.sleep(0.5)
                assert daemon.remote_writes() == []
        finally:
            daemon.close()


# ---------------------------------------------------------------------------------------------
# TLS and mutual TLS on loopback


def _serve_elements(config: zenoh.Config):
    session = zenoh.open(config)
    publisher = SkinmapPublisher(session, "skinmap", DEVICE)
    publisher.publish_elements(elements_payload(7))
    return session, publisher


@pytest.mark.slow
def test_server_only_tls_accepts_clients_that_trust_its_ca(pki, tmp_path):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    session, publisher = _serve_elements(daemon_config(server_only_tls_file(pki, tmp_path), endpoint))
    try:
        with open_client(endpoint, client_file(tmp_path, pki / "ca.pem", None, pki)) as client:
            assert connected(client)
            assert client.latest("elements", timeout=3.0).seq == 7
        # a client that does not trust the server's CA refuses the link
        with open_client(endpoint, client_file(tmp_path, pki / "rogue-ca.pem", None, pki)) as client:
            assert not connected(client, timeout=1.5)
    finally:
        publisher.close()
        session.close()


@pytest.mark.slow
def test_mutual_tls_refuses_clients_without_a_certificate_of_the_ca(pki, tmp_path):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    config = daemon_config(production_copy(pki, tmp_path), endpoint)
    config.insert_json5("access_control/enabled", "false")  # only the TLS layer is under test
    session, publisher = _serve_elements(config)
    try:
        for cert in (None, "forged"):  # no client certificate; allowed CN signed by another CA
            with open_client(endpoint, client_file(tmp_path, pki / "ca.pem", cert, pki)) as client:
                assert not connected(client, timeout=1.5), f"client certificate {cert} was accepted"
        with open_client(endpoint, client_file(tmp_path, pki / "ca.pem", "client", pki)) as client:
            assert connected(client)
            assert client.latest("elements", timeout=3.0).seq == 7
    finally:
        publisher.close()
        session.close()


@pytest.mark.slow
def test_plain_tcp_client_cannot_talk_to_a_tls_listener(pki, tmp_path):
    port = free_port()
    session, publisher = _serve_elements(
        daemon_config(server_only_tls_file(pki, tmp_path), f"tls/127.0.0.1:{port}"))
    try:
        with SkinmapClient([f"tcp/127.0.0.1:{port}"], prefix="skinmap", device=DEVICE) as client:
            assert not connected(client, timeout=1.5)
    finally:
        publisher.close()
        session.close()


# ---------------------------------------------------------------------------------------------
# running unprivileged


UNIT = REPO / "systemd" / "skinmapd.service"


def _unit_settings() -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for line in UNIT.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "[")) and "=" in line:
            key, value = line.split("=", 1)
            settings.setdefault(key.strip(), []).append(value.strip())
    return settings


def test_unit_file_runs_the_service_without_privileges():
    s = _unit_settings()
    assert s["DynamicUser"] == ["yes"] and "User" not in s
    assert s["CapabilityBoundingSet"] == [""] and s["AmbientCapabilities"] == [""]
    assert s["NoNewPrivileges"] == ["yes"] and s["ProtectSystem"] == ["strict"]
    assert s["DevicePolicy"] == ["closed"] and "/dev/skinmap0 rw" in s["DeviceAllow"]
    assert set(s["RestrictAddressFamilies"][0].split()) <= {"AF_UNIX", "AF_INET", "AF_INET6",
                                                            "AF_NETLINK"}
    for key in ("ProtectHome", "PrivateTmp", "RestrictSUIDSGID", "ProtectKernelModules"):
        assert s[key] == ["yes"], key


@pytest.mark.slow
def test_daemon_runs_as_an_unprivileged_user():
    """skinmapd needs no privilege: as root we drop to nobody (what DynamicUser gives it) and
    check it streams, logs and stops cleanly with no capabilities."""
    import os
    import signal
    import tempfile

    from skinmap.daemon.cli import start_emulator, stop_process

    uid = 65534 if os.geteuid() == 0 else os.geteuid()
    if uid == 0:
        pytest.skip("cannot switch to an unprivileged user")
    work = Path(tempfile.mkdtemp(prefix="skinmap-unprivileged-"))  # pytest's tmp is root-only
    serial_port, zenoh_port = free_port(), free_port()
    cfg = work / "skinmapd.toml"
    cfg.write_text(f"""
[device]
port = "socket://127.0.0.1:{serial_port}"
name = "{DEVICE}"
scan_rate_hz = 20
[zenoh]
listen = ["tcp/127.0.0.1:{zenoh_port}"]
[log]
directory = "logs"
[state]
directory = "state"
""")
    if os.geteuid() == 0:
        os.chown(work, uid, uid)
        os.chown(cfg, uid, uid)
    # setpriv (util-linux) switches user and group and execs, as systemd does for the unit
    drop = ["setpriv", f"--reuid={uid}", f"--regid={uid}", "--clear-groups"] \
        if os.geteuid() == 0 else []
    if drop and shutil.which("setpriv") is None:
        pytest.skip("setpriv is needed to drop to an unprivileged user")
    # a checkout in a private directory is out of the unprivileged user's reach: use a copy
    with python_for_other_users() as (python, env_extra, _):
        # as the unit: a cache directory of the service's own, filled before the daemon starts
        env = {**os.environ, **env_extra, "NUMBA_CACHE_DIR": str(work / "numba-cache")}
        fill = subprocess.run([*drop, python, "-m", "skinmap.reconstruction.kernels"], cwd=work, env=env,
                              stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=600)
        assert fill.returncode == 0 and "cached" in fill.stdout.split(), fill.stdout + fill.stderr
        emulator = start_emulator(serial_port, size="4x4", shape="flat", rate=20.0)
        daemon = subprocess.Popen([*drop, python, "-m", "skinmap.daemon.service", "--config",
                                   str(cfg)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, cwd=work, env=env)
        try:
            with SkinmapClient([f"tcp/127.0.0.1:{zenoh_port}"], prefix="skinmap",
                               device=DEVICE) as client:
                try:
                    first = client.elements(timeout=30.0)
                except TimeoutError:
                    daemon.kill()
                    pytest.fail("no elements from the unprivileged daemon; its log:\n"
                                + daemon.stderr.read().decode()[-3000:])
                assert first.valid.any()
                proc_status = dict(line.split(":", 1) for line in
                                   Path(f"/proc/{daemon.pid}/status").read_text().splitlines())
                assert proc_status["Uid"].split()[:2] == [str(uid), str(uid)]
                assert int(proc_status["CapEff"].strip(), 16) == 0
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(timeout=30) == 0, daemon.stderr.read().decode()[-2000:]
            logs = sorted((work / "logs").glob("*.mcap"))
            assert logs and all(p.stat().st_uid == uid for p in logs)
        finally:
            stop_process(daemon, timeout=10)
            stop_process(emulator)
            shutil.rmtree(work, ignore_errors=True)
