"""Fixtures of the core's tests (the rig itself is in ``rig.py``)."""

from __future__ import annotations

import pytest

from tests.daemon.core.rig import Rig


@pytest.fixture
def rig():
    rig = Rig()
    rig.up()
    return rig
