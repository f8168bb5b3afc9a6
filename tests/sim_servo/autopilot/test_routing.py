"""Routing between links: ArduPilot's MAVLink_routing.cpp rules as measured on ArduCopter
SITL, and PX4's forwarding (``MAV_n_FORWARD``, ``component_was_seen``) as measured on PX4
SITL."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.params import ParamTable
from sim_servo.autopilot.wire import Wire
from sim_servo.config import Px4TimingConfig, SimConfig, config_from_mapping
from sim_servo.faults import FaultInjector
from tests.sim_servo.autopilot.conftest import (
    COMPANION,
    KEY,
    READY_PX4,
    START_S,
    WALL_S,
    Harness,
    acks,
    part_state,
    routing_harness,
)


def test_commands_for_another_component_heard_elsewhere_are_not_handled_here():
    # Once 1/154 (a camera, say) has been heard on link 1, a command for it is its business
    # (routing: forwarded there, not handled). Never heard: see the routing tests below.
    h = Harness(links=2)
    camera = mavlink.MAVLink(None, 1, 154)
    h.ap.receive(camera.heartbeat_encode(30, 8, 0, 0, 0).pack(camera), h.now, 1)
    h.run_for(0.01)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500, target=(1, 154))
    assert acks(h.run_for(0.1)) == [] and h.ap.pwm_us[9] == 0
    assert [ch for ch, _ in h.forwarded()] == [1]
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500, target=(0, 0))  # broadcast
    assert len(acks(h.run_for(0.1))) == 1


def test_heartbeats_are_forwarded_to_the_other_link_and_routes_learned():
    h = Harness(links=2)
    companion = mavlink.MAVLink(None, *COMPANION)
    frame = companion.heartbeat_encode(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
    ).pack(companion)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == []  # nobody heard on another link yet: nowhere to forward
    gcs_frame = h.gcs.heartbeat_encode(6, 8, 0, 0, 0).pack(h.gcs)
    h.ap.receive(gcs_frame, h.now, 1)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == [(0, gcs_frame), (1, frame)]
    assert h.ap.snapshot(h.now)["routes"] == [[1, 191, 0], [255, 190, 1]]


def test_target_for_the_companion_is_forwarded_unchanged_and_not_handled_here():
    h, _ = routing_harness()
    routed = h.ap.stats["routed"]
    msg = h.gcs.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, 1, 2, 3, 4, 5, 6, 0)
    frame = msg.pack(h.gcs)
    h.ap.receive(frame, h.now, 1)
    replies = h.run_for(0.01)
    assert h.forwarded() == [(0, frame)]
    assert h.of_type("COMMAND_ACK", replies) == []  # the companion answers, not the autopilot
    assert h.ap.stats["routed"] == routed + 1


def test_commands_for_the_autopilot_are_handled_and_not_forwarded():
    h, _ = routing_harness()
    h.ap.receive(
        h.gcs.command_long_encode(
            1, 1, mavlink.MAV_CMD_DO_SET_SERVO, 0, 9, 1500, 0, 0, 0, 0, 0
        ).pack(h.gcs),
        h.now,
        1,
    )
    replies = h.run_for(0.01)
    assert h.forwarded() == []
    # The ACK goes back on the ground station's link only, as GCS_Common.cpp sends it on
    # the command's channel: the companion's link (0) does not see it.
    assert [a.result for a in h.on_link(1, "COMMAND_ACK")] == [mavlink.MAV_RESULT_ACCEPTED]
    assert h.of_type("COMMAND_ACK", replies) == []


def test_unknown_targets_go_nowhere_and_replies_go_back_to_their_sender():
    h, companion = routing_harness()
    h.ap.receive(
        h.gcs.command_long_encode(7, 191, mavlink.MAV_CMD_USER_1, 0, *[0] * 7).pack(h.gcs), h.now, 1
    )
    h.run_for(0.01)
    assert h.forwarded() == []
    ack = companion.command_ack_encode(mavlink.MAV_CMD_USER_1, 0, 0, 0, 255, 190)
    frame = ack.pack(companion)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == [(1, frame)]


def test_statustext_is_a_broadcast_and_is_also_handled_here():
    h, companion = routing_harness()
    frame = companion.statustext_encode(4, b"unreachable").pack(companion)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == [(1, frame)]


def test_signed_frames_are_forwarded_with_their_signature_unsigned_ones_dropped():
    h, _ = routing_harness(signing_key=KEY)
    signed = h.gcs.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[1] * 7)
    frame = signed.pack(h.gcs)
    assert frame[2] & mavlink.MAVLINK_IFLAG_SIGNED
    h.ap.receive(frame, h.now, 1)
    h.run_for(0.01)
    assert h.forwarded() == [(0, frame)]
    plain = mavlink.MAVLink(None, 255, 190)
    h.ap.receive(
        plain.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[1] * 7).pack(plain),
        h.now,
        1,
    )
    forger = mavlink.MAVLink(None, 255, 190)
    forger.signing.secret_key = bytes(32)
    forger.signing.sign_outgoing = True
    forger.signing.timestamp = 10**12
    h.ap.receive(
        forger.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[1] * 7).pack(forger),
        h.now,
        1,
    )
    h.run_for(0.01)
    assert h.forwarded() == []
    assert h.ap.stats["rejected_signature"] == 2


USER_1 = mavlink.MAV_CMD_USER_1


def user_1(h: Harness, target=COMPANION) -> bytes:
    return h.gcs.command_long_encode(*target, USER_1, 0, *[1] * 7).pack(h.gcs)


def heartbeat_from(codec) -> bytes:
    return codec.heartbeat_encode(18, 8, 0, 0, 0).pack(codec)


def test_a_command_for_a_component_never_heard_is_answered_unsupported_by_the_autopilot():
    h = Harness(links=2)
    h.ap.receive(heartbeat_from(h.gcs), h.now, 1)  # the ground station on link 1
    h.run_for(0.01)
    h.ap.receive(user_1(h), h.now, 1)  # for 1/191, before any companion was heard
    h.run_for(0.01)
    ack = h.on_link(1, "COMMAND_ACK")[0]
    assert (ack.get_srcSystem(), ack.get_srcComponent()) == (1, 1)
    assert (ack.command, ack.result) == (USER_1, mavlink.MAV_RESULT_UNSUPPORTED)
    assert (ack.target_system, ack.target_component) == (255, 190)
    assert h.forwarded() == []


def test_a_component_that_left_keeps_its_route_and_gets_the_frames_no_ack_comes():
    h, companion = routing_harness()
    h.run_for(60.0)  # the companion's link closed / it stopped talking long ago
    frame = user_1(h)
    h.ap.receive(frame, h.now, 1)
    h.run_for(0.5)
    assert h.forwarded() == [(0, frame)]  # to the dead link, as ArduPilot never forgets
    assert h.on_link(1, "COMMAND_ACK") == []
    assert [1, 191, 0] in h.ap.snapshot(h.now)["routes"]


def test_a_frame_is_never_forwarded_back_out_of_the_link_it_came_in_on():
    # A ground station and the companion behind one link (link 0): the GCS's USER_1 for the
    # companion is not sent back down that link, so the autopilot answers it itself.
    h = Harness(links=2)
    companion = mavlink.MAVLink(None, *COMPANION)
    h.ap.receive(heartbeat_from(companion), h.now, 0)
    h.ap.receive(heartbeat_from(h.gcs), h.now, 0)
    h.run_for(0.01)
    h.forwarded()
    h.ap.receive(user_1(h), h.now, 0)
    replies = h.run_for(0.01)
    assert h.forwarded() == []
    assert [(a.command, a.result) for a in acks(replies)] == [
        (USER_1, mavlink.MAV_RESULT_UNSUPPORTED)
    ]


def test_a_component_heard_on_two_links_gets_frames_on_the_other_one():
    h, companion = routing_harness()
    h.ap.receive(heartbeat_from(companion), h.now, 1)  # now also heard on link 1
    h.run_for(0.01)
    h.forwarded()
    frame = user_1(h)
    h.ap.receive(frame, h.now, 1)
    h.run_for(0.01)
    assert h.forwarded() == [(0, frame)]  # not back onto link 1, and not handled here
    assert h.on_link(1, "COMMAND_ACK") == []


def test_another_system_is_reached_whatever_its_component():
    h = Harness(links=2)
    other = mavlink.MAVLink(None, 7, 1)
    h.ap.receive(heartbeat_from(other), h.now, 1)
    h.run_for(0.01)
    frame = user_1(h, target=(7, 50))  # a component of system 7 never heard
    h.ap.receive(frame, h.now, 0)
    replies = h.run_for(0.01)
    assert (1, frame) in h.forwarded() and acks(replies) == []


def test_our_own_frames_looped_back_teach_no_route_and_radio_status_is_not_forwarded():
    h, companion = routing_harness()
    me = mavlink.MAVLink(None, 1, 1)
    h.ap.receive(heartbeat_from(me), h.now, 1)
    radio = companion.radio_status_encode(200, 190, 100, 10, 10, 0, 0).pack(companion)
    h.ap.receive(radio, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == []
    assert [1, 1, 1] not in h.ap.snapshot(h.now)["routes"]


def test_the_routing_table_holds_at_most_20_routes():
    h = Harness(links=2)
    for component in range(1, 31):
        codec = mavlink.MAVLink(None, 9, component)
        h.ap.receive(heartbeat_from(codec), h.now, 1)
    h.run_for(0.01)
    assert len(h.ap.routes) == 20
    assert h.ap.routes[-1] == (9, 20, 1)


def px4_pair(**settings) -> Harness:
    """PX4 with the companion (1/191) on link 0, heard; the ground station on link 1."""
    h = Harness(config_from_mapping({"flavour": "px4", **settings}), links=2)
    companion = mavlink.MAVLink(None, 1, 191)
    h.ap.receive(
        companion.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 0).pack(companion),
        h.now,
        0,
    )
    h.run_for(0.01)
    h.forwarded()
    return h


def test_px4_forwards_only_between_links_with_forwarding_on_to_a_heard_component():
    user_1 = mavlink.MAV_CMD_USER_1
    both = {"MAV_0_FORWARD": 1, "MAV_1_FORWARD": 1}

    def send_user_1(h, component=191):
        h.send(h.gcs.command_long_encode(1, component, user_1, 0, 0, 0, 0, 0, 0, 0, 0), 1)
        h.run_for(0.01)
        return [channel for channel, _ in h.forwarded()]

    # PX4's defaults: forwarding on for instance 0 (the ground station's), off for the
    # companion's: nothing goes through, and the command is not ours: no answer.
    h = px4_pair()
    assert send_user_1(h) == [] and h.of_type("COMMAND_ACK") == []
    assert [e["to"] for e in h.events if e["event"] == "ignored"] == [[1, 191]]
    h = px4_pair(params=both)
    assert send_user_1(h) == [0]
    assert send_user_1(h, component=192) == []  # never heard on link 0
    h = px4_pair(params={"MAV_0_FORWARD": 0, "MAV_1_FORWARD": 1})
    assert send_user_1(h) == []  # the link it came in on does not forward


def test_px4_udpin_race_a_target_before_the_companion_spoke_is_dropped():
    h = Harness(
        config_from_mapping({"flavour": "px4", "params": {"MAV_0_FORWARD": 1, "MAV_1_FORWARD": 1}}),
        links=2,
    )
    h.send(h.gcs.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0), 1)
    h.run_for(0.01)
    assert h.forwarded() == [] and h.of_type("COMMAND_ACK") == []


def test_px4_timing_forwarded_frames_wait_forward_delay_then_a_main_loop_pass():
    timing = Px4TimingConfig(commander_period_ms=10.0, mavlink_loop_ms=1.5, forward_delay_ms=3.5)
    h = Harness(READY_PX4, px4_timing=timing, links=2)
    companion = mavlink.MAVLink(None, 1, 191)
    h.ap.receive(companion.heartbeat_encode(18, 8, 0, 0, 0).pack(companion), h.now, 0)
    h.run_for(0.01)
    h.forwarded()
    h.run_until(START_S + 0.1003)
    sent = h.now
    h.send(h.gcs.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0), 1)
    while not (out := h.forwarded()):
        h.now = h.ap.next_event_s(h.now + 1e-9)
        h._collect()
    assert out[0][0] == 0
    # 100.3 ms after boot + 3.5 ms = 103.8 ms, then the next 1.5 ms pass: 105.0 ms.
    assert (h.now - sent) * 1000 == pytest.approx(4.7)


# -- the routers alone -----------------------------------------------------------------------


def router_for(config: SimConfig, events: list):
    state = part_state(config, events)
    wire = Wire(state, FaultInjector(config.faults), links=2, wall_clock=lambda: WALL_S)
    return state.flavour.make_router(state, wire, ParamTable(state)), wire


def test_ardupilot_router_learns_routes_and_forwards_a_command_to_a_heard_component():
    events: list = []
    router, wire = router_for(SimConfig(), events)
    companion = mavlink.MAVLink(None, *COMPANION)
    gcs = mavlink.MAVLink(None, 255, 190)
    hb = companion.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 0)
    assert router.route(decoded(hb.pack(companion)), 0, START_S) is True
    assert router.routes == [(1, 191, 0)] and router.active_links == {0}
    command = gcs.command_long_encode(1, 191, 31010, 0, 0, 0, 0, 0, 0, 0, 0)
    assert router.route(decoded(command.pack(gcs)), 1, START_S) is False  # the companion's
    assert router.routes == [(1, 191, 0), (255, 190, 1)]
    assert [e["links"] for e in events if e["event"] == "routed"] == [[0]]
    router.boot(START_S)
    assert (router.routes, router.active_links, router.peer) == ([], set(), None)


def test_px4_router_forwards_only_where_forwarding_is_on_and_the_target_was_heard():
    events: list = []
    router, _ = router_for(SimConfig(flavour="px4"), events)
    companion = mavlink.MAVLink(None, *COMPANION)
    gcs = mavlink.MAVLink(None, 255, 190)
    assert (router.forwarding(0), router.forwarding(1)) == (False, True)  # MAV_1, MAV_0
    router.route(decoded(companion.heartbeat_encode(18, 8, 0, 0, 0).pack(companion)), 0, START_S)
    command = gcs.command_long_encode(1, 191, 31010, 0, 0, 0, 0, 0, 0, 0, 0)
    assert router.route(decoded(command.pack(gcs)), 1, START_S) is False
    # Forwarding is off on the companion's link (MAV_1_FORWARD 0): nothing goes out; the
    # command for another component of ours is ignored without an answer.
    assert [e["event"] for e in events] == ["ignored"]
    assert router.routes == []


def decoded(frame: bytes) -> mavlink.MAVLink_message:
    (msg,) = mavlink.MAVLink(None).parse_buffer(frame)
    return msg
