"""The simulated autopilot: bytes in, frames out, given the time.

:class:`SimAutopilot` does no I/O and reads no clock: :meth:`~SimAutopilot.receive` takes the
bytes that arrived and the time, :meth:`~SimAutopilot.poll` returns the frames due by a time,
:meth:`~SimAutopilot.next_event_s` says when to call ``poll`` next. A test drives it with plain
numbers; the server (:mod:`sim_servo.server`) drives it with ``time.monotonic``.

It composes the parts, each the one home of a behaviour: :mod:`~sim_servo.autopilot.wire`
(decoding, encoding, signing, each link's timing), :mod:`~sim_servo.autopilot.routing`,
:mod:`~sim_servo.autopilot.params`, :mod:`~sim_servo.autopilot.outputs`,
:mod:`~sim_servo.autopilot.streams`, :mod:`~sim_servo.autopilot.commands`,
:mod:`~sim_servo.autopilot.lua`, :mod:`~sim_servo.autopilot.reboot`,
:mod:`~sim_servo.autopilot.world` and a test fault, :mod:`~sim_servo.autopilot.forge`; what
differs between ArduPilot and PX4 is in :mod:`~sim_servo.autopilot.flavour`.

When frames are handled and leave:

* ArduPilot handles received frames on the next main-loop pass (``loop_rate_hz``, 400 Hz as
  ArduCopter), like ``GCS::update_receive`` running once per loop. Each link's output goes
  through :class:`~sim_servo.linktiming.LinkOutput`, a delay-and-hold model fitted to ArduCopter
  4.7.0-dev SITL over TCP loopback with a pymavlink client (one DO_SET_SERVO round trip 5.7 ms
  median, range 5.3–6.1; six in sequence 32.2 ms; six back-to-back 3.2 ms median, 6.0 max, so a
  burst beats a lone command). Frames leave ``output_delay_ms`` (1.0) after they were produced
  at the earliest, then are held until the link sends a frame, or ``hold_ms`` (4.8) after the
  first frame the link sent since it was last quiet, or at once when two frames came within
  that window. See :class:`~sim_servo.config.LinkTimingConfig` (defaults, fit, limits);
  ``instant()`` turns it off. Applied to every transport; serial links were not measured.
* PX4 (:class:`~sim_servo.config.Px4TimingConfig`): frames handled on arrival, commander
  commands acted on and answered on the next 10 ms cycle, frames out on each link's 1.5 ms
  main-loop pass (:class:`~sim_servo.linktiming.LoopLinkOutput`), routed frames 2.5 ms later.
* One pass of :meth:`SimAutopilot.poll`: the vehicle log, the reboot, the forger's frame (a
  forger goes on through a reboot), then (unless rebooting)
  prearm, the received frames, the Lua script, the commander, the deferred frames, the
  heartbeat and the other streams, in this order.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.commands import Commands
from sim_servo.autopilot.flavour import flavour_for
from sim_servo.autopilot.forge import Forger, Forgery
from sim_servo.autopilot.lua import LuaScript
from sim_servo.autopilot.messages import message_fields, message_name
from sim_servo.autopilot.outputs import Outputs, make_servos
from sim_servo.autopilot.params import ParamService, ParamTable
from sim_servo.autopilot.reboot import Reboot
from sim_servo.autopilot.state import AutopilotState, Emit
from sim_servo.autopilot.streams import Streams
from sim_servo.autopilot.wire import Wire
from sim_servo.autopilot.world import WorldLog
from sim_servo.config import SimConfig
from sim_servo.faults import FaultInjector
from sim_servo.hand import HandModel
from sim_servo.hover import HoverDisturbance, VehicleState
from sim_servo.servo import Servo
from sim_servo.world import WorldPose

#: Handles a received message: (message, time, link it came on).
MessageHandler = Callable[[Any, float, int], None]


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
        state = AutopilotState(
            config, flavour_for(config), now_s=now_s, emit=emit, wall_clock=wall_clock
        )
        self._state = state
        self._wire = Wire(state, self.faults, links=links, wall_clock=wall_clock)
        #: Received frames waiting to be handled: (due, link, message).
        self._inbox: list[tuple[float, int, mavlink.MAVLink_message]] = []
        self.params = ParamTable(state)
        servos = make_servos(state, hand, now_s)
        self._world = WorldLog(state, hand, servos, now_s=now_s)
        self._outputs = Outputs(
            state,
            self.params,
            servos,
            self._wire,
            hand=hand,
            before_course_change=self._world.run,
            now_s=now_s,
        )
        self._router = state.flavour.make_router(state, self._wire, self.params)
        self._streams = Streams(state, self._wire, self._outputs, self.vehicle, now_s=now_s)
        self._forger = Forger(state, self._wire, lambda: self._outputs.pwm_us)
        params = ParamService(state, self.params, self._wire, self._outputs.on_param_change)
        self._lua = (
            LuaScript(state, self.params, self._outputs, self._wire, now_s=now_s)
            if config.lua_script
            else None
        )
        self._commands = Commands(
            state,
            self._wire,
            {**self._streams.handlers(), **state.flavour.command_handlers(self._outputs)},
            self._lua,
        )
        halt = [self._drop_inbox, self._wire.halt, self._commands.halt]
        if self._lua is not None:
            halt.append(self._lua.halt)
        halt.append(self._outputs.halt)  # last: its events follow the queues' clearing
        self._reboot = Reboot(
            state,
            halt=halt,
            boot=[self._wire.boot, self._router.boot, self._outputs.boot, self._streams.boot],
            now_s=now_s,
        )
        self._handlers: dict[str, MessageHandler] = {
            "HEARTBEAT": self._router.on_heartbeat,
            **self._commands.message_handlers(),
            **params.handlers(),
        }

    # -- what the server, the queries and tests read -----------------------------------------

    @property
    def stats(self) -> dict[str, int]:
        return self._state.stats

    @property
    def vehicle(self) -> HoverDisturbance:
        """The vehicle's motion (pure, seeded): it goes on through a reboot of the autopilot."""
        return self._world.vehicle

    @property
    def routes(self) -> list[tuple[int, int, int]]:
        """ArduPilot's routing table: (system, component, link) in the order learned."""
        return self._router.routes

    @property
    def peer(self) -> tuple[int, int] | None:
        return self._router.peer

    @property
    def servos(self) -> dict[int, Servo]:
        return self._outputs.servos

    @property
    def pwm_us(self) -> dict[int, int]:
        """What the autopilot reports (SERVO_OUTPUT_RAW, ACTUATOR_OUTPUT_STATUS) per output."""
        return self._outputs.pwm_us

    @property
    def output_us(self) -> dict[int, int]:
        """What each servo physically receives (0: no pulses)."""
        return self._outputs.output_us

    @property
    def armed(self) -> bool:
        return self._outputs.armed

    @property
    def prearmed(self) -> bool:
        return self._outputs.prearmed

    @property
    def safety_on(self) -> bool:
        return self._outputs.safety_on

    @property
    def actuator_values(self) -> list[float]:
        return self._outputs.actuator_values

    @property
    def outputs_live(self) -> bool:
        """PX4: armed or prearmed; ArduPilot: the safety switch off (per output: the mask)."""
        return self._outputs.outputs_live

    @property
    def rebooting(self) -> bool:
        return self._state.rebooting

    def emit(self, now_s: float, event: str, **fields: Any) -> None:
        self._state.emit(now_s, event, **fields)

    def set_links(self, count: int) -> None:
        """Serve ``count`` links (channels 0 … count−1): our own frames go out on each."""
        self._wire.set_links(count)

    # -- what the queries do -----------------------------------------------------------------

    def reboot(self, now_s: float, gap_s: float | None = None) -> bool:
        """Reboot now (see :mod:`sim_servo.autopilot.reboot`); False while rebooting."""
        return self._reboot.reboot(now_s, gap_s)

    def set_armed(self, armed: bool, now_s: float, cause: str = "query") -> bool:
        """PX4: arm or disarm now; False (nothing done) on ArduPilot or while rebooting."""
        return self._outputs.set_armed(armed, now_s, cause)

    def set_safety(self, on: bool, now_s: float, cause: str = "query") -> bool:
        """ArduPilot: the safety switch on or off now; False on PX4 or while rebooting."""
        return self._outputs.set_safety(on, now_s, cause)

    def forge(self, request: dict[str, Any], now_s: float) -> Forgery:
        """A test fault: frames forged as if from us on the companion's link, from now (see
        :mod:`sim_servo.autopilot.forge`); ``ValueError`` for a request it cannot carry out."""
        return self._forger.start(request, now_s)

    def pause_heartbeat(self, paused: bool, now_s: float) -> None:
        """Stop or restart our HEARTBEAT now (see :meth:`Streams.pause_heartbeat`)."""
        self._streams.pause_heartbeat(paused, now_s)

    def hand_world(self, now_s: float, vehicle: VehicleState | None = None) -> WorldPose | None:
        """The hand in LOCAL_NED at ``now_s`` (see :meth:`WorldLog.hand_world`)."""
        return self._world.hand_world(now_s, vehicle)

    def world_sample(self, now_s: float) -> dict[str, Any]:
        """The vehicle's state and the hand in the world at ``now_s``, JSON-ready."""
        return self._world.sample(now_s)

    # -- bytes in, frames out ----------------------------------------------------------------

    def receive(self, data: bytes, now_s: float, channel: int = 0) -> None:
        """Feed bytes that arrived at ``now_s`` on link ``channel`` (0: the companion's link;
        others: e.g. a ground station's), a datagram or a chunk of a serial stream."""
        self._reboot.run(now_s)
        state = self._state
        if state.rebooting:
            state.stats["ignored_rebooting"] += 1
            return
        corrupted = self.faults.corrupt_in(data)
        if corrupted != data:
            state.stats["corrupted_in"] += 1
            state.emit(now_s, "fault", fault="corrupt_in", bytes=len(data))
        messages = self._wire.decode(corrupted, now_s, channel)
        due = state.flavour.rx_due_s(state, now_s)
        self._inbox.extend((due, channel, msg) for msg in messages)

    def poll(self, now_s: float) -> list[tuple[int, bytes]]:
        """Run the periodic work due by ``now_s``; the frames to write now, as ``(link,
        frame)``: our own (on every link, or the one a reply is for) and those routed from one
        link to another (as received: a signed frame keeps its signature)."""
        # First: the sample's horn positions are those before this pass's commands.
        self._world.run(now_s)
        self._reboot.run(now_s)
        self._forger.run(now_s)
        if not self._state.rebooting:
            self._outputs.run_prearm(now_s)
            self._outputs.run_mask(now_s)
            self._run_inbox(now_s)
            if self._lua is not None:
                self._lua.run(now_s)
            self._commands.run_commander(now_s)
            self._wire.run_deferred(now_s)
            self._streams.run_heartbeat(now_s)
            self._streams.run(now_s)
        frames = self._wire.take(now_s)
        # The settled event's hand pose costs a forward kinematics: not while frames wait to be
        # written (next_event_s() asks for another call at once; the event keeps its time).
        if not frames:
            self._outputs.check_settled(now_s)
        return frames

    def next_event_s(self, now_s: float) -> float:
        """The earliest time at which :meth:`poll` has something to do (≥ ``now_s``)."""
        candidates = self._reboot.next_events_s() + self._forger.next_events_s()
        if not self._state.rebooting:
            candidates += self._streams.next_events_s()
            candidates += self._wire.deferred_due_s()
            candidates += [due for due, _, _ in self._inbox]
            if self._lua is not None:
                candidates += self._lua.next_events_s()
            candidates += self._commands.next_events_s()
            prearm_s = self._outputs.prearm_due_s()
            if prearm_s is not None and not self._outputs.prearmed:
                candidates.append(prearm_s)
            if (mask_s := self._outputs.mask_due_s()) is not None:
                candidates.append(mask_s)
        if (vehicle_s := self._world.next_event_s()) is not None:
            candidates.append(vehicle_s)
        candidates += self._wire.links_due_s()
        if (arrival_s := self._outputs.arrival_s()) is not None:
            candidates.append(arrival_s)
        return max(now_s, min(candidates)) if candidates else now_s + 1.0

    def _drop_inbox(self, now_s: float) -> None:
        self._inbox.clear()

    def _run_inbox(self, now_s: float) -> None:
        due = [(channel, msg) for at, channel, msg in self._inbox if at <= now_s]
        self._inbox = [entry for entry in self._inbox if entry[0] > now_s]
        for channel, msg in due:
            self._dispatch(msg, now_s, channel)

    def _dispatch(self, msg: mavlink.MAVLink_message, now_s: float, channel: int) -> None:
        state = self._state
        kind = msg.get_type()
        if kind == "BAD_DATA":
            reason = str(getattr(msg, "reason", ""))
            if "signature" in reason:
                state.stats["rejected_signature"] += 1
                state.emit(now_s, "rejected", reason=reason)
            else:
                state.stats["bad_frames"] += 1
                state.emit(now_s, "bad_frame", reason=reason)
            return
        if self.faults.drop_in():
            state.stats["dropped_in"] += 1
            state.emit(now_s, "fault", fault="drop_in", msg=kind)
            return
        state.stats["rx"] += 1
        source = [msg.get_srcSystem(), msg.get_srcComponent()]
        state.emit(now_s, "rx", msg=kind, src=source, fields=message_fields(msg))
        if not self._router.route(msg, channel, now_s):
            return
        handler = self._handlers.get(kind)
        if handler is not None:
            handler(msg, now_s, channel)

    # -- state for the query socket ----------------------------------------------------------

    def snapshot(self, now_s: float) -> dict[str, Any]:
        """Everything a test may assert on, as JSON-ready data."""
        out = self._outputs
        positions = out.positions(now_s)
        outputs = {
            str(o): {
                "function": self.params.function(o),
                "pwm_us": out.output_us[o],
                "reported_us": out.pwm_us[o],
                "live": out.live(o),
                "position_us": positions[o],
                "target_us": round(s.target_us, 3),
                "moving": s.moving(now_s),
            }
            for o, s in out.servos.items()
        }
        streams = self._streams
        return {
            "t_s": self._state.t(now_s),
            "flavour": self.config.flavour,
            "system_id": self.config.system_id,
            "peer": list(self.peer) if self.peer else None,
            "routes": [list(route) for route in sorted(self.routes)],
            "rebooting": self.rebooting,
            "armed": out.armed,
            "prearmed": out.prearmed,
            "safety_on": out.safety_on,
            "outputs_live": out.outputs_live and not self.rebooting,
            "actuator_values": [None if math.isnan(v) else v for v in out.actuator_values],
            "time_boot_ms": self._state.time_boot_us(now_s) // 1000,
            "outputs": outputs,
            "settled": not any(s.moving(now_s) for s in out.servos.values()),
            "hand": self.hand.state(positions).as_dict() if self.hand else None,
            **self.world_sample(now_s),
            "streams": {message_name(m): streams.interval_ms[m] for m in streams.ids},
            "stats": dict(self.stats),
        }
