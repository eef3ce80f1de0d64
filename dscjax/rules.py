"""The rules of settings: how one value is read from a file (TOML or JSON data, `parse`) and
from the command line (its text, `from_text`), written back (`dump`) and described (`text`, as
in "must be <text>"). "none" reads as None alike in both places (`Maybe`).

    Maybe(Positive()).parse("none") is None; AtLeast(1).from_text("1e5") == 100000
    Number(gt=0, le=1).text == "a finite number in (0, 1]"
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np


class Invalid(Exception):
    """A value refused by a rule: what it must be, and the value."""

    def __init__(self, must: str, value):
        super().__init__(must)
        self.must, self.value = must, value


class Rule:
    """How one setting is read (`parse`: from TOML/JSON data; `from_text`: from the command
    line), written (`dump`) and described (`text`, as in "must be <text>")."""

    text = "a value"
    metavar = "VALUE"
    hint = ""  # how a value is typed on the command line, where it differs from a file

    def from_text(self, text: str):
        return self.parse(_literal(text))  # each rule has its `parse`

    def dump(self, value):
        """The value as plain data; a tuple (of `Numbers`, `Strings`) as a list: TOML and JSON
        have no tuples."""
        return list(value) if isinstance(value, tuple) else value


@dataclasses.dataclass(frozen=True)
class Number(Rule):
    """A finite number (not a boolean) within the bounds given; `integer`: an int."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    integer: bool = False

    @property
    def text(self) -> str:
        kind = "an integer" if self.integer else "a finite number"
        lo = ("(", ">", self.gt) if self.gt is not None else ("[", ">=", self.ge)
        hi = (")", "<", self.lt) if self.lt is not None else ("]", "<=", self.le)
        if lo[2] is not None and hi[2] is not None:
            return f"{kind} in {lo[0]}{lo[2]:g}, {hi[2]:g}{hi[0]}"
        bound = lo if lo[2] is not None else hi if hi[2] is not None else None
        return kind if bound is None else f"{kind} {bound[1]} {bound[2]:g}"

    @property
    def metavar(self) -> str:
        return "N" if self.integer else "X"

    def parse(self, value):
        ok_type = (int, np.integer) if self.integer else (int, float, np.integer, np.floating)
        if isinstance(value, bool | np.bool_) or not isinstance(value, ok_type) \
                or not math.isfinite(value):
            raise Invalid(self.text, value)
        x = int(value) if self.integer else float(value)
        if ((self.gt is not None and not x > self.gt) or (self.ge is not None and not x >= self.ge)
                or (self.lt is not None and not x < self.lt)
                or (self.le is not None and not x <= self.le)):
            raise Invalid(self.text, value)
        return x

    def from_text(self, text: str):
        value = _literal(text)
        if self.integer and isinstance(value, float) and value.is_integer():
            value = int(value)  # 1e5 typed for a count
        return self.parse(value)


def Positive() -> Number:  # noqa: N802 (a rule reads as a type)
    return Number(gt=0)


def AtLeast(low: int) -> Number:  # noqa: N802
    """An integer >= low."""
    return Number(ge=low, integer=True)


@dataclasses.dataclass(frozen=True)
class Choice(Rule):
    """One of a few names; with a mapping, the name's object (a strategy) is the value."""

    options: tuple[str, ...] | Mapping[str, Any]

    @property
    def text(self) -> str:
        return "one of " + ", ".join(repr(k) for k in self.options)

    @property
    def metavar(self) -> str:
        return "{" + ",".join(self.options) + "}"

    def parse(self, value):
        if not isinstance(value, str) and isinstance(self.options, Mapping) and any(
                type(value) is type(o) for o in self.options.values()):
            return value  # a strategy built in code (`settings.checked`)
        if not isinstance(value, str) or value not in self.options:
            raise Invalid(self.text, value)
        return self.options[value] if isinstance(self.options, Mapping) else value

    def from_text(self, text: str):
        return self.parse(text)

    def dump(self, value):
        if not isinstance(self.options, Mapping):
            return value
        return next((name for name, obj in self.options.items() if obj is value or obj == value),
                    getattr(value, "name", value))


