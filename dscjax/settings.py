"""Each setting declared once: its default, meaning, rule and command-line option on its field.

    @dataclasses.dataclass(frozen=True)
    class Optimizer:
        time_limit: float | None = setting(100.0, "wall seconds, compilation included",
                                           Maybe(Number(gt=0)), flag="--time-limit")

A rule (`dscjax.rules`) reads, checks, writes and describes the value. Four readers of that
metadata replace parallel tables: `from_table` (a config table: unknown
keys, parse, check; errors name the config path), `to_table` (plain data for the TOML writer,
`"none"` for None, a strategy by its name), `add_arguments` and `given` (argparse options whose
errors name the option typed) and `doc_rows` (the docs' key tables). A rule parses a value read
from TOML or JSON and the text typed on the command line alike, so "none" means the same in both.
Cross-field rules stay in a group's own `validate(prefix)`.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

from dscjax.markdown import escape, table
from dscjax.rules import Choice, Custom, Invalid, Maybe, Rule
from dscjax.validation import by_rule, known_keys


@dataclasses.dataclass(frozen=True)
class Setting:
    """What a person must know about one setting."""

    doc: str
    rule: Rule
    flag: str | None = None  # its command-line option, e.g. "--time-limit"


def setting(default, doc: str, rule: Rule, *, flag: str | None = None,
            factory: Callable[[], Any] | None = None):
    """A dataclass field declared with its `Setting`."""
    given = {"default": default} if factory is None else {"default_factory": factory}
    return dataclasses.field(**given, metadata={"setting": Setting(doc, rule, flag)})


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
    occurrence's (`group`), else the class's. `obj` may be a class: its defaults."""
    obj = obj() if isinstance(obj, type) else obj
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
    return by_rule(s.rule, value, field)


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
    keys, subs = declared(cls), groups(cls)
    known_keys(table, field_name, [*keys, *subs, *skip])
    obj = base if base is not None else cls()
    changes = {k: parse_field(keys[k], v, prefix + k) for k, v in table.items() if k in keys}
    changes |= {k: from_table(subs[k], v, f"{prefix}{k}.", getattr(obj, k))
                for k, v in table.items() if k in subs}
    obj = dataclasses.replace(obj, **changes)
    # a group's cross-field check, unless `validate` is one of its settings (identify's)
    if "validate" not in keys and hasattr(obj, "validate"):
        obj.validate(field_name)
    return obj


def to_table(obj) -> dict[str, Any]:
    """A group as plain data (each value as its rule writes it, nested groups as tables)."""
    out = {k: s.rule.dump(getattr(obj, k)) for k, s in declared(type(obj)).items()}
    out |= {k: to_table(getattr(obj, k)) for k in groups(type(obj))}
    return out


def plain(obj) -> dict[str, Any]:
    """`dataclasses.asdict` of a group with each strategy by its name, as files write it (what
    a fingerprint hashes)."""
    return dataclasses.asdict(obj) | {k: s.rule.dump(getattr(obj, k))
                                      for k, s in declared(type(obj)).items()
                                      if isinstance(s.rule, Choice)}


def shown(s: Setting, value) -> str:
    """A value as a person reads it in a help text or a docs table."""
    v = s.rule.dump(value)
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v) + "]"
    return str(v)


def _options(obj, prefix: str, keys):
    """(path, key, Setting, value, option) of the settings with an option: every one of the
    group and its nested groups that declares one, or with `keys` those keys of the group
    itself (by their option or --key-with-dashes)."""
    for path, key, s, value, flag in walk(obj, prefix):
        if keys is not None and (path != prefix + key or key not in keys):
            continue
        flag = flag or ("--" + key.replace("_", "-") if keys is not None else None)
        if flag is not None:
            yield path, key, s, value, flag


def add_arguments(parser, obj, prefix: str, *, keys: tuple[str, ...] | None = None,
                  defaults: Mapping[str, Any] | None = None) -> None:
    """An argparse option for each setting of the group `obj` (an instance or a class: its
    defaults) that has one (`_options`). Its value is parsed by the setting's rule, a refusal
    names the option ("argument --time-limit: must be ..."); its help gives the default
    (`defaults` may give a command's own) and the config path."""
    for path, key, s, value, flag in _options(obj, prefix, keys):
        default = (defaults or {}).get(key, value)
        allowed = "" if isinstance(s.rule, Choice) else f"; {s.rule.text}"  # (the metavar)
        allowed += f"; {s.rule.hint}" if s.rule.hint else ""
        text = f"{s.doc} (default {shown(s, default)}, or the config's {path}){allowed}"
        parser.add_argument(flag, dest=dest(flag), type=argtype(s.rule), metavar=s.rule.metavar,
                            help=text.replace("%", "%%"))


def dest(flag: str) -> str:
    """The argparse attribute of an option: --time-limit -> time_limit."""
    return flag.lstrip("-").replace("-", "_")


def given(args, obj, prefix: str) -> tuple[dict[str, Any], dict[str, str]]:
    """(table, names): the options of `add_arguments(obj, prefix)` given on the
    command line, as a table for `from_table` (nested groups as sub-tables; "none" typed as
    None), and {config path: option typed} for `cli.common.blame_options`."""
    table: dict[str, Any] = {}
    names: dict[str, str] = {}
    for path, key, _, _, flag in _options(obj, prefix, None):
        value = getattr(args, dest(flag), None)
        if value is not None:
            where = table
            for part in path[len(prefix):].split(".")[:-1]:
                where = where.setdefault(part, {})
            where[key], names[path] = (None if value is NONE else value), flag
    return table, names


NONE = object()  # an option typed as "none": given, unlike one left out (None in argparse)


def argtype(rule: Rule):
    """An argparse type reading an option's text by `rule`; a refusal: "must be ... (got
    TEXT)"."""

    def parse(text: str):
        try:
            value = rule.from_text(text)
        except Invalid as err:
            raise argparse.ArgumentTypeError(f"must be {err.must} (got {text!r})") from None
        return NONE if value is None else value

    parse.__name__ = rule.metavar  # argparse names the type in some messages
    return parse


def meanings(obj, prefix: str) -> dict[str, str]:
    """{config path: meaning} of a group's settings (the comments of a printed config)."""
    return {path: s.doc for path, _, s, _, _ in walk(obj, prefix)}


def doc_rows(obj, prefix: str) -> list[str]:
    """The docs' table of a group (an instance or a class: its defaults) and its nested
    groups: key, default, allowed values, meaning, option (markdown rows, with the header)."""
    return table(("key", "default", "allowed", "meaning", "option"),
                 [(f"`{path}`", f"`{shown(s, value)}`", escape(s.rule.text), escape(s.doc),
                   f"`{flag}`" if flag else "") for path, _, s, value, flag in walk(obj, prefix)])


__all__ = ["Setting", "add_arguments", "argtype", "checked", "declared", "dest", "doc_rows",
           "from_table", "given", "group", "groups", "meanings", "parse_field", "plain", "setting",
           "shown", "to_table", "walk"]
