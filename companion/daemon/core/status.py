"""Status: the answers to requests (counted, and logged when accepted), the last target, and
the JSON snapshot of the acknowledged state."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

from companion.daemon.core.actions import Action, Answer
from companion.daemon.core.world import POSE_KEYS
from companion.daemon.requests import LATCH_KINDS, MOTION_KINDS, Outcome, Reply, Request

if TYPE_CHECKING:
    from companion.daemon.core.dispatcher import ControlCore

log = logging.getLogger("armbridge")

#: At most one "accepted" log line per second per kind and source for motion requests.
ACCEPT_LOG_INTERVAL_S = 1.0
#: Kinds and sources remembered for the "accepted" log lines, at most (sources come and go).
ACCEPT_LOG_SOURCES = 256


class StatusAndAnswers:
    """Answers requests, and builds the status snapshot (module docstring)."""

    def __init__(self, core: ControlCore) -> None:
        self._core = core
        #: The last target solved, for status and the log (None: none yet).
        self.last_target: dict[str, Any] | None = None
        #: The request the last target came with (None: a trajectory's point).
        self.last_target_request: Request | None = None
        #: The hand (base frame) at a pose, computed once per pose.
        self._hand_at: tuple[tuple[float, ...], dict[str, float]] | None = None
        #: (kind, source) → (when its last "accepted" line was logged, how many since)
        self._accept_log: dict[tuple[str, Any], tuple[float, int]] = {}

    def answer(self, actions: list[Action], request: Request, reply: Reply) -> None:
        actions.append(Answer(request, reply))
        if request is self.last_target_request and self.last_target is not None:
            self.last_target = {
                **self.last_target,
                "outcome": reply.outcome.value,
                "answer": reply.message,
            }
        if reply.outcome is Outcome.ACCEPTED:
            self._log_accepted(request, reply)
        if request.kind not in LATCH_KINDS:
            self._core.state.counters[reply.outcome.value] += 1

    def record_first_out(self, timing: dict[str, float]) -> None:
        """The last target's first update went out and was acknowledged (``timing``)."""
        last = self.last_target
        if last is not None and "first_out_s" not in last["timing"]:
            self.last_target = {**last, "timing": {**last["timing"], **timing}}

    def _log_accepted(self, request: Request, reply: Reply) -> None:
        """One line per request carried out (refusals are summarised by the intake), but a
        stream of targets (50 Hz from a ground station) at most one line per second per kind
        and source, saying how many it stood for: the journal of a board on an SD card."""
        key = (request.kind, request.source)
        now = self._core.clock()
        last_s, skipped = self._accept_log.get(key, (-math.inf, 0))
        if request.kind in MOTION_KINDS and now - last_s < ACCEPT_LOG_INTERVAL_S:
            self._accept_log[key] = (last_s, skipped + 1)
            return
        if len(self._accept_log) >= ACCEPT_LOG_SOURCES:
            self._accept_log.clear()
        self._accept_log[key] = (now, 0)
        target = ""
        if request.kind == "goto" and self.last_target is not None:
            target = " (" + ", ".join(f"{v:.2f}" for v in self.last_target["pose"]) + ")"
            if self.last_target.get("mode", "pose") != "pose":
                target += f" {self.last_target['mode']}"
        more = f" (and {skipped} more since the last line)" if skipped else ""
        log.info(
            "%s%s from %s accepted: %s%s",
            request.kind,
            target,
            source_name(request),
            reply.message,
            more,
        )

    def snapshot(self) -> dict[str, Any]:
        """A JSON-ready snapshot (build it on the driving thread)."""
        core = self._core
        state, outputs_truth, motion, watch = core.state, core.outputs, core.motion, core.watch
        now = core.clock()
        dead = {**outputs_truth.unknown(now), **outputs_truth.dead()}
        # Only what the outputs showed: with no autopilot heard, or its link down, nothing.
        if watch.pinned is None:
            dead = dict.fromkeys(state.outputs, "not known live (no autopilot heard)")
        elif not state.link_up:
            dead = dict.fromkeys(state.outputs, "not known live (autopilot link down)")
        for output, why in state.refused.items():  # what it said outweighs what is unknown
            dead[output] = f"refused by the autopilot: {why}"
        outputs = {}
        for output in state.outputs:
            if output in state.refused:
                entry: dict[str, Any] = {"state": "refused", "reason": state.refused[output]}
            elif output in state.acked_pwm:
                entry = {"state": "acknowledged"}
            else:
                entry = {"state": "unknown"}
            outputs[output] = {
                "pwm_us": state.acked_pwm.get(output),
                **entry,
                "shown_us": outputs_truth.shown.get(output),
                "live": output not in dead,
            }
        position = tuple(state.position)
        if self._hand_at is None or self._hand_at[0] != position:
            hand = core.config.arm.fk(position)
            self._hand_at = (position, dict(zip(POSE_KEYS, hand.as_tuple(), strict=True)))
        goal = motion.goal
        return {
            "autopilot": list(watch.pinned) if watch.pinned else None,
            # Its uptime by the last SYSTEM_TIME (None until one came): reboots are seen from it.
            "autopilot_boot_ms": watch.boot_ms,
            "autopilot_heard_us": watch.heard_us_on_link,
            "holding": not state.link_up and state.ever_sent,
            "current_deg": list(position),
            # The hand where the acknowledged joints put it (forward kinematics of current_deg).
            "hand": dict(self._hand_at[1]),
            "goal_deg": list(goal) if goal is not None else None,
            "moving": motion.moving(position),
            "last_pwm_us": dict(state.acked_pwm) or None,
            # What the outputs do: not live = disarmed / safety on, with why.
            "outputs_live": not dead,
            "not_live": {str(o): why for o, why in sorted(dead.items())},
            "armed": watch.armed,
            "safety_on": outputs_truth.safety_on,
            # The last output the readback showed set by another sender (ArduPilot).
            "foreign_command": outputs_truth.foreign_command,
            "outputs": outputs,
            "last_target": self.last_target,
            "trajectory_points_left": len(motion.trajectory),
            "trajectory_aborted": motion.trajectory_aborted,
            # World-frame targets: the one held, whether it is within reach, the telemetry's
            # age, the hand in LOCAL_NED by the acknowledged joints.
            "world": core.world.status(position, self._hand_at),
            "counters": dict(state.counters),
        }


def source_name(request: Request) -> str:
    """Who asked, for a log line: ``mavlink 255/190``, ``socket 3``."""
    kind, *ids = request.source or ("unknown",)
    return f"{kind} {'/'.join(str(i) for i in ids)}".strip()
