"""The link budget: bytes per update x rate against a serial line, and which dialect fits."""

from __future__ import annotations

import pytest

from firmware_interface.calibration import calibration_from_ranges, default_calibration
from firmware_interface.errors import ConfigurationError, InvalidUrl
from firmware_interface.link_budget import link_budget, update_cost

CAL = default_calibration()


def test_frame_sizes_are_the_issues():
    ardupilot = update_cost("ardupilot", CAL, 115_200)
    lua = update_cost("ardupilot-lua", CAL, 115_200)
    px4 = update_cost("px4", CAL, 115_200)
    assert (ardupilot.frames, ardupilot.to_fc_bytes, ardupilot.ack_bytes) == (6, 264, 22)
    assert (lua.frames, lua.to_fc_bytes, lua.ack_bytes) == (1, 44, 22)
    assert (px4.frames, px4.to_fc_bytes) == (1, 44)
    # 264 B at 115 200 baud, 8N1: 22.9 ms; plus the last ACK (22 B, 1.9 ms).
    assert ardupilot.wire_ms == pytest.approx(22.9 + 1.9, abs=0.05)
    assert lua.median_ms == pytest.approx(3.8 + 1.9 + 8.9, abs=0.05)
    signed = update_cost("ardupilot", CAL, 115_200, signed=True)
    assert (signed.to_fc_bytes, signed.ack_bytes) == (264 + 6 * 13, 22 + 13)


def test_115200_at_50_hz_ardupilot_does_not_fit_and_lua_would():
    budget = link_budget("/dev/ttyAMA0,115200", "ardupilot", CAL, 50.0)
    assert not budget.fits and budget.alternatives == ("ardupilot-lua",)
    assert "does not fit control.rate_hz=50" in budget.message
    assert "dialect = 'ardupilot-lua'" in budget.message
    assert link_budget("serial:///dev/ttyAMA0?baud=115200", "ardupilot-lua", CAL, 50.0).fits


def test_57600_at_50_hz_nothing_fits_and_the_message_says_what_to_change():
    budget = link_budget("/dev/ttyS1,57600", "ardupilot", CAL, 50.0)
    assert not budget.fits and budget.alternatives == ()
    assert "lower control.rate_hz or raise the baud rate" in budget.message
    assert link_budget("/dev/ttyS1,57600", "ardupilot-lua", CAL, 20.0).fits
    assert not link_budget("/dev/ttyS1,57600", "ardupilot", CAL, 20.0).fits


def test_921600_everything_fits_and_network_links_have_no_byte_budget():
    for dialect in ("ardupilot", "ardupilot-lua", "px4"):
        assert link_budget("/dev/ttyACM0,921600", dialect, CAL, 50.0).fits
    udp = link_budget("udpout:127.0.0.1:14550", "ardupilot", CAL, 50.0)
    assert udp.fits and udp.baud is None and "no serial byte budget" in udp.message


def test_alternatives_are_the_same_autopilots_only():
    budget = link_budget("/dev/ttyS1,57600", "px4", CAL, 200.0)
    assert not budget.fits and set(budget.costs) == {"px4"}


def test_seven_joints_skip_px4_and_take_two_lua_frames():
    seven = calibration_from_ranges([(-90, 90)] * 7, outputs=range(8, 15))
    assert update_cost("ardupilot-lua", seven, 57_600).frames == 2
    budget = link_budget("/dev/ttyS1,57600", "ardupilot", seven, 10.0)
    assert set(budget.costs) == {"ardupilot", "ardupilot-lua"}


def test_bad_input_is_refused_naming_it():
    with pytest.raises(ConfigurationError, match="rate_hz=0"):
        link_budget("/dev/ttyS1,57600", "ardupilot", CAL, 0)
    with pytest.raises(ConfigurationError, match="unknown servo dialect 'inav'"):
        link_budget("/dev/ttyS1,57600", "inav", CAL, 20.0)
    with pytest.raises(InvalidUrl):
        link_budget("/dev/ttyS1", "ardupilot", CAL, 20.0)
