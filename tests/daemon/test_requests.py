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
