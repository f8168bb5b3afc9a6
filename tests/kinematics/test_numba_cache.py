"""companion.kinematics.numba_cache: a numba cache another local user could have written is
never loaded, for the IK kernels and the keep-out kernels alike."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from companion.kinematics.numba_cache import untrusted

PROBE = (
    "import logging, sys; logging.basicConfig(stream=sys.stderr); "
    "from companion.ik import kernels; from companion.kinematics import collision_kernels; "
    "print(kernels.CACHE, collision_kernels.CACHE)"
)


def caches_used(cache_dir) -> tuple[str, str]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True
    )
    return out.stdout.strip(), out.stderr


def test_a_cache_directory_of_the_daemons_own_is_used(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o755)
    assert caches_used(cache)[0] == "True True"


def test_a_cache_directory_others_could_write_is_not_used(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    cache.chmod(0o777)  # not sticky: anyone could plant a pickle there
    used, log = caches_used(cache)
    assert used == "False False"
    assert "writable by its group or others (mode 777)" in log
    assert "IK kernels" in log and "keep-out kernels" in log


def test_a_planted_cache_file_is_not_loaded(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("a file of another user's needs root to make")
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o755)
    where = "from companion.ik import kernels; print(kernels.search._cache._cache_path)"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    found = subprocess.run(
        [sys.executable, "-c", where], env=env, capture_output=True, text=True, check=True
    )
    directory = Path(found.stdout.strip())  # where numba keeps the IK kernels' cache
    directory.mkdir(parents=True, exist_ok=True)
    planted = directory / "kernels.search-1.py311.nbi"
    planted.write_bytes(b"not numba's")
    os.chown(planted, 65534, 65534)
    used, log = caches_used(cache)
    assert used.split()[0] == "False" and "owned by uid 65534" in log


def test_a_sticky_directory_above_the_cache_is_fine(tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    own = shared / "mine"
    own.mkdir(mode=0o755)
    assert untrusted(own) is None
    own.chmod(0o1777)  # the cache directory itself shared: refused, sticky or not
    assert "writable by its group or others" in (untrusted(own) or "")
