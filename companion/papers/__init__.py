"""A reproduction of the source papers: their objective, DE, MSFLA, harmony search and
paper 004's inverse acceleration, with one result type (``SolverResult``).

Used by ``bench/papers.py`` and the tests; the daemon never imports it. It depends on
:mod:`companion.kinematics` only.
"""
