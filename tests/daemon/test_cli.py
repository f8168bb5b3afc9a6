"""The ``armbridge`` command line: in-process for the quick commands, a subprocess for ``run``."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import signal
import socket
import sys
import time

import pytest

from companion.daemon.cli import format_status, main, read_trajectory
from companion.daemon.config import parse_config
from companion.daemon.control_socket import request
from companion.daemon.demo import PAPER_TARGET_G, write_demo_plot
from companion.kinematics.arm import Arm, Pose
from devkit.control_client import ControlConnection
from devkit.timing import wait_until

WAIT_S = 15.0


def test_solve_reachable_and_unreachable(capsys):
    assert main(["solve", "71", "0", "-2", "0", "0", "0"]) == 0
    assert "REACHED" in capsys.readouterr().out
    assert main(["solve", "-20", "3", "40", "0", "10", "15", "--budget-ms", "5"]) == 1
    assert "NOT REACHED" in capsys.readouterr().out


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
    # Issue 15: on real ArduCopter, output 1 of a quad is refused at the first target.
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


VERBS = ("run", "demo", "check-config", "solve", "goto", "trajectory", "status", "park", "stop")


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
    # Issue 15: --help of every verb, and the mistakes a first-day user makes, each end in a
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


@pytest.mark.slow
def test_demo_runs_the_tour(capsys, tmp_path):
    png = tmp_path / "demo.png"
    assert main(["demo", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert out.count("ACCEPTED") == 3
    assert "FAILED: unreachable" in out and "nothing sent" in out
    assert "figure-eight" in out and "'servo_errors': 0" in out
    # With matplotlib (the `plots` extra) a PNG; without it (CI) a note, and the demo still ran.
    if importlib.util.find_spec("matplotlib") is not None:
        assert f"plot written to {png}" in out and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    else:
        assert "plot skipped: matplotlib is not installed" in out and not png.exists()


DEMO_PLOT_ARGS = (
    [("pose 1", Pose(40, 0, 40, 0, 0, 0), Pose(40.05, 0, 40, 0, 0, 0)),
     ("G", PAPER_TARGET_G, None)],
    [Pose(40, 5 * math.sin(k / 5), 40 + math.sin(k / 2.5), 0, 0, 0) for k in range(32)],
    [Pose(40, 5 * math.sin(k / 4), 40 + math.sin(k / 2), 0, 0, 0) for k in range(10)],
)  # fmt: skip


def test_demo_plot_is_skipped_without_matplotlib(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    note = write_demo_plot(tmp_path / "demo.png", *DEMO_PLOT_ARGS)
    assert note.startswith("plot skipped: matplotlib is not installed")
    assert not (tmp_path / "demo.png").exists()


def test_demo_plot_is_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "demo.png"
    assert write_demo_plot(png, *DEMO_PLOT_ARGS) == f"plot written to {png}"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_run_as_a_service_ready_goto_sigterm(tmp_path, sims, daemons, capsys):
    """The daemon as systemd runs it: READY=1 once it serves (saying what it waits for), the
    link up once the autopilot is heard, targets over the control socket, SIGTERM → park →
    STOPPING=1 → exit 0 within a second."""
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.settimeout(WAIT_S)
    sim = sims("--udp", "127.0.0.1:0")
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "2000000"}
    # The harness returns once the control socket answers; the notifications wait in `notify`.
    daemon = daemons(
        {"link": {"url": sim.url}, "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "park_on_stop": True}},
        env=env,
    )
    control = daemon.control_path
    config = daemon.config_path
    try:
        messages = []
        while not any(m.startswith(b"READY=1") for m in messages):
            messages.append(notify.recv(4096))  # each recv bounded by the socket timeout
        assert messages[-1] == b"READY=1\nSTATUS=waiting for the autopilot heartbeat on " + (
            sim.url.encode()
        )
        assert any(m.startswith(b"EXTEND_TIMEOUT_USEC=") for m in messages)
        assert wait_until(lambda: request(control, {"cmd": "status"})["status"]["link"] == "up")
        _cli_clients_against_a_live_daemon(str(control), tmp_path, capsys)
        reply = request(
            control, {"cmd": "goto", "pose": [62.14, 22.25, -3.32, 17.24, -1.47, 19.70]}
        )
        assert reply["ok"] and reply["outcome"] == "accepted", reply
        assert (
            request(control, {"cmd": "goto", "pose": [-20, 3, 40, 0, 10, 15]})["outcome"]
            == "failed"
        )
        status = request(control, {"cmd": "status"})["status"]
        assert status["link"] == "up" and status["counters"]["failed"] == 1
        assert "goto (62.14, 22.25, -3.32, 17.24, -1.47, 19.70) from socket" in daemon.log()
        notify.settimeout(3.0)
        assert any(notify.recv(4096) == b"WATCHDOG=1" for _ in range(20))
        # SIGHUP: a new budget applies at once; a new link URL needs a restart and is kept.
        config.write_text(
            config.read_text()
            .replace("[arm]", "[solver]\nbudget_ms = 5.0\n[arm]")
            .replace("udpout:127.0.0.1:", "udpout:127.0.0.2:")
        )
        daemon.proc.send_signal(signal.SIGHUP)
        seen = []
        while not (
            b"RELOADING=1" in seen
            and any(m.startswith(b"READY=1") for m in seen[seen.index(b"RELOADING=1") :])
        ):
            seen.append(notify.recv(4096))  # each recv bounded by the socket timeout
        assert request(control, {"cmd": "status"})["status"]["link"] == "up"
        started = time.monotonic()
        daemon.proc.send_signal(signal.SIGTERM)
        assert daemon.proc.wait(timeout=5) == 0
        assert time.monotonic() - started < 1.5
        rest = []
        notify.settimeout(0.5)
        try:
            while True:
                rest.append(notify.recv(4096))
        except TimeoutError:
            pass
        assert any(m.startswith(b"STOPPING=1") for m in rest)
        log = daemon.log()
        assert "stopping (parking)" in log
        assert "reload: link changed: restart the daemon to apply it" in log
        assert "reloaded" in log
    finally:
        notify.close()


def _cli_clients_against_a_live_daemon(control: str, tmp_path, capsys) -> None:
    """``goto --wait``, ``trajectory FILE --wait`` and ``status`` (for people and ``--json``)."""
    arm = Arm.default()
    park = [0, 90, 0, 0, 0, 0]  # where the daemon starts: short moves from there
    near = [[g + k * d for g, d in zip(park, (2, -2, 2, 1, 2, 1), strict=True)] for k in (1, 2)]
    there = arm.fk(near[0])
    capsys.readouterr()
    assert main(["goto", *map(str, there.as_tuple()), "--socket", control, "--wait", "-q"]) == 0
    out = capsys.readouterr().out
    assert '"outcome": "accepted"' in out and "still: hand" in out
    path = tmp_path / "path.csv"
    rows = [(0.0, there), (0.2, arm.fk(near[1]))]
    path.write_text(
        "# a short path\nt_s,x_cm,y_cm,z_cm,roll_deg,pitch_deg,yaw_deg\n"
        + "".join(f"{t},{','.join(map(str, pose.as_tuple()))}\n" for t, pose in rows)
    )
    assert main(["trajectory", str(path), "--socket", control, "--wait"]) == 0
    assert "trajectory of 2 points" in capsys.readouterr().out
    assert main(["status", "--socket", control]) == 0
    human = capsys.readouterr().out
    assert human.startswith("link up  autopilot 1/1") and "hand " in human
    assert human.count("acknowledged") >= 6 and "last target" in human
    assert main(["status", "--json", "--socket", control]) == 0
    hand = json.loads(capsys.readouterr().out)["status"]["hand"]
    final = arm.fk(near[1])  # where the trajectory ends, up to PWM steps
    assert list(hand) == ["x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg"]
    assert math.dist(list(hand.values())[:3], final.as_tuple()[:3]) < 0.2, hand
    assert f"x {hand['x_cm']:8.2f} cm" in human


@pytest.mark.slow
def test_a_goto_waiting_at_sigterm_is_answered(sims, daemons):
    """Every request gets one answer, also at shutdown: a goto whose servo update is still
    unconfirmed (the autopilot applies DO_SET_SERVO but withholds the ACKs) when SIGTERM comes
    gets a reply line on its connection, whatever the outcome."""
    sim = sims("--udp", "127.0.0.1:0", "--withhold-ack", "DO_SET_SERVO")
    daemon = daemons(
        {"link": {"url": sim.url}, "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "park_on_stop": True}}
    )
    daemon.wait_link("up")
    with ControlConnection(daemon.control_path, timeout_s=WAIT_S) as conn:
        pose = [62.14, 22.25, -3.32, 17.24, -1.47, 19.70]
        conn.send({"cmd": "goto", "pose": pose})
        # Its update reached the autopilot, whose ACKs will not come (FAILED only after
        # (1 + command_retries) × command_timeout_s = 1.5 s): SIGTERM now.
        assert wait_until(lambda: sim.events("servo"), WAIT_S)
        daemon.proc.send_signal(signal.SIGTERM)
        assert daemon.proc.wait(timeout=5) == 0
        try:
            reply = conn.reply()
        except ConnectionError as exc:
            raise AssertionError(f"no answer, the connection ended: {exc}") from exc
    assert reply["outcome"] in ("cancelled", "failed")
    # Parked all the same (the autopilot applies what it does not acknowledge), no traceback.
    park_pwm = parse_config(daemon.config).calibration.angles_to_pwm_us([0, 90, 0, 0, 0, 0])
    outputs = sim.state()["outputs"]
    assert {o: outputs[str(o)]["pwm_us"] for o in park_pwm} == park_pwm
    assert "Traceback" not in daemon.log()


def test_check_config_warns_of_a_serial_device_that_is_not_there(tmp_path, capsys):
    device = tmp_path / "ttyACM9"
    path = tmp_path / "a.toml"
    path.write_text(f'[link]\nurl = "{device},921600"\n', encoding="utf-8")
    assert main(["check-config", str(path)]) == 0
    assert f"link.url: {device} is not there now" in capsys.readouterr().err
    device.touch()
    assert main(["check-config", str(path)]) == 0
    assert "is not there now" not in capsys.readouterr().err


@pytest.mark.slow
def test_run_without_its_serial_device_serves_and_waits_for_it(tmp_path, daemons):
    """The flight controller's port is missing (unplugged, not enumerated yet): the daemon
    serves its socket, says what it waits for, and opens the port once it appears."""
    device = tmp_path / "ttyACM9"
    daemon = daemons({"link": {"url": f"{device},115200"}})
    daemon.wait_link("waiting")  # (the socket serves a moment before the link is opened)
    assert daemon.status()["link_waiting_for"] == str(device)
    assert f"waiting for {device} to appear" in daemon.log()
    master, slave = os.openpty()  # the board enumerates the flight controller
    try:
        device.symlink_to(os.ttyname(slave))
        assert wait_until(lambda: daemon.status()["link_waiting_for"] is None, WAIT_S)
        assert daemon.status()["link_counters"]["reconnects"] == 1
    finally:
        daemon.stop()
        os.close(master)
        os.close(slave)


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
