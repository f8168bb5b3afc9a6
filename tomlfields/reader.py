"""The reader: :class:`FieldError`, value checks, :func:`load_toml` and :class:`Table`."""

from __future__ import annotations

import math
import numbers
import tomllib
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any, Self

_MISSING: Any = object()
"""Default of a required field. Optional fields: test ``key in table`` first."""


class FieldError(ValueError):
    """A setting is invalid. ``source`` names the file (``""``: a value built in code),
    ``field`` the setting in dotted form, ``problem`` the value and what is allowed.

    Each package raises its own subclass (``companion.errors.ConfigError``, sim_servo's and
    firmware_interface's settings errors); every subclass is built as
    ``error(source, field, problem)``.
    """

    def __init__(self, source: str, field: str, problem: str) -> None:
        self.source = source
        self.field = field
        self.problem = problem
        super().__init__(f"{source}: {field}: {problem}" if source else f"{field}: {problem}")

    def at(self, source: str) -> Self:
        """The same error, naming ``source`` (for a value checked before its file was known)."""
        return type(self)(source, self.field, self.problem)


def is_int(value: object) -> bool:
    """An integer, not a bool (numpy integers count)."""
    # The exact type first: the ABC check costs a microsecond, several times a control tick.
    return type(value) is int or (
        isinstance(value, numbers.Integral) and not isinstance(value, bool)
    )


def is_real(value: object) -> bool:
    """A real number, not a bool (numpy floats and integers count; NaN too: see
    :func:`check_number`)."""
    return type(value) in (float, int) or (
        isinstance(value, numbers.Real) and not isinstance(value, bool)
    )


def _text(bound: float) -> str:
    if is_int(bound):
        return str(bound)
    if float(bound).is_integer() and abs(bound) < 1e16:  # 1e6 reads as 1000000, not 1e+06
        return str(int(bound))
    return f"{bound:g}"


def range_text(min_value: float | None, max_value: float | None, *, positive: bool = False) -> str:
    """``[1, 400]``, ``(0, 60]`` (``positive``, no lower bound of its own), ``[0, inf)``."""
    if positive and (min_value is None or min_value <= 0):
        low = "(0"
    else:
        low = "(-inf" if min_value is None else f"[{_text(min_value)}"
    high = "inf)" if max_value is None else f"{_text(max_value)}]"
    return f"{low}, {high}"


def _range_problem(
    value: float, min_value: float | None, max_value: float | None, positive: bool, unit: str
) -> str | None:
    unit = f" {unit}" if unit else ""
    if (
        (positive and not value > 0)
        or (min_value is not None and value < min_value)
        or (max_value is not None and value > max_value)
    ):
        if positive and min_value is None and max_value is None:
            return f"{value!r} must be > 0{unit}"
        return f"{value!r} outside {range_text(min_value, max_value, positive=positive)}{unit}"
    return None


