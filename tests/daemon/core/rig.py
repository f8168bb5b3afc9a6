"""The rig the core's tests drive: a core with a fake clock, the autopilot's codec, and what
came out.

A fake solver makes a target's six numbers the joint angles it "solves" to (a first number
above 1000 is unreachable), so each test says exactly which joints it asks for. Frames are real
pymavlink frames, encoded by a codec standing in for the autopilot and decoded again. Also: a
model of PX4's outputs, a keep-out rig and the world-frame helpers."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.core import (
    Answer,
    ControlCore,
    ReadParam,
    SendCommand,
    stream_intervals_s,
)
from companion.daemon.requests import Request
from devkit.timing import FakeClock

PARK = (0.0, 90.0, 0.0, 0.0, 0.0, 0.0)


SPEED_DEG_S, RATE_HZ = 60.0, 20.0


STEP_DEG = SPEED_DEG_S / RATE_HZ  # 3 degrees a tick


SERVO = mavlink.MAV_CMD_DO_SET_SERVO


ACCEPTED, FAILED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED


def fake_solve(pose, q_start_deg, mode="pose", budget_ms=None, *, seed=None):
    q = pose.as_tuple()
    return SimpleNamespace(
        q_deg=tuple(q),
        q_rad=np.radians(q),
        converged=q[0] < 1000,
        pos_err_cm=0.0 if q[0] < 1000 else 99.0,
        ori_err_deg=0.0,
        cost=0.0 if q[0] < 1000 else 99.0**2,
        elapsed_ms=0.1,
    )


class Rig:
    """A core, the autopilot's codec, and what came out.

    ArduPilot: once the test says where the safety switch is (:meth:`sys_status`), the rig
    streams SYS_STATUS saying so at the interval the core asked for, as ArduPilot does, until
    the link goes down or the core asks for the stream again (a reboot or a silence: the test
    says when the autopilot answers). From :meth:`up` it streams the readback too, showing
    what the core has acknowledged (ArduPilot shows what it was told), until the link goes
    down, the core asks for it again or the test sends a readback of its own."""

    def __init__(
        self, dialect: str = "ardupilot", sections: dict | None = None, **link: object
    ) -> None:
        self.clock = FakeClock()
        config = parse_config(
            {
                "link": {"url": "udpout:127.0.0.1:14550", "dialect": dialect, **link},
                "arm": {"park_deg": list(PARK), "joint_speed_deg_s": SPEED_DEG_S},
                "control": {"rate_hz": RATE_HZ},
                **(sections or {}),
            }
        )
        self.config = config
        self.calibration = config.calibration
        self.core = ControlCore(config, solve=fake_solve, clock=self.clock)
        self.sent: list[SendCommand] = []
        self.reads: list[ReadParam] = []
        self.answers: dict[int, list] = {}
        self.requests: list[Request] = []
        self.codecs: dict[tuple[int, int], mavlink.MAVLink] = {}
        self.decoder = mavlink.MAVLink(None)
        #: The safety switch the rig's SYS_STATUS stream says (None: not streaming).
        self.safety_stream: bool | None = None
        self._status_due_s = math.inf
        intervals_s = stream_intervals_s(ardupilot=True, url=config.link.url)
        self.readback_interval_s, self.status_interval_s = intervals_s
        #: Whether the rig streams the readback (ArduPilot, see the class docstring).
        self.readback_stream = False
        self._readback_due_s = math.inf
        #: The autopilot's clock by the last SYSTEM_TIME it sent: time_boot_ms, and when.
        self._boot = (600_000, self.clock())

    # -- driving ----------------------------------------------------------------------------

    def take(self, actions) -> list[SendCommand]:
        new = []
        for action in actions:
            if isinstance(action, Answer):
                self.answers.setdefault(id(action.request), []).append(action.reply)
                action.request.answer(action.reply)
            elif isinstance(action, ReadParam):
                self.reads.append(action)
            else:
                new.append(action)
                if action.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                    # Asked again: the test says when it answers.
                    if action.params[0] == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
                        self.safety_stream = None
                    elif action.params[0] == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
                        self.readback_stream = False
        self.sent += new
        return new

    def frame(self, build, src=(1, 1), received_s=None):
        """A frame from ``src``, taken now; ``received_s``: when it arrived (default: now)."""
        codec = self.codecs.setdefault(src, mavlink.MAVLink(None, *src))
        buf = build(codec).pack(codec)
        msg = self.decoder.parse_buffer(buf)[0]
        return self.take(self.core.frame(msg, received_s))

    def heartbeat(self, src=(1, 1), autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA):
        return self.frame(
            lambda c: c.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, autopilot, 0, 0, 3), src
        )

    def ack(self, result=ACCEPTED, command=SERVO, src=(1, 1)):
        return self.frame(lambda c: c.command_ack_encode(command, result, 0, 0, 1, 191), src)

    def statustext(self, text, src=(1, 1)):
        return self.frame(lambda c: c.statustext_encode(6, text.encode()), src)

    def system_time(self, boot_ms, src=(1, 1), received_s=None):
        if src == (1, 1):
            self._boot = (boot_ms, self.clock())
        return self.frame(lambda c: c.system_time_encode(0, boot_ms), src, received_s)

    def answer_clock_probes(self) -> None:
        """Answer every SYSTEM_TIME the core asked for since the last call (its probe: a
        readback started to disagree, or shows where an output is), the autopilot's clock
        going on from the last SYSTEM_TIME it sent."""
        probes = [
            c
            for c in self.sent
            if c.command == mavlink.MAV_CMD_REQUEST_MESSAGE
            and c.params[0] == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME
        ]
        for c in probes:
            self.sent.remove(c)
            self.clock_goes_on()

    def clock_goes_on(self) -> None:
        """A SYSTEM_TIME from the autopilot, its clock going on from the last one it sent."""
        boot_ms, at_s = self._boot
        self.system_time(boot_ms + round((self.clock() - at_s) * 1000))

    def readback(self, pwm_by_output, src=(1, 1), *, stream=False):
        """A SERVO_OUTPUT_RAW showing ``pwm_by_output`` (others 0); from the autopilot, it ends
        the rig's readback stream unless ``stream`` (the rig's own)."""
        if src == (1, 1) and not stream:
            self.readback_stream = False
        values = [int(pwm_by_output.get(n, 0)) for n in range(1, 17)]
        return self.frame(lambda c: c.servo_output_raw_encode(0, 0, *values), src)

    def sys_status(self, safety_on, src=(1, 1), *, stream=True):
        """A SYS_STATUS; from the autopilot (``stream``), it goes on streaming that."""
        outputs = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        enabled = 0 if safety_on else outputs
        if stream and src == (1, 1):
            self.safety_stream = safety_on
            self._status_due_s = self.clock() + self.status_interval_s
        return self.frame(
            lambda c: c.sys_status_encode(outputs, enabled, outputs, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
            src,
        )

    def tick(self, link_up=True):
        if not link_up:
            self.safety_stream = None
            self.readback_stream = False
        else:
            if self.safety_stream is not None and self.clock() >= self._status_due_s:
                self.sys_status(self.safety_stream)
            if self.readback_stream and self.clock() >= self._readback_due_s:
                self._readback_due_s = self.clock() + self.readback_interval_s
                self.readback(dict(self.core.state.acked_pwm), stream=True)
        return self.take(self.core.tick(link_up))

    def advance(self, seconds, link_up=True):
        self.clock.advance(seconds)
        return self.tick(link_up)

    def up(self):
        self.heartbeat()
        sent = self.tick()
        if self.config.link.dialect.startswith("ardupilot"):
            # ArduPilot moves once a readback said where the joints are (no pulses on the
            # arm's outputs since its boot: nothing) and it knows the switch is off.
            self.readback({})
            self.readback_stream = True
            self._readback_due_s = self.clock() + self.readback_interval_s
            self.switch_off()
        return sent

    def switch_off(self):
        """ArduPilot's SYS_STATUS stream says the safety switch is off, long enough to be
        believed while it is unknown (1.5 intervals, none saying on): two frames, the second
        stamped 1.5 intervals after the first (the stream's next frames, stamped 1 and 2
        intervals after it, are then no closer to it than half an interval: its cadence
        holds). The clock stays where it is (the tests' timing is unchanged)."""
        self.sys_status(safety_on=False)
        later_s = self.clock() + 1.5 * self.status_interval_s + 1e-6
        outputs = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        return self.frame(
            lambda c: c.sys_status_encode(outputs, outputs, outputs, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
            received_s=later_s,
        )

    def request(self, kind, payload=None, **kw) -> Request:
        request = Request(kind, payload, received_s=self.clock(), **kw)
        self.requests.append(request)  # alive: answers are keyed by id()
        self.take(self.core.request(request))
        return request

    def goto(self, q_deg) -> Request:
        return self.request("goto", tuple(q_deg))

    def reply(self, request):
        [reply] = self.answers.get(id(request), [None]) or [None]
        return reply

    # -- reading ----------------------------------------------------------------------------

    def servo(self, commands=None) -> dict[int, int]:
        """{output: pwm_us} of the DO_SET_SERVO commands given (default: all sent)."""
        commands = self.sent if commands is None else commands
        return {int(c.params[0]): int(c.params[1]) for c in commands if c.command == SERVO}

    def angle(self, output, pwm):
        return self.calibration.for_output(output).pwm_us_to_angle_deg(pwm)

    def ack_all(self, commands, result=ACCEPTED):
        out = []
        for c in list(commands):
            if c.command == SERVO:
                out += self.ack(result)
        return out


def near(q_deg, delta_deg=STEP_DEG / 2):
    """Joints each within one step of the park pose: a target reached in one update."""
    return tuple(p + delta_deg for p in PARK)


ACTUATOR = mavlink.MAV_CMD_DO_SET_ACTUATOR


class Px4OutputsModel:
    """PX4's outputs as measured on SITL, for these tests: DO_SET_ACTUATOR stores values (NaN:
    unchanged) and is always ACCEPTED; the outputs show the disarmed PWM until live, then the
    stored values at once; SERVO_OUTPUT_RAW reads back what they show."""

    def __init__(self, rig: Rig, disarmed_us: int) -> None:
        self.rig = rig
        self.disarmed_us = disarmed_us
        self.live = False
        self.stored: dict[int, int | None] = dict.fromkeys(rig.calibration.outputs)
        self.physical_moves: list[tuple[int, int, int]] = []  # (output, from, to)
        self.shown = self._shown()

    def _shown(self) -> dict[int, int]:
        return {
            o: (v if self.live and v is not None else self.disarmed_us)
            for o, v in self.stored.items()
        }

    def _refresh(self, record: bool = True) -> None:
        shown = self._shown()
        for o, pwm in shown.items():
            if pwm != self.shown[o] and record:
                self.physical_moves.append((o, self.shown[o], pwm))
        self.shown = shown

    def handle(self) -> None:
        """Apply and acknowledge every DO_SET_ACTUATOR sent so far, one after the other."""
        for _ in self.apply(one=True):
            self.rig.ack(command=ACTUATOR)

    def apply(self, one: bool = False) -> list[SendCommand]:
        """Apply every DO_SET_ACTUATOR sent so far, its ACK not sent yet (PX4 answers on its
        commander's cycle, after the output cycle may have applied it); ``one``: each command's
        outputs change apart (as many physical moves as commands)."""
        self.rig.answer_clock_probes()
        commands = [c for c in self.rig.sent if c.command == ACTUATOR]
        self.rig.sent.clear()
        for c in commands:
            for slot, output in enumerate(self.rig.calibration.outputs):
                value = c.params[slot]
                if not math.isnan(value):
                    joint = self.rig.calibration.for_output(output)
                    span = joint.pwm_max_us - joint.pwm_min_us
                    self.stored[output] = round(joint.pwm_min_us + (value + 1) / 2 * span)
            if one:
                self._refresh()
        self._refresh()
        return commands

    def foreign_store(self, output: int, pwm_us: int) -> None:
        """Another sender's DO_SET_ACTUATOR stores ``pwm_us`` on ``output`` (shown at once if
        live; its move is not ours, so not recorded)."""
        self.stored[output] = pwm_us
        self._refresh(record=False)

    def set_live(self, live: bool) -> None:
        """Arm or prearm (live), disarm or kill (not). Disarming drives every output to the
        disarmed PWM at once: PX4's doing, not ours, so not recorded as a move."""
        self.live = live
        self._refresh(record=live)

    def readback(self) -> None:
        """A SERVO_OUTPUT_RAW of what the outputs show, and a SYSTEM_TIME after it (PX4
        streams both; its clock going on is what a readback's belief waits for)."""
        self.rig.readback(self.shown)
        self.rig.clock_goes_on()


def px4_rig(disarmed_us: int = 1500) -> tuple[Rig, Px4OutputsModel]:
    rig = Rig(dialect="px4")
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    rig.sent.clear()
    return rig, Px4OutputsModel(rig, disarmed_us)


def run(rig: Rig, px4: Px4OutputsModel, seconds: float, step_s: float = 0.05) -> None:
    """Time passes: ticks, PX4 handles what was sent, readbacks every 0.1 s."""
    for _ in range(round(seconds / step_s)):
        rig.advance(step_s)
        px4.handle()
        if round(rig.clock() / step_s) % 2 == 0:
            px4.readback()


def max_physical_step_us(px4: Px4OutputsModel) -> float:
    """The largest physical move over one step's PWM (≤ 1: within the speed limit)."""
    worst = 0.0
    for output, before, after in px4.physical_moves:
        joint = px4.rig.calibration.for_output(output)
        step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
        worst = max(worst, abs(after - before) / (step_us + 1))
    return worst


def assert_seen_live_at_the_next_readback(rig: Rig, px4: Px4OutputsModel) -> None:
    """Armed with the markers stored: the first readback says live, and nothing jumped."""
    px4.set_live(True)
    px4.readback()
    assert rig.core.status()["outputs_live"] is True
    assert max_physical_step_us(px4) <= 1.0


def rig_park_pwm() -> int:
    """One PWM inside every joint's calibration (the default 1000-2000 us)."""
    return 1500


def keepout_rig(q_in_the_way) -> Rig:
    """A rig whose config has a 4 cm sphere around the hand of ``q_in_the_way`` (body frame)."""
    from companion.kinematics.vehicle import Mount

    arm = Rig().config.arm
    centre = Mount().to_body(arm.fk(q_in_the_way).position_cm)
    sphere = {"name": "ball", "type": "sphere", "center_cm": list(centre), "radius_cm": 4.0}
    rig = Rig(sections={"keepout": [sphere]})
    rig.up()
    return rig


MOUNT_Z_CM = 10.0  # the default mount: the base 10 cm below the body origin, axes aligned


LEAD_MS = 20.0


def world_rig(**world) -> Rig:
    rig = Rig(sections={"world": {"enabled": True, "lead_ms": LEAD_MS, **world}})
    rig.up()
    return rig


def telemetry(rig, north_cm=0.0, vn_cm_s=0.0, yaw_rad=0.0, boot_ms=None):
    boot_ms = int(rig.clock() * 1000) if boot_ms is None else boot_ms
    rig.frame(lambda c: c.attitude_encode(boot_ms, 0.0, 0.0, yaw_rad, 0.0, 0.0, 0.0))
    rig.frame(
        lambda c: c.local_position_ned_encode(
            boot_ms, north_cm / 100, 0.0, 0.0, vn_cm_s / 100, 0.0, 0.0
        )
    )


def world_goto(rig, base_q):
    """A LOCAL_NED target that is ``base_q`` in the base frame with the vehicle at the origin."""
    x, y, z, roll, pitch, yaw = base_q
    pose = (x, y, z + MOUNT_Z_CM, roll, pitch, yaw)
    return rig.request("goto", {"pose": pose, "frame": "local_ned"})
