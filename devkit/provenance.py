"""Where a measurement came from: the header every bench report opens with.

A figure is worth only as much as what it says about its origin: the code (the commit, marked
``+dirty`` when the working tree had changes), the time, the machine, how busy the machine was
and the exact command that produced it. ``bench/report.py`` puts :func:`run_header` at the top
of every Markdown report a bench writes. It lives here, not in ``bench/``, so that the tests can
check it (``tests/`` never imports ``bench/``).
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def machine() -> str:
    """Architecture, cores, Python and kernel: ``x86_64, 2 cores, Python 3.11.2, Linux 6.1``."""
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}, {platform.system()} {platform.release()}"
    )


def git(*args: str, cwd: Path = ROOT) -> str | None:
    """``git ARGS`` in ``cwd``: its stripped output, or None without git or a repository."""
    try:
        out = subprocess.run(
            ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


#: What the benches write (``--markdown``, results): changes there say nothing of the code.
BENCH_OUTPUTS = ("docs/measurements", "docs/papers-report.md", "bench/results")


def commit(cwd: Path = ROOT, run_git: Callable[..., str | None] = git) -> str:
    """The short commit of ``cwd``'s checkout, ``+dirty`` if tracked files changed (but the
    benches' own pages and results, :data:`BENCH_OUTPUTS`: a run of several benches writes
    them one after the other); ``unknown`` outside a git checkout."""
    head = run_git("rev-parse", "--short", "HEAD", cwd=cwd)
    if not head:
        return "unknown"
    exclude = [f":(exclude){path}" for path in BENCH_OUTPUTS]
    dirty = run_git("status", "--porcelain", "--untracked-files=no", "--", ".", *exclude, cwd=cwd)
    return head + ("+dirty" if dirty else "")


def command(argv: Sequence[str] | None = None, module: str | None = None) -> str:
    """The command line as typed from the repository root: ``python -m bench.latency --seed 1``.

    ``module`` defaults to the running ``__main__``'s module name when it is a bench
    (``python -m bench.X`` sets it), else ``bench.<script name>``; ``argv`` to ``sys.argv``.
    """
    argv = list(sys.argv if argv is None else argv)
    if module is None:
        spec = getattr(sys.modules.get("__main__"), "__spec__", None)
        name = str(getattr(spec, "name", "") or "")
        stem = Path(argv[0]).stem if argv else "unknown"
        module = name if name.startswith("bench.") else f"bench.{stem}"
    return " ".join(["python -m", module, *argv[1:]])


def run_header(
    argv: Sequence[str] | None = None,
    *,
    module: str | None = None,
    cwd: Path = ROOT,
    now: datetime.datetime | None = None,
    load: tuple[float, float, float] | None = None,
    run_git: Callable[..., str | None] = git,
) -> list[str]:
    """The report's provenance as Markdown lines: command, commit, date (UTC), machine, load.

    ``load`` is the 1, 5 and 15 minute load average (default: ``os.getloadavg()`` now, i.e.
    when the report is written, at the end of the run).
    """
    now = now or datetime.datetime.now(datetime.UTC)
    load = load if load is not None else os.getloadavg()
    return [
        f"- command: `{command(argv, module)}`",
        f"- commit: {commit(cwd, run_git)}",
        f"- date: {now.astimezone(datetime.UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- machine: {machine()}",
        "- load average (1, 5, 15 min) when written: " + " ".join(f"{v:.2f}" for v in load),
    ]


def with_header(text: str, header: Sequence[str]) -> str:
    """``text`` with ``header`` (and a blank line) after its ``# title`` line, else at its top."""
    block = "\n".join(header) + "\n\n"
    if text.startswith("# "):
        title, _, rest = text.partition("\n")
        return f"{title}\n\n{block}{rest.lstrip(chr(10))}"
    return block + text
