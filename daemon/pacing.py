"""Output pacing on the host clock."""
from __future__ import annotations

__all__ = ["HostDecimator"]


class HostDecimator:
    """Chooses the scans to process from the HOST clock at their arrival: the output keeps its
    rate whatever the scanner's clock does (replay picks the same scans from the logged strains).

    A scan up to a quarter period early still counts (arrival jitter, scans read in bursts), so
    an output rate equal to the scan rate passes every scan. rate_hz = 0 passes every scan.
    """

    def __init__(self, rate_hz: float) -> None:
        self.period_ns = 0 if rate_hz <= 0 else int(round(1e9 / rate_hz))
        self._next_due: int | None = None

    def due(self, host_mono_ns: int) -> bool:
        if self.period_ns == 0:
            return True
        if self._next_due is None or host_mono_ns >= self._next_due + 4 * self.period_ns:
            self._next_due = host_mono_ns  # first scan or a long gap: restart the schedule here
        if host_mono_ns >= self._next_due - self.period_ns // 4:
            self._next_due += self.period_ns
            return True
        return False

    def ahead(self, host_mono_ns: int, lead_ns: int) -> bool:
        """Whether a scan that :meth:`due` just passed over arrives within ``lead_ns`` before
        the next due scan's window opens (a lead scan: reconstructed, not published)."""
        if self.period_ns == 0 or self._next_due is None or lead_ns <= 0:
            return False
        opens = self._next_due - self.period_ns // 4
        return opens - lead_ns <= host_mono_ns < opens
