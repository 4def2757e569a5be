"""When a log file ends and what files are called: `RotationPolicy`, separate from the writer.

Files are named `<basename>-<UTC yyyymmddThhmmssZ>-<index:04d>.mcap.active` while being
written and renamed to `.mcap` when finished. A file ends when it would reach `max_bytes` or
has been open `max_seconds`.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

__all__ = ["RotationPolicy", "ACTIVE_SUFFIX", "FINISHED_SUFFIX", "final_name"]

ACTIVE_SUFFIX = ".mcap.active"
FINISHED_SUFFIX = ".mcap"
MiB = 1024 * 1024


def final_name(path: str) -> str:
    """The finished name of a file being written: `x.mcap.active` -> `x.mcap`."""
    if not path.endswith(ACTIVE_SUFFIX):
        raise ValueError(f"{path!r} does not end with {ACTIVE_SUFFIX!r}")
    return path[: -len(ACTIVE_SUFFIX)] + FINISHED_SUFFIX


@dataclass
class RotationPolicy:
    """Size and age limits of one file, and the names of the files in turn."""

    basename: str = "skinmap"
    max_bytes: int = 256 * MiB
    max_seconds: float = 3600.0
    file_index: int = field(default=0, init=False)  # the index of the latest name handed out

    def __post_init__(self) -> None:
        b = self.basename
        if not isinstance(b, str) or not b or os.sep in b or (os.altsep and os.altsep in b):
            raise ValueError(f"basename must be a plain file-name prefix, got {b!r}")
        if isinstance(self.max_bytes, bool) or not isinstance(self.max_bytes, int) or self.max_bytes < 4096:
            raise ValueError(f"max_bytes must be an integer >= 4096, got {self.max_bytes!r}")
        if not self.max_seconds > 0:
            raise ValueError(f"max_seconds must be > 0, got {self.max_seconds!r}")
        self.max_seconds = float(self.max_seconds)

    def due(self, size_bytes: int, open_ns: int) -> bool:
        """Whether a file of `size_bytes` (written and pending), open for `open_ns`, ends now."""
        return size_bytes >= self.max_bytes or open_ns >= self.max_seconds * 1e9

    def next_path(self, directory: str, unix_ns: int) -> str:
        """A new `.mcap.active` path in `directory` that is not taken (as active or finished)."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(unix_ns / 1e9))
        while True:
            self.file_index += 1
            path = os.path.join(directory, f"{self.basename}-{stamp}-{self.file_index:04d}{ACTIVE_SUFFIX}")
            if not os.path.exists(path) and not os.path.exists(final_name(path)):
                return path
