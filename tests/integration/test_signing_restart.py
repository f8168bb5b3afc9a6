"""A daemon restarted more than a minute after the simulated autopilot booted must
reconnect with signing on. A simulator that kept its own signing timestamp where it started
(pymavlink adds 1 per frame) would look, to a companion whose clock is over a minute ahead,
like a stream more than a minute old ("bad signature") for ever; it adopts the companion's
newer timestamp, as the signing spec asks.

The "two minutes later" is the link's wall clock set 120 s ahead: the same timestamps a daemon
started two minutes after the simulator would use, without waiting two minutes.
"""

from __future__ import annotations

import time

import pytest

from firmware_interface.link import LinkConfig, LinkState, MavlinkLink
from firmware_interface.signing import SigningConfig

pytestmark = pytest.mark.slow  # a simulator and daemon processes

KEY = bytes(range(32))


def test_a_daemon_started_two_minutes_after_the_autopilot_reconnects(sims, tmp_path):
    key_file = tmp_path / "signing.key"
    key_file.write_bytes(KEY)
    key_file.chmod(0o600)
    sim = sims("--udp", "127.0.0.1:0", "--signing-key", str(key_file))
    signing = SigningConfig(
        KEY, state_path=tmp_path / "signing.state", wall_clock=lambda: time.time() + 120.0
    )
    with MavlinkLink.open(sim.url, LinkConfig(heartbeat_rate_hz=5.0, signing=signing)) as link:
        link.wait_for_autopilot(10.0)
        assert link.state is LinkState.UP
        # Only frames sent before the simulator heard our timestamp can have been refused.
        assert link.stats.rejected_bad_signature == 0
