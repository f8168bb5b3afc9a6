"""Compiled kernels of the deadline-bounded IK solver: one search loop, three methods.

A generation is either a DE step (rand/1/bin over the joint box) or a restart: the population
drawn anew (a quarter of it at corners of the joint box), the best found so far kept aside
("record"). After each, damped-least-squares (Levenberg–Marquardt) iterations with the analytic
geometric Jacobian refine the best individual that is not yet known to be stuck; the result is
clamped to the limits, accepted only if the pose error drops, and written back into the
population. The settings (:data:`companion.ik.METHODS`) make the methods: ``restarts``, the
default, restarts at every generation (LM from the best of NP fresh draws, no DE step);
``memetic`` runs DE steps and restarts after ``stall_generations`` without improvement; the
papers' ``de`` runs no LM.

:func:`search` is the entry point the solver calls (with :func:`goal_matrix` for the
pointing-direction mode); it holds every other kernel, compiled into it. Two ways to compile
them. Ahead of time: ``python -m companion.ik`` (the board install runs it) builds the two into
an extension module with explicit signatures (:mod:`companion.ik.aot`, numba's ``pycc``; a few
seconds of CPU), which the solver then loads without importing numba. Otherwise numba's JIT,
for the same signatures (:func:`companion.ik.warm_up` compiles them and the solver calls the
compiled functions, not numba's dispatchers), with the on-disk cache: the first compile after
an install takes about 20 s of CPU, later processes load the cache. Either way the daemon calls
:func:`companion.ik.warm_up` before READY, so no target pays for it. Where no cache location is
writable (no ``NUMBA_CACHE_DIR``, a read-only install and home), the JIT kernels still work,
compiled at every start, and a warning says how to fix it. The kernels are pure: arrays in and
out, no clocks. :mod:`companion.ik.solver` owns the deadline loop.

Twins: compiled code cannot call numpy's vectorised helpers, so some kernels re-implement a
numpy function of :mod:`companion.kinematics`. Each twin and the test that keeps the two equal
(in ``tests/ik/test_kernels.py``):

* :func:`fk_frames` ↔ ``Arm.fk_batch`` (the general chain ``F_0·M_1(q_1)·F_1·…``: DH arms of
  both conventions, prismatic joints, base, direction, URDF):
  ``test_compiled_fk_equals_numpy_fk``;
  its joint axes ↔ central differences of ``Arm.fk_matrix``:
  ``test_joint_axes_give_the_geometric_jacobian``;
* :func:`goal_matrix` ↔ ``Pose.as_matrix`` (``rotations.rpy_to_matrix``):
  ``test_goal_matrix_equals_pose_as_matrix``;
* :func:`pose_residual`'s orientation error ↔ ``rotations.rotation_angle``:
  ``test_pose_residual_is_position_and_rotation_vector``.

Units inside: radians and centimetres. The pose residual is ``(Δp in cm, rotation vector in
degrees)``, so one degree of orientation error weighs like one centimetre of position error. The
cost minimised is ``‖Δp‖² + θ_deg² + movement_weight·‖q − q_prev‖²`` (rad² for the last term).

Randomness: a splitmix64 stream whose state lives in a ``uint64[1]`` array, seeded by the caller
from a seed or ``numpy.random.Generator``. Passing numpy's ``Generator`` into compiled code
costs about 6 µs per call, more than a whole generation.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numba as nb
import numpy as np
from numba.extending import intrinsic

from companion.ik.layout import (
    F_CR,
    F_LM_LAMBDA0,
    F_LM_NEAR,
    F_LM_PROGRESS,
    F_LM_WINDOW,
    F_MOVE_W,
    F_SCALE,
    F_SPREAD,
    F_STALL_GAIN,
    F_TOL_ORI,
    F_TOL_POS,
    I_DOF,
    I_HAS_PREV,
    I_LM_ITERS,
    I_MODE,
    I_POP,
    I_STALL_GENS,
    MODE_AXIS,
    MODE_POSE,
    MODE_POSITION,
    N_IPARAMS,
    O_COST,
    O_DE_GAINS,
    O_EVALUATIONS,
    O_GENERATIONS,
    O_LM_ITERATIONS,
    O_ORI_DEG,
    O_POS_CM,
    O_Q,
    O_RESTARTS,
    R_COST,
    R_ORI_DEG,
    R_POS_CM,
    S_DE_GAINS,
    S_EVALUATIONS,
    S_GENERATIONS,
    S_LM_ITERATIONS,
    S_RESTARTS,
    S_STALE,
    START_GOAL_SET,
    START_HAS_PREV,
    START_NEW,
    float_layout,
    int_layout,
)
from companion.kinematics.numba_cache import cache_usable

log = logging.getLogger(__name__)


def _probe() -> int:
    return 0


#: numba caches this module's kernels on disk (see :mod:`companion.kinematics.numba_cache`).
CACHE = cache_usable(_probe, "IK kernels")

DEG_PER_RAD = 180.0 / math.pi
RAD_PER_DEG = math.pi / 180.0  # what math.radians multiplies by
TWO_PI = 2.0 * math.pi

# The calling convention (index constants) lives in layout.py, which the solver reads without
# numba. numba freezes these globals into the compiled code, and its cache is keyed to this
# file and each function's bytecode, not to them: this digest of layout.py makes a change there
# change this file too, so the cache is rebuilt (tests/ik/test_aot.py checks that it is current).
LAYOUT_SHA256 = "6a0fb365dc6c0a45f7170580c23dbedba4cd2f74ab4520503503ae242a83bf18"

_U64 = nb.types.uint64

# numba's option for a function compiled without NRT, its reference counting: for the kernels
# that allocate nothing, every array passed to or aliased in them is otherwise an atomic
# increment and decrement, an eighth of a solve's time (perf, UR5). A dict: numba's type stubs
# do not list this (underscored, but supported) option.
NO_NRT: dict[str, Any] = {"_nrt": False}

# The buffers' layouts (plain-Python arithmetic in layout.py), compiled for search().
_float_layout = nb.njit(cache=CACHE)(float_layout)
_int_layout = nb.njit(cache=CACHE)(int_layout)


# The views search() cuts its buffers into at every call (30 of them), built directly: numba's
# slice and reshape check the bounds and the shape and call a C helper for each, code that made
# _search and _scratch 19 KB of the kernels' 76 KB (numba's JIT on x86-64), fetched anew by a
# call that finds the caches cold (another program ran between two solves: a daemon's usual
# case). With these the two are 3 KB; the rest of the code is unchanged, and so are the results,
# bit for bit. Median CPU time per solve 0.92-0.95x on 8 arms not used to tune, after an rtb
# ik_LM call and bench.solver's judge and in a tight loop (docs/measurements/solver_ab_views.md:
# python -m bench.solver_ab --rev c0781f1 --poses 2000).
def _view_typer(typingctx, buf, start, shape):
    """``_view(buf, start, shape)``: ``buf[start : start + prod(shape)]`` as a C-contiguous
    array of ``shape`` (a tuple of ints), sharing ``buf``'s memory. No bounds check:
    ``layout.float_layout`` and ``layout.int_layout`` size the buffers for every view cut from
    them."""
    ndim = len(shape)

    def codegen(context, builder, sig, args):
        intp = nb.types.intp
        src = context.make_array(sig.args[0])(context, builder, args[0])
        out = context.make_array(sig.return_type)(context, builder)
        first = context.cast(builder, args[1], sig.args[1], intp)
        dims = [
            context.cast(builder, builder.extract_value(args[2], i), sig.args[2][i], intp)
            for i in range(ndim)
        ]
        strides = [src.itemsize] * ndim
        for i in range(ndim - 2, -1, -1):
            strides[i] = builder.mul(strides[i + 1], dims[i + 1])
        context.populate_array(
            out,
            data=builder.gep(src.data, [first], inbounds=True),
            shape=dims,
            strides=strides,
            itemsize=src.itemsize,
            meminfo=src.meminfo,
            parent=src.parent,
        )
        return out._getvalue()

    return nb.types.Array(buf.dtype, ndim, "C")(buf, start, shape), codegen


# Any: numba's stubs type an intrinsic's call with the typer's own arguments (typingctx first).
_view: Any = intrinsic(_view_typer)


# No inline="always" on these three: LLVM inlines them anyway (solve times unchanged, 1500
# poses: median 0.044 ms, p99 0.43 ms either way) and the first compile takes 2.5 s less.
@nb.njit(cache=CACHE)
def _next_u64(rng):
    z = rng[0] + _U64(0x9E3779B97F4A7C15)
    rng[0] = z
    z = (z ^ (z >> _U64(30))) * _U64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> _U64(27))) * _U64(0x94D049BB133111EB)
    return z ^ (z >> _U64(31))


@nb.njit(cache=CACHE)
def _rand(rng):
    """Uniform in [0, 1) with 53 random bits."""
    return float(_next_u64(rng) >> _U64(11)) * (1.0 / 9007199254740992.0)


@nb.njit(cache=CACHE)
def _randint(rng, n):
    return min(int(_rand(rng) * n), n - 1)


@nb.njit(cache=CACHE)
def _into_range(v, lo, hi, wraps):
    """``v`` into ``[lo, hi]``: a joint whose range holds a whole turn (``wraps`` = 1.0) takes
    the same angle modulo 2π (no false wall at ±180° on a joint that turns all the way round);
    any other is clamped."""
    if lo <= v <= hi:
        return v
    if wraps > 0.5:
        return min(lo + (v - lo) % TWO_PI, hi)
    return min(max(v, lo), hi)


# sin and cos of one angle for the FK, inline instead of two libm calls (the FK of a
# 10-joint arm called libm's sincos 10 times, an eighth of a solve's CPU time): the angle
# reduced by the nearest multiple of π/2 (π/2 in two parts, Cody–Waite: exact products for
# |n| < 2²⁰), then fdlibm's minimax polynomials on [−π/4, π/4] (k_sin.c, k_cos.c), within a
# few units in the last place of libm's values.
_INV_PIO2 = 6.36619772367581382433e-01
_PIO2_HI = 1.57079632673412561417e00  # the first 33 bits of π/2
_PIO2_LO = 6.07710050650619224932e-11  # π/2 − _PIO2_HI
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11


@nb.njit(cache=CACHE, **NO_NRT)
def _sin_cos(x):
    """``(sin x, cos x)``; libm's beyond |x| = 10⁵ (no joint turns that far)."""
    if not abs(x) < 1e5:
        return math.sin(x), math.cos(x)
    fn = math.floor(x * _INV_PIO2 + 0.5)
    y = (x - fn * _PIO2_HI) - fn * _PIO2_LO
    z = y * y
    # Estrin's scheme, not Horner's: three multiply-adds deep instead of six.
    z2 = z * z
    z4 = z2 * z2
    s = y + y * z * ((_S1 + z * _S2) + z2 * (_S3 + z * _S4) + z4 * (_S5 + z * _S6))
    c = 1.0 - 0.5 * z + z2 * ((_C1 + z * _C2) + z2 * (_C3 + z * _C4) + z4 * (_C5 + z * _C6))
    # The quadrant by arithmetic, not branches (it is as random as the angle): an odd one
    # swaps the two, the upper two negate both; each product is exact (by 0, 1 or −1).
    quadrant = int(fn)
    odd = float(quadrant & 1)
    even = 1.0 - odd
    sign = 1.0 - 2.0 * float((quadrant >> 1) & 1)
    return (s * even + c * odd) * sign, (c * even - s * odd) * sign


