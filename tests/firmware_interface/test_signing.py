import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import ScriptedPeer, UdpEndpoint
from devkit.timing import wait_until
from firmware_interface.errors import ConfigurationError, SigningStateError
from firmware_interface.link import LinkConfig, MavlinkLink
from firmware_interface.signing import (
    LOCKOUT_HOLD_S,
    SIGNING_EPOCH_UNIX_S,
    TICKS_PER_S,
    SigningConfig,
    SigningLockout,
    TimestampKeeper,
    duration_text,
    load_key,
    lockout_message,
    wall_to_ticks,
)

KEY = bytes(range(32))
WRONG_KEY = bytes(32)
NOW_UNIX_S = 1_790_000_000.0  # late 2026


def test_load_key_raw_and_hex(tmp_path):
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    raw.chmod(0o600)
    hexed = tmp_path / "hex.key"
    hexed.write_text(KEY.hex() + "\n")
    hexed.chmod(0o640)  # a group of its own may read it
    assert load_key(raw) == KEY and load_key(hexed) == KEY


@pytest.mark.parametrize("mode", [0o644, 0o666, 0o604, 0o660, 0o620])
def test_a_key_file_others_may_read_or_the_group_may_write_is_refused(tmp_path, mode):
    key = tmp_path / "signing.key"
    key.write_bytes(KEY)
    key.chmod(mode)
    with pytest.raises(ConfigurationError, match=f"has mode {mode:04o}.*chmod 0600"):
        load_key(key)


def test_load_key_refuses_wrong_sizes_and_missing_files(tmp_path):
    short = tmp_path / "short.key"
    short.write_bytes(b"x" * 31)
    short.chmod(0o600)
    with pytest.raises(ConfigurationError, match="holds 31 bytes; expected 32 raw bytes or 64 hex"):
        load_key(short)
    with pytest.raises(ConfigurationError, match="cannot read signing key file") as info:
        load_key(tmp_path / "absent.key")
    assert isinstance(info.value.__cause__, OSError)
    assert str(info.value).count("absent.key") == 1  # the path once, not again in the errno text
    assert str(info.value).endswith(": No such file or directory")
    with pytest.raises(ConfigurationError, match=r"link_id=256 outside \[0, 255\]"):
        SigningConfig(key=KEY, link_id=256)


def test_wall_clock_ticks_from_2015():
    assert wall_to_ticks(SIGNING_EPOCH_UNIX_S + 1.5) == 150_000
    assert wall_to_ticks(0.0) == 0  # a companion without RTC booting in 1970


def test_an_autopilot_signing_a_year_ahead_is_a_problem_with_both_clocks_and_the_fix():
    ours = wall_to_ticks(NOW_UNIX_S)  # 2026-09-21 14:13:20 UTC
    lockout = SigningLockout()
    assert lockout.problem(0.0) is None and not lockout.seen
    year = 365 * 86_400 * TICKS_PER_S
    assert lockout.refused((1, 1), ours + year, ours, now_s=10.0)  # it begins: say so
    assert not lockout.refused((1, 1), ours + year + 100, ours + 100, now_s=11.0)  # once
    problem = lockout.problem(12.0)
    assert problem == (
        "the autopilot 1/1 signs 365.0 days ahead of our clock (its 2027-09-21 14:13:20 UTC, "
        "ours 2026-09-21 14:13:20 UTC): we refuse its frames as from the future, and once it "
        "restarts it refuses ours as too old"
    )
    message = lockout_message(problem)
    assert "set it" in message and "SETUP_SIGNING" in message and "disarmed" in message
    # It stands while the autopilot's frames keep coming from the future, then lapses ...
    assert lockout.problem(11.0 + LOCKOUT_HOLD_S) is not None
    assert lockout.problem(11.1 + LOCKOUT_HOLD_S) is None
    # ... or ends at once when one of its frames is accepted (its timestamp was reset).
    assert lockout.refused((1, 1), ours + year, ours, now_s=30.0)
    assert lockout.clear() and lockout.problem(30.0) is None and not lockout.clear()


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (75, "75 s"),
        (2520, "42 min"),
        (19_080, "5.3 h"),
        (259_200, "3.0 days"),
        (3 * 31_557_600, "3.0 years"),
    ],  # fmt: skip
)
def test_how_far_ahead_reads_for_people(seconds, text):
    assert duration_text(seconds) == text


def test_timestamps_stay_monotonic_across_restart_when_the_wall_clock_goes_back(tmp_path):
    state = tmp_path / "signing.state"
    first = TimestampKeeper(SigningConfig(KEY, state_path=state, wall_clock=lambda: NOW_UNIX_S))
    start = first.initial_timestamp
    assert start == wall_to_ticks(NOW_UNIX_S)
    assert int(state.read_text()) == first.reserved_until == start + 60 * TICKS_PER_S
    last = start
    for step in range(1, 200):  # use up more than half the reservation: it is renewed
        last = first.next_timestamp(start + step * 200_000)
        assert last < int(state.read_text())
    assert int(state.read_text()) > start + 60 * TICKS_PER_S
    # Restart with the clock back in 1970: we still continue above everything sent.
    second = TimestampKeeper(SigningConfig(KEY, state_path=state, wall_clock=lambda: 0.0))
    assert second.initial_timestamp > last


