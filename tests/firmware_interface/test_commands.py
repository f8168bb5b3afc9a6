import threading

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import ScriptedPeer, UdpEndpoint
from devkit.timing import wait_until
from firmware_interface.commands import CommandSender, command_name, result_name
from firmware_interface.errors import CommandRejected, ConfigurationError, LinkClosed, LinkTimeout
from firmware_interface.link import LinkConfig, MavlinkLink

SERVO = mavlink.MAV_CMD_DO_SET_SERVO


@pytest.fixture
def peer():
    peer = ScriptedPeer(UdpEndpoint(), system_id=42)
    yield peer
    peer.close()


@pytest.fixture
def link(peer, clock):
    link = MavlinkLink.open(
        f"udpout:127.0.0.1:{peer.endpoint.port}", LinkConfig(heartbeat_rate_hz=20.0), clock=clock
    )
    peer.wait_for_messages("HEARTBEAT")
    peer.send_heartbeat()
    link.wait_for_autopilot(timeout_s=5.0)
    yield link
    link.close()


@pytest.fixture
def sender(link):
    sender = CommandSender(link, timeout_s=0.5, retries=2)
    yield sender
    sender.close()


def test_accepted_command_round_trip(peer, sender):
    outcome = sender.command_long(SERVO, (9, 1500))
    assert (outcome.attempts, outcome.confirmation, outcome.target) == (1, 0, (42, 1))
    cmd = peer.messages("COMMAND_LONG")[0]
    assert (cmd.target_system, cmd.target_component, cmd.command) == (42, 1, SERVO)
    assert (cmd.param1, cmd.param2, cmd.param3, cmd.confirmation) == (9.0, 1500.0, 0.0, 0)
    assert (cmd.get_srcSystem(), cmd.get_srcComponent()) == (42, 191)


def test_dropped_ack_is_retried_with_incremented_confirmation(peer, sender, clock):
    peer.drop_acks = 1
    # The peer "waits out" the timeout on the fake clock instead of anyone sleeping.
    peer.on_command = lambda cmd: clock.advance(0.6) if cmd.confirmation == 0 else None
    outcome = sender.command_long(SERVO, (10, 1200))
    assert (outcome.attempts, outcome.confirmation) == (2, 1)
    sent = peer.messages("COMMAND_LONG")
    assert [c.confirmation for c in sent] == [0, 1]
    assert {(c.param1, c.param2) for c in sent} == {(10.0, 1200.0)}


def test_every_ack_dropped_gives_a_timeout_after_all_attempts(peer, sender, clock):
    peer.drop_acks = 99
    peer.on_command = lambda cmd: clock.advance(0.6)
    with pytest.raises(
        LinkTimeout,
        match=r"no COMMAND_ACK for MAV_CMD_DO_SET_SERVO from 42/1 "
        r"after 3 attempts of timeout_s=0.5",
    ):
        sender.command_long(SERVO, (9, 1500))
    assert [c.confirmation for c in peer.messages("COMMAND_LONG")] == [0, 1, 2]


def test_rejection_carries_the_result(peer, sender):
    peer.ack_result = mavlink.MAV_RESULT_DENIED
    with pytest.raises(CommandRejected) as info:
        sender.command_long(mavlink.MAV_CMD_USER_1, ())
    assert info.value.result == mavlink.MAV_RESULT_DENIED
    assert info.value.result_name == "MAV_RESULT_DENIED"
    assert info.value.statustext is None


def test_in_progress_and_acks_for_others_are_not_the_answer(peer, sender):
    def before_answer(cmd):
        peer.send(
            peer.mav.command_ack_encode(cmd.command, mavlink.MAV_RESULT_IN_PROGRESS, 50, 0, 42, 191)
        )
        peer.send(
            peer.mav.command_ack_encode(cmd.command, mavlink.MAV_RESULT_DENIED, 0, 0, 255, 190)
        )  # meant for a GCS

    peer.on_command = before_answer
    assert sender.command_long(SERVO, (9, 1500)).attempts == 1


def test_unmatched_ack_is_counted(peer, sender):
    peer.send(peer.mav.command_ack_encode(SERVO, 0, 0, 0, 42, 191))
    assert wait_until(lambda: sender.unmatched_acks == 1)


def test_only_one_command_of_an_id_in_flight_per_target(peer, sender, clock):
    peer.drop_acks = 1
    first_sent = threading.Event()
    peer.on_command = lambda cmd: first_sent.set()
    results = {}

    def call(name, params):
        results[name] = sender.command_long(SERVO, params)

    a = threading.Thread(target=call, args=("a", (9, 1100)))
    a.start()
    assert first_sent.wait(5.0)
    b = threading.Thread(target=call, args=("b", (10, 1900)))
    b.start()
    # While the first DO_SET_SERVO is unanswered the second must not go out.
    assert not peer.wait_for(lambda: len(peer.messages("COMMAND_LONG")) >= 2, timeout_s=0.3)
    clock.advance(0.6)
    a.join(5.0)
    b.join(5.0)
    assert not a.is_alive() and not b.is_alive()
    sent = [(c.param1, c.confirmation) for c in peer.messages("COMMAND_LONG")]
    assert sent == [(9.0, 0), (9.0, 1), (10.0, 0)]
    assert results["a"].attempts == 2 and results["b"].attempts == 1


def test_link_closing_ends_the_wait(peer, sender, link):
    peer.drop_acks = 1
    peer.on_command = lambda cmd: link.close()
    with pytest.raises(LinkClosed):
        sender.command_long(SERVO, (9, 1500))


def test_bad_arguments_are_refused(sender, link):
    with pytest.raises(ConfigurationError, match="at most 7 params, got 8"):
        sender.command_long(SERVO, range(8))
    with pytest.raises(ConfigurationError, match=r"retries=-1 outside \[0, 254\]"):
        CommandSender(link, retries=-1)
    assert command_name(99999) == "99999" and result_name(4) == "MAV_RESULT_FAILED"
