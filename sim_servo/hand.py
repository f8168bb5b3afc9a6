"""Servo horn positions (PWM µs) → joint angles (degrees) → hand pose (the arm's FK).

The simulator's own servo model, the physical truth the daemon's calibration is tested against:
it shares no code with the daemon, only the kinematics (:mod:`companion.kinematics`).

Each joint ``theta1``, ``theta2``, … (in arm order) is driven by one output. Its servo sweeps the
joint's whole range, from its lower limit to its upper limit, as the pulse goes linearly from
``pwm_min_us`` to ``pwm_max_us`` (from ``pwm_max_us`` to ``pwm_min_us`` if the joint is
reversed). A trim of ``trim_us`` shifts that sweep along the pulse axis: the horn is where the
untrimmed pulse ``pwm_us - trim_us`` would put it. The servo accepts only pulses within
``[pwm_min_us, pwm_max_us]``; a horn position outside that range has no joint angle, and the
hand is then reported as unknown with a message naming the output, the PWM and the allowed
range — never extrapolated. With a trim, the ends of the PWM range give angles slightly beyond
the joint's limits; they are reported as they are, since that is where the horn is.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from companion.kinematics import Arm, Pose
from sim_servo.config import ArmConfig
from sim_servo.errors import ServoPwmOutOfRange, SimConfigError


def joint_name(index: int) -> str:
    """The name of the joint at 0-based ``index`` in arm order: ``theta1``, ``theta2``, …"""
    return f"theta{index + 1}"


@dataclass(frozen=True)
class JointServo:
    """One joint's servo: the joint angle (degrees) its horn is at for a pulse width (µs).

    Built by :meth:`HandModel.from_config` from a validated :class:`ArmConfig` and the arm's joint
    limits, so the fields are not checked again here.
    """

    name: str
    output: int
    pwm_min_us: int
    pwm_max_us: int
    angle_min_deg: float
    angle_max_deg: float
    reversed: bool = False
    trim_us: int = 0

    @property
    def deg_per_us(self) -> float:
        """Horn travel in degrees per µs of pulse width (always positive)."""
        return (self.angle_max_deg - self.angle_min_deg) / (self.pwm_max_us - self.pwm_min_us)

    def angle_deg(self, pwm_us: float) -> float:
        """The joint angle (degrees) at pulse width ``pwm_us`` (µs).

        Raises :class:`ServoPwmOutOfRange` if ``pwm_us`` is outside ``[pwm_min_us, pwm_max_us]``
        (or not a number): the servo has no position for it.
        """
        # Written so that NaN fails the test too.
        if not self.pwm_min_us <= pwm_us <= self.pwm_max_us:
            raise ServoPwmOutOfRange(
                f"pwm_us={pwm_us!r} outside [{self.pwm_min_us}, {self.pwm_max_us}] "
                f"for joint {self.name!r} (servo output {self.output})"
            )
        # How far along its sweep the horn is: 0 at the lower joint limit, 1 at the upper one.
        sweep = (pwm_us - self.trim_us - self.pwm_min_us) / (self.pwm_max_us - self.pwm_min_us)
        if self.reversed:
            sweep = 1.0 - sweep
        return self.angle_min_deg + sweep * (self.angle_max_deg - self.angle_min_deg)


@dataclass(frozen=True)
class HandState:
    """Joint angles (degrees, by joint name) and hand pose, or why they are unknown."""

    angles_deg: Mapping[str, float] | None
    pose: Pose | None
    error: str | None

    def as_dict(self) -> dict[str, Any]:
        pose = None
        if self.pose is not None:
            pose = {
                name: getattr(self.pose, name)
                for name in ("x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg")
            }
        return {
            "angles_deg": dict(self.angles_deg) if self.angles_deg is not None else None,
            "pose": pose,
            "error": self.error,
        }


class HandModel:
    """Computes the hand from ``{output: horn position µs}``: one :class:`JointServo` per joint."""

    def __init__(self, arm: Arm, joints: tuple[JointServo, ...]) -> None:
        joints = tuple(joints)
        if len(joints) != arm.dof:
            raise SimConfigError(f"{len(joints)} joint servos, arm {arm.name!r} has {arm.dof}")
        self.arm = arm
        self.joints = joints
        self._by_output = {joint.output: joint for joint in joints}
        if len(self._by_output) != len(joints):
            raise SimConfigError(f"joint servos repeat an output: {[j.output for j in joints]}")

    @classmethod
    def from_config(cls, config: ArmConfig) -> HandModel:
        """The arm (default or ``config.arm_file``) with its joints' servos on ``config.outputs``.

        Each joint sweeps its limits over ``[config.pwm_min_us, config.pwm_max_us]``.
        """
        try:
            arm = Arm.default() if config.arm_file is None else Arm.from_toml(config.arm_file)
        except (OSError, ValueError) as exc:  # ArmConfigError is a ValueError
            raise SimConfigError(f"cannot load arm: {exc}") from exc
        if len(config.outputs) != arm.dof:
            raise SimConfigError(
                f"arm outputs={list(config.outputs)} name {len(config.outputs)} outputs; "
                f"arm {arm.name!r} has {arm.dof} joints"
            )
        names = [joint_name(index) for index in range(arm.dof)]
        # Joint names are only known once the arm is loaded, so they are checked here.
        for field, given in (("reversed", config.reversed_joints), ("trims_us", config.trims_us)):
            unknown = sorted(set(given) - set(names))
            if unknown:
                raise SimConfigError(
                    f"arm {field} names unknown joints {unknown}; the arm's joints are {names}"
                )
        joints = tuple(
            JointServo(
                name=name,
                output=output,
                pwm_min_us=config.pwm_min_us,
                pwm_max_us=config.pwm_max_us,
                angle_min_deg=math.degrees(arm_joint.min_rad),
                angle_max_deg=math.degrees(arm_joint.max_rad),
                reversed=name in config.reversed_joints,
                trim_us=config.trims_us.get(name, 0),
            )
            for name, output, arm_joint in zip(names, config.outputs, arm.joints, strict=True)
        )
        return cls(arm, joints)

    @property
    def outputs(self) -> tuple[int, ...]:
        """The outputs driving the joints, in joint order."""
        return tuple(joint.output for joint in self.joints)

    def joint_for_output(self, output: int) -> JointServo:
        """The servo of the joint on ``output``; :class:`KeyError` if no joint is on it."""
        try:
            return self._by_output[output]
        except KeyError:
            raise KeyError(
                f"output {output} drives no joint; arm outputs are {self.outputs}"
            ) from None

    def deg_per_us(self, output: int) -> float:
        """Horn travel in degrees per µs on an arm output (the joint span over the PWM span)."""
        return self.joint_for_output(output).deg_per_us

    def state(self, position_us: Mapping[int, float]) -> HandState:
        """The hand for horn positions ``{output: µs}`` (every arm output needed).

        Unknown (angles and pose None, ``error`` saying why) as soon as one horn is outside its
        joint's PWM range; the first such joint in arm order is named.
        """
        angles_deg: dict[str, float] = {}
        for joint in self.joints:
            try:
                angles_deg[joint.name] = joint.angle_deg(position_us[joint.output])
            except ServoPwmOutOfRange as exc:
                return HandState(angles_deg=None, pose=None, error=str(exc))
        return HandState(
            angles_deg=angles_deg, pose=self.arm.fk(list(angles_deg.values())), error=None
        )
