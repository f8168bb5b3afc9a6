"""The IK kernels compiled ahead of time: a plain CPython extension module, no numba at run time.

``python -m companion.ik`` (the board install runs it) calls :func:`build`: numba's ``pycc``
compiles :func:`companion.ik.kernels.search` and :func:`~companion.ik.kernels.goal_matrix`, with
the explicit signatures below, into an extension module. Importing that module takes well under
a millisecond and does not import numba (whose own import and type registries are most of a
start from the JIT cache, ~0.8 s on the development machine); a call skips numba's dispatcher
(the type of each argument looked up at every call), as the solver's calls of the JIT kernels
do too. The code is the same: the same functions, compiled by the same numba and LLVM, give
the same results bit for bit (``tests/ik/test_aot.py``).

The build needs a C compiler and Python's headers (``pycc`` compiles a small C helper and links
the module; on Debian ``sudo apt-get install gcc g++ python3-dev``), setuptools in the venv, and
numba's ``pycc``, pending deprecation since numba 0.57 (it warns; still present in 0.68, the
only version this was tried with). Where any of it is missing,
:func:`build` raises :class:`AotUnavailable` with the reason and the solver uses numba's JIT
and its cache, as before. The code is compiled for the architecture's generic CPU (no
host-specific instructions: as fast here, and a card moved to another board of the same
architecture still runs).

**Never a stale module.** The module's name holds a digest of this file, ``kernels.py``,
``layout.py`` and numpy's version (:func:`module_name`); :func:`load` imports only the file of
exactly that name, so after any change to the kernels, their calling convention or numpy, the
old file is ignored (and the JIT runs) until :func:`build` runs again. The file is written under
a temporary name and renamed into place, so a build that dies half-way leaves nothing loadable.

**Where.** :func:`directories`: ``$NUMBA_CACHE_DIR`` (where the daemon's unit keeps the numba
cache, ``/var/cache/armbridge``), then the package's ``__pycache__``, then the user's cache
directory (``$XDG_CACHE_HOME/armbridge``, default ``~/.cache/armbridge``). :func:`load` takes
the first that holds the module; :func:`build` writes into the first it can write to.

The wrapper ``pycc`` generates does not check its arguments' types (a float32 array would be
read as float64 memory): the solver checks its arrays against ``layout.SEARCH_ARRAYS`` once,
when it makes them, and nothing else calls these functions.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import logging
import os
import sys
import tempfile
import warnings
from pathlib import Path
from types import ModuleType

import numpy as np

from companion.ik import layout
from companion.kinematics import numba_cache

log = logging.getLogger(__name__)

_HERE = Path(__file__).resolve().parent
_SOURCES = ("kernels.py", "layout.py", "aot.py")
MODULE_PREFIX = "_armbridge_ik_"

_NUMBA_DTYPES = {"float64": "f8", "int64": "i8", "uint64": "u8", "bool": "b1"}


def _array_type(dtype: str, ndim: int) -> str:
    # C-contiguous (``::1`` on the last axis), as the solver's arrays are: the JIT infers the
    # same layout from them, so both compile the same code.
    return f"{_NUMBA_DTYPES[dtype]}[{':, ' * (ndim - 1)}::1]"


SEARCH_SIGNATURE = (
    "b1("
    + ", ".join(_array_type(dtype, ndim) for _, dtype, ndim in layout.SEARCH_ARRAYS)
    + ", i8, f8, f8, f8, f8, f8, f8, i8)"
)
"""``kernels.search``: the arrays of ``layout.SEARCH_ARRAYS``, ``start``, the pose (cm, deg),
``gens``; returns whether the tolerances are met."""
GOAL_MATRIX_SIGNATURE = "void(f8, f8, f8, f8, f8, f8, f8[:, ::1])"
"""``kernels.goal_matrix``: x, y, z (cm), roll, pitch, yaw (rad), the 4×4 goal to fill."""


class AotUnavailable(RuntimeError):
    """The ahead-of-time module could not be built here (the reason is the message)."""


def source_digest() -> str:
    """A digest of what the module is compiled from: the kernels' source, their calling
    convention, this file (the signatures) and numpy's version (the C API it is built for)."""
    h = hashlib.sha256()
    for name in _SOURCES:
        h.update(name.encode())
        h.update((_HERE / name).read_bytes())
    h.update(np.__version__.encode())
    return h.hexdigest()[:24]


