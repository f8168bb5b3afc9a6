import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import PtyEndpoint, ScriptedPeer, UdpEndpoint
from firmware_interface.calibration import calibration_from_ranges, default_calibration
from firmware_interface.commands import CommandSender
from firmware_interface.errors import (
    AngleOutOfRange,
    CommandRejected,
    ConfigurationError,
    PwmOutOfRange,
    ServoOutputUnavailable,
)
from firmware_interface.link import LinkConfig, MavlinkLink
from firmware_interface.lua_bridge import MAV_CMD_USER_2
from firmware_interface.servo import (
    ArduPilotLuaServoDialect,
    ArduPilotServoDialect,
    Px4ServoDialect,
    make_servo_dialect,
)
from firmware_interface.updates import UpdateState, UpdateTracker

IN_USE = "ServoRelayEvent: Channel 11 is already in use"


def connect(endpoint, url, autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA):
    peer = ScriptedPeer(endpoint, system_id=42)
    link = MavlinkLink.open(url, LinkConfig(heartbeat_rate_hz=20.0))
    peer.wait_for_messages("HEARTBEAT")
    peer.send_heartbeat(autopilot=autopilot)
    link.wait_for_autopilot(timeout_s=5.0)
    return peer, link, CommandSender(link, timeout_s=2.0, retries=1)


@pytest.fixture
def udp():
    endpoint = UdpEndpoint()
    peer, link, sender = connect(endpoint, f"udpout:127.0.0.1:{endpoint.port}")
    yield peer, sender
    sender.close()
    link.close()
    peer.close()


def servo_commands(peer):
    return [
        (int(c.param1), int(c.param2))
        for c in peer.messages("COMMAND_LONG")
        if c.command == mavlink.MAV_CMD_DO_SET_SERVO
    ]


def test_ardupilot_one_do_set_servo_per_joint_in_joint_order(udp):
    peer, sender = udp
    dialect = make_servo_dialect("ardupilot", sender, default_calibration())
    sent = dialect.send_angles([0, 90, 0, -90, 90, -70])
    assert sent == {9: 1500, 10: 1500, 11: 1500, 12: 1000, 13: 2000, 14: 1000}
    assert servo_commands(peer) == list(sent.items())
    assert all(c.confirmation == 0 for c in peer.messages("COMMAND_LONG"))


@pytest.mark.parametrize("after_ack", [True, False], ids=["text-after-ack", "text-before-ack"])
def test_ardupilot_failed_names_the_output_and_the_statustext(udp, after_ack):
    # Real ArduPilot sends the STATUSTEXT just after the FAILED ACK (it is queued for the main
    # loop); either order must end up in the error.
    peer, sender = udp
    peer.failed_outputs = {11: IN_USE}
    peer.statustext_after_ack = after_ack
    dialect = ArduPilotServoDialect(sender, default_calibration())
    with pytest.raises(ServoOutputUnavailable) as info:
        dialect.send_angles([0, 90, 0, 0, 0, 10])
    err = info.value
    assert (err.output, err.statustext, err.result) == (11, IN_USE, mavlink.MAV_RESULT_FAILED)
    assert "servo output 11" in str(err) and "SERVO11_FUNCTION" in str(err)
    assert isinstance(err, CommandRejected) and isinstance(err.__cause__, CommandRejected)
    assert [out for out, _ in servo_commands(peer)] == [9, 10, 11]  # stops at the failure


def test_ardupilot_skip_unchanged_sends_only_what_the_autopilot_has_not_acked(udp):
    peer, sender = udp
    dialect = ArduPilotServoDialect(sender, default_calibration())
    first = dict.fromkeys(range(9, 15), 1500)
    dialect.send_pwm(first, skip_unchanged=True)  # nothing acknowledged yet: all six
    assert servo_commands(peer) == list(first.items())
    second = {**first, 10: 1600, 12: 1400}
    dialect.send_pwm(second, skip_unchanged=True)
    assert servo_commands(peer)[6:] == [(10, 1600), (12, 1400)]
    dialect.send_pwm(second)  # the default re-sends everything (e.g. after a link loss)
    assert servo_commands(peer)[8:] == list(second.items())
    # A refused output is unknown afterwards, and so are the ones never reached: sent again.
    peer.failed_outputs = {11: IN_USE}
    third = {**second, 11: 1700, 13: 1300}
    with pytest.raises(ServoOutputUnavailable):
        dialect.send_pwm(third, skip_unchanged=True)
    peer.failed_outputs = {}
    sent_before = len(servo_commands(peer))
    dialect.send_pwm(third, skip_unchanged=True)
    assert servo_commands(peer)[sent_before:] == [(11, 1700), (13, 1300)]