# inline="always" (numba inlines the function's code at each call site) on the FK, the
# residual, the normal equations, LM's step and the LDL solve, which LLVM left as calls: a call
# passes each array as its 7-9 scalars (the FK takes 8 arrays). Measured beside rtb pose by
# pose: 2-4 % less CPU per solve (hyper, ball, planar3, UR5), and the residual-sized step
# (:func:`_damped_step`) gains only inlined. The price is the first JIT compile (empty cache):
# 18 s of CPU instead of 15.5 s on the development machine (the ahead-of-time build likewise).
@nb.njit(cache=CACHE, inline="always", **NO_NRT)
def fk_frames(q, frames, joint_params, rot, pos, axes, points, want_axes):
    """Hand rotation ``rot`` (3×3) and position ``pos`` (3,) for joints ``q``.

    The arm is ``F_0 · M_1(q_1) · F_1 · … · M_n(q_n) · F_n`` (``frames``, ``(n + 1, 4, 4)``, cm; see
    :mod:`companion.kinematics.arm`); ``joint_params`` rows: direction, offset, 1.0 for a revolute
    joint (``M = Rz``) or 0.0 for a prismatic one (``M = Tz``), and (not used here) 1.0 for a joint
    whose range holds a whole turn, the lower and the upper limits. With ``want_axes``, also each
    joint's axis (the z axis it moves about or along, signed by its direction) and a point on it, in
    the base frame, for the geometric Jacobian."""
    n = q.shape[0]
    # Rotation and position as scalars until the end: stores into ``rot``/``pos`` that the
    # compiler cannot prove apart from ``frames`` would be re-read at every step.
    r00, r01, r02, p0 = frames[0, 0, 0], frames[0, 0, 1], frames[0, 0, 2], frames[0, 0, 3]
    r10, r11, r12, p1 = frames[0, 1, 0], frames[0, 1, 1], frames[0, 1, 2], frames[0, 1, 3]
    r20, r21, r22, p2 = frames[0, 2, 0], frames[0, 2, 1], frames[0, 2, 2], frames[0, 2, 3]
    for i in range(n):
        v = joint_params[0, i] * q[i] + joint_params[1, i]
        if want_axes:
            d = joint_params[0, i]
            axes[i, 0] = r02 * d
            axes[i, 1] = r12 * d
            axes[i, 2] = r22 * d
            points[i, 0] = p0
            points[i, 1] = p1
            points[i, 2] = p2
        if joint_params[2, i] > 0.5:
            sv, cv = _sin_cos(v)
            r00, r01 = r00 * cv + r01 * sv, r01 * cv - r00 * sv
            r10, r11 = r10 * cv + r11 * sv, r11 * cv - r10 * sv
            r20, r21 = r20 * cv + r21 * sv, r21 * cv - r20 * sv
        else:
            p0 += r02 * v
            p1 += r12 * v
            p2 += r22 * v
        f = i + 1
        f00, f01, f02, f03 = frames[f, 0, 0], frames[f, 0, 1], frames[f, 0, 2], frames[f, 0, 3]
        f10, f11, f12, f13 = frames[f, 1, 0], frames[f, 1, 1], frames[f, 1, 2], frames[f, 1, 3]
        f20, f21, f22, f23 = frames[f, 2, 0], frames[f, 2, 1], frames[f, 2, 2], frames[f, 2, 3]
        p0 += r00 * f03 + r01 * f13 + r02 * f23
        p1 += r10 * f03 + r11 * f13 + r12 * f23
        p2 += r20 * f03 + r21 * f13 + r22 * f23
        r00, r01, r02 = (
            r00 * f00 + r01 * f10 + r02 * f20,
            r00 * f01 + r01 * f11 + r02 * f21,
            r00 * f02 + r01 * f12 + r02 * f22,
        )
        r10, r11, r12 = (
            r10 * f00 + r11 * f10 + r12 * f20,
            r10 * f01 + r11 * f11 + r12 * f21,
            r10 * f02 + r11 * f12 + r12 * f22,
        )
        r20, r21, r22 = (
            r20 * f00 + r21 * f10 + r22 * f20,
            r20 * f01 + r21 * f11 + r22 * f21,
            r20 * f02 + r21 * f12 + r22 * f22,
        )
    rot[0, 0], rot[0, 1], rot[0, 2], pos[0] = r00, r01, r02, p0
    rot[1, 0], rot[1, 1], rot[1, 2], pos[1] = r10, r11, r12, p1
    rot[2, 0], rot[2, 1], rot[2, 2], pos[2] = r20, r21, r22, p2


