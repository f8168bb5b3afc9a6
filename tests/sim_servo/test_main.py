"""``python -m sim_servo``'s command line, in-process: the help documents every flag, bad
settings exit 2, and the flags' mapping onto the settings (``settings``). The simulator as a
process: ``test_main_process.py``.
"""

from __future__ import annotations

import pytest

from sim_servo.__main__ import build_parser, config_data, main
from sim_servo.config import config_from_mapping


def test_help_documents_every_fault_flag(capsys):
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for flag in (
        "--udp",
        "--tcp",
        "--pty",
        "--flavour",
        "--system-id",
        "--function",
        "--config",
        "--slew-s-per-60deg",
        "--deadband-us",
        "--arm",
        "--event-log",
        "--query-socket",
        "--seed",
        "--drop-in",
        "--drop-out",
        "--corrupt-in",
        "--corrupt-out",
        "--latency-ms",
        "--jitter-ms",
        "--heartbeat-pause-after",
        "--withhold-ack",
        "--nack-output",
        "--hangup-after",
        "--hangup-for",
        "--pty-link",
        "--signing-key",
        "--reboot-after",
        "--reboot-gap",
        "--link-hold-ms",
        "--link-delay-ms",
        "--link-burst-frames",
        "--system-time-rate-hz",
    ):
        assert flag in text


def test_bad_settings_exit_2_with_a_message(capsys, tmp_path):
    assert main(["--udp", "127.0.0.1:0", "--system-id", "300"]) == 2
    assert "<flags>: system_id: 300 outside [1, 255]" in capsys.readouterr().err
    assert main(["--udp", "127.0.0.1:0", "--withhold-ack", "NO_SUCH_COMMAND"]) == 2
    assert "NO_SUCH_COMMAND" in capsys.readouterr().err
    assert main(["--udp", "127.0.0.1:0", "--signing-key", str(tmp_path / "missing")]) == 2
    assert "cannot read signing key" in capsys.readouterr().err
    assert main(["--udp", "127.0.0.1:0", "--hangup-after", "1", "--hangup-for", "1"]) == 2
    assert "--hangup-for (hangup_for_s) needs --pty" in capsys.readouterr().err
    assert main(["--udp", "127.0.0.1:0", "--pty-link", str(tmp_path / "tty")]) == 2
    assert "--pty-link needs --pty" in capsys.readouterr().err


def settings(*argv: str):
    """The config the flags give (no process, no port)."""
    data, base_dir = config_data(build_parser().parse_args(["--udp", "127.0.0.1:0", *argv]))
    return config_from_mapping(data, base_dir=base_dir)


def test_ready_param_armed_and_safety_flags():
    raw = settings("--flavour", "px4")
    assert raw.functions[9] == 0 and raw.params == {} and raw.armed is False
    ready = settings("--flavour", "px4", "--ready", "--arm-outputs", "3,4,5,6,7,8")
    assert [ready.functions[o] for o in range(3, 9)] == [301, 302, 303, 304, 305, 306]
    assert ready.params["COM_PREARM_MODE"] == 2 and ready.armed is True
    tuned = settings("--flavour", "px4", "--ready", "--param", "COM_PREARM_MODE=0", "--armed")
    assert tuned.params["COM_PREARM_MODE"] == 0 and tuned.armed is True
    safety = settings("--safety", "on", "--param", "BRD_SAFETY_MASK=256", "--ready")
    assert safety.params == {"BRD_SAFETY_DEFLT": 1, "BRD_SAFETY_MASK": 256}
    timing = settings(
        "--flavour", "px4", "--px4-commander-period-ms", "0", "--px4-mavlink-loop-ms", "2"
    )
    assert (timing.px4_timing.commander_period_ms, timing.px4_timing.mavlink_loop_ms) == (0.0, 2.0)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--udp", "127.0.0.1:0", "--param", "COM_PREARM_MODE"])
    assert main(["--udp", "127.0.0.1:0", "--param", "NO_SUCH=1"]) == 2


def test_help_documents_the_vehicle_setup_flags(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = capsys.readouterr().out
    for flag in ("--ready", "--param", "--armed", "--safety", "--px4-forward-delay-ms", "'kill'"):
        assert flag in text


def test_vehicle_motion_flags():
    default = settings()
    assert default.vehicle.hover is True and default.vehicle.log_rate_hz == 25.0
    still = settings("--no-hover", "--vehicle-log-hz", "0", "--attitude-rate-hz", "50")
    assert (still.vehicle.hover, still.vehicle.log_rate_hz, still.attitude_rate_hz) == (
        False,
        0.0,
        50.0,
    )
    moved = settings(
        "--hover-seed", "9", "--drift-cm", "6", "--tilt-deg", "2", "--mount-xyz-cm", "1,2,15",
        "--mount-rpy-deg", "180,0,0", "--local-position-rate-hz", "10",
    )  # fmt: skip
    assert (moved.vehicle.seed, moved.vehicle.drift_cm, moved.vehicle.tilt_deg) == (9, 6.0, 2.0)
    assert moved.vehicle.mount.xyz_cm == (1.0, 2.0, 15.0)
    assert moved.vehicle.mount.rpy_deg == (180.0, 0.0, 0.0)
    assert moved.local_position_rate_hz == 10.0
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--udp", "127.0.0.1:0", "--mount-xyz-cm", "1,2"])


def test_px4_scales_its_streams_to_half_a_serial_line():
    def on_pty(*argv: str):
        data, base_dir = config_data(build_parser().parse_args(["--pty", *argv]))
        return config_from_mapping(data, base_dir=base_dir)

    # PX4: MAV_x_RATE 0 is baud / 20 bytes/s; 130 frames/s of 40 bytes need 5200 B/s.
    slow = on_pty("--flavour", "px4", "--pty-baud", "57600")
    assert slow.attitude_rate_hz == pytest.approx(100 * (2880 - 21) / 5200)
    assert slow.local_position_rate_hz == pytest.approx(30 * (2880 - 21) / 5200)
    fast = on_pty("--flavour", "px4", "--pty-baud", "115200")
    assert (fast.attitude_rate_hz, fast.local_position_rate_hz) == (100.0, 30.0)
    asked = on_pty("--flavour", "px4", "--pty-baud", "57600", "--attitude-rate-hz", "5")
    assert asked.attitude_rate_hz == 5.0  # a flag wins
    assert on_pty("--pty-baud", "57600").attitude_rate_hz is None  # ArduPilot: its SRn_ 0
    assert on_pty("--flavour", "px4").attitude_rate_hz is None  # no line: the ONBOARD defaults
