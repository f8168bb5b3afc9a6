"""The calling convention of the compiled IK kernels: index constants and argument types.

Plain Python (no numba), so that :mod:`companion.ik.solver` can drive the kernels ahead-of-time
compiled module (:mod:`companion.ik.aot`) without importing numba. :mod:`companion.ik.kernels`
reads these names as globals, which numba freezes into the compiled code; numba's cache does
not notice when they change, so ``kernels.LAYOUT_SHA256`` records this file's digest (a change
here must change that line, which invalidates the cache; ``tests/ik/test_aot.py`` checks it).
"""

from __future__ import annotations

# Layout of the float parameter vector ``fp``.
F_SCALE, F_CR, F_TOL_POS, F_TOL_ORI, F_MOVE_W, F_LM_LAMBDA0, F_LM_WINDOW, F_LM_PROGRESS = range(8)
F_SPREAD, F_STALL_GAIN = 8, 9
N_FPARAMS = 10
# Layout of the integer parameter vector ``ip``.
I_LM_ITERS, I_STALL_GENS, I_HAS_PREV, I_MODE = range(4)
N_IPARAMS = 4
# Target modes (``ip[I_MODE]``): the whole pose, the position only, the position and one axis.
MODE_POSE, MODE_POSITION, MODE_AXIS = range(3)
# Flags of ``kernels.search``'s ``start`` (the low two bits are the mode).
START_HAS_PREV, START_GOAL_SET, START_NEW = 4, 8, 16
# Layout of the integer state vector ``st`` (counters the Python loop reads).
S_GENERATIONS, S_EVALUATIONS, S_LM_ITERATIONS, S_STALE, S_RESTARTS = range(5)
N_STATE = 5
# Layout of ``record``: best found so far, pose-wise (q is kept in ``record_q``).
R_COST, R_POS_CM, R_ORI_DEG = range(3)
# Layout of ``out`` (what ``kernels.search`` returns to Python, 7 + 2n floats): the record, the
# counters, then the record's joints in joint units (rad, cm) and in user units (deg, cm).
O_COST, O_POS_CM, O_ORI_DEG, O_GENERATIONS, O_EVALUATIONS, O_LM_ITERATIONS, O_RESTARTS = range(7)
O_Q = 7

# ``kernels.search``'s array arguments, in order: (name, numpy dtype, ndim), each C-contiguous.
# The ahead-of-time module is compiled for exactly these and its wrapper does not check them
# (a wrong dtype is read as raw memory), so the solver checks its arrays once, when it makes them.
SEARCH_ARRAYS = (
    ("pop", "float64", 2),
    ("cost", "float64", 1),
    ("stuck", "bool", 1),
    ("frames", "float64", 3),
    ("jp", "float64", 2),
    ("goal", "float64", 2),
    ("q_start", "float64", 1),
    ("fp", "float64", 1),
    ("ip", "int64", 1),
    ("rng", "uint64", 1),
    ("st", "int64", 1),
    ("record", "float64", 1),
    ("record_q", "float64", 1),
    ("out", "float64", 1),
)
# Then the scalars: start (int64), x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg (float64),
# gens (int64); it returns a bool.
