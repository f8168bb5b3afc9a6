"""``armbridge demo``: the tour against a simulator (seconds in-process), and its optional plot."""

from __future__ import annotations

import importlib.util
import math
import sys

import pytest

from companion.daemon.cli import main
from companion.daemon.demo import PAPER_TARGET_G, write_demo_plot
from companion.kinematics.arm import Pose

pytestmark = pytest.mark.slow


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
