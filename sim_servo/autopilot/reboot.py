"""A reboot of the autopilot (:meth:`Reboot.reboot`, ``reboot_after_s``, the query ``reboot``).

Silent and deaf for ``reboot_gap_s`` (0.36 s, measured on a real reboot), then back with
time_boot from 0, outputs at their boot values, streams at their defaults (requested intervals
lost), an empty routing table and the MAVLink sequence from 0; parameters keep their values and
the vehicle goes on moving. Frames not yet sent are lost.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from sim_servo.autopilot.state import AutopilotState

#: What a part does when a reboot starts (``halt``) or when the autopilot is back (``boot``).
Step = Callable[[float], None]
MAX_GAP_S = 600.0


class Reboot:
    """The reboot's schedule and its gap; ``halt`` and ``boot`` are the parts' steps, run in
    the order given."""

    def __init__(
        self,
        state: AutopilotState,
        *,
        halt: Sequence[Step],
        boot: Sequence[Step],
        now_s: float,
    ) -> None:
        self._state = state
        self._halt = list(halt)
        self._boot = list(boot)
        after_s = state.config.faults.reboot_after_s
        #: The scheduled reboot (``reboot_after_s``), None once done or without one.
        self.due_s: float | None = None if after_s is None else now_s + after_s

    def reboot(self, now_s: float, gap_s: float | None = None) -> bool:
        """Reboot now: silent and deaf for ``gap_s`` (default ``reboot_gap_s``); False
        (nothing done) while already rebooting."""
        state = self._state
        if state.rebooting:
            return False
        gap_s = state.config.faults.reboot_gap_s if gap_s is None else gap_s
        if not 0.0 <= gap_s <= MAX_GAP_S:
            raise ValueError(f"reboot gap_s={gap_s!r} outside [0.0, {MAX_GAP_S}]")
        state.rebooting_until_s = now_s + gap_s
        state.stats["reboots"] += 1
        state.emit(now_s, "fault", fault="reboot", gap_s=gap_s)
        for halt in self._halt:
            halt(now_s)
        if gap_s == 0.0:
            self._come_back(now_s)
        return True

    def run(self, now_s: float) -> None:
        """The scheduled reboot, and the end of the gap, when due by ``now_s``."""
        if self.due_s is not None and self.due_s <= now_s:
            due_s, self.due_s = self.due_s, None
            self.reboot(due_s)
        back_s = self._state.rebooting_until_s
        if back_s is not None and back_s <= now_s:
            self._come_back(back_s)

    def _come_back(self, now_s: float) -> None:
        state = self._state
        state.rebooting_until_s = None
        state.boot_s = now_s
        for boot in self._boot:
            boot(now_s)
        state.emit(now_s, "fault", fault="booted")

    def next_events_s(self) -> list[float]:
        times = [] if self.due_s is None else [self.due_s]
        if self._state.rebooting_until_s is not None:
            times.append(self._state.rebooting_until_s)
        return times
