"""Joint motion limiting: never faster than the limit, all joints arrive together."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.daemon.motion import limit_step

angles = st.lists(st.floats(-180, 180), min_size=6, max_size=6)


def test_small_move_reaches_the_goal_exactly():
    assert limit_step([0, 90, 0, 0, 0, 0], [1, 89, 0, 0.5, 0, 0], 3.0) == (1, 89, 0, 0.5, 0, 0)


def test_large_move_is_scaled_so_joints_arrive_together():
    step = limit_step([0, 0, 0], [30, -15, 0], 3.0)
    assert step == pytest.approx((3.0, -1.5, 0.0))


@given(angles, angles, st.floats(0.01, 50))
def test_no_joint_ever_moves_more_than_the_limit_and_progress_is_made(cur, goal, max_step):
    nxt = limit_step(cur, goal, max_step)
    assert all(abs(n - c) <= max_step + 1e-9 for n, c in zip(nxt, cur, strict=True))
    before = max(abs(g - c) for c, g in zip(cur, goal, strict=True))
    after = max(abs(g - n) for n, g in zip(nxt, goal, strict=True))
    assert after <= max(before - max_step, 0.0) + 1e-9


def test_bad_step():
    with pytest.raises(ValueError, match="max_step_deg"):
        limit_step([0], [1], 0.0)
    with pytest.raises(ValueError, match="goal joints"):
        limit_step([0, 1], [1], 1.0)
