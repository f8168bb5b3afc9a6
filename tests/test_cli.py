"""The ``armbridge`` command line, called in-process through ``main(argv)``."""

from __future__ import annotations

from companion.cli import main


def test_demo_reaches_the_reachable_poses_and_refuses_g(capsys):
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    # Three reachable demo poses are reached; the papers' G is shown as a compromise.
    assert out.count("REACHED") == 4
    assert out.count("NOT REACHED") == 1


def test_solve_reachable_pose_exits_zero(capsys):
    assert main(["solve", "71", "0", "-2", "0", "0", "0"]) == 0
    assert "REACHED" in capsys.readouterr().out


def test_solve_unreachable_pose_exits_one(capsys):
    assert main(["solve", "-20", "3", "40", "0", "10", "15"]) == 1
    assert "NOT REACHED" in capsys.readouterr().out


def test_solve_nan_is_a_clear_error(capsys):
    assert main(["solve", "1", "2", "nan", "0", "0", "0"]) == 2
    assert "Pose.z_cm=nan must be finite" in capsys.readouterr().err


def test_solve_with_broken_arm_file(tmp_path, capsys):
    bad = tmp_path / "arm.toml"
    bad.write_text('convention = "sideways"\n')
    assert main(["solve", "--arm", str(bad), "1", "2", "3", "0", "0", "0"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "convention" in err
