"""The calling convention of the compiled IK kernels: index constants and argument types.

Plain Python (no numba), so that :mod:`companion.ik.solver` can drive the kernels ahead-of-time
compiled module (:mod:`companion.ik.aot`) without importing numba. :mod:`companion.ik.kernels`
reads these names as globals, which numba freezes into the compiled code; numba's cache does
not notice when they change, so ``kernels.LAYOUT_SHA256`` records this file's digest (a change
here must change that line, which invalidates the cache; ``tests/ik/test_aot.py`` checks it).
"""

from __future__ import annotations

# Layout of the float parameter vector ``fparams``.
F_SCALE, F_CR, F_TOL_POS, F_TOL_ORI, F_MOVE_W, F_LM_LAMBDA0, F_LM_WINDOW, F_LM_PROGRESS = range(8)
F_SPREAD, F_STALL_GAIN, F_LM_NEAR = 8, 9, 10
N_FPARAMS = 11
# Layout of the integer parameter vector ``iparams``.
I_LM_ITERS, I_STALL_GENS, I_HAS_PREV, I_MODE, I_DOF, I_POP = range(6)
N_IPARAMS = 6
# Target modes (``iparams[I_MODE]``): the whole pose, the position only, the position and one axis.
MODE_POSE, MODE_POSITION, MODE_AXIS = range(3)
# Flags of ``kernels.search``'s ``start`` (the low two bits are the mode).
START_HAS_PREV, START_GOAL_SET, START_NEW = 4, 8, 16
# Layout of the integer state vector ``counts`` (counters the Python loop reads).
S_GENERATIONS, S_EVALUATIONS, S_LM_ITERATIONS, S_STALE, S_RESTARTS, S_DE_GAINS = range(6)
N_STATE = 6
# Layout of ``record``: best found so far, pose-wise (q is kept in ``record_q``).
R_COST, R_POS_CM, R_ORI_DEG = range(3)
# Layout of ``out`` (what ``kernels.search`` returns to Python, 8 + 2n floats): the record, the
# counters, then the record's joints in joint units (rad, cm) and in user units (deg, cm).
O_COST, O_POS_CM, O_ORI_DEG, O_GENERATIONS, O_EVALUATIONS, O_LM_ITERATIONS, O_RESTARTS = range(7)
O_DE_GAINS = 7
O_Q = 8

# ``kernels.search``'s array arguments, in order: (name, numpy dtype, ndim), each C-contiguous.
# Three buffers, not an argument per array: the compiled wrapper unboxes every array argument at
# every call (a reference-counted wrapper allocated and freed each), ~0.05 µs apiece.
# ``kernels.search`` cuts them into the arrays the kernels use; :mod:`companion.ik.solver` holds
# numpy views of the same memory. The ahead-of-time module is compiled for exactly these and its
# wrapper does not check them (a wrong dtype is read as raw memory), so the solver checks its
# arrays once, when it makes them.
SEARCH_ARRAYS = (
    ("fbuf", "float64", 1),
    ("ibuf", "int64", 1),
    ("rng", "uint64", 1),
)
# Then the scalars: start (int64), x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg (float64),
# gens (int64); it returns a bool.


def float_layout(n: int, n_pop: int) -> tuple[int, ...]:
    """Where each float64 array starts in ``fbuf``, for ``n`` joints and a population of
    ``n_pop``: pop ``(n_pop, n)``, cost ``(n_pop,)``, frames ``(n + 1, 4, 4)``, joint_params
    ``(6, n)``, goal ``(4, 4)``, q_start ``(n,)``, fparams ``(N_FPARAMS,)``, record ``(3,)``,
    record_q ``(n,)``, out ``(O_Q + 2n,)``, the kernels' scratch (``kernels._scratch``), then the
    buffer's length. Plain arithmetic: the kernels compile this very function."""
    pop = 0
    cost = pop + n_pop * n
    frames = cost + n_pop
    joint_params = frames + (n + 1) * 16
    goal = joint_params + 6 * n
    q_start = goal + 16
    fparams = q_start + n
    record = fparams + N_FPARAMS
    record_q = record + 3
    out = record_q + n
    scratch = out + O_Q + 2 * n
    # rot, pos, axes, points, res, jac, jtj, jtr, a, g, hold, q_try, q, out, then DE's trials
    # and their costs: kernels._scratch
    end = scratch + 9 + 3 + 3 * n + 3 * n + 6 + 6 * n + n * n + n + n * n + n + n + n + n + 3
    end += n_pop * n + n_pop
    return (
        pop,
        cost,
        frames,
        joint_params,
        goal,
        q_start,
        fparams,
        record,
        record_q,
        out,
        scratch,
        end,
    )


def int_layout(n_pop: int) -> tuple[int, ...]:
    """Where each int64 array starts in ``ibuf``: iparams ``(N_IPARAMS,)`` (``iparams[I_DOF]`` and
    ``iparams[I_POP]`` give the sizes), counts ``(N_STATE,)``, stuck ``(n_pop,)`` (0 or 1), then the
    length."""
    iparams = 0
    counts = iparams + N_IPARAMS
    stuck = counts + N_STATE
    end = stuck + n_pop
    return iparams, counts, stuck, end
