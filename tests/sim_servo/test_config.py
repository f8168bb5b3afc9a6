"""Simulator settings: defaults, validation messages, TOML file, flag layering."""

from dataclasses import replace
from pathlib import Path

import pytest

from sim_servo.__main__ import build_parser, config_data
from sim_servo.config import (
    ArmConfig,
    FaultConfig,
    LinkTimingConfig,
    MountConfig,
    ServoConfig,
    SimConfig,
    VehicleConfig,
    config_from_mapping,
    load_key,
    load_toml,
    parse_withhold,
    ready_setup,
)
from sim_servo.errors import SimConfigError

EXAMPLE = Path(__file__).resolve().parents[2] / "sim_servo" / "examples" / "quad_arm.toml"


def test_ardupilot_defaults_motors_on_1_to_4():
    config = SimConfig()
    assert [config.functions[o] for o in (1, 2, 3, 4)] == [33, 34, 35, 36]
    assert all(config.functions[o] == 0 for o in range(5, 17))


def test_px4_defaults_leave_the_arm_outputs_unmapped_and_ready_maps_them():
    config = SimConfig(flavour="px4", arm=ArmConfig(outputs=(5, 6, 7, 8, 9, 10)))
    assert [config.functions[o] for o in (1, 2, 3, 4)] == [101, 102, 103, 104]
    assert all(config.functions[o] == 0 for o in range(5, 17))  # PWM_MAIN_FUNC5..16 ship as 0
    assert config.params == {} and config.armed is False
    ready = config_from_mapping({"flavour": "px4", **ready_setup("px4", (5, 6, 7, 8, 9, 10))})
    assert [ready.functions[o] for o in range(5, 11)] == [301, 302, 303, 304, 305, 306]
    assert ready.params == {"COM_PREARM_MODE": 2, "MAV_0_FORWARD": 1, "MAV_1_FORWARD": 1}
    assert ready.armed is True
    assert ready_setup("ardupilot", (9, 10)) == {}


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"flavour": "inav"}, "flavour: 'inav' is not one of ardupilot, px4"),
        ({"system_id": 0}, "system_id: 0 outside [1, 255]"),
        ({"functions": {17: 0}}, "outputs.17: output number 17 outside [1, 16]"),
        ({"servo_output_rate_hz": -1}, "servo_output_rate_hz: -1 outside [0, 1000]"),
        ({"signing_key": b"short"}, "signing_key: must be 32 bytes"),
        (
            {"servo_output_min_interval_ms": -1},
            "servo_output_min_interval_ms: -1 outside [0, 60000]",
        ),
        ({"system_time_rate_hz": 2000}, "system_time_rate_hz: 2000 outside [0, 1000]"),
    ],
)
def test_validation_names_value_and_range(kwargs, message):
    with pytest.raises(SimConfigError) as info:
        SimConfig(**kwargs)
    assert message in str(info.value)


