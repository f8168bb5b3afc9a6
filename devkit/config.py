"""The one TOML writer of the tests: a dict becomes a daemon config file.

The standard library reads TOML but does not write it; this small writer covers what the daemon
config uses (tables, arrays of tables, strings, numbers, booleans, arrays, inline tables) plus
non-finite floats and date-times, which the config fuzz needs.
"""

from __future__ import annotations

import datetime
import json
import math
from pathlib import Path
from typing import Any


def toml_value(value: Any) -> str:
    """``value`` as a TOML literal."""
    if isinstance(value, datetime.datetime):
        return value.isoformat().replace("+00:00", "Z")
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a TOML basic string
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML for {value!r}")


def _is_table_array(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def toml_document(data: dict[str, Any]) -> str:
    """``data`` as a TOML document: top-level keys first, then ``[table]`` for each dict and
    ``[[table]]`` rows for each non-empty list of dicts."""
    lines = [
        f"{key} = {toml_value(value)}"
        for key, value in data.items()
        if not isinstance(value, dict) and not _is_table_array(value)
    ]
    for key, value in data.items():
        if isinstance(value, dict):
            lines.append(f"[{key}]")
            lines += [f"{k} = {toml_value(v)}" for k, v in value.items()]
        elif _is_table_array(value):
            for row in value:
                lines.append(f"[[{key}]]")
                lines += [f"{k} = {toml_value(v)}" for k, v in row.items()]
    return "\n".join(lines) + "\n"


def write_config(path: Path, data: dict[str, Any]) -> Path:
    """Write ``data`` as TOML to ``path``; returns ``path``."""
    path.write_text(toml_document(data))
    return path
