"""The ``armbridge`` command line, in-process: the quick commands, configs ``run`` refuses,
client verbs without a daemon. ``run`` as a subprocess: ``test_cli_run.py``."""

from __future__ import annotations

import json
import logging
import os
import re
import socket

import pytest

from companion.daemon.cli import LOG_DATE_FORMAT, format_status, log_format, main, read_trajectory
from companion.kinematics.arm import Arm

WAIT_S = 15.0


def test_solve_reachable_and_unreachable(capsys):
    # The largest budget: the default 20 ms is met in about 1 ms, but a solve preempted past it
    # on a loaded machine would stop short of the target.
    assert main(["solve", "71", "0", "-2", "0", "0", "0", "--budget-ms", "1000"]) == 0
    assert "REACHED" in capsys.readouterr().out
    # Its 5 ms of CPU spent (the ceiling far off, however busy the machine): DEADLINE.
    argv = ["solve", "-20", "3", "40", "0", "10", "15", "--budget-ms", "5", "--ceiling-ms", "1000"]
    assert main(argv) == 1
    assert "NOT REACHED (deadline)" in capsys.readouterr().out


def test_solve_takes_a_wall_clock_ceiling(capsys):
    # A ceiling below the budget ends the search first (CPU time never runs ahead of it).
    argv = ["solve", "-20", "3", "40", "0", "10", "15", "--budget-ms", "50", "--ceiling-ms", "2"]
    assert main(argv) == 1
    assert "NOT REACHED (ceiling)" in capsys.readouterr().out
    assert main([*argv[:-1], "0"]) == 2
    assert "ceiling_ms=0.0 must be a finite number > 0" in capsys.readouterr().err


def test_solve_takes_the_search_settings_of_the_daemon_config(capsys, monkeypatch):
    from companion import ik

    seen = []
    real = ik.solve
    monkeypatch.setattr(ik, "solve", lambda *a, **kw: seen.append(kw["settings"]) or real(*a, **kw))
    reach = ["solve", "71", "0", "-2", "0", "0", "0", "--budget-ms", "1000"]
    assert main([*reach, "--method", "de", "--pop-size", "16", "--mutation-f", "0.8"]) == 0
    assert "REACHED" in capsys.readouterr().out
    assert (seen[0].pop_size, seen[0].F, seen[0].Cr, seen[0].lm_iterations) == (16, 0.8, 0.95, 0)
    for flags, words in (
        (["--pop-size", "3"], "--pop-size: 3 outside [4, 100]"),
        (["--method", "memetic", "--crossover-cr", "1.5"], "--crossover-cr: 1.5 outside [0, 1]"),
        (["--method", "ga"], "--method: 'ga' is not one of restarts, memetic, de"),
        (
            ["--method", "de", "--lm-iterations", "5"],
            '--lm-iterations: goes with method = "restarts" or "memetic"',
        ),
        (["--mutation-f", "0.8"], '--mutation-f: goes with method = "memetic" or "de"'),
    ):
        assert main([*reach, *flags]) == 2
        assert words in capsys.readouterr().err


def test_solve_takes_a_urdf_arm_and_its_tip_link(capsys):
    from importlib.resources import files

    urdf = str(files("companion.kinematics") / "arms" / "ur5.urdf")
    arm = Arm.from_urdf(urdf)
    hand = arm.fk([10.0, -60.0, 70.0, -20.0, 30.0, 15.0]).as_tuple()
    assert main(["solve", *map(str, hand), "--arm", urdf, "--budget-ms", "200"]) == 0
    assert "REACHED" in capsys.readouterr().out
    assert main(["solve", *map(str, hand), "--tip-link", "tool0"]) == 2
    assert "--tip-link goes with a URDF --arm file" in capsys.readouterr().err


@pytest.mark.parametrize("verb", ["solve", "goto"])
def test_a_nan_coordinate_is_a_usage_error_before_anything_runs(verb, tmp_path, capsys):
    # goto checks it before it looks for the daemon: exit 2, not 3 (no socket here).
    argv = [verb, "1", "2", "nan", "0", "0", "0"]
    with pytest.raises(SystemExit) as info:
        main([*argv, "--socket", str(tmp_path / "none.sock")] if verb == "goto" else argv)
    assert info.value.code == 2
    assert "argument z_cm: 'nan' is not a finite number" in capsys.readouterr().err


