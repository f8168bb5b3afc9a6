"""A reproduction of the source papers: their objective, DE, MSFLA, harmony search and
paper 004's inverse acceleration, with one result type (``SolverResult``).

Used by ``bench/papers.py`` and the tests; the daemon never imports it. It depends on
:mod:`companion.kinematics` only.
"""

from companion.papers import constants
from companion.papers.base import Boundary, SolverResult, StopReason
from companion.papers.de import differential_evolution
from companion.papers.hs import harmony_search
from companion.papers.msfla import classic_shuffled_frog_leaping, shuffled_frog_leaping
from companion.papers.objective import IKObjective, OrientationMetric, pose_objective

__all__ = [
    "Boundary",
    "IKObjective",
    "OrientationMetric",
    "SolverResult",
    "StopReason",
    "classic_shuffled_frog_leaping",
    "constants",
    "differential_evolution",
    "harmony_search",
    "pose_objective",
    "shuffled_frog_leaping",
]
