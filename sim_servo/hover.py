"""A seeded hover disturbance: the vehicle's pose and rates in LOCAL_NED as a function of time.

Pure: :meth:`HoverDisturbance.state` takes a time (s since the simulator started) and returns
the vehicle's :class:`VehicleState` at that instant, so the ATTITUDE and LOCAL_POSITION_NED
frames, the ``vehicle`` events of the log and a bench that rebuilds the motion from the seed
all agree exactly. No clock, no global random state: the motion is drawn once, from a seed or a
``numpy.random.Generator``.

The model is a light-wind hover, not flight dynamics: each of north, east, down, roll, pitch
and yaw is its home value plus a sum of ``components`` sinusoids ``a_k sin(ω_k t + φ_k)``. The
periods ``2π/ω_k`` are drawn uniformly in [``period_min_s``, ``period_max_s``] (yaw: its own,
slower range, a wander), the phases uniformly in [0, 2π), and the amplitudes as weights drawn
uniformly in [0.5, 1] scaled so that they sum to the axis's bound (``drift_cm``, ``heave_cm``,
``tilt_deg``, ``yaw_deg``): an axis never leaves its bound and comes near it when the phases
line up. Tilt and drift are drawn independently (a gust tilts a real vehicle without a
matching drift). Velocities and rates are the analytic derivatives, never finite differences.

Conventions, as the autopilots report them (checked in their sources):

* **LOCAL_POSITION_NED** (x, y, z m; vx, vy, vz m/s): north, east, down from the autopilot's
  local origin, and their rates in the same frame (ArduPilot ``send_local_position``: the AHRS's
  position relative to the EKF origin and its NED velocity; PX4 ``LOCAL_POSITION_NED.hpp``:
  ``vehicle_local_position``).
* **ATTITUDE** (roll, pitch, yaw rad; rollspeed, pitchspeed, yawspeed rad/s): "the attitude in
  the aeronautical frame (right-handed, Z-down, Y-right, X-front, ZYX, intrinsic)" (MAVLink
  common.xml): the body frame FRD with respect to NED, ``R_ned_body = Rz(yaw) · Ry(pitch) ·
  Rx(roll)``. The three speeds are the **body-frame angular velocity** (p, q, r), not the
  Euler angle rates: ArduPilot sends ``ahrs.get_gyro()`` (GCS_Common.cpp ``send_attitude``),
  PX4 ``vehicle_angular_velocity.xyz`` (``ATTITUDE.hpp``). :meth:`VehicleState.body_rates`
  converts: p = φ̇ − ψ̇ sin θ, q = θ̇ cos φ + ψ̇ sin φ cos θ, r = −θ̇ sin φ + ψ̇ cos φ cos θ.
* **time_boot_ms**: ArduPilot stamps both with ``AP_HAL::millis()`` at the moment it sends
  (the state is the current one, up to 1 ms newer than its truncated stamp); PX4 with the
  estimate's own timestamp (``att.timestamp / 1000``). The simulator evaluates the state at
  exactly the time its stamp names, so a frame's age is what the link adds.

Stream rates on a companion link (the defaults in :mod:`sim_servo.config`):

* ArduCopter: ATTITUDE is in the EXTRA1 stream and LOCAL_POSITION_NED in POSITION
  (``GCS_MAVLink_Parameters.cpp``); ``SRn_EXTRA1`` and ``SRn_POSITION`` default to 0 on Copter
  (``AP_MAV_DEFAULT_STREAM_RATE_*``, every port), so neither streams until the companion asks
  with SET_MESSAGE_INTERVAL (or REQUEST_DATA_STREAM). The stream parameters range 0–50 Hz; a
  SET_MESSAGE_INTERVAL may ask for more, down to ``cap_message_interval``: no shorter than
  1/(0.8 × SCHED_LOOP_RATE), 3 ms at Copter's 400 Hz (``GCS_Common.cpp``), the cap the
  simulator applies to every stream.
* PX4: a link in ONBOARD mode (a companion's, ``MAV_x_MODE`` 2) streams ATTITUDE at 100 Hz and
  LOCAL_POSITION_NED at 30 Hz by default (``mavlink_main.cpp`` ``configure_streams_to_default``,
  ``MAVLINK_MODE_ONBOARD``; NORMAL mode: 15 Hz and 1 Hz). SET_MESSAGE_INTERVAL changes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sim_servo.config import VehicleConfig

FloatArray = NDArray[np.float64]

#: The axes of the disturbance, in the order of :attr:`HoverDisturbance.amplitudes`.
AXES = ("north", "east", "down", "roll", "pitch", "yaw")
#: Amplitude weights are drawn in [WEIGHT_LOW, 1], then scaled to sum to the axis's bound.
WEIGHT_LOW = 0.5


@dataclass(frozen=True)
class VehicleState:
    """The vehicle at one instant: position and velocity in LOCAL_NED, attitude of the body
    (FRD) in NED (ZYX roll/pitch/yaw), Euler angle rates and body rates."""

    t_s: float
    north_m: float
    east_m: float
    down_m: float
    vn_m_s: float
    ve_m_s: float
    vd_m_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    roll_rate_rad_s: float
    pitch_rate_rad_s: float
    yaw_rate_rad_s: float

    @property
    def position_m(self) -> FloatArray:
        return np.array([self.north_m, self.east_m, self.down_m])

    @property
    def velocity_m_s(self) -> FloatArray:
        return np.array([self.vn_m_s, self.ve_m_s, self.vd_m_s])

    def body_rates(self) -> tuple[float, float, float]:
        """Angular velocity in the body frame (p, q, r) rad/s: ATTITUDE's rollspeed,
        pitchspeed and yawspeed."""
        sr, cr = math.sin(self.roll_rad), math.cos(self.roll_rad)
        sp, cp = math.sin(self.pitch_rad), math.cos(self.pitch_rad)
        droll, dpitch, dyaw = self.roll_rate_rad_s, self.pitch_rate_rad_s, self.yaw_rate_rad_s
        return (
            droll - dyaw * sp,
            dpitch * cr + dyaw * sr * cp,
            -dpitch * sr + dyaw * cr * cp,
        )

    def attitude_wrapped(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw) rad with yaw in [−π, π), as ATTITUDE carries them."""
        yaw = (self.yaw_rad + math.pi) % (2.0 * math.pi) - math.pi
        return self.roll_rad, self.pitch_rad, yaw

    def as_dict(self) -> dict[str, float]:
        """JSON-ready, with the body rates (``p_rad_s``, ``q_rad_s``, ``r_rad_s``)."""
        data = {name: getattr(self, name) for name in self.__dataclass_fields__}
        data["p_rad_s"], data["q_rad_s"], data["r_rad_s"] = self.body_rates()
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VehicleState:
        """Inverse of :meth:`as_dict` (extra keys such as the body rates are ignored)."""
        return cls(**{name: float(data[name]) for name in cls.__dataclass_fields__})


