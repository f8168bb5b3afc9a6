"""Signing findings, each against a real link on loopback: far-future frames,
replays after a restart, and a state file that cannot be written (disk full, read-only)."""

from __future__ import annotations

import errno
import os

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import ScriptedPeer, UdpEndpoint
from devkit.timing import FakeClock, wait_until
from firmware_interface.errors import SigningStateError
from firmware_interface.link import LinkConfig, LinkState, MavlinkLink
from firmware_interface.signing import (
    RETRY_S,
    TICKS_PER_S,
    SigningConfig,
    TimestampKeeper,
    wall_to_ticks,
    write_state_file,
)

KEY = bytes(range(32))
NOW_UNIX_S = 1_790_000_000.0  # late 2026
NOW_TICKS = wall_to_ticks(NOW_UNIX_S)
YEAR_TICKS = 365 * 86_400 * TICKS_PER_S


class Writer:
    """The state writer, failing on demand with ``error`` (ENOSPC: a full disk)."""

    def __init__(self) -> None:
        self.error: OSError | None = None
        self.stored: list[int] = []

    def __call__(self, path, reserved_until: int) -> None:
        if self.error is not None:
            raise self.error
        write_state_file(path, reserved_until)
        self.stored.append(reserved_until)


@pytest.fixture
def peer():
    peer = ScriptedPeer(UdpEndpoint(), system_id=42, signing_key=KEY)
    yield peer
    peer.close()


def open_signed(peer, tmp_path, *, wall=None, writer=write_state_file, clock=None):
    wall = wall or [NOW_UNIX_S]
    signing = SigningConfig(
        KEY,
        link_id=3,
        state_path=tmp_path / "signing.state",
        wall_clock=lambda: wall[0],
        write_state=writer,
    )
    kwargs = {"clock": clock} if clock is not None else {}
    return MavlinkLink.open(
        f"udpout:127.0.0.1:{peer.endpoint.port}",
        LinkConfig(heartbeat_rate_hz=20.0, signing=signing),
        **kwargs,
    )


def connect(link, peer) -> None:
    """The peer heard us (and adopted our timestamp), we heard its HEARTBEAT."""
    heard = len(peer.messages("HEARTBEAT"))
    peer.wait_for_messages("HEARTBEAT", count=heard + 1)
    peer.send_heartbeat()
    link.wait_for_autopilot(5.0)


def gcs_target(timestamp: int, x_cm: float = 10.0) -> bytes:
    """A ground station's USER_1 to 42/191, signed with the right key at ``timestamp``."""
    gcs = mavlink.MAVLink(None, 255, 190)
    gcs.signing.secret_key = KEY
    gcs.signing.sign_outgoing = True
    gcs.signing.timestamp = timestamp
    return gcs.command_long_encode(42, 191, mavlink.MAV_CMD_USER_1, 0, x_cm, 0, 0, 0, 0, 0, 0).pack(
        gcs
    )


def timestamp_of(msg) -> int:
    return int.from_bytes(msg.get_msgbuf()[-12:-6], "little")


def test_a_far_future_signed_frame_never_locks_out_a_sender_with_a_correct_clock(peer, tmp_path):
    link = open_signed(peer, tmp_path)
    try:
        connect(link, peer)
        targets = link.messages(["COMMAND_LONG"])
        # Right key, one year ahead: today it moved the stream and the reservation a year on.
        peer.endpoint.write(gcs_target(NOW_TICKS + YEAR_TICKS, x_cm=99.0))
        peer.endpoint.write(gcs_target(NOW_TICKS + 100, x_cm=1.0))  # the GCS, correct clock
        assert targets.get(5.0).param1 == 1.0
        assert link.stats.rejected_future == 1
        assert link.signing_reserved_until < NOW_TICKS + 120 * TICKS_PER_S
    finally:
        link.close()
    # After a restart the link comes up (today: every stream "more than a minute behind").
    link = open_signed(peer, tmp_path)
    try:
        connect(link, peer)
        assert link.state is LinkState.UP
    finally:
        link.close()


def test_a_signed_target_captured_before_a_restart_is_refused_after_it(peer, tmp_path):
    link = open_signed(peer, tmp_path)
    try:
        connect(link, peer)
        targets = link.messages(["COMMAND_LONG"])
        captured = gcs_target(NOW_TICKS + 500)
        peer.endpoint.write(captured)
        assert targets.get(5.0).param1 == 10.0
        link.send(link.mav.statustext_encode(6, b"moved"))  # as the servo commands after it
        peer.wait_for(lambda: any(m.text == "moved" for m in peer.messages("STATUSTEXT")))
    finally:
        link.close()
    link = open_signed(peer, tmp_path)  # restarted 0 s later: the wall clock has not moved
    try:
        connect(link, peer)
        targets = link.messages(["COMMAND_LONG", "STATUSTEXT"])
        peer.endpoint.write(captured)  # within a minute: the spec alone would accept it
        peer.send_statustext("after the replay")
        assert targets.get(5.0).get_type() == "STATUSTEXT"
        assert targets.get_nowait() is None
        assert link.stats.rejected_replay == 1
    finally:
        link.close()


