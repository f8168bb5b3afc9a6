"""One link's outgoing side (the delay-and-hold model), driven with plain numbers."""

import pytest

from sim_servo.config import LinkTimingConfig
from sim_servo.linktiming import LinkOutput

D_MS, H_MS = 1.0, 5.0
MODEL = LinkTimingConfig(output_delay_ms=D_MS, hold_ms=H_MS, burst_frames=2)


def out_times(link: LinkOutput, until_s: float) -> list[tuple[float, bytes]]:
    """Step through every event of ``link`` up to ``until_s``: (time, frame) as they leave."""
    left = []
    now = 0.0
    while (due := link.next_event_s()) is not None and due <= until_s:
        now = max(now, due)
        left += [(round(now, 9), frame) for frame in link.take(now)]
    return left


def test_a_lone_answer_leaves_hold_ms_after_the_frame_it_answers_arrived():
    link = LinkOutput(MODEL)
    link.arrived(1, 0.0)  # the command
    link.write(b"ack", 0.0017)  # handled on the next main-loop pass
    assert out_times(link, 1.0) == [(pytest.approx(H_MS / 1000), b"ack")]


def test_without_input_a_frame_is_held_hold_ms_after_its_delay():
    link = LinkOutput(MODEL)
    link.write(b"heartbeat", 2.0)
    assert out_times(link, 3.0) == [(pytest.approx(2.0 + (D_MS + H_MS) / 1000), b"heartbeat")]


def test_the_next_frame_from_the_link_flushes_what_is_held():
    link = LinkOutput(MODEL)
    link.write(b"a", 0.0)
    link.write(b"b", 0.0005)
    assert link.take(0.002) == []  # ready at 1 ms and 1.5 ms, held
    link.arrived(1, 0.003)
    assert link.take(0.003) == [b"a", b"b"]


def test_a_burst_releases_every_answer_in_its_window_at_once():
    link = LinkOutput(MODEL)
    link.arrived(6, 0.0)  # six commands in one read
    for k in range(6):
        link.write(b"ack%d" % k, 0.002)
    times = out_times(link, 1.0)
    assert [f for _, f in times] == [b"ack%d" % k for k in range(6)]
    assert [t for t, _ in times] == pytest.approx([0.002 + D_MS / 1000] * 6)


def test_frames_arriving_one_at_a_time_count_towards_the_burst():
    link = LinkOutput(MODEL)
    link.arrived(1, 0.0)
    link.arrived(1, 0.0001)  # the second frame of the window: answers go at once
    link.write(b"ack", 0.001)
    assert out_times(link, 1.0) == [(pytest.approx(0.002), b"ack")]


def test_the_window_closes_hold_ms_after_its_first_frame():
    link = LinkOutput(MODEL)
    link.arrived(1, 0.0)  # e.g. the peer's heartbeat, unanswered
    link.arrived(1, 0.006)  # after the window closed: a new window, not a burst
    link.write(b"ack", 0.007)
    assert out_times(link, 1.0) == [(pytest.approx(0.011), b"ack")]


def test_a_frame_after_the_window_was_answered_opens_a_new_window():
    link = LinkOutput(MODEL)
    link.arrived(6, 0.0)
    link.write(b"acks", 0.001)  # a burst: leaves at 2 ms, answering the window
    assert out_times(link, 0.002) == [(pytest.approx(0.002), b"acks")]
    link.arrived(6, 0.0045)  # the next burst, while the first window (to 5 ms) is still open
    link.write(b"more", 0.0055)
    # Its own window is a burst too: out at once, not held past the old window's end.
    assert out_times(link, 1.0) == [(pytest.approx(0.0065), b"more")]


def test_the_latency_fault_adds_to_the_delay():
    link = LinkOutput(LinkTimingConfig(output_delay_ms=1.0, hold_ms=0.0))
    link.write(b"x", 0.0, extra_delay_s=0.05)
    assert out_times(link, 1.0) == [(pytest.approx(0.051), b"x")]


def test_instant_sends_at_once_in_order():
    link = LinkOutput(LinkTimingConfig.instant())
    link.arrived(1, 0.0)
    for frame in (b"1", b"2", b"3"):
        link.write(frame, 0.5)
    assert link.next_event_s() == 0.5
    assert link.take(0.5) == [b"1", b"2", b"3"]
    assert link.next_event_s() is None


def test_clear_forgets_frames_and_the_window():
    link = LinkOutput(MODEL)
    link.arrived(3, 0.0)
    link.write(b"lost", 0.0)
    link.clear()
    assert link.pending == 0 and link.next_event_s() is None
    link.write(b"after", 0.001)  # no burst window left: held hold_ms after its delay
    assert out_times(link, 1.0) == [(pytest.approx(0.001 + (D_MS + H_MS) / 1000), b"after")]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"hold_ms": -1}, "link_timing.hold_ms: -1 outside [0, 1000]"),
        (
            {"output_delay_ms": float("nan")},
            "link_timing.output_delay_ms: must be a finite number, got nan",
        ),
        ({"burst_frames": 0}, "link_timing.burst_frames: 0 outside [1, 1000]"),
    ],
)
def test_config_validation_names_field_and_range(kwargs, message):
    from sim_servo.errors import SimConfigError

    with pytest.raises(SimConfigError) as info:
        LinkTimingConfig(**kwargs)
    assert message in str(info.value)
