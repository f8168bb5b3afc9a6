"""Servo positions → joint angles (the daemon's calibration) → hand pose (the arm's FK).

The calibration is built exactly as the daemon builds it: the arm's joint limits (degrees) mapped
linearly onto ``[pwm_min_us, pwm_max_us]`` of each joint's output by
:func:`firmware_interface.calibration.calibration_from_ranges`. A horn position outside its
joint's PWM range has no angle under that calibration: the hand is then reported as unknown with
the calibration's own message, never extrapolated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from companion.kinematics.arm import Arm, Pose
from firmware_interface.calibration import ArmCalibration, calibration_from_ranges
from firmware_interface.errors import CalibrationError, ConfigurationError
from sim_servo.config import ArmConfig
from sim_servo.errors import SimConfigError


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
    """Computes the hand from ``{output: horn position µs}``."""

    def __init__(self, arm: Arm, calibration: ArmCalibration) -> None:
        if len(calibration) != arm.dof:
            raise SimConfigError(
                f"calibration has {len(calibration)} joints, arm {arm.name!r} has {arm.dof}"
            )
        self.arm = arm
        self.calibration = calibration

    @classmethod
    def from_config(cls, config: ArmConfig) -> HandModel:
        """The arm (default or ``config.arm_file``) and its calibration onto ``config.outputs``."""
        try:
            arm = Arm.default() if config.arm_file is None else Arm.from_toml(config.arm_file)
        except (OSError, ValueError) as exc:  # ArmConfigError is a ValueError
            raise SimConfigError(f"cannot load arm: {exc}") from exc
        if len(config.outputs) != arm.dof:
            raise SimConfigError(
                f"arm outputs={list(config.outputs)} name {len(config.outputs)} outputs; "
                f"arm {arm.name!r} has {arm.dof} joints"
            )
        ranges = [(math.degrees(j.min_rad), math.degrees(j.max_rad)) for j in arm.joints]
        try:
            calibration = calibration_from_ranges(
                ranges,
                outputs=config.outputs,
                pwm_min_us=config.pwm_min_us,
                pwm_max_us=config.pwm_max_us,
                reversed_joints=config.reversed_joints,
                trims_us=config.trims_us,
            )
        except ConfigurationError as exc:
            raise SimConfigError(f"arm calibration: {exc}") from exc
        return cls(arm, calibration)

    @property
    def outputs(self) -> tuple[int, ...]:
        return self.calibration.outputs

    def deg_per_us(self, output: int) -> float:
        """Horn travel per µs on a calibrated output (the joint span over the PWM span)."""
        joint = self.calibration.for_output(output)
        return (joint.angle_max_deg - joint.angle_min_deg) / (joint.pwm_max_us - joint.pwm_min_us)

    def state(self, position_us: Mapping[int, float]) -> HandState:
        """The hand for horn positions ``{output: µs}`` (every calibrated output needed)."""
        try:
            angles = self.calibration.pwm_us_to_angles_deg(
                {output: position_us[output] for output in self.outputs}
            )
        except CalibrationError as exc:
            return HandState(angles_deg=None, pose=None, error=str(exc))
        ordered = [angles[joint.name] for joint in self.calibration.joints]
        return HandState(angles_deg=angles, pose=self.arm.fk(ordered), error=None)
