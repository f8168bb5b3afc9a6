"""The pose file (``companion/daemon/pose_file.py``): where the outputs were left, for the next
start."""

from __future__ import annotations

import json
import logging

from companion.daemon import pose_file
from companion.daemon.config import parse_config
from tests.daemon.core.rig import PARK, Rig, px4_rig, run

CONFIG = parse_config({"link": {"url": "udpout:127.0.0.1:14550"}})
CALIBRATION = CONFIG.calibration


def test_what_is_offered_is_written_and_loaded_at_the_next_start(tmp_path):
    path = str(tmp_path / "pose.json")
    saver = pose_file.PoseSaver(path)
    low = dict.fromkeys(CALIBRATION.outputs, 1600)
    saver.offer(None)  # nothing new: nothing written
    saver.offer((low, {**low, 9: 1620}))
    saver.offer((low, {**low, 9: 1640}))  # the latest wins
    saver.close()
    assert pose_file.load(path, CALIBRATION) == (low, {**low, 9: 1640})


def test_a_file_of_one_pwm_per_output_is_that_band(tmp_path):
    path = tmp_path / "pose.json"
    path.write_text(json.dumps({"pwm_us": {str(o): 1600 for o in CALIBRATION.outputs}}))
    left = pose_file.load(str(path), CALIBRATION)
    assert left is not None and pose_file.same_everywhere(left)
    assert pose_file.pose_of(left) == dict.fromkeys(CALIBRATION.outputs, 1600)


def test_a_file_that_does_not_match_the_config_is_set_aside(tmp_path, caplog):
    path = tmp_path / "pose.json"
    good = {str(o): 1500 for o in CALIBRATION.outputs}
    cases = [
        b"not json",
        json.dumps({"pwm_us": {**good, "9": 2500}}).encode(),  # outside the range
        json.dumps({"pwm_us": {"1": 1500}}).encode(),  # other outputs
        json.dumps({"pwm_us": {**good, "9": 1500.5}}).encode(),
        json.dumps({"pwm_us": [1500]}).encode(),
        json.dumps({"pwm_us": good, "low_us": {**good, "9": 1600}}).encode(),  # low above
        json.dumps([1500]).encode(),
        b"[" * 5000,
    ]
    with caplog.at_level(logging.WARNING, logger="armbridge"):
        for raw in cases:
            path.write_bytes(raw)
            assert pose_file.load(str(path), CALIBRATION) is None
    assert sum("set aside" in r.getMessage() for r in caplog.records) == len(cases)


def test_a_file_that_cannot_be_written_is_said_once(tmp_path, caplog):
    saver = pose_file.PoseSaver(str(tmp_path / "no-such-dir" / "pose.json"))
    with caplog.at_level(logging.WARNING, logger="armbridge"):
        for pwm in (1500, 1600):
            pwm_by_output = dict.fromkeys(CALIBRATION.outputs, pwm)
            saver.offer((pwm_by_output, pwm_by_output))
        saver.close()
    assert sum("not written" in r.getMessage() for r in caplog.records) == 1


def test_the_core_starts_where_the_outputs_were_left_unless_a_readback_shows_them():
    # ArduPilot after a reboot shows no pulses: the restored pose is where the first step
    # starts from, not the park pose (a restarted daemon's first goto jumped from park).
    rig = Rig()
    left = {o: 1700 for o in CALIBRATION.outputs}
    rig.core.restore_pose((left, left))
    rig.up()
    angles = [CALIBRATION.for_output(o).pwm_us_to_angle_deg(1700) for o in CALIBRATION.outputs]
    assert rig.core.status()["current_deg"] == angles != list(PARK)
    for _ in range(3):  # readbacks that show one (over an interval, the clock after): they win
        rig.readback({CALIBRATION.outputs[0]: 1500})
        rig.clock.advance(0.02)
    rig.system_time(600_000)
    rig.readback({CALIBRATION.outputs[0]: 1500})
    assert rig.core.status()["current_deg"][0] == CALIBRATION.for_output(9).pwm_us_to_angle_deg(
        1500
    )