def test_nothing_is_signed_past_the_stored_reservation_when_the_disk_is_full(peer, tmp_path):
    writer, wall, clock = Writer(), [NOW_UNIX_S], FakeClock()
    link = open_signed(peer, tmp_path, wall=wall, writer=writer, clock=clock)
    try:
        connect(link, peer)
        writer.error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        wall[0] += 45.0  # past half the 60 s reservation: a new one must be stored first
        with pytest.raises(SigningStateError, match="No space left on device"):
            link.send(link.mav.statustext_encode(6, b"past the reservation"))
        assert link.state is LinkState.FAULT
        assert "No space left on device" in link.fault
        assert int((tmp_path / "signing.state").read_text()) == writer.stored[-1]
        # The heartbeat thread keeps trying (and is refused) meanwhile.
        assert wait_until(lambda: link.stats.signing_state_errors >= 3)
        writer.error = None
        clock.advance(RETRY_S)
        link.send(link.mav.statustext_encode(6, b"stored again"))
        assert link.fault is None and link.state is LinkState.UP
        peer.wait_for(lambda: any(m.text == "stored again" for m in peer.messages("STATUSTEXT")))
    finally:
        link.close()
    sent = [m for m in peer.received if m.get_srcSystem() == 42 and m.get_srcComponent() == 191]
    assert not any(m.text == "past the reservation" for m in peer.messages("STATUSTEXT"))
    before_recovery = writer.stored[-2]  # the last reservation stored before the disk filled
    late = [m for m in sent if timestamp_of(m) >= before_recovery]
    assert all(timestamp_of(m) < writer.stored[-1] for m in sent)
    # Only frames signed after the new reservation was stored are past the old one.
    assert all(m.get_type() != "STATUSTEXT" or m.text == "stored again" for m in late)


def test_a_read_only_state_file_is_refused_at_start_and_never_replaced(peer, tmp_path):
    state = tmp_path / "signing.state"
    state.write_text(f"{NOW_TICKS}\n")
    state.chmod(0o444)
    with pytest.raises(PermissionError, match="read-only"):
        open_signed(peer, tmp_path)
    assert state.read_text() == f"{NOW_TICKS}\n" and state.stat().st_mode & 0o777 == 0o444


def test_a_state_file_made_read_only_while_running_stops_signing(peer, tmp_path):
    wall = [NOW_UNIX_S]
    link = open_signed(peer, tmp_path, wall=wall)
    state = tmp_path / "signing.state"
    try:
        connect(link, peer)
        stored = state.read_text()
        state.chmod(0o444)
        wall[0] += 45.0
        with pytest.raises(SigningStateError, match="read-only"):
            link.send(link.mav.statustext_encode(6, b"x"))
        assert link.state is LinkState.FAULT
        assert state.read_text() == stored  # today it was silently replaced
    finally:
        link.close()


def test_the_keeper_moves_its_reservation_only_once_stored(tmp_path):
    writer, wall = Writer(), [NOW_UNIX_S]
    keeper = TimestampKeeper(
        SigningConfig(
            KEY,
            state_path=tmp_path / "signing.state",
            wall_clock=lambda: wall[0],
            write_state=writer,
        ),
        clock=FakeClock(),
    )
    reserved = keeper.reserved_until
    writer.error = PermissionError(errno.EROFS, os.strerror(errno.EROFS))
    wall[0] += 45.0
    with pytest.raises(SigningStateError, match="Read-only file system"):
        keeper.next_timestamp(0)
    assert keeper.reserved_until == reserved == writer.stored[-1]
    # Within the retry interval it does not even try again.
    writer.error = None
    with pytest.raises(SigningStateError):
        keeper.next_timestamp(0)
    assert len(writer.stored) == 1


DAY_TICKS = 86_400 * TICKS_PER_S


def test_an_autopilot_that_took_a_far_future_timestamp_is_named_with_the_fix(
    peer, tmp_path, caplog
):
    link = open_signed(peer, tmp_path)
    try:
        peer.wait_for_messages("HEARTBEAT")
        # A ground station's clock a year ahead: refused, but not the autopilot's problem.
        peer.endpoint.write(gcs_target(NOW_TICKS + YEAR_TICKS))
        assert wait_until(lambda: link.stats.rejected_future == 1)
        assert link.signing_problem is None
        # The autopilot (42/1) took a key holder's timestamp a day ahead of ours.
        peer.mav.signing.timestamp = NOW_TICKS + DAY_TICKS
        with caplog.at_level("ERROR", logger="firmware_interface.link"):
            for _ in range(3):
                peer.send_heartbeat()
            assert wait_until(lambda: link.stats.rejected_future == 4)
        problem = link.signing_problem
        assert problem is not None and problem.startswith("the autopilot 42/1 signs 24.0 h ahead")
        assert link.autopilot is None  # its HEARTBEAT is what is refused
        [error] = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
        assert problem in error and "SETUP_SIGNING" in error
        # Its timestamp reset (SETUP_SIGNING): its frames are accepted, the problem ends.
        peer.mav.signing.timestamp = NOW_TICKS + TICKS_PER_S
        peer.send_heartbeat()
        link.wait_for_autopilot(5.0)
        with caplog.at_level("WARNING", logger="firmware_interface.link"):
            peer.send_heartbeat()
            assert wait_until(lambda: link.signing_problem is None)
        assert any("accepted again" in r.getMessage() for r in caplog.records)
    finally:
        link.close()