class HoverDisturbance:
    """The vehicle's motion: home plus, per axis, a sum of seeded sinusoids.

    ``amplitudes``, ``omegas_rad_s`` and ``phases_rad`` have shape ``(6, components)``, axes in
    :data:`AXES` order, amplitudes in m (north, east, down) and rad (roll, pitch, yaw).
    """

    def __init__(
        self,
        home_ned_m: tuple[float, float, float],
        home_yaw_rad: float,
        amplitudes: FloatArray,
        omegas_rad_s: FloatArray,
        phases_rad: FloatArray,
    ) -> None:
        self.home = np.array([*home_ned_m, 0.0, 0.0, home_yaw_rad], dtype=float)
        self.amplitudes = np.asarray(amplitudes, dtype=float)
        self.omegas_rad_s = np.asarray(omegas_rad_s, dtype=float)
        self.phases_rad = np.asarray(phases_rad, dtype=float)
        shape = self.amplitudes.shape
        if len(shape) != 2 or shape[0] != len(AXES):
            raise ValueError(f"amplitudes shape {shape}; expected ({len(AXES)}, components)")
        if self.omegas_rad_s.shape != shape or self.phases_rad.shape != shape:
            raise ValueError(
                f"omegas {self.omegas_rad_s.shape} and phases {self.phases_rad.shape} must have "
                f"the amplitudes' shape {shape}"
            )
        # Per-term rate amplitude, for the derivative.
        self._rate_amplitudes = self.amplitudes * self.omegas_rad_s

    @classmethod
    def from_config(
        cls, config: VehicleConfig, rng: np.random.Generator | None = None
    ) -> HoverDisturbance:
        """The motion ``config`` describes, drawn from ``rng`` (default: from ``config.seed``).
        Without ``config.hover`` every amplitude is 0: the vehicle holds its home."""
        rng = rng if rng is not None else np.random.default_rng(config.seed)
        count = config.components
        bounds = np.array(
            [
                config.drift_cm / 100.0,
                config.drift_cm / 100.0,
                config.heave_cm / 100.0,
                math.radians(config.tilt_deg),
                math.radians(config.tilt_deg),
                math.radians(config.yaw_deg),
            ]
        )
        # Drawn whether or not hover is on, so turning it on never changes another draw.
        weights = rng.uniform(WEIGHT_LOW, 1.0, size=(len(AXES), count))
        periods = rng.uniform(config.period_min_s, config.period_max_s, size=(len(AXES), count))
        periods[5] = rng.uniform(config.yaw_period_min_s, config.yaw_period_max_s, size=count)
        phases = rng.uniform(0.0, 2.0 * math.pi, size=(len(AXES), count))
        amplitudes = weights / weights.sum(axis=1, keepdims=True) * bounds[:, None]
        if not config.hover:
            amplitudes = np.zeros_like(amplitudes)
        return cls(
            config.home_ned_m,
            math.radians(config.home_yaw_deg),
            amplitudes,
            2.0 * math.pi / periods,
            phases,
        )

    @property
    def periods_s(self) -> FloatArray:
        return 2.0 * math.pi / self.omegas_rad_s

    def offsets(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        """(values, rates) of the six axes at ``t_s``: home + Σ a sin(ωt + φ), Σ aω cos(ωt + φ)."""
        arg = self.omegas_rad_s * t_s + self.phases_rad
        values = self.home + (self.amplitudes * np.sin(arg)).sum(axis=1)
        rates = (self._rate_amplitudes * np.cos(arg)).sum(axis=1)
        return values, rates

    def state(self, t_s: float) -> VehicleState:
        """The vehicle at ``t_s`` (s since the simulator started)."""
        values, rates = self.offsets(t_s)
        v = values.tolist()
        r = rates.tolist()
        return VehicleState(float(t_s), *v[:3], *r[:3], *v[3:], *r[3:])
