"""The wire module: one definition of every published and logged layout, the docs rendered
from it, and the light client importable and working without the gateway's dependencies."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from skinmap.wire import messages as wire

DOCS = os.path.join(os.path.dirname(__file__), "..", "docs")


@pytest.mark.parametrize("kind", list(wire.LAYOUT_TABLES))
def test_docs_byte_tables_are_the_wire_modules(kind):
    text = open(os.path.join(DOCS, "zenoh.md"), encoding="utf-8").read()
    assert wire.layout_table(kind) in text


def _length(kind: str, **symbols: int) -> int:
    return sum(c * (1 if not sym else int(np.prod([symbols[s] for s in sym.split("·")])))
               for sym, c in wire.layout_size(kind).items())


def test_encoders_follow_the_tables():
    k, n, m, p = 5, 3, 4, 7
    el = wire.encode_elements(1, 2, 3, np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k),
                              np.zeros(k, np.uint8))
    assert len(el) == _length("elements", K=k)
    for itemsize, dtype in ((4, "float32"), (8, "float64")):
        sf = wire.encode_surface(1, 2, 3, np.zeros((n, m, 3)), np.zeros((n, m, 3)),
                                 np.zeros((n, m)), np.zeros((p, 3)), cloud_dtype=dtype)
        assert len(sf) == _length("surface", N=n, M=m, P=p, s=itemsize)
    st = wire.encode_strains(1, 2, 3, np.zeros((2, n, m)), np.zeros((2, n, m)),
                             np.zeros((2, n, m), np.uint8))
    assert len(st) == _length("strains", N=n, M=m)
    with pytest.raises(ValueError, match="unknown layout"):
        wire.layout_table("nope")


def test_logged_layouts_are_the_published_ones():
    """The MCAP schema text of every binary topic is the wire module's byte table."""
    from skinmap.daemon.mcapschema import TOPICS

    for topic, kind in (("/strains", "strains"), ("/surface/nodes", "surface"),
                        ("/elements", "elements")):
        assert wire.layout_table(kind).encode() in TOPICS[topic].schema_data
        assert TOPICS[topic].message_encoding == f"skinmap.{kind}/{wire.LAYOUT_VERSION}"


HEAVY = ("scipy", "numba", "clarabel", "serial", "matplotlib", "mcap", "mcap_protobuf",
         "foxglove", "cobs", "threadpoolctl", "rich", "zstandard", "lz4")

LIGHT_CLIENT = textwrap.dedent('''
    import sys
    HEAVY = set(sys.argv[1].split(","))

    class Refuse:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in HEAVY:
                raise ImportError(f"light client must not import {name}")
            return None

    sys.meta_path.insert(0, Refuse())
    import numpy as np
    from skinmap.client import RejectedMessage, SkinmapClient, check_message
    from skinmap.wire import messages as wire

    ok = wire.encode_elements(4, 5, 6, np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)),
                              np.full(2, 1e-5), [1, 0])
    msg = check_message("elements", ok)
    assert msg.seq == 4 and msg.count == 2 and list(msg.valid) == [True, False]
    bad = wire.encode_elements(4, 5, 6, [[np.nan, 0, 0], [0, 0, 0]], np.tile([0, 0, 1.0], (2, 1)),
                               np.full(2, 1e-5), [1, 0])
    try:
        check_message("elements", bad)
    except RejectedMessage as exc:
        assert "element 0 is flagged VALID" in str(exc), exc
    else:
        raise AssertionError("NaN in a VALID element was accepted")
    st = wire.encode_strains(1, 2, 3, np.zeros((2, 2, 2)), np.zeros((2, 2, 2)),
                             np.full((2, 2, 2), 3, np.uint8))
    assert check_message("strains", st).eps_upper.shape == (2, 2, 2)
    loaded = sorted(m for m in sys.modules if m.split(".")[0] in HEAVY)
    assert not loaded, loaded
    print("light client ok")
''')


def test_light_client_needs_no_gateway_dependency():
    result = subprocess.run([sys.executable, "-c", LIGHT_CLIENT, ",".join(HEAVY)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "light client ok" in result.stdout


def test_light_client_receives_over_zenoh_without_gateway_dependencies():
    """A real publisher in this process, the light client in a subprocess with the heavy
    modules refused: it decodes the messages it receives."""
    from skinmap.daemon.zenoh_io import SkinmapPublisher, make_session_config, open_session

    from conftest import free_port

    port = free_port()
    script = LIGHT_CLIENT.split("import numpy as np")[0] + textwrap.dedent(f'''
        from skinmap.client import SkinmapClient
        with SkinmapClient(["tcp/127.0.0.1:{port}"], prefix="wiretest", device="demo") as c:
            c.subscribe("elements")
            print("subscribed", flush=True)
            m = c.elements(timeout=20)
            print("got", m.seq, m.count, flush=True)
        from skinmap.daemon.cli import main  # echo, info and ls need the light client only
        assert main(["ls", "--connect", "tcp/127.0.0.1:{port}", "--prefix", "wiretest"]) == 0
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in HEAVY)
        assert not loaded, loaded
    ''')
    config = make_session_config([f"tcp/127.0.0.1:{port}"], [])
    with open_session(config) as session, SkinmapPublisher(session, "wiretest", "demo") as pub:
        proc = subprocess.Popen([sys.executable, "-c", script, ",".join(HEAVY)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout.readline().strip() == "subscribed", proc.stderr.read()[-3000:]
            payload = wire.encode_elements(9, 1, 2, np.zeros((3, 3)), np.tile([0, 0, 1.0], (3, 1)),
                                           np.full(3, 1e-5), [1, 1, 1])
            out = ""
            for _ in range(100):  # until the subscription has reached the publisher
                pub.publish_elements(payload)
                if proc.poll() is not None:
                    break
                try:
                    out, err = proc.communicate(timeout=0.2)
                    break
                except subprocess.TimeoutExpired:
                    continue
            else:
                out, err = proc.communicate(timeout=30)
            assert proc.returncode == 0, err[-3000:]
            assert "got 9 3" in out and "wiretest/demo  (alive; no status published yet)" in out
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
