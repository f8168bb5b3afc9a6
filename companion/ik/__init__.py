"""The daemon's inverse kinematics: deadline-bounded, warm-startable, compiled.

:func:`solve` returns an :class:`IKResult` (degrees, centimetres, milliseconds) whatever
happens; :func:`warm_up` loads (or compiles) the kernels ahead of the first time-critical solve.
Importing this package compiles nothing and does not import numba (:func:`warm_up` does, unless
the ahead-of-time module is there: :mod:`companion.ik.aot`).
"""

from companion.ik.solver import (
    DEFAULT_METHOD,
    DEFAULT_SETTINGS,
    METHODS,
    IKResult,
    SolverSettings,
    StopReason,
    TargetMode,
    kernel_arrays,
    kernels_origin,
    method_settings,
    solve,
    warm_up,
)

__all__ = [
    "DEFAULT_METHOD",
    "DEFAULT_SETTINGS",
    "IKResult",
    "METHODS",
    "SolverSettings",
    "StopReason",
    "TargetMode",
    "kernel_arrays",
    "kernels_origin",
    "method_settings",
    "solve",
    "warm_up",
]