def test_a_band_restored_is_re_sent_at_its_middle_before_the_first_targets_steps():
    # A daemon killed mid-motion left the outputs between two steps: the next one re-sends
    # the middle (within half the band of where they are), then steps from there.
    rig = Rig()
    low = {o: 1600 for o in CALIBRATION.outputs}
    high = {o: 1630 for o in CALIBRATION.outputs}
    rig.core.restore_pose((low, high))
    rig.up()
    assert rig.servo() == {}  # nothing before a target
    rig.goto(PARK)
    rig.tick()
    assert rig.servo() == dict.fromkeys(CALIBRATION.outputs, 1615)


def test_the_band_written_holds_the_acknowledged_pose_and_the_step_on_its_way():
    rig = Rig()
    rig.up()
    assert rig.core.outputs_left() is None  # nothing sent: the file keeps what it says
    rig.goto([q + 30.0 for q in PARK])
    rig.tick()
    first = rig.servo()
    low, high = rig.core.outputs_left()
    park = rig.core.status()["current_deg"]
    park_us = {
        o: CALIBRATION.for_output(o).angle_to_pwm_us(park[i])
        for i, o in enumerate(CALIBRATION.outputs)
    }
    for output in CALIBRATION.outputs:
        assert {low[output], high[output]} == {park_us[output], first[output]}
    assert first != park_us
    rig.ack_all(rig.sent)
    low, high = rig.core.outputs_left()  # the switch may have gone on before the step
    assert {low[9], high[9]} == {park_us[9], first[9]}
    rig.clock.advance(0.02)
    rig.sys_status(safety_on=False)  # it did not (an "off" that left the autopilot after it)
    low, high = rig.core.outputs_left()
    assert low == high == first


def test_joints_placed_by_readbacks_are_saved_before_anything_is_sent():
    # PX4 showed another sender's 1900 us for seconds while this daemon sent nothing; the
    # file kept an earlier daemon's pose, and a daemon started after the outputs went back to
    # PX4 SITL's disarmed 900 us (which says nothing of where a joint is) moved from that pose:
    # 89 deg in one command.
    rig, px4 = px4_rig(disarmed_us=900)
    px4.set_live(True)
    for output in CALIBRATION.outputs:
        px4.foreign_store(output, 1900)
    for _ in range(6):  # readbacks at 50 Hz, the control thread not ticking yet
        px4.readback()
        rig.clock.advance(0.02)
    assert rig.core.counters["servo_updates"] == 0
    left = rig.core.outputs_left()
    assert left == (dict.fromkeys(CALIBRATION.outputs, 1900),) * 2
    px4.set_live(False)  # 900 us: the file keeps where the joints were shown (or a marker)
    run(rig, px4, 0.5)
    low, high = rig.core.outputs_left()
    assert all(1900 - 2 <= low[o] <= high[o] <= 1900 + 2 for o in CALIBRATION.outputs)


def test_a_band_restored_stays_in_the_file_until_the_outputs_are_sent_to_it():
    # A daemon restarted while ArduPilot's safety switch held the outputs somewhere in a band
    # sent nothing; readbacks placed one joint (another sender's command), and the file it
    # wrote held the band's middle alone for the others. After a reboot the next daemon stepped
    # from that middle: 7 deg from where the switch had held a joint (bench.state_cycles).
    rig = Rig()
    low = dict.fromkeys(CALIBRATION.outputs, 1600)
    high = dict.fromkeys(CALIBRATION.outputs, 1630)
    rig.core.restore_pose((low, high))
    rig.heartbeat()
    rig.tick()
    rig.sys_status(safety_on=True)
    first = CALIBRATION.outputs[0]
    for _ in range(3):
        rig.readback({first: 1800})
        rig.clock.advance(0.02)
    rig.system_time(600_000)
    rig.readback({first: 1800})
    left_low, left_high = rig.core.outputs_left()
    assert left_low[first] == left_high[first] == 1800  # where the readbacks show it
    for output in CALIBRATION.outputs[1:]:
        assert (left_low[output], left_high[output]) == (1600, 1630)
    rig.switch_off()
    rig.clock.advance(0.005)
    rig.answer_clock_probes()  # "off" after "on": believed once the clock went on after it
    rig.sys_status(safety_on=False)
    rig.goto(PARK)
    rig.tick()
    assert rig.servo() == {first: 1800, **dict.fromkeys(CALIBRATION.outputs[1:], 1615)}
    rig.ack_all(rig.sent)
    left_low, left_high = rig.core.outputs_left()
    assert left_low == left_high  # sent to the middle: they hold it
