"""Target payloads: the mode and frame of a MAVLink USER_1, the socket's and the CLI's."""

import math

import pytest

from companion.daemon.requests import as_target, mavlink_target_payload


@pytest.mark.parametrize(
    ("param7", "mode", "frame"),
    [
        (0, "pose", "base"),
        (2, "position_axis", "base"),
        (16, "pose", "local_ned"),
        (17, "position", "local_ned"),
        (18, "position_axis", "local_ned"),
    ],
)
def test_user1_param7_says_the_target_mode_and_frame(param7, mode, frame):
    target = as_target(mavlink_target_payload((1, 2, 3, 0, 0, 0), float(param7)))
    assert (target.mode, target.frame) == (mode, frame)


@pytest.mark.parametrize("param7", [3.0, 15.0, 19.0, -1.0, 16.5, math.nan])
def test_user1_param7_unknown_is_refused_naming_it(param7):
    with pytest.raises(ValueError, match="param7"):
        as_target(mavlink_target_payload((1, 2, 3, 0, 0, 0), param7))


def test_an_unknown_frame_is_refused_naming_it():
    with pytest.raises(ValueError, match="frame='ecef'"):
        as_target({"pose": (1, 2, 3, 0, 0, 0), "frame": "ecef"})


def test_a_trajectory_out_of_order_or_too_long_is_refused_not_sorted():
    from companion.daemon.requests import MAX_TRAJECTORY_POINTS, parse_trajectory

    pose = [60, 10, 5, 0, 20, 10]
    assert [t for t, _ in parse_trajectory([(0, pose), (0.5, pose)])] == [0.0, 0.5]
    with pytest.raises(ValueError, match=r"point 1: t_s = 0.5 after 1: times must not go back"):
        parse_trajectory([(1, pose), (0.5, pose)])
    assert len(parse_trajectory([(1, pose), (1, pose)])) == 2  # at once: the last one wins
    too_long = [(i, pose) for i in range(MAX_TRAJECTORY_POINTS + 1)]
    with pytest.raises(ValueError, match=f"at most {MAX_TRAJECTORY_POINTS}"):
        parse_trajectory(too_long)
