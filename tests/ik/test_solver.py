"""companion.ik.solve: deadline, early exit, warm-start continuity, unreachable G, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.ik import SolverSettings, StopReason, TargetMode, layout, solve, solver, warm_up
from companion.kinematics import rotation_angle
from companion.kinematics.arm import Arm, Pose
from companion.papers.objective import IKObjective
from devkit.timing import FakeClock

ARM = Arm.default()
G = Pose(-20, 3, 40, 0, 10, 15)  # the papers' target: unreachable within the Table 2 limits
#: Where a test checks where the hand ends up, the search is bounded by generations alone
#: (``budget_ms=None``): its answer then depends on the target and the seed, never on how busy
#: the machine is (a solve preempted past a wall-clock budget would end short of the target).
#: These targets converge within 6 generations (2430 for DE alone, below): far below the bound.
GENERATIONS = 10_000
UNTIMED = SolverSettings(max_generations=GENERATIONS)


def reachable(seed: int) -> Pose:
    q = ARM.random_q_rad(np.random.default_rng(seed), 1)[0]
    return Pose.from_matrix(ARM.fk_matrix(q))


def independent_errors(arm: Arm, q_deg, target: Pose) -> tuple[float, float]:
    """Errors recomputed with the numpy FK, not the compiled kernel."""
    e = IKObjective(arm, target).errors(np.radians(q_deg))
    return float(e.pos_err_cm[0]), float(e.ori_err_deg[0])


def _charged_run(
    monkeypatch,
    clock,
    init_s,
    per_generation_s,
    cpu_clock=None,
    init_cpu_s=0.0,
    cpu_per_generation_s=None,
):
    """The kernel advances ``clock`` as if initialising took ``init_s`` and each generation
    took ``per_generation_s`` (a callable of the generation's index); ``cpu_clock``, if given,
    advances by ``init_cpu_s`` for the initialisation and by ``cpu_per_generation_s`` (a
    callable likewise; default: like ``clock``) for generations."""
    cpu_step = per_generation_s if cpu_per_generation_s is None else cpu_per_generation_s
    warm_up()  # the kernels loaded, so solve() calls the patched entry point
    real_search = solver._search
    count = [0]

    def search(*args):
        fresh = args[len(layout.SEARCH_ARRAYS)] & layout.START_NEW  # start
        done = real_search(*args)
        if fresh:
            clock.advance(init_s)
            if cpu_clock is not None:
                cpu_clock.advance(init_cpu_s)
        for _ in range(args[-1]):
            clock.advance(per_generation_s(count[0]))
            if cpu_clock is not None:
                cpu_clock.advance(cpu_step(count[0]))
            count[0] += 1
        return done

    monkeypatch.setattr(solver, "_search", search)


def test_deadline_on_a_fake_clock(monkeypatch):
    # Initialisation and every generation cost 1 ms; chunks of 1, 2, then 3 (not 4: a chunk
    # takes at most half the time left), then single generations while one fits in half of
    # what is left: at 9 ms, 1.5 ms are left and none is started.
    clock = FakeClock(0.0)
    _charged_run(monkeypatch, clock, 1e-3, lambda i: 1e-3)
    res = solve(ARM, G, budget_ms=10.5, seed=1, clock=clock, cpu_clock=clock)
    assert res.stop_reason is StopReason.DEADLINE and not res.converged
    assert res.generations == 8
    assert res.elapsed_ms == pytest.approx(9.0)


def test_a_generation_predicted_to_overrun_is_not_started(monkeypatch):
    # 3 ms each: init ends at 3, one generation at 6; the next would take more than half of the
    # 4 ms left, so it is not started.
    clock = FakeClock(0.0)
    _charged_run(monkeypatch, clock, 3e-3, lambda i: 3e-3)
    res = solve(ARM, G, budget_ms=10.0, seed=1, clock=clock, cpu_clock=clock)
    assert res.stop_reason is StopReason.DEADLINE
    assert res.generations == 1
    assert res.elapsed_ms == pytest.approx(6.0)


@pytest.mark.parametrize("seed", range(20))
def test_reachable_poses_converge_early_within_tolerance(seed):
    target = reachable(seed)
    res = solve(ARM, target, seed=seed, budget_ms=None, settings=UNTIMED)
    assert res.converged and res.stop_reason is StopReason.CONVERGED
    assert res.pos_err_cm <= 1e-3 and res.ori_err_deg <= 1e-3
    pos, ori = independent_errors(ARM, res.q_deg, target)
    assert pos == pytest.approx(res.pos_err_cm, abs=1e-9)
    assert ori == pytest.approx(res.ori_err_deg, abs=1e-6)
    assert ARM.within_limits(res.q_rad)


def test_tighter_tolerances_are_honoured():
    res = solve(
        ARM,
        reachable(3),
        seed=0,
        tol_pos_cm=1e-6,
        tol_ori_deg=1e-6,
        budget_ms=None,
        settings=UNTIMED,
    )
    assert res.converged and res.pos_err_cm <= 1e-6 and res.ori_err_deg <= 1e-6


def test_modified_convention_arm_solves_too():
    arm = Arm.from_package_file("paper_arm_modified.toml")
    q = arm.random_q_rad(np.random.default_rng(4), 1)[0]
    target = Pose.from_matrix(arm.fk_matrix(q))
    res = solve(arm, target, seed=0, budget_ms=None, settings=UNTIMED)
    assert res.converged
    pos, ori = independent_errors(arm, res.q_deg, target)
    assert pos <= 1e-3 and ori <= 1e-3


def test_unreachable_target_is_reported_not_converged_with_both_errors():
    # The ceiling far off: on however busy a machine, the 5 ms of CPU run out first.
    res = solve(ARM, G, seed=0, budget_ms=5.0, ceiling_ms=1000.0)
    assert not res.converged and res.stop_reason is StopReason.DEADLINE
    pos, ori = independent_errors(ARM, res.q_deg, G)
    assert pos == pytest.approx(res.pos_err_cm, abs=1e-9)
    assert ori == pytest.approx(res.ori_err_deg, abs=1e-6)
    # The spec page: no configuration within limits comes closer than ~48° in orientation
    # while on target; whatever compromise is returned, it is far from tolerance.
    assert res.pos_err_cm > 1e-3 or res.ori_err_deg > 1.0
    assert ARM.within_limits(res.q_rad)


def test_iteration_limit():
    res = solve(ARM, G, seed=0, budget_ms=None, settings=SolverSettings(max_generations=7))
    assert res.stop_reason is StopReason.ITERATION_LIMIT and res.generations == 7


def test_without_a_budget_only_the_generation_limit_ends_the_search(monkeypatch):
    # Every generation costs a second on the clock: any budget would have ended the search at
    # once; with none, the generation limit does, and the clock only says how long it took.
    clock = FakeClock(0.0)
    _charged_run(monkeypatch, clock, 1.0, lambda i: 1.0)
    few = SolverSettings(max_generations=7)
    res = solve(ARM, G, budget_ms=None, seed=1, settings=few, clock=clock, cpu_clock=clock)
    assert res.stop_reason is StopReason.ITERATION_LIMIT and res.generations == 7
    assert res.elapsed_ms == pytest.approx(8000.0)


@pytest.mark.parametrize("target", [G, reachable(2), reachable(5)])
def test_without_a_budget_the_result_is_the_one_an_uncut_budget_gives(target):
    # A clock that never moves: the budget cuts nothing short, chunk after chunk.
    bounded = SolverSettings(max_generations=40)
    budgeted = solve(ARM, target, seed=9, budget_ms=10.0, settings=bounded, clock=FakeClock())
    unbudgeted = solve(ARM, target, seed=9, budget_ms=None, settings=bounded)
    assert unbudgeted.stop_reason is budgeted.stop_reason is not StopReason.DEADLINE
    assert (unbudgeted.q, unbudgeted.generations, unbudgeted.evaluations) == (
        budgeted.q,
        budgeted.generations,
        budgeted.evaluations,
    )


def test_same_seed_same_result():
    few = SolverSettings(max_generations=40)
    a = solve(ARM, G, seed=123, budget_ms=None, settings=few)
    b = solve(ARM, G, seed=123, budget_ms=None, settings=few)
    c = solve(ARM, G, seed=124, budget_ms=None, settings=few)
    assert a.q_deg == b.q_deg and a.evaluations == b.evaluations
    assert a.q_deg != c.q_deg


def test_generator_seed_is_accepted_and_repeatable():
    a = solve(ARM, reachable(8), seed=np.random.default_rng(5), budget_ms=None, settings=UNTIMED)
    b = solve(ARM, reachable(8), seed=np.random.default_rng(5), budget_ms=None, settings=UNTIMED)
    assert a.q_deg == b.q_deg


CIRCLE_CENTRE_DEG = [20, 70, 50, 20, 30, 10]  # elbow bent: the whole circle is reachable


def circle_path(samples: int, radius_cm: float) -> list[Pose]:
    """Hand circle in a plane, orientation fixed; centred on a comfortable pose."""
    centre = ARM.fk(CIRCLE_CENTRE_DEG)
    return [
        Pose(
            centre.x_cm,
            centre.y_cm + radius_cm * math.cos(2 * math.pi * k / samples),
            centre.z_cm + radius_cm * math.sin(2 * math.pi * k / samples),
            centre.roll_deg,
            centre.pitch_deg,
            centre.yaw_deg,
        )
        for k in range(samples + 1)
    ]


def test_warm_start_follows_a_path_without_branch_flips():
    # 5 cm circle in 200 samples (about 0.16 cm per sample, a 100 Hz path at 16 cm/s).
    path = circle_path(200, 5.0)
    first = solve(
        ARM, path[0], seed=0, q_start_deg=CIRCLE_CENTRE_DEG, budget_ms=None, settings=UNTIMED
    )
    assert first.converged
    q_prev = np.array(first.q_deg)
    steps = []
    for k, pose in enumerate(path[1:], start=1):
        res = solve(ARM, pose, seed=k, q_start_deg=q_prev, budget_ms=None, settings=UNTIMED)
        assert res.converged, k
        steps.append(np.abs(np.array(res.q_deg) - q_prev).max())
        q_prev = np.array(res.q_deg)
    # No elbow or wrist flip: every joint moves only a little between samples.
    assert max(steps) < 1.0


def test_cold_solves_along_the_same_path_do_jump_branches():
    # Why the warm start matters: independent cold solves pick different branches.
    path = circle_path(40, 5.0)
    q = [
        np.array(solve(ARM, pose, seed=k, budget_ms=None, settings=UNTIMED).q_deg)
        for k, pose in enumerate(path)
    ]
    jumps = [np.abs(b - a).max() for a, b in zip(q, q[1:], strict=False)]
    assert max(jumps) > 20.0


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"target": Pose(0, 0, 50, 0, 0, 0), "budget_ms": 0.0}, "budget_ms"),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "budget_ms": math.nan}, "budget_ms"),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "budget_ms": -5}, "budget_ms"),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "ceiling_ms": 0.0}, "ceiling_ms"),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "ceiling_ms": math.inf}, "ceiling_ms"),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "tol_pos_cm": 0}, "tol_pos_cm"),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "tol_ori_deg": math.inf}, "tol_ori_deg"),
        ({"target": [1, 2, 3, 4, 5]}, "6 values"),
        ({"target": [1, 2, math.nan, 4, 5, 6]}, "Pose.z_cm"),
        ({"target": [1, 2, math.inf, 4, 5, 6]}, "Pose.z_cm"),
        ({"target": 7}, "target"),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "q_start_deg": [0] * 5}, "q_start_deg"),
        (
            {"target": Pose(0, 0, 50, 0, 0, 0), "q_start_deg": [0, 90, 0, 0, math.nan, 0]},
            "q_start_deg",
        ),
        ({"target": Pose(0, 0, 50, 0, 0, 0), "seed": "abc"}, "seed"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        solve(ARM, **kwargs)


@settings(max_examples=40)
@given(
    st.tuples(*[st.floats(-200, 200)] * 3, *[st.floats(-720, 720)] * 3),
    st.integers(0, 2**64 - 1),
)
def test_result_is_always_within_limits_whatever_the_target(values, seed):
    res = solve(ARM, Pose(*values), seed=seed, budget_ms=1.0)
    assert ARM.within_limits(res.q_rad, tol_rad=0.0)
    assert math.isfinite(res.pos_err_cm) and math.isfinite(res.ori_err_deg)


@pytest.mark.parametrize("seed", range(10))
def test_de_only_converged_result_is_within_both_tolerances(seed):
    # Without least-squares steps DE ends just inside the tolerances; the returned joints must
    # be the ones that met both, not an earlier record with a lower cm² + deg² sum.
    target = reachable(100 + seed)
    de_only = SolverSettings(
        lm_iterations=0,
        pop_size=20,
        stall_generations=100,
        stall_gain=0.5,
        max_generations=GENERATIONS,
    )
    res = solve(
        ARM, target, seed=seed, budget_ms=None, settings=de_only, tol_pos_cm=1e-2, tol_ori_deg=1e-2
    )
    assert res.converged
    pos, ori = independent_errors(ARM, res.q_deg, target)
    assert pos <= 1e-2 and ori <= 1e-2


def test_target_beyond_float_range_reports_infinite_errors_and_an_in_limit_start():
    # |p| beyond ~1e154 cm: every cost overflows to inf and no configuration becomes the
    # record. The result must not be whatever np.empty holds: another solve's errors and joints.
    solve(ARM, G, budget_ms=1.0, seed=0)  # leave a finished solve's arrays behind
    start = (10.0, 80.0, 20.0, 10.0, 20.0, 30.0)
    far = Pose(1e308, -1e308, 1e200, 0, 0, 0)
    res = solve(ARM, far, budget_ms=1.0, ceiling_ms=1000.0, seed=0, q_start_deg=start)
    assert not res.converged and res.stop_reason is StopReason.DEADLINE
    assert res.pos_err_cm == math.inf and res.ori_err_deg == math.inf
    assert res.q_deg == pytest.approx(start)
    cold = solve(ARM, Pose(1e155, 0, 0, 0, 0, 0), budget_ms=1.0, seed=0)
    assert cold.pos_err_cm == math.inf and not cold.converged
    assert ARM.within_limits(np.radians(cold.q_deg))


# -- any arm, target modes, the deadline under load ------------------------------------------------

SHIPPED = ["puma560.toml", "ur5.toml", "ur10.toml", "panda.toml", "stanford.toml", "baxter.toml"]
SHIPPED += ["ur5.urdf"]


def _numpy_errors(arm: Arm, q, target: Pose) -> tuple[float, float]:
    t = arm.fk_matrix(np.asarray(q))
    pos = float(np.linalg.norm(t[:3, 3] - target.position_cm))
    ori = float(np.degrees(rotation_angle(target.rotation, t[:3, :3])))
    return pos, ori


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_arm_solves_and_no_answer_is_wrong(name):
    # "Converged" must mean within both tolerances by the numpy FK, and never outside limits.
    arm = Arm.from_package_file(name)
    rng = np.random.default_rng(1616)
    for i, q in enumerate(arm.random_q_rad(rng, 4)):
        target = Pose.from_matrix(arm.fk_matrix(q))
        res = solve(arm, target, seed=i, budget_ms=None, settings=UNTIMED)
        assert res.converged, (name, i, res)
        assert arm.within_limits(res.q_rad, tol_rad=0.0)
        pos, ori = _numpy_errors(arm, res.q_rad, target)
        assert pos <= 1e-3 + 1e-9 and ori <= 1e-3 + 1e-9


def test_prismatic_joint_comes_back_in_cm():
    arm = Arm.from_package_file("stanford.toml")
    q = np.array([0.3, -0.5, 80.0, 0.2, 0.4, -0.1])
    res = solve(arm, Pose.from_matrix(arm.fk_matrix(q)), seed=0, budget_ms=None, settings=UNTIMED)
    assert res.converged
    assert 30.48 <= res.q_deg[2] <= 127.0
    assert res.q_deg[2] == pytest.approx(res.q_rad[2])
    assert res.q_deg[0] == pytest.approx(math.degrees(res.q_rad[0]))


def test_position_mode_ignores_the_orientation():
    q = ARM.random_q_rad(np.random.default_rng(5), 1)[0]
    t = ARM.fk_matrix(q)
    target = Pose(*t[:3, 3], 123.0, -45.0, 77.0)  # an orientation the hand cannot have there
    assert not solve(ARM, target, seed=0, budget_ms=5.0).converged
    res = solve(ARM, target, seed=0, budget_ms=None, settings=UNTIMED, mode=TargetMode.POSITION)
    assert res.converged and res.ori_err_deg == 0.0
    pos, _ = _numpy_errors(ARM, res.q_rad, target)
    assert pos <= 1e-3 + 1e-9


@pytest.mark.parametrize("axis", [(0, 0, 1), (1, 0, 0)])
def test_position_axis_mode_points_the_tool_axis(axis):
    arm = Arm.from_package_file("ur5.toml")
    q = arm.random_q_rad(np.random.default_rng(7), 1)[0]
    t = arm.fk_matrix(q)
    want = t[:3, :3] @ np.asarray(axis, float)
    target = Pose(*t[:3, 3], 0.0, 0.0, 0.0)
    res = solve(
        arm,
        target,
        seed=3,
        budget_ms=None,
        settings=UNTIMED,
        mode=TargetMode.POSITION_AXIS,
        tool_axis=axis,
        direction=want * 2.0,
    )
    assert res.converged
    got = arm.fk_matrix(res.q_rad)
    pointing = got[:3, :3] @ np.asarray(axis, float)
    unit = want / np.linalg.norm(want)
    # atan2, not acos: acos of a dot product near 1 is only good to ~1e-6 degrees.
    angle = math.degrees(
        math.atan2(float(np.linalg.norm(np.cross(pointing, unit))), float(pointing @ unit))
    )
    assert angle <= 1e-3 + 1e-9
    assert res.ori_err_deg == pytest.approx(angle, abs=1e-6)
    assert np.linalg.norm(got[:3, 3] - t[:3, 3]) <= 1e-3 + 1e-9


def test_position_axis_default_direction_is_the_targets_axis():
    q = ARM.random_q_rad(np.random.default_rng(8), 1)[0]
    target = Pose.from_matrix(ARM.fk_matrix(q))
    res = solve(
        ARM, target, seed=0, budget_ms=None, settings=UNTIMED, mode=TargetMode.POSITION_AXIS
    )
    assert res.converged
    got = ARM.fk_matrix(res.q_rad)
    assert float(got[:3, 2] @ target.rotation[:, 2]) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"mode": "pose"}, "mode"),
        ({"mode": TargetMode.POSITION_AXIS, "direction": (0, 0, 0)}, "direction"),
        ({"mode": TargetMode.POSITION_AXIS, "tool_axis": (1, 0)}, "tool_axis"),
    ],
)
def test_bad_mode_arguments_are_named(kwargs, name):
    with pytest.raises(ValueError, match=name):
        solve(ARM, G, budget_ms=1.0, **kwargs)


def test_one_preempted_generation_does_not_end_the_search_early(monkeypatch):
    # Generations take 0.1 ms except the first, which a busy machine stretched to 4 ms. The
    # old rule ("elapsed + slowest so far") stopped at ~4.3 ms of a 10 ms budget; the capped
    # moving average lets the search go on, and it still stops within the budget.
    clock = FakeClock(0.0)
    _charged_run(monkeypatch, clock, 1e-4, lambda i: 4e-3 if i == 0 else 1e-4)
    res = solve(ARM, G, budget_ms=10.0, seed=1, clock=clock, cpu_clock=clock)
    assert res.stop_reason is StopReason.DEADLINE
    assert res.generations > 40
    assert 9.0 <= res.elapsed_ms <= 10.0


_ARMS = {name: Arm.from_package_file(name) for name in SHIPPED}


@settings(max_examples=40)
@given(
    st.sampled_from(SHIPPED),
    st.sampled_from(list(TargetMode)),
    st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7),
    st.tuples(*[st.floats(-30, 30)] * 3),
    st.integers(0, 2**32),
)
def test_property_no_false_convergence_and_never_outside_limits(name, mode, u, shift_cm, seed):
    # A reachable pose (joints drawn from u) moved by up to 30 cm: often unreachable. Whatever
    # comes back is within the limits, and "converged" holds by the numpy FK.
    arm = _ARMS[name]
    q = arm.lower_q + np.asarray(u[: arm.dof]) * (arm.upper_q - arm.lower_q)
    t = arm.fk_matrix(q)
    t[:3, 3] += shift_cm
    target = Pose.from_matrix(t)
    res = solve(arm, target, seed=seed, budget_ms=2.0, mode=mode)
    assert arm.within_limits(res.q_rad, tol_rad=0.0)
    if res.converged:
        got = arm.fk_matrix(res.q_rad)
        assert np.linalg.norm(got[:3, 3] - target.position_cm) <= 1e-3 + 1e-9
        if mode is TargetMode.POSE:
            assert math.degrees(rotation_angle(target.rotation, got[:3, :3])) <= 1e-3 + 1e-9
        elif mode is TargetMode.POSITION_AXIS:
            cos = float(got[:3, 2] @ target.rotation[:, 2])
            assert math.degrees(math.acos(min(1.0, cos))) <= 1e-3 + 1e-9


def test_initialisation_preempted_for_half_the_budget_does_not_end_the_search(monkeypatch):
    # Another process held the CPU for 11 ms of the initialisation, which itself used 0.1 ms of
    # CPU. In wall time alone one generation would look like 11 ms; the CPU time says 0.1 ms,
    # and the search runs on until it has had its 20 ms of CPU (11 ms of wall time later).
    wall, cpu = FakeClock(0.0), FakeClock(0.0)
    _charged_run(monkeypatch, wall, 11e-3, lambda i: 1e-4, cpu_clock=cpu, init_cpu_s=1e-4)
    res = solve(ARM, G, budget_ms=20.0, seed=1, clock=wall, cpu_clock=cpu)
    assert res.stop_reason is StopReason.DEADLINE
    assert res.generations > 40
    assert 19.0 <= res.elapsed_ms - 11.0 <= 20.0


def test_the_estimate_carries_over_to_the_next_call_on_the_same_clock(monkeypatch):
    # Second call on the same clock: the initialisation and a first chunk run in one compiled
    # call, sized by the estimate the first call left (1 ms a generation), and the budget holds.
    clock = FakeClock(0.0)
    _charged_run(monkeypatch, clock, 1e-3, lambda i: 1e-3)
    solve(ARM, G, budget_ms=10.5, seed=1, clock=clock, cpu_clock=clock)
    calls = []
    real = solver._search

    def counting(*args):
        calls.append(args[-1])
        return real(*args)

    monkeypatch.setattr(solver, "_search", counting)
    started = clock()
    res = solve(ARM, G, budget_ms=10.5, seed=1, clock=clock, cpu_clock=clock)
    assert res.stop_reason is StopReason.DEADLINE
    assert calls[0] == 4  # the initialisation plus 4 generations in the first call
    assert clock() - started <= 10.5e-3
    assert res.generations >= 7


# -- the budget is CPU time, the ceiling wall time -----------------------------------------------

#: A reachable pose that seed 80 solves in 6 generations after the initialisation (untimed).
SLOW = reachable(80)


def test_a_preempted_solve_is_not_ended_by_its_budget(monkeypatch):
    # Other processes hold the CPU: every step takes 5 ms of wall time for 0.05 ms of the
    # solver's CPU. Past the 10 ms budget in wall time, the search has used 0.1 ms of CPU and
    # goes on to the answer an untimed solve gives.
    untimed = solve(ARM, SLOW, seed=80, budget_ms=None, settings=UNTIMED)
    assert untimed.converged and untimed.generations == 6
    wall, cpu = FakeClock(0.0), FakeClock(0.0)
    _charged_run(monkeypatch, wall, 5e-3, lambda i: 5e-3, cpu, 5e-5, lambda i: 5e-5)
    res = solve(ARM, SLOW, seed=80, budget_ms=10.0, ceiling_ms=100.0, clock=wall, cpu_clock=cpu)
    assert res.stop_reason is StopReason.CONVERGED
    assert (res.q, res.generations) == (untimed.q, untimed.generations)
    assert res.elapsed_ms == pytest.approx(40.0)  # init, chunks of 1, 2 and 4 generations


def test_a_wall_clock_budget_gave_the_preempted_solve_up(monkeypatch):
    # The same solve with the budget counted in wall time (the CPU clock is the wall clock, and
    # the ceiling the budget): the initialisation took half of it, and no generation is started.
    clock = FakeClock(0.0)
    _charged_run(monkeypatch, clock, 5e-3, lambda i: 5e-3)
    res = solve(ARM, SLOW, seed=80, budget_ms=10.0, ceiling_ms=10.0, clock=clock, cpu_clock=clock)
    assert res.stop_reason is StopReason.DEADLINE and not res.converged
    assert res.generations == 0


def test_the_ceiling_ends_a_search_starved_of_cpu(monkeypatch):
    # 1 ms of wall time a generation for 0.01 ms of CPU: the 10 ms budget is never spent; the
    # 30 ms ceiling ends the search, and nothing is started that would end past it.
    wall, cpu = FakeClock(0.0), FakeClock(0.0)
    _charged_run(monkeypatch, wall, 1e-3, lambda i: 1e-3, cpu, 1e-5, lambda i: 1e-5)
    res = solve(ARM, G, seed=1, budget_ms=10.0, ceiling_ms=30.0, clock=wall, cpu_clock=cpu)
    assert res.stop_reason is StopReason.CEILING and not res.converged
    assert 27.0 <= res.elapsed_ms <= 30.0


def test_without_a_ceiling_it_is_a_multiple_of_the_budget(monkeypatch):
    # The CPU clock does not move at all; the default ceiling, 4 x the 5 ms budget, ends it.
    assert solver.CEILING_PER_BUDGET == 4.0
    wall, cpu = FakeClock(0.0), FakeClock(0.0)
    _charged_run(monkeypatch, wall, 1e-3, lambda i: 1e-3, cpu, 0.0, lambda i: 0.0)
    res = solve(ARM, G, seed=1, budget_ms=5.0, clock=wall, cpu_clock=cpu)
    assert res.stop_reason is StopReason.CEILING
    assert 17.0 <= res.elapsed_ms <= 20.0


def test_a_cpu_heavy_solve_stops_on_its_budget(monkeypatch):
    # Half a core: 2 ms of wall time for each 1 ms of CPU. The 10 ms of CPU run out at about
    # 20 ms of wall time, well inside the 100 ms ceiling: DEADLINE, the budget kept.
    wall, cpu = FakeClock(0.0), FakeClock(0.0)
    _charged_run(monkeypatch, wall, 2e-3, lambda i: 2e-3, cpu, 1e-3, lambda i: 1e-3)
    res = solve(ARM, G, seed=1, budget_ms=10.0, ceiling_ms=100.0, clock=wall, cpu_clock=cpu)
    assert res.stop_reason is StopReason.DEADLINE and not res.converged
    assert res.generations == 8  # as on one clock (test_deadline_on_a_fake_clock)
    assert res.elapsed_ms == pytest.approx(18.0)


def test_a_ceiling_below_the_budget_ends_the_search_first(monkeypatch):
    clock = FakeClock(0.0)
    _charged_run(monkeypatch, clock, 1e-3, lambda i: 1e-3)
    res = solve(ARM, G, seed=1, budget_ms=20.0, ceiling_ms=10.5, clock=clock, cpu_clock=clock)
    assert res.stop_reason is StopReason.CEILING
    assert res.generations == 8 and res.elapsed_ms == pytest.approx(9.0)


def test_without_a_budget_neither_clock_ends_the_search(monkeypatch):
    # A second of wall time and of CPU a generation: only the generation limit ends it, with
    # the answer of a search that never reads a clock.
    wall, cpu = FakeClock(0.0), FakeClock(0.0)
    _charged_run(monkeypatch, wall, 1.0, lambda i: 1.0, cpu, 1.0, lambda i: 1.0)
    few = SolverSettings(max_generations=7)
    res = solve(ARM, G, budget_ms=None, seed=1, settings=few, clock=wall, cpu_clock=cpu)
    assert res.stop_reason is StopReason.ITERATION_LIMIT and res.generations == 7
    monkeypatch.undo()
    plain = solve(ARM, G, budget_ms=None, seed=1, settings=few)
    assert (res.q, res.evaluations) == (plain.q, plain.evaluations)


# -- methods ---------------------------------------------------------------------------------------


def test_methods_are_settings_by_name():
    from companion.ik import DEFAULT_METHOD, DEFAULT_SETTINGS, METHODS, method_settings

    assert DEFAULT_METHOD == "restarts" and list(METHODS) == ["restarts", "memetic", "de"]
    assert method_settings() is DEFAULT_SETTINGS is METHODS["restarts"]
    assert method_settings("de") is METHODS["de"]
    assert method_settings("de", pop_size=20).pop_size == 20
    assert method_settings("restarts", pop_size=6, lm_iterations=10).stall_generations == 0
    with pytest.raises(ValueError, match="method='ga' must be one of restarts, memetic, de"):
        method_settings("ga")
    with pytest.raises(
        ValueError, match="lm_iterations=3 goes with method 'restarts' or 'memetic'"
    ):
        method_settings("de", lm_iterations=3)
    with pytest.raises(ValueError, match="F=0.9 goes with method 'memetic' or 'de'"):
        method_settings("restarts", F=0.9)
    with pytest.raises(ValueError, match="stall_generations=2 goes with method 'memetic' or 'de'"):
        method_settings("restarts", stall_generations=2)
    with pytest.raises(ValueError, match="is method 'restarts'"):
        method_settings("memetic", stall_generations=0)


#: Reachable poses and seeds of which about a third need more than the first LM run.
HARD_SEEDS = range(300, 500)


def test_restarts_run_no_de_generation():
    # Every generation of "restarts" draws the population anew: as many restarts as
    # generations, and no DE step lowers anything.
    from companion.ik import METHODS

    went_on = 0
    for seed in HARD_SEEDS:
        res = solve(ARM, reachable(seed), seed=seed, budget_ms=None, settings=UNTIMED)
        assert res.converged
        assert res.restarts == res.generations and res.de_improvements == 0
        went_on += res.generations > 0
    assert went_on >= 20  # the seeds do exercise restarts
    assert METHODS["restarts"].stall_generations == 0


def test_memetic_runs_de_generations_that_lower_the_best():
    # "memetic" keeps its population between restarts: DE steps run (generations beyond
    # the restarts), and on some poses one of them lowers the population's best cost.
    from companion.ik import method_settings

    memetic = method_settings("memetic", max_generations=GENERATIONS)
    de_steps = gains = 0
    for seed in HARD_SEEDS:
        res = solve(ARM, reachable(seed), seed=seed, budget_ms=None, settings=memetic)
        assert res.converged
        de_steps += res.generations - res.restarts
        gains += res.de_improvements
        assert res.de_improvements <= res.generations - res.restarts
    assert de_steps > 0 and gains > 0


@pytest.mark.parametrize("seed", range(4))
def test_de_reaches_the_daemons_tolerances_without_least_squares(seed):
    from companion.ik import method_settings

    target = reachable(200 + seed)
    de = method_settings("de", max_generations=GENERATIONS)
    res = solve(
        ARM, target, seed=seed, budget_ms=None, settings=de, tol_pos_cm=0.01, tol_ori_deg=0.1
    )
    assert res.converged and res.lm_iterations == 0 and res.generations > 10
    pos, ori = independent_errors(ARM, res.q_deg, target)
    assert pos <= 0.01 and ori <= 0.1


def test_jit_kernels_are_called_without_numbas_dispatcher(monkeypatch):
    """On numba's JIT, solve() calls the compiled search itself, not the dispatcher that would
    look up every argument's type at every call; the answers are those of the dispatcher, bit
    for bit, in both the pose and the pointing-direction mode (which builds its goal with
    ``goal_matrix``)."""
    warm_up()
    if solver.kernels_origin() != "numba JIT":
        pytest.skip("the ahead-of-time module is loaded")
    from companion.ik import kernels

    assert solver._search is not kernels.search
    assert solver._goal_matrix is not kernels.goal_matrix
    targets = [reachable(seed) for seed in range(8)]

    def answers() -> list[tuple]:
        return [
            (r.q, r.pos_err_cm, r.ori_err_deg, r.generations, r.lm_iterations)
            for seed, t in enumerate(targets)
            for r in (
                solve(ARM, t, seed=seed, budget_ms=None, settings=UNTIMED),
                solve(
                    ARM,
                    t,
                    seed=seed,
                    budget_ms=None,
                    settings=UNTIMED,
                    mode=TargetMode.POSITION_AXIS,
                ),
            )
        ]

    direct = answers()
    monkeypatch.setattr(solver, "_search", kernels.search)
    monkeypatch.setattr(solver, "_goal_matrix", kernels.goal_matrix)
    assert answers() == direct
