"""Type-check skinmap with mypy.

The top-level folders are mapped onto the `skinmap` namespace by `package-dir` (protocol/ is
skinmap.protocol, firmware-host/ is skinmap.emulator, ...), which mypy cannot follow from the
source tree. This script makes a view of the package as installed, build/typecheck/skinmap/
(symbolic links to the folders), and runs mypy there.

    python .ci/typecheck.py            # the installed package must have no error (CI)
    python .ci/typecheck.py --report   # and the error count per package
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
    "skinmap",  # the whole installed package: every module is checked
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