def check_number(
    value: Any,
    field: str,
    *,
    error: type[FieldError],
    source: str = "",
    min_value: float | None = None,
    max_value: float | None = None,
    positive: bool = False,
    unit: str = "",
) -> float:
    """``value`` as a float: a finite number within ``[min_value, max_value]`` (``positive``:
    also ``> 0``). Otherwise raises ``error(source, field, problem)``, the problem giving the
    value and the whole allowed range (``1e-10 outside [1, 400]``, ``0 outside (0, 1000]``),
    followed by ``unit`` if given."""
    if not is_real(value):
        raise error(source, field, f"must be a number, got {value!r}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond the float range, e.g. 10**400
        number = math.inf
    if not math.isfinite(number):
        raise error(source, field, f"must be a finite number, got {value!r}")
    problem = _range_problem(value, min_value, max_value, positive, unit)
    if problem:
        raise error(source, field, problem)
    return number


def check_integer(
    value: Any,
    field: str,
    *,
    error: type[FieldError],
    source: str = "",
    min_value: int | None = None,
    max_value: int | None = None,
    unit: str = "",
) -> int:
    """``value`` as an int within ``[min_value, max_value]``; a bool or a float (even ``2.0``)
    is refused."""
    if not is_int(value):
        raise error(source, field, f"must be an integer, got {value!r}")
    problem = _range_problem(value, min_value, max_value, False, unit)
    if problem:
        raise error(source, field, problem)
    return int(value)


def check_numbers(
    value: Any,
    field: str,
    *,
    length: int,
    error: type[FieldError],
    source: str = "",
    min_value: float | None = None,
    max_value: float | None = None,
    unit: str = "",
) -> list[float]:
    """A list (or tuple) of exactly ``length`` finite numbers, each within
    ``[min_value, max_value]``; a bad one is named ``field[i]``, counted from 0."""
    if not isinstance(value, list | tuple) or len(value) != length:
        raise error(source, field, f"must be a list of {length} numbers, got {value!r}")
    out = []
    for i, item in enumerate(value):
        if not is_real(item):
            raise error(source, f"{field}[{i}]", f"must be a finite number, got {item!r}")
        out.append(
            check_number(
                item,
                f"{field}[{i}]",
                error=error,
                source=source,
                min_value=min_value,
                max_value=max_value,
                unit=unit,
            )
        )
    return out


def check_boolean(value: Any, field: str, *, error: type[FieldError], source: str = "") -> bool:
    """``value`` if it is ``True`` or ``False`` (not 0 or 1, not a string)."""
    if not isinstance(value, bool):
        raise error(source, field, f"must be true or false, got {value!r}")
    return value


def load_toml(path: str | Path, error: type[FieldError]) -> dict[str, Any]:
    """Read and parse a TOML file; an unreadable or invalid file raises
    ``error(path, "<file>", problem)``."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(str(path), "<file>", f"cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:  # TOML is UTF-8
        raise error(
            str(path), "<file>", f"not valid TOML: not UTF-8 ({exc.reason} at byte {exc.start})"
        ) from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(str(path), "<file>", f"not valid TOML: {exc}") from exc
    except RecursionError as exc:  # tomllib recurses once per nested array or inline table
        raise error(str(path), "<file>", "not valid TOML: nested too deeply") from exc


class Table:
    """One table of a settings file; ``prefix`` is its dotted name (``""`` for the root).

    ``allowed``: the only keys it may hold (None: any). Every problem raises ``error``.
    """

    def __init__(
        self,
        data: Any,
        source: str,
        prefix: str = "",
        *,
        error: type[FieldError],
        allowed: Collection[str] | None = None,
    ) -> None:
        self.source = source
        self.prefix = prefix
        self.error = error
        if not isinstance(data, Mapping):
            raise error(source, prefix or "<root>", "must be a table")
        self.data: Mapping[Any, Any] = data
        if allowed is not None:
            self.allow(allowed)

    def allow(self, allowed: Collection[str]) -> None:
        """Refuse any key but ``allowed``, naming the first unknown one and listing the rest."""
        unknown = sorted((key for key in self.data if key not in allowed), key=str)
        if unknown:
            raise self.fail(unknown[0], f"unknown field; allowed: {', '.join(sorted(allowed))}")

    def name(self, key: object) -> str:
        return f"{self.prefix}.{key}" if self.prefix else str(key)

    def fail(self, key: object, problem: str) -> FieldError:
        """The error naming ``key`` of this table (for the caller to raise)."""
        return self.error(self.source, self.name(key), problem)

    def __contains__(self, key: str) -> bool:
        return key in self.data

    def _get(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            raise self.fail(key, "missing (required)")
        return default

    def number(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        min_value: float | None = None,
        max_value: float | None = None,
        positive: bool = False,
        unit: str = "",
    ) -> float:
        """A finite number (see :func:`check_number`)."""
        return check_number(
            self._get(key, default),
            self.name(key),
            error=self.error,
            source=self.source,
            min_value=min_value,
            max_value=max_value,
            positive=positive,
            unit=unit,
        )

    def integer(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        min_value: int | None = None,
        max_value: int | None = None,
        unit: str = "",
    ) -> int:
        """An integer (see :func:`check_integer`)."""
        return check_integer(
            self._get(key, default),
            self.name(key),
            error=self.error,
            source=self.source,
            min_value=min_value,
            max_value=max_value,
            unit=unit,
        )

    def string(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] = ()) -> str:
        """A non-empty string, one of ``choices`` if given."""
        value = self._get(key, default)
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"must be a non-empty string, got {value!r}")
        if choices and value not in choices:
            raise self.fail(key, f"{value!r} is not one of {', '.join(choices)}")
        return value

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        return check_boolean(
            self._get(key, default), self.name(key), error=self.error, source=self.source
        )

    def numbers(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        length: int,
        min_value: float | None = None,
        max_value: float | None = None,
        unit: str = "",
    ) -> list[float]:
        """A list of exactly ``length`` finite numbers (see :func:`check_numbers`)."""
        return check_numbers(
            self._get(key, default),
            self.name(key),
            length=length,
            error=self.error,
            source=self.source,
            min_value=min_value,
            max_value=max_value,
            unit=unit,
        )

    def table(self, key: str, *, allowed: Collection[str] | None = None) -> Table:
        """A sub-table (an empty one if absent)."""
        return Table(
            self.data.get(key, {}), self.source, self.name(key), allowed=allowed, error=self.error
        )

    def tables(self, key: str, *, allowed: Collection[str] | None = None) -> list[Table]:
        """An array of tables (``[[key]]``), required and non-empty; row ``i`` (from 1) is
        named ``key[i]``."""
        rows = self.data.get(key)
        if not isinstance(rows, list) or not rows or not all(isinstance(r, Mapping) for r in rows):
            raise self.fail(key, f"must be an array of tables ([[{key}]]), one per entry")
        return [
            Table(row, self.source, f"{self.name(key)}[{i}]", allowed=allowed, error=self.error)
            for i, row in enumerate(rows, start=1)
        ]
