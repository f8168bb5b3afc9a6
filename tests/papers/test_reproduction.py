"""Row names (``TABLE:TEST``) and the verdict rule of companion.papers.reproduction."""

from __future__ import annotations

import pytest

from companion.papers import constants
from companion.papers.reproduction import TableRow, Verdict, judge, parse_row


def test_a_row_name_gives_the_printed_row():
    row = parse_row("5:12")
    assert row == TableRow(5, 12)
    assert row.settings == constants.TABLE5_DE[11]
    assert row.printed_j == constants.TABLE5_DE[11][3]
    assert str(row) == "5:12"
    msfla = parse_row(" 7:18 ")
    assert msfla.settings == constants.TABLE7_MSFLA[17]
    assert msfla.printed_j == constants.TABLE7_MSFLA[17][4]


@pytest.mark.parametrize("text", ["12", "5:", ":3", "5:x", "6:1", "5:0", "5:15", "7:21", "5:-1"])
def test_a_bad_row_name_is_refused_with_the_forms_allowed(text):
    with pytest.raises(ValueError, match=r"5:1…5:14, 7:1…7:20"):
        parse_row(text)


def test_every_printed_row_has_a_name():
    names = [f"5:{r[0]}" for r in constants.TABLE5_DE] + [
        f"7:{r[0]}" for r in constants.TABLE7_MSFLA
    ]
    assert [str(parse_row(n)) for n in names] == names


def test_at_least_half_of_the_runs_at_or_below_the_printed_j_reproduce_it():
    v = judge([0.1, 0.2, 0.3, 0.4], 0.2)  # 0.2 itself counts: "at most the printed J"
    assert (v.verdict, v.reached, v.runs) == (Verdict.REPRODUCED, 2, 4)
    assert str(v) == "reproduced (2/4)"
    assert judge([0.5], 0.5).verdict is Verdict.REPRODUCED


def test_fewer_than_half_is_sometimes_and_none_is_not_reproduced():
    assert judge([0.1, 0.3, 0.4, 0.5], 0.2).verdict is Verdict.SOMETIMES
    assert judge([1e-5] + [1.0] * 9, 1.2e-5).reached == 1
    v = judge([0.3, 0.4], 0.2)
    assert (v.verdict, v.reached) == (Verdict.NOT_REPRODUCED, 0)


@pytest.mark.parametrize(
    ("costs", "printed"), [([], 1.0), ([float("nan")], 1.0), ([-1.0], 1.0), ([1.0], -1.0)]
)
def test_judge_refuses_what_is_not_a_cost(costs, printed):
    with pytest.raises(ValueError):
        judge(costs, printed)
