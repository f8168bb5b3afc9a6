"""Joint angle ↔ servo PWM calibration: the one place where PWM is range-checked.

Each joint maps its angle range [angle_min_deg, angle_max_deg] linearly onto
[pwm_min_us, pwm_max_us] (or the other way round when ``reversed``), then adds ``trim_us``.
Nothing is ever clamped: a NaN or infinite angle, an angle outside the joint's range, or a PWM
that would fall outside [pwm_min_us, pwm_max_us] (possible only with a non-zero trim) raises a
:class:`~firmware_interface.errors.CalibrationError` naming the joint, its output, the value and
the allowed range. ArduPilot does not clamp DO_SET_SERVO values, so this check is the only one.

Rounding: PWM travels as an integer number of microseconds. The exact value is rounded to the
nearest µs with halves rounded up (``floor(x + 0.5)``), so the round trip angle → PWM → angle is
exact to within half a microsecond's worth of angle: ``0.5 * angle_span_deg / pwm_span_us``.

This module knows nothing of the arm model: joint ranges come in as plain numbers.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from firmware_interface.errors import (
    AngleOutOfRange,
    ConfigurationError,
    NonFiniteAngle,
    PwmOutOfRange,
    SettingError,
)
from tomlfields import check_boolean, check_integer, check_number, is_int, is_real

#: Servo output numbers ArduPilot addresses with DO_SET_SERVO (SERVO1…SERVO16).
OUTPUT_MIN = 1
OUTPUT_MAX = 16
#: Sanity bounds for a calibration's PWM limits; hobby servos live well inside them.
PWM_LIMIT_MIN_US = 500
PWM_LIMIT_MAX_US = 2500
#: Sanity bound for joint angle limits.
ANGLE_LIMIT_DEG = 360.0

#: Table 2 of the arm paper: joint ranges θ1…θ6 in degrees.
TABLE2_RANGES_DEG: tuple[tuple[float, float], ...] = (
    (-90.0, 90.0),
    (0.0, 180.0),
    (-90.0, 90.0),
    (-90.0, 90.0),
    (-90.0, 90.0),
    (-70.0, 90.0),
)
#: Outputs 1–4 drive the motors of a quad; the arm uses the next six by default.
DEFAULT_OUTPUTS: tuple[int, ...] = (9, 10, 11, 12, 13, 14)
DEFAULT_PWM_MIN_US = 1000
DEFAULT_PWM_MAX_US = 2000


def round_half_up_us(pwm_exact_us: float) -> int:
    """Round an exact PWM to the integer µs sent on the wire (nearest, halves up)."""
    return math.floor(pwm_exact_us + 0.5)


@dataclass(frozen=True)
class JointCalibration:
    """How one joint's angle becomes one servo output's PWM.

    ``angle_min_deg`` maps to ``pwm_min_us`` and ``angle_max_deg`` to ``pwm_max_us`` (swapped
    when ``reversed``); ``trim_us`` is then added. ``output`` is the 1-based servo output number.
    """

    name: str
    output: int
    angle_min_deg: float
    angle_max_deg: float
    pwm_min_us: int = DEFAULT_PWM_MIN_US
    pwm_max_us: int = DEFAULT_PWM_MAX_US
    reversed: bool = False
    trim_us: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise SettingError("joint", "name", f"must be a non-empty string, got {self.name!r}")
        where = f"joint {self.name!r}"
        check_integer(
            self.output,
            "output",
            min_value=OUTPUT_MIN,
            max_value=OUTPUT_MAX,
            error=SettingError,
            source=where,
        )
        for label in ("angle_min_deg", "angle_max_deg"):
            check_number(
                getattr(self, label),
                label,
                min_value=-ANGLE_LIMIT_DEG,
                max_value=ANGLE_LIMIT_DEG,
                unit="deg",
                error=SettingError,
                source=where,
            )
        if not self.angle_min_deg < self.angle_max_deg:
            raise SettingError(
                where,
                "angle_min_deg",
                f"{self.angle_min_deg!r} must be below angle_max_deg = {self.angle_max_deg!r}",
            )
        for label in ("pwm_min_us", "pwm_max_us"):
            check_integer(
                getattr(self, label),
                label,
                min_value=PWM_LIMIT_MIN_US,
                max_value=PWM_LIMIT_MAX_US,
                unit="µs",
                error=SettingError,
                source=where,
            )
        if not self.pwm_min_us < self.pwm_max_us:
            raise SettingError(
                where,
                "pwm_min_us",
                f"{self.pwm_min_us} must be below pwm_max_us = {self.pwm_max_us}",
            )
        check_boolean(self.reversed, "reversed", error=SettingError, source=where)
        # Beyond half the span the joint's mid-range would leave the PWM range.
        half_span = (self.pwm_max_us - self.pwm_min_us) // 2
        check_integer(
            self.trim_us,
            "trim_us",
            min_value=-half_span,
            max_value=half_span,
            unit="µs",
            error=SettingError,
            source=where,
        )

    @property
    def pwm_range_us(self) -> tuple[int, int]:
        """The servo's allowed PWM range ``(pwm_min_us, pwm_max_us)``."""
        return (self.pwm_min_us, self.pwm_max_us)

    def _describe(self) -> str:
        return f"joint {self.name!r} (servo output {self.output})"

    def check_angle_deg(self, angle_deg: float) -> float:
        """Return ``angle_deg`` as a float, or raise if it is non-finite or out of range."""
        if not is_real(angle_deg):
            raise NonFiniteAngle(
                f"angle_deg={angle_deg!r} is not a real number for {self._describe()}"
            )
        angle = float(angle_deg)
        if not math.isfinite(angle):
            raise NonFiniteAngle(
                f"angle_deg={angle!r} is not finite for {self._describe()}; "
                f"allowed [{self.angle_min_deg}, {self.angle_max_deg}]"
            )
        if not self.angle_min_deg <= angle <= self.angle_max_deg:
            raise AngleOutOfRange(
                f"angle_deg={angle!r} outside [{self.angle_min_deg}, {self.angle_max_deg}] "
                f"for {self._describe()}"
            )
        return angle

    def check_pwm_us(self, pwm_us: float) -> None:
        """Raise :class:`PwmOutOfRange` unless ``pwm_us`` is finite and in the servo's range."""
        if (
            not is_real(pwm_us)
            or not math.isfinite(float(pwm_us))
            or not (self.pwm_min_us <= pwm_us <= self.pwm_max_us)
        ):
            raise PwmOutOfRange(
                f"pwm_us={pwm_us!r} outside [{self.pwm_min_us}, {self.pwm_max_us}] "
                f"for {self._describe()}"
            )

    def angle_to_pwm_us(self, angle_deg: float) -> int:
        """Convert a joint angle (degrees) to the integer PWM (µs) for this joint's output."""
        pwm_us = self.mapped_pwm_us(angle_deg)
        # Only a trim can push an in-range angle past the servo's limits: refuse, don't clamp.
        self.check_pwm_us(pwm_us)
        return pwm_us

    def mapped_pwm_us(self, angle_deg: float) -> int:
        """The integer PWM (µs) ``angle_deg`` maps to, reversal and trim included, *before* the
        servo-range check. Only for saying how far out a refused PWM is: what is sent goes
        through :meth:`angle_to_pwm_us`. The angle is checked as there."""
        angle = self.check_angle_deg(angle_deg)
        fraction = (angle - self.angle_min_deg) / (self.angle_max_deg - self.angle_min_deg)
        if self.reversed:
            fraction = 1.0 - fraction
        exact_us = self.pwm_min_us + fraction * (self.pwm_max_us - self.pwm_min_us) + self.trim_us
        return round_half_up_us(exact_us)

    def pwm_us_to_angle_deg(self, pwm_us: float) -> float:
        """Convert a PWM (µs, within the servo's range) back to the joint angle in degrees.

        With a non-zero trim the result may lie slightly outside the joint's angle range; it is
        returned as is, since it describes what the servo is actually doing.
        """
        self.check_pwm_us(pwm_us)
        fraction = (float(pwm_us) - self.trim_us - self.pwm_min_us) / (
            self.pwm_max_us - self.pwm_min_us
        )
        if self.reversed:
            fraction = 1.0 - fraction
        return self.angle_min_deg + fraction * (self.angle_max_deg - self.angle_min_deg)

    def pwm_us_to_normalized(self, pwm_us: int) -> float:
        """Map a PWM in the servo's range onto −1…1 (pwm_min_us → −1), as PX4 actuators expect."""
        self.check_pwm_us(pwm_us)
        value = 2.0 * (pwm_us - self.pwm_min_us) / (self.pwm_max_us - self.pwm_min_us) - 1.0
        return min(1.0, max(-1.0, value))  # guards float rounding only; pwm_us was checked


