"""The arm model and its geometry: pure numpy, no I/O but reading arm files, no clocks.

Lengths in centimetres and angles in degrees at this API (the papers' units); radians inside
the maths. Modules: :mod:`~companion.kinematics.arm` (``Arm``, ``Pose``, arm files),
:mod:`~companion.kinematics.dh` (batched Denavit–Hartenberg transforms),
:mod:`~companion.kinematics.rotations` (roll–pitch–yaw, angle helpers),
:mod:`~companion.kinematics.jacobian` (geometric Jacobian and its derivative).
"""

from companion.kinematics.arm import Arm, Joint, Pose
from companion.kinematics.dh import DHConvention, chain, link_transforms
from companion.kinematics.rotations import (
    FloatArray,
    matrix_to_rpy,
    rotation_angle,
    rpy_to_matrix,
    wrap_angle,
)

__all__ = [
    "Arm",
    "DHConvention",
    "FloatArray",
    "Joint",
    "Pose",
    "chain",
    "link_transforms",
    "matrix_to_rpy",
    "rotation_angle",
    "rpy_to_matrix",
    "wrap_angle",
]
