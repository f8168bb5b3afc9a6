"""``armbridge run``: the daemon as a systemd ``Type=notify`` service or in the foreground.

Start-up order: the config (a bad one exits 2 with nothing opened), the instance lock (a second
``run`` for the same control socket exits 2, "already running (pid N)", having touched nothing:
see :mod:`companion.daemon.instance_lock`), the IK kernels (compiled the first time, loaded from
numba's cache after; systemd's start timeout is extended meanwhile), the control socket, the
autopilot link; then READY=1, without waiting for the autopilot (see ``_run``: the wait is
logged and shown in STATUS=). SIGTERM/SIGINT stop (parking if configured), SIGHUP
re-reads the config.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import select
import signal
import sys
import time
from dataclasses import dataclass, field

from companion import ik
from companion.daemon import pose_file
from companion.daemon.config import DaemonConfig, load_config
from companion.daemon.control_socket import ControlServer
from companion.daemon.instance_lock import AlreadyRunning, InstanceLock, lock_path
from companion.daemon.service import ArmDaemon
from companion.daemon.systemd import Notifier
from companion.errors import ConfigError
from firmware_interface import LinkError

log = logging.getLogger("armbridge")


#: How long systemd should wait for the kernels (EXTEND_TIMEOUT_USEC before warm_up): a first
#: compile on a Raspberry Pi 4 is a minute or more; loading them from the cache takes ~1 s.
KERNEL_LOAD_ALLOWANCE_S = 300.0
#: While no autopilot heartbeat has been heard: the first warning after this long, then again
#: at each doubling of the wait, up to once every WAIT_LOG_MAX_S.
WAIT_LOG_FIRST_S = 5.0
WAIT_LOG_MAX_S = 300.0


@dataclass
class HeartbeatWait:
    """Says, in the log, how long the daemon has waited for the autopilot: once at
    ``WAIT_LOG_FIRST_S``, then at 2x, 4x... (capped at one line per ``WAIT_LOG_MAX_S``), and once
    when it is heard. A link that is lost later is the link's business (it logs that itself)."""

    url: str
    started_s: float
    heard: bool = False
    _next_log_s: float = field(init=False)

    def __post_init__(self) -> None:
        self._next_log_s = self.started_s + WAIT_LOG_FIRST_S

    def update(self, link_up: bool, now_s: float) -> None:
        if self.heard:
            return
        waited_s = now_s - self.started_s
        if link_up:
            self.heard = True
            log.info("autopilot link up after %.1f s", waited_s)
        elif now_s >= self._next_log_s:
            log.warning(
                "no heartbeat from the autopilot on %s after %.0f s: is it powered, is the "
                "url (port, baud) right, does it send MAVLink on that port? "
                "`armbridge doctor` checks the link",
                self.url,
                waited_s,
            )
            self._next_log_s = now_s + min(max(waited_s, WAIT_LOG_FIRST_S), WAIT_LOG_MAX_S)


class SignalFlags:
    """SIGTERM / SIGINT and SIGHUP for the main loop, without a lock in the handler.

    A handler runs on the main thread between two of its bytecodes: ``threading.Event.set()``
    there takes the event's lock, which the main thread may hold inside ``Event.wait()`` at
    that moment (a daemon once did not exit within 10 s of SIGTERM). The handlers only set a
    flag; the wake-up comes from the interpreter itself, which writes the signal's number to
    a pipe (``signal.set_wakeup_fd``) that :meth:`wait` selects on."""

    def __init__(self) -> None:
        self.stop = False
        self.reload = False
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._read_fd, False)
        os.set_blocking(self._write_fd, False)
        self._previous_fd = signal.set_wakeup_fd(self._write_fd, warn_on_full_buffer=False)

    def on_stop(self, signum: int, frame: object) -> None:
        self.stop = True

    def on_reload(self, signum: int, frame: object) -> None:
        self.reload = True

    def wait(self, timeout_s: float) -> None:
        """Until a signal came or ``timeout_s`` passed."""
        self._drain()  # the wake-ups of signals already seen
        if self.stop or self.reload:
            return
        ready, _, _ = select.select([self._read_fd], [], [], timeout_s)
        if ready:
            self._drain()

    def _drain(self) -> None:
        with contextlib.suppress(BlockingIOError):
            os.read(self._read_fd, 4096)

    def close(self) -> None:
        signal.set_wakeup_fd(self._previous_fd)
        os.close(self._read_fd)
        os.close(self._write_fd)