@dataclass(frozen=True)
class ArmCalibration:
    """The calibration of every joint, in joint order. Outputs and names must be unique."""

    joints: tuple[JointCalibration, ...]

    def __post_init__(self) -> None:
        joints = tuple(self.joints)
        object.__setattr__(self, "joints", joints)
        if not joints:
            raise ConfigurationError("an arm calibration needs at least one joint, got 0")
        for joint in joints:
            if not isinstance(joint, JointCalibration):
                raise ConfigurationError(f"{joint!r} is not a JointCalibration")
        outputs = [j.output for j in joints]
        names = [j.name for j in joints]
        unique: tuple[tuple[str, Sequence[object]], ...] = (("output", outputs), ("name", names))
        for label, values in unique:
            duplicates = sorted({v for v in values if values.count(v) > 1}, key=str)
            if duplicates:
                raise ConfigurationError(f"joint {label}s must be unique, repeated: {duplicates}")

    def __len__(self) -> int:
        return len(self.joints)

    @property
    def outputs(self) -> tuple[int, ...]:
        """Servo output numbers in joint order."""
        return tuple(j.output for j in self.joints)

    def joint(self, name: str) -> JointCalibration:
        """The calibration of the joint called ``name``."""
        for joint in self.joints:
            if joint.name == name:
                return joint
        raise ConfigurationError(
            f"no joint named {name!r}; joints are {[j.name for j in self.joints]}"
        )

    def for_output(self, output: int) -> JointCalibration:
        """The calibration of the joint driving servo ``output``."""
        for joint in self.joints:
            if joint.output == output:
                return joint
        raise ConfigurationError(f"output={output!r} is not calibrated; outputs are {self.outputs}")

    def angles_to_pwm_us(self, angles_deg: Sequence[float] | Mapping[str, float]) -> dict[int, int]:
        """Convert joint angles to ``{output: pwm_us}``, all or nothing.

        ``angles_deg`` is either one angle per joint in joint order, or a mapping from joint
        name to angle for a subset of joints. Every value is checked before any is returned.
        """
        if isinstance(angles_deg, Mapping):
            pairs = [(self.joint(name), angle) for name, angle in angles_deg.items()]
        else:
            angles = list(angles_deg)
            if len(angles) != len(self.joints):
                raise ConfigurationError(
                    f"got {len(angles)} joint angles, expected {len(self.joints)} "
                    f"({[j.name for j in self.joints]})"
                )
            pairs = list(zip(self.joints, angles, strict=True))
        return {joint.output: joint.angle_to_pwm_us(angle) for joint, angle in pairs}

    def pwm_us_to_angles_deg(self, pwm_by_output: Mapping[int, float]) -> dict[str, float]:
        """Convert ``{output: pwm_us}`` back to ``{joint name: angle_deg}``."""
        return {
            self.for_output(output).name: self.for_output(output).pwm_us_to_angle_deg(pwm)
            for output, pwm in pwm_by_output.items()
        }

    def check_pwm_us(self, pwm_by_output: Mapping[int, int]) -> None:
        """Refuse any PWM that is not an integer within its output's range.

        This is the last gate before anything is sent."""
        for output, pwm in pwm_by_output.items():
            joint = self.for_output(output)
            if not is_int(pwm):
                raise PwmOutOfRange(
                    f"pwm_us={pwm!r} is not an integer µs for servo output {output} "
                    f"(joint {joint.name!r}); allowed [{joint.pwm_min_us}, {joint.pwm_max_us}]"
                )
            joint.check_pwm_us(pwm)


