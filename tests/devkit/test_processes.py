"""The process starters run the daemon and the simulator from this checkout."""

from __future__ import annotations

import pytest

from devkit import daemon_process, sim_process


@pytest.mark.parametrize("module", [daemon_process, sim_process])
def test_the_processes_run_in_this_checkout_so_its_packages_come_first(module):
    # Their working directory was the checkout's parent: a worktree's `--daemon-root` ran the
    # installed packages, not its own.
    assert (module.ROOT / "companion" / "daemon" / "cli.py").is_file()
    assert (module.ROOT / "sim_servo" / "__main__.py").is_file()
