"""The compiled kernels in a process of their own: where numba may not cache them."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow


def test_kernels_work_without_a_writable_cache_location():
    """numba raises "cannot cache function" at import where no cache directory is writable (a
    read-only install, no home). Here no locator is allowed at all: the kernels must still
    import and run, uncached (one small kernel is compiled and called; compiling them all would
    take seconds)."""
    from numba.core import config

    if not hasattr(config, "CACHE_LOCATOR_CLASSES"):  # older numba (0.59) reads no such setting
        pytest.skip("this numba cannot be told to refuse every cache location")
    env = dict(os.environ, NUMBA_CACHE_LOCATOR_CLASSES="UserProvidedCacheLocator")
    env.pop("NUMBA_CACHE_DIR", None)
    code = (
        "import numpy as np\n"
        "from companion.ik import kernels\n"
        "goal = np.empty((4, 4))\n"
        "kernels.goal_matrix(1.0, 2.0, 3.0, 0.0, 0.0, 0.0, goal)\n"
        "print(kernels.CACHE, goal[:3, 3].tolist())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split(maxsplit=1) == ["False", "[1.0, 2.0, 3.0]\n"]
    assert "NUMBA_CACHE_DIR" in out.stderr  # the warning says how to fix it
