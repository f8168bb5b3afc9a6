"""The I/O loop: owns the endpoints and the query socket, hands bytes to the autopilot.

One thread, one ``select``: it waits until a descriptor is readable or the autopilot's next
event is due, feeds what arrived to :meth:`SimAutopilot.receive` (tagged with the link it came
on: 0 for the companion's endpoint, 1 for the optional ground-station endpoint), writes each
frame :meth:`SimAutopilot.poll` returns to the link it names (when frames leave, and on which
links, is the autopilot's decision), answers queries and applies the hang-up fault (to the
companion's endpoint). Nothing here decides protocol behaviour. An exception from the
autopilot ends the loop; it is logged as an ``error`` event and :meth:`SimServer.run` returns 1.
"""

from __future__ import annotations

import logging
import os
import select
import time
import traceback
from collections.abc import Callable
from typing import Any

from sim_servo.autopilot import SimAutopilot
from sim_servo.endpoints import Endpoint
from sim_servo.eventlog import EventLog
from sim_servo.faults import HangupSchedule
from sim_servo.query import QueryServer

log = logging.getLogger(__name__)
#: Longest sleep between two looks at the clock (bounds the hang-up fault's lateness).
MAX_WAIT_S = 0.1


class SimServer:
    """Runs ``autopilot`` over ``endpoint`` until :meth:`stop` (or a signal via ``wakeup_fd``)."""

    def __init__(
        self,
        autopilot: SimAutopilot,
        endpoint: Endpoint,
        events: EventLog,
        *,
        gcs: Endpoint | None = None,
        query_path: str | None = None,
        hangup_after_s: float | None = None,
        hangup_for_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        start_s: float | None = None,
    ) -> None:
        self.autopilot = autopilot
        self.endpoint = endpoint
        self.gcs = gcs
        #: The links by channel number: 0 the companion's, 1 the ground station's.
        self.links: list[Endpoint] = [endpoint] + ([gcs] if gcs is not None else [])
        autopilot.set_links(len(self.links))
        self.events = events
        self.clock = clock
        self._start_s = clock() if start_s is None else start_s
        self._hangup = HangupSchedule(self._start_s, hangup_after_s, hangup_for_s)
        self._stopping = False
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self.query = QueryServer(query_path, self._respond) if query_path else None

    @property
    def wakeup_fd(self) -> int:
        """Write end of the self-pipe, for ``signal.set_wakeup_fd``."""
        return self._wake_w

    def stop(self) -> None:
        """Ask the loop to end (safe from a signal handler or another thread)."""
        self._stopping = True
        try:
            os.write(self._wake_w, b"\0")
        except OSError:
            pass

    def _respond(self, request: str, args: dict[str, Any]) -> dict[str, Any]:
        try:
            return self._answer(request, args)
        finally:
            self.events.flush()  # what the asker reads next includes what it just caused

    def _answer(self, request: str, args: dict[str, Any]) -> dict[str, Any]:
        if request == "state":
            state = self.autopilot.snapshot(self.clock())
            state["link"] = {
                "url": self.endpoint.url,
                "closed": self.endpoint.closed,
                "dropped_writes": self.endpoint.dropped_writes,
            }
            if self.gcs is not None:
                state["gcs_link"] = {
                    "url": self.gcs.url,
                    "closed": self.gcs.closed,
                    "dropped_writes": self.gcs.dropped_writes,
                }
            return state
        if request == "events":
            return {"events": list(self.events.recent)}
        if request in ("pause_heartbeat", "resume_heartbeat"):
            self.autopilot.pause_heartbeat(request == "pause_heartbeat", self.clock())
        if request == "reboot":
            return {"ok": self.autopilot.reboot(self.clock())}
        if request == "hangup":
            return {"ok": self._hangup.hang_up_now(self.clock())}
        if request in ("arm", "disarm", "kill"):
            cause = "kill" if request == "kill" else "query"
            return {"ok": self.autopilot.set_armed(request == "arm", self.clock(), cause=cause)}
        if request in ("safety_on", "safety_off"):
            return {"ok": self.autopilot.set_safety(request == "safety_on", self.clock())}
        if request == "forge":
            try:
                self.autopilot.forge(args, self.clock())
            except ValueError as exc:
                return {"error": f"forge: {exc}"}
        return {"ok": True}

    def run(self) -> int:
        """Serve until stopped; 0 on a requested stop, 1 if the protocol code failed."""
        try:
            while not self._stopping:
                self._step()
            return 0
        except Exception as exc:  # protocol code failed: end cleanly, keep the cause
            now = self.clock()
            self.autopilot.emit(now, "error", error=repr(exc), traceback=traceback.format_exc())
            log.error("simulator stopped on an error: %r", exc)
            return 1
        finally:
            self.close()

    def _step(self) -> None:
        now = self.clock()
        wait_s = min(MAX_WAIT_S, self.autopilot.next_event_s(now) - now)
        wait_s = min(wait_s, self._hangup.next_s() - now)
        for link in self.links:  # a modelled serial line's next byte boundary
            if (due := link.next_event_s()) is not None:
                wait_s = min(wait_s, due - now)
        link_fds = {fd: channel for channel, link in enumerate(self.links) for fd in link.fds()}
        query_fds = self.query.fds() if self.query else []
        readable, _, _ = select.select(
            [self._wake_r, *link_fds, *query_fds], [], [], max(0.0, wait_s)
        )
        now = self.clock()
        for fd in readable:
            if fd == self._wake_r:
                try:
                    os.read(self._wake_r, 512)
                except BlockingIOError:
                    pass
            elif fd in link_fds:
                channel = link_fds[fd]
                data = self.links[channel].read_ready(fd)
                if data:
                    self.autopilot.receive(data, now, channel)
            elif self.query is not None:
                self.query.handle(fd)
        for fault in self._hangup.due(now):
            if fault == HangupSchedule.REOPEN:
                self.endpoint.reopen()
            else:
                self.endpoint.close()
            self.autopilot.emit(now, "fault", fault=fault, url=self.endpoint.url)
        for channel, link in enumerate(self.links):  # bytes a serial line delivers now
            if data := link.service(now):
                self.autopilot.receive(data, now, channel)
        for channel, frame in self.autopilot.poll(now):
            self.links[channel].write(frame)
        self.events.flush()  # after the frames: they never wait for the log

    def close(self) -> None:
        for link in self.links:
            link.close()
        if self.query is not None:
            self.query.close()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
