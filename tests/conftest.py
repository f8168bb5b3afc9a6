"""Fixtures over the shared helpers in ``devkit``: simulator and daemon processes that
are always stopped and reaped, whatever the test did. Also what every test process needs on a
busy machine: one hypothesis profile, and the collected heap kept out of the collector's way."""

from __future__ import annotations

import gc
import subprocess
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any, Protocol

import pytest
from hypothesis import HealthCheck, settings

from companion.ik import warm_up
from devkit.daemon_process import DaemonProcess
from devkit.sim_process import SimProcess
from devkit.timing import FakeClock

# Examples are judged by what they assert, never by how long one took: a machine shared with
# other processes stretches an example's wall time many times over, and hypothesis would call
# that a failure (deadline) or an error (too_slow).
settings.register_profile("armbridge", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("armbridge")


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze the heap collection built (every test module and what it imports: ~115 000
    objects, numba's among them), as ``armbridge run`` and the simulator freeze theirs: it
    lives as long as the process, and a full collection pass over it stops every thread of the
    process (1.3 s measured at load 13), in-process daemons' control threads included, which
    then judge ACKs and SYSTEM_TIME late."""
    gc.freeze()


@pytest.fixture(scope="session", autouse=True)
def _kernels_loaded() -> None:
    """The IK kernels loaded once per test process before its first test, as ``armbridge run``
    loads them before READY: with numba's cache cold (a fresh clone) the first solve compiles
    them, about 20 s of CPU, and an in-process daemon's first target would pay that inside a
    test's bounded wait. The heap they leave is frozen with the rest."""
    warm_up()
    gc.freeze()


class _Started(Protocol):
    proc: subprocess.Popen

    def stop(self) -> int: ...


def _stop_all(started: Sequence[_Started]) -> None:
    """Stop every process still running; each must exit 0 (one that already ended was checked
    by its test)."""
    codes = [p.stop() for p in started if p.proc.poll() is None]
    assert all(code == 0 for code in codes), codes


@pytest.fixture
def sims(tmp_path) -> Iterator[Callable[..., SimProcess]]:
    """Starts simulators (``sims(*flags)``), each in its own directory; at the end each one
    still running is stopped, asserting a clean exit (0)."""
    started: list[SimProcess] = []

    def start(*args: str) -> SimProcess:
        started.append(SimProcess(tmp_path / f"sim{len(started)}", *args))
        return started[-1]

    yield start
    for sim in started:  # reap those that already ended, too
        if sim.proc.poll() is not None:
            sim.stop()
    _stop_all(started)


@pytest.fixture
def daemons(tmp_path) -> Iterator[Callable[..., DaemonProcess]]:
    """Starts ``armbridge run`` processes (``daemons(config_dict, env=None)``); at the end
    each one still running is stopped (SIGTERM), asserting exit 0. Their logs are printed at
    teardown, so pytest shows them with a failure."""
    started: list[DaemonProcess] = []

    def start(config: Mapping[str, Any], **kwargs: Any) -> DaemonProcess:
        started.append(DaemonProcess(tmp_path / f"daemon{len(started)}", config, **kwargs))
        return started[-1]

    yield start
    try:
        _stop_all(started)
    finally:
        for daemon in started:
            daemon.stop()  # reaps those that had already ended
            print(f"--- {daemon.log_path} ---\n{daemon.log()}")


@pytest.fixture
def clock() -> FakeClock:
    """A fake monotonic clock the test advances by hand."""
    return FakeClock()
