"""The simulated autopilot's MAVLink behaviour: bytes in, frames out, given the time.

:class:`SimAutopilot` does no I/O and reads no clock: :meth:`~SimAutopilot.receive` takes the
bytes that arrived and the time, :meth:`~SimAutopilot.poll` returns the frames due by a time,
:meth:`~SimAutopilot.next_event_s` says when to call ``poll`` next. A test drives it with plain
numbers; the server (:mod:`sim_servo.server`) drives it with ``time.monotonic``.

ArduPilot behaviour copied (source files in ArduPilot/ardupilot):

* HEARTBEAT at 1 Hz: MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA, disarmed, STANDBY.
* Received frames are handled on the next main-loop pass (``loop_rate_hz``, 400 Hz as
  ArduCopter), like ``GCS::update_receive`` running once per loop.
* When frames leave: each link's output goes through :class:`~sim_servo.linktiming.LinkOutput`,
  a delay-and-hold model fitted to ArduCopter 4.7.0-dev SITL over TCP loopback with a
  pymavlink client (one DO_SET_SERVO round trip 5.7 ms median, range 5.3–6.1; six in sequence
  32.2 ms; six back-to-back 3.2 ms median, 6.0 max, so a burst beats a lone command). Frames
  leave ``output_delay_ms`` (1.0) after they were produced at the earliest, then are held until
  the link sends a frame, or ``hold_ms`` (4.8) after the first frame the link sent since it was
  last quiet, or at once when two frames came within that window. See
  :class:`~sim_servo.config.LinkTimingConfig` (defaults, fit, limits); ``instant()`` turns it
  off. Applied to every transport; serial links were not measured.
* Routing between links as ``MAVLink_routing::check_and_forward`` (see :meth:`_route`): a
  command for our system and a component never heard (or heard only on the link it came from)
  is handled here, so it gets our UNSUPPORTED; routes are never forgotten (frames for a
  companion that left still go to its dead link); nothing goes back out of the link it came on.
* COMMAND_LONG / COMMAND_INT that routing gives us are handled (GCS_Common.cpp
  ``handle_command_long`` checks no target itself); the COMMAND_ACK is produced at once,
  addressed to the sender, on the link the command came from only.
* MAV_CMD_DO_SET_SERVO (GCS_ServoRelay.cpp, AP_ServoRelayEvents.cpp ``do_set_servo``): an output
  outside 1–16 → FAILED; an output whose SERVOn_FUNCTION is not 0 (disabled), 1 (RC pass-through)
  or 51–66 (RC input 1–16) → STATUSTEXT severity INFO "ServoRelayEvent: Channel N is already in
  use" and FAILED; otherwise the PWM is applied as given (no clamping) and ACCEPTED.
  STATUSTEXTs are queued and sent from the main loop (GCS.cpp ``service_statustext``), so the
  text arrives one loop period *after* the ACK.
* MAV_CMD_SET_MESSAGE_INTERVAL (GCS_Common.cpp ``set_message_interval``): −1 stops, 0 resets to
  the default, < 1000 µs becomes 1 ms, > 60 s becomes 60 s, otherwise whole milliseconds, then
  ``cap_message_interval``: at most 80 % of the loop rate (3 ms at 400 Hz); ACCEPTED for
  messages we can stream (HEARTBEAT, SERVO_OUTPUT_RAW, SYSTEM_TIME, ATTITUDE,
  LOCAL_POSITION_NED; ArduPilot SYS_STATUS, PX4 ACTUATOR_OUTPUT_STATUS), FAILED for the
  others. SERVO_OUTPUT_RAW never streams faster than ``servo_output_min_interval_ms``
  (ArduPilot: 20 ms, measured on SITL: at most 50 Hz even when 400 Hz is asked);
  GET_MESSAGE_INTERVAL reports the stored interval, as ``get_ap_message_interval`` reads it
  back, not the rate achieved (3000 µs for a 400 Hz ask).
* SYSTEM_TIME (``time_unix_usec``, ``time_boot_ms``): in ArduPilot's EXTRA3 stream, whose
  SRn_EXTRA3 default is 0 on Copter (GCS_MAVLink_Parameters.cpp), so off until
  SET_MESSAGE_INTERVAL asks; PX4 streams it at 1 Hz on a companion (ONBOARD mode) link
  (mavlink_main.cpp ``configure_streams_to_default``).
* Reboot (:meth:`reboot`, ``reboot_after_s``, the query ``reboot``): silent and deaf for
  ``reboot_gap_s`` (0.36 s, measured on a real reboot), then time_boot from 0, outputs at their
  boot values, streams at their defaults, an empty routing table, the sequence number from 0;
  parameters keep their values.
* PARAM_SET / PARAM_REQUEST_READ / PARAM_REQUEST_LIST (GCS_Param.cpp): unknown names get no
  reply; integer parameters take ``value + 0.01`` (away from zero) truncated; the answer is
  PARAM_VALUE with ``param_index`` −1 (65535 on the wire, a uint16) for a set or a read by name.
* Anything else in COMMAND_LONG → UNSUPPORTED.

* ArduPilot's safety switch (AP_BoardConfig; ``AP_HAL_ChibiOS/RCOutput.cpp`` ``push_local``):
  on at each boot when ``BRD_SAFETY_DEFLT`` is 1 (0 here by default, so outputs are live);
  :meth:`set_safety` (the queries ``safety_on`` / ``safety_off``) flips it. While on, an output
  whose bit (output − 1) is not in ``BRD_SAFETY_MASK`` sends no pulses; DO_SET_SERVO is still
  ACCEPTED and SERVO_OUTPUT_RAW still reports the PWM given (``read()`` returns the stored
  period); switched off, the stored PWMs go out in one step. SYS_STATUS (streamable, off until
  asked, as Copter's EXT_STAT stream) tells it: ``onboard_control_sensors_enabled`` has
  MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS unless the switch is on (Copter's
  ``update_vehicle_sensor_status_flags``).

With ``lua_script`` (ArduPilot only): MAV_CMD_USER_2 is answered as armbridge's Lua bridge
answers it, after the script's own delay (:mod:`sim_servo.lua_bridge`); the arm's outputs get
``SERVOn_MIN`` / ``MAX`` = the arm's PWM range, as the script's install notes ask.

PX4 flavour, as measured on PX4 SITL (main of 2026-03, SIH quadrotor; issue 20):

* HEARTBEAT with MAV_AUTOPILOT_PX4, ``MAV_MODE_FLAG_SAFETY_ARMED`` while armed; parameters
  INT32 sent bytewise; DO_SET_SERVO UNSUPPORTED; SYSTEM_TIME at 1 Hz; no SERVO_OUTPUT_RAW floor.
* Disarmed at boot (``SimConfig.armed``: armed at start). MAV_CMD_COMPONENT_ARM_DISARM param1
  1 / 0 arms / disarms (param2 21196: forced, a kill) → ACCEPTED; other values DENIED.
* ``COM_PREARM_MODE`` 0 (default): never prearmed; 2 (and 1: no safety button here, as SITL):
  prearmed from 5 s after each boot. Changes apply at once.
* Outputs are live while armed or prearmed. Otherwise every output shows ``PWM_MAIN_DISn``
  (1000 as boards; SITL 900) — at boot, on disarm and kill, after a reboot. Live, an output on
  function 301–306 shows its slot of actuator set 1 (a slot never set since boot is NaN: the
  disarmed PWM), a motor (101–104) its minimum once armed. What was stored while dead appears
  in one step when the outputs come alive.
* MAV_CMD_DO_SET_ACTUATOR (Commander.cpp) is ACCEPTED whatever happens: nothing mapped,
  disarmed, param7 ≠ 0 (then ignored), values out of range. Param7 0 stores params 1–6 (NaN:
  slot unchanged). PWM = 1500 + 500·v rounded half away from zero, clamped to
  ``PWM_MAIN_MINn`` / ``MAXn``.
* ``PWM_MAIN_FUNCn`` 0 by default except motors 1–4; PARAM_SET applies without a reboot.
* SERVO_OUTPUT_RAW and ACTUATOR_OUTPUT_STATUS (``active`` 16, µs as floats) report the outputs.
* Routing: :meth:`_route_px4` (forwarding per link, ``MAV_n_FORWARD``; only to a link that has
  heard the target; commands for another component of ours ignored without an answer).
* Timing: :class:`~sim_servo.config.Px4TimingConfig` — frames handled on arrival, commander
  commands acted on and answered on the next 10 ms cycle, frames out on each link's 1.5 ms
  main-loop pass (:class:`~sim_servo.linktiming.LoopLinkOutput`), routed frames 2.5 ms later.

The vehicle moves (:mod:`sim_servo.hover`, ``[vehicle]``): ATTITUDE and LOCAL_POSITION_NED are
streamable (ArduPilot: off until asked, SRn_EXTRA1 / SRn_POSITION 0 on Copter; PX4: 100 and
30 Hz, its ONBOARD defaults), each frame carrying the state at exactly its ``time_boot_ms``; the
motion goes on through a reboot. :meth:`SimAutopilot.hand_world` puts the hand in LOCAL_NED
(vehicle ∘ mount ∘ the hand the horns give, :mod:`sim_servo.world`); the periodic ``vehicle``
event logs both (written in batches, always before a servo's course changes).

The ``output`` event logs every change of what a servo physically receives (with its cause),
``arming`` / ``prearm`` / ``safety`` the state changes, so a bench can check from the log alone
that no joint stepped faster than its limit.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.config import (
    ARDUPILOT_PWM_MAX_US,
    ARDUPILOT_PWM_MIN_US,
    ARDUPILOT_PWM_TRIM_US,
    OUTPUT_COUNT,
    PX4_ACTUATOR_SET_COUNT,
    PX4_ACTUATOR_SET_FIRST_FUNCTION,
    PX4_DISARMED_PWM_US,
    PX4_MOTOR_FUNCTIONS,
    PX4_PREARM_DELAY_S,
    PX4_PREARM_MODES,
    PX4_PWM_MAX_US,
    PX4_PWM_MIN_US,
    SimConfig,
)
from sim_servo.errors import SimConfigError
from sim_servo.faults import FaultInjector
from sim_servo.hand import HandModel
from sim_servo.hover import HoverDisturbance, VehicleState
from sim_servo.linktiming import LinkOutput, LoopLinkOutput
from sim_servo.lua_bridge import MAV_CMD_USER_2, LuaScriptTiming, check_user2, refusal_text
from sim_servo.servo import Servo, ServoParams
from sim_servo.world import FloatArray, WorldPose, hand_in_world, mount_matrix, pose_matrix

Emit = Callable[[dict[str, Any]], None]

#: SERVOn_FUNCTION values DO_SET_SERVO may drive (AP_ServoRelayEvents.cpp): k_none, k_manual,
#: k_rcin1 … k_rcin16.
ARDUPILOT_FREE_FUNCTIONS = frozenset({0, 1, *range(51, 67)})
STATUSTEXT_IN_USE = "ServoRelayEvent: Channel {output} is already in use"
#: What an output assigned to a function (a motor, disarmed) reports before any command.
IDLE_ASSIGNED_PWM_US = 1000
#: ArduPilot's SET_MESSAGE_INTERVAL bounds (GCS_Common.cpp).
MAX_INTERVAL_MS = 60_000
#: Signing timestamps: 10 µs ticks since 2015-01-01 UTC (MAVLink signing spec).
SIGNING_EPOCH_UNIX_S = 1_420_070_400
#: Accepted unsigned even when signing is required (GCS_Signing.cpp accept list).
UNSIGNED_ALLOWED_IDS = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS})
#: MAVLink_routing.h: the routing table holds at most this many (system, component, link).
MAX_ROUTES = 20
#: Handled here and never forwarded (MAVLink_routing.cpp ``check_and_forward``): RADIO and
#: RADIO_STATUS are about the link itself, ADSB_VEHICLE has its own stream.
NOT_FORWARDED_IDS = frozenset(
    {
        mavlink.MAVLINK_MSG_ID_RADIO,
        mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
        mavlink.MAVLINK_MSG_ID_ADSB_VEHICLE,
    }
)
#: PX4: the commands its commander handles, answered on the commander's next cycle.
PX4_COMMANDER_COMMANDS = frozenset(
    {mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_SET_ACTUATOR}
)
#: MAV_CMD_COMPONENT_ARM_DISARM param2 that forces (PX4 skips its checks; here: a kill).
PX4_FORCE_MAGIC = 21196
#: Our links as PX4 MAVLink instances, for their ``MAV_n_FORWARD``: the companion's link (0)
#: is instance 1 (TELEM2), the ground station's (1) instance 0 (TELEM1), as on a Pixhawk.
PX4_FORWARD_PARAMS = {0: "MAV_1_FORWARD", 1: "MAV_0_FORWARD"}
#: ``vehicle`` events are written in batches at most this long after they were due (a wake-up
#: per sample would cost more than the samples), and never more than VEHICLE_LOG_MAX_S behind.
VEHICLE_LOG_LAG_S = 0.2
VEHICLE_LOG_MAX_S = 2.0
#: PX4's defaults: forwarding on for instance 0 (TELEM1), off for the others.
PX4_FORWARD_DEFAULTS = {"MAV_0_FORWARD": 1, "MAV_1_FORWARD": 0}


@dataclass
class Param:
    name: str
    value: int
    param_type: int  # MAV_PARAM_TYPE
    low: int
    high: int


@dataclass(frozen=True)
class Command:
    """A COMMAND_LONG or COMMAND_INT, normalised (``params`` has 7 floats)."""

    command: int
    params: tuple[float, ...]
    source: tuple[int, int]
    channel: int = 0


class SimAutopilot:
    """A simulated ArduPilot (or PX4) flight controller with 16 servo outputs."""

    def __init__(
        self,
        config: SimConfig,
        *,
        now_s: float,
        emit: Emit | None = None,
        hand: HandModel | None = None,
        faults: FaultInjector | None = None,
        wall_clock: Callable[[], float] = time.time,
        links: int = 1,
    ) -> None:
        self.config = config
        self.hand = hand
        self.faults = faults or FaultInjector(config.faults)
        #: The vehicle's motion (pure, seeded): it goes on through a reboot of the autopilot.
        self.vehicle = HoverDisturbance.from_config(config.vehicle)
        self._mount = mount_matrix(config.vehicle.mount)
        #: The hand in the arm's base frame for the last horn positions seen (an FK is costly).
        self._hand_key: tuple[float, ...] | None = None
        self._hand_base: FloatArray | None = None
        log_rate_hz = config.vehicle.log_rate_hz
        self._vehicle_log_s = 1.0 / log_rate_hz if log_rate_hz > 0 else 0.0
        self._vehicle_due_s: float | None = now_s if log_rate_hz > 0 else None
        #: Samples fall at origin + n·period (no drift from adding periods up).
        self._vehicle_origin_s, self._vehicle_n = now_s, 0
        self._emit_sink = emit or (lambda event: None)
        self._start_s = now_s
        #: When the current boot started: time_boot, the main-loop phase (a reboot moves it).
        self._boot_s = now_s
        #: The wall clock at ``now_s``, for SYSTEM_TIME; later read as ``now_s`` goes on.
        self._unix_at_start_s = wall_clock()
        self._loop_s = 1.0 / config.loop_rate_hz
        self._enc = mavlink.MAVLink(
            None, srcSystem=config.system_id, srcComponent=config.component_id
        )
        # One decoder per link: a serial stream's partial frame must not meet another link's.
        self._decoders: dict[int, mavlink.MAVLink] = {}
        if config.signing_key is not None:
            self._enc.signing.secret_key = config.signing_key
            self._enc.signing.sign_outgoing = True
            self._enc.signing.link_id = 0
            self._enc.signing.timestamp = max(
                1, int((wall_clock() - SIGNING_EPOCH_UNIX_S) * 100_000)
            )
        #: ArduPilot's routing table: (system, component, link) in the order learned, at most
        #: MAX_ROUTES, never forgotten (only a reboot clears it).
        self.routes: list[tuple[int, int, int]] = []
        #: Links a frame was received on since boot (ArduPilot's ``active_channel_mask``).
        self._active_links: set[int] = set()
        #: Each link's outgoing side (channel 0 the companion's): delay and hold, see
        #: :mod:`sim_servo.linktiming`.
        self._links: list[LinkOutput | LoopLinkOutput] = []
        self.set_links(links)
        self._deferred: list[tuple[float, mavlink.MAVLink_message]] = []
        self._inbox: list[tuple[float, int, mavlink.MAVLink_message]] = []
        #: The link of the frame being handled (a COMMAND_ACK goes back on it only).
        self._rx_channel = 0
        #: While rebooting: when the autopilot comes back (silent and deaf until then).
        self._rebooting_until_s: float | None = None
        self.params: dict[str, Param] = self._make_params()
        self._param_names = list(self.params)
        #: PX4: the commander's queue of commands waiting for its next cycle, (due, command).
        self._commander: list[tuple[float, Command]] = []
        #: PX4: armed (MAV_CMD_COMPONENT_ARM_DISARM); prearmed (COM_PREARM_MODE, 5 s after boot).
        self.armed = config.flavour == "px4" and config.armed
        self.prearmed = False
        #: PX4: actuator set 1–6 as last set by DO_SET_ACTUATOR (NaN: never set since boot).
        self.actuator_values = [math.nan] * PX4_ACTUATOR_SET_COUNT
        #: PX4: the (system, component)s each link has heard (``component_was_seen``).
        self._heard: dict[int, set[tuple[int, int]]] = {}
        #: ArduPilot: the PWM each output was last given (boot values until a command).
        self._commanded_us: dict[int, int] = self._boot_pwm_us()
        #: ArduPilot: the safety switch (BRD_SAFETY_DEFLT at each boot).
        self.safety_on = self._safety_default()
        #: What the autopilot reports (SERVO_OUTPUT_RAW, ACTUATOR_OUTPUT_STATUS) …
        self.pwm_us: dict[int, int] = {}
        #: … and what each servo physically receives (0: no pulses).
        self.output_us: dict[int, int] = {}
        self.servos: dict[int, Servo] = {}
        for output in range(1, OUTPUT_COUNT + 1):
            deg_per_us = config.servo.deg_per_us
            if hand is not None and output in hand.outputs:
                deg_per_us = hand.deg_per_us(output)
            params = ServoParams(
                slew_s_per_60deg=config.servo.slew_s_per_60deg,
                deg_per_us=deg_per_us,
                deadband_us=config.servo.deadband_us,
                travel_min_us=config.servo.travel_min_us,
                travel_max_us=config.servo.travel_max_us,
            )
            self.servos[output] = Servo(params, config.servo.initial_us, now_s)
        self.pwm_us, self.output_us = self._outputs_now()
        if config.flavour == "px4":
            # PX4 drives every output to its disarmed PWM at boot: the horns go there.
            for output, pwm in self.output_us.items():
                self.servos[output].command(pwm, now_s)
        self._stream_msgs = self._streamable()
        self._interval_ms: dict[int, int] = {
            msg_id: self._default_interval_ms(msg_id) for msg_id in self._stream_msgs
        }
        self._next_due_s: dict[int, float | None] = {
            msg_id: now_s if self._interval_ms[msg_id] > 0 else None for msg_id in self._stream_msgs
        }
        self._heartbeat_paused = False
        # Set by pause_heartbeat() (a test asking over the query socket): overrides the schedule.
        self._heartbeat_held: bool | None = None
        after_s = config.faults.reboot_after_s
        self._reboot_due_s: float | None = None if after_s is None else now_s + after_s
        self._moving = config.flavour == "px4"  # PX4 drove the horns to the disarmed PWM
        self.peer: tuple[int, int] | None = None
        self._peers_seen: set[tuple[int, int]] = set()
        self.stats = dict.fromkeys(
            (
                "rx",
                "tx",
                "bad_frames",
                "rejected_signature",
                "dropped_in",
                "dropped_out",
                "corrupted_in",
                "corrupted_out",
                "acks",
                "acks_withheld",
                "routed",
                "reboots",
                "ignored_rebooting",
            ),
            0,
        )
        self._commands: dict[int, Callable[[Command, float], int]] = {
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_message_interval,
            mavlink.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
        }
        if config.flavour == "ardupilot":
            self._commands[mavlink.MAV_CMD_DO_SET_SERVO] = self._cmd_do_set_servo
        else:
            self._commands[mavlink.MAV_CMD_DO_SET_ACTUATOR] = self._cmd_do_set_actuator
            self._commands[mavlink.MAV_CMD_COMPONENT_ARM_DISARM] = self._cmd_arm_disarm
        self._lua: LuaScriptTiming | None = None
        self._lua_pending: list[tuple[float, Command]] = []
        if config.lua_script:
            self._lua_setup(now_s)
        self._handlers: dict[str, Callable[[Any, float], None]] = {
            "HEARTBEAT": self._on_heartbeat,
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "PARAM_SET": self._on_param_set,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
        }

    def set_links(self, count: int) -> None:
        """Serve ``count`` links (channels 0 … count−1): our own frames go out on each."""
        if count < 1:
            raise ValueError(f"links={count} must be >= 1")
        while len(self._links) < count:
            if self.config.flavour == "px4":
                loop_s = self.config.px4_timing.mavlink_loop_ms / 1000.0
                self._links.append(LoopLinkOutput(loop_s, self._boot_s))
            else:
                self._links.append(LinkOutput(self.config.link_timing))

    def _link(self, channel: int) -> LinkOutput | LoopLinkOutput:
        self.set_links(channel + 1)  # a link we hear from exists
        return self._links[channel]

    def _boot_pwm_us(self) -> dict[int, int]:
        """ArduPilot: each output's PWM at boot: none on a disabled output, idle on an
        assigned one."""
        return {
            output: 0 if self._function(output) == 0 else IDLE_ASSIGNED_PWM_US
            for output in range(1, OUTPUT_COUNT + 1)
        }

    def _safety_default(self) -> bool:
        return self.config.flavour == "ardupilot" and self.params["BRD_SAFETY_DEFLT"].value != 0

    # -- outputs: what is reported, what the servos receive ----------------------------------

    @property
    def outputs_live(self) -> bool:
        """PX4: armed or prearmed; ArduPilot: the safety switch off (per output: the mask)."""
        if self.config.flavour == "px4":
            return self.armed or self.prearmed
        return not self.safety_on

    def _live(self, output: int) -> bool:
        if self.rebooting:
            return False
        if self.config.flavour == "px4":
            return self.armed or self.prearmed
        mask = self.params["BRD_SAFETY_MASK"].value
        return not self.safety_on or bool(mask >> (output - 1) & 1)

    def _outputs_now(
        self, outputs: Iterable[int] | None = None
    ) -> tuple[dict[int, int], dict[int, int]]:
        """(reported, physical) PWM of every output (or of ``outputs``) in the current state.

        PX4 reports what it outputs. ArduPilot reports the PWM it was given (SERVO_OUTPUT_RAW
        reads back what the output driver was told), while the safety switch keeps an output
        out of ``BRD_SAFETY_MASK`` without pulses. During a reboot nothing has pulses."""
        reported: dict[int, int] = {}
        physical: dict[int, int] = {}
        for output in range(1, OUTPUT_COUNT + 1) if outputs is None else outputs:
            if self.config.flavour == "px4":
                reported[output] = self._px4_output_us(output)
                physical[output] = reported[output]
            else:
                reported[output] = self._commanded_us[output]
                physical[output] = reported[output] if self._live(output) else 0
            if self.rebooting:
                physical[output] = 0
        return reported, physical

    def _px4_output_us(self, output: int) -> int:
        """PX4's output: the disarmed PWM (PWM_MAIN_DISn) unless live; live, an actuator-set
        output shows its slot (NaN: never set, still disarmed), a motor its minimum."""
        disarmed = self.params[f"PWM_MAIN_DIS{output}"].value
        if not self._live(output):
            return disarmed
        function = self._function(output)
        low, high = self._pwm_limits(output)
        slot = function - PX4_ACTUATOR_SET_FIRST_FUNCTION
        if 0 <= slot < PX4_ACTUATOR_SET_COUNT:
            value = self.actuator_values[slot]
            if math.isnan(value):
                return disarmed
            return min(max(px4_actuator_pwm_us(value), low), high)
        if function in PX4_MOTOR_FUNCTIONS.values() and self.armed:
            return low  # motors idle at their minimum once armed
        return disarmed

    def _refresh_outputs(
        self, now_s: float, cause: str, outputs: Iterable[int] | None = None
    ) -> None:
        """Bring the reported and physical PWMs up to the current state; every physical change
        moves its servo and is logged as an ``output`` event (what the servo receives).
        ``outputs``: only those changed (a command to one output; the rest of the state is as
        the last full refresh left it)."""
        self._run_vehicle_log(now_s)  # the samples due before a servo's course changes
        reported, physical = self._outputs_now(outputs)
        self.pwm_us = reported if outputs is None else {**self.pwm_us, **reported}
        for output, pwm in physical.items():
            before = self.output_us.get(output)
            if before == pwm:
                continue
            self.output_us[output] = pwm
            servo = self.servos[output]
            servo.command(pwm, now_s)
            self._moving = True
            self.emit(
                now_s,
                "output",
                output=output,
                pwm_us=pwm,
                from_us=before,
                cause=cause,
                position_us=round(servo.position_us(now_s), 3),
            )

    def _run_prearm(self, now_s: float) -> None:
        if self.config.flavour != "px4":
            return
        due_s = self._prearm_due_s()
        prearmed = due_s is not None and now_s >= due_s
        if prearmed != self.prearmed:
            self.prearmed = prearmed
            self.emit(now_s, "prearm", prearmed=prearmed)
            self._refresh_outputs(now_s, "prearm")

    def _prearm_due_s(self) -> float | None:
        """When PX4 prearms this boot (None: never). Mode 1 (safety button) is mode 2 here:
        the simulated PX4 has no safety button, as SITL."""
        if self.config.flavour != "px4" or self.rebooting:
            return None
        if self.params["COM_PREARM_MODE"].value not in (1, 2):
            return None
        return self._boot_s + PX4_PREARM_DELAY_S

    def set_armed(self, armed: bool, now_s: float, cause: str = "query") -> bool:
        """PX4: arm or disarm now (``cause`` goes in the event: query, command, kill …); False
        (nothing done) on ArduPilot or while rebooting."""
        if self.config.flavour != "px4" or self.rebooting:
            return False
        if armed != self.armed:
            self.armed = armed
            self.emit(now_s, "arming", armed=armed, cause=cause)
            self._refresh_outputs(now_s, "arm" if armed else cause)
        return True

    def set_safety(self, on: bool, now_s: float, cause: str = "query") -> bool:
        """ArduPilot: engage (``on``) or disengage the safety switch now; False (nothing done)
        on PX4 or while rebooting."""
        if self.config.flavour != "ardupilot" or self.rebooting:
            return False
        if on != self.safety_on:
            self.safety_on = on
            self.emit(now_s, "safety", on=on, cause=cause)
            self._refresh_outputs(now_s, "safety_on" if on else "safety_off")
        return True

    # -- parameters ------------------------------------------------------------------------

    def _make_params(self) -> dict[str, Param]:
        params: dict[str, Param] = {}
        functions = self.config.functions
        if self.config.flavour == "ardupilot":
            int16 = mavlink.MAV_PARAM_TYPE_INT16
            for n in range(1, OUTPUT_COUNT + 1):
                for suffix, value in (
                    ("FUNCTION", functions[n]),
                    ("MIN", ARDUPILOT_PWM_MIN_US),
                    ("MAX", ARDUPILOT_PWM_MAX_US),
                    ("TRIM", ARDUPILOT_PWM_TRIM_US),
                ):
                    name = f"SERVO{n}_{suffix}"
                    params[name] = Param(name, value, int16, -32768, 32767)
            # AP_BoardConfig: the safety switch's state at boot (boards default 1; off here so
            # a bench vehicle's outputs are live) and the outputs it leaves alone.
            params["BRD_SAFETY_DEFLT"] = Param(
                "BRD_SAFETY_DEFLT", 0, mavlink.MAV_PARAM_TYPE_INT8, -128, 127
            )
            params["BRD_SAFETY_MASK"] = Param(
                "BRD_SAFETY_MASK", 0, mavlink.MAV_PARAM_TYPE_INT32, -(2**31), 2**31 - 1
            )
        else:
            int32 = mavlink.MAV_PARAM_TYPE_INT32
            for n in range(1, OUTPUT_COUNT + 1):
                for prefix, value in (
                    ("PWM_MAIN_FUNC", functions[n]),
                    ("PWM_MAIN_MIN", PX4_PWM_MIN_US),
                    ("PWM_MAIN_MAX", PX4_PWM_MAX_US),
                    ("PWM_MAIN_DIS", PX4_DISARMED_PWM_US),
                ):
                    name = f"{prefix}{n}"
                    params[name] = Param(name, value, int32, -(2**31), 2**31 - 1)
            for name, value in (("COM_PREARM_MODE", 0), *PX4_FORWARD_DEFAULTS.items()):
                params[name] = Param(name, value, int32, -(2**31), 2**31 - 1)
        for name, value in self.config.params.items():
            param = params.get(name)
            if param is None:
                raise SimConfigError(
                    f"parameter {name!r} unknown to the {self.config.flavour} flavour"
                )
            if not param.low <= value <= param.high:
                raise SimConfigError(
                    f"parameter {name}={value} outside [{param.low}, {param.high}]"
                )
            if name == "COM_PREARM_MODE" and value not in PX4_PREARM_MODES:
                raise SimConfigError(f"COM_PREARM_MODE={value}; valid: {list(PX4_PREARM_MODES)}")
            param.value = value
        return params

    def _forwarding(self, channel: int) -> bool:
        """PX4: whether the MAVLink instance on ``channel`` forwards (``MAV_n_FORWARD``)."""
        name = PX4_FORWARD_PARAMS.get(channel)
        return name is not None and self.params[name].value != 0

    def _function(self, output: int) -> int:
        key = (
            f"SERVO{output}_FUNCTION"
            if self.config.flavour == "ardupilot"
            else f"PWM_MAIN_FUNC{output}"
        )
        return self.params[key].value

    def _pwm_limits(self, output: int) -> tuple[int, int]:
        if self.config.flavour == "ardupilot":
            return (
                self.params[f"SERVO{output}_MIN"].value,
                self.params[f"SERVO{output}_MAX"].value,
            )
        return (
            self.params[f"PWM_MAIN_MIN{output}"].value,
            self.params[f"PWM_MAIN_MAX{output}"].value,
        )

    def _encode_param_value(self, param: Param) -> float:
        if self.config.flavour == "px4":
            # PX4 sends integer parameters bytewise: the int32's bits read as a float.
            return struct.unpack("<f", struct.pack("<i", param.value))[0]
        return float(param.value)

    def _decode_param_value(self, param: Param, value: float) -> int | None:
        if self.config.flavour == "px4":
            return struct.unpack("<i", struct.pack("<f", value))[0]
        if not math.isfinite(value):
            return None
        # GCS_Param: add 0.01 away from zero before truncating, then constrain to the type.
        nudged = value + (0.01 if value >= 0 else -0.01)
        return int(min(max(nudged, param.low), param.high))

    # -- time helpers ----------------------------------------------------------------------

    def _t(self, now_s: float) -> float:
        return round(now_s - self._start_s, 6)

    def emit(self, now_s: float, event: str, **fields: Any) -> None:
        self._emit_sink({"t_s": self._t(now_s), "event": event, **fields})

    def _time_boot_us(self, now_s: float) -> int:
        return max(0, round((now_s - self._boot_s) * 1e6))

    def _time_unix_us(self, now_s: float) -> int:
        return max(0, round((self._unix_at_start_s + now_s - self._start_s) * 1e6))

    # -- output pipeline -------------------------------------------------------------------

    def _send(self, msg: mavlink.MAVLink_message, now_s: float, channel: int | None = None) -> None:
        """Send ``msg`` on every link, or only on ``channel``."""
        if self.config.signing_key is not None:
            self._enc.signing.timestamp = self._signing_timestamp(now_s)
        frame = msg.pack(self._enc)
        self._enc.seq = (self._enc.seq + 1) % 256
        self._enc.total_packets_sent += 1
        if self.faults.drop_out():
            self.stats["dropped_out"] += 1
            self.emit(now_s, "fault", fault="drop_out", msg=msg.get_type())
            return
        corrupted = self.faults.corrupt_out(frame)
        if corrupted != frame:
            self.stats["corrupted_out"] += 1
            self.emit(now_s, "fault", fault="corrupt_out", msg=msg.get_type())
        self.stats["tx"] += 1
        delay_s = self.faults.delay_s()
        links = self._links if channel is None else [self._link(channel)]
        for link in links:
            link.write(corrupted, now_s, delay_s)

    def _signing_timestamp(self, now_s: float) -> int:
        """The timestamp our next signed frame carries, as the MAVLink signing spec asks
        ("Timestamp Handling"): never below the last one sent (pymavlink adds 1 per frame),
        the system clock's, or any correctly signed incoming one (each link's decoder keeps the
        highest it accepted, as the C library does). Without the last rule, a companion that
        restarts over a minute after we booted (its clock then ahead of our frames by more)
        refuses every frame of ours as a stream more than a minute old, and never reconnects."""
        wall_ticks = (self._time_unix_us(now_s) - SIGNING_EPOCH_UNIX_S * 1_000_000) // 10
        seen = max((d.signing.timestamp for d in self._decoders.values()), default=0)
        return max(self._enc.signing.timestamp, wall_ticks, seen)

    def _defer(self, msg: mavlink.MAVLink_message, now_s: float) -> None:
        """Send on the next main-loop pass, as ArduPilot does for STATUSTEXT and PARAM_VALUE."""
        self._deferred.append((now_s + self._loop_s, msg))

    def poll(self, now_s: float) -> list[tuple[int, bytes]]:
        """Run the periodic work due by ``now_s``; the frames to write now, as ``(link,
        frame)``: our own (on every link, or the one a reply is for) and those routed from one
        link to another (as received: a signed frame keeps its signature)."""
        # First: the sample's horn positions are those before this pass's commands.
        self._run_vehicle_log(now_s)
        self._run_reboot(now_s)
        if self._rebooting_until_s is None:
            self._run_prearm(now_s)
            self._run_inbox(now_s)
            self._run_lua(now_s)
            self._run_commander(now_s)
            self._run_deferred(now_s)
            self._run_heartbeat(now_s)
            self._run_streams(now_s)
        frames = [
            (channel, frame)
            for channel, link in enumerate(self._links)
            for frame in link.take(now_s)
        ]
        # The settled event's hand pose costs a forward kinematics: not while frames wait to be
        # written (next_event_s() asks for another call at once; the event keeps its time).
        if not frames:
            self._check_settled(now_s)
        return frames

    def next_event_s(self, now_s: float) -> float:
        """The earliest time at which :meth:`poll` has something to do (≥ ``now_s``)."""
        candidates: list[float] = []
        if self._rebooting_until_s is not None:
            candidates.append(self._rebooting_until_s)
        else:
            candidates += [due for due in self._next_due_s.values() if due is not None]
            candidates += [due for due, _ in self._deferred]
            candidates += [due for due, _, _ in self._inbox]
            candidates += [due for due, _ in self._lua_pending]
            candidates += [due for due, _ in self._commander]
            prearm_s = self._prearm_due_s()
            if prearm_s is not None and not self.prearmed:
                candidates.append(prearm_s)
        if self._reboot_due_s is not None:
            candidates.append(self._reboot_due_s)
        if self._vehicle_due_s is not None:
            # Samples are written late, in batches (see _run_vehicle_log): no wake-up each.
            candidates.append(self._vehicle_due_s + VEHICLE_LOG_LAG_S)
        candidates += [due for link in self._links if (due := link.next_event_s()) is not None]
        if self._moving:
            candidates.append(max(servo.arrival_s() for servo in self.servos.values()))
        return max(now_s, min(candidates)) if candidates else now_s + 1.0

    def _run_deferred(self, now_s: float) -> None:
        due = [msg for at, msg in self._deferred if at <= now_s]
        self._deferred = [(at, msg) for at, msg in self._deferred if at > now_s]
        for msg in due:
            self._send(msg, now_s)

    def pause_heartbeat(self, paused: bool, now_s: float) -> None:
        """Stop (``paused``) or restart our HEARTBEAT now, whatever the configured schedule says
        from then on: a test triggers a link loss when it is ready instead of at a fixed time.
        A restart sends a heartbeat at once and every period from there, so the daemon's
        reaction is measured from the heartbeat, not from where the old schedule stood."""
        self._heartbeat_held = paused
        msg_id = mavlink.MAVLINK_MSG_ID_HEARTBEAT
        if not paused and self._heartbeat_paused and self._next_due_s.get(msg_id) is not None:
            self._next_due_s[msg_id] = now_s
        if paused != self._heartbeat_paused:
            self._heartbeat_paused = paused
            self.emit(now_s, "fault", fault="heartbeat_paused" if paused else "heartbeat_resumed")

    # -- reboot ----------------------------------------------------------------------------

    @property
    def rebooting(self) -> bool:
        return self._rebooting_until_s is not None

    def reboot(self, now_s: float, gap_s: float | None = None) -> bool:
        """Reboot now: silent and deaf for ``gap_s`` (default ``reboot_gap_s``), then back with
        time_boot from 0, outputs at their boot values, streams at their defaults (requested
        intervals lost), an empty routing table and the MAVLink sequence from 0; parameters
        keep their values. Frames not yet sent are lost. False (nothing done) while already
        rebooting."""
        if self._rebooting_until_s is not None:
            return False
        gap_s = self.config.faults.reboot_gap_s if gap_s is None else gap_s
        if not 0.0 <= gap_s <= 600.0:
            raise ValueError(f"reboot gap_s={gap_s!r} outside [0.0, 600.0]")
        self._rebooting_until_s = now_s + gap_s
        self.stats["reboots"] += 1
        self.emit(now_s, "fault", fault="reboot", gap_s=gap_s)
        self._inbox.clear()
        self._deferred.clear()
        self._lua_pending.clear()
        self._commander.clear()
        self._decoders.clear()  # a partial frame does not survive the reboot
        for link in self._links:
            link.clear()
        if self.armed:
            self.armed = False
            self.emit(now_s, "arming", armed=False, cause="reboot")
        if self.prearmed:
            self.prearmed = False
            self.emit(now_s, "prearm", prearmed=False)
        # No pulses while the board restarts: servos hold where they are.
        self._refresh_outputs(now_s, "reboot")
        if gap_s == 0.0:
            self._boot(now_s)
        return True

    def _run_reboot(self, now_s: float) -> None:
        if self._reboot_due_s is not None and self._reboot_due_s <= now_s:
            due_s, self._reboot_due_s = self._reboot_due_s, None
            self.reboot(due_s)
        if self._rebooting_until_s is not None and self._rebooting_until_s <= now_s:
            self._boot(self._rebooting_until_s)

    def _boot(self, now_s: float) -> None:
        self._rebooting_until_s = None
        self._boot_s = now_s
        self._enc.seq = 0
        self.routes.clear()
        self._active_links.clear()
        self.peer = None
        self._peers_seen.clear()
        self._heard.clear()
        for link in self._links:
            if isinstance(link, LoopLinkOutput):
                link.phase_s = now_s
        self._commanded_us = self._boot_pwm_us()
        self.actuator_values = [math.nan] * PX4_ACTUATOR_SET_COUNT
        safety_on = self._safety_default()
        if safety_on != self.safety_on:
            self.safety_on = safety_on
            self.emit(now_s, "safety", on=safety_on, cause="boot")
        self._refresh_outputs(now_s, "boot")
        for msg_id in self._stream_msgs:
            self._interval_ms[msg_id] = self._default_interval_ms(msg_id)
            self._next_due_s[msg_id] = now_s if self._interval_ms[msg_id] > 0 else None
        self.emit(now_s, "fault", fault="booted")

    def _heartbeat_paused_at(self, now_s: float) -> bool:
        if self._heartbeat_held is not None:
            return self._heartbeat_held
        after = self.config.faults.heartbeat_pause_after_s
        if after is None:
            return False
        elapsed = now_s - self._start_s
        length = self.config.faults.heartbeat_pause_for_s
        return elapsed >= after and (length is None or elapsed < after + length)

    def _run_heartbeat(self, now_s: float) -> None:
        msg_id = mavlink.MAVLINK_MSG_ID_HEARTBEAT
        due = self._next_due_s.get(msg_id)
        if due is None or now_s < due:
            return
        self._advance(msg_id, now_s)
        paused = self._heartbeat_paused_at(now_s)
        if paused != self._heartbeat_paused:
            self._heartbeat_paused = paused
            self.emit(now_s, "fault", fault="heartbeat_paused" if paused else "heartbeat_resumed")
        if not paused:
            self._send(self._heartbeat(), now_s)

    def _heartbeat(self) -> mavlink.MAVLink_message:
        autopilot = (
            mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
            if self.config.flavour == "ardupilot"
            else mavlink.MAV_AUTOPILOT_PX4
        )
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return self._enc.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR,
            autopilot,
            base_mode,
            0,
            mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY,
        )

    def _effective_interval_ms(self, msg_id: int) -> int:
        """The interval a stream really runs at: SERVO_OUTPUT_RAW never beats the configured
        floor (50 Hz on ArduCopter, measured), whatever interval is stored and reported."""
        interval_ms = self._interval_ms[msg_id]
        if msg_id == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW and interval_ms > 0:
            return max(interval_ms, self.config.servo_output_floor_ms)
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

    def _run_streams(self, now_s: float) -> None:
        for msg_id in self._stream_msgs:
            if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                continue
            due = self._next_due_s[msg_id]
            if due is None or now_s < due:
                continue
            self._advance(msg_id, now_s)
            self._send(self._stream_message(msg_id, now_s), now_s)

    def _streamable(self) -> tuple[int, ...]:
        ids = [
            mavlink.MAVLINK_MSG_ID_HEARTBEAT,
            mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
            mavlink.MAVLINK_MSG_ID_ATTITUDE,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
        ]
        if self.config.flavour == "px4":
            ids.append(mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS)
        else:
            ids.append(mavlink.MAVLINK_MSG_ID_SYS_STATUS)
        return tuple(ids)

    def _default_interval_ms(self, msg_id: int) -> int:
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return round(1000.0 / self.config.heartbeat_rate_hz)
        if msg_id == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW and self.config.servo_output_rate_hz:
            return max(1, round(1000.0 / self.config.servo_output_rate_hz))
        if msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME and self.config.system_time_default_hz:
            return max(1, round(1000.0 / self.config.system_time_default_hz))
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE and self.config.attitude_default_hz:
            return max(1, round(1000.0 / self.config.attitude_default_hz))
        if (
            msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
            and self.config.local_position_default_hz
        ):
            return max(1, round(1000.0 / self.config.local_position_default_hz))
        return 0

    def _stream_message(self, msg_id: int, now_s: float) -> mavlink.MAVLink_message:
        if msg_id == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
            values = [self.pwm_us[o] & 0xFFFF for o in range(1, OUTPUT_COUNT + 1)]
            return self._enc.servo_output_raw_encode(
                self._time_boot_us(now_s) & 0xFFFFFFFF, 0, *values
            )
        if msg_id == mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS:
            actuators = [float(self.pwm_us[o]) for o in range(1, OUTPUT_COUNT + 1)]
            return self._enc.actuator_output_status_encode(
                self._time_boot_us(now_s), OUTPUT_COUNT, actuators + [0.0] * (32 - OUTPUT_COUNT)
            )
        if msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME:
            # time_boot_ms restarts at 0 on a reboot: how a peer tells a reboot from a link loss.
            return self._enc.system_time_encode(
                self._time_unix_us(now_s), (self._time_boot_us(now_s) // 1000) & 0xFFFFFFFF
            )
        if msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            # Copter's update_vehicle_sensor_status_flags: motor outputs "enabled" unless the
            # safety switch is on (the only sensor bit modelled here).
            motors = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            enabled = 0 if self.safety_on else motors
            return self._enc.sys_status_encode(
                motors, enabled, motors, 0, 0, -1, -1, 0, 0, 0, 0, 0, 0
            )
        if msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
            # The state at exactly the time the stamp names (see sim_servo.hover).
            stamp_ms = self._time_boot_us(now_s) // 1000
            state = self.vehicle.state(self._boot_s + stamp_ms / 1000.0 - self._start_s)
            if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
                return self._enc.attitude_encode(
                    stamp_ms & 0xFFFFFFFF, *state.attitude_wrapped(), *state.body_rates()
                )
            return self._enc.local_position_ned_encode(
                stamp_ms & 0xFFFFFFFF,
                state.north_m,
                state.east_m,
                state.down_m,
                state.vn_m_s,
                state.ve_m_s,
                state.vd_m_s,
            )
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return self._heartbeat()
        raise AssertionError(f"message id {msg_id} is not streamable")  # _streamable() guards

    # -- input pipeline --------------------------------------------------------------------

    def receive(self, data: bytes, now_s: float, channel: int = 0) -> None:
        """Feed bytes that arrived at ``now_s`` on link ``channel`` (0: the companion's link;
        others: e.g. a ground station's), a datagram or a chunk of a serial stream."""
        self._run_reboot(now_s)
        if self._rebooting_until_s is not None:
            self.stats["ignored_rebooting"] += 1
            return
        corrupted = self.faults.corrupt_in(data)
        if corrupted != data:
            self.stats["corrupted_in"] += 1
            self.emit(now_s, "fault", fault="corrupt_in", bytes=len(data))
        try:
            messages = self._decoder(channel).parse_buffer(corrupted) or []
        except mavlink.MAVError as exc:  # robust_parsing reports most problems as BAD_DATA
            messages = [mavlink.MAVLink_bad_data(b"", str(exc))]
        self._link(channel).arrived(len(messages), now_s)
        # PX4's receiver thread handles a frame as it is read; ArduPilot on a main-loop pass.
        due = now_s if self.config.flavour == "px4" else self._next_tick_s(now_s)
        self._inbox.extend((due, channel, msg) for msg in messages)

    def _decoder(self, channel: int) -> mavlink.MAVLink:
        decoder = self._decoders.get(channel)
        if decoder is None:
            decoder = mavlink.MAVLink(None)
            decoder.robust_parsing = True
            if self.config.signing_key is not None:
                decoder.signing.secret_key = self.config.signing_key
                decoder.signing.allow_unsigned_callback = lambda _mav, msg_id: (
                    msg_id in UNSIGNED_ALLOWED_IDS
                )
            self._decoders[channel] = decoder
        return decoder

    def _next_tick_s(self, now_s: float) -> float:
        """The next main-loop pass at or after ``now_s`` (passes every ``1/loop_rate_hz`` from
        boot)."""
        ticks = math.ceil(round((now_s - self._boot_s) / self._loop_s, 9))
        return self._boot_s + ticks * self._loop_s

    def _run_inbox(self, now_s: float) -> None:
        # ArduPilot reads its links once per main-loop pass (GCS::update_receive), so a frame
        # waits for the next pass before it is handled and answered.
        due = [(channel, msg) for at, channel, msg in self._inbox if at <= now_s]
        self._inbox = [entry for entry in self._inbox if entry[0] > now_s]
        for channel, msg in due:
            self._dispatch(msg, now_s, channel)

    def _dispatch(self, msg: mavlink.MAVLink_message, now_s: float, channel: int = 0) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            reason = str(getattr(msg, "reason", ""))
            if "signature" in reason:
                self.stats["rejected_signature"] += 1
                self.emit(now_s, "rejected", reason=reason)
            else:
                self.stats["bad_frames"] += 1
                self.emit(now_s, "bad_frame", reason=reason)
            return
        if self.faults.drop_in():
            self.stats["dropped_in"] += 1
            self.emit(now_s, "fault", fault="drop_in", msg=kind)
            return
        self.stats["rx"] += 1
        self.emit(
            now_s,
            "rx",
            msg=kind,
            src=[msg.get_srcSystem(), msg.get_srcComponent()],
            fields=_fields(msg),
        )
        self._active_links.add(channel)
        route = self._route_px4 if self.config.flavour == "px4" else self._route
        if not route(msg, channel, now_s):
            return
        handler = self._handlers.get(kind)
        if handler is not None:
            self._rx_channel = channel
            handler(msg, now_s)

    def _route(self, msg: mavlink.MAVLink_message, channel: int, now_s: float) -> bool:
        """Learn where ``msg`` came from and forward it to the links of its target; True if it
        is (also) for us. ArduPilot's rules, libraries/GCS_MAVLink/MAVLink_routing.cpp
        ``check_and_forward``:

        * our own (system, component) looped back: handled, neither learned nor forwarded;
        * every other source is learned as (system, component, link), never forgotten (a
          reboot clears the table), at most MAX_ROUTES entries;
        * RADIO, RADIO_STATUS, ADSB_VEHICLE: handled, not forwarded; HEARTBEAT: handled and
          forwarded to every active link but its own and those its sender was heard on;
        * target (system, component) ours: handled only;
        * otherwise forwarded to each link (never the one it came in on) with a route that
          matches: target system 0 or absent, any route; else the route's system and, for our
          own system, its component (or target component 0/absent); for another system, any
          of its components;
        * for our system and not forwarded anywhere (a component never heard, or heard only on
          the link the frame came in on): handled here, so a command gets our UNSUPPORTED.
        """
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        own = (self.config.system_id, self.config.component_id)
        if source == own:
            return True
        self._learn_route(source, channel)
        msg_id = msg.get_msgId()
        if msg_id in NOT_FORWARDED_IDS:
            return True
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            heard_on = {link for s, c, link in self.routes if (s, c) == source}
            others = sorted(self._active_links - {channel} - heard_on)
            self._forward(msg, others, now_s, source, (0, 0), log=False)
            return True
        target_system = getattr(msg, "target_system", -1)
        target_component = getattr(msg, "target_component", -1)
        broadcast_system = target_system in (0, -1)
        broadcast_component = target_component in (0, -1)
        match_system = broadcast_system or target_system == own[0]
        process_locally = match_system and (broadcast_component or target_component == own[1])
        if process_locally and not broadcast_system and not broadcast_component:
            return True
        links: list[int] = []
        for system, component, link in self.routes:
            matches = broadcast_system or (
                target_system == system
                and (broadcast_component or target_component == component or not match_system)
            )
            if matches and link != channel and link not in links:
                links.append(link)
        self._forward(msg, links, now_s, source, (target_system, target_component))
        if not links and match_system:
            process_locally = True
        return process_locally

    def _route_px4(self, msg: mavlink.MAVLink_message, channel: int, now_s: float) -> bool:
        """PX4's routing (mavlink_main.cpp ``forward_message``, mavlink_receiver.cpp): True if
        ``msg`` is for us.

        * each link remembers the (system, component)s heard on it (``component_was_seen``);
        * a frame is forwarded only when forwarding is on for the link it came in on *and* for
          the link it goes out on (``MAV_n_FORWARD``, see :data:`PX4_FORWARD_PARAMS`), never
          back out of its own link, and only to a link that has heard its target (a target
          system 0, or no target: a link that has heard anyone; component 0: any component
          of the system);
        * handled here when its target is us or a broadcast; a command for another component
          of our system is otherwise ignored, without an answer ("Ignore command 31010 from
          255/190 to 1/191" in PX4's log), whether or not it was forwarded.
        """
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        own = (self.config.system_id, self.config.component_id)
        if source == own:
            return True
        if source[0] != 0:
            self._heard.setdefault(channel, set()).add(source)
        target_system = max(0, getattr(msg, "target_system", 0))
        target_component = max(0, getattr(msg, "target_component", 0))
        local = target_system in (0, own[0]) and target_component in (0, own[1])
        if (target_system, target_component) != own and self._forwarding(channel):
            links = [
                link
                for link in range(len(self._links))
                if link != channel
                and self._forwarding(link)
                and self._was_seen(link, target_system, target_component)
            ]
            if links:
                delay_s = self.config.px4_timing.forward_delay_ms / 1000.0
                self._forward(
                    msg, links, now_s, source, (target_system, target_component), delay_s=delay_s
                )
        is_command = msg.get_type() in ("COMMAND_LONG", "COMMAND_INT")
        if not local and is_command and target_system == own[0]:
            self.emit(
                now_s,
                "ignored",
                command=msg.command,
                src=list(source),
                to=[target_system, target_component],
            )
        return local

    def _was_seen(self, channel: int, system: int, component: int) -> bool:
        heard = self._heard.get(channel, set())
        if system == 0:
            return bool(heard)
        return any(s == system and component in (0, c) for s, c in heard)

    def _learn_route(self, source: tuple[int, int], channel: int) -> None:
        route = (*source, channel)
        if source[0] != 0 and route not in self.routes and len(self.routes) < MAX_ROUTES:
            self.routes.append(route)

    def _forward(
        self,
        msg: mavlink.MAVLink_message,
        links: list[int],
        now_s: float,
        source: tuple[int, int],
        target: tuple[int, int],
        *,
        log: bool = True,
        delay_s: float = 0.0,
    ) -> None:
        frame = bytes(msg.get_msgbuf())
        for link in links:
            # Routed frames take the same way out as ours (delay and hold), without faults.
            self._link(link).write(frame, now_s, delay_s)
            self.stats["routed"] += 1
        if links and log:
            self.emit(
                now_s,
                "routed",
                msg=msg.get_type(),
                src=list(source),
                to=list(target),
                links=links,
            )

    def _on_heartbeat(self, msg: Any, now_s: float) -> None:
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        self.peer = source
        if source not in self._peers_seen:
            self._peers_seen.add(source)
            self.emit(now_s, "peer", src=list(source), type=msg.type, autopilot=msg.autopilot)

    def _on_command_long(self, msg: Any, now_s: float) -> None:
        # Routing decided it is ours (MAVLink_routing.cpp); GCS_Common.cpp handle_command_long
        # checks no target itself, so a command for a component never heard gets our answer.
        params = (
            msg.param1,
            msg.param2,
            msg.param3,
            msg.param4,
            msg.param5,
            msg.param6,
            msg.param7,
        )
        self._run_command(self._command(msg, params), now_s)

    def _on_command_int(self, msg: Any, now_s: float) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._run_command(self._command(msg, params), now_s)

    def _command(self, msg: Any, params: tuple[float, ...]) -> Command:
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        return Command(msg.command, params, source, self._rx_channel)

    def _run_command(self, command: Command, now_s: float) -> None:
        if self._lua is not None and command.command == MAV_CMD_USER_2:
            self._lua_pending.append((self._lua.answer_s(now_s), command))
            return
        period_s = self.config.px4_timing.commander_period_ms / 1000.0
        if (
            self.config.flavour == "px4"
            and command.command in PX4_COMMANDER_COMMANDS
            and period_s > 0.0
        ):
            # Commander.cpp handles it (and answers) on its next cycle.
            cycles = math.floor(round((now_s - self._boot_s) / period_s, 9)) + 1
            self._commander.append((self._boot_s + cycles * period_s, command))
            return
        self._execute(command, now_s)

    def _run_commander(self, now_s: float) -> None:
        due = [command for at, command in self._commander if at <= now_s]
        self._commander = [entry for entry in self._commander if entry[0] > now_s]
        for command in due:
            self._execute(command, now_s)

    def _execute(self, command: Command, now_s: float) -> None:
        handler = self._commands.get(command.command)
        result = handler(command, now_s) if handler is not None else mavlink.MAV_RESULT_UNSUPPORTED
        withheld = (
            self.config.faults.withhold_all_acks
            or command.command in self.config.faults.withhold_ack_commands
        )
        self.emit(
            now_s,
            "ack",
            command=command.command,
            command_name=_command_name(command.command),
            result=result,
            result_name=_result_name(result),
            withheld=withheld,
        )
        if withheld:
            self.stats["acks_withheld"] += 1
            return
        self.stats["acks"] += 1
        # On the link the command came from only (GCS_Common.cpp: sent on ``chan``).
        ack = self._enc.command_ack_encode(command.command, result, 0, 0, *command.source)
        self._send(ack, now_s, command.channel)

    def _statustext(self, severity: int, text: str, now_s: float) -> None:
        self.emit(now_s, "statustext", severity=severity, text=text)
        self._defer(self._enc.statustext_encode(severity, text.encode()), now_s)

    # -- commands --------------------------------------------------------------------------

    def _cmd_do_set_servo(self, command: Command, now_s: float) -> int:
        channel_f, pwm_f = command.params[0], command.params[1]
        # param1/param2 reach do_set_servo as uint8_t / uint16_t (C truncation).
        if not (math.isfinite(channel_f) and math.isfinite(pwm_f)) or not 0 <= channel_f < 256:
            return mavlink.MAV_RESULT_FAILED
        output, pwm = int(channel_f), int(pwm_f) % 65536
        if not 1 <= output <= OUTPUT_COUNT:
            return mavlink.MAV_RESULT_FAILED
        if output in self.config.faults.nack_outputs:
            self.emit(now_s, "fault", fault="nack_output", output=output, pwm_us=pwm)
            return mavlink.MAV_RESULT_FAILED
        if self._function(output) not in ARDUPILOT_FREE_FUNCTIONS:
            self._statustext(
                mavlink.MAV_SEVERITY_INFO, STATUSTEXT_IN_USE.format(output=output), now_s
            )
            return mavlink.MAV_RESULT_FAILED
        self._apply(output, pwm, now_s)
        return mavlink.MAV_RESULT_ACCEPTED

    def _apply(self, output: int, pwm: int, now_s: float) -> None:
        """An ArduPilot output given ``pwm`` (DO_SET_SERVO, or the Lua bridge's command)."""
        self._run_vehicle_log(now_s)
        self._commanded_us[output] = pwm
        self._refresh_outputs(now_s, "command", (output,))
        self._servo_event(output, pwm, now_s)
        if self.output_us[output] == pwm:
            # A command re-sends the pulse even when it is unchanged (the servo's own timing).
            self.servos[output].command(pwm, now_s)
            self._moving = True

    def _cmd_do_set_actuator(self, command: Command, now_s: float) -> int:
        """PX4 (Commander.cpp, actuator set 1–6): ACCEPTED whatever it does — no output mapped,
        disarmed, param7 not 0, values out of range. Param7 0 stores params 1–6 in the
        actuator set (a NaN leaves its slot as it was); outputs on functions 301–306 show their
        slot once live (see :meth:`_px4_output_us`)."""
        if command.params[6] != 0:
            return mavlink.MAV_RESULT_ACCEPTED  # no other set drives functions 301–306
        mapped = {
            output: slot
            for output in range(1, OUTPUT_COUNT + 1)
            if 0
            <= (slot := self._function(output) - PX4_ACTUATOR_SET_FIRST_FUNCTION)
            < PX4_ACTUATOR_SET_COUNT
        }
        for output in mapped:
            if output in self.config.faults.nack_outputs:
                self.emit(now_s, "fault", fault="nack_output", output=output)
                return mavlink.MAV_RESULT_FAILED
        for slot in range(PX4_ACTUATOR_SET_COUNT):
            if not math.isnan(command.params[slot]):
                self.actuator_values[slot] = command.params[slot]
        self._refresh_outputs(now_s, "command")
        for output, slot in mapped.items():
            value = self.actuator_values[slot]
            if math.isnan(value):
                continue
            low, high = self._pwm_limits(output)
            pwm = min(max(px4_actuator_pwm_us(value), low), high)
            self._servo_event(output, pwm, now_s, value=value, live=self._live(output))
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_arm_disarm(self, command: Command, now_s: float) -> int:
        """PX4 MAV_CMD_COMPONENT_ARM_DISARM: param1 1 arms, 0 disarms (a force, param2 21196,
        disarms at once whatever the state: a kill); anything else DENIED. The outputs go to
        the disarmed PWM on a disarm, to the stored values on an arm (one step)."""
        action = command.params[0]
        if not math.isfinite(action) or round(action) not in (0, 1):
            return mavlink.MAV_RESULT_DENIED
        forced = command.params[1] == PX4_FORCE_MAGIC
        cause = "command" if round(action) == 1 or not forced else "kill"
        self.set_armed(round(action) == 1, now_s, cause=cause)
        return mavlink.MAV_RESULT_ACCEPTED

    def _servo_event(self, output: int, pwm: int, now_s: float, **extra: Any) -> None:
        """A command gave ``output`` the PWM ``pwm`` (what it shows once live)."""
        servo = self.servos[output]
        self.emit(
            now_s,
            "servo",
            output=output,
            pwm_us=pwm,
            position_us=round(servo.position_us(now_s), 3),
            target_us=round(servo.target_us, 3),
            arrival_t_s=self._t(servo.arrival_s()),
            **{
                k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in extra.items()
            },
        )

    def _check_settled(self, now_s: float) -> None:
        if not self._moving or any(servo.moving(now_s) for servo in self.servos.values()):
            return
        self._moving = False
        arrival = max(servo.arrival_s() for servo in self.servos.values())
        self.emit(
            arrival,
            "settled",
            positions_us=self._positions(now_s),
            hand=self.hand.state(self._positions(now_s)).as_dict() if self.hand else None,
        )

    def _positions(self, now_s: float) -> dict[int, float]:
        return {o: round(s.position_us(now_s), 3) for o, s in self.servos.items()}

    # -- the vehicle and the hand in the world ---------------------------------------------

    def hand_world(self, now_s: float, vehicle: VehicleState | None = None) -> WorldPose | None:
        """The hand in LOCAL_NED at ``now_s``: the vehicle's pose then (``vehicle``, if already
        computed), the mount, and the hand the servos' horns give (None without a hand model or
        while a horn is outside its joint's PWM range)."""
        if self.hand is None:
            return None
        key = tuple(round(self.servos[o].position_us(now_s), 3) for o in self.hand.outputs)
        if key != self._hand_key:
            pose = self.hand.state(dict(zip(self.hand.outputs, key, strict=True))).pose
            self._hand_key = key
            self._hand_base = None if pose is None else pose_matrix(*pose.as_tuple())
        if self._hand_base is None:
            return None
        if vehicle is None:
            vehicle = self.vehicle.state(now_s - self._start_s)
        return hand_in_world(vehicle, self._mount, self._hand_base)

    def world_sample(self, now_s: float) -> dict[str, Any]:
        """The vehicle's state and the hand in the world at ``now_s``, JSON-ready (the
        ``vehicle`` event's fields)."""
        vehicle = self.vehicle.state(now_s - self._start_s)
        hand = self.hand_world(now_s, vehicle)
        return {
            "vehicle": vehicle.as_dict(),
            "hand_ned": hand.as_dict() if hand is not None else None,
        }

    def _run_vehicle_log(self, now_s: float) -> None:
        """The ``vehicle`` events due by ``now_s``, each stamped and computed at its own due
        time. They are written late, in batches (on any pass, at most VEHICLE_LOG_LAG_S after
        they were due), and always before a servo is given a new course (every command and
        output change calls this first), so the horn positions of a past sample are exact: a
        servo's motion between two commands is known at any time. More than VEHICLE_LOG_MAX_S
        behind (a stalled process) the cadence restarts from now."""
        due = self._vehicle_due_s
        if due is None or now_s < due:
            return
        if now_s - due > VEHICLE_LOG_MAX_S:
            self._vehicle_origin_s, self._vehicle_n, due = now_s, 0, now_s
        while due <= now_s:
            self.emit(due, "vehicle", **self.world_sample(due))
            self._vehicle_n += 1
            due = self._vehicle_origin_s + self._vehicle_n * self._vehicle_log_s
        self._vehicle_due_s = due

    def _cmd_set_message_interval(self, command: Command, now_s: float) -> int:
        msg_id_f, interval_f = command.params[0], command.params[1]
        if not (math.isfinite(msg_id_f) and math.isfinite(interval_f)):
            return mavlink.MAV_RESULT_FAILED
        msg_id, interval_us = int(msg_id_f), int(interval_f)
        if msg_id not in self._stream_msgs:
            return mavlink.MAV_RESULT_FAILED
        if interval_us == 0:
            interval_ms = self._default_interval_ms(msg_id)
        elif interval_us == -1:
            interval_ms = 0
        elif interval_us < 1000:
            interval_ms = 1  # "don't squash sub-ms times to zero"
        elif interval_us > MAX_INTERVAL_MS * 1000:
            interval_ms = MAX_INTERVAL_MS
        else:
            interval_ms = interval_us // 1000
        # GCS_Common.cpp cap_message_interval: at most 80 % of the main-loop rate (3 ms at 400 Hz).
        loop_period_us = 1e6 / self.config.loop_rate_hz
        if 0 < interval_ms and interval_ms * 800 < loop_period_us:
            interval_ms = int(loop_period_us / 800)
        self._interval_ms[msg_id] = interval_ms
        self._next_due_s[msg_id] = now_s if interval_ms > 0 else None
        self.emit(now_s, "stream", msg=_message_name(msg_id), interval_ms=interval_ms)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, command: Command, now_s: float) -> int:
        msg_id = int(command.params[0]) if math.isfinite(command.params[0]) else -1
        if msg_id in self._interval_ms:
            # The stored interval, as GCS_Common.cpp get_ap_message_interval reads it back, not
            # the rate achieved: SERVO_OUTPUT_RAW asked for at 400 Hz reports 3000 µs (the
            # 0.8 x loop-rate cap) while it streams at 50 Hz.
            interval_ms = self._interval_ms[msg_id]
            interval_us = interval_ms * 1000 if interval_ms > 0 else -1
        else:
            interval_us = 0  # not available
        self._defer(self._enc.message_interval_encode(max(0, msg_id) & 0xFFFF, interval_us), now_s)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, command: Command, now_s: float) -> int:
        msg_id = int(command.params[0]) if math.isfinite(command.params[0]) else -1
        if msg_id not in self._stream_msgs:
            return mavlink.MAV_RESULT_FAILED
        self._defer(self._stream_message(msg_id, now_s), now_s)
        return mavlink.MAV_RESULT_ACCEPTED

    # -- parameters over MAVLink -----------------------------------------------------------

    def _param_value(self, param: Param, index: int) -> mavlink.MAVLink_message:
        # param_index is a uint16_t on the wire: ArduPilot's -1 arrives as 65535.
        return self._enc.param_value_encode(
            param.name.encode(),
            self._encode_param_value(param),
            param.param_type,
            len(self.params),
            index & 0xFFFF,
        )

    def _on_param_set(self, msg: Any, now_s: float) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        name = _param_id(msg.param_id)
        param = self.params.get(name)
        if param is None:
            self.emit(now_s, "param_unknown", name=name)
            return
        value = self._decode_param_value(param, msg.param_value)
        if value is None:
            return
        old = param.value
        param.value = value
        self.emit(now_s, "param_set", name=name, old=old, value=value)
        # Applied at once (PX4: functions, limits, prearm mode; here also BRD_SAFETY_MASK).
        self._run_prearm(now_s)
        self._refresh_outputs(now_s, "param")
        index = -1 if self.config.flavour == "ardupilot" else self._param_names.index(name)
        self._defer(self._param_value(param, index), now_s)

    def _on_param_request_read(self, msg: Any, now_s: float) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        if msg.param_index == -1:
            name = _param_id(msg.param_id)
            index = -1
        elif 0 <= msg.param_index < len(self._param_names):
            name = self._param_names[msg.param_index]
            index = msg.param_index
        else:
            return
        param = self.params.get(name)
        if param is None:
            self.emit(now_s, "param_unknown", name=name)
            return
        self._defer(self._param_value(param, index), now_s)

    def _on_param_request_list(self, msg: Any, now_s: float) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        for index, name in enumerate(self._param_names):
            self._defer(self._param_value(self.params[name], index), now_s)

    # -- state for the query socket --------------------------------------------------------

    # -- the Lua bridge script (lua_script) ------------------------------------------------

    def _lua_setup(self, now_s: float) -> None:
        if self.config.flavour != "ardupilot":
            raise ValueError("lua_script needs flavour='ardupilot'")
        self._lua = LuaScriptTiming(now_s)
        for output in self.config.arm.outputs:
            self.params[f"SERVO{output}_MIN"].value = self.config.arm.pwm_min_us
            self.params[f"SERVO{output}_MAX"].value = self.config.arm.pwm_max_us

    def _lua_param(self, name: str) -> float | None:
        param = self.params.get(name)
        return None if param is None else float(param.value)

    def _run_lua(self, now_s: float) -> None:
        if not self._lua_pending:
            return
        due = [command for at, command in self._lua_pending if at <= now_s]
        self._lua_pending = [entry for entry in self._lua_pending if entry[0] > now_s]
        for command in due:
            verdict = check_user2(command.params, self._lua_param)
            if verdict.accepted:
                for output, pwm in verdict.settings.items():
                    self._apply(output, pwm, now_s)
                result = mavlink.MAV_RESULT_ACCEPTED
            else:
                # The script sends its text at once (gcs:send_text), before its ACK.
                self._statustext(mavlink.MAV_SEVERITY_WARNING, refusal_text(verdict), now_s)
                result = mavlink.MAV_RESULT_FAILED
            withheld = self.config.faults.withhold_all_acks or (
                command.command in self.config.faults.withhold_ack_commands
            )
            self.emit(
                now_s,
                "ack",
                command=command.command,
                command_name="MAV_CMD_USER_2 (lua)",
                result=result,
                result_name=_result_name(result),
                withheld=withheld,
                refused_output=verdict.refused_output,
            )
            if withheld:
                self.stats["acks_withheld"] += 1
                continue
            self.stats["acks"] += 1
            ack = self._enc.command_ack_encode(
                command.command, result, 0, verdict.refused_output, *command.source
            )
            self._send(ack, now_s, command.channel)

    def snapshot(self, now_s: float) -> dict[str, Any]:
        """Everything a test may assert on, as JSON-ready data."""
        positions = self._positions(now_s)
        outputs = {
            str(o): {
                "function": self._function(o),
                "pwm_us": self.output_us[o],
                "reported_us": self.pwm_us[o],
                "live": self._live(o),
                "position_us": positions[o],
                "target_us": round(s.target_us, 3),
                "moving": s.moving(now_s),
            }
            for o, s in self.servos.items()
        }
        return {
            "t_s": self._t(now_s),
            "flavour": self.config.flavour,
            "system_id": self.config.system_id,
            "peer": list(self.peer) if self.peer else None,
            "routes": [list(route) for route in sorted(self.routes)],
            "rebooting": self.rebooting,
            "armed": self.armed,
            "prearmed": self.prearmed,
            "safety_on": self.safety_on,
            "outputs_live": self.outputs_live and not self.rebooting,
            "actuator_values": [None if math.isnan(v) else v for v in self.actuator_values],
            "time_boot_ms": self._time_boot_us(now_s) // 1000,
            "outputs": outputs,
            "settled": not any(s.moving(now_s) for s in self.servos.values()),
            "hand": self.hand.state(positions).as_dict() if self.hand else None,
            **self.world_sample(now_s),
            "streams": {_message_name(m): self._interval_ms[m] for m in self._stream_msgs},
            "stats": dict(self.stats),
        }


