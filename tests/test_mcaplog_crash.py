"""A logging process killed with SIGKILL leaves a `.mcap.active` that loses at most the
unfinished chunk."""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import textwrap

import pytest
from mcap.reader import make_reader

from skinmap.daemon.mcapread import iter_messages_file_order
from skinmap.daemon.mcaprecover import recover

CHILD = textwrap.dedent("""
    import struct, sys, time
    from skinmap.daemon.mcaplog import McapLogger

    logger = McapLogger(sys.argv[1], chunk_size=2048, fsync="chunk")
    logger.log_config(time.time_ns(), "rate = 100\\n", {"gf": [1.24]})
    flushed = -1
    i = 0
    while True:
        logger.log_raw_frame(time.time_ns(), struct.pack("<Q", i) + bytes(range(120)))
        i += 1
        if logger.messages_flushed != flushed:
            flushed = logger.messages_flushed
            # Everything counted here is in a chunk that has been fsynced.
            print(flushed, flush=True)
""")


@pytest.mark.slow
def test_sigkill_loses_at_most_the_open_chunk(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path)],
                             stdout=subprocess.PIPE, text=True)
    durable = 0
    try:
        for line in child.stdout:
            durable = int(line)
            if durable >= 300:
                break
        assert child.poll() is None, "the logging child died on its own"
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=10)
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    (active,) = [p for p in tmp_path.iterdir() if p.name.endswith(".mcap.active")]
    it = iter_messages_file_order(active)
    raw = [m.data for m in it if m.topic == "/raw"]
    assert not it.end.complete
    seqs = [struct.unpack_from("<Q", d)[0] for d in raw]
    assert seqs == list(range(len(seqs)))  # an exact prefix, nothing garbled
    assert len(seqs) >= durable  # every message reported durable survived
    out = tmp_path / "recovered.mcap"
    report = recover(active, out)
    with open(out, "rb") as f:
        reader = make_reader(f)
        got = [m.data for _, c, m in reader.iter_messages() if c.topic == "/raw"]
        assert reader.get_summary().statistics.message_count == report.messages
    assert got == raw and report.attachments == 2
