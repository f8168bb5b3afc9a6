"""The whole chain in real processes on loopback: a ground station, the simulated autopilot, the
daemon.

``python -m sim_servo`` runs with a ground-station link (``--gcs``) and routes between it and
the daemon's link as ArduPilot does. ``armbridge run`` (as
``python -m companion.daemon.cli``) is the daemon, on UDP or on
the simulator's pseudo-terminal. A pymavlink ground station (:class:`sim_servo.gcs.GroundStation`)
sends ``MAV_CMD_USER_1`` targets through the autopilot and reads the daemon's COMMAND_ACKs. The
daemon's state comes from its control socket, the servos' and the hand's from the simulator's
query socket. Every wait is bounded and waits on a condition.
"""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.kinematics.arm import Arm
from devkit.sim_process import assert_within_quantisation
from devkit.timing import wait_until
from sim_servo.gcs import GroundStation

pytestmark = pytest.mark.slow  # three processes per test

WAIT_S = 15.0
G = (-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)  # the papers' target G: out of reach
KEY = bytes(range(100, 132))
#: The simulator's HEARTBEAT period; the daemon's loss timeout (3 s) is three of them, so a
#: heartbeat delayed by a loaded machine is not a link loss.
HEARTBEAT_PERIOD_S = 1.0
ARM = Arm.default()


class Chain:
    """A simulator and a daemon as subprocesses, and a ground station (the processes are owned
    by the ``sims`` and ``daemons`` fixtures, so they are always stopped and reaped)."""

    def __init__(
        self,
        sims,
        daemons,
        *,
        sim_args=(),
        pty=False,
        dialect="ardupilot",
        link_extra: dict | None = None,
        loss_timeout_s: float = 3.0,
        gcs_key: bytes | None = None,
    ) -> None:
        transport = ["--pty"] if pty else ["--udp", "127.0.0.1:0"]
        self.sim = sims(*transport, "--gcs", "127.0.0.1:0", *sim_args)
        self.daemon = daemons(
            {
                "link": {
                    "url": self.sim.url,
                    "dialect": dialect,
                    "loss_timeout_s": loss_timeout_s,
                    "command_timeout_s": 0.3,
                    **(link_extra or {}),
                },
                "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "joint_speed_deg_s": 720.0},
                "solver": {"seed": 1},
                "control": {"rate_hz": 50.0},
            }
        )
        self.daemon.wait_link("up", WAIT_S)
        self.gcs_url = self.sim.gcs_url
        self.gcs = GroundStation(self.gcs_url, signing_key=gcs_key)
        if not self.gcs.connect(WAIT_S):
            self.gcs.close()
            raise AssertionError("no companion HEARTBEAT through the autopilot")

    def status(self) -> dict:
        return self.daemon.status()

    def sim_state(self) -> dict:
        return self.sim.state()

    def target(self, pose, **ids):
        """Send a target from the ground station; its ACK (or None)."""
        sent_s = self.gcs.send_target(pose, **ids)
        return self.gcs.wait_ack(WAIT_S, since_s=sent_s)

    def settled(self) -> bool:
        return not self.status()["moving"] and self.sim_state()["settled"]


@pytest.fixture
def chain(sims, daemons):
    """Starts a chain (``chain(**kwargs)``); its ground station is closed at the end, the
    daemon and the simulator stopped by their fixtures (daemon first), asserting exit 0."""
    made: list[Chain] = []

    def start(**kwargs) -> Chain:
        made.append(Chain(sims, daemons, **kwargs))
        return made[-1]

    yield start
    for chain in made:
        chain.gcs.close()


def assert_hand_at(c: Chain, pose, slack_us: float) -> tuple[float, float]:
    """The sim's hand is at ``pose`` as nearly as PWM off by ``slack_us`` allows (rounding to
    whole µs: 0.5; plus the servos' dead band); the errors."""
    return assert_within_quantisation(
        pose, c.sim_state()["hand"], c.status()["current_deg"], slack_us=slack_us
    )


