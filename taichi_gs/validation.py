"""Config values checked before any work starts: types come from the dataclasses (``config.py``),
ranges, choices and relations between fields from the rules each stage's config declares.

A field declares its rules beside its default, ``name: float = setting(0.5, FRACTION)`` (they live in the
field's ``metadata["rules"]``); every non-boolean field declares at least one (``ANY`` where no value is
wrong, ``LEARNING_RATE`` for every ``lr_*``: all are per-step rates in metres, radians, logits or colour
units, or fractions of the scene extent). Relations between a config's fields are its ``RELATIONS``. Every
float must be finite. A broken rule is an :class:`~taichi_gs.errors.InputError` naming the section and key.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import InputError

# The field metadata keys configs may set: "rules" (see setting) and "pair" (stage 1: False for a field that
# does not change a pair's own result, so stays out of the pair cache's key).
METADATA_KEYS = frozenset({"rules", "pair"})


@dataclass(frozen=True)
class Rule:
    """What a value must be: ``check`` passes it, ``text`` says it ("at least 1")."""

    check: Callable[[Any], bool]
    text: str

    def error(self, key: str, value: Any) -> tuple[str, str]:
        """(message, fix) of a value that breaks the rule."""
        return f"{key} = {value!r} must be {self.text}", "fix the value in the config file"


@dataclass(frozen=True)
class _LearningRate(Rule):
    def error(self, key: str, value: Any) -> tuple[str, str]:
        return (f"{key} = {value:g} is not a learning rate in [0, 1]",
                "use the preset's value (see OUT/config.toml) or one near it")


def at_least(low: float) -> Rule:
    return Rule(lambda v: v >= low, f"at least {low:g}")


def above(low: float) -> Rule:
    return Rule(lambda v: v > low, f"above {low:g}")


def within(low: float, high: float) -> Rule:
    return Rule(lambda v: low <= v <= high, f"in [{low:g}, {high:g}]")


def one_of(*choices: Any) -> Rule:
    return Rule(lambda v: v in choices, "one of " + ", ".join(map(str, choices)))


def each(rule: Rule) -> Rule:
    return Rule(lambda v: len(v) > 0 and all(rule.check(x) for x in v), f"a non-empty list, each {rule.text}")


POSITIVE, NON_NEGATIVE, FRACTION = above(0), at_least(0), within(0, 1)
COUNT, OPTIONAL_COUNT = at_least(1), at_least(0)
FRAME_GAPS = Rule(lambda v: all(isinstance(k, int) and k >= 2 for k in v), "a list of frame gaps of at least 2")
LEARNING_RATE = _LearningRate(lambda v: 0.0 <= v <= 1.0, "a learning rate in [0, 1]")
ANY = Rule(lambda v: True, "any value")  # declared free: every value of the field's type is allowed


def setting(default: Any, *rules: Rule, **metadata: Any) -> Any:
    """A config field with ``default`` and the ``rules`` its values must keep, checked in order; ``metadata``
    (``METADATA_KEYS``) beside them."""
    unknown = set(metadata) - METADATA_KEYS
    if unknown:
        raise TypeError(f"unknown config field metadata {sorted(unknown)}; use {sorted(METADATA_KEYS - {'rules'})}")
    return dataclasses.field(default=default, metadata={"rules": rules, **metadata})


def rules_of(field: dataclasses.Field) -> tuple[Rule, ...]:
    """The rules a config field declares (none for a field made without :func:`setting`)."""
    return field.metadata.get("rules", ())


def validate_sections(sections: dict[str, Any], source: Path | None = None) -> None:
    """Raise an InputError for the first value of any section that breaks a rule (see module doc), then
    for the first broken relation."""
    for name, section in sections.items():
        for field in dataclasses.fields(section):
            value = getattr(section, field.name)
            key = f"[{name}] {field.name}"
            if isinstance(value, float) and not math.isfinite(value):
                raise InputError(source, f"{key} = {value} is not a finite number", "give a finite value")
            for rule in rules_of(field):
                if not rule.check(value):
                    raise InputError(source, *rule.error(key, value))
    for name, section in sections.items():
        for text, check in getattr(section, "RELATIONS", ()):
            if not check(section):
                raise InputError(source, f"[{name}] {text}", "fix the values in the config file")
