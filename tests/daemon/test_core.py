"""The core's tests live in ``tests/daemon/core/``, one module per part; this module only
re-exports the rig's names that other test modules import from here."""

from tests.daemon.core.rig import PARK, RATE_HZ, Rig, near

__all__ = ["PARK", "RATE_HZ", "Rig", "near"]
