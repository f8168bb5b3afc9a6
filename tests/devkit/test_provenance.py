"""The header every bench report opens with: command, commit (+dirty), date, machine, load."""

from __future__ import annotations

import datetime
import subprocess
from pathlib import Path

from devkit.provenance import command, commit, run_header, with_header

NOW = datetime.datetime(2026, 12, 3, 4, 43, 59, tzinfo=datetime.UTC)


def fake_git(head: str | None, porcelain: str):
    def run_git(*args: str, cwd: Path) -> str | None:
        if args[0] == "rev-parse":
            return head
        return porcelain

    return run_git


def test_the_header_names_command_commit_date_machine_and_load():
    lines = run_header(
        ["/repo/bench/latency.py", "--targets", "300"],
        module="bench.latency",
        now=NOW,
        load=(0.5, 1.25, 2.0),
        run_git=fake_git("c4e263a", ""),
    )
    assert lines[0] == "- command: `python -m bench.latency --targets 300`"
    assert lines[1] == "- commit: c4e263a"
    assert lines[2] == "- date: 2026-12-03 04:43 UTC"
    assert lines[3].startswith("- machine: ") and " cores, Python " in lines[3]
    assert lines[4] == "- load average (1, 5, 15 min) when written: 0.50 1.25 2.00"


def test_a_dirty_tree_and_no_repository_are_said():
    assert commit(run_git=fake_git("abc1234", " M bench/x.py")) == "abc1234+dirty"
    assert commit(run_git=fake_git(None, "")) == "unknown"


def test_the_module_defaults_to_the_script_name():
    assert command(["/x/bench/flood.py", "--seed", "1"]) == "python -m bench.flood --seed 1"


def test_this_checkout_gives_a_commit():
    # The real git, on this repository (a fresh clone in CI): a short hash, maybe +dirty.
    assert commit().split("+")[0] != "unknown"


def test_the_header_goes_under_the_title():
    header = ["- command: `python -m bench.x`"]
    assert with_header("# Title\n\nbody\n", header) == (
        "# Title\n\n- command: `python -m bench.x`\n\nbody\n"
    )
    assert with_header("| a |\n", header) == "- command: `python -m bench.x`\n\n| a |\n"


def test_the_benches_own_pages_do_not_make_the_tree_dirty(tmp_path):
    # A run of several benches writes their pages one after the other: the later ones must
    # still name the commit the code came from, without "+dirty".
    def run(*args: str) -> None:
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    (tmp_path / "docs/measurements").mkdir(parents=True)
    (tmp_path / "docs/measurements/latency.md").write_text("old\n")
    (tmp_path / "code.py").write_text("x = 1\n")
    run("init", "-q")
    run("add", ".")
    run("-c", "user.name=t", "-c", "user.email=t@example.org", "commit", "-qm", "start")
    (tmp_path / "docs/measurements/latency.md").write_text("new\n")
    assert not commit(tmp_path).endswith("+dirty")
    (tmp_path / "code.py").write_text("x = 2\n")
    assert commit(tmp_path).endswith("+dirty")
