"""Whether numba's on-disk cache may be used by this process: one rule for every compiled cache
the daemon loads (the IK kernels' JIT cache, the keep-out kernels' and the ahead-of-time module).

Loading a cache runs what is in it: numba's index and data files are pickles, the ahead-of-time
module is machine code. A cache another local user could have written (a group- or
world-writable ``NUMBA_CACHE_DIR``, a file in it owned by someone else) would run their code in
the daemon, as root for a root daemon. So a cache directory is used only when it, and every
directory above it, is owned by this user or root and writable by no one else (a sticky
directory such as ``/tmp`` is fine above it: nobody may rename or remove another's entries
there), and the cached files of the module are owned by this user or root and writable by no
one else. Otherwise the kernels compile in memory, at every start (``cache=False``).
"""

from __future__ import annotations

import logging
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def untrusted(path: Path) -> str | None:
    """Why the cache at ``path`` (a directory or a file) must not be loaded, or None: it and
    every directory above it owned by this user or root and writable by no one else (a sticky
    directory above it excepted)."""
    me = os.geteuid()
    for depth, item in enumerate([path, *path.parents]):
        try:
            st = item.stat()
        except OSError as exc:
            return f"{item}: {exc.strerror or exc}"
        if st.st_uid not in (me, 0):
            return f"{item} is owned by uid {st.st_uid}"
        shared = st.st_mode & 0o022
        if shared and not (depth > 0 and stat.S_ISDIR(st.st_mode) and st.st_mode & stat.S_ISVTX):
            return f"{item} is writable by its group or others (mode {st.st_mode & 0o777:o})"
    return None


def cache_usable(probe: Callable[[], int], what: str) -> bool:
    """Whether ``cache=True`` may be used for the module that defines ``probe`` (a trivial
    function of that module): numba finds a writable cache location for it (else
    ``cache=True`` raises at decoration) and :func:`untrusted` finds nothing wrong with it or
    with the module's files in it. Says once why not (``what`` names the kernels)."""
    import numba as nb

    try:
        dispatcher: Any = nb.njit(cache=True)(probe)
    except RuntimeError:
        log.warning(
            "no writable numba cache directory: the %s compile at every start; set "
            "NUMBA_CACHE_DIR to a directory this user can write",
            what,
        )
        return False
    try:
        directory = Path(dispatcher._cache._cache_path)
    except AttributeError:  # numba's internals moved: the directory cannot be checked
        log.warning("numba's cache directory cannot be checked: the %s are not cached", what)
        return False
    module = Path(probe.__code__.co_filename).stem
    why = untrusted(directory) if directory.exists() else untrusted(directory.parent)
    if why is None:
        for cached in directory.glob(f"{module}.*") if directory.exists() else ():
            why = untrusted(cached)
            if why is not None:
                break
    if why is not None:
        log.warning(
            "numba cache %s not used for the %s (%s): they compile in memory at every start; "
            "give the daemon a cache directory of its own (NUMBA_CACHE_DIR, mode 0755)",
            directory,
            what,
            why,
        )
        return False
    return True
