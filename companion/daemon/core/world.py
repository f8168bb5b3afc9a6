"""World-frame targets: the vehicle's telemetry, and a target held in LOCAL_NED followed while
the vehicle moves (solved again each tick for where the vehicle will be when the step lands)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from companion.daemon.requests import Outcome, Reply, Target
from companion.daemon.telemetry import VehicleTelemetry
from companion.kinematics.arm import Pose
from companion.kinematics.vehicle import base_to_world, matrix_to_base

if TYPE_CHECKING:
    from companion.daemon.core.dispatcher import ControlCore

log = logging.getLogger("armbridge")

#: Before any update's round trip was measured, the link's one-way latency is taken as this.
WORLD_DEFAULT_ONE_WAY_S = 0.005
#: The keys of a pose in status and replies, in ``Pose`` order.
POSE_KEYS = ("x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg")


class WorldTargets:
    """The vehicle's telemetry and the world target held (module docstring)."""

    def __init__(self, core: ControlCore) -> None:
        self._core = core
        self.telemetry = VehicleTelemetry()
        #: The target held in the world (None: none), and what following it last found.
        self._target: Target | None = None
        self.note: dict[str, Any] = {}
        self._target_matrix: tuple[Target, Any] | None = None  # the target's 4×4, once

    @property
    def following(self) -> bool:
        return self._target is not None

    def on_frame(self, msg: Any, received_s: float) -> None:
        """An ATTITUDE or LOCAL_POSITION_NED, dated by its arrival."""
        self.telemetry.on_frame(msg, received_s)

    def hold(self, target: Target) -> None:
        """``target`` was accepted: it is followed from now on."""
        self._target = target
        self.note = {"reachable": True, "reason": None}

    def drop(self) -> None:
        self._target = None

    def refusal(self, target: Target) -> Reply | None:
        if not self._core.config.world.enabled:
            return Reply(
                Outcome.DENIED,
                f"frame={target.frame!r}: world-frame targets are off ([world] enabled = false)",
            )
        return None

    def in_base(self, target: Target) -> Pose | None:
        """The world target in the arm's base frame when the next step will reach the
        servos (None: no usable telemetry; ``note["reason"]`` says why)."""
        core = self._core
        now = core.clock()
        state = self.telemetry.state()
        world = core.config.world
        if state is None:
            self.note = {
                "reachable": None,
                "reason": "no vehicle telemetry yet (ATTITUDE and LOCAL_POSITION_NED)",
            }
            return None
        age_ms = 1000.0 * state.age_s(now)
        if age_ms > world.max_age_ms:
            self.note = {
                "reachable": None,
                "reason": f"vehicle telemetry {age_ms:.0f} ms old (world.max_age_ms = "
                f"{world.max_age_ms:g}): holding",
            }
            return None
        one_way_s = core.updates.one_way_s()
        if one_way_s is None:
            one_way_s = WORLD_DEFAULT_ONE_WAY_S
        apply_s = now + one_way_s + world.lead_ms / 1000.0
        if self._target_matrix is None or self._target_matrix[0] is not target:
            self._target_matrix = (target, target.pose.as_matrix())  # held for many ticks
        return matrix_to_base(
            self._target_matrix[1], state.predict(apply_s), core.settings.mount_matrix
        )

    def follow(self) -> None:
        """Each tick: the held world target solved again (warm) for where the vehicle will be.
        Out of reach, or with no fresh telemetry, the arm holds its last goal and status says
        why; it follows again once the target is back within reach."""
        core = self._core
        target = self._target
        assert target is not None
        pose = self.in_base(target)
        if pose is None:
            return
        goal = core.motion.goal
        start = goal if goal is not None else tuple(core.state.position)
        budget_ms = core.settings.world_solve_budget_ms
        result, refusal = core.keepout.solve(pose, start, target.mode, budget_ms)
        core.state.counters["solved"] += 1
        if refusal is None and result is not None and result.converged:
            hit = core.keepout.solution_refusal(result.q_deg)
            refusal = None if hit is None else f"keep-out: {hit}"
        if refusal is not None or result is None:
            self.note = {
                "reachable": False,
                "reason": f"{refusal or 'no solution'}; holding the last clear pose",
            }
            return
        if result.converged:
            core.motion.retarget(result.q_deg)
            self.note = {"reachable": True, "reason": None, "solve_ms": result.elapsed_ms}
            return
        if self.note.get("reachable") is not False:
            log.warning(
                "world target out of reach (pos %.2f cm, ori %.1f deg): holding the last "
                "reachable pose",
                result.pos_err_cm,
                result.ori_err_deg,
            )
        self.note = {
            "reachable": False,
            "reason": f"out of reach: pos {result.pos_err_cm:.2f} cm ori "
            f"{result.ori_err_deg:.1f} deg; holding the last reachable pose",
        }

    def status(
        self, position: tuple[float, ...], hand_at: tuple[tuple[float, ...], dict[str, float]]
    ) -> dict[str, Any]:
        """The world part of status; ``hand_at``: the hand (base frame) at ``position``."""
        core = self._core
        world = core.config.world
        out: dict[str, Any] = {"enabled": world.enabled}
        if not world.enabled:
            return out
        now = core.clock()
        state = self.telemetry.state()
        out["telemetry_age_ms"] = None if state is None else 1000.0 * state.age_s(now)
        out["target"] = (
            None
            if self._target is None
            else {"pose": list(self._target.pose.as_tuple()), "mode": self._target.mode}
        )
        out["following"] = self._target is not None
        out.update(self.note if self._target is not None else {})
        if state is not None and hand_at[0] == position:
            hand = base_to_world(Pose(**hand_at[1]), state.predict(now), core.settings.mount_matrix)
            out["hand_ned"] = dict(zip(POSE_KEYS, hand.as_tuple(), strict=True))
        return out
