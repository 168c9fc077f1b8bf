"""Configuration as data: stage dataclasses to and from TOML, with clear errors for bad keys."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

from .errors import InputError
from .io.atomic import write_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if value is None:
        raise ValueError("TOML has no null: give the field a concrete default")
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def to_toml(sections: dict[str, Any]) -> str:
    """TOML text with one table per dataclass section."""
    lines: list[str] = []
    for name, section in sections.items():
        lines.append(f"[{name}]")
        for field in dataclasses.fields(section):
            lines.append(f"{field.name} = {_toml_value(getattr(section, field.name))}")
        lines.append("")
    return "\n".join(lines)


def write_config(path: str | Path, sections: dict[str, Any]) -> None:
    """Write the resolved configuration atomically."""
    write_text(path, to_toml(sections))


def read_config(path: str | Path, sections: dict[str, Any]) -> dict[str, Any]:
    """Sections updated with the values of a TOML file; unknown tables or keys are errors."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "config file not found", "give an existing TOML file")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise InputError(path, f"invalid TOML ({err})", "fix the syntax") from None
    updated = dict(sections)
    for table, values in data.items():
        if table not in sections or not isinstance(values, dict):
            raise InputError(path, f"unknown table [{table}]", f"use one of {', '.join(f'[{s}]' for s in sections)}")
        updated[table] = _apply(path, table, sections[table], values)
    return updated


def _apply(path: Path, table: str, section: Any, values: dict[str, Any]) -> Any:
    fields = {f.name: f for f in dataclasses.fields(section)}
    changes = {}
    for key, value in values.items():
        if key not in fields:
            raise InputError(path, f"unknown key {key!r} in [{table}]", f"valid keys: {', '.join(fields)}")
        current = getattr(section, key)
        if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if isinstance(current, tuple) and isinstance(value, list):
            value = tuple(value)
        if type(value) is not type(current):
            raise InputError(path, f"[{table}] {key} must be {type(current).__name__}, got {type(value).__name__}", "fix the value's type")
        changes[key] = value
    return dataclasses.replace(section, **changes)
