"""The compiled objective computes the numpy objective's J."""

from __future__ import annotations

import numpy as np
import pytest

from companion.kinematics.arm import Arm
from companion.papers import constants
from companion.papers.compiled import CompiledIKObjective
from companion.papers.objective import IKObjective, OrientationMetric


@pytest.mark.parametrize("arm_file", ["paper_arm.toml", "paper_arm_modified.toml"])
@pytest.mark.parametrize("metric", list(OrientationMetric))
def test_compiled_cost_equals_the_numpy_cost(arm_file, metric):
    rng = np.random.default_rng(7)
    arm = Arm.from_package_file(arm_file)
    obj = IKObjective(
        arm, constants.TARGET_G, metric=metric, movement_weight=0.2, q_prev_rad=rng.normal(size=6)
    )
    fast = CompiledIKObjective(obj)
    q = np.vstack([arm.random_q_rad(rng, 20), rng.uniform(-4.0, 4.0, (20, 6))])  # some outside
    np.testing.assert_allclose(fast.cost(q), obj.cost(q), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(fast.lower, obj.lower)
    np.testing.assert_array_equal(fast.errors(q[:3]).ori_err_deg, obj.errors(q[:3]).ori_err_deg)


def test_compiled_cost_rejects_a_wrong_shape():
    fast = CompiledIKObjective(IKObjective(Arm.default(), constants.TARGET_G))
    with pytest.raises(ValueError, match=r"\(S, 6\)"):
        fast.cost(np.zeros(6))
