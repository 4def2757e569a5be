"""The gateway's live status on a console: a fixed panel redrawn in place on a terminal (rich),
one short line per report on a pipe or a file (so journald and tests read plain text).

Lines printed while the panel is shown (the demo's emulator, prefixed ``[emulator]``, and log
records) appear above the panel instead of breaking it.
"""

from __future__ import annotations

import logging
import sys
from typing import Any, TextIO

import numpy as np

__all__ = ["StatusConsole", "shape_summary", "status_line"]


def shape_summary(nodes_mm: np.ndarray | None, elements_mm: np.ndarray | None) -> dict[str, Any]:
    """The few numbers that show the shape: z range of the nodes, first and last element."""
    out: dict[str, Any] = {}
    if nodes_mm is not None and np.size(nodes_mm):
        z = np.asarray(nodes_mm)[..., 2]
        out["z_mm"] = (float(np.nanmin(z)), float(np.nanmax(z)))
    if elements_mm is not None and len(elements_mm):
        out["first_mm"] = tuple(float(v) for v in elements_mm[0])
        out["last_mm"] = tuple(float(v) for v in elements_mm[-1])
    return out


def _xyz(p: Any) -> str:
    return "(" + ", ".join(f"{v:+.1f}" for v in p) + ")"


def status_line(st: dict[str, Any], shape: dict[str, Any]) -> str:
    """One line of at most about 100 characters: state, rates, seq, latency, problems."""
    problems = len(st.get("warnings") or [])
    z = shape.get("z_mm")
    ztext = f" z {z[0]:+.1f}..{z[1]:+.1f} mm" if z else ""
    return (f"[{st.get('link_state', '?')}] {st.get('scan_rate_hz', 0):.0f} scans/s "
            f"{st.get('publish_rate_hz', 0):.1f} Hz seq {st.get('seq', 0)} "
            f"solver {st.get('solver_time_ms', 0):.1f} ms p99 {st.get('latency_ms_p99', 0):.0f} ms "
            f"drop {st.get('frames_dropped', 0)} log {st.get('log_state', '?')}"
            f"{ztext}{f' WARN {problems}' if problems else ''}")


class StatusConsole:
    """Shows status reports: ``update(status, shape_summary)``; ``close()`` when done."""

    def __init__(self, stream: TextIO | None = None, *, force_panel: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stdout
        tty = self.stream.isatty() if hasattr(self.stream, "isatty") else False
        self.panel = tty if force_panel is None else force_panel
        self._live: Any = None
        self._handlers: list[tuple[logging.StreamHandler, Any]] = []

    def _start(self) -> None:
        from rich.console import Console
        from rich.live import Live

        console = Console(file=self.stream, force_terminal=self.panel)
        self._live = Live(console=console, auto_refresh=False, redirect_stdout=True,
                          redirect_stderr=True, transient=False)
        self._live.start()
        # Log records go through the redirected streams, so they print above the panel.
        for handler in logging.getLogger().handlers:
            if isinstance(handler, logging.StreamHandler) and handler.stream in (
                    sys.__stderr__, sys.__stdout__):
                target = sys.stderr if handler.stream is sys.__stderr__ else sys.stdout
                self._handlers.append((handler, handler.setStream(target)))

    def render(self, st: dict[str, Any], shape: dict[str, Any]) -> Any:
        """The panel for one report (a rich renderable)."""
        from rich.panel import Panel
        from rich.table import Table

        table = Table.grid(padding=(0, 2))
        for style in ("bold", None, "bold", None):
            table.add_column(style=style, no_wrap=True)
        lat = f"p50 {st.get('latency_ms_p50', 0):.1f}  p99 {st.get('latency_ms_p99', 0):.1f} ms" \
            if "latency_ms_p50" in st else f"p99 {st.get('latency_ms_p99', 0):.1f} ms"
        rows = [
            ("link", str(st.get("link_state", "?")), "seq", str(st.get("seq", 0))),
            ("scans", f"{st.get('scan_rate_hz', 0):.1f}/s", "published",
             f"{st.get('publish_rate_hz', 0):.1f}/s"),
            ("solver", f"{st.get('solver_time_ms', 0):.2f} ms", "latency", lat),
            ("dropped", str(st.get("frames_dropped", 0)), "crc / reconnects",
             f"{st.get('crc_errors', 0)} / {st.get('reconnects', 0)}"),
            ("log", str(st.get("log_state", "?")), "z range",
             "{:+.2f} .. {:+.2f} mm".format(*shape["z_mm"]) if "z_mm" in shape else "-"),
        ]
        if "first_mm" in shape:
            rows.append(("first element", _xyz(shape["first_mm"]) + " mm", "last element",
                         _xyz(shape["last_mm"]) + " mm"))
        for row in rows:
            table.add_row(*row)
        warnings = st.get("warnings") or []
        for text in warnings[:4]:
            table.add_row("[yellow]warning[/]", f"[yellow]{text}[/]", "", "")
        title = f"skinmapd {st.get('device', '')}"
        return Panel(table, title=title, border_style="yellow" if warnings else "green",
                     expand=False)

    def update(self, st: dict[str, Any], shape: dict[str, Any]) -> None:
        if not self.panel:
            print(status_line(st, shape), file=self.stream, flush=True)
            return
        if self._live is None:
            self._start()
        self._live.update(self.render(st, shape), refresh=True)

    def close(self) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None
        for handler, previous in self._handlers:
            handler.setStream(previous)
        self._handlers.clear()
