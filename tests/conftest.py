"""Fixtures over the shared helpers in ``tests/support``: simulator and daemon processes that
are always stopped and reaped, whatever the test did."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

import pytest

from tests.support.daemon_process import DaemonProcess
from tests.support.sim_process import SimProcess
from tests.support.timing import FakeClock


@pytest.fixture
def sims(tmp_path) -> Iterator[Callable[..., SimProcess]]:
    """Starts simulators (``sims(*flags)``), each in its own directory; at the end each one
    still running is stopped, asserting a clean exit (0)."""
    started: list[SimProcess] = []

    def start(*args: str) -> SimProcess:
        sim = SimProcess(tmp_path / f"sim{len(started)}", *args)
        started.append(sim)
        return sim

    yield start
    codes = []
    for sim in started:
        running = sim.proc.poll() is None
        code = sim.stop()
        if running:
            codes.append(code)
    assert all(code == 0 for code in codes), codes


@pytest.fixture
def daemons(tmp_path) -> Iterator[Callable[..., DaemonProcess]]:
    """Starts ``armbridge run`` processes (``daemons(config_dict, env=None)``); at the end
    each one still running is stopped (SIGTERM), asserting exit 0. Their logs are printed at
    teardown, so pytest shows them with a failure."""
    started: list[DaemonProcess] = []

    def start(config: Mapping[str, Any], **kwargs: Any) -> DaemonProcess:
        daemon = DaemonProcess(tmp_path / f"daemon{len(started)}", config, **kwargs)
        started.append(daemon)
        return daemon

    yield start
    codes = []
    for daemon in started:
        running = daemon.proc.poll() is None
        code = daemon.stop()
        if running:
            codes.append(code)
        print(f"--- {daemon.log_path} ---\n{daemon.log()}")
    assert all(code == 0 for code in codes), codes


@pytest.fixture
def clock() -> FakeClock:
    """A fake monotonic clock the test advances by hand."""
    return FakeClock()
