"""A reproduction of the source papers: their objective, DE, MSFLA, harmony search and
paper 004's inverse acceleration, with one result type (``SolverResult``).

Used by ``bench/papers.py`` and the tests; the daemon never imports it. It depends on
:mod:`companion.kinematics` only.
"""

from companion.papers import constants
from companion.papers.base import SolverResult, StopReason
from companion.papers.de import differential_evolution
from companion.papers.hs import harmony_search
from companion.papers.msfla import shuffled_frog_leaping
from companion.papers.objective import IKObjective, OrientationMetric

__all__ = [
    "IKObjective",
    "OrientationMetric",
    "SolverResult",
    "StopReason",
    "constants",
    "differential_evolution",
    "harmony_search",
    "shuffled_frog_leaping",
]
