"""The daemon's control logic as a state machine: events in, actions out, no I/O.

:class:`ControlCore` owns the arm's state. It is driven by one thread (the daemon's control
thread, :mod:`companion.daemon.service`) with events — a request taken from the intake
(:meth:`~ControlCore.request`), a frame from the autopilot (:meth:`~ControlCore.frame`), a tick
(:meth:`~ControlCore.tick`) — and returns the actions to carry out: commands to send to the
autopilot (:class:`SendCommand`, :class:`ReadParam`) and answers to requests
(:class:`Answer`). Time comes from the injected clock, the solver is injected too, so every
rule is an in-process test with a fake clock.

Each rule has one home:

* :mod:`.dispatcher` — :class:`ControlCore`: the events, handed to the parts below.
* :mod:`.settings` — everything derived from the config, computed by one pure function
  (:meth:`CoreSettings.from_config`) and again on a reload (:meth:`ControlCore.reconfigure`).
* :mod:`.state` — what the parts share (the acknowledged pose and PWMs, the updates in flight),
  and who writes what. **Status is what the autopilot acknowledged**: per output, the PWM the
  autopilot ACCEPTED; per joint, the angle whose PWM it accepted. Motion steps from there, so a
  partial update can neither break the speed limit nor make the status lie.
* :mod:`.updates` — pipelined updates, ACKs counted in order, confirmation one command at a
  time, retries; a refused output stops the motion.
* :mod:`.motion` — the goal, the targets waiting, the steps at the speed limit, trajectories;
  every request gets one answer.
* :mod:`.watch` — the pinned autopilot, reboots, link loss, silences, the streams asked for.
* :mod:`.outputs` — **the outputs tell the truth** (an ACK proves nothing): one interface,
  :mod:`.outputs_px4` (the readback, markers, probes) and :mod:`.outputs_ardupilot` (the safety
  switch, its band and rewind). Coming alive never moves a joint faster than the speed limit.
* :mod:`.world` — world-frame targets followed from the vehicle's telemetry.
* :mod:`.keepout_gate` — targets solved clear of the keep-out volumes, every step's path
  checked.
* :mod:`.status` — the answers, the accepted-log lines, the JSON snapshot.
"""

from companion.daemon.core.actions import Action, Answer, ReadParam, SendCommand
from companion.daemon.core.dispatcher import ControlCore, Solve
from companion.daemon.core.outputs import READBACK_SETTLE_S
from companion.daemon.core.outputs_ardupilot import SYS_STATUS_SILENT_S, SYS_STATUS_WAIT_S
from companion.daemon.core.outputs_px4 import MARKER_OFFSET_US
from companion.daemon.core.settings import (
    READBACK_FAST_INTERVAL_S,
    READBACK_INTERVAL_S,
    SAFETY_STEPS_AHEAD,
    SLOW_LINK_BAUD,
    STOP_STREAM,
    CoreSettings,
    stream_intervals_s,
    stream_requests,
)
from companion.daemon.core.updates import PIPELINE_DEPTH, UPDATE_ATTEMPTS

__all__ = [
    "MARKER_OFFSET_US",
    "PIPELINE_DEPTH",
    "READBACK_FAST_INTERVAL_S",
    "READBACK_INTERVAL_S",
    "READBACK_SETTLE_S",
    "SAFETY_STEPS_AHEAD",
    "SLOW_LINK_BAUD",
    "STOP_STREAM",
    "SYS_STATUS_SILENT_S",
    "SYS_STATUS_WAIT_S",
    "UPDATE_ATTEMPTS",
    "Action",
    "Answer",
    "ControlCore",
    "CoreSettings",
    "ReadParam",
    "SendCommand",
    "Solve",
    "stream_intervals_s",
    "stream_requests",
]