# Each transport and each dialect once (all four pairs cost the suite 13 s).
@pytest.mark.parametrize(
    ("pty", "dialect"), [(False, "ardupilot"), (True, "px4")], ids=["udp-ardupilot", "pty-px4"]
)
def test_ground_station_targets_end_to_end(chain, pty, dialect):
    """USER_1 from a ground station moves the simulated hand; G is FAILED with a STATUSTEXT and
    nothing moves; NaN is DENIED; a target for a component never heard is answered UNSUPPORTED by
    the autopilot itself, and the daemon never sees it."""
    c = chain(pty=pty, dialect=dialect, sim_args=["--flavour", dialect])
    target = ARM.fk([20, 70, 50, 20, 30, 10]).as_tuple()
    ack = c.target(target)
    assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED, ack
    assert wait_until(c.settled, WAIT_S)
    assert_hand_at(c, target, slack_us=1.5)  # rounding + the 1 µs dead band

    before = c.sim_state()["outputs"]
    ack = c.target(G)
    assert ack is not None and ack.result == mavlink.MAV_RESULT_FAILED
    assert any(t.startswith("unreachable: pos") for t in ack.statustexts), ack.statustexts
    ack = c.target((1.0, 2.0, math.nan, 0.0, 0.0, 0.0))
    assert ack is not None and ack.result == mavlink.MAV_RESULT_DENIED
    assert any("must be finite" in t for t in ack.statustexts), ack.statustexts
    assert c.sim_state()["outputs"] == before

    # Addressed to component 192, never heard: ArduPilot's routing keeps it and answers
    # UNSUPPORTED itself (from 1/1); PX4 ignores it without an answer (measured). The
    # daemon never sees it.
    c.gcs.send_target(target, component_id=192)
    if dialect == "ardupilot":
        ack = c.gcs.wait_for(
            lambda m: m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_USER_1, WAIT_S
        )
        assert ack is not None and ack.result == mavlink.MAV_RESULT_UNSUPPORTED
        assert (ack.get_srcSystem(), ack.get_srcComponent()) == (1, 1)
    else:
        assert wait_until(lambda: c.sim.events("ignored", to=[1, 192]), WAIT_S)
    assert c.gcs.wait_ack(0.5) is None  # and nothing from the daemon
    counters = c.status()["counters"]
    assert (counters["targets"], counters["accepted"], counters["failed"], counters["denied"]) == (
        3,
        1,
        1,
        1,
    )
    assert counters["servo_errors"] == 0


def test_streamed_trajectory_the_hand_follows_each_sample(chain):
    """A ground station streams a circle of the hand; after each ACK the hand is at that sample
    (instant servos without a dead band: what the sim reports is what the daemon commanded)."""
    c = chain(sim_args=["--slew-s-per-60deg", "0", "--deadband-us", "0"])
    centre = ARM.fk([10, 80, 40, 10, 20, 0])
    samples = []
    for k in range(12):
        angle = 2 * math.pi * k / 12
        samples.append(
            (
                centre.x_cm + 3 * math.cos(angle),
                centre.y_cm + 3 * math.sin(angle),
                centre.z_cm,
                centre.roll_deg,
                centre.pitch_deg,
                centre.yaw_deg,
            )
        )
    for sample in samples:
        ack = c.target(sample)
        assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED, sample
        assert wait_until(c.settled, WAIT_S)
        assert_hand_at(c, sample, slack_us=0.5)
    assert c.status()["counters"]["accepted"] == len(samples)


def test_signing_signed_accepted_unsigned_and_forged_refused(chain, tmp_path):
    """Vehicle, ground station and daemon share a key: a signed target moves the arm; the same
    target unsigned or signed with another key goes nowhere (the autopilot drops it)."""
    key_file = tmp_path / "signing.key"
    key_file.write_bytes(KEY)
    key_file.chmod(0o600)
    c = chain(
        sim_args=["--signing-key", str(key_file)],
        link_extra={"signing_key": str(key_file), "signing_state": str(tmp_path / "state")},
        gcs_key=KEY,
    )
    target = ARM.fk([30, 60, 40, 0, 20, 10]).as_tuple()
    for name, key in (("unsigned", None), ("forged", bytes(32))):
        rogue = GroundStation(c.gcs_url, signing_key=key, system_id=254)
        try:
            rogue.heartbeat()
            rogue.send_target(target)
            assert rogue.wait_ack(0.5) is None, name
        finally:
            rogue.close()
    assert c.status()["counters"]["targets"] == 0
    assert c.sim_state()["stats"]["rejected_signature"] >= 4  # 2 heartbeats, 2 targets
    ack = c.target(target)
    assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert wait_until(c.settled, WAIT_S)
    assert_hand_at(c, target, slack_us=1.5)


def test_link_loss_rejects_targets_temporarily_then_recovers(chain):
    """Heartbeats stop: the daemon holds and answers TEMPORARILY_REJECTED through the autopilot
    (which still routes); when they return, targets are accepted again.

    No step rests on timing: the test stops the heartbeat once the chain is up, sends the
    target that must be refused only once the daemon itself reports the link lost, and
    restarts the heartbeat only after that answer (the loss timeout is three heartbeat
    periods, so a late heartbeat is no loss)."""
    c = chain(loss_timeout_s=3 * HEARTBEAT_PERIOD_S)
    c.sim.pause_heartbeat()
    c.daemon.wait_link("lost", 3 * HEARTBEAT_PERIOD_S + WAIT_S)
    ack = c.target(ARM.fk([20, 70, 50, 20, 30, 10]).as_tuple())
    assert ack is not None and ack.result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED, ack
    c.sim.pause_heartbeat(False)
    c.daemon.wait_link("up", WAIT_S)
    ack = c.target(ARM.fk([20, 70, 50, 20, 30, 10]).as_tuple())
    assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
