"""One ``armbridge run`` per config: an exclusive ``flock`` taken before anything is touched.

What identifies "one config" is the daemon's public address, its control socket: two daemons
that share it would fight over it (the second deleted the first's socket before this lock, and
both drove the autopilot), whatever their config files are called. The lock file is
``<control.socket>.lock``, beside the socket, in a directory the daemon must be able to write to
anyway (``/run/armbridge`` under the shipped unit). A config without a control socket is
identified by its file's real path (symlinks resolved): the lock is
``armbridge-<sha256 of that path, 16 hex digits>.lock`` in ``$RUNTIME_DIRECTORY`` (systemd's
``RuntimeDirectory=``), else ``$XDG_RUNTIME_DIR``, else the temporary directory; that one only
catches a second instance started the same way (the unit's ``PrivateTmp=`` hides /tmp).

The holder writes its pid into the file once it has the lock; a second instance reads it for
its one-line refusal and changes nothing: it neither truncates nor deletes the file, which is
never deleted (deleting a lock file lets a third instance lock a new inode beside the old one).
The kernel releases the lock when the holder exits, however it exits.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import stat
import tempfile
from collections.abc import Mapping
from pathlib import Path

#: The longest pid file content read back (a pid is at most 7 digits on Linux).
_PID_READ_BYTES = 32


class AlreadyRunning(Exception):
    """Another ``armbridge run`` holds the lock; ``pid`` is what it wrote (None: unreadable)."""

    def __init__(self, path: Path, pid: int | None) -> None:
        self.path = path
        self.pid = pid
        super().__init__(
            f"already running (pid {pid if pid is not None else 'unknown'}; lock {path})"
        )


def lock_path(
    config_path: str | os.PathLike[str],
    control_socket: str | None,
    environ: Mapping[str, str] | None = None,
) -> Path:
    """The lock file for a config at ``config_path`` with ``control_socket`` (see above)."""
    if control_socket:
        return Path(control_socket + ".lock")
    env = os.environ if environ is None else environ
    digest = hashlib.sha256(os.fsencode(os.path.realpath(config_path))).hexdigest()[:16]
    directory = (
        env.get("RUNTIME_DIRECTORY", "").split(":")[0]
        or env.get("XDG_RUNTIME_DIR")
        or tempfile.gettempdir()
    )
    return Path(directory) / f"armbridge-{digest}.lock"


class InstanceLock:
    """Holds the lock at ``path`` from :meth:`acquire` to :meth:`release` (or process exit).

    :meth:`acquire` raises :class:`AlreadyRunning` if another process holds it, and
    ``OSError`` if the file cannot be created or opened (a missing directory, a symlink, not a
    regular file).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self) -> None:
        # O_NOFOLLOW: in a shared directory a planted symlink must not make us write our pid
        # into someone else's file. No O_TRUNC: a second instance must leave the pid alone.
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o644)
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise OSError(errno.EINVAL, "not a regular file", str(self.path))
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise AlreadyRunning(self.path, _read_pid(fd)) from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd

    def release(self) -> None:
        """Unlock and close (the file stays: see the module's docstring). Idempotent."""
        if self._fd is not None:
            os.close(self._fd)  # closing the last descriptor drops the flock
            self._fd = None

    def __enter__(self) -> InstanceLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read_pid(fd: int) -> int | None:
    """The pid the holder wrote, or None (not written yet, or not a pid)."""
    text = os.pread(fd, _PID_READ_BYTES, 0).decode("ascii", "replace").strip()
    return int(text) if text.isdigit() else None
