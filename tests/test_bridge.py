"""Live view: the Foxglove bridge subscribes over Zenoh and serves the Foxglove WebSocket
protocol on loopback; a client speaking it subscribes and decodes the scene, the element
poses and the status. foxglove-sdk 0.30's server negotiates the subprotocol `foxglove.sdk.v1`
(the successor of `foxglove.websocket.v1`, same framing) and refuses the old name."""
from __future__ import annotations

import asyncio
import json
import struct
import threading
import time

import numpy as np
import pytest
from conftest import free_port

from skinmap.daemon.bridge import FoxgloveBridge
from skinmap.daemon.foxglove_log import decode_protobuf
from skinmap.daemon.zenoh_io import SkinmapPublisher, make_session_config, open_session
from skinmap.wire import messages as wire

websockets = pytest.importorskip("websockets")


def _status(seq: int) -> dict:
    return {"device": "live", "host_time_ns": time.time_ns(), "connected": True, "seq": seq,
            "scan_rate_hz": 50.0, "publish_rate_hz": 10.0, "frames_dropped": 0, "crc_errors": 0,
            "reconnects": 0, "solver_time_ms": 3.0, "log_state": "off"}


def _publish_loop(pub: SkinmapPublisher, stop: threading.Event) -> None:
    n, m, k = 3, 4, 5
    u, v = np.meshgrid(np.linspace(-0.02, 0.02, m), np.linspace(-0.015, 0.015, n))
    nodes = np.stack([u, v, 0.002 * np.cos(u * 50)], axis=-1)
    normals = np.zeros_like(nodes)
    normals[..., 2] = 1.0
    seq = 0
    while not stop.is_set():
        seq += 5
        now = time.time_ns()
        pos = np.column_stack([np.linspace(-0.02, 0.02, k), np.zeros(k), np.zeros(k)])
        nrm = np.tile([0.0, 0.0, 1.0], (k, 1))
        flags = np.array([1, 1, 3, 0, 1], dtype=np.uint8)
        pos[3] = np.nan  # not VALID: may be NaN, is left out of the poses
        nrm[3] = np.nan
        pub.publish_elements(wire.encode_elements(seq, seq * 20_000, now, pos, nrm, np.full(k, 1e-5), flags))
        pub.publish_surface(wire.encode_surface(seq, seq * 20_000, now, nodes, normals,
                                                np.full((n, m), 2e-5), nodes.reshape(-1, 3)))
        pub.publish_strains(wire.encode_strains(seq, seq * 20_000, now, np.zeros((2, n, m)),
                                                np.zeros((2, n, m)), np.full((2, n, m), 3, np.uint8)))
        pub.publish_status(_status(seq))
        stop.wait(0.1)


async def _client(url: str, wanted: list[str], timeout: float = 20.0) -> dict[str, tuple[dict, bytes]]:
    """Speak foxglove.sdk.v1: read the advertisements, subscribe to `wanted`, return
    the first message of each (channel, payload)."""
    got: dict[str, tuple[dict, bytes]] = {}
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1"
        channels: dict[str, dict] = {}
        by_sub: dict[int, str] = {}
        next_sub = 1
        deadline = time.monotonic() + timeout
        while len(got) < len(wanted):
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"got {sorted(got)}, advertised {sorted(channels)}"
            frame = await asyncio.wait_for(ws.recv(), remaining)
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    new = []
                    for ch in msg["channels"]:
                        channels[ch["topic"]] = ch
                        if ch["topic"] in wanted:
                            by_sub[next_sub] = ch["topic"]
                            new.append({"id": next_sub, "channelId": ch["id"]})
                            next_sub += 1
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            if frame[0] == 0x01:  # message data: op, u32 subscription, u64 log time, payload
                sub_id, _t = struct.unpack_from("<IQ", frame, 1)
                topic = by_sub.get(sub_id)
                if topic is not None and topic not in got:
                    got[topic] = (channels[topic], bytes(frame[13:]))
    return got


def test_foxglove_client_receives_the_live_scene(tmp_path):
    zport = free_port()
    config = make_session_config([f"tcp/127.0.0.1:{zport}"], [])
    stop = threading.Event()
    with open_session(config) as gw_session, SkinmapPublisher(gw_session, "bridge", "live") as pub:
        feeder = threading.Thread(target=_publish_loop, args=(pub, stop), daemon=True)
        feeder.start()
        try:
            with open_session(make_session_config([], [f"tcp/127.0.0.1:{zport}"])) as session, \
                    FoxgloveBridge(session, "bridge", ["*"], port=0) as bridge:
                assert bridge.port > 0
                wanted = ["/live/scene", "/live/elements/poses", "/live/status", "/live/surface",
                          "/live/elements/plot", "/live/strains/plot", "/live/tf"]
                got = asyncio.run(_client(f"ws://127.0.0.1:{bridge.port}", wanted))
        finally:
            stop.set()
            feeder.join(timeout=5)
    channel, data = got["/live/scene"]
    assert channel["schemaName"] == "foxglove.SceneUpdate" and channel["encoding"] == "protobuf"
    scene = decode_protobuf("foxglove.SceneUpdate", data)
    ids = {e.id for e in scene.entities}
    assert ids & {"sheet", "elements"}
    poses = decode_protobuf("foxglove.PosesInFrame", got["/live/elements/poses"][1])
    assert len(poses.poses) == 4 and poses.frame_id == "live"  # the NaN element is left out
    assert json.loads(got["/live/status"][1])["device"] == "live"
    plot = json.loads(got["/live/elements/plot"][1])
    assert plot["valid"] == [1, 1, 1, 0, 1] and plot["sigma_um"][0] == pytest.approx(10.0)
    assert plot["latency_ms"] is not None
    assert got["/live/surface"][0]["schemaName"] == "foxglove.PointCloud"


def test_bridge_refuses_a_non_loopback_host():
    with open_session(make_session_config([], [])) as session:
        with pytest.raises(ValueError, match="not loopback"):
            FoxgloveBridge(session, "bridge", host="0.0.0.0", port=8765)
