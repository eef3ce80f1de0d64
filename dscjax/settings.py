"""Each setting declared once: its default, meaning, rule and command-line option on its field.

    @dataclasses.dataclass(frozen=True)
    class Optimizer:
        time_limit: float | None = setting(100.0, "wall seconds, compilation included",
                                           Maybe(Number(gt=0)), flag="--time-limit")

Four readers of that metadata replace parallel tables: `from_table` (a config table: unknown
keys, parse, check; errors name the config path), `to_table` (plain data for the TOML writer,
`"none"` for None, a strategy by its name), `add_arguments` and `given` (argparse options whose
errors name the option typed) and `doc_rows` (the docs' key tables). A rule parses a value read
from TOML or JSON and the text typed on the command line alike, so "none" means the same in both.
Cross-field rules stay in a group's own `validate(prefix)`.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from dscjax.validation import ConfigError, got


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

    def parse(self, value):
        return value

    def from_text(self, text: str):
        return self.parse(_literal(text))

    def dump(self, value):
        return value


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
        lo = f"> {self.gt:g}" if self.gt is not None else (
            f">= {self.ge:g}" if self.ge is not None else None)
        hi = f"< {self.lt:g}" if self.lt is not None else (
            f"<= {self.le:g}" if self.le is not None else None)
        if lo and hi:
            left = "(" if self.gt is not None else "["
            right = ")" if self.lt is not None else "]"
            return f"{kind} in {left}{self.gt if self.gt is not None else self.ge:g}, " \
                   f"{self.lt if self.lt is not None else self.le:g}{right}"
        return " ".join(x for x in (kind, lo or hi) if x)

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
        if self.integer and isinstance(value, float) and math.isfinite(value) \
                and value == int(value):
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
        if not isinstance(value, str) or value not in self.options:
            raise Invalid(self.text, value)
        return self.options[value] if isinstance(self.options, Mapping) else value

    def from_text(self, text: str):
        return self.parse(text)

    def dump(self, value):
        if isinstance(self.options, Mapping):
            for name, obj in self.options.items():
                if obj is value or obj == value:
                    return name
            return getattr(value, "name", value)
        return value


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

    def parse(self, value):
        if value is None or (isinstance(value, str) and value.lower() == "none"):
            return None
        try:
            return self.rule.parse(value)
        except Invalid:
            raise Invalid(self.text, value) from None

    def from_text(self, text: str):
        if text.strip().lower() == "none":
            return None
        try:
            return self.rule.from_text(text)
        except Invalid:
            raise Invalid(self.text, text) from None

    def dump(self, value):
        return "none" if value is None else self.rule.dump(value)


@dataclasses.dataclass(frozen=True)
class Either(Rule):
    """The first of several rules that takes the value."""

    rules: tuple[Rule, ...]

    @property
    def text(self) -> str:
        return " or ".join(r.text for r in self.rules)

    def parse(self, value):
        for rule in self.rules:
            try:
                return rule.parse(value)
            except Invalid:
                pass
        raise Invalid(self.text, value)

    def from_text(self, text: str):
        for rule in self.rules:
            try:
                return rule.from_text(text)
            except Invalid:
                pass
        raise Invalid(self.text, text)

    def dump(self, value):
        for rule in self.rules:
            try:
                if rule.parse(value) == value:
                    return rule.dump(value)
            except Invalid:
                pass
        return value


@dataclasses.dataclass(frozen=True)
class Boolean(Rule):
    text = "true or false"
    metavar = "BOOL"

    def parse(self, value):
        if not isinstance(value, bool):
            raise Invalid(self.text, value)
        return value


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
        if isinstance(value, list | tuple):
            try:
                return tuple(self.each.parse(v) for v in value)
            except Invalid:
                raise Invalid(self.text, value) from None
        try:
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

    def dump(self, value):
        return list(value) if isinstance(value, tuple) else value


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

    def dump(self, value):
        return list(value)


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


@dataclasses.dataclass(frozen=True)
class Setting:
    """What a person must know about one setting."""

    doc: str
    rule: Rule
    flag: str | None = None  # its command-line option, e.g. "--time-limit"


def setting(default, doc: str, rule: Rule, *, flag: str | None = None,
            static: bool = False, factory: Callable[[], Any] | None = None):
    """A dataclass (or `eqx.Module`) field declared with its `Setting`."""
    meta: dict[str, Any] = {"setting": Setting(doc, rule, flag)}
    if static:
        meta["static"] = True
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def group(cls: type, factory: Callable[[], Any] | None = None,
          flags: Mapping[str, str | None] | None = None, docs: Mapping[str, str] | None = None):
    """A field holding a nested settings group (a sub-table, e.g. [tuning.optimizer]), built
    by `factory` (default `cls()`); `flags` and `docs` give this occurrence's options and
    meanings where they differ from the class's (a class used at two paths: [tuning.robust]
    and [tuning.heldout])."""
    return dataclasses.field(default_factory=factory or cls, metadata={
        "group": cls, "flags": dict(flags or {}), "docs": dict(docs or {})})


def declared(cls) -> dict[str, Setting]:
    """{key: Setting} of a group's declared fields, in declaration order."""
    return {f.name: f.metadata["setting"] for f in dataclasses.fields(cls)
            if "setting" in f.metadata}


