"""Compile the IK and keep-out kernels into numba's cache ahead of time: ``python -m companion.ik``.

Run it at install, as the user the daemon runs as and with the daemon's ``NUMBA_CACHE_DIR``
(the shipped unit uses ``/var/cache/armbridge``), e.g.::

    sudo -u armbridge env NUMBA_CACHE_DIR=/var/cache/armbridge python3 -m companion.ik

Then the daemon's first start loads compiled kernels (about half a second) instead of compiling
them (about 17 s of CPU on two cores). The cache is keyed to the installed source files and to
this CPU: re-run it after an upgrade (the daemon would otherwise compile at its first start,
before READY, as it does without it).
"""

from __future__ import annotations

import sys
import time

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
    where = "the numba cache" if kernels.CACHE else "nowhere (no writable cache directory)"
    print(f"IK kernels ready in {wall_s:.1f} s ({cpu_s:.1f} s CPU), stored in {where}")
    return 0 if kernels.CACHE else 1


if __name__ == "__main__":
    sys.exit(main())
