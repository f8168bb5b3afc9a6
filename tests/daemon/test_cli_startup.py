"""The quick commands start without the solver: no numba (nor its compile) for ``--help``,
``--version``, the socket clients and ``check-config``; timing figures are for bench/, the
import set is checked here."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow  # a Python process per test

HEAVY = ("numba", "llvmlite", "companion.ik")

PROBE = """
import sys
from companion.daemon.cli import main
try:
    rc = main(sys.argv[1:])
except SystemExit as exc:
    rc = exc.code
print("loaded:", *[m for m in {heavy!r} if m in sys.modules])
print("rc:", rc)
"""


def run_cli(*argv: str) -> tuple[list[str], str]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE.format(heavy=HEAVY), *argv],
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines = out.stdout.splitlines()
    loaded = next(line for line in lines if line.startswith("loaded:")).split()[1:]
    rc = next(line for line in lines if line.startswith("rc:")).split()[1]
    return loaded, rc


@pytest.mark.parametrize(
    "argv",
    [
        ("--help",),
        ("--version",),
        ("goto", "--help"),
        ("status", "--socket", "/nonexistent/armbridge.sock"),
        ("park", "--socket", "/nonexistent/armbridge.sock"),
        ("goto", "1", "2", "3", "0", "0", "0", "--socket", "/nonexistent/armbridge.sock"),
    ],
)
def test_quick_commands_do_not_load_the_solver(argv):
    loaded, rc = run_cli(*argv)
    assert loaded == []
    assert rc in ("0", "3")  # 3: no daemon at that socket


def test_check_config_does_not_load_the_solver(tmp_path):
    # The example config: its park pose is checked against its keep-out volumes in numpy (the
    # compiled checks would load numba, or on a cold cache compile it).
    from importlib import resources

    example = (resources.files("companion.daemon") / "examples" / "armbridge.toml").read_text()
    config = tmp_path / "armbridge.toml"
    config.write_text(example.replace('socket = "/run/armbridge/control.sock"', 'socket = ""'))
    loaded, rc = run_cli("check-config", str(config))
    assert (loaded, rc) == ([], "0")


def test_the_probe_would_see_the_solver():
    """The check above can fail: ``solve`` does load it (and numba, unless the kernels'
    ahead-of-time module is built: companion.ik.aot)."""
    loaded, rc = run_cli("solve", "30", "10", "20", "0", "45", "0", "--budget-ms", "50")
    assert "companion.ik" in loaded


def test_the_daemon_package_lists_its_api_and_loads_it_lazily():
    import companion.daemon as daemon

    assert sorted(daemon.__all__) == sorted(daemon._WHERE)
    for name in daemon.__all__:
        assert getattr(daemon, name) is not None
