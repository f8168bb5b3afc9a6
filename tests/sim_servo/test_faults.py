"""Seeded fault decisions."""

import math

import numpy as np

from sim_servo.config import FaultConfig
from sim_servo.faults import FaultInjector, HangupSchedule


def test_off_by_default_and_rng_untouched():
    rng = np.random.default_rng(1)
    faults = FaultInjector(FaultConfig(), rng)
    assert not faults.drop_in() and not faults.drop_out()
    assert faults.corrupt_out(b"abc") == b"abc" and faults.delay_s() == 0.0
    assert rng.random() == np.random.default_rng(1).random()  # nothing was drawn


def test_same_seed_same_faults():
    config = FaultConfig(drop_out=0.3, corrupt_out=0.3, jitter_ms=5, latency_ms=5, seed=11)

    def run():
        faults = FaultInjector(config)
        return [
            (faults.drop_out(), faults.corrupt_out(b"0123456789"), faults.delay_s())
            for _ in range(50)
        ]

    assert run() == run()


def test_corruption_always_changes_exactly_one_byte():
    faults = FaultInjector(FaultConfig(corrupt_in=1.0, seed=2))
    for _ in range(100):
        data = bytes(range(20))
        corrupted = faults.corrupt_in(data)
        assert sum(a != b for a, b in zip(data, corrupted, strict=True)) == 1


def test_drop_rate_close_to_probability():
    faults = FaultInjector(FaultConfig(drop_in=0.2, seed=5))
    rate = sum(faults.drop_in() for _ in range(5000)) / 5000
    assert 0.17 < rate < 0.23


def test_delay_within_latency_plus_minus_jitter_never_negative():
    faults = FaultInjector(FaultConfig(latency_ms=2, jitter_ms=5, seed=3))
    delays = [faults.delay_s() for _ in range(1000)]
    assert min(delays) == 0.0 and max(delays) <= 0.007


def test_hangup_schedule_hangs_up_once_and_reopens_once():
    schedule = HangupSchedule(100.0, hangup_after_s=2.0, hangup_for_s=3.0)
    assert schedule.next_s() == 102.0 and schedule.due(101.9) == []
    assert schedule.due(102.0) == [HangupSchedule.HANGUP]
    assert schedule.next_s() == 105.0 and schedule.due(104.0) == []
    assert schedule.due(110.0) == [HangupSchedule.REOPEN]
    assert schedule.due(200.0) == [] and schedule.next_s() == math.inf
    late = HangupSchedule(0.0, hangup_after_s=1.0, hangup_for_s=0.5)
    assert late.due(9.0) == [HangupSchedule.HANGUP, HangupSchedule.REOPEN]  # in order
    assert HangupSchedule(0.0, hangup_after_s=1.0).due(1e9) == [HangupSchedule.HANGUP]
    assert HangupSchedule(0.0, None).next_s() == math.inf


def test_an_on_demand_hangup_replaces_the_scheduled_one_and_not_while_away():
    schedule = HangupSchedule(0.0, hangup_after_s=50.0, hangup_for_s=3.0)
    assert schedule.hang_up_now(10.0)
    assert schedule.due(10.0) == [HangupSchedule.HANGUP]
    assert not schedule.hang_up_now(11.0)  # the port is away
    assert schedule.due(12.9) == [] and schedule.due(13.0) == [HangupSchedule.REOPEN]
    assert schedule.due(100.0) == []  # the scheduled hang-up at 50 s was replaced
    assert schedule.hang_up_now(100.0) and schedule.due(100.0) == [HangupSchedule.HANGUP]
    for_good = HangupSchedule(0.0, None)
    assert for_good.hang_up_now(1.0) and for_good.due(1.0) == [HangupSchedule.HANGUP]
    assert not for_good.hang_up_now(2.0) and for_good.next_s() == math.inf