def test_unreadable_state_file_is_refused(tmp_path):
    state = tmp_path / "signing.state"
    state.write_text("not a number")
    with pytest.raises(ConfigurationError, match="signing state file"):
        TimestampKeeper(SigningConfig(KEY, state_path=state))


@pytest.fixture
def peer():
    peer = ScriptedPeer(UdpEndpoint(), system_id=42, signing_key=KEY)
    yield peer
    peer.close()


def open_signed(peer, tmp_path, wall_s=NOW_UNIX_S):
    signing = SigningConfig(
        KEY, link_id=3, state_path=tmp_path / "signing.state", wall_clock=lambda: wall_s
    )
    return MavlinkLink.open(
        f"udpout:127.0.0.1:{peer.endpoint.port}",
        LinkConfig(heartbeat_rate_hz=20.0, signing=signing),
    )


def rogue_frame(peer, key, msg, timestamp=None, link_id=7):
    """A frame from the peer's own system/component, unsigned (key None) or signed with key."""
    codec = mavlink.MAVLink(None, 42, 1)
    codec.seq = 200
    if key is not None:
        codec.signing.secret_key = key
        codec.signing.link_id = link_id
        codec.signing.sign_outgoing = True
        codec.signing.timestamp = timestamp or peer.mav.signing.timestamp + 1
    return msg.pack(codec)


def test_signed_link_accepts_signed_and_rejects_unsigned_or_forged(peer, tmp_path):
    with open_signed(peer, tmp_path) as link:
        beat = peer.wait_for_messages("HEARTBEAT")[0]
        assert beat.get_signed() and beat.get_link_id() == 3
        assert peer.bad_frames == []  # the peer checked every signature with the shared key

        received = []
        link.subscribe(received.append, ["COMMAND_LONG", "STATUSTEXT"])
        peer.send_heartbeat()  # signed by the peer
        link.wait_for_autopilot(timeout_s=5.0)

        cmd = peer.mav.command_long_encode(42, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0)
        peer.endpoint.write(rogue_frame(peer, None, cmd))  # unsigned
        peer.endpoint.write(rogue_frame(peer, WRONG_KEY, cmd))  # wrong key
        # wrong key with a far-future timestamp must not poison the genuine stream (link id 7)
        peer.endpoint.write(rogue_frame(peer, WRONG_KEY, cmd, timestamp=2**47))
        peer.send_statustext("genuine")  # signed, sent after the forgeries
        assert wait_until(lambda: any(m.get_type() == "STATUSTEXT" for m in received))
        assert [m.get_type() for m in received] == ["STATUSTEXT"]
        assert received[0].text == "genuine"
        stats = link.stats
        assert (stats.rejected_unsigned, stats.rejected_bad_signature) == (1, 2)


def test_signing_timestamp_survives_a_restart_with_a_clock_in_the_past(peer, tmp_path):
    with open_signed(peer, tmp_path) as link:
        peer.wait_for_messages("HEARTBEAT", count=2)
    count = len(peer.messages("HEARTBEAT"))
    # Same peer keeps its per-stream timestamps and rejects anything not newer.
    with open_signed(peer, tmp_path, wall_s=0.0) as link:
        peer.wait_for_messages("HEARTBEAT", count=count + 2)
        assert link.signing_reserved_until > wall_to_ticks(NOW_UNIX_S)
    assert peer.bad_frames == []


def test_a_signing_state_that_cannot_be_stored_stops_sending(peer, tmp_path):
    """Signing beyond the stored reservation could reuse timestamps after a restart, so a state
    file that can no longer be written refuses the send with a LinkError (not an OSError that
    would kill the caller's thread)."""
    state_dir = tmp_path / "state"
    state_dir.mkdir()
    signing = SigningConfig(KEY, state_path=state_dir / "signing.state", reservation_s=1e-5)
    link = MavlinkLink.open(
        f"udpout:127.0.0.1:{peer.endpoint.port}",
        LinkConfig(heartbeat_rate_hz=20.0, signing=signing),
    )
    try:
        link.send(link.mav.statustext_encode(6, b"stored"))
        # The state directory vanished (unmounted, removed): moved away in one step, as the
        # heartbeat thread rewrites the state file all the time (unlink + rmdir raced it).
        state_dir.rename(tmp_path / "gone")
        with pytest.raises(SigningStateError, match="cannot store the signing timestamp"):
            link.send(link.mav.statustext_encode(6, b"not signed"))
        assert not link.closed
    finally:
        link.close()
    assert not any(m.text == "not signed" for m in peer.messages("STATUSTEXT"))