def module_name() -> str:
    """The extension module's name (also its init symbol): ``_armbridge_ik_<digest>``."""
    return MODULE_PREFIX + source_digest()


def file_name() -> str:
    """The module's file name for this interpreter (its ABI and platform suffix)."""
    return module_name() + importlib.machinery.EXTENSION_SUFFIXES[0]


def directories() -> list[Path]:
    """Where the module is looked for, in this order (see the module docstring)."""
    found = []
    numba_dir = os.environ.get("NUMBA_CACHE_DIR")
    if numba_dir:
        found.append(Path(numba_dir))
    found.append(_HERE / "__pycache__")
    xdg = os.environ.get("XDG_CACHE_HOME")
    try:
        found.append((Path(xdg) if xdg else Path.home() / ".cache") / "armbridge")
    except RuntimeError:  # no home directory (a service user may have none)
        pass
    return found


def untrusted(path: Path) -> str | None:
    """Why ``path`` must not be imported (None: it may). Importing it runs its machine code
    in this process, so another local user must not have been able to write it or swap it:
    the rule of every cache the daemon loads (:mod:`companion.kinematics.numba_cache`)."""
    return numba_cache.untrusted(path)


def find() -> Path | None:
    """The up-to-date module's file, or None. A file another user could have written is
    skipped, with a warning (:func:`untrusted`)."""
    name = file_name()
    for directory in directories():
        path = directory / name
        try:
            if not path.is_file():
                continue
            reason = untrusted(path)
        except OSError:  # a directory this user may not read (ProtectHome=, another user's)
            continue
        if reason is None:
            return path
        log.warning("not loading the ahead-of-time IK kernels: %s", reason)
    return None


def load() -> ModuleType | None:
    """Import the up-to-date module (None if there is none, or it fails to import: logged)."""
    path = find()
    if path is None:
        return None
    name = path.name.split(".", 1)[0]
    if name in sys.modules:
        return sys.modules[name]
    try:
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            raise ImportError(f"no loader for {path}")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except ImportError as exc:
        log.warning("cannot import the ahead-of-time IK kernels %s (%s): using the JIT", path, exc)
        return None
    sys.modules[name] = module
    return module


def build(directory: Path | None = None) -> Path:
    """Compile the module into ``directory`` (default: the first writable of
    :func:`directories`) and return its path; :class:`AotUnavailable` if it cannot be built
    here. Takes a few seconds of CPU (numba compiles the kernels, then the C compiler links)."""
    if directory is None:
        directory = _first_writable(directories())
    try:
        with warnings.catch_warnings():
            # numba.pycc is pending deprecation (numba 0.57+): it warns at import.
            warnings.simplefilter("ignore")
            from numba.pycc import CC
    except ImportError as exc:  # pycc needs setuptools, which venvs of Python 3.12+ lack
        raise AotUnavailable(
            f"numba.pycc is not available ({exc}; it needs setuptools: pip install setuptools)"
        ) from exc
    from companion.ik import kernels

    name = module_name()
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=directory, prefix=".build-") as tmp:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # setuptools' distutils shims warn
                # CC() itself probes the toolchain: RuntimeError without a compiler.
                cc = CC(name)
                cc.output_dir = tmp
                cc.verbose = False
                cc.export("search", SEARCH_SIGNATURE)(kernels.search.py_func)
                cc.export("goal_matrix", GOAL_MATRIX_SIGNATURE)(kernels.goal_matrix.py_func)
                cc.compile()
        except Exception as exc:  # the C toolchain's errors have no common base class
            first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise AotUnavailable(
                f"compiling the ahead-of-time IK module failed ({type(exc).__name__}: "
                f"{first_line}); it needs C and C++ compilers and Python's headers (Debian: "
                "apt-get install gcc g++ python3-dev)"
            ) from exc
        built = Path(tmp) / file_name()
        if not built.is_file():
            raise AotUnavailable(f"numba.pycc wrote no {built.name} in {tmp}")
        target = directory / built.name
        os.replace(built, target)  # atomic: a reader sees the whole file or none
    for old in directory.glob(MODULE_PREFIX + "*"):
        if old.name != target.name:  # built from other sources: never loaded again
            old.unlink(missing_ok=True)
    return target


def _first_writable(candidates: list[Path]) -> Path:
    for directory in candidates:
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(directory, os.W_OK | os.X_OK):
            return directory
    raise AotUnavailable(
        "no writable directory for the ahead-of-time IK module: "
        + ", ".join(str(d) for d in candidates)
    )
