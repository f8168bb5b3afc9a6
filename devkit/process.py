"""Stopping a test's subprocess: SIGTERM, a bounded wait, SIGKILL if it hangs; always reaped."""

from __future__ import annotations

import signal
import subprocess

from devkit.timing import WAIT_S


def terminate(proc: subprocess.Popen, timeout_s: float = WAIT_S) -> int:
    """SIGTERM, wait up to ``timeout_s`` and reap; the exit code (-9 if it had to be killed)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        kill(proc)
        return proc.returncode
    finally:
        kill(proc)


def kill(proc: subprocess.Popen) -> None:
    """SIGKILL if still running, and reap (idempotent)."""
    if proc.poll() is None:
        proc.kill()
        proc.wait(WAIT_S)