def reload_config(daemon: ArmDaemon, config_path: str, server: ControlServer | None = None) -> bool:
    """SIGHUP: re-read the config through the same ``load_config`` as start-up, so the same
    bounds apply; a config it refuses never reaches ``daemon.reload`` and the running one is
    kept. The control socket's limits go to ``server``. True if the new config was handed
    over."""
    try:
        config = load_config(config_path)
    except ConfigError as exc:
        log.error("reload refused, keeping the running config: %s", exc)
        return False
    daemon.reload(config)
    if server is not None:
        server.reconfigure(config.control_max_connections, config.control_idle_timeout_s)
    return True


def run(config_path: str) -> int:
    """``armbridge run``: the service until SIGTERM/SIGINT; returns the exit code."""
    config = load_config(config_path)  # ConfigError → exit 2, nothing opened or sent
    if config.control_socket:
        _make_socket_directory(config)
    # Before anything is touched (the kernel cache, the socket, the link, the signing state):
    # a second instance must leave the first one's socket and link alone. Held until exit.
    lock = InstanceLock(lock_path(config_path, config.control_socket))
    try:
        lock.acquire()
    except AlreadyRunning as exc:
        log.error("%s", exc)
        return 2
    except OSError as exc:
        raise ConfigError(
            config.source,
            "control.socket",  # the lock sits beside it (without one: in the runtime directory)
            f"cannot lock {lock.path}: {exc.strerror or exc}",
        ) from exc
    try:
        return _run(config, config_path)
    finally:
        lock.release()


def _make_socket_directory(config: DaemonConfig) -> None:
    """The socket's directory, made (mode 0750) when missing, as systemd's ``RuntimeDirectory=``
    would for the service: a foreground ``run`` with the default ``/run/armbridge/control.sock``
    then works as root. ``check-config`` already refused a directory this user cannot make."""
    assert config.control_socket is not None
    directory = os.path.dirname(config.control_socket)
    try:
        os.mkdir(directory, 0o750)
    except FileExistsError:
        return
    except OSError as exc:
        raise ConfigError(
            config.source, "control.socket", f"cannot create {directory}: {exc.strerror or exc}"
        ) from exc
    log.info("created %s for the control socket", directory)