@pytest.mark.parametrize(
    ("cls", "kwargs", "message"),
    [
        (FaultConfig, {"drop_in": 1.5}, "faults.drop_in: 1.5 outside [0, 1]"),
        (FaultConfig, {"nack_outputs": frozenset({0})}, "faults.nack_outputs: 0 outside [1, 16]"),
        (FaultConfig, {"hangup_for_s": -1.0}, "faults.hangup_for_s: -1.0 outside [0, 1000000]"),
        (FaultConfig, {"reboot_after_s": -1.0}, "faults.reboot_after_s: -1.0 outside [0, 1000000]"),
        (FaultConfig, {"reboot_gap_s": 601}, "faults.reboot_gap_s: 601 outside [0, 600]"),
        (ServoConfig, {"deadband_us": -1}, "servo.deadband_us: -1 outside [0, 100]"),
        (ServoConfig, {"travel_min_us": 2000, "travel_max_us": 1000}, "must be below"),
        (ArmConfig, {"outputs": (9, 9)}, "repeat an output"),
        (ArmConfig, {"pwm_min_us": 499}, "arm.pwm_min_us: 499 outside [500, 2500] µs"),
        (ArmConfig, {"pwm_max_us": 2501}, "arm.pwm_max_us: 2501 outside [500, 2500] µs"),
        (ArmConfig, {"pwm_min_us": 1000.5}, "arm.pwm_min_us: must be an integer, got 1000.5"),
        (
            ArmConfig,
            {"pwm_min_us": 2000},
            "arm.pwm_min_us: 2000 must be below arm.pwm_max_us = 2000",
        ),
        (
            ArmConfig,
            {"reversed_joints": "theta1"},
            "arm.reversed: must be a list of joint names, got 'theta1'",
        ),
        (ArmConfig, {"reversed_joints": (1,)}, "arm.reversed: 1 is not a joint name"),
        (
            ArmConfig,
            {"trims_us": ["theta1"]},
            "arm.trims_us: must be a table of joint name = trim in µs, got ['theta1']",
        ),
        (
            ArmConfig,
            {"trims_us": {"theta1": 501}},
            "arm.trims_us.theta1: 501 outside [-500, 500] µs",
        ),
        (
            ArmConfig,
            {"pwm_min_us": 1100, "pwm_max_us": 1901, "trims_us": {"theta2": -401}},
            "arm.trims_us.theta2: -401 outside [-400, 400] µs",
        ),
        (
            ArmConfig,
            {"trims_us": {"theta1": 1.5}},
            "arm.trims_us.theta1: must be an integer, got 1.5",
        ),
    ],
)
def test_part_validation(cls, kwargs, message):
    with pytest.raises(SimConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        cls(**kwargs)


def test_flavour_defaults_for_the_servo_stream_floor_and_system_time():
    ardupilot, px4 = SimConfig(), SimConfig(flavour="px4")
    assert (ardupilot.servo_output_floor_ms, px4.servo_output_floor_ms) == (20, 0)
    assert (ardupilot.system_time_default_hz, px4.system_time_default_hz) == (0.0, 1.0)
    # Not frozen into the config: changing the flavour changes the defaults.
    assert replace(ardupilot, flavour="px4").servo_output_floor_ms == 0
    assert SimConfig(servo_output_min_interval_ms=5).servo_output_floor_ms == 5
    assert FaultConfig().reboot_gap_s == 0.36 and FaultConfig().reboot_after_s is None


def test_link_timing_from_toml_and_validated():
    config = config_from_mapping({"link_timing": {"hold_ms": 0, "output_delay_ms": 0}})
    assert config.link_timing == LinkTimingConfig.instant()
    assert SimConfig().link_timing == LinkTimingConfig()
    with pytest.raises(
        SimConfigError,
        match="x.toml: link_timing.hold: unknown field; allowed: burst_frames, hold_ms, output_",
    ):
        config_from_mapping({"link_timing": {"hold": 1}}, "x.toml")
    with pytest.raises(
        SimConfigError, match=r"x.toml: link_timing.hold_ms: -2 outside \[0, 1000\]"
    ):
        config_from_mapping({"link_timing": {"hold_ms": -2}}, "x.toml")


def test_arm_table_from_toml():
    config = config_from_mapping(
        {"arm": {"pwm_min_us": 1100, "reversed": ["theta2"], "trims_us": {"theta3": -15}}}
    )
    assert config.arm.pwm_min_us == 1100 and config.arm.pwm_max_us == 2000
    assert config.arm.reversed_joints == ("theta2",)
    assert config.arm.trims_us == {"theta3": -15}
    with pytest.raises(
        SimConfigError, match="<dict>: arm.reversed: must be a list of joint names, got 'theta2'"
    ):
        config_from_mapping({"arm": {"reversed": "theta2"}})


def test_example_file_loads():
    config = config_from_mapping(load_toml(EXAMPLE), str(EXAMPLE), EXAMPLE.parent)
    assert config.flavour == "ardupilot" and config.functions[9] == 0
    assert config.servo.slew_s_per_60deg == 0.12


def test_px4_example_is_the_ready_vehicle():
    path = EXAMPLE.parent / "quad_arm_px4.toml"
    config = config_from_mapping(load_toml(path), str(path), path.parent)
    ready = config_from_mapping({"flavour": "px4", **ready_setup("px4", config.arm.outputs)})
    assert (config.functions, config.params, config.armed) == (
        ready.functions,
        ready.params,
        ready.armed,
    )
    assert config.px4_timing == ready.px4_timing  # the defaults, written out


def test_params_table_and_px4_timing_are_checked():
    with pytest.raises(SimConfigError, match="params.COM_PREARM_MODE: must be an integer, got 1.5"):
        config_from_mapping({"params": {"COM_PREARM_MODE": 1.5}})
    with pytest.raises(SimConfigError, match="armed: must be true or false, got 'yes'"):
        config_from_mapping({"armed": "yes"})
    with pytest.raises(SimConfigError, match="px4_timing.loop_ms: unknown field"):
        config_from_mapping({"px4_timing": {"loop_ms": 1}})
    with pytest.raises(SimConfigError, match="px4_timing.commander_period_ms: -1 outside"):
        config_from_mapping({"px4_timing": {"commander_period_ms": -1}})


def test_unknown_keys_are_refused():
    with pytest.raises(SimConfigError, match="x.toml: colour: unknown field; allowed: arm, armed,"):
        config_from_mapping({"colour": "red"}, "x.toml")
    with pytest.raises(
        SimConfigError, match="x.toml: faults.drop: unknown field; allowed: corrupt_in,"
    ):
        config_from_mapping({"faults": {"drop": 0.1}}, "x.toml")


def test_bad_toml_names_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("flavour = \n")
    with pytest.raises(SimConfigError, match="bad.toml"):
        load_toml(path)


def test_withhold_names_ids_and_all():
    assert parse_withhold(["DO_SET_SERVO", "511"]) == (frozenset({183, 511}), False)
    assert parse_withhold(["MAV_CMD_DO_SET_SERVO"]) == (frozenset({183}), False)
    assert parse_withhold(["all"]) == (frozenset(), True)
    with pytest.raises(SimConfigError, match="NOPE"):
        parse_withhold(["NOPE"])


def test_key_file_forms(tmp_path):
    raw = tmp_path / "raw"
    raw.write_bytes(bytes(range(32)))
    hexed = tmp_path / "hex"
    hexed.write_text(bytes(range(32)).hex() + "\n")
    assert load_key(raw) == load_key(hexed) == bytes(range(32))
    bad = tmp_path / "bad"
    bad.write_text("abc")
    with pytest.raises(SimConfigError, match="expected 32 raw bytes or 64 hex digits"):
        load_key(bad)


def test_flags_override_the_file():
    args = build_parser().parse_args(
        [
            "--udp",
            "127.0.0.1:0",
            "--config",
            str(EXAMPLE),
            "--flavour",
            "px4",
            "--function",
            "9=33",
            "--drop-in",
            "0.25",
            "--withhold-ack",
            "all",
            "--nack-output",
            "10",
            "--slew-s-per-60deg",
            "0.2",
            "--hangup-after",
            "5",
            "--hangup-for",
            "1.5",
            "--reboot-after",
            "7",
            "--reboot-gap",
            "0.5",
            "--link-hold-ms",
            "3",
            "--link-delay-ms",
            "0.5",
            "--link-burst-frames",
            "3",
            "--system-time-rate-hz",
            "2",
        ]
    )
    data, base = config_data(args)
    config = config_from_mapping(data, "flags", base)
    assert config.flavour == "px4" and config.functions[9] == 33
    assert config.faults.drop_in == 0.25 and config.faults.withhold_all_acks
    assert config.faults.nack_outputs == {10} and config.faults.hangup_after_s == 5
    assert config.faults.hangup_for_s == 1.5
    assert config.servo.slew_s_per_60deg == 0.2 and config.servo.deadband_us == 1.0
    assert (config.faults.reboot_after_s, config.faults.reboot_gap_s) == (7, 0.5)
    assert config.link_timing == LinkTimingConfig(output_delay_ms=0.5, hold_ms=3, burst_frames=3)
    assert config.system_time_default_hz == 2


def test_vehicle_and_mount_tables_from_toml_and_the_stream_defaults():
    config = config_from_mapping(
        {
            "attitude_rate_hz": 50,
            "vehicle": {
                "hover": False,
                "seed": 3,
                "drift_cm": 6.0,
                "home_ned_m": [1, 2, -5],
                "mount": {"xyz_cm": [2, 0, 12], "rpy_deg": [180, 0, 90]},
            },
        }
    )
    assert config.attitude_default_hz == 50.0 and config.local_position_default_hz == 0.0
    vehicle = config.vehicle
    assert (vehicle.hover, vehicle.seed, vehicle.drift_cm, vehicle.home_ned_m) == (
        False,
        3,
        6.0,
        (1.0, 2.0, -5.0),
    )
    assert vehicle.mount == MountConfig((2.0, 0.0, 12.0), (180.0, 0.0, 90.0))
    assert vehicle.as_dict()["mount"] == {"xyz_cm": [2.0, 0.0, 12.0], "rpy_deg": [180.0, 0.0, 90.0]}
    assert config_from_mapping(vehicle_data := {"vehicle": vehicle.as_dict()}).vehicle == vehicle
    assert vehicle_data["vehicle"]["seed"] == 3
    for example in (EXAMPLE, EXAMPLE.parent / "quad_arm_px4.toml"):  # the defaults, written out
        assert config_from_mapping(load_toml(example)).vehicle == VehicleConfig()
    # The shared default: an arm hanging 10 cm under the body origin, axes the body's.
    assert VehicleConfig().mount == MountConfig((0.0, 0.0, 10.0), (0.0, 0.0, 0.0))
    px4 = SimConfig(flavour="px4")
    assert (px4.attitude_default_hz, px4.local_position_default_hz) == (100.0, 30.0)
    assert (SimConfig().attitude_default_hz, SimConfig().local_position_default_hz) == (0.0, 0.0)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"vehicle": {"colour": 1}}, "vehicle.colour: unknown field"),
        (
            {"vehicle": {"mount": {"xyz": [0, 0, 0]}}},
            "vehicle.mount.xyz: unknown field; allowed: rpy_deg, xyz_cm",
        ),
        (
            {"vehicle": {"mount": {"xyz_cm": [0, 0]}}},
            r"vehicle.mount.xyz_cm: must be a list of 3 numbers, got \[0, 0\]",
        ),
        (
            {"vehicle": {"mount": {"rpy_deg": [0, 0, 400]}}},
            r"vehicle.mount.rpy_deg\[2\]: 400 outside \[-360, 360\]",
        ),
        ({"vehicle": {"hover": "yes"}}, "vehicle.hover: must be true or false, got 'yes'"),
        ({"vehicle": {"tilt_deg": 50}}, r"vehicle.tilt_deg: 50 outside \[0, 45\]"),
        (
            {"vehicle": {"period_min_s": 6.0}},
            "vehicle.period_min_s: 6.0 must not exceed vehicle.period_max_s = 5.0",
        ),
        (
            {"vehicle": {"home_ned_m": [0, 0, "x"]}},
            r"vehicle.home_ned_m\[2\]: must be a finite number, got 'x'",
        ),
        ({"vehicle": {"log_rate_hz": -1}}, "vehicle.log_rate_hz: -1 outside"),
        ({"vehicle": {"mount": 3}}, "<dict>: vehicle.mount: must be a table"),
        ({"local_position_rate_hz": -1}, "local_position_rate_hz: -1 outside"),
    ],
)
def test_vehicle_settings_are_validated(data, message):
    with pytest.raises(SimConfigError, match=message):
        config_from_mapping(data)


