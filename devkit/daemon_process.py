"""``armbridge run`` as a subprocess: the one way the tests (and benches) start the daemon.

:class:`DaemonProcess` writes the config it is given (a dict, see
:func:`devkit.config.write_config`), starts ``python -m companion.daemon.cli run
--config FILE``, and returns once the control socket answers a ``status`` request, bounded.
It always stops and reaps the process; its stdout and stderr go to one log file, which every
failure message includes.
"""

from __future__ import annotations

import copy
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from companion.daemon.control_socket import request
from devkit.config import write_config
from devkit.process import kill, terminate
from devkit.provenance import ROOT  # the checkout
from devkit.timing import WAIT_S, wait_until

#: Start-up bound: importing numba and loading the solver's kernels take seconds when loaded.
READY_S = 30.0

#: What a status request raises while the daemon is not (yet, or any more) serving.
NOT_SERVING = (OSError, ConnectionError, ValueError)


def daemon_command(config_path: Path) -> list[str]:
    """The command line of ``armbridge run --config config_path`` in this interpreter."""
    return [sys.executable, "-m", "companion.daemon.cli", "run", "--config", str(config_path)]


def run_daemon(config_path: Path, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """Run ``armbridge run`` to its exit (for configs it must refuse); output captured."""
    return subprocess.run(
        daemon_command(config_path),
        cwd=ROOT,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


class DaemonProcess:
    """``armbridge run`` on ``config`` (TOML tables as dicts) in ``directory``.

    ``control.socket`` defaults to ``directory/control.sock``. ``env`` replaces the
    environment (e.g. to add ``NOTIFY_SOCKET``). ``root``: the checkout whose code runs (the
    working directory, so its packages come first; default this one). A context manager;
    :meth:`stop` is idempotent.
    """

    def __init__(
        self,
        directory: Path,
        config: Mapping[str, Any],
        *,
        env: Mapping[str, str] | None = None,
        ready_timeout_s: float = READY_S,
        root: Path = ROOT,
    ) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.config: dict[str, Any] = copy.deepcopy(dict(config))
        control = self.config.setdefault("control", {})
        control.setdefault("socket", str(directory / "control.sock"))
        self.control_path = Path(control["socket"])
        self.config_path = write_config(directory / "armbridge.toml", self.config)
        self.log_path = directory / "daemon.log"
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                daemon_command(self.config_path),
                cwd=root,
                env=None if env is None else dict(env),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        try:
            self.wait_ready(ready_timeout_s)
        except BaseException:
            self.kill()
            raise

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log(self) -> str:
        """Everything the daemon wrote so far (stdout and stderr)."""
        return self.log_path.read_text(errors="replace")

    def answers(self) -> bool:
        """Whether the control socket answers a status request now."""
        try:
            return bool(self.request("status", timeout_s=2.0)["ok"])
        except NOT_SERVING:
            return False

    def wait_ready(self, timeout_s: float = READY_S) -> None:
        """Bounded wait until the control socket answers (a socket file existing is not
        enough); fails with the log if the daemon exits or stays silent."""
        wait_until(lambda: self.proc.poll() is not None or self.answers(), timeout_s)
        code = self.proc.poll()
        if code is not None:
            raise AssertionError(f"the daemon exited with {code}:\n{self.log()}")
        if not self.answers():
            raise AssertionError(f"the daemon did not answer within {timeout_s} s:\n{self.log()}")

    def request(self, cmd: str, *, timeout_s: float = WAIT_S, **fields: Any) -> dict[str, Any]:
        """One control-socket request ``{"cmd": cmd, **fields}``; the reply."""
        return request(self.control_path, {"cmd": cmd, **fields}, timeout_s=timeout_s)

    def status(self) -> dict[str, Any]:
        return self.request("status")["status"]

    def wait_link(self, state: str, timeout_s: float = WAIT_S) -> None:
        """Bounded wait until the daemon itself reports its autopilot link ``state``
        (``up``, ``lost``, ...)."""
        if not wait_until(lambda: self.status()["link"] == state, timeout_s, ignore=NOT_SERVING):
            raise AssertionError(f"link not {state!r} within {timeout_s} s:\n{self.log()}")

    def stop(self, timeout_s: float = WAIT_S) -> int:
        """SIGTERM, bounded wait, reap; the exit code (SIGKILL, then -9, if it hangs)."""
        return terminate(self.proc, timeout_s)

    def kill(self) -> None:
        """SIGKILL if still running, and reap (idempotent)."""
        kill(self.proc)

    def __enter__(self) -> DaemonProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
