"""``armbridge run``: the daemon as a systemd ``Type=notify`` service or in the foreground.

Start-up order: the config (a bad one exits 2 with nothing opened), the instance lock (a second
``run`` for the same control socket exits 2, "already running (pid N)", having touched nothing:
see :mod:`companion.daemon.instance_lock`), the IK kernels (compiled the first time, loaded from
numba's cache after), the control socket, the autopilot link; READY=1
once the autopilot's heartbeat is heard. SIGTERM/SIGINT stop (parking if configured), SIGHUP
re-reads the config.
"""

from __future__ import annotations

import gc
import logging
import signal
import sys
import threading

from companion import ik
from companion.daemon.config import DaemonConfig, load_config
from companion.daemon.control_socket import ControlServer
from companion.daemon.instance_lock import AlreadyRunning, InstanceLock, lock_path
from companion.daemon.service import ArmDaemon
from companion.daemon.systemd import Notifier
from companion.errors import ConfigError
from firmware_interface import LinkError, LinkState

log = logging.getLogger("armbridge")


def reload_config(daemon: ArmDaemon, config_path: str) -> bool:
    """SIGHUP: re-read the config through the same ``load_config`` as start-up, so the same
    bounds apply; a config it refuses never reaches ``daemon.reload`` and the running one is
    kept. True if the new config was handed over."""
    try:
        config = load_config(config_path)
    except ConfigError as exc:
        log.error("reload refused, keeping the running config: %s", exc)
        return False
    daemon.reload(config)
    return True


def run(config_path: str) -> int:
    """``armbridge run``: the service until SIGTERM/SIGINT; returns the exit code."""
    config = load_config(config_path)  # ConfigError → exit 2, nothing opened or sent
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


def _run(config: DaemonConfig, config_path: str) -> int:
    # Compile (first start) or load (later starts) the IK kernels now, before the link opens
    # and long before READY, so that no target pays for it.
    log.info("IK kernels ready in %.2f s", ik.warm_up())
    # The start-up heap (numpy, numba, pymavlink: ~120k objects) never dies. Frozen, the
    # collector's full passes skip it: one took ~55 ms here, long enough to stall the control
    # thread past a 20 ms target slot; after the freeze it takes microseconds.
    gc.freeze()
    # The GIL is handed between threads every 5 ms by default: under a flood the reader thread
    # would keep a `stop` on the control socket waiting in 5 ms slices. 1 ms costs nothing
    # while only one thread has work (measured: python -m bench.flood).
    sys.setswitchinterval(0.001)
    stop = threading.Event()
    reload = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGHUP, lambda *_: reload.set())

    notifier = Notifier()
    daemon = ArmDaemon(config)
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
        notifier.status("waiting for the autopilot heartbeat")
        ready = False
        ping_s = notifier.watchdog_period_s / 2 if notifier.watchdog_period_s else 1.0
        while not stop.is_set():
            link_up = daemon.link is not None and daemon.link.state is LinkState.UP
            if link_up and not ready:
                ready = True
                notifier.ready("autopilot link up")
                log.info("ready: autopilot link up")
            if reload.is_set():
                reload.clear()
                notifier.reloading()
                reload_config(daemon, config_path)
                notifier.ready()
            if daemon.healthy:
                notifier.watchdog()
            s = daemon.status()
            notifier.status(
                f"link {s['link']}; {s['counters']['accepted']} targets accepted, "
                f"{s['counters']['failed'] + s['counters']['denied']} refused"
            )
            stop.wait(min(ping_s, 0.5))
    finally:
        notifier.stopping()
        log.info("stopping%s", " (parking)" if config.park_on_stop else "")
        # The daemon first: it refuses new requests and answers every waiting one (its socket
        # client is still connected to read the answer); then the socket closes.
        daemon.close(park=config.park_on_stop)
        if server is not None:
            server.close()
        notifier.close()
    return 0