@dataclasses.dataclass(frozen=True)
class Maybe(Rule):
    """`rule`, or None, written "none" in a file and on the command line alike."""

    rule: Rule

    @property
    def text(self) -> str:
        return f'{self.rule.text}, or "none"'

    @property
    def metavar(self) -> str:
        return self.rule.metavar

    @property
    def hint(self) -> str:
        return self.rule.hint

    def _read(self, read, value):
        if value is None or (isinstance(value, str) and value.strip().lower() == "none"):
            return None
        try:
            return read(self.rule, value)
        except Invalid:
            raise Invalid(self.text, value) from None

    def parse(self, value):
        return self._read(lambda r, v: r.parse(v), value)

    def from_text(self, text: str):
        return self._read(lambda r, v: r.from_text(v), text)

    def dump(self, value):
        return "none" if value is None else self.rule.dump(value)


@dataclasses.dataclass(frozen=True)
class Either(Rule):
    """The first of several rules that takes the value."""

    rules: tuple[Rule, ...]

    @property
    def text(self) -> str:
        return " or ".join(r.text for r in self.rules)

    def _first(self, read, value):
        for rule in self.rules:
            try:
                return rule, read(rule, value)
            except Invalid:
                pass
        raise Invalid(self.text, value)

    def parse(self, value):
        return self._first(lambda r, v: r.parse(v), value)[1]

    def from_text(self, text: str):
        return self._first(lambda r, v: r.from_text(v), text)[1]

    def dump(self, value):
        return self._first(lambda r, v: r.parse(v), value)[0].dump(value)


@dataclasses.dataclass(frozen=True)
class Text(Rule):
    text = "a string"
    metavar = "TEXT"

    def parse(self, value):
        if not isinstance(value, str):
            raise Invalid(self.text, value)
        return value

    def from_text(self, text: str):
        return text


@dataclasses.dataclass(frozen=True)
class Numbers(Rule):
    """One number or a list of numbers, each taken by `each`; on the command line one number
    or several separated by commas. A list is read as a tuple of floats."""

    each: Number = Number()

    @property
    def text(self) -> str:
        return f"{self.each.text.replace('a finite number', 'one finite number')} or a list of them"

    metavar = "X[,X...]"
    hint = "on the command line one number or several separated by commas, e.g. 0.01,0,0.02"

    def parse(self, value):
        if isinstance(value, np.ndarray) and value.ndim <= 1:
            value = value.tolist()
        try:
            if isinstance(value, list | tuple):
                return tuple(self.each.parse(v) for v in value)
            return self.each.parse(value)
        except Invalid:
            raise Invalid(self.text, value) from None

    def from_text(self, text: str):
        parts = text.split(",")
        try:
            values = [self.each.from_text(p) for p in parts]
        except Invalid:
            raise Invalid(self.text + ", separated by commas", text) from None
        return values[0] if len(parts) == 1 else tuple(values)


@dataclasses.dataclass(frozen=True)
class Strings(Rule):
    """A list of strings (e.g. parameter paths); on the command line separated by commas."""

    text = "a list of strings"
    metavar = "A[,B...]"

    def parse(self, value):
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise Invalid(self.text, value)
        return tuple(value)

    def from_text(self, text: str):
        return tuple(p.strip() for p in text.split(",") if p.strip())


@dataclasses.dataclass(frozen=True)
class Custom(Rule):
    """A rule of a caller's own functions: `read(value, field)` raises ConfigError itself
    (tables of ranges, waveforms); `write(value)` gives it back as plain data."""

    read: Callable[[Any, str], Any]
    text: str = "a value"
    write: Callable[[Any], Any] | None = None
    metavar: str = "VALUE"

    def parse(self, value):
        return value  # `read` runs in `parse_field`, where the field's name is known

    def dump(self, value):
        return self.write(value) if self.write is not None else value


def _literal(text: str):
    """Command-line text as the value TOML would give: true/false, an int, a float, else the
    text itself."""
    t = text.strip()
    if t in ("true", "false"):
        return t == "true"
    for kind in (int, float):
        try:
            return kind(t)
        except ValueError:
            pass
    return text


__all__ = ["AtLeast", "Choice", "Custom", "Either", "Invalid", "Maybe", "Number", "Numbers",
           "Positive", "Rule", "Strings", "Text"]