def test_out_of_range_values_are_never_sent(udp):
    peer, sender = udp
    dialect = ArduPilotServoDialect(sender, default_calibration())
    with pytest.raises(PwmOutOfRange, match=r"pwm_us=2210 outside \[1000, 2000\]"):
        dialect.send_pwm({9: 1500, 10: 2210})
    with pytest.raises(AngleOutOfRange):
        dialect.send_angles({"theta1": 91})
    with pytest.raises(PwmOutOfRange):
        dialect.send_pwm({9: float("nan")})
    dialect.send_pwm({12: 1234})
    assert servo_commands(peer) == [(12, 1234)]  # nothing before it went out


def test_px4_one_do_set_actuator_with_normalised_values(udp):
    peer, sender = udp
    dialect = make_servo_dialect("px4", sender, default_calibration())
    dialect.send_angles([-90, 180, 0, 45, -45, -70])
    (cmd,) = peer.messages("COMMAND_LONG")
    assert cmd.command == mavlink.MAV_CMD_DO_SET_ACTUATOR
    params = [cmd.param1, cmd.param2, cmd.param3, cmd.param4, cmd.param5, cmd.param6]
    assert params == pytest.approx([-1.0, 1.0, 0.0, 0.5, -0.5, -1.0])
    assert cmd.param7 == 0.0


def test_px4_needs_every_joint_and_pads_with_nan(udp):
    peer, sender = udp
    with pytest.raises(ConfigurationError, match=r"missing \['theta2'"):
        Px4ServoDialect(sender, default_calibration()).send_pwm({9: 1500})
    four = calibration_from_ranges([(-90, 90)] * 4, outputs=(1, 2, 3, 4))
    Px4ServoDialect(sender, four).send_angles([0, 0, 0, 90])
    (cmd,) = peer.messages("COMMAND_LONG")
    assert [cmd.param1, cmd.param2, cmd.param3, cmd.param4] == [0.0, 0.0, 0.0, 1.0]
    assert math.isnan(cmd.param5) and math.isnan(cmd.param6)


def test_px4_refuses_more_than_six_joints(udp):
    _, sender = udp
    seven = calibration_from_ranges([(-90, 90)] * 7, outputs=range(1, 8))
    with pytest.raises(ConfigurationError, match="at most 6 joints"):
        Px4ServoDialect(sender, seven)


def test_unknown_dialect_lists_the_valid_ones(udp):
    _, sender = udp
    with pytest.raises(
        ConfigurationError,
        match=r"unknown servo dialect 'betaflight'; "
        r"valid: \['ardupilot', 'ardupilot-lua', 'px4'\]",
    ):
        make_servo_dialect("betaflight", sender, default_calibration())


def test_ardupilot_commands_and_acks_over_a_pty():
    endpoint = PtyEndpoint()
    peer, link, sender = connect(endpoint, f"{endpoint.path},57600")
    try:
        dialect = ArduPilotServoDialect(sender, default_calibration())
        sent = dialect.send_angles([10, 20, 30, 40, 50, 60])
        assert servo_commands(peer) == list(sent.items())
        assert peer.bad_frames == []
    finally:
        sender.close()
        link.close()
        peer.close()


# -- ardupilot-lua: one MAV_CMD_USER_2 per window of six outputs, for the shipped Lua bridge --


def test_lua_plans_six_consecutive_outputs_as_one_command():
    dialect = make_servo_dialect("ardupilot-lua", None, default_calibration())
    pwm = {9: 1100, 10: 1200, 11: 1300, 12: 1400, 13: 1500, 14: 1600}
    (cmd,) = dialect.plan(pwm)
    assert cmd.command == MAV_CMD_USER_2
    assert cmd.params == (1100.0, 1200.0, 1300.0, 1400.0, 1500.0, 1600.0, 9.0)
    assert dict(cmd.pwm_by_output) == pwm
    assert dialect.plan(pwm, acked_pwm_us=pwm) == []  # nothing to change: nothing sent
    (again,) = dialect.plan(pwm, acked_pwm_us={**pwm, 12: 1401})
    assert dict(again.pwm_by_output) == pwm  # one output differs: the whole window goes


