"""The shared strict reader: every refusal is the caller's error class, naming the source, the
dotted field, the value and what is allowed."""

import math

import numpy as np
import pytest

from tomlfields import (
    FieldError,
    Table,
    check_boolean,
    check_integer,
    check_number,
    is_int,
    is_real,
    load_toml,
    range_text,
)


class MyError(FieldError):
    """A package's own error class, as each package passes its own."""


def refused(call, *args, **kwargs) -> MyError:
    with pytest.raises(MyError) as info:
        call(*args, **kwargs)
    return info.value


def test_the_message_is_source_field_problem_and_the_parts_are_kept():
    error = MyError("x.toml", "link.url", "missing (required)")
    assert str(error) == "x.toml: link.url: missing (required)"
    assert (error.source, error.field, error.problem) == (
        "x.toml",
        "link.url",
        "missing (required)",
    )
    assert str(MyError("", "servo.deadband_us", "-1 outside [0, 100]")) == (
        "servo.deadband_us: -1 outside [0, 100]"
    )
    located = MyError("", "a.b", "bad").at("flags")
    assert isinstance(located, MyError) and str(located) == "flags: a.b: bad"
    assert isinstance(error, ValueError)


def test_range_text_shows_integers_exactly_and_floats_short():
    assert range_text(1, 255) == "[1, 255]"
    assert range_text(0, 2**63 - 1) == f"[0, {2**63 - 1}]"
    assert range_text(1.0, 400.0) == "[1, 400]"
    assert range_text(1e-6, 10.0) == "[1e-06, 10]"
    assert range_text(None, 1000.0, positive=True) == "(0, 1000]"
    assert range_text(0, None) == "[0, inf)"
    assert range_text(None, None) == "(-inf, inf)"


@pytest.mark.parametrize(
    ("value", "bounds", "problem"),
    [
        ("1", {}, "must be a number, got '1'"),
        (True, {}, "must be a number, got True"),
        (None, {}, "must be a number, got None"),
        (math.nan, {}, "must be a finite number, got nan"),
        (-math.inf, {}, "must be a finite number, got -inf"),
        (10**400, {}, "must be a finite number, got 1000"),  # beyond the float range
        (1e-10, {"min_value": 1.0, "max_value": 400.0}, "1e-10 outside [1, 400]"),
        (0, {"max_value": 1000.0, "positive": True}, "0 outside (0, 1000]"),
        (-2.5, {"positive": True}, "-2.5 must be > 0"),
        (3000, {"min_value": 500, "max_value": 2500, "unit": "µs"}, "3000 outside [500, 2500] µs"),
    ],
)
def test_check_number_refusals(value, bounds, problem):
    error = refused(check_number, value, "a.b", error=MyError, source="s.toml", **bounds)
    assert error.field == "a.b" and error.source == "s.toml"
    assert error.problem.startswith(problem), error.problem


def test_check_number_accepts_the_ends_and_numpy_numbers():
    assert check_number(1, "f", error=MyError, min_value=1.0, max_value=2.0) == 1.0
    assert check_number(2.0, "f", error=MyError, min_value=1.0, max_value=2.0) == 2.0
    value = check_number(np.float32(1.5), "f", error=MyError)
    assert value == 1.5 and type(value) is float


def test_check_integer_and_boolean():
    assert check_integer(np.int64(7), "f", error=MyError, min_value=1) == 7
    assert refused(check_integer, 2.0, "f", error=MyError).problem == "must be an integer, got 2.0"
    assert refused(check_integer, False, "f", error=MyError).problem == (
        "must be an integer, got False"
    )
    assert refused(check_integer, 256, "f", error=MyError, min_value=1, max_value=255).problem == (
        "256 outside [1, 255]"
    )
    assert check_boolean(False, "f", error=MyError) is False
    assert refused(check_boolean, 1, "f", error=MyError).problem == "must be true or false, got 1"


def test_is_int_and_is_real_refuse_bools_and_text():
    assert is_int(3) and is_int(np.int16(3)) and not is_int(True) and not is_int(3.0)
    assert is_real(3) and is_real(np.float64(0.5)) and is_real(math.nan)
    assert not is_real(False) and not is_real("1") and not is_real(None)


def test_load_toml_names_the_file_for_every_way_it_can_fail(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("a = 1\n")
    assert load_toml(good, MyError) == {"a": 1}
    cases = {
        "missing.toml": (None, "cannot read"),
        "broken.toml": (b"a = \n", "not valid TOML"),
        "latin.toml": (b"a = 'caf\xe9'\n", "not UTF-8"),
        "deep.toml": (b"a = " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested too deeply"),
    }
    for name, (content, words) in cases.items():
        path = tmp_path / name
        if content is not None:
            path.write_bytes(content)
        error = refused(load_toml, path, MyError)
        assert (error.source, error.field) == (str(path), "<file>") and words in error.problem


def test_table_names_dotted_fields_and_refuses_unknown_keys():
    root = Table({"link": {"url": "u", "typo": 1}}, "x.toml", error=MyError)
    error = refused(root.table, "link", allowed=("url", "dialect"))
    assert str(error) == "x.toml: link.typo: unknown field; allowed: dialect, url"
    link = root.table("link")
    assert link.string("url") == "u" and link.number("rate", 2.5) == 2.5
    assert refused(link.number, "absent").field == "link.absent"
    assert refused(link.string, "typo").problem == "must be a non-empty string, got 1"
    assert refused(Table, 5, "x.toml", "servo", error=MyError).problem == "must be a table"
    rows = Table({"joint": [{"output": 9}, {"output": 0}]}, "x.toml", error=MyError).tables("joint")
    assert [row.prefix for row in rows] == ["joint[1]", "joint[2]"]
    assert str(refused(rows[1].integer, "output", min_value=1, max_value=16)) == (
        "x.toml: joint[2].output: 0 outside [1, 16]"
    )


def test_an_unknown_key_that_is_not_text_is_named():
    error = refused(Table, {1: "x", "a": 2}, "<dict>", "outputs", error=MyError, allowed=("a",))
    assert error.field == "outputs.1"


def test_numbers_checks_length_type_finiteness_and_range_naming_the_item():
    t = Table(
        {"xyz": [0, 1e308, 2], "two": [1, 2], "text": [0, "x", 1]}, "f", "mount", error=MyError
    )
    assert t.numbers("xyz", length=3) == [0.0, 1e308, 2.0]
    error = refused(t.numbers, "xyz", length=3, min_value=-500.0, max_value=500.0)
    assert str(error) == "f: mount.xyz[1]: 1e+308 outside [-500, 500]"
    assert refused(t.numbers, "two", length=3).problem == "must be a list of 3 numbers, got [1, 2]"
    assert refused(t.numbers, "text", length=3).field == "mount.text[1]"
