"""A fleet on loopback: 3 gateways (emulators + skinmapd) through one router, a recorder and
5 subscribers (bench/fleet.py's topology). Correctness only: every device discovered, the
recording holds every topic of every gateway, no NaN in a VALID element anywhere."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))
import fleet as F  # noqa: E402  (bench/fleet.py)

from skinmap.daemon.cli import main as skinmap_main  # noqa: E402
from skinmap.wire import messages as wire  # noqa: E402

pytestmark = pytest.mark.slow

PER_DEVICE_TOPICS = ("elements", "elements/poses", "elements/plot", "scene", "strains",
                     "strains/plot", "surface", "surface/nodes", "tf", "status", "info")


def test_three_gateways_a_router_a_recorder_and_five_subscribers(tmp_path, capsys):
    with F.Fleet(tmp_path, gateways=3, subscribers=5) as fleet:
        fleet.wait_streaming()
        assert fleet.discover() == ["gw0", "gw1", "gw2"]
        assert skinmap_main(["ls", "--connect", fleet.router, "--prefix", F.PREFIX]) == 0
        listed = capsys.readouterr().out.splitlines()
        assert [line.split()[0] for line in listed] == [f"{F.PREFIX}/gw{i}" for i in range(3)]
        assert all("streaming" in line or "no status published yet" in line for line in listed), listed
        rec = fleet.record(4.0)
    assert rec.dropped == 0 and all(c.rejected == 0 for c in rec.counts.values())
    topics = F.recorded(fleet.record_dir)
    for device in fleet.devices:
        missing = [t for t in PER_DEVICE_TOPICS if f"/{device}/{t}" not in topics]
        assert not missing, (device, missing, sorted(topics))
        for payload in topics[f"/{device}/elements"]:
            el = wire.decode_elements(payload)
            assert np.isfinite(el.positions[el.valid]).all() and np.isfinite(el.normals[el.valid]).all()
    for stats in fleet.stats:
        assert stats.nan_in_valid == 0 and stats.rejected == 0
        assert set(stats.seqs) == set(fleet.devices)
    # The recording is a valid MCAP file by the doctor.
    doctor = os.path.join(os.path.dirname(sys.executable), "pymcap-cli")
    for path in sorted(fleet.record_dir.glob("*.mcap")):
        result = subprocess.run([doctor, "doctor", str(path), "--format", "jsonl"],
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 0 and '"severity":"error"' not in result.stdout, result.stdout[-2000:]


def test_ls_and_record_say_when_nothing_is_there(tmp_path, capsys):
    from conftest import free_port

    from skinmap.daemon.fleet import router_config
    from skinmap.daemon.zenoh_io import open_session

    router = f"tcp/127.0.0.1:{free_port()}"
    with open_session(router_config([router])):
        assert skinmap_main(["ls", "--connect", router, "--prefix", "empty", "--timeout", "0.5"]) == 1
        assert "no device alive under 'empty/*'" in capsys.readouterr().err
        assert skinmap_main(["record", "--connect", router, "--prefix", "empty", "-o",
                             str(tmp_path / "rec"), "--duration", "0.5"]) == 0
        out = capsys.readouterr().out
        assert "devices alive now: none" in out and "wrote nothing" in out
    with pytest.raises(ValueError, match="listen endpoint"):
        router_config([])
    with pytest.raises(ValueError, match="not loopback"):
        router_config(["tcp/192.0.2.1:7447"])
