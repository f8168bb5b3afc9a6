"""Typed, validated access to a parsed TOML table, for every config file of the project.

Every problem raises ``ConfigError(source, "dotted.field", problem)`` with the allowed values,
so a user reading the message knows which line to fix and what to write there. Unknown keys
are refused too: a typo must not silently fall back to a default.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from companion.errors import ConfigError

_MISSING: Any = object()
"""Default of a required field. Optional fields: test ``key in table`` first."""


def load_toml(path: str | Path, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """Read and parse a TOML file; unreadable or invalid files raise ``error`` naming the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(str(path), "<file>", f"cannot read: {exc.strerror}") from exc
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


def _range_text(min_value: float | None, max_value: float | None, *, positive: bool = False) -> str:
    """``[1, 400]``, ``(0, 60]`` (``positive``, no lower bound of its own), ``[0, inf)``."""
    if positive and (min_value is None or min_value <= 0):
        low = "(0"
    else:
        low = "(-inf" if min_value is None else f"[{min_value:g}"
    high = "inf)" if max_value is None else f"{max_value:g}]"
    return f"{low}, {high}"


class Table:
    """One table of a config file; ``prefix`` is its dotted name (``""`` for the root)."""

    def __init__(
        self,
        data: Any,
        source: str,
        prefix: str = "",
        *,
        allowed: Sequence[str] | None = None,
        error: type[ConfigError] = ConfigError,
    ) -> None:
        self.source = source
        self.prefix = prefix
        self.error = error
        if not isinstance(data, Mapping):
            raise error(source, prefix or "<root>", "must be a table")
        self.data = data
        if allowed is not None:
            unknown = sorted(set(data) - set(allowed))
            if unknown:
                raise error(
                    source,
                    self.name(unknown[0]),
                    f"unknown field; allowed: {', '.join(sorted(allowed))}",
                )

    def name(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def fail(self, key: str, problem: str) -> ConfigError:
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
    ) -> float:
        """A finite number, optionally within ``[min_value, max_value]``; ``positive``: ``> 0``.

        Out of range, the message gives the value and the whole allowed range, e.g.
        ``1e-10 outside [1, 400]`` or ``0 outside (0, 1000]``.
        """
        value = self._get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(key, f"must be a number, got {value!r}")
        if not math.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        if (
            (positive and not value > 0)
            or (min_value is not None and value < min_value)
            or (max_value is not None and value > max_value)
        ):
            if positive and min_value is None and max_value is None:
                raise self.fail(key, f"{value!r} must be > 0")
            raise self.fail(
                key, f"{value!r} outside {_range_text(min_value, max_value, positive=positive)}"
            )
        return float(value)

    def integer(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        min_value: int | None = None,
        max_value: int | None = None,
    ) -> int:
        value = self._get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"must be an integer, got {value!r}")
        if (min_value is not None and value < min_value) or (
            max_value is not None and value > max_value
        ):
            raise self.fail(key, f"{value!r} outside {_range_text(min_value, max_value)}")
        return value

    def string(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] = ()) -> str:
        value = self._get(key, default)
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"must be a non-empty string, got {value!r}")
        if choices and value not in choices:
            raise self.fail(key, f"{value!r} is not one of {', '.join(choices)}")
        return value

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        value = self._get(key, default)
        if not isinstance(value, bool):
            raise self.fail(key, f"must be true or false, got {value!r}")
        return value

    def numbers(self, key: str, default: Any = _MISSING, *, length: int) -> list[float]:
        """A list of exactly ``length`` finite numbers."""
        value = self._get(key, default)
        if not isinstance(value, list) or len(value) != length:
            raise self.fail(key, f"must be a list of {length} numbers, got {value!r}")
        for i, v in enumerate(value):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise self.fail(f"{key}[{i}]", f"must be a finite number, got {v!r}")
        return [float(v) for v in value]

    def table(self, key: str, *, allowed: Sequence[str] | None = None) -> Table:
        """A sub-table (an empty one if absent)."""
        return Table(
            self.data.get(key, {}), self.source, self.name(key), allowed=allowed, error=self.error
        )

    def tables(self, key: str, *, allowed: Sequence[str] | None = None) -> list[Table]:
        """An array of tables (``[[key]]``), required and non-empty."""
        rows = self.data.get(key)
        if not isinstance(rows, list) or not rows or not all(isinstance(r, Mapping) for r in rows):
            raise self.fail(key, f"must be an array of tables ([[{key}]]), one per entry")
        return [
            Table(row, self.source, f"{self.name(key)}[{i}]", allowed=allowed, error=self.error)
            for i, row in enumerate(rows, start=1)
        ]
