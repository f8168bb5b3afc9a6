"""The serial line model: bytes take 10 bits / baud each way, a bounded transmit buffer."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.serial_line import FrameSplitter, SerialLine, byte_time_s


def command_frames(n: int, *, signed: bool = False) -> list[bytes]:
    enc = mavlink.MAVLink(None, 255, 190)
    if signed:
        enc.signing.secret_key = bytes(range(32))
        enc.signing.sign_outgoing = True
        enc.signing.timestamp = 1
    return [
        bytes(enc.command_long_encode(1, 1, 183, 0, 9 + k, 1500, 0, 0, 0, 0, 0).pack(enc))
        for k in range(n)
    ]


def test_byte_times_are_the_issues_figures():
    # 264 B (six DO_SET_SERVO) at 8N1: 45.8 / 22.9 / 2.9 ms; 44 B: 7.6 / 3.8 / 0.5 ms.
    for baud, six_ms, one_ms in ((57_600, 45.8, 7.6), (115_200, 22.9, 3.8), (921_600, 2.9, 0.5)):
        assert 264 * byte_time_s(baud) * 1e3 == pytest.approx(six_ms, abs=0.05)
        assert 44 * byte_time_s(baud) * 1e3 == pytest.approx(one_ms, abs=0.05)


def test_back_to_back_frames_arrive_one_by_one_as_their_last_byte_does():
    frames = command_frames(6)
    assert {len(f) for f in frames} == {44}  # MAVLink 2 COMMAND_LONG, trailing zeros dropped
    line = SerialLine(115_200, split_frames=True)
    line.send(b"".join(frames), 10.0)
    byte_s = byte_time_s(115_200)
    times = []
    while (due := line.next_event_s()) is not None:
        times.append(due)
        assert line.take(due - 1e-9) == []
        (piece,) = line.take(due)
        assert piece == frames[len(times) - 1]
    assert times == pytest.approx([10.0 + 44 * k * byte_s for k in range(1, 7)])


def test_bytes_queue_behind_those_on_the_wire():
    line = SerialLine(57_600)
    byte_s = byte_time_s(57_600)
    line.send(b"a" * 100, 0.0)
    line.send(b"b" * 10, 50 * byte_s)  # written while the first is half through
    assert line.take(109.9 * byte_s) == [b"a" * 100]
    assert line.next_event_s() == pytest.approx(110 * byte_s)


def test_full_transmit_buffer_drops_whole_frames_and_counts_them():
    line = SerialLine(57_600, buffer_bytes=256)
    assert all(line.send(b"x" * 22, 0.0) for _ in range(11))  # 242 B queued
    assert not line.send(b"y" * 22, 0.0)  # 264 > 256: dropped, as comm_send_buffer does
    assert line.dropped == 1
    assert line.send(b"z" * 22, 22 * byte_time_s(57_600))  # one ACK's worth has left
    assert line.bytes_sent == 12 * 22


def test_splitter_follows_frames_across_chunks_signed_and_garbage():
    signed = command_frames(1, signed=True)[0]
    plain = command_frames(1)[0]
    assert len(signed) == len(plain) + 13
    stream = b"\x00\x11" + signed + plain
    splitter = FrameSplitter()
    cuts = splitter.cuts(stream[:5]) + [c + 5 for c in splitter.cuts(stream[5:])]
    assert cuts == [2 + len(signed), 2 + len(signed) + len(plain)]


def test_bad_baud_is_refused_naming_it():
    with pytest.raises(ValueError, match="baud=0 outside"):
        SerialLine(0)