def px4_actuator_pwm_us(value: float) -> int:
    """PX4's PWM for an actuator value: 1500 + 500·v rounded half away from zero (measured on
    SITL, whose outputs span 1000–2000); the caller clamps it to the output's min/max."""
    exact = 1500.0 + 500.0 * min(max(value, -1e6), 1e6)
    return int(math.copysign(math.floor(abs(exact) + 0.5), exact))


def _param_id(raw: Any) -> str:
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes | bytearray) else str(raw)
    return text.split("\x00", 1)[0]


def _fields(msg: mavlink.MAVLink_message) -> dict[str, Any]:
    fields = {}
    for name in msg.get_fieldnames():
        value = getattr(msg, name)
        if isinstance(value, bytes | bytearray):
            value = value.decode("ascii", "replace").split("\x00", 1)[0]
        elif isinstance(value, float) and not math.isfinite(value):
            value = str(value)  # JSON has no NaN / inf
        elif isinstance(value, list):
            value = [str(v) if isinstance(v, float) and not math.isfinite(v) else v for v in value]
        fields[name] = value
    return fields


def _command_name(command: int) -> str:
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else str(command)


def _result_name(result: int) -> str:
    return mavlink.enums["MAV_RESULT"][result].name


def _message_name(msg_id: int) -> str:
    return mavlink.mavlink_map[msg_id].msgname