def groups(cls) -> dict[str, type]:
    """{key: class} of a group's nested groups."""
    return {f.name: f.metadata["group"] for f in dataclasses.fields(cls) if "group" in f.metadata}


def walk(obj, prefix: str, flags: Mapping[str, str | None] | None = None,
         docs: Mapping[str, str] | None = None):
    """(config path, key, Setting, value, option or None) of every declared setting of a group
    instance and of its nested groups, depth first; an option and a meaning are the
    occurrence's (`group`), else the class's."""
    for key, s in declared(type(obj)).items():
        if docs and key in docs:
            s = dataclasses.replace(s, doc=docs[key])
        yield prefix + key, key, s, getattr(obj, key), (flags or {}).get(key, s.flag)
    for f in dataclasses.fields(obj):
        if "group" in f.metadata:
            yield from walk(getattr(obj, f.name), f"{prefix}{f.name}.", f.metadata["flags"],
                            f.metadata["docs"])


def _custom(rule: Rule) -> Custom | None:
    """The `Custom` rule of `rule` (itself, or under `Maybe`), or None."""
    inner = rule.rule if isinstance(rule, Maybe) else rule
    return inner if isinstance(inner, Custom) else None


def parse_field(s: Setting, value, field: str):
    """One value through its rule; ConfigError "FIELD must be RANGE (got VALUE)"."""
    custom = _custom(s.rule)
    if custom is not None:
        if s.rule is not custom and (value is None or str(value).lower() == "none"):
            return None
        return custom.read(value, field)
    try:
        return s.rule.parse(value)
    except Invalid as err:
        raise ConfigError(f"{field} must be {err.must} ({got(err.value)})") from None


def checked(obj, name: Callable[[str], str]):
    """`obj` (a group built in code, e.g. from keyword arguments) with each declared field
    read again by its rule (a `Custom` one reads file data only: its value is taken as
    built); a refusal names the field `name(key)`."""
    return dataclasses.replace(obj, **{k: parse_field(s, getattr(obj, k), name(k))
                                       for k, s in declared(type(obj)).items()
                                       if _custom(s.rule) is None})


def from_table(cls, table: Mapping[str, Any], prefix: str, base=None, *,
               skip: tuple[str, ...] = ()):
    """The group `cls` from its table laid over `base` (default: its defaults): unknown keys
    refused, each value parsed and checked by its rule, nested groups read recursively, then
    the group's own `validate(prefix)` if it has one. `skip`: keys a caller reads itself."""
    field_name = prefix.rstrip(".")
    if not isinstance(table, Mapping):
        raise ConfigError(f"'{field_name}' must be a table ([{field_name}])")
    keys, subs = declared(cls), groups(cls)
    allowed = [*keys, *subs, *skip]
    for key in table:
        if key not in allowed:
            raise ConfigError(f"unknown key '{prefix}{key}' (allowed: {', '.join(allowed)})")
    obj = base if base is not None else cls()
    changes = {k: parse_field(keys[k], v, prefix + k) for k, v in table.items() if k in keys}
    changes |= {k: from_table(subs[k], v, f"{prefix}{k}.", getattr(obj, k))
                for k, v in table.items() if k in subs}
    obj = dataclasses.replace(obj, **changes)
    check = getattr(obj, "validate", None)
    if check is not None:
        check(field_name)
    return obj


def to_table(obj) -> dict[str, Any]:
    """A group as plain data (each value as its rule writes it, nested groups as tables)."""
    out = {k: s.rule.dump(getattr(obj, k)) for k, s in declared(type(obj)).items()}
    out |= {k: to_table(getattr(obj, k)) for k in groups(type(obj))}
    return out


def shown(s: Setting, value) -> str:
    """A value as a person reads it in a help text or a docs table."""
    v = s.rule.dump(value)
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v) + "]"
    return str(v)


