"""Every hostile scenario, one after the other: the scanner link (bench/hostile_link.py), the
service (bench/hostile_service.py) and the log tools and published data
(bench/hostile_tools.py).  Each prints one line per scenario with what was observed; nothing is
asserted.  All on loopback, multicast scouting off.

    .venv/bin/python bench/hostile.py
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
PARTS = ["hostile_link.py", "hostile_service.py", "hostile_tools.py"]


def main() -> int:
    failed = 0
    for script in PARTS:
        print(f"\n=== {script} ===", flush=True)
        failed += subprocess.call([sys.executable, str(HERE / script)]) != 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
