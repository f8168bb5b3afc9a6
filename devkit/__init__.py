"""Helpers shared by the tests and the benches, not shipped in the wheel.

Process starters for the simulator and the daemon, one MAVLink peer (a scripted autopilot or a
ground station on UDP, TCP or a pty), one control-socket client on the daemon's own framing,
bounded waits and a fake clock, the reliability campaign, the joint-step detector, the keep-out
sampling and the config writers. ``tests/`` and ``bench/`` import it; the product packages never do.
"""
