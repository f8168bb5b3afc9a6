"""The settings derived from the config (``core/settings.py``), and a reload that changes
them."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.daemon.core.rig import Rig


@pytest.mark.parametrize(
    ("url", "dialect", "interval_s"),
    [
        ("/dev/ttyAMA0,115200", "ardupilot-lua", 1.0),  # status only: spare the slow line
        ("/dev/ttyAMA0,921600", "ardupilot", 0.1),
        ("/dev/ttyAMA0,57600", "px4", 0.1),  # PX4's liveness comes from it
        ("udpin:0.0.0.0:14550", "px4", 0.02),  # room for it: a disarm seen sooner
    ],
)
def test_the_readback_is_asked_for_less_often_where_it_only_feeds_status_on_a_slow_line(
    url, dialect, interval_s
):
    rig = Rig(dialect=dialect, url=url)
    autopilot = (
        mavlink.MAV_AUTOPILOT_PX4 if dialect == "px4" else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    )
    rig.heartbeat(autopilot=autopilot)
    rig.tick()
    [ask] = [
        c
        for c in rig.sent
        if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
        and c.params[0] == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
    ]
    assert ask.params[1] == pytest.approx(interval_s * 1e6)
