"""What every bench script's report shares: the machine line, Markdown tables, the file.

The scripts print their Markdown and, with ``--markdown FILE`` (or their default file), write
the same text there through :func:`write_markdown`, which heads it with the run's provenance
(:func:`devkit.provenance.run_header`: the command, commit, date, machine and load average).
"""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from devkit.provenance import machine, run_header, with_header

__all__ = ["cores", "format_cell", "interpreter", "machine", "md_table", "write_markdown"]


def cores() -> int:
    return os.cpu_count() or 1


def interpreter() -> str:
    """Python implementation and version, and numpy's: ``CPython 3.11.2, numpy 2.1.0``."""
    return f"{platform.python_implementation()} {platform.python_version()}, numpy {np.__version__}"


def format_cell(value: Any) -> str:
    """A table cell: floats with two decimals (NaN as a dash), anything else as ``str``."""
    if isinstance(value, float):
        return "–" if math.isnan(value) else f"{value:.2f}"
    return str(value)


def md_table(
    headers: Sequence[str],
    rows: Sequence[Sequence[Any]],
    cell: Callable[[Any], str] = format_cell,
) -> list[str]:
    """A Markdown table's lines: header, separator, one line per row (cells by ``cell``)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return lines


def write_markdown(path: Path, text: str) -> None:
    """Write a report (UTF-8) headed with the run's provenance, making its directory if needed.

    The header goes under the report's ``# title`` line (at the top without one): the exact
    command from ``sys.argv``, the commit (``+dirty`` with uncommitted changes), the UTC date,
    the machine and the load average when written.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(with_header(text, run_header()), encoding="utf-8")
