"""The world-frame tests live in ``tests/daemon/core/test_world.py``; this module only
re-exports the world helpers that other test modules import from here."""

from tests.daemon.core.rig import telemetry, world_goto, world_rig

__all__ = ["telemetry", "world_goto", "world_rig"]