@nb.njit(cache=CACHE)
def goal_matrix(x_cm, y_cm, z_cm, roll_rad, pitch_rad, yaw_rad, goal):
    """Fill ``goal`` (4×4) with the pose: translation in cm, ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    goal[0, 0] = cy * cp
    goal[0, 1] = cy * sp * sr - sy * cr
    goal[0, 2] = cy * sp * cr + sy * sr
    goal[1, 0] = sy * cp
    goal[1, 1] = sy * sp * sr + cy * cr
    goal[1, 2] = sy * sp * cr - cy * sr
    goal[2, 0] = -sp
    goal[2, 1] = cp * sr
    goal[2, 2] = cp * cr
    goal[0, 3] = x_cm
    goal[1, 3] = y_cm
    goal[2, 3] = z_cm
    goal[3, 0] = 0.0
    goal[3, 1] = 0.0
    goal[3, 2] = 0.0
    goal[3, 3] = 1.0


@nb.njit(cache=CACHE, inline="always", **NO_NRT)
def residual(rot, pos, goal, mode, res):
    """The residual of ``mode`` into ``res`` (6,): ``(p_goal − p [cm], a rotation vector
    [deg])``; returns ``(position error cm, the mode's angle error deg)``.

    * MODE_POSE: ``rotvec(R_goal·Rᵀ)``, the angle is the rotation angle;
    * MODE_AXIS: the rotation vector turning the hand's axis onto the target direction; the
      hand axis (hand frame) is ``goal[:3, 0]``, the direction (base frame) ``goal[:3, 2]``,
      both unit; the angle is the one between them;
    * MODE_POSITION: zero, and the angle 0.

    One function, not three: each level of compiled calls costs first-compile time.
    """
    for k in range(3):
        res[k] = goal[k, 3] - pos[k]
    pos_err = math.sqrt(res[0] * res[0] + res[1] * res[1] + res[2] * res[2])
    if mode == MODE_POSITION:
        res[3] = 0.0
        res[4] = 0.0
        res[5] = 0.0
        return pos_err, 0.0
    if mode == MODE_AXIS:
        wx = rot[0, 0] * goal[0, 0] + rot[0, 1] * goal[1, 0] + rot[0, 2] * goal[2, 0]
        wy = rot[1, 0] * goal[0, 0] + rot[1, 1] * goal[1, 0] + rot[1, 2] * goal[2, 0]
        wz = rot[2, 0] * goal[0, 0] + rot[2, 1] * goal[1, 0] + rot[2, 2] * goal[2, 0]
        dx, dy, dz = goal[0, 2], goal[1, 2], goal[2, 2]
        cx = wy * dz - wz * dy
        cy = wz * dx - wx * dz
        cz = wx * dy - wy * dx
        s = math.sqrt(cx * cx + cy * cy + cz * cz)
        c = wx * dx + wy * dy + wz * dz
        theta = math.atan2(s, c)
        if s < 1e-12:
            if c > 0.0:
                cx, cy, cz, s = 0.0, 0.0, 0.0, 1.0
            else:
                # Pointing the opposite way: turn about any axis perpendicular to w.
                if abs(wx) < 0.9:
                    cx, cy, cz = 0.0, wz, -wy
                else:
                    cx, cy, cz = -wz, 0.0, wx
                s = math.sqrt(cx * cx + cy * cy + cz * cz)
        scale = theta / s * DEG_PER_RAD
        res[3] = cx * scale
        res[4] = cy * scale
        res[5] = cz * scale
        return pos_err, theta * DEG_PER_RAD
    # E = R_goal · Rᵀ, the rotation still to apply, in the world frame.
    e00 = goal[0, 0] * rot[0, 0] + goal[0, 1] * rot[0, 1] + goal[0, 2] * rot[0, 2]
    e01 = goal[0, 0] * rot[1, 0] + goal[0, 1] * rot[1, 1] + goal[0, 2] * rot[1, 2]
    e02 = goal[0, 0] * rot[2, 0] + goal[0, 1] * rot[2, 1] + goal[0, 2] * rot[2, 2]
    e10 = goal[1, 0] * rot[0, 0] + goal[1, 1] * rot[0, 1] + goal[1, 2] * rot[0, 2]
    e11 = goal[1, 0] * rot[1, 0] + goal[1, 1] * rot[1, 1] + goal[1, 2] * rot[1, 2]
    e12 = goal[1, 0] * rot[2, 0] + goal[1, 1] * rot[2, 1] + goal[1, 2] * rot[2, 2]
    e20 = goal[2, 0] * rot[0, 0] + goal[2, 1] * rot[0, 1] + goal[2, 2] * rot[0, 2]
    e21 = goal[2, 0] * rot[1, 0] + goal[2, 1] * rot[1, 1] + goal[2, 2] * rot[1, 2]
    e22 = goal[2, 0] * rot[2, 0] + goal[2, 1] * rot[2, 1] + goal[2, 2] * rot[2, 2]
    vx = 0.5 * (e21 - e12)
    vy = 0.5 * (e02 - e20)
    vz = 0.5 * (e10 - e01)
    s = math.sqrt(vx * vx + vy * vy + vz * vz)
    c = 0.5 * (e00 + e11 + e22 - 1.0)
    theta = math.atan2(s, c)
    if s > 1e-6 or c > 0.0:
        scale = theta / s if s > 1e-12 else 1.0
        res[3] = scale * vx * DEG_PER_RAD
        res[4] = scale * vy * DEG_PER_RAD
        res[5] = scale * vz * DEG_PER_RAD
    else:
        # Half a turn: the axis is the dominant column of (E + I)/2.
        if e00 >= e11 and e00 >= e22:
            ax, ay, az = e00 + 1.0, e10, e20
        elif e11 >= e22:
            ax, ay, az = e01, e11 + 1.0, e21
        else:
            ax, ay, az = e02, e12, e22 + 1.0
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        res[3] = theta * ax / norm * DEG_PER_RAD
        res[4] = theta * ay / norm * DEG_PER_RAD
        res[5] = theta * az / norm * DEG_PER_RAD
    return pos_err, theta * DEG_PER_RAD


def pose_residual(rot, pos, goal, res):
    """MODE_POSE's :func:`residual` (a plain-Python name kept for the tests)."""
    return residual(rot, pos, goal, MODE_POSE, res)


@nb.njit(cache=CACHE, **NO_NRT)
def _movement(q, q_prev):
    m = 0.0
    for j in range(q.shape[0]):
        m += (q[j] - q_prev[j]) ** 2
    return m


@nb.njit(cache=CACHE, **NO_NRT)
def candidate_cost(q, frames, joint_params, goal, mode, q_prev, move_w, rot, pos, res):
    """Cost of one joint vector: ‖Δp‖² + θ_deg² + move_w·‖q − q_prev‖²."""
    # No axes wanted. ``mode < 0`` (always False) rather than the literal: numba compiles a
    # literal argument as a specialisation of its own, ~1 s more of the first compile.
    fk_frames(q, frames, joint_params, rot, pos, rot, rot, mode < 0)
    pos_err, ori_err = residual(rot, pos, goal, mode, res)
    cost = pos_err * pos_err + ori_err * ori_err
    if move_w > 0.0:
        cost += move_w * _movement(q, q_prev)
    return cost


@nb.njit(cache=CACHE, inline="always", **NO_NRT)
def _ldl_solve(a, b, n):
    """Solve a·x = b in place (b becomes x) for a symmetric positive definite n×n ``a``.

    ``a = L·D·Lᵀ`` (L unit lower triangular): no square roots, one division per column, where
    a Cholesky factor waits on a square root and a division in every column (the factorisation
    is on LM's critical path). Only ``a``'s lower triangle is read; afterwards the strict lower
    triangle holds L, the diagonal 1/D and the strict upper triangle ``L[i, k]·D[k]`` (at
    ``a[k, i]``, the unscaled value each later column needs).
    """
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[k, j]
        if not s > 0.0:
            return False
        inv = 1.0 / s
        a[j, j] = inv
        for i in range(j + 1, n):
            w = a[i, j]
            for k in range(j):
                w -= a[i, k] * a[k, j]
            a[j, i] = w
            a[i, j] = w * inv
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= a[i, k] * b[k]
        b[i] = s
    for i in range(n - 1, -1, -1):
        s = b[i] * a[i, i]
        for k in range(i + 1, n):
            s -= a[k, i] * b[k]
        b[i] = s
    return True


@nb.njit(cache=CACHE, inline="always", **NO_NRT)
def _normal_equations(rot, pos, axes, points, goal, joint_params, mode, res, jac, jtj, jtr, rows):
    """Fill ``jac`` (n×6: row j is the residual's derivative by joint j, i.e. Jᵀ) and, for
    ``rows`` 0 (the n×n form of :func:`_damped_step`), ``jtj`` = JᵀJ (its lower triangle: all
    :func:`_ldl_solve` reads) and ``jtr`` = Jᵀr; otherwise JᵀJ's diagonal, and r in ``jtr``
    (its first min(n, 6) entries)."""
    n = jac.shape[0]
    wx = wy = wz = 0.0
    if mode == MODE_AXIS:
        # The hand axis in the base frame: a turn about it leaves the residual alone, so the
        # angular rows are projected onto the plane perpendicular to it.
        wx = rot[0, 0] * goal[0, 0] + rot[0, 1] * goal[1, 0] + rot[0, 2] * goal[2, 0]
        wy = rot[1, 0] * goal[0, 0] + rot[1, 1] * goal[1, 0] + rot[1, 2] * goal[2, 0]
        wz = rot[2, 0] * goal[0, 0] + rot[2, 1] * goal[1, 0] + rot[2, 2] * goal[2, 0]
    r0, r1, r2, r3, r4, r5 = res[0], res[1], res[2], res[3], res[4], res[5]
    for j in range(n):
        zx, zy, zz = axes[j, 0], axes[j, 1], axes[j, 2]
        if joint_params[2, j] > 0.5:
            dx = pos[0] - points[j, 0]
            dy = pos[1] - points[j, 1]
            dz = pos[2] - points[j, 2]
            a0 = zy * dz - zz * dy
            a1 = zz * dx - zx * dz
            a2 = zx * dy - zy * dx
            if mode == MODE_POSITION:
                zx, zy, zz = 0.0, 0.0, 0.0
            elif mode == MODE_AXIS:
                along = zx * wx + zy * wy + zz * wz
                zx, zy, zz = zx - along * wx, zy - along * wy, zz - along * wz
            a3 = zx * DEG_PER_RAD
            a4 = zy * DEG_PER_RAD
            a5 = zz * DEG_PER_RAD
        else:
            a0, a1, a2, a3, a4, a5 = zx, zy, zz, 0.0, 0.0, 0.0
        jac[j, 0] = a0
        jac[j, 1] = a1
        jac[j, 2] = a2
        jac[j, 3] = a3
        jac[j, 4] = a4
        jac[j, 5] = a5
        if rows > 0:
            jtj[j, j] = a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3 + a4 * a4 + a5 * a5
            if j < 6:
                # r itself: ``res`` is overwritten by every evaluation, rejected ones too.
                jtr[j] = res[j]
            continue
        # Row j of the products, against the rows computed so far (scalars: no inner loop).
        jtr[j] = a0 * r0 + a1 * r1 + a2 * r2 + a3 * r3 + a4 * r4 + a5 * r5
        for c in range(j + 1):
            jtj[j, c] = (
                a0 * jac[c, 0]
                + a1 * jac[c, 1]
                + a2 * jac[c, 2]
                + a3 * jac[c, 3]
                + a4 * jac[c, 4]
                + a5 * jac[c, 5]
            )


@nb.njit(cache=CACHE, inline="always", **NO_NRT)
def _damped_step(jac, jtj, jtr, lam, hold, a, g, rows):
    """LM's step into ``g``: ``(JᵀJ + D)·Δq = Jᵀr`` with ``D = λ·diag(JᵀJ) + 1e-9·I``, over
    the joints not held (``hold[j]`` 1.0: ``Δq_j`` = 0); False if the matrix is not positive
    definite to working precision. ``jac``, ``jtj``, ``jtr`` from :func:`_normal_equations`.

    ``rows`` 0: those n×n normal equations. Otherwise (``rows`` = the residual's length, 3 or
    6, less than n) the same step through a rows×rows system: ``(J·D⁻¹·Jᵀ + I)·y = r``,
    ``Δq = D⁻¹·Jᵀ·y`` (push-through identity: ``(JᵀJ + D)⁻¹·Jᵀ = D⁻¹·Jᵀ·(J·D⁻¹·Jᵀ + I)⁻¹``).
    Forming and factoring it costs ~27n multiply-adds against the n×n form's ~n³/6 + 4n²: on
    a 10-joint arm about half of the linear algebra of an LM step. Measured beside rtb pose by
    pose (median CPU per solve): hyper and ball (10 joints) −5-6 %, P8 (8) −4 %, Panda (7)
    −2 %; the same LM iterations. There ``jtr[:rows]`` holds r, ``y`` is solved for in ``a``'s
    row below the block, and ``g`` holds ``D⁻¹`` until Δq replaces it.
    """
    n = jac.shape[0]
    if rows == 0:
        for r in range(n):
            if hold[r] > 0.5:
                g[r] = 0.0
                for c in range(r):
                    a[r, c] = 0.0
                a[r, r] = 1.0
            else:
                g[r] = jtr[r]
                for c in range(r):
                    a[r, c] = 0.0 if hold[c] > 0.5 else jtj[r, c]
                a[r, r] = jtj[r, r] + (lam * jtj[r, r] + 1e-9)
        return _ldl_solve(a, g, n)
    y = a[rows]
    for r in range(rows):
        y[r] = jtr[r]
        for c in range(r):
            a[r, c] = 0.0
        a[r, r] = 1.0
    for j in range(n):
        w = 0.0 if hold[j] > 0.5 else 1.0 / (lam * jtj[j, j] + 1e-9)
        g[j] = w
        if w == 0.0:
            continue
        for r in range(rows):
            wr = w * jac[j, r]
            for c in range(r + 1):
                a[r, c] += wr * jac[j, c]
    if not _ldl_solve(a, y, rows):
        return False
    for j in range(n):
        s = 0.0
        for r in range(rows):
            s += jac[j, r] * y[r]
        g[j] *= s
    return True


@nb.njit(cache=CACHE)
def lm_refine(q, lo, hi, frames, joint_params, goal, mode, fparams, iters, out):
    """Damped least squares on the target residual from ``q`` (modified in place).

    Each step solves ``(JᵀJ + λ·diag(JᵀJ) + 1e-9·I)·Δq = Jᵀr``; joints at a limit that the
    step would push further out are then held and the system solved again for the others (one
    active-set pass: a clamped step is no descent step, and solutions at the limits stalled).
    It clamps ``q + Δq`` into the limits and keeps it only if ``‖r‖`` drops (λ shrinks on
    success; on failure it grows and the same normal equations are solved again). Stops at the
    tolerances, after ``iters`` steps, when λ explodes, or (``fparams[F_LM_WINDOW]`` > 0) when a
    window of steps did not bring the cost below ``fparams[F_LM_PROGRESS]`` times what it was.
    ``out`` receives ``(pose cost, pos_err_cm, ori_err_deg)``; returns the number of steps.

    One call site of the FK and of the residual: compiling each inlined copy of them cost
    seconds of the first compile.
    """
    n = q.shape[0]
    return _lm_steps(
        q,
        lo,
        hi,
        frames,
        joint_params,
        goal,
        mode,
        fparams,
        iters,
        out,
        np.empty((3, 3)),
        np.empty(3),
        np.empty((n, 3)),
        np.empty((n, 3)),
        np.empty(6),
        np.empty((n, 6)),
        np.empty((n, n)),
        np.empty(n),
        np.empty((n, n)),
        np.empty(n),
        np.empty(n),
        q.copy(),
    )


# See _lm_steps' window test.
NEAR_STALL = 0.9

# A revolute joint whose range is at least this wide (but less than a turn) is free in LM: its
# steps are not clamped at the limits, and only the configuration LM ends at is brought back
# into them (:func:`_lm_steps`). Clamped steps stall at a limit, where a step round the other
# way, through the short forbidden arc, leads to a solution. Tuning seeds: on
# Stanford (4 joints of 340°) p99 of the work −35 %, Puma560 (one of 320°) −10 %, Panda (4 of
# 332°) −15 %, and the median −8–20 % on the three; with every revolute joint free, the default
# arm's and Panda's narrower joints (180°, about 200°) did worse.
FREE_SPAN_RAD = math.radians(300.0)
# LM ends with a free joint outside its range: within this of a limit the joint goes to the
# limit and LM goes on with every joint clamped (a target reached with joints at their limits:
# Panda's joints-at-limits poses converge so); further out the configuration at the limit is
# only evaluated, and the search goes on from other starts (measured, tuning seeds: 2°, 5°,
# 10°, always and never: 5° about the best on both kinds of poses).
POLISH_RAD = math.radians(5.0)


@nb.njit(cache=CACHE, **NO_NRT)
def _free(j, lo, hi, joint_params):
    return joint_params[2, j] > 0.5 and joint_params[3, j] < 0.5 and hi[j] - lo[j] >= FREE_SPAN_RAD


@nb.njit(cache=CACHE, **NO_NRT)
def _lm_steps(
    q, lo, hi, frames, joint_params, goal, mode, fparams, iters, out,
    rot, pos, axes, points, res, jac, jtj, jtr, a, g, hold, q_try,
):  # fmt: skip
    """:func:`lm_refine`'s loop, on the scratch arrays it allocates (``q_try`` a copy of ``q``).

    Two phases: the first with the free joints (:data:`FREE_SPAN_RAD`) unclamped. If it ends
    with one of them outside its range (taken modulo a turn), that joint goes to the nearer
    limit; within :data:`POLISH_RAD` of it a second phase, every joint clamped, goes on from
    there with the steps left, otherwise that configuration is only evaluated. Either way ``q``
    ends within the limits and ``out`` holds its own errors.
    """
    n = q.shape[0]
    tol_pos = fparams[F_TOL_POS]
    tol_ori = fparams[F_TOL_ORI]
    window = int(fparams[F_LM_WINDOW])
    progress = fparams[F_LM_PROGRESS]
    near = fparams[F_LM_NEAR]
    # The residual's length where it is below n (a redundant arm, or the position alone on
    # more than 3 joints): then each step solves a system of that size (:func:`_damped_step`).
    rows = 3 if mode == MODE_POSITION else 6
    if rows >= n:
        rows = 0
    cost = np.inf
    pos_err = np.inf
    ori_err = np.inf
    steps = 0
    limit = iters
    free = True
    while True:
        lam = fparams[F_LM_LAMBDA0]
        cost = np.inf
        checkpoint = np.inf
        first = True
        start = steps
        evaluate = True
        while True:
            if evaluate:
                fk_frames(
                    q_try, frames, joint_params, rot, pos, axes, points, mode >= 0
                )  # candidate_cost
                new_pos, new_ori = residual(rot, pos, goal, mode, res)
                new_cost = new_pos * new_pos + new_ori * new_ori
                if new_cost < cost or first:
                    if not first:
                        lam = max(lam * 0.2, 1e-12)
                    first = False
                    for j in range(n):
                        q[j] = q_try[j]
                    cost, pos_err, ori_err = new_cost, new_pos, new_ori
                    if (pos_err <= tol_pos and ori_err <= tol_ori) or steps >= limit:
                        break
                    _normal_equations(
                        rot, pos, axes, points, goal, joint_params, mode, res, jac, jtj, jtr, rows
                    )
                else:
                    lam *= 8.0
                    if lam > 1e8 or steps >= limit:
                        break
            elif steps >= limit:
                break
            done = steps - start
            if window > 0 and done > 0 and done % window == 0:
                # Slow progress over the last window: a local minimum, or far from the basin.
                # Give up early; a restart or DE supplies other starts. Within
                # fparams[F_LM_NEAR] of the target, only when it stalls (cost not below
                # NEAR_STALL of what it was): there steady but slow progress is more likely a
                # solution near a singularity approached (linearly) than a local minimum.
                if cost > progress * checkpoint and (cost > near or cost > NEAR_STALL * checkpoint):
                    break
                checkpoint = cost
            elif done == 0:
                checkpoint = cost
            steps += 1
            for j in range(n):
                hold[j] = 0.0
            # A joint at a limit that the step pushes further out would only be clamped back,
            # and the clamped step is no longer a descent step: hold such joints and solve
            # again for the others (one active-set pass). Solutions with joints at their limits
            # converge. (One call site of the step, in a loop: it is compiled inline.)
            solved = True
            for active_set_pass in range(2):
                if not _damped_step(jac, jtj, jtr, lam, hold, a, g, rows):
                    solved = False
                    break
                if active_set_pass == 1:
                    break
                held = 0
                for j in range(n):
                    if (
                        joint_params[3, j] < 0.5
                        and not (free and _free(j, lo, hi, joint_params))
                        and ((q[j] <= lo[j] and g[j] < 0.0) or (q[j] >= hi[j] and g[j] > 0.0))
                    ):
                        held += 1
                        hold[j] = 1.0
                if not 0 < held < n:
                    break
            if not solved:
                lam *= 10.0
                evaluate = False
                continue
            evaluate = True
            for j in range(n):
                if free and _free(j, lo, hi, joint_params):
                    q_try[j] = q[j] + g[j]
                else:
                    q_try[j] = _into_range(q[j] + g[j], lo[j], hi[j], joint_params[3, j])
        if not free:
            break
        # The free joints back into their ranges: the same angle where it is within the
        # limits (the pose unchanged); otherwise the nearer limit, and the second phase
        # evaluates that (so every configuration LM hands back is within the limits, with its
        # own errors) and, if no joint was more than POLISH_RAD outside, goes on from there.
        outside = -1.0
        for j in range(n):
            if _free(j, lo, hi, joint_params) and not lo[j] <= q[j] <= hi[j]:
                v = lo[j] + (q[j] - lo[j]) % TWO_PI
                if v > hi[j]:
                    below = lo[j] + TWO_PI - v
                    outside = max(outside, min(v - hi[j], below))
                    v = hi[j] if v - hi[j] < below else lo[j]
                q[j] = v
        if outside < 0.0:
            break
        if outside > POLISH_RAD:
            limit = steps
        free = False
        for j in range(n):
            q_try[j] = q[j]
    out[0] = cost
    out[1] = pos_err
    out[2] = ori_err
    return steps


@nb.njit(cache=CACHE, **NO_NRT)
def _evaluate_all(pop, cost, frames, joint_params, goal, mode, q_prev, move_w, scratch):
    rot, pos, res = scratch[0], scratch[1], scratch[4]
    for i in range(pop.shape[0]):
        cost[i] = candidate_cost(
            pop[i], frames, joint_params, goal, mode, q_prev, move_w, rot, pos, res
        )


@nb.njit(cache=CACHE, **NO_NRT)
def _min(values):
    # A loop, not ``values.min()``: numba's generic reduction costs ~3 s of the first compile.
    smallest = np.inf
    for v in values:
        smallest = min(smallest, v)
    return smallest


@nb.njit(cache=CACHE, **NO_NRT)
def _draw_population(pop, lo, hi, rng, first):
    for i in range(first, pop.shape[0]):
        for j in range(pop.shape[1]):
            pop[i, j] = lo[j] + _rand(rng) * (hi[j] - lo[j])


@nb.njit(cache=CACHE, **NO_NRT)
def _update_record(q, pose_cost, pos_err, ori_err, within_tol, record, record_q):
    # A configuration within both tolerances always wins: a lower cm² + deg² sum is no use if
    # one of the two errors is outside its tolerance.
    if within_tol or pose_cost < record[R_COST]:
        record[R_COST] = pose_cost
        record[R_POS_CM] = pos_err
        record[R_ORI_DEG] = ori_err
        for j in range(q.shape[0]):
            record_q[j] = q[j]


@nb.njit(cache=CACHE, **NO_NRT)
def _scratch(buf, n, n_pop):
    """The kernels' scratch arrays, views of ``buf`` (its size: ``layout.float_layout``): LM's,
    then DE's trials and their costs. Made once per :func:`search` call: an allocation per LM
    run cost a few percent of a solve, and with none the kernels run without NRT."""
    o = 0
    rot = _view(buf, o, (3, 3))
    o += 9
    pos = _view(buf, o, (3,))
    o += 3
    axes = _view(buf, o, (n, 3))
    o += 3 * n
    points = _view(buf, o, (n, 3))
    o += 3 * n
    res = _view(buf, o, (6,))
    o += 6
    jac = _view(buf, o, (n, 6))
    o += 6 * n
    jtj = _view(buf, o, (n, n))
    o += n * n
    jtr = _view(buf, o, (n,))
    o += n
    a = _view(buf, o, (n, n))
    o += n * n
    g = _view(buf, o, (n,))
    o += n
    hold = _view(buf, o, (n,))
    o += n
    q_try = _view(buf, o, (n,))
    o += n
    q = _view(buf, o, (n,))
    o += n
    out = _view(buf, o, (3,))
    o += 3
    trials = _view(buf, o, (n_pop, n))
    o += n_pop * n
    trial_cost = _view(buf, o, (n_pop,))
    return (
        rot,
        pos,
        axes,
        points,
        res,
        jac,
        jtj,
        jtr,
        a,
        g,
        hold,
        q_try,
        q,
        out,
        trials,
        trial_cost,
    )


@nb.njit(cache=CACHE, **NO_NRT)
def _refine_best(
    pop,
    cost,
    stuck,
    lo,
    hi,
    frames,
    joint_params,
    goal,
    q_prev,
    fparams,
    iparams,
    counts,
    record,
    record_q,
    scratch,
):
    """LM on the best individual not marked stuck; returns True once the tolerances are met.
    ``scratch``: :func:`_scratch`."""
    best = -1
    for i in range(pop.shape[0]):
        if not stuck[i] and (best < 0 or cost[i] < cost[best]):
            best = i
    if best < 0:
        return False
    q, q_try, out = scratch[12], scratch[11], scratch[13]
    for j in range(q.shape[0]):
        q[j] = pop[best, j]
        q_try[j] = q[j]
    counts[S_LM_ITERATIONS] += _lm_steps(
        q,
        lo,
        hi,
        frames,
        joint_params,
        goal,
        iparams[I_MODE],
        fparams,
        iparams[I_LM_ITERS],
        out,
        scratch[0],
        scratch[1],
        scratch[2],
        scratch[3],
        scratch[4],
        scratch[5],
        scratch[6],
        scratch[7],
        scratch[8],
        scratch[9],
        scratch[10],
        q_try,
    )
    counts[S_EVALUATIONS] += 1
    pose_cost, pos_err, ori_err = out[0], out[1], out[2]
    new_cost = pose_cost
    if iparams[I_HAS_PREV]:
        new_cost += fparams[F_MOVE_W] * _movement(q, q_prev)
    # LM that still made good progress may go on next generation; otherwise it has done what it
    # can from here, until DE replaces the individual.
    stuck[best] = 0 if new_cost < 0.5 * cost[best] else 1
    if new_cost < cost[best]:
        for j in range(q.shape[0]):
            pop[best, j] = q[j]
        cost[best] = new_cost
    within_tol = pos_err <= fparams[F_TOL_POS] and ori_err <= fparams[F_TOL_ORI]
    _update_record(q, pose_cost, pos_err, ori_err, within_tol, record, record_q)
    return within_tol


@nb.njit(cache=CACHE, **NO_NRT)
def init_population(
    pop,
    cost,
    stuck,
    lo,
    hi,
    frames,
    joint_params,
    goal,
    q_prev,
    fparams,
    iparams,
    rng,
    counts,
    record,
    record_q,
    q_start,
    spread_rad,
    scratch,
):
    """Fill the population (around ``q_start`` when ``iparams[I_HAS_PREV]``), evaluate, refine
    the best.

    Warm start: row 0 is ``q_start`` (clamped), the next third are ``q_start`` plus uniform noise
    of ±``spread_rad``, the rest uniform in the box, for when the target has jumped.
    Returns True if the tolerances are already met.
    """
    n_pop, n = pop.shape
    for k in range(counts.shape[0]):
        counts[k] = 0
    # "Nothing found yet": infinite errors at the start (or mid-range) configuration.
    record[R_POS_CM] = np.inf
    record[R_ORI_DEG] = np.inf
    for j in range(n):
        record_q[j] = q_start[j] if iparams[I_HAS_PREV] else 0.5 * (lo[j] + hi[j])
    first = 0
    if iparams[I_HAS_PREV]:
        n_local = max(1, n_pop // 3)
        for i in range(n_local):
            for j in range(n):
                noise = 0.0 if i == 0 else (2.0 * _rand(rng) - 1.0) * spread_rad
                pop[i, j] = min(max(q_start[j] + noise, lo[j]), hi[j])
        first = n_local
    _draw_population(pop, lo, hi, rng, first)
    _evaluate_all(
        pop,
        cost,
        frames,
        joint_params,
        goal,
        iparams[I_MODE],
        q_prev,
        fparams[F_MOVE_W] * iparams[I_HAS_PREV],
        scratch,
    )
    counts[S_EVALUATIONS] += n_pop
    stuck[:] = 0
    record[R_COST] = np.inf
    return _refine_best(
        pop,
        cost,
        stuck,
        lo,
        hi,
        frames,
        joint_params,
        goal,
        q_prev,
        fparams,
        iparams,
        counts,
        record,
        record_q,
        scratch,
    )


@nb.njit(cache=CACHE, **NO_NRT)
def generation(
    pop,
    cost,
    stuck,
    lo,
    hi,
    frames,
    joint_params,
    goal,
    q_prev,
    fparams,
    iparams,
    rng,
    counts,
    record,
    record_q,
    scratch,
    gens,
):
    """``gens`` memetic generations (fewer once the tolerances are met; returns True then).

    One generation: DE rand/1/bin with greedy selection, then LM on the best unstuck
    individual. After ``iparams[I_STALL_GENS]`` generations in a row that did not bring the best
    cost below ``fparams[F_STALL_GAIN]`` times what it was, the next generation is a restart
    instead of a DE step (the population drawn anew, a quarter at corners of the box), and LM
    then starts from the fresh population's best: an LM run from a fresh start converges far
    more often than one from a population that has gathered around a local minimum.
    Several generations per call keep the cost of Python and of the call (~1 µs for these
    arguments) off every generation. (The loop is here, not around a helper: every level of
    compiled calls re-optimises the code of all below it, ~2 s of the first compile.)
    """
    n_pop, n = pop.shape
    f_scale = fparams[F_SCALE]
    cr = fparams[F_CR]
    move_w = fparams[F_MOVE_W] * iparams[I_HAS_PREV]
    mode = iparams[I_MODE]
    # Scratch (:func:`_scratch`): LM's, free while DE runs, and DE's own trials.
    rot, pos, res, trial, trials, trial_cost = (
        scratch[0],
        scratch[1],
        scratch[4],
        scratch[11],
        scratch[14],
        scratch[15],
    )
    for _ in range(gens):
        if counts[S_STALE] >= iparams[I_STALL_GENS]:
            # Restart, instead of a DE step: the record keeps the best so far; the whole
            # population is drawn anew and LM starts from its best below. intp(0), not the
            # literal 0: numba would compile a second specialisation.
            _draw_population(pop, lo, hi, rng, np.intp(0))
            # A quarter of a restart's individuals are corners of the joint box: a target
            # reached only with joints at their limits is where LM from inside the box
            # stalls (each step is clamped), and a corner starts LM right there.
            for i in range(n_pop // 4):
                for j in range(n):
                    pop[i, j] = hi[j] if _rand(rng) < 0.5 else lo[j]
            _evaluate_all(pop, cost, frames, joint_params, goal, mode, q_prev, move_w, scratch)
            stuck[:] = 0
            counts[S_STALE] = 0
            counts[S_RESTARTS] += 1
            best_before = _min(cost)
        else:
            best_before = _min(cost)
            for i in range(n_pop):
                r1 = _randint(rng, n_pop - 1)
                r1 += r1 >= i
                r2 = r1
                while r2 == r1 or r2 == i:
                    r2 = _randint(rng, n_pop)
                r3 = r1
                while r3 == r1 or r3 == r2 or r3 == i:
                    r3 = _randint(rng, n_pop)
                j_rand = _randint(rng, n)
                for j in range(n):
                    if j == j_rand or _rand(rng) <= cr:
                        v = pop[r1, j] + f_scale * (pop[r2, j] - pop[r3, j])
                        trial[j] = _into_range(v, lo[j], hi[j], joint_params[3, j])
                    else:
                        trial[j] = pop[i, j]
                trial_cost[i] = candidate_cost(
                    trial, frames, joint_params, goal, mode, q_prev, move_w, rot, pos, res
                )
                for j in range(n):
                    trials[i, j] = trial[j]
            for i in range(n_pop):
                if trial_cost[i] <= cost[i]:
                    if trial_cost[i] < cost[i]:
                        stuck[i] = 0
                    cost[i] = trial_cost[i]
                    for j in range(n):
                        pop[i, j] = trials[i, j]
            if _min(cost) < best_before:
                counts[S_DE_GAINS] += 1
        counts[S_GENERATIONS] += 1
        counts[S_EVALUATIONS] += n_pop
        done = _refine_best(
            pop,
            cost,
            stuck,
            lo,
            hi,
            frames,
            joint_params,
            goal,
            q_prev,
            fparams,
            iparams,
            counts,
            record,
            record_q,
            scratch,
        )
        if done:
            return True
        # Progress is the best cost cut below F_STALL_GAIN of what it was this generation.
        if _min(cost) < best_before * fparams[F_STALL_GAIN]:
            counts[S_STALE] = 0
        else:
            counts[S_STALE] += 1
    return False


@nb.njit(cache=CACHE, **NO_NRT)
def _report(counts, record, record_q, joint_params, out):
    out[O_COST] = record[R_COST]
    out[O_POS_CM] = record[R_POS_CM]
    out[O_ORI_DEG] = record[R_ORI_DEG]
    out[O_GENERATIONS] = counts[S_GENERATIONS]
    out[O_EVALUATIONS] = counts[S_EVALUATIONS]
    out[O_LM_ITERATIONS] = counts[S_LM_ITERATIONS]
    out[O_RESTARTS] = counts[S_RESTARTS]
    out[O_DE_GAINS] = counts[S_DE_GAINS]
    n = record_q.shape[0]
    for j in range(n):
        out[O_Q + j] = record_q[j]
        out[O_Q + n + j] = record_q[j] * DEG_PER_RAD if joint_params[2, j] > 0.5 else record_q[j]


@nb.njit(cache=CACHE)
def search(
    fbuf,
    ibuf,
    rng,
    start,
    x_cm,
    y_cm,
    z_cm,
    roll_deg,
    pitch_deg,
    yaw_deg,
    gens,
):
    """The solver's one compiled entry point: up to ``gens`` generations of a search.

    ``start`` 0 goes on with the search in the arrays. ``START_NEW | mode`` (a ``MODE_*``),
    with ``START_HAS_PREV`` for a warm start and ``START_GOAL_SET`` when the caller has filled
    ``goal`` itself (else it is built from the pose arguments, cm and degrees), first starts a
    new one: :func:`init_population` from ``q_start`` (also the warm start's movement
    reference). ``joint_params`` rows 4 and 5 are the lower and
    upper limits. Returns True once the tolerances are met; ``out`` receives the best so far
    (layout ``O_*``) either way. The per-call values are scalar arguments and the first call
    does the initialisation too: each call from Python, and each numpy item it sets, costs
    time (0.1 µs per item).

    The arrays arrive in two buffers and the generator's state (``layout.SEARCH_ARRAYS``),
    cut here into views as ``layout.float_layout`` and ``layout.int_layout`` say: an array
    argument costs the compiled wrapper ~0.05 µs at every call (a call that returns at once:
    1.13 µs with the 14 arrays of before, 0.56 µs with these 3).
    """
    # The body is a function of its own, compiled without NRT like every kernel it calls
    # (the ahead-of-time module compiles this entry point with numba's default options).
    return _search(fbuf, ibuf, rng, start, x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg, gens)


@nb.njit(cache=CACHE, **NO_NRT)
def _search(fbuf, ibuf, rng, start, x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg, gens):
    """:func:`search`'s body: the views of the buffers, then the search."""
    iparams = _view(ibuf, 0, (N_IPARAMS,))
    n = iparams[I_DOF]
    n_pop = iparams[I_POP]
    i_ip, i_st, i_stuck, i_end = _int_layout(n_pop)
    counts = _view(ibuf, i_st, (i_stuck - i_st,))
    stuck = _view(ibuf, i_stuck, (i_end - i_stuck,))
    o_pop, o_cost, o_frames, o_jp, o_goal, o_q, o_fp, o_rec, o_rec_q, o_out, o_lm, o_end = (
        _float_layout(n, n_pop)
    )
    pop = _view(fbuf, o_pop, (n_pop, n))
    cost = _view(fbuf, o_cost, (o_frames - o_cost,))
    frames = _view(fbuf, o_frames, (n + 1, 4, 4))
    joint_params = _view(fbuf, o_jp, (6, n))
    goal = _view(fbuf, o_goal, (4, 4))
    q_start = _view(fbuf, o_q, (o_fp - o_q,))
    fparams = _view(fbuf, o_fp, (o_rec - o_fp,))
    record = _view(fbuf, o_rec, (o_rec_q - o_rec,))
    record_q = _view(fbuf, o_rec_q, (o_out - o_rec_q,))
    out = _view(fbuf, o_out, (o_lm - o_out,))
    scratch = _scratch(_view(fbuf, o_lm, (o_end - o_lm,)), n, n_pop)
    lo = joint_params[4]
    hi = joint_params[5]
    done = False
    if start & START_NEW:
        iparams[I_MODE] = start & 3
        iparams[I_HAS_PREV] = 1 if start & START_HAS_PREV else 0
        if not start & START_GOAL_SET:
            goal_matrix(
                x_cm,
                y_cm,
                z_cm,
                roll_deg * RAD_PER_DEG,
                pitch_deg * RAD_PER_DEG,
                yaw_deg * RAD_PER_DEG,
                goal,
            )
        done = init_population(
            pop,
            cost,
            stuck,
            lo,
            hi,
            frames,
            joint_params,
            goal,
            q_start,
            fparams,
            iparams,
            rng,
            counts,
            record,
            record_q,
            q_start,
            fparams[F_SPREAD],
            scratch,
        )
    if not done and gens > 0:
        done = generation(
            pop,
            cost,
            stuck,
            lo,
            hi,
            frames,
            joint_params,
            goal,
            q_start,
            fparams,
            iparams,
            rng,
            counts,
            record,
            record_q,
            scratch,
            gens,
        )
    _report(counts, record, record_q, joint_params, out)
    return done
