"""The pose file (``companion/daemon/pose_file.py``): where the outputs were left, for the next
start."""

from __future__ import annotations

import json
import logging

from companion.daemon import pose_file
from companion.daemon.config import parse_config
from tests.daemon.core.rig import PARK, Rig

CONFIG = parse_config({"link": {"url": "udpout:127.0.0.1:14550"}})
CALIBRATION = CONFIG.calibration


def test_what_is_saved_at_rest_is_loaded_at_the_next_start(tmp_path):
    path = str(tmp_path / "pose.json")
    saver = pose_file.PoseSaver(path, 0.0)
    pwm = dict.fromkeys(CALIBRATION.outputs, 1600)
    saver.offer(None, 5.0)  # moving: nothing written
    assert pose_file.load(path, CALIBRATION) is None
    saver.offer(pwm, 5.0)
    assert pose_file.load(path, CALIBRATION) == pwm
    saver.offer({**pwm, 9: 1700}, 5.5)  # within a second of the last write: not yet
    assert pose_file.load(path, CALIBRATION) == pwm
    saver.offer({**pwm, 9: 1700}, 6.1)
    assert pose_file.load(path, CALIBRATION)[9] == 1700


def test_a_file_that_does_not_match_the_config_is_set_aside(tmp_path, caplog):
    path = tmp_path / "pose.json"
    good = {str(o): 1500 for o in CALIBRATION.outputs}
    cases = [
        b"not json",
        json.dumps({"pwm_us": {**good, "9": 2500}}).encode(),  # outside the range
        json.dumps({"pwm_us": {"1": 1500}}).encode(),  # other outputs
        json.dumps({"pwm_us": {**good, "9": 1500.5}}).encode(),
        json.dumps({"pwm_us": [1500]}).encode(),
        b"[" * 5000,
    ]
    with caplog.at_level(logging.WARNING, logger="armbridge"):
        for raw in cases:
            path.write_bytes(raw)
            assert pose_file.load(str(path), CALIBRATION) is None
    assert sum("set aside" in r.getMessage() for r in caplog.records) == len(cases)


def test_a_file_that_cannot_be_written_is_said_once(tmp_path, caplog):
    saver = pose_file.PoseSaver(str(tmp_path / "no-such-dir" / "pose.json"), 0.0)
    with caplog.at_level(logging.WARNING, logger="armbridge"):
        saver.offer(dict.fromkeys(CALIBRATION.outputs, 1500), 5.0)
        saver.offer(dict.fromkeys(CALIBRATION.outputs, 1600), 7.0)
    assert sum("not written" in r.getMessage() for r in caplog.records) == 1


def test_the_core_starts_where_the_outputs_were_left_unless_a_readback_shows_them():
    # ArduPilot after a reboot shows no pulses: the restored pose is where the first step
    # starts from, not the park pose (a restarted daemon's first goto jumped from park).
    rig = Rig()
    left = {o: 1700 for o in CALIBRATION.outputs}
    rig.core.restore_pose(left)
    rig.up()
    angles = [CALIBRATION.for_output(o).pwm_us_to_angle_deg(1700) for o in CALIBRATION.outputs]
    assert rig.core.status()["current_deg"] == angles != list(PARK)
    rig.readback({CALIBRATION.outputs[0]: 1500})  # a readback that shows one: it wins
    assert rig.core.status()["current_deg"][0] == CALIBRATION.for_output(9).pwm_us_to_angle_deg(
        1500
    )
