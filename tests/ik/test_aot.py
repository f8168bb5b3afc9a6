"""companion.ik.aot: which module is loaded (never one built from other sources, or one
another user could have written), and the arrays the solver refuses to hand it. A module built
and run: ``test_aot_build.py``."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.ik import aot, kernels, layout, solver, warm_up


def test_kernels_record_the_digest_of_their_calling_convention():
    # numba's cache does not see layout.py's constants change: kernels.py must change with it.
    digest = hashlib.sha256(Path(layout.__file__).read_bytes()).hexdigest()
    assert kernels.LAYOUT_SHA256 == digest, "update LAYOUT_SHA256 in companion/ik/kernels.py"


def test_the_module_name_follows_the_sources(tmp_path, monkeypatch):
    for name in ("kernels.py", "layout.py", "aot.py"):
        shutil.copy(Path(aot.__file__).parent / name, tmp_path / name)
    monkeypatch.setattr(aot, "_HERE", tmp_path)
    before = aot.module_name()
    assert before == aot.MODULE_PREFIX + aot.source_digest()
    assert before.isidentifier()  # it is also the module's init symbol
    with (tmp_path / "kernels.py").open("a") as f:
        f.write("\n")
    assert aot.module_name() != before


def test_only_the_module_of_the_current_sources_is_loaded(tmp_path, monkeypatch):
    monkeypatch.setattr(aot, "directories", lambda: [tmp_path])
    monkeypatch.delitem(sys.modules, aot.module_name(), raising=False)  # loaded by a solve
    suffix = aot.file_name()[len(aot.module_name()) :]
    (tmp_path / (aot.MODULE_PREFIX + "0" * 24 + suffix)).write_bytes(b"stale")
    assert aot.find() is None and aot.load() is None
    # The right name, but not a loadable module (a truncated copy): the JIT is used instead.
    (tmp_path / aot.file_name()).write_bytes(b"not an ELF file")
    assert aot.find() == tmp_path / aot.file_name()
    assert aot.load() is None


def test_a_module_another_user_could_have_written_is_not_loaded(tmp_path, monkeypatch):
    monkeypatch.setattr(aot, "directories", lambda: [tmp_path])
    path = tmp_path / aot.file_name()
    path.write_bytes(b"not an ELF file")
    tmp_path.chmod(0o700)
    path.chmod(0o644)
    assert aot.find() == path
    path.chmod(0o666)  # writable by anyone: its code could be anyone's
    assert aot.find() is None and "writable by its group or others" in aot.untrusted(path)
    path.chmod(0o644)
    tmp_path.chmod(0o777)  # anyone could swap the file
    assert aot.find() is None and str(tmp_path) in aot.untrusted(path)
    tmp_path.chmod(0o700)


def test_directories_start_with_numbas_cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    found = aot.directories()
    assert found[0] == tmp_path
    assert found[-1] == tmp_path / "xdg" / "armbridge"


def test_the_solver_refuses_arrays_the_compiled_wrapper_would_misread():
    good = tuple(
        np.zeros((2,) * ndim, dtype=np.dtype(dtype)) for _, dtype, ndim in layout.SEARCH_ARRAYS
    )
    solver._check_search_arrays(good)
    for k, (name, _, ndim) in enumerate(layout.SEARCH_ARRAYS):
        wrong = list(good)
        wrong[k] = np.zeros((2,) * ndim, dtype=np.float32)
        with pytest.raises(TypeError, match=name):
            solver._check_search_arrays(tuple(wrong))
    strided = list(good)
    strided[0] = np.zeros(6)[::2]  # float64 1-d, but not contiguous
    with pytest.raises(TypeError, match="fbuf"):
        solver._check_search_arrays(tuple(strided))


def test_without_a_compiler_the_build_says_why_instead_of_raising(tmp_path):
    # distutils takes the compiler from $CC: one that does not exist is a board without gcc.
    # In a process of its own: numba remembers a failed compiler probe for the process's life.
    probe = (
        "import sys; from pathlib import Path; from companion.ik import aot\n"
        "try:\n    aot.build(Path(sys.argv[1]))\nexcept aot.AotUnavailable as exc:\n"
        "    print('unavailable:', exc)\n"
    )
    env = {**os.environ, "CC": str(tmp_path / "no-such-cc")}
    out = subprocess.run(
        [sys.executable, "-c", probe, str(tmp_path / "out")],
        env=env, capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert out.stdout.startswith("unavailable:") and "gcc g++ python3-dev" in out.stdout
    assert not list((tmp_path / "out").glob(aot.MODULE_PREFIX + "*"))


def test_the_first_solve_says_it_compiles_when_numbas_cache_is_empty(tmp_path):
    # Only whether the cache holds the kernels is asked (numba imported, nothing compiled).
    probe = "from companion.ik import solver; print(solver.jit_cache_ready())"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "False"
    warm_up()  # this process's cache (the suite's): compiled or loaded now
    assert solver.jit_cache_ready() or not kernels.CACHE
