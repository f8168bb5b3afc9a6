"""armbridge's companion-computer side.

Four packages, one concern each, imports pointing one way (checked in CI, see
``[tool.importlinter]`` in ``pyproject.toml``):

* :mod:`companion.kinematics`: the arm model, DH forward kinematics, rotations (pure numpy);
* :mod:`companion.ik`: the daemon's deadline-bounded IK solver and its compiled kernels;
* :mod:`companion.papers`: a reproduction of the source papers (never imported by the daemon);
* :mod:`companion.daemon`: the service, its config, control socket and the ``armbridge`` CLI.
"""

__version__ = "0.1.0"