def test_check_config(tmp_path, capsys):
    good = tmp_path / "good.toml"
    good.write_text('[link]\nurl = "udpout:127.0.0.1:14550"\n')
    assert main(["check-config", str(good)]) == 0
    bad = tmp_path / "bad.toml"
    bad.write_text('[link]\nurl = "udpout:127.0.0.1:14550"\n[solver]\nbudget_ms = -1\n')
    assert main(["check-config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "solver.budget_ms" in err


def test_check_config_warns_of_a_joint_on_a_default_motor_output(tmp_path, capsys):
    # On real ArduCopter, output 1 of a quad is refused at the first target.
    joints = "".join(f"[[joint]]\noutput = {o}\n" for o in (3, 10, 11, 12, 13, 14))
    path = tmp_path / "motor.toml"
    path.write_text('[link]\nurl = "udpout:127.0.0.1:14550"\n' + joints)
    assert main(["check-config", str(path)]) == 0  # a warning: the vehicle may have no motor 3
    err = capsys.readouterr().err
    assert "output 3 drives a motor by default on a quad/hexa/octa frame" in err
    assert "SERVO3_FUNCTION = 0" in err and "output 10" not in err
    px4 = tmp_path / "px4.toml"
    px4.write_text('[link]\nurl = "udpout:127.0.0.1:14550"\ndialect = "px4"\n' + joints)
    assert main(["check-config", str(px4)]) == 0
    assert "drives a motor" not in capsys.readouterr().err


def test_check_config_lists_the_keepout_volumes_or_warns_of_none(tmp_path, capsys):
    from importlib import resources

    example = (resources.files("companion.daemon") / "examples" / "armbridge.toml").read_text()
    path = tmp_path / "example.toml"
    path.write_text(example.replace('socket = "/run/armbridge/control.sock"', 'socket = ""'))
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr()
    assert "keep-out: body, prop_front_right" in out.out and "margin 1 cm" in out.out
    assert "[[keepout]]" not in out.err
    bare = tmp_path / "bare.toml"
    bare.write_text('[link]\nurl = "udpout:127.0.0.1:14550"\n')
    assert main(["check-config", str(bare)]) == 0
    assert "no [[keepout]] volumes" in capsys.readouterr().err


def test_run_with_broken_config_exits_2_and_sends_nothing(tmp_path, capsys):
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    listener.settimeout(0.3)
    port = listener.getsockname()[1]
    bad = tmp_path / "bad.toml"
    bad.write_text(f'[link]\nurl = "udpout:127.0.0.1:{port}"\ndialect = "inav"\n')
    try:
        assert main(["run", "--config", str(bad)]) == 2
        assert "link.dialect" in capsys.readouterr().err
        with pytest.raises(TimeoutError):
            listener.recv(4096)  # not even a heartbeat went out
    finally:
        listener.close()


OUT_OF_BOUNDS = {
    "rate": ("[control]\nrate_hz = 1e-10\n", "control.rate_hz", "1e-10 outside [1, 400]"),
    "ack-wait": (
        "[link]\ncommand_timeout_s = 1e300\n",
        "link.command_timeout_s",
        "outside [0.001, 60]",
    ),
    "joint-speed": (
        "[arm]\njoint_speed_deg_s = 1e6\n",
        "arm.joint_speed_deg_s",
        "outside [1, 1000]",
    ),
    "trim": (
        "[arm]\npark_deg = [0, 170, 0, 0, 0, 0]\n"
        + "".join(f"[[joint]]\noutput = {o}\n" for o in range(9, 15)).replace(
            "output = 10\n", "output = 10\ntrim_us = 100\n"
        ),
        "joint[2].trim_us",
        "2100 µs, outside [1000, 2000] µs",
    ),
}


@pytest.mark.parametrize("case", OUT_OF_BOUNDS, ids=list(OUT_OF_BOUNDS))
def test_check_config_and_run_refuse_the_same_out_of_bounds_values(tmp_path, capsys, case):
    """Both go through load_config: what check-config refuses, run refuses with the same
    message (exit 2) before it opens or sends anything."""
    text, field, words = OUT_OF_BOUNDS[case]
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    listener.settimeout(0.2)
    url = f"udpout:127.0.0.1:{listener.getsockname()[1]}"
    path = tmp_path / "bounds.toml"
    if text.startswith("[link]"):
        text = f'[link]\nurl = "{url}"\n' + text.removeprefix("[link]\n")
    else:
        text = f'[link]\nurl = "{url}"\n' + text
    path.write_text(text)
    try:
        assert main(["check-config", str(path)]) == 2
        checked = capsys.readouterr().err
        assert f"{path}: {field}: " in checked and words in checked, checked
        assert main(["run", "--config", str(path)]) == 2
        assert capsys.readouterr().err == checked
        with pytest.raises(TimeoutError):
            listener.recv(4096)  # not even a heartbeat went out
    finally:
        listener.close()


VERBS = (
    "run",
    "demo",
    "check-config",
    "solve",
    "goto",
    "trajectory",
    "status",
    "park",
    "stop",
    "resume",
)


@pytest.mark.parametrize(
    ("argv", "code", "says"),
    [
        *[([verb, "--help"], 0, "usage: armbridge") for verb in VERBS],
        (["--help"], 0, "usage: armbridge"),
        (["--version"], 0, "armbridge "),
        ([], 2, "required: COMMAND"),
        (["solve"], 2, "required: x_cm"),
        (["solve", "1", "2", "3"], 2, "required: roll_deg, pitch_deg, yaw_deg"),
        (["solve", "45,10,20,0,45,0"], 2, "invalid float value: '45,10,20,0,45,0'"),
        (["goto", "1", "2", "3"], 2, "required: roll_deg"),
        (["goto", "1", "2", "3", "4", "5", "x"], 2, "yaw_deg: invalid float value: 'x'"),
        (["status", "--timeout-s", "0"], 2, "'0' must be a positive number of seconds"),
        (["status", "--watch", "nan"], 2, "'nan' must be a positive number of seconds"),
        (["status", "--log-level", "LOUD"], 2, "invalid choice: 'LOUD'"),
        (["trajectory"], 2, "required: file"),
        (["trajectory", "/nonexistent/path.csv"], 2, "cannot read /nonexistent/path.csv"),
        (["check-config"], 2, "required: config"),
        (["check-config", "/nonexistent.toml"], 2, "/nonexistent.toml"),
        (["run"], 2, "required: --config"),
        (["frobnicate"], 2, "invalid choice: 'frobnicate'"),
    ],
)
def test_a_newcomer_meets_no_traceback(argv, code, says, capsys):
    # --help of every verb, and the mistakes a first-day user makes, each end in a
    # clear message and an exit code, never a traceback.
    try:
        got = main(argv)
    except SystemExit as exc:  # argparse: --help, --version, usage errors
        got = exc.code
    out, err = capsys.readouterr()
    assert got == code, (out, err)
    assert says in out + err
    assert "Traceback" not in out + err


def test_log_options_work_before_and_after_the_verb(tmp_path, capsys):
    sock = str(tmp_path / "none.sock")
    for argv in (["-q", "status", "--socket", sock], ["status", "--socket", sock, "-v"],
                 ["status", "--log-level", "debug", "--socket", sock]):  # fmt: skip
        assert main(argv) == 3
        assert "cannot reach the daemon" in capsys.readouterr().err


def test_trajectory_files_csv_and_json_and_their_errors(tmp_path):
    good = [[0, 60, 10, 5, 0, 20, 10], [0.5, 61, 10, 5, 0, 20, 10]]
    csv_path = tmp_path / "a.csv"
    csv_path.write_text("# comment\nt_s,x_cm,y_cm,z_cm,roll_deg,pitch_deg,yaw_deg\n\n"
                        "0,60,10,5,0,20,10\n0.5, 61, 10, 5, 0, 20, 10\n")  # fmt: skip
    assert read_trajectory(str(csv_path)) == good
    for text in (json.dumps(good), json.dumps({"points": good})):
        (tmp_path / "a.json").write_text(text)
        assert read_trajectory(str(tmp_path / "a.json")) == good
    for text, says in (
        ("0,60,10,5,0,20\n", "line 1: expected 7 values"),
        ("0,60,10,5,0,20,10\n1,60,ten,5,0,20,10\n", "line 2: y_cm = 'ten' is not a number"),
        ("0,60,10,5,0,20,nan\n", "line 1: yaw_deg = 'nan' is not finite"),
        ("# nothing\n", "no points"),
        ('{"pts": []}', 'JSON must be a list of rows or {"points": [...]}'),
        ("[[0, 1, 2, 3, 4, 5, null]]", "point 0: yaw_deg = None is not a number"),
        ("1,60,10,5,0,20,10\n0.5,61,10,5,0,20,10\n", "line 2: t_s = 0.5 after 1: times must"),
        ("[" * 100_000 + "]" * 100_000, "JSON nested too deeply"),
        ("[[0, 1, 2", "not valid JSON"),
    ):
        (tmp_path / "bad.txt").write_text(text)
        with pytest.raises(ValueError, match=re.escape(says)):
            read_trajectory(str(tmp_path / "bad.txt"))


def test_status_for_people_names_a_refused_output():
    status = {
        "link": "up", "autopilot": [1, 1], "autopilot_boot_ms": 12_345, "moving": False,
        "hand": {"x_cm": 1.0, "y_cm": 2.0, "z_cm": 3.0, "roll_deg": 4.0, "pitch_deg": 5.0,
                 "yaw_deg": 6.0},
        "current_deg": [10.0, 20.0], "goal_deg": None,
        "outputs": {"9": {"pwm_us": 1500, "state": "acknowledged"},
                    "1": {"pwm_us": None, "state": "refused",
                          "reason": "Set SERVO1_FUNCTION = 0"}},
        "last_target": None, "counters": {"targets": 2, "failed": 0},
    }  # fmt: skip
    text = format_status(status)
    assert text.splitlines()[0] == "link up  autopilot 1/1 (up 12.3 s)  still"
    assert "x     1.00 cm" in text
    assert "    1      10.00          -       9    1500  acknowledged" in text
    assert "refused (Set SERVO1_FUNCTION = 0)" in text
    assert text.endswith("counters  targets 2")


def test_stop_holds_the_arm_until_resume(tmp_path, capsys):
    from companion.daemon.config import parse_config
    from companion.daemon.control_socket import ControlServer
    from companion.daemon.service import ArmDaemon

    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # an autopilot that never talks
    silent.bind(("127.0.0.1", 0))
    daemon = ArmDaemon(
        parse_config({"link": {"url": f"udpout:127.0.0.1:{silent.getsockname()[1]}"}})
    )
    daemon.start()
    server = ControlServer(tmp_path / "control.sock", daemon)
    sock = ["--socket", str(server.path)]
    try:
        assert main(["stop", *sock]) == 0
        assert json.loads(capsys.readouterr().out)["message"] == "holding until resume"
        assert main(["status", *sock]) == 0
        out = capsys.readouterr().out
        assert "stopped" in out.splitlines()[0]
        assert "the arm holds until `armbridge resume`" in out
        assert main(["resume", *sock]) == 0
        assert json.loads(capsys.readouterr().out)["message"] == "resumed"
        assert main(["status", "--json", *sock]) == 0
        assert json.loads(capsys.readouterr().out)["status"]["stopped"] is False
    finally:
        server.close()
        daemon.close()
        silent.close()


def test_status_for_people_says_when_no_autopilot_was_heard():
    text = format_status({"link": "waiting", "autopilot": None, "current_deg": [], "counters": {}})
    assert text.splitlines()[0] == "link waiting  autopilot none yet  still"
    assert "no autopilot heard yet: targets are refused" in text.splitlines()[1]
    heard = format_status(
        {"link": "up", "autopilot": [1, 1], "autopilot_heard_us": False, "current_deg": []}
    )
    assert "has not answered us yet" in heard


def test_client_without_daemon_exits_3(tmp_path, capsys):
    assert main(["status", "--socket", str(tmp_path / "none.sock")]) == 3
    assert "cannot reach the daemon" in capsys.readouterr().err


def test_check_config_warns_of_a_serial_device_that_is_not_there(tmp_path, capsys):
    device = tmp_path / "ttyACM9"
    path = tmp_path / "a.toml"
    path.write_text(f'[link]\nurl = "{device},921600"\n', encoding="utf-8")
    assert main(["check-config", str(path)]) == 0
    assert f"link.url: {device} is not there now" in capsys.readouterr().err
    device.touch()
    assert main(["check-config", str(path)]) == 0
    assert "is not there now" not in capsys.readouterr().err


def test_a_trajectory_file_is_limited_by_its_points_not_its_bytes(tmp_path):
    from companion.daemon.requests import MAX_TRAJECTORY_POINTS

    row = "{t},60.000000000000,10.000000000000,5.000000000000,0,20.000000000000,10\n"
    path = tmp_path / "long.csv"
    with path.open("w") as file:  # the limit's points, each well over 60 bytes
        file.writelines(row.format(t=i) for i in range(MAX_TRAJECTORY_POINTS))
    assert len(read_trajectory(str(path))) == MAX_TRAJECTORY_POINTS
    with path.open("a") as file:  # one more, then a huge tail that is never read
        file.write(row.format(t=MAX_TRAJECTORY_POINTS))
        file.write("x" * 50_000_000)
    with pytest.raises(ValueError, match=f"more than {MAX_TRAJECTORY_POINTS} points"):
        read_trajectory(str(path))
    big = tmp_path / "big.json"
    big.write_text("[" + " " * (MAX_TRAJECTORY_POINTS * 256) + "]")
    with pytest.raises(ValueError, match=f"more than {MAX_TRAJECTORY_POINTS} points"):
        read_trajectory(str(big))


@pytest.mark.parametrize(
    "reply",
    [
        b"not json\n",
        b"[1, 2]\n",
        b'{"ok": true, "status": "fine"}\n',
        b'{"ok": true, "status": {"current_deg": [1, "x"]}}\n',
    ],  # fmt: skip
)
def test_status_against_a_reply_it_cannot_read_says_so(reply, tmp_path, capsys):
    import socket
    import threading

    path = str(tmp_path / "odd.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(path)
    server.listen(1)

    def answer() -> None:
        conn, _ = server.accept()
        with conn:
            conn.recv(4096)
            conn.sendall(reply)

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    try:
        assert main(["status", "--socket", path, "--timeout-s", "5"]) == 1
    finally:
        thread.join(timeout=5)
        server.close()
    err = capsys.readouterr().err
    assert "armbridge:" in err and "Traceback" not in err


def test_status_for_people_never_says_reached_for_a_target_that_failed():
    base = {"link": "up", "autopilot": [1, 1], "current_deg": [], "counters": {},
            "moving": False, "outputs_live": True}  # fmt: skip
    target = {"pose": [1.0] * 6, "converged": True, "solve_ms": 0.2}
    failed = {**target, "outcome": "failed", "answer": "servo output 14 refused"}
    assert "FAILED: servo output 14 refused" in format_status({**base, "last_target": failed})
    assert "reached" not in format_status({**base, "last_target": failed})
    accepted = {**target, "outcome": "accepted", "answer": "moving"}
    assert "reached" in format_status({**base, "last_target": accepted})
    assert "moving" in format_status({**base, "moving": True, "last_target": accepted})
    dead = {**base, "outputs_live": False, "last_target": accepted}
    assert "reached" not in format_status(dead)


@pytest.mark.parametrize("name", ["unit", "config", "lua"])
def test_shipped_prints_the_file_the_package_carries(name, capsys):
    assert main(["shipped", name]) == 0
    text = capsys.readouterr().out
    first = {"unit": "[Unit]", "config": "[link]", "lua": "--[["}[name]
    assert first in text


def test_log_lines_carry_the_time_of_day_unless_journald_stamps_them(tmp_path):
    # A terminal or a bench's log file: each line starts with the time, to the millisecond;
    # under systemd (stderr is the JOURNAL_STREAM named) journald stamps it.
    with open(tmp_path / "stderr", "w") as stream:
        st = os.fstat(stream.fileno())
        journal = {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        assert "asctime" not in log_format(journal, stream)
        for environ in (
            {},
            {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"},
            {"JOURNAL_STREAM": "x"},
        ):
            fmt = log_format(environ, stream)
            record = logging.LogRecord("armbridge", logging.INFO, __file__, 1, "up", None, None)
            line = logging.Formatter(fmt, LOG_DATE_FORMAT).format(record)
            assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} INFO armbridge: up", line)
