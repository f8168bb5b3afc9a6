"""Frames in and out of the links: faults on the way, signing, a serial stream split across
reads, and the link timing model through the autopilot (the model's own figures, no I/O)."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.config import LinkTimingConfig, SimConfig
from tests.sim_servo.autopilot.conftest import (
    COMPANION,
    KEY,
    WALL_S,
    Harness,
    acks,
    faulty,
    frame_source,
    routing_harness,
    wait_ack,
)


def test_drop_out_everything():
    h = faulty(drop_out=1.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert h.run_for(2.0) == []
    assert h.ap.stats["dropped_out"] >= 3 and h.ap.pwm_us[9] == 1600


def _drop_pattern(seed: int) -> list[bool]:
    h = faulty(drop_in=0.5, seed=seed)
    pattern = []
    for _ in range(40):
        before = h.ap.stats["dropped_in"]
        h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
        h.run_for(0.003)
        pattern.append(h.ap.stats["dropped_in"] > before)
    return pattern


def test_drops_are_reproducible_from_the_seed():
    first = _drop_pattern(7)
    assert first == _drop_pattern(7)
    assert first != _drop_pattern(8)
    assert 5 < sum(first) < 35


def test_corrupt_out_makes_every_frame_fail_its_check():
    h = faulty(corrupt_out=1.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    msgs = h.run_for(0.1)
    assert acks(msgs) == [] and h.of_type("HEARTBEAT", msgs) == []
    assert h.ap.stats["corrupted_out"] >= 2


def test_latency_and_jitter_delay_replies():
    h = faulty(latency_ms=50, jitter_ms=20, seed=3)
    h.run_for(0.0)
    delays = []
    for _ in range(20):
        h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
        sent = h.now
        h.run_for(0.2)
        ack_times = [t for t, m in h.received if m.get_type() == "COMMAND_ACK"]
        delays.append(ack_times[-1] - sent)
    assert all(0.030 - 1e-9 <= d <= 0.070 + 1e-9 for d in delays)
    assert max(delays) - min(delays) > 0.01


def test_signing_required_rejects_unsigned_and_signs_replies():
    config = SimConfig(signing_key=KEY)
    unsigned = Harness(config)
    unsigned.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert acks(unsigned.run_for(0.1)) == []
    assert unsigned.ap.stats["rejected_signature"] == 1 and unsigned.ap.pwm_us[9] == 0

    signed = Harness(config, signing_key=KEY)
    signed.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    ack = acks(signed.run_for(0.1))[0]
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert ack.get_signed() and signed.dec.signing.goodsig_count >= 1

    wrong = Harness(config, signing_key=bytes(32))
    wrong.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert acks(wrong.run_for(0.1)) == []


def own_timestamps(h: Harness) -> list[int]:
    """The signing timestamps of our own frames on link 0, in the order sent."""
    own = (h.config.system_id, h.config.component_id)
    return [
        int.from_bytes(f[-12:-6], "little")
        for _, ch, f in h.wire
        if ch == 0 and frame_source(f) == own and f[2] & 0x01
    ]


def test_signing_timestamp_follows_the_clock_and_adopts_newer_signed_incoming_ones():
    """The signing spec's "Timestamp Handling": our timestamp is at least the system clock's
    and moves up to a correctly signed incoming one. Without it, a companion restarted over a
    minute after the simulator booted refused every frame of ours, for ever."""
    h = Harness(SimConfig(signing_key=KEY), signing_key=KEY)
    h.run_for(5.0)
    wall_ticks = int((WALL_S - 1_420_070_400) * 100_000)
    assert own_timestamps(h)[-1] >= wall_ticks + 4 * 100_000  # 4 s of clock, not 4 frames
    # A companion restarted with its clock two minutes ahead of ours.
    ahead = own_timestamps(h)[-1] + 120 * 100_000
    h.gcs.signing.timestamp = ahead
    h.send(h.gcs.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 4))
    sent_before = len(own_timestamps(h))
    h.run_for(1.5)
    later = own_timestamps(h)[sent_before:]
    assert later and all(t >= ahead for t in later)
    assert later == sorted(later)
    # Such a companion (its own timestamp at `ahead`) takes our frames as a fresh stream.
    restarted = mavlink.MAVLink(None)
    restarted.signing.secret_key = KEY
    restarted.signing.timestamp = ahead
    own = (h.config.system_id, h.config.component_id)
    frames = [f for _, ch, f in h.wire if ch == 0 and frame_source(f) == own][sent_before:]
    assert all(restarted.parse_buffer(f) for f in frames)


def test_a_stream_split_across_reads_on_one_link_survives_frames_on_another():
    h, companion = routing_harness()
    frame = h.gcs.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[2] * 7).pack(h.gcs)
    other = companion.statustext_encode(6, b"hello").pack(companion)
    h.ap.receive(frame[:10], h.now, 1)
    h.ap.receive(other, h.now, 0)
    h.ap.receive(frame[10:], h.now, 1)
    h.run_for(0.01)
    assert sorted(h.forwarded()) == [(0, frame), (1, other)]
    assert h.ap.stats["bad_frames"] == 0


def _timed_harness(rng_seed: int = 0):
    h = Harness(link_timing=LinkTimingConfig())
    return h, np.random.default_rng(rng_seed)


def test_default_timing_a_lone_command_is_answered_hold_ms_after_it_arrived():
    h, rng = _timed_harness()
    hold_s = h.config.link_timing.hold_ms / 1000
    rtts = []
    for _ in range(40):
        h.run_for(rng.uniform(0.0, 0.02))  # a random phase of the 400 Hz loop
        sent = h.now
        h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
        rtts.append(wait_ack(h) - sent)
    assert rtts == pytest.approx([hold_s] * 40)
    sent = h.now
    for _ in range(6):  # six in sequence, each waiting for its ACK
        h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
        wait_ack(h)
    assert h.now - sent == pytest.approx(6 * hold_s)


def test_default_timing_a_burst_is_answered_faster_than_a_lone_command():
    h, rng = _timed_harness(1)
    timing = h.config.link_timing
    loop_s, delay_s = 1 / h.config.loop_rate_hz, timing.output_delay_ms / 1000
    totals = []
    for _ in range(60):
        h.run_for(rng.uniform(0.0, 0.02))
        sent = h.now
        for output in range(9, 15):
            h.command(mavlink.MAV_CMD_DO_SET_SERVO, output, 1500)
        wait_ack(h, 6)
        totals.append(h.now - sent)
    assert all(delay_s - 1e-9 <= t <= loop_s + delay_s + 1e-9 for t in totals)
    assert float(np.median(totals)) < timing.hold_ms / 1000
    assert all(a.result == mavlink.MAV_RESULT_ACCEPTED for a in h.of_type("COMMAND_ACK"))


def test_a_statustext_still_follows_its_ack_under_the_timing_model():
    h, _ = _timed_harness()
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 2, 1500)  # a motor: FAILED + STATUSTEXT
    kinds = [m.get_type() for m in h.run_for(0.1) if m.get_type() != "HEARTBEAT"]
    assert kinds == ["COMMAND_ACK", "STATUSTEXT"]
