"""Type-check skinmap with mypy.

The top-level folders are mapped onto the `skinmap` namespace by `package-dir` (protocol/ is
skinmap.protocol, firmware-host/ is skinmap.emulator, ...), which mypy cannot follow from the
source tree. This script makes a view of the package as installed, build/typecheck/skinmap/
(symbolic links to the folders), and runs mypy there.

    python .ci/typecheck.py            # the modules in CLEAN must have no error (CI)
    python .ci/typecheck.py --report   # and the error count of every other package

Add a module to CLEAN once it is clean; the list only grows.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VIEW = ROOT / "build" / "typecheck"

CLEAN = [
    "skinmap.protocol",  # the whole package
    "skinmap.emulator.__init__",  # the package's own module (its __init__.py) alone
    "skinmap.emulator.cli",
    "skinmap.emulator.device",
    "skinmap.emulator.emulator",
    "skinmap.emulator.linkfaults",
    "skinmap.emulator.mechanics",
    "skinmap.emulator.physics",
    "skinmap.emulator.scenes",
    "skinmap.emulator.transport",
    "skinmap.emulator.loopback",
    "skinmap.emulator.electrical",
    "skinmap.ports",  # the whole package
    "skinmap.strains",  # the whole package
    "skinmap.elements",  # the whole package
    "skinmap.daemon.link",
    "skinmap.daemon.pipeline",
    "skinmap.wire",
    "skinmap.client",
    "skinmap.reconstruction.decouple",
    "skinmap.reconstruction.engine",
    "skinmap.reconstruction.forward",
    "skinmap.reconstruction.graphfit",
    "skinmap.reconstruction.graphsheet",
    "skinmap.reconstruction.grid",
    "skinmap.reconstruction.kernels",
    "skinmap.reconstruction.leaveout",
    "skinmap.reconstruction.linalg",
    "skinmap.reconstruction.productnoise",
    "skinmap.reconstruction.robust",
    "skinmap.reconstruction.surface",
    "skinmap.reconstruction.uncertainty",
    "skinmap.daemon.bridge",
    "skinmap.daemon.calibrate",
    "skinmap.daemon.cli",
    "skinmap.daemon.config",
    "skinmap.daemon.fleet",
    "skinmap.daemon.moldcal",
    "skinmap.daemon.notify",
    "skinmap.daemon.service",
    "skinmap.daemon.gateway",
    "skinmap.daemon.fanout",
    "skinmap.daemon.health",
    "skinmap.daemon.processing",
    "skinmap.daemon.output",
    "skinmap.daemon.pacing",
    "skinmap.daemon.device_setup",
    "skinmap.daemon.publisher",
    "skinmap.daemon.logsink",
    "skinmap.daemon.zenoh_io",
    "skinmap.daemon.mcaplog",
    "skinmap.daemon.mcapfile",
    "skinmap.daemon.mcapschema",
    "skinmap.daemon.rotation",
    "skinmap.daemon.mcapread",
    "skinmap.daemon.mcaprecover",
    "skinmap.daemon.mcapinspect",
    "skinmap.daemon.mcapsnapshot",
]


def make_view() -> Path:
    """build/typecheck/skinmap/... as symbolic links, following pyproject's package-dir."""
    package_dir = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    for name, folder in sorted(package_dir.items(), key=lambda kv: kv[0].count(".")):
        link = VIEW.joinpath(*name.split("."))
        link.parent.mkdir(parents=True, exist_ok=True)
        if name == "skinmap":  # the namespace root holds the subpackages' links: link its files
            link.mkdir(exist_ok=True)
            for f in (ROOT / folder).iterdir():
                if f.is_file():
                    target = link / f.name
                    if not target.is_symlink():
                        target.symlink_to(f)
        elif not link.is_symlink():
            link.symlink_to(ROOT / folder, target_is_directory=True)
    return VIEW


def mypy(targets: list[str]) -> tuple[int, str]:
    args = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"),
            "--python-executable", sys.executable, "--no-error-summary"]
    for t in targets:
        if t.endswith(".__init__"):  # a package's own module, without its submodules
            args += ["-m", t.removesuffix(".__init__")]
        else:
            args += ["-p" if (VIEW / Path(*t.split("."))).is_dir() else "-m", t]
    proc = subprocess.run(args, cwd=make_view(), capture_output=True, text=True,
                          env={**os.environ, "MYPY_CACHE_DIR": str(ROOT / "build" / "mypy-cache")})
    return proc.returncode, proc.stdout + proc.stderr


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", action="store_true", help="also count the errors of the other packages")
    args = parser.parse_args()
    rc, out = mypy(CLEAN)
    errors = [line for line in out.splitlines() if ": error:" in line]
    print(f"mypy on {', '.join(CLEAN)}: {len(errors)} errors")
    if rc != 0:
        print(out)
        return 1
    if args.report:
        for package in ("skinmap.emulator", "skinmap.reconstruction", "skinmap.daemon"):
            _, out = mypy([package])
            files: dict[str, int] = {}
            for line in out.splitlines():
                m = re.match(r"([^:]+\.py):\d+: error:", line)
                if m:
                    files[m.group(1)] = files.get(m.group(1), 0) + 1
            detail = ", ".join(f"{Path(f).name} {n}" for f, n in sorted(files.items(), key=lambda kv: -kv[1]))
            print(f"mypy on {package}: {sum(files.values())} errors ({detail or 'clean'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