def add_arguments(parser, obj, prefix: str, *, keys: tuple[str, ...] | None = None,
                  defaults: Mapping[str, Any] | None = None) -> None:
    """An option for each setting of the group `obj` (an instance or a class: its defaults)
    and its nested groups that has an option (or, with `keys`, for those keys of `obj`
    itself, by their option or --key-with-dashes). Its value is parsed by the setting's rule,
    a refusal names the option ("argument --time-limit: must be ..."); its help gives the
    default (`defaults` may give a command's own) and the config path."""
    obj = obj() if isinstance(obj, type) else obj
    for path, key, s, value, flag in walk(obj, prefix):
        if keys is not None:
            if path != prefix + key or key not in keys:
                continue
            flag = flag or "--" + key.replace("_", "-")
        elif flag is None:
            continue
        default = (defaults or {}).get(key, value)
        allowed = "" if isinstance(s.rule, Choice) else f"; {s.rule.text}"  # (the metavar)
        allowed += f"; {s.rule.hint}" if s.rule.hint else ""
        text = f"{s.doc} (default {shown(s, default)}, or the config's {path}){allowed}"
        parser.add_argument(flag, dest=dest(flag), type=_argtype(s.rule), metavar=s.rule.metavar,
                            help=text.replace("%", "%%"))


def dest(flag: str) -> str:
    """The argparse attribute of an option: --time-limit -> time_limit."""
    return flag.lstrip("-").replace("-", "_")


def given(args, obj, prefix: str, *, keys: tuple[str, ...] | None = None
          ) -> tuple[dict[str, Any], dict[str, str]]:
    """(table, names): the settings of the group `obj` (as `add_arguments` declared them)
    given on the command line as a table for `from_table` (nested groups as sub-tables), and
    {config path: option typed} for `cli.common.blame_options`. An option typed as "none" is
    given as None."""
    obj = obj() if isinstance(obj, type) else obj
    table: dict[str, Any] = {}
    names: dict[str, str] = {}
    for path, key, _, _, flag in walk(obj, prefix):
        if keys is not None:
            if path != prefix + key or key not in keys:
                continue
            flag = flag or "--" + key.replace("_", "-")
        elif flag is None:
            continue
        value = getattr(args, dest(flag), None)
        if value is None:
            continue
        where = table
        for part in path[len(prefix):].split(".")[:-1]:
            where = where.setdefault(part, {})
        where[key] = unwrap(value)
        names[path] = flag
    return table, names


def _argtype(rule: Rule):
    def parse(text: str):
        try:
            value = rule.from_text(text)
        except Invalid as err:
            raise argparse.ArgumentTypeError(f"must be {err.must} (got {text!r})") from None
        return _Given(value) if value is None else value

    parse.__name__ = rule.metavar  # argparse names the type in some messages
    return parse


class _Given:
    """An option typed as "none": given, unlike an option left out (None in argparse)."""

    def __init__(self, value):
        self.value = value


def unwrap(value):
    """The value of an option parsed by `add_arguments` ("none" typed: None)."""
    return value.value if isinstance(value, _Given) else value


def meanings(obj, prefix: str) -> dict[str, str]:
    """{config path: meaning} of a group's settings (the comments of a printed config)."""
    obj = obj() if isinstance(obj, type) else obj
    return {path: s.doc for path, _, s, _, _ in walk(obj, prefix)}


def doc_rows(obj, prefix: str) -> list[str]:
    """The docs' table of a group (an instance or a class: its defaults) and its nested
    groups: key, default, allowed values, meaning, option (markdown rows, with the header)."""
    obj = obj() if isinstance(obj, type) else obj
    rows = ["| key | default | allowed | meaning | option |", "|---|---|---|---|---|"]
    for path, _, s, value, flag in walk(obj, prefix):
        rows.append(f"| `{path}` | `{shown(s, value)}` | {_md(s.rule.text)} | {_md(s.doc)} | "
                    f"{f'`{flag}`' if flag else ''} |")
    return rows


def _md(text: str) -> str:
    return text.replace("|", "\\|")


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


__all__ = ["AtLeast", "Boolean", "Choice", "Custom", "Either", "Invalid", "Maybe", "Number",
           "Numbers", "Positive", "Rule", "Setting", "Strings", "Text", "add_arguments",
           "checked", "declared", "dest", "doc_rows", "from_table", "given", "group", "groups",
           "meanings", "parse_field", "setting", "shown", "to_table", "unwrap", "walk"]
