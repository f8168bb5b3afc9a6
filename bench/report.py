"""What every bench script's report shares: the machine line, Markdown tables, the file.

The scripts print their Markdown and, with ``--markdown FILE`` (or their default file), write
the same text there through :func:`write_markdown`.
"""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def cores() -> int:
    return os.cpu_count() or 1


def machine() -> str:
    """Architecture, cores, Python and kernel: ``x86_64, 2 cores, Python 3.11.2, Linux 6.1``."""
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}, {platform.system()} {platform.release()}"
    )


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
    """Write a report (UTF-8), making its directory if needed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