def test_lua_outputs_apart_take_one_command_per_window_with_nan_gaps():
    calibration = calibration_from_ranges([(-90, 90)] * 4, outputs=(1, 3, 9, 10))
    dialect = ArduPilotLuaServoDialect(None, calibration)
    low, high = dialect.plan({1: 1500, 3: 1600, 9: 1700, 10: 1800})
    assert low.params[0] == 1500.0 and math.isnan(low.params[1]) and low.params[2] == 1600.0
    assert all(math.isnan(p) for p in low.params[3:6]) and low.params[6] == 1.0
    assert dict(low.pwm_by_output) == {1: 1500, 3: 1600}
    assert high.params[:2] == (1700.0, 1800.0) and high.params[6] == 9.0
    assert ArduPilotLuaServoDialect.windows([14, 9, 15, 3]) == [(3,), (9, 14), (15,)]


def test_lua_out_of_range_pwm_never_planned():
    dialect = ArduPilotLuaServoDialect(None, default_calibration())
    with pytest.raises(PwmOutOfRange, match="pwm_us=2210"):
        dialect.plan({9: 1500, 10: 2210})


def test_lua_failed_ack_refuses_every_output_of_the_command():
    dialect = ArduPilotLuaServoDialect(None, default_calibration())
    commands = dialect.plan(dict.fromkeys(range(9, 15), 1500))
    tracker = UpdateTracker(commands, sent_s=0.0, timeout_s=0.1, grace_s=0.01)
    tracker.on_ack(MAV_CMD_USER_2, mavlink.MAV_RESULT_FAILED, 0.009)
    tracker.on_statustext("armbridge: Channel 12 is already in use; none set")
    outcome = tracker.poll(0.02)
    assert outcome is not None and outcome.state is UpdateState.DONE
    assert sorted(outcome.refused) == list(range(9, 15)) and not outcome.accepted
    assert "Channel 12" in outcome.refused[12]


def test_lua_send_pwm_one_command_long_then_refusal_names_the_output(udp):
    peer, sender = udp
    dialect = make_servo_dialect("ardupilot-lua", sender, default_calibration())
    dialect.send_angles([0, 90, 0, -90, 90, -70])
    (cmd,) = peer.messages("COMMAND_LONG")
    assert cmd.command == MAV_CMD_USER_2
    assert [cmd.param1, cmd.param2, cmd.param6, cmd.param7] == [1500, 1500, 1000, 9]
    text = "armbridge: Channel 12 is already in use; none set"
    peer.ack_result = mavlink.MAV_RESULT_FAILED
    peer.on_command = lambda _cmd: peer.send_statustext(text)
    with pytest.raises(ServoOutputUnavailable) as info:
        dialect.send_pwm(dict.fromkeys(range(9, 15), 1600))
    assert (info.value.output, info.value.statustext) == (12, text)
    assert "none set" in str(info.value)


def test_lua_denied_ack_refuses_every_output_naming_the_parameters_not_the_output():
    dialect = ArduPilotLuaServoDialect(None, default_calibration())
    commands = dialect.plan(dict.fromkeys(range(9, 15), 1500))
    tracker = UpdateTracker(commands, sent_s=0.0, timeout_s=0.1, grace_s=0.01)
    tracker.on_ack(MAV_CMD_USER_2, mavlink.MAV_RESULT_DENIED, 0.009)
    tracker.on_statustext("armbridge: denied 1/191: not ARMB_SYSID/COMPID")
    outcome = tracker.poll(0.02)
    assert outcome is not None and outcome.state is UpdateState.DONE
    assert sorted(outcome.refused) == list(range(9, 15)) and not outcome.accepted
    for reason in outcome.refused.values():
        assert reason.startswith("MAV_RESULT_DENIED (")
        assert "ARMB_SYSID / ARMB_COMPID" in reason and "link.component_id" in reason


def test_lua_send_pwm_denied_says_which_parameters_to_set_to_our_ids(udp):
    peer, sender = udp
    dialect = make_servo_dialect("ardupilot-lua", sender, default_calibration())
    peer.ack_result = mavlink.MAV_RESULT_DENIED
    with pytest.raises(CommandRejected) as info:
        dialect.send_pwm(dict.fromkeys(range(9, 15), 1600))
    assert not isinstance(info.value, ServoOutputUnavailable)
    assert info.value.result == mavlink.MAV_RESULT_DENIED
    message = str(info.value)
    assert "as from 42/191" in message  # the vehicle's system id, learned; our component id
    assert "set ARMB_SYSID = 0 (the vehicle's own system id) and ARMB_COMPID = 191" in message
