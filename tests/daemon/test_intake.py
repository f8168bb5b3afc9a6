"""The intake in-process: bounded, the newest target wins, stop and park first, per-source
rate limits, everything answered once."""

from __future__ import annotations

import logging
import tracemalloc

from companion.daemon.intake import Intake, RefusalLog, TokenBucket
from companion.daemon.requests import Outcome, Reply, Request
from devkit.timing import FakeClock


def req(kind="goto", source=("mavlink", 255, 190), payload=(1, 2, 3, 0, 0, 0)) -> Request:
    return Request(kind, payload if kind == "goto" else None, source=source)


def outcome(request: Request) -> Outcome | None:
    return request.future.result().outcome if request.answered else None


def test_a_new_target_supersedes_a_waiting_one_which_is_cancelled_at_once():
    intake = Intake(clock=FakeClock())
    a, b = req(), req()
    intake.submit(a)
    intake.submit(b)
    assert outcome(a) is Outcome.CANCELLED and not b.answered
    assert intake.take() == [b] and b.taken.is_set()
    assert intake.take() == []


def test_stop_and_park_go_first_and_cancel_the_target_asked_before_them():
    intake = Intake(clock=FakeClock())
    goto, stop = req(), req("stop")
    intake.submit(goto)
    intake.submit(stop)
    assert outcome(goto) is Outcome.CANCELLED
    later = req()
    intake.submit(later)
    park = req("park")
    intake.submit(park)
    assert outcome(later) is Outcome.CANCELLED
    assert intake.take() == [stop, park]


def test_the_same_command_asked_again_while_waiting_gets_the_same_answer():
    intake = Intake(clock=FakeClock())
    stops = [req("stop") for _ in range(1000)]
    for stop in stops:
        intake.submit(stop)
    [leader] = intake.take()
    leader.answer(Reply(Outcome.ACCEPTED, "holding"))
    assert {outcome(s) for s in stops} == {Outcome.ACCEPTED}


def test_targets_over_a_sources_rate_are_rejected_and_other_sources_are_not():
    clock = FakeClock()
    intake = Intake(clock=clock, rate_hz=10.0, burst=5.0)
    flood = [req(source=("mavlink", 9, 9)) for _ in range(50)]
    for r in flood:
        intake.submit(r)
    rejected = [r for r in flood if outcome(r) is Outcome.TEMPORARILY_REJECTED]
    assert len(rejected) == 45 and "rate limited" in rejected[0].future.result().message
    other = req(source=("socket", 1))
    intake.submit(other)
    assert not other.answered  # (the flood's last allowed one was superseded by it)
    stop = req("stop", source=("mavlink", 9, 9))
    intake.submit(stop)
    assert not stop.answered  # stop is never rate limited
    clock.advance(1.0)
    late = req(source=("mavlink", 9, 9))
    intake.submit(late)
    assert not late.answered  # tokens came back


def test_rotating_system_ids_cannot_multiply_the_rate_limit():
    clock = FakeClock()
    intake = Intake(clock=clock, rate_hz=10.0, burst=5.0)
    # Each forged id is a new source with a full burst of its own; the input's bucket (twice a
    # source's: LINK_SHARE) is not.
    flood = [req(source=("mavlink", 1 + i % 250, 190)) for i in range(200)]
    for r in flood:
        intake.submit(r)
    rejected = [r for r in flood if outcome(r) is Outcome.TEMPORARILY_REJECTED]
    assert len(rejected) == 190
    assert "from all mavlink sources" in rejected[-1].future.result().message
    socket_side = req(source=("socket", 3))
    intake.submit(socket_side)
    assert outcome(socket_side) is not Outcome.TEMPORARILY_REJECTED  # another input's bucket
    clock.advance(1.0)
    honest = req(source=("mavlink", 255, 190))
    intake.submit(honest)
    assert outcome(honest) is not Outcome.TEMPORARILY_REJECTED  # tokens came back


def test_memory_stays_flat_under_a_flood_from_many_sources():
    clock = FakeClock()
    intake = Intake(clock=clock, max_sources=64)
    for i in range(2_000):  # warm up allocator caches
        intake.submit(req(source=("mavlink", i % 256, 1)))
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for i in range(10_000):
        intake.submit(req(source=("mavlink", i % 256, i % 7)))
        clock.advance(0.0002)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, "filename"))
    assert len(intake._buckets) <= 64
    assert grown < 200_000, grown


def test_withdraw_takes_back_a_waiting_request_only():
    intake = Intake(clock=FakeClock())
    a = req()
    intake.submit(a)
    assert intake.withdraw(a)
    assert intake.take() == []
    b = req()
    intake.submit(b)
    intake.take()
    assert not intake.withdraw(b)  # the control thread has it: its answer is on its way


def test_close_answers_what_waits_and_refuses_what_comes():
    intake = Intake(clock=FakeClock())
    waiting = [req(), req("stop")]
    for r in waiting:
        intake.submit(r)
    intake.close(
        Reply(Outcome.TEMPORARILY_REJECTED, "stopping"), Reply(Outcome.CANCELLED, "stopping")
    )
    assert {outcome(r) for r in waiting} == {Outcome.CANCELLED}
    late = req("stop")
    intake.submit(late)
    assert outcome(late) is Outcome.TEMPORARILY_REJECTED


def test_token_bucket():
    bucket = TokenBucket(rate_hz=2.0, burst=2.0, now_s=0.0)
    assert [bucket.take(0.0) for _ in range(3)] == [True, True, False]
    assert bucket.take(0.5) and not bucket.take(0.5)


def test_refusals_are_logged_as_a_summary(caplog):
    clock = FakeClock()
    refusals = RefusalLog(clock=clock, interval_s=10.0)
    with caplog.at_level(logging.INFO, logger="armbridge"):
        for _ in range(5_000):
            refusals.note("goto", Outcome.TEMPORARILY_REJECTED, "rate limited")
        clock.advance(10.0)
        refusals.note("goto", Outcome.CANCELLED, "superseded")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2
    assert "5000 requests refused" in lines[1] and "4999 goto temporarily_rejected" in lines[1]


def test_a_stop_cancels_a_park_or_resume_asked_before_it():
    # The last word is the stop's: a resume taken after it would move the arm it stopped.
    intake = Intake(clock=FakeClock())
    park, resume, stop = req("park", ("socket", 1)), req("resume", ("socket", 1)), req("stop")
    for request in (park, resume, stop):
        intake.submit(request)
    assert outcome(park) is outcome(resume) is Outcome.CANCELLED
    later = req("resume", ("socket", 1))
    intake.submit(later)
    assert intake.take() == [stop, later]


def test_a_resume_joins_only_one_from_the_same_input():
    # A resume from the link may be refused where one from the companion is not.
    intake = Intake(clock=FakeClock())
    link = [req("resume") for _ in range(3)]
    socket = req("resume", ("socket", 2))
    for request in (*link, socket):
        intake.submit(request)
    assert intake.take() == [link[0], socket]
