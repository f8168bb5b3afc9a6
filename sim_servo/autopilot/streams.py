"""The messages the autopilot streams, their intervals, and the commands that set them.

HEARTBEAT at ``heartbeat_rate_hz`` (1 Hz): MAV_TYPE_QUADROTOR, the flavour's autopilot,
``MAV_MODE_FLAG_SAFETY_ARMED`` and ACTIVE while armed, STANDBY otherwise.

MAV_CMD_SET_MESSAGE_INTERVAL (GCS_Common.cpp ``set_message_interval``): −1 stops, 0 resets to
the default, < 1000 µs becomes 1 ms, > 60 s becomes 60 s, otherwise whole milliseconds, then
``cap_message_interval``: at most 80 % of the loop rate (3 ms at 400 Hz); ACCEPTED for messages
we can stream (HEARTBEAT, SERVO_OUTPUT_RAW, SYSTEM_TIME, ATTITUDE, LOCAL_POSITION_NED; ArduPilot
SYS_STATUS, PX4 ACTUATOR_OUTPUT_STATUS), FAILED for the others. SERVO_OUTPUT_RAW never streams
faster than ``servo_output_min_interval_ms`` (ArduPilot: 20 ms, measured on SITL: at most 50 Hz
even when 400 Hz is asked); GET_MESSAGE_INTERVAL reports the stored interval, as
``get_ap_message_interval`` reads it back, not the rate achieved (3000 µs for a 400 Hz ask).

SYSTEM_TIME (``time_unix_usec``, ``time_boot_ms``): in ArduPilot's EXTRA3 stream, whose
SRn_EXTRA3 default is 0 on Copter (GCS_MAVLink_Parameters.cpp), so off until
SET_MESSAGE_INTERVAL asks; PX4 streams it at 1 Hz on a companion (ONBOARD mode) link
(mavlink_main.cpp ``configure_streams_to_default``). ATTITUDE and LOCAL_POSITION_NED
(ArduPilot: off until asked, SRn_EXTRA1 / SRn_POSITION 0 on Copter; PX4: 100 and 30 Hz, its
ONBOARD defaults) carry the vehicle's state at exactly their ``time_boot_ms``. SERVO_OUTPUT_RAW
and PX4's ACTUATOR_OUTPUT_STATUS (``active`` 16, µs as floats) report the outputs. SYS_STATUS
(ArduPilot, off until asked, as Copter's EXT_STAT stream) tells whether the safety switch holds
the outputs. A reboot puts every stream back to its default.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.messages import message_name
from sim_servo.autopilot.outputs import Outputs
from sim_servo.autopilot.state import AutopilotState
from sim_servo.autopilot.wire import Wire
from sim_servo.config import OUTPUT_COUNT
from sim_servo.hover import HoverDisturbance

if TYPE_CHECKING:
    from sim_servo.autopilot.commands import Command

#: ArduPilot's SET_MESSAGE_INTERVAL bounds (GCS_Common.cpp).
MAX_INTERVAL_MS = 60_000
HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT


class Streams:
    """Each streamable message's interval and next due time; the heartbeat's pause."""

    def __init__(
        self,
        state: AutopilotState,
        wire: Wire,
        outputs: Outputs,
        vehicle: HoverDisturbance,
        *,
        now_s: float,
    ) -> None:
        self._state = state
        self._wire = wire
        self._outputs = outputs
        self._vehicle = vehicle
        self.ids = (
            HEARTBEAT,
            mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
            mavlink.MAVLINK_MSG_ID_ATTITUDE,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
            state.flavour.own_stream_id,
        )
        #: The stored interval of each stream (0: off), as GET_MESSAGE_INTERVAL reports it.
        self.interval_ms: dict[int, int] = {}
        self._next_due_s: dict[int, float | None] = {}
        self.boot(now_s)
        self._heartbeat_paused = False
        #: What the last SERVO_OUTPUT_RAW showed (see :meth:`_note_readback`).
        self._readback_shown: dict[int, int] = {}
        #: Set by pause_heartbeat() (a test asking over the query socket): overrides the
        #: configured schedule.
        self._heartbeat_held: bool | None = None

    def handlers(self) -> dict[int, Callable[[Command, float], int]]:
        return {
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self.set_message_interval,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: self.get_message_interval,
            mavlink.MAV_CMD_REQUEST_MESSAGE: self.request_message,
        }

    def boot(self, now_s: float) -> None:
        """Every stream at its default interval, the first frame due now."""
        for msg_id in self.ids:
            self.interval_ms[msg_id] = self.default_interval_ms(msg_id)
            self._next_due_s[msg_id] = now_s if self.interval_ms[msg_id] > 0 else None

    def next_events_s(self) -> list[float]:
        return [due for due in self._next_due_s.values() if due is not None]

    # -- intervals ---------------------------------------------------------------------------

    def default_interval_ms(self, msg_id: int) -> int:
        config = self._state.config
        if msg_id == HEARTBEAT:
            return round(1000.0 / config.heartbeat_rate_hz)
        for stream_id, rate_hz in (
            (mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, config.servo_output_rate_hz),
            (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, config.system_time_default_hz),
            (mavlink.MAVLINK_MSG_ID_ATTITUDE, config.attitude_default_hz),
            (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, config.local_position_default_hz),
        ):
            if msg_id == stream_id and rate_hz:
                return max(1, round(1000.0 / rate_hz))
        return 0

    def _effective_interval_ms(self, msg_id: int) -> int:
        """The interval a stream really runs at: SERVO_OUTPUT_RAW never beats the configured
        floor (50 Hz on ArduCopter, measured), whatever interval is stored and reported."""
        interval_ms = self.interval_ms[msg_id]
        if msg_id == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW and interval_ms > 0:
            return max(interval_ms, self._state.config.servo_output_floor_ms)
        return interval_ms

    def _advance(self, msg_id: int, now_s: float) -> None:
        interval_ms = self._effective_interval_ms(msg_id)
        if interval_ms <= 0:
            self._next_due_s[msg_id] = None
            return
        previous = self._next_due_s[msg_id]
        assert previous is not None  # both callers advance only a stream that was due
        due = previous + interval_ms / 1000.0
        # Behind by more than a period (a stalled loop): restart the cadence from now.
        self._next_due_s[msg_id] = due if due > now_s else now_s + interval_ms / 1000.0

    # -- the heartbeat -----------------------------------------------------------------------

    def pause_heartbeat(self, paused: bool, now_s: float) -> None:
        """Stop (``paused``) or restart our HEARTBEAT now, whatever the configured schedule says
        from then on: a test triggers a link loss when it is ready instead of at a fixed time.
        A restart sends a heartbeat at once and every period from there, so the daemon's
        reaction is measured from the heartbeat, not from where the old schedule stood."""
        self._heartbeat_held = paused
        if not paused and self._heartbeat_paused and self._next_due_s.get(HEARTBEAT) is not None:
            self._next_due_s[HEARTBEAT] = now_s
        if paused != self._heartbeat_paused:
            self._heartbeat_paused = paused
            self._state.emit(
                now_s, "fault", fault="heartbeat_paused" if paused else "heartbeat_resumed"
            )

    def _heartbeat_paused_at(self, now_s: float) -> bool:
        if self._heartbeat_held is not None:
            return self._heartbeat_held
        faults = self._state.config.faults
        after = faults.heartbeat_pause_after_s
        if after is None:
            return False
        elapsed = now_s - self._state.start_s
        length = faults.heartbeat_pause_for_s
        return elapsed >= after and (length is None or elapsed < after + length)

    def run_heartbeat(self, now_s: float) -> None:
        due = self._next_due_s.get(HEARTBEAT)
        if due is None or now_s < due:
            return
        self._advance(HEARTBEAT, now_s)
        paused = self._heartbeat_paused_at(now_s)
        if paused != self._heartbeat_paused:
            self._heartbeat_paused = paused
            self._state.emit(
                now_s, "fault", fault="heartbeat_paused" if paused else "heartbeat_resumed"
            )
        if not paused:
            self._wire.send(self._heartbeat(), now_s)

    def _heartbeat(self) -> mavlink.MAVLink_message:
        armed = self._outputs.armed
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if armed:
            base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return self._wire.encoder.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR,
            self._state.flavour.autopilot_type,
            base_mode,
            0,
            mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY,
        )

    # -- the other streams -------------------------------------------------------------------

    def run(self, now_s: float) -> None:
        """Send every stream but the heartbeat that is due by ``now_s``."""
        for msg_id in self.ids:
            if msg_id == HEARTBEAT:
                continue
            due = self._next_due_s[msg_id]
            if due is None or now_s < due:
                continue
            self._advance(msg_id, now_s)
            if msg_id == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
                self._note_readback(now_s)
            self._wire.send(self.message(msg_id, now_s), now_s)

    def _note_readback(self, now_s: float) -> None:
        """A SERVO_OUTPUT_RAW goes out: a ``readback`` event names the outputs whose PWM it
        shows for the first time since the one before (when a peer could first see a change;
        a bench tells from it what the companion could know when it sent a command)."""
        pwm_us = self._outputs.pwm_us
        shown = {o: pwm_us[o] for o in range(1, OUTPUT_COUNT + 1)}
        changed = {str(o): v for o, v in shown.items() if self._readback_shown.get(o) != v}
        self._readback_shown = shown
        if changed:
            self._state.emit(now_s, "readback", pwm_us=changed)

    def message(self, msg_id: int, now_s: float) -> mavlink.MAVLink_message:
        """The streamed message ``msg_id`` as at ``now_s``."""
        state = self._state
        enc = self._wire.encoder
        pwm_us = self._outputs.pwm_us
        if msg_id == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
            values = [pwm_us[o] & 0xFFFF for o in range(1, OUTPUT_COUNT + 1)]
            return enc.servo_output_raw_encode(state.time_boot_us(now_s) & 0xFFFFFFFF, 0, *values)
        if msg_id == mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS:
            actuators = [float(pwm_us[o]) for o in range(1, OUTPUT_COUNT + 1)]
            return enc.actuator_output_status_encode(
                state.time_boot_us(now_s), OUTPUT_COUNT, actuators + [0.0] * (32 - OUTPUT_COUNT)
            )
        if msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME:
            # time_boot_ms restarts at 0 on a reboot: how a peer tells a reboot from a link loss.
            return enc.system_time_encode(
                state.time_unix_us(now_s), (state.time_boot_us(now_s) // 1000) & 0xFFFFFFFF
            )
        if msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            # Copter's update_vehicle_sensor_status_flags: motor outputs "enabled" unless the
            # safety switch is on (the only sensor bit modelled here).
            motors = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            enabled = 0 if self._outputs.safety_on else motors
            return enc.sys_status_encode(motors, enabled, motors, 0, 0, -1, -1, 0, 0, 0, 0, 0, 0)
        if msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
            # The state at exactly the time the stamp names (see sim_servo.hover).
            stamp_ms = state.time_boot_us(now_s) // 1000
            vehicle = self._vehicle.state(state.boot_s + stamp_ms / 1000.0 - state.start_s)
            if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
                return enc.attitude_encode(
                    stamp_ms & 0xFFFFFFFF, *vehicle.attitude_wrapped(), *vehicle.body_rates()
                )
            return enc.local_position_ned_encode(
                stamp_ms & 0xFFFFFFFF,
                vehicle.north_m,
                vehicle.east_m,
                vehicle.down_m,
                vehicle.vn_m_s,
                vehicle.ve_m_s,
                vehicle.vd_m_s,
            )
        if msg_id == HEARTBEAT:
            return self._heartbeat()
        raise AssertionError(f"message id {msg_id} is not streamable")  # self.ids guards

    # -- commands ----------------------------------------------------------------------------

    def set_message_interval(self, command: Command, now_s: float) -> int:
        msg_id_f, interval_f = command.params[0], command.params[1]
        if not (math.isfinite(msg_id_f) and math.isfinite(interval_f)):
            return mavlink.MAV_RESULT_FAILED
        msg_id, interval_us = int(msg_id_f), int(interval_f)
        if msg_id not in self.ids:
            return mavlink.MAV_RESULT_FAILED
        if interval_us == 0:
            interval_ms = self.default_interval_ms(msg_id)
        elif interval_us == -1:
            interval_ms = 0
        elif interval_us < 1000:
            interval_ms = 1  # "don't squash sub-ms times to zero"
        elif interval_us > MAX_INTERVAL_MS * 1000:
            interval_ms = MAX_INTERVAL_MS
        else:
            interval_ms = interval_us // 1000
        # GCS_Common.cpp cap_message_interval: at most 80 % of the main-loop rate (3 ms at 400 Hz).
        loop_period_us = 1e6 / self._state.config.loop_rate_hz
        if 0 < interval_ms and interval_ms * 800 < loop_period_us:
            interval_ms = int(loop_period_us / 800)
        self.interval_ms[msg_id] = interval_ms
        self._next_due_s[msg_id] = now_s if interval_ms > 0 else None
        self._state.emit(now_s, "stream", msg=message_name(msg_id), interval_ms=interval_ms)
        return mavlink.MAV_RESULT_ACCEPTED

    def get_message_interval(self, command: Command, now_s: float) -> int:
        msg_id = int(command.params[0]) if math.isfinite(command.params[0]) else -1
        if msg_id in self.interval_ms:
            # The stored interval, as GCS_Common.cpp get_ap_message_interval reads it back, not
            # the rate achieved: SERVO_OUTPUT_RAW asked for at 400 Hz reports 3000 µs (the
            # 0.8 x loop-rate cap) while it streams at 50 Hz.
            interval_ms = self.interval_ms[msg_id]
            interval_us = interval_ms * 1000 if interval_ms > 0 else -1
        else:
            interval_us = 0  # not available
        self._wire.defer(
            self._wire.encoder.message_interval_encode(max(0, msg_id) & 0xFFFF, interval_us),
            now_s,
        )
        return mavlink.MAV_RESULT_ACCEPTED

    def request_message(self, command: Command, now_s: float) -> int:
        msg_id = int(command.params[0]) if math.isfinite(command.params[0]) else -1
        if msg_id not in self.ids:
            return mavlink.MAV_RESULT_FAILED
        if msg_id == HEARTBEAT and self._heartbeat_paused_at(now_s):
            return mavlink.MAV_RESULT_ACCEPTED  # the fault: no HEARTBEAT, asked for or not
        self._wire.defer(self.message(msg_id, now_s), now_s)
        return mavlink.MAV_RESULT_ACCEPTED
