"""The JSON-lines event log."""

import json

import pytest

from sim_servo.config import MountConfig, VehicleConfig
from sim_servo.errors import SimIOError
from sim_servo.eventlog import (
    EventLog,
    WorldSample,
    physical_pwm_timeline,
    read_events,
    world_timeline,
)
from sim_servo.hover import HoverDisturbance
from sim_servo.world import WorldPose


def test_lines_are_json_and_flushed(tmp_path):
    path = tmp_path / "events.jsonl"
    log = EventLog(path, keep=2)
    log({"t_s": 0.0, "event": "start"})
    log({"t_s": 0.5, "event": "servo", "output": 9, "pwm_us": 1500})
    log.flush()  # the server's, once per loop pass
    assert read_events(path)[1]["pwm_us"] == 1500  # readable before close
    log({"t_s": 1.0, "event": "stop", "odd": b"bytes"})
    log.close()
    lines = path.read_text().splitlines()
    assert [json.loads(line)["event"] for line in lines] == ["start", "servo", "stop"]
    assert [e["event"] for e in log.recent] == ["servo", "stop"]


def test_memory_only_and_bad_path(tmp_path):
    log = EventLog(None)
    log({"t_s": 0, "event": "x"})
    assert len(log.recent) == 1
    log.close()
    with pytest.raises(SimIOError, match="cannot open event log"):
        EventLog(tmp_path / "no" / "such" / "dir.jsonl")


def test_physical_pwm_timeline_from_the_log():
    events = [
        {"t_s": 0.0, "event": "start", "outputs_us": {"9": 1000, "10": 1000}},
        {"t_s": 0.5, "event": "servo", "output": 9, "pwm_us": 1700},
        {"t_s": 1.0, "event": "output", "output": 9, "pwm_us": 1700, "from_us": 1000},
        {"t_s": 2.0, "event": "output", "output": 9, "pwm_us": 1000, "from_us": 1700},
    ]
    timeline = physical_pwm_timeline(events)
    assert timeline == {9: [(0.0, 1000), (1.0, 1700), (2.0, 1000)], 10: [(0.0, 1000)]}
    with pytest.raises(ValueError, match="output 9: event at t_s=3.0 goes from 1500"):
        physical_pwm_timeline(
            [*events, {"t_s": 3.0, "event": "output", "output": 9, "pwm_us": 1, "from_us": 1500}]
        )


def test_world_timeline_from_the_vehicle_events():
    vehicle = HoverDisturbance.from_config(VehicleConfig(seed=2)).state(0.5)
    hand = WorldPose(1.0, 0.0, -1.5, 0.0, 0.1, 0.2)
    events = [
        {"t_s": 0.0, "event": "start", "vehicle": VehicleConfig(seed=2).as_dict()},
        {"t_s": 0.5, "event": "vehicle", "vehicle": vehicle.as_dict(), "hand_ned": hand.as_dict()},
        {"t_s": 0.6, "event": "output", "output": 9, "pwm_us": 1700, "from_us": 1000},
        {"t_s": 0.7, "event": "vehicle", "vehicle": vehicle.as_dict(), "hand_ned": None},
    ]
    # Through JSON, as a bench reads the file.
    timeline = world_timeline(json.loads(json.dumps(events)))
    assert timeline == [WorldSample(0.5, vehicle, hand), WorldSample(0.7, vehicle, None)]
    # The start event's settings rebuild the same motion.
    rebuilt = HoverDisturbance.from_config(VehicleConfig(**{
        **events[0]["vehicle"], "mount": MountConfig(**events[0]["vehicle"]["mount"])
    }))  # fmt: skip
    assert rebuilt.state(0.5) == vehicle


def test_a_log_read_while_it_is_written_yields_only_whole_lines(tmp_path):
    # Seen in CI: a test read the log while the simulator's write of a pass was half through
    # the file's buffer, and the last line was cut (JSONDecodeError).
    path = tmp_path / "events.jsonl"
    path.write_text('{"t_s":0.1,"event":"start"}\n{"t_s":0.2,"event":"rx","ms')
    assert read_events(path) == [{"t_s": 0.1, "event": "start"}]