def calibration_from_ranges(
    ranges_deg: Sequence[tuple[float, float]],
    *,
    outputs: Iterable[int] = DEFAULT_OUTPUTS,
    names: Iterable[str] | None = None,
    pwm_min_us: int = DEFAULT_PWM_MIN_US,
    pwm_max_us: int = DEFAULT_PWM_MAX_US,
    reversed_joints: Iterable[str] = (),
    trims_us: Mapping[str, int] | None = None,
) -> ArmCalibration:
    """Build an arm calibration from joint ranges given as plain ``(min_deg, max_deg)`` pairs.

    Joint names default to ``theta1``, ``theta2``, …; ``reversed_joints`` and ``trims_us`` are
    keyed by name. This is how the daemon passes in the arm model's joint limits.
    """
    ranges = [tuple(r) for r in ranges_deg]
    output_list = list(outputs)
    name_list = list(names) if names is not None else [f"theta{i + 1}" for i in range(len(ranges))]
    if not len(ranges) == len(output_list) == len(name_list):
        raise ConfigurationError(
            f"got {len(ranges)} ranges, {len(output_list)} outputs and {len(name_list)} names; "
            "they must have the same length"
        )
    reversed_set = set(reversed_joints)
    trims = dict(trims_us or {})
    unknown = (reversed_set | set(trims)) - set(name_list)
    if unknown:
        raise ConfigurationError(f"unknown joint names {sorted(unknown)}; joints are {name_list}")
    joints = []
    for name, output, rng in zip(name_list, output_list, ranges, strict=True):
        if len(rng) != 2:
            raise ConfigurationError(f"range {rng!r} for joint {name!r} must be (min_deg, max_deg)")
        joints.append(
            JointCalibration(
                name=name,
                output=output,
                angle_min_deg=rng[0],
                angle_max_deg=rng[1],
                pwm_min_us=pwm_min_us,
                pwm_max_us=pwm_max_us,
                reversed=name in reversed_set,
                trim_us=trims.get(name, 0),
            )
        )
    return ArmCalibration(tuple(joints))


def default_calibration(
    outputs: Iterable[int] = DEFAULT_OUTPUTS,
    *,
    pwm_min_us: int = DEFAULT_PWM_MIN_US,
    pwm_max_us: int = DEFAULT_PWM_MAX_US,
) -> ArmCalibration:
    """The paper arm's calibration: Table 2 ranges onto ``pwm_min_us``…``pwm_max_us``."""
    return calibration_from_ranges(
        TABLE2_RANGES_DEG, outputs=outputs, pwm_min_us=pwm_min_us, pwm_max_us=pwm_max_us
    )
