"""What counts as reproducing a row of the papers' Tables 5 and 7, and how a row is named.

A row is named ``TABLE:TEST`` (``5:12`` is Table 5 test 12, the DE row with NP 20 and 750
generations; ``7:18`` is Table 7 test 18, an MSFLA row). :func:`parse_row` checks the name
against the tables in :mod:`companion.papers.constants`.

A row's verdict compares our runs of its settings with the J the paper prints for it
(:func:`judge`): a run *reaches* the row when its J is at most the printed J. The paper prints
one run per row and does not say how many it made, so the rule asks how often a run of ours
does at least as well:

* :attr:`Verdict.REPRODUCED` — at least half of our runs reach it (a typical run does);
* :attr:`Verdict.SOMETIMES` — at least one, fewer than half;
* :attr:`Verdict.NOT_REPRODUCED` — none does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

from companion.papers import constants

TABLES: dict[int, list[tuple[Any, ...]]] = {
    5: list(constants.TABLE5_DE),
    7: list(constants.TABLE7_MSFLA),
}
"""The tables a row can name, by number: Table 5 (DE) and Table 7 (MSFLA)."""

_PRINTED_J_COLUMN = {5: 3, 7: 4}


@dataclass(frozen=True)
class TableRow:
    """One row of Table 5 or Table 7: ``table`` (5 or 7) and its ``test`` number."""

    table: int
    test: int

    def __post_init__(self) -> None:
        if self.table not in TABLES:
            raise ValueError(f"table={self.table!r} is not one of {sorted(TABLES)}")
        tests = [row[0] for row in TABLES[self.table]]
        if self.test not in tests:
            raise ValueError(
                f"test={self.test!r} outside [{min(tests)}, {max(tests)}] for Table {self.table}"
            )

    @property
    def settings(self) -> tuple[Any, ...]:
        """The row as printed (:data:`constants.TABLE5_DE` / :data:`constants.TABLE7_MSFLA`)."""
        return next(row for row in TABLES[self.table] if row[0] == self.test)

    @property
    def printed_j(self) -> float:
        """The J the paper prints for the row."""
        return float(self.settings[_PRINTED_J_COLUMN[self.table]])

    def __str__(self) -> str:
        return f"{self.table}:{self.test}"


def parse_row(text: str) -> TableRow:
    """``"5:12"`` → Table 5 test 12. Raises ``ValueError`` naming the bad value and the forms
    allowed."""
    table, sep, test = text.strip().partition(":")
    allowed = ", ".join(f"{t}:1…{t}:{max(row[0] for row in rows)}" for t, rows in TABLES.items())
    if not sep or not table.isdigit() or not test.isdigit():
        raise ValueError(f"row={text!r} is not TABLE:TEST; allowed: {allowed}")
    try:
        return TableRow(int(table), int(test))
    except ValueError as exc:
        raise ValueError(f"row={text!r}: {exc}; allowed: {allowed}") from exc


class Verdict(Enum):
    """How often our runs of a row's settings reach the J the paper prints for it."""

    REPRODUCED = "reproduced"
    SOMETIMES = "sometimes"
    NOT_REPRODUCED = "not reproduced"


@dataclass(frozen=True)
class RowVerdict:
    """``reached`` of ``runs`` runs ended with J at most the printed J."""

    verdict: Verdict
    reached: int
    runs: int

    def __str__(self) -> str:
        return f"{self.verdict.value} ({self.reached}/{self.runs})"


def judge(costs: Sequence[float], printed_j: float) -> RowVerdict:
    """The verdict of our runs' final J values ``costs`` against a row's ``printed_j``."""
    if len(costs) == 0:
        raise ValueError("costs is empty: a verdict needs at least one run")
    if not all(math.isfinite(c) and c >= 0.0 for c in costs):
        raise ValueError(f"costs={list(costs)!r} must be finite values >= 0")
    if not (math.isfinite(printed_j) and printed_j >= 0.0):
        raise ValueError(f"printed_j={printed_j!r} must be a finite value >= 0")
    reached = sum(1 for c in costs if c <= printed_j)
    if 2 * reached >= len(costs):
        verdict = Verdict.REPRODUCED
    elif reached > 0:
        verdict = Verdict.SOMETIMES
    else:
        verdict = Verdict.NOT_REPRODUCED
    return RowVerdict(verdict, reached, len(costs))