@pytest.mark.parametrize(
    ("data", "field", "problem"),
    [
        # Checked by the settings classes, named with the file all the same.
        ({"servo": {"deadband_us": -1}}, "servo.deadband_us", "-1 outside [0, 100]"),
        ({"arm": {"trims_us": {"theta1": 501}}}, "arm.trims_us.theta1", "outside [-500, 500] µs"),
        ({"vehicle": {"mount": {"xyz_cm": [0, 0, 1e308]}}}, "vehicle.mount.xyz_cm[2]", "outside"),
        ({"outputs": {"nine": 33}}, "outputs.nine", "'nine' is not an output number (1-16)"),
        ({"outputs": {"9": 1.5}}, "outputs.9", "must be an integer, got 1.5"),
        ({"faults": {"withhold_ack": ["NOPE"]}}, "faults.withhold_ack", "'NOPE' is not a command"),
        # Shapes a plain tuple() or frozenset() would meet with a TypeError.
        ({"arm": {"outputs": 9}}, "arm.outputs", "must be a list of output numbers, got 9"),
        ({"faults": {"nack_outputs": 9}}, "faults.nack_outputs", "must be a list of output"),
        ({"faults": {"nack_outputs": [[9]]}}, "faults.nack_outputs", "must be a list of output"),
        ({"arm": {"file": 5}}, "arm.file", "must be a non-empty string, got 5"),
        ({"servo": 5}, "servo", "must be a table"),
    ],
)
def test_every_refusal_names_the_file_and_the_dotted_field(data, field, problem):
    with pytest.raises(SimConfigError) as info:
        config_from_mapping(data, "sim.toml")
    assert (info.value.source, info.value.field) == ("sim.toml", field), str(info.value)
    assert problem in info.value.problem
    assert str(info.value).startswith(f"sim.toml: {field}: ")


@pytest.mark.parametrize(
    ("key", "absurd", "lowest", "range_text"),
    [
        # A heartbeat every 1e300 s, a main loop that never runs a pass: refused (the reasons
        # are at HEARTBEAT_RATE_HZ and LOOP_RATE_HZ).
        ("heartbeat_rate_hz", 1e-300, 0.1, "[0.1, 100]"),
        ("loop_rate_hz", 1e-300, 1, "[1, 10000]"),
    ],
)
def test_absurdly_slow_rates_are_refused_naming_the_range(key, absurd, lowest, range_text):
    assert getattr(SimConfig(**{key: lowest}), key) == lowest
    for value in (absurd, 0):
        with pytest.raises(SimConfigError, match=rf"{key}: {value!r} outside \{range_text[:-1]}\]"):
            config_from_mapping({key: value}, "sim.toml")
