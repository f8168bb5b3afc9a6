"""Status (``core/status.py``): the snapshot and the accepted-log lines."""

from __future__ import annotations

import logging

import pytest

from companion.daemon.core.status import source_name
from companion.daemon.requests import Outcome, Request
from tests.daemon.core.rig import PARK, Rig, near


def test_a_stream_of_targets_logs_one_accepted_line_a_second_per_source(rig, caplog):
    # Each target carried out is logged; at 50 Hz a line each would be 180 000 journal lines
    # an hour on an SD card: one line a second per source, saying how many it stands for.
    caplog.set_level(logging.INFO, logger="armbridge")
    gcs = ("mavlink", 255, 190)
    kept = []  # alive: the rig files answers by id()
    for k in range(20):
        request = rig.request("goto", near(PARK, 0.2 * (k % 2)), source=gcs)
        kept.append(request)
        rig.ack_all(rig.sent)
        rig.sent.clear()
        assert rig.reply(request).outcome is Outcome.ACCEPTED
        rig.clock.advance(0.02)
    rig.request("goto", near(PARK), source=("socket", 3))  # another source: its own line
    rig.ack_all(rig.sent)
    rig.clock.advance(1.0)
    rig.request("goto", near(PARK, 0.2), source=gcs)
    rig.ack_all(rig.sent)
    rig.request("stop", source=gcs)  # never thinned out
    lines = [r.getMessage() for r in caplog.records if " accepted: " in r.getMessage()]
    assert len(lines) == 4, lines
    assert lines[0].startswith("goto (") and "from mavlink 255/190 accepted: moving" in lines[0]
    assert "from socket 3 accepted" in lines[1]
    assert lines[2].endswith("(and 19 more since the last line)")
    assert lines[3].startswith("stop from mavlink 255/190 accepted")


def test_a_log_line_names_who_asked():
    assert source_name(Request("goto", None, source=("mavlink", 255, 190))) == "mavlink 255/190"
    assert source_name(Request("goto", None, source=("socket", 3))) == "socket 3"


def test_before_any_ack_status_holds_nothing_acknowledged_and_the_assumed_start_pose():
    rig = Rig()  # the link never came up
    status = rig.core.status()
    assert status["current_deg"] == list(PARK) and status["last_pwm_us"] is None
    assert status["autopilot"] is None and status["holding"] is False
    assert {o["state"] for o in status["outputs"].values()} == {"unknown"}
    assert status["moving"] is False and status["goal_deg"] is None
    # The cheap subset the service publishes each step agrees with it.
    assert rig.core.link_and_outcome_counts() == (False, 0, 0, 0)


@pytest.mark.parametrize("dialect", ["ardupilot", "px4"])
def test_outputs_are_not_said_live_before_an_autopilot_was_heard_or_while_its_link_is_down(dialect):
    rig = Rig(dialect=dialect)
    status = rig.core.status()
    assert status["outputs_live"] is False
    assert "no autopilot heard" in status["not_live"]["9"]
    rig.up()
    rig.tick(link_up=False)
    status = rig.core.status()
    assert status["outputs_live"] is False
    assert "link down" in status["not_live"]["9"]


def test_the_last_target_says_its_answer(rig):
    request = rig.goto(near(PARK))
    assert rig.core.status()["last_target"]["outcome"] is None  # not answered yet
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    last = rig.core.status()["last_target"]
    assert last["outcome"] == "accepted" and last["answer"] == "moving"
