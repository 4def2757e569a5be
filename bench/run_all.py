"""Run every benchmark once with short settings and print their figures (`make bench`)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

RUNS = [
    ["decode_rate.py"],
    ["emulator_rate.py"],
    ["mechanics.py", "--sizes", "5"],
    ["reconstruction.py", "--quick"],
    ["latency.py", "--seconds", "15"],
    ["pipeline_accuracy.py", "--sizes", "5,8", "--outputs", "10"],
    # the gauges lagging at the paper's bound: σ carries the lag (docs/reconstruction.md, "A sheet that moves")
    ["pipeline_accuracy.py", "--sizes", "5,8", "--outputs", "10", "--hysteresis", "on", "--response-tau", "0.057"],
    ["soak.py", "--seconds", "60"],
]


def main() -> int:
    failed = 0
    for args in RUNS:
        print(f"\n=== {' '.join(args)} ===", flush=True)
        failed += subprocess.call([sys.executable, str(HERE / args[0]), *args[1:]]) != 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
