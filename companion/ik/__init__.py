"""The daemon's inverse kinematics: deadline-bounded, warm-startable, compiled.

:func:`solve` returns an :class:`IKResult` (degrees, centimetres, milliseconds) whatever
happens; :func:`warm_up` compiles or loads the kernels ahead of the first time-critical solve.
Importing this package imports numba (a fraction of a second) but compiles nothing.
"""

from companion.ik.solver import (
    DEFAULT_SETTINGS,
    IKResult,
    SolverSettings,
    StopReason,
    TargetMode,
    kernel_arrays,
    solve,
    warm_up,
)

__all__ = [
    "DEFAULT_SETTINGS",
    "IKResult",
    "SolverSettings",
    "StopReason",
    "TargetMode",
    "kernel_arrays",
    "solve",
    "warm_up",
]
