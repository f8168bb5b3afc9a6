"""The armbridge service: targets in, servo PWM out.

Modules: :mod:`~companion.daemon.service` (``ArmDaemon``: the control loop and safety rules),
:mod:`~companion.daemon.requests` (requests, outcomes, replies, payload parsing),
:mod:`~companion.daemon.config` (the TOML config and its validation),
:mod:`~companion.daemon.control_socket` (the JSON-lines control socket) and
:mod:`~companion.daemon.client` (its client),
:mod:`~companion.daemon.motion` (joint speed limit), :mod:`~companion.daemon.systemd`
(sd_notify), :mod:`~companion.daemon.run` (``armbridge run``), :mod:`~companion.daemon.demo`
(``armbridge demo``), :mod:`~companion.daemon.cli` (the ``armbridge`` command).

Nothing is imported here, so that the command line starts without loading the solver.
"""
