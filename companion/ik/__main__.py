"""Compile the IK and keep-out kernels ahead of time: ``python -m companion.ik``.

Run it at install with the daemon's ``NUMBA_CACHE_DIR`` and the installed package (the shipped
unit uses ``/var/cache/armbridge``; ``docs/board.md``)::

    sudo NUMBA_CACHE_DIR=/var/cache/armbridge /opt/armbridge/.venv/bin/python -P -m companion.ik

It first builds the IK kernels into an extension module (:mod:`companion.ik.aot`, numba's
``pycc``; needs C and C++ compilers and Python's headers, e.g. ``apt-get install gcc g++
python3-dev``) in that directory: the daemon then loads them without importing numba. Where
that build is not possible it says why and compiles them into numba's JIT cache instead, as the
keep-out checks' kernel always is. ``-P`` keeps the current directory off ``sys.path``: run
from a checkout, ``-m`` would compile the checkout's copy, and numba keys its cache to the
source file's directory, so the installed daemon would not find it. The files belong to root;
at the unit's first start systemd moves the directory to ``/var/cache/private/armbridge`` and
hands it to the dynamic user (``DynamicUser=`` with ``CacheDirectory=``), which needs to write
there (numba refuses a cache directory it cannot write) and then only reads. Both the module
and the cache are keyed to the source files' contents (and numba's cache to their directory,
numba's version and this CPU): re-run it after an upgrade (the daemon would otherwise use, or
compile, the JIT kernels at its first start, before READY, as it does without it).

Exit status 0 when the daemon's next start will load compiled kernels, 1 when it will compile
them (no writable cache location).
"""

from __future__ import annotations

import sys
import time

from companion.ik import aot
from companion.ik.solver import kernels_origin, warm_up


def main() -> int:
    started = time.process_time()
    wall_started = time.perf_counter()
    print("compiling the IK kernels (once, ~20 s of CPU) ...", flush=True)
    try:
        path = aot.build()
        print(f"IK kernels compiled ahead of time into {path}")
    except aot.AotUnavailable as exc:
        print(f"no ahead-of-time IK module ({exc}); using numba's JIT cache instead")
    warm_up()
    from companion.kinematics import collision_kernels

    collision_kernels.warm_up()  # the keep-out checks' kernel, in numba's cache
    wall_s = time.perf_counter() - wall_started
    cpu_s = time.process_time() - started
    from numba.core import config as numba_config

    from companion.ik import kernels

    where = (
        f"the numba cache ({getattr(numba_config, 'CACHE_DIR', '') or 'numba default'}) for "
        f"{kernels.__file__}"
        if kernels.CACHE
        else "nowhere (no writable cache directory)"
    )
    print(
        f"kernels ready in {wall_s:.1f} s ({cpu_s:.1f} s CPU): IK from {kernels_origin()}; "
        f"JIT kernels stored in {where}"
    )
    return 0 if kernels.CACHE else 1


if __name__ == "__main__":
    sys.exit(main())
