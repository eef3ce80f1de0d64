"""A config file's tables, read as they are written: TOML (.toml) or JSON (.json), a key given
twice refused with its dotted path (TOML forbids it; JSON's last-one-wins would hide a
mistake), a TOML syntax error named by its line and column. Nothing is interpreted here
(`dscjax.config` lays the tables over a setup); nothing is evaluated as code.
"""

from __future__ import annotations

import ast
import json
import re
import tomllib
from pathlib import Path

from dscjax.validation import ConfigError

SUFFIXES = (".toml", ".json")


def read(path: str | Path, option: str | None = None) -> dict:
    """The tables of a .toml (or .json) file, not yet interpreted; ConfigError if unreadable,
    a directory, of another format, or if it gives a key twice (`duplicate key 'controller.k'
    in FILE`: TOML forbids it, and JSON's last-one-wins would hide a mistake). `option`: how
    the message names where the path came from (e.g. "--config")."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{option + ': ' if option else ''}{str(path)!r} is a directory "
                          f"(give a .toml or .json file)")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ConfigError(f"{path}: configs are TOML (.toml) or JSON (.json) (got "
                          f"{suffix or 'no suffix'!r})")
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"cannot read config file {str(path)!r}: {err.strerror}") from None
    is_json = suffix == ".json"
    try:
        d = (_unique(json.loads(text, object_pairs_hook=_Pairs), path) if is_json
             else tomllib.loads(text))
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        dup = None if is_json else _toml_duplicate(text, str(err))
        if dup is not None:
            raise ConfigError(f"duplicate key {dup!r} in {path}") from None
        if is_json:
            raise ConfigError(f"{path}: not valid JSON: {err}") from None
        raise ConfigError(f"{path}, {_toml_where(text, str(err))}") from None
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: the top level must be a table of sections")
    return d


def _toml_where(text: str, message: str) -> str:
    """A TOML parser's message as "line L, column C: not valid TOML: REASON" (the line of the
    end of the file where the parser ran out of text, e.g. an unclosed array)."""
    # tomllib ends every message so (`tomllib._parser.suffixed_err`)
    found = re.search(r"\s*\(at (?:line (\d+), column (\d+)|end of document)\)$", message)
    reason = message[:found.start()]
    if found[1]:
        return f"line {found[1]}, column {found[2]}: not valid TOML: {reason}"
    last = max(len(text.rstrip("\n").splitlines()), 1)
    return f"line {last} (the end of the file): not valid TOML: {reason} (opened and never closed)"


class _Pairs(list):
    """A JSON object as the (key, value) pairs it was written with (duplicates kept)."""


def _unique(value, path: Path, where: str = ""):
    """A JSON value read with `_Pairs` as dicts, a key given twice a ConfigError naming it."""
    if isinstance(value, _Pairs):
        out = {}
        for key, item in value:
            name = f"{where}.{key}" if where else key
            if key in out:
                raise ConfigError(f"duplicate key {name!r} in {path}")
            out[key] = _unique(item, path, name)
        return out
    if isinstance(value, list):
        return [_unique(item, path, f"{where}[{i}]") for i, item in enumerate(value)]
    return value


def _toml_duplicate(text: str, message: str) -> str | None:
    """The dotted path of the key (or table) a TOMLDecodeError says is given twice, or None
    if the error is of another kind. tomllib's own message names no key for a value."""
    declared = re.match(r"Cannot (?:declare (\(.*\)) twice|redefine namespace (\(.*\))) \(at ",
                        message)
    if declared:  # tomllib writes the key as a tuple of strings (a key may hold parentheses)
        return ".".join(ast.literal_eval(declared[1] or declared[2]))
    value = re.match(r"(Cannot overwrite a value|Duplicate inline table key '(.*)') "
                     r"\((?:at line (\d+)|at end of document)", message)
    if not value:
        return None
    lines = text.splitlines()
    n = (int(value[3]) - 1 if value[3]  # at the end of the document: its last line
         else max((i for i, ln in enumerate(lines) if ln.strip()), default=0))
    table = next((_toml_path(ln.strip()) for ln in reversed(lines[:n])
                  if ln.strip().startswith("[")), [])
    key = _toml_path(lines[n].partition("=")[0] + "= 0") if n < len(lines) else []
    inline = [value.group(2)] if value.group(2) else []
    return ".".join([*table, *key, *inline]) or None


def _toml_path(line: str) -> list[str]:
    """The key path of one TOML header (`[a.b]`, `[[a]]`) or `key = 0` line."""
    try:
        d = tomllib.loads(line)
    except tomllib.TOMLDecodeError:
        return []
    path = []
    while isinstance(d, dict | list) and d:
        if isinstance(d, list):
            d = d[-1]
            continue
        key = next(iter(d))
        path.append(key)
        d = d[key]
    return path