def _run(config: DaemonConfig, config_path: str) -> int:
    notifier = Notifier()
    # Compile (first start) or load (later starts) the IK kernels now, before the link opens
    # and READY, so that no target pays for it. A first compile takes 10-20 s on 2 cores and
    # longer on a Raspberry Pi: systemd's start timeout (90 s by default) is extended for it.
    notifier.notify(
        f"EXTEND_TIMEOUT_USEC={int(KERNEL_LOAD_ALLOWANCE_S * 1e6)}",
        "STATUS=loading the IK kernels (the first start compiles them)",
    )
    log.info("IK kernels ready in %.2f s (%s)", ik.warm_up(), ik.kernels_origin())
    if config.keepout:
        from companion.kinematics import collision_kernels

        collision_kernels.warm_up()  # the checks on every step: compiled before READY
    # The start-up heap (numpy, numba, pymavlink: ~120k objects) never dies. Frozen, the
    # collector's full passes skip it: one took ~55 ms here, long enough to stall the control
    # thread past a 20 ms target slot; after the freeze it takes microseconds.
    gc.freeze()
    # The GIL is handed between threads every 5 ms by default: under a flood the reader thread
    # would keep a `stop` on the control socket waiting in 5 ms slices. 1 ms costs nothing
    # while only one thread has work (measured: python -m bench.flood).
    sys.setswitchinterval(0.001)
    signals = SignalFlags()
    signal.signal(signal.SIGTERM, signals.on_stop)
    signal.signal(signal.SIGINT, signals.on_stop)
    signal.signal(signal.SIGHUP, signals.on_reload)

    daemon = ArmDaemon(config)
    saver = None
    if config.pose_file is not None:
        saved = pose_file.load(config.pose_file, config.calibration)
        if saved is not None:
            daemon.restore_pose(saved)
            log.info(
                "outputs left at %s (%s): the joints are taken there%s",
                dict(pose_file.pose_of(saved)),
                config.pose_file,
                "" if pose_file.same_everywhere(saved) else " (within a band: re-sent first)",
            )
        saver = pose_file.PoseSaver(config.pose_file)
        daemon.pose_sink = saver.offer
    server = None
    try:
        if config.control_socket:
            # Before the link opens: a socket path the system refuses is a config error, and
            # nothing has been sent yet. Requests wait in the queue until start().
            try:
                server = ControlServer(config.control_socket, daemon)
            except OSError as exc:
                raise ConfigError(
                    config.source, "control.socket", f"cannot listen on it: {exc.strerror or exc}"
                ) from exc
        try:
            daemon.start()
        except LinkError as exc:
            # E.g. the serial device is not there (yet): say so in one line and fail, so
            # systemd's Restart=on-failure tries again (RestartSec=2 in the shipped unit).
            log.error("cannot open the autopilot link: %s", exc)
            return 1
        except OSError as exc:
            # The link maps transport errors to its own; an OSError left is the signing state
            # file, the only file it writes (its directory may be missing or read-only).
            signing = config.link.signing
            if signing is None or signing.state_path is None:
                raise
            raise ConfigError(
                config.source, "link.signing_state", f"cannot write it: {exc.strerror or exc}"
            ) from exc
        # READY as soon as the daemon serves (socket listening, link open), not when the
        # autopilot is first heard: a companion board often boots before the flight
        # controller is powered or plugged in, and a start that waits for it would time out
        # and restart in a loop. Until the link is up, `status` says so and targets are
        # answered "no autopilot link"; the log and STATUS= say what it waits for.
        device = daemon.link.waiting_for_device if daemon.link is not None else None
        if device is not None:
            notifier.ready(f"waiting for {device} (the flight controller's serial port)")
        else:
            notifier.ready(f"waiting for the autopilot heartbeat on {config.link.url}")
        log.info(
            "serving%s; waiting for the autopilot heartbeat on %s",
            f" on {config.control_socket}" if config.control_socket else "",
            config.link.url,
        )
        waiting = HeartbeatWait(config.link.url, time.monotonic())
        ping_s = notifier.watchdog_period_s / 2 if notifier.watchdog_period_s else 1.0
        while not signals.stop:
            # Not status(): a snapshot built on the control thread twice a second for this.
            s = daemon.brief()
            # Up for targets once the autopilot has answered us, so knows our route.
            waiting.update(s["link"] == "up" and s["autopilot_heard_us"], time.monotonic())
            if signals.reload:
                signals.reload = False
                notifier.reloading()
                reload_config(daemon, config_path, server)
                notifier.ready()
            # The watchdog is fed only while both threads serve: a control socket whose thread
            # died would leave operators unable to stop the arm, so systemd restarts us.
            if daemon.healthy and (server is None or server.alive):
                notifier.watchdog()
            device = daemon.link.waiting_for_device if daemon.link is not None else None
            notifier.status(
                f"link {s['link']}; {s['accepted']} targets accepted, {s['refused']} refused"
                if waiting.heard
                else f"waiting for {device} (the flight controller's serial port)"
                if device is not None
                else f"waiting for the autopilot heartbeat on {config.link.url}"
            )
            signals.wait(min(ping_s, 0.5))
    finally:
        signals.close()
        notifier.stopping()
        log.info("stopping%s", " (parking)" if config.park_on_stop else "")
        # The daemon first: it refuses new requests and answers every waiting one (its socket
        # client is still connected to read the answer); then the socket closes.
        daemon.close(park=config.park_on_stop)
        if saver is not None:
            saver.close()  # what the control thread offered last
        if server is not None:
            server.close()
        notifier.close()
    return 0
