"""Compile the IK and keep-out kernels into numba's cache ahead of time: ``python -m companion.ik``.

Run it at install with the daemon's ``NUMBA_CACHE_DIR`` and the installed package (the shipped
unit uses ``/var/cache/armbridge``; README "Running on a board")::

    sudo NUMBA_CACHE_DIR=/var/cache/armbridge /opt/armbridge/.venv/bin/python -P -m companion.ik

``-P`` keeps the current directory off ``sys.path``: run from a checkout, ``-m`` would compile
the checkout's copy, and numba keys its cache to the source file's directory, so the installed
daemon would not find it. The files belong to root; at the unit's first start systemd moves
the directory to ``/var/cache/private/armbridge`` and hands it to the dynamic user
(``DynamicUser=`` with ``CacheDirectory=``), which needs to write there (numba refuses a cache
directory it cannot write) and then only reads. Then the daemon's first start loads compiled
kernels (about half a second) instead of compiling them (about 20 s of CPU on two cores). The
cache is keyed to the source files' contents and directory, numba's version and this CPU:
re-run it after an upgrade (the daemon would otherwise compile at its first start, before
READY, as it does without it).
"""

from __future__ import annotations

import sys
import time

from numba.core import config as numba_config

from companion.ik import kernels
from companion.ik.solver import warm_up
from companion.kinematics import collision_kernels


def main() -> int:
    started = time.process_time()
    wall_s = warm_up()
    wall_started = time.perf_counter()
    collision_kernels.warm_up()  # the keep-out checks' kernel, in the same cache
    wall_s += time.perf_counter() - wall_started
    cpu_s = time.process_time() - started
    where = (
        f"the numba cache ({getattr(numba_config, 'CACHE_DIR', '') or 'numba default'}) for "
        f"{kernels.__file__}"
        if kernels.CACHE
        else "nowhere (no writable cache directory)"
    )
    print(f"IK kernels ready in {wall_s:.1f} s ({cpu_s:.1f} s CPU), stored in {where}")
    return 0 if kernels.CACHE else 1


if __name__ == "__main__":
    sys.exit(main())
