"""One parser for every configuration: dataclasses are the schema.

A configuration is a tree of dataclasses. Each field's annotation is its type, and carries its
choices (``Literal["lm", "lbfgs"]``); range checks live in the class (``__post_init__`` raising
``ValueError`` with the key in its message). Field metadata marks what a person may not set:

- ``fixed``: a constant the code carries in the configuration because the frame rate scales it
  (``slam.config.at_frame_rate``); the metadata says why it is fixed. Not in ``default.yaml``,
  refused from YAML and ``--set``.

:func:`build` makes the tree from a nested mapping, :func:`parse_into` checks a mapping's keys
and types against it, naming the source (a file, ``--set``) and the key in one line: an unknown
key with the closest known one ("did you mean"), a removed key with what replaces it
(``removed``: key -> message), a wrong type or choice with the allowed values.
"""
from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from typing import Any, Literal

from slam.errors import ConfigError

TRUE = ("true", "yes", "on", "1")
FALSE = ("false", "no", "off", "0")


def is_fixed(f: dataclasses.Field) -> bool:
    return "fixed" in f.metadata


def settable_fields(cls_or_obj) -> list[dataclasses.Field]:
    """The fields a person may set (every field but the ``fixed`` ones)."""
    return [f for f in dataclasses.fields(cls_or_obj) if not is_fixed(f)]


def choices_of(typ: Any) -> tuple | None:
    """The allowed values of a ``Literal[...]`` annotation (None for other types)."""
    return typing.get_args(typ) if typing.get_origin(typ) is Literal else None


def coerce(value: Any, typ: Any, key: str, source: str) -> Any:
    """``value`` checked against / converted to the annotation ``typ``; ConfigError naming
    ``key`` and ``source`` otherwise."""
    def bad(expected: str) -> ConfigError:
        return ConfigError(f"{source}: '{key}' must be {expected}, got {value!r}")

    origin = typing.get_origin(typ)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        inner = [a for a in typing.get_args(typ) if a is not type(None)]
        return coerce(value, inner[0], key, source)
    choices = choices_of(typ)
    if choices is not None:
        if isinstance(value, bool) and "yes" in choices:
            value = "yes" if value else "no"        # YAML reads an unquoted yes / no as a boolean
        if value not in choices:
            raise ConfigError(f"{source}: '{key}' must be one of {', '.join(map(str, choices))}, got {value!r}")
        return value
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in TRUE + FALSE:
            return value.lower() in TRUE
        raise bad("true or false")
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise bad("an integer")
        try:
            return int(value)
        except ValueError:
            raise bad("an integer") from None
    if typ is float:
        if isinstance(value, bool):
            raise bad("a number")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise bad("a number") from None
    if typ is str:
        if isinstance(value, (dict, list)):
            raise bad("a string")
        return "" if value is None else str(value)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise bad("a list")
        (inner,) = typing.get_args(typ)[:1] or (Any,)
        return [coerce(v, inner, key, source) if inner is not Any else v for v in value]
    return value


def parse_into(obj: Any, data: Any, source: str, removed: dict[str, str] | None = None, prefix: str = "") -> None:
    """Set the fields of the dataclass tree ``obj`` from the nested mapping ``data``, checking
    each key and value (see the module docstring). Range checks run when the tree is rebuilt
    (:func:`rebuild`)."""
    removed = removed or {}
    where = prefix.rstrip(".") or "top level"
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: '{where}' must be a mapping, got {data!r}")
    hints = typing.get_type_hints(type(obj))
    fields = {f.name: f for f in dataclasses.fields(obj)}
    for key, value in data.items():
        full = f"{prefix}{key}"
        if full in removed:
            raise ConfigError(f"{source}: '{full}' {removed[full]}")
        f = fields.get(key)
        if f is None:
            names = [x.name for x in settable_fields(obj)]
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f" (did you mean '{prefix}{close[0]}'?)" if close else f" (known: {', '.join(names)})"
            raise ConfigError(f"{source}: unknown key '{full}'{hint}")
        if is_fixed(f):
            raise ConfigError(f"{source}: '{full}' is not a setting: {f.metadata['fixed']}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            parse_into(current, value, source, removed, full + ".")
        else:
            setattr(obj, key, coerce(value, hints[key], full, source))


def rebuild(obj: Any) -> Any:
    """The tree ``obj`` constructed again from its values, so that every class's range checks
    (``__post_init__``) run on the final values; ConfigError (one line) where one fails."""
    values = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        values[f.name] = rebuild(v) if dataclasses.is_dataclass(v) else v
    init = {k: v for k, v in values.items() if next(f for f in dataclasses.fields(obj) if f.name == k).init}
    try:
        out = type(obj)(**init)
    except ValueError as err:
        raise ConfigError(f"config: {err}") from None
    for f in dataclasses.fields(obj):
        if not f.init:
            setattr(out, f.name, values[f.name])
    return out


def user_dict(obj: Any, skip: tuple[str, ...] = ()) -> dict:
    """The settable values of the tree as a nested dict (what ``default.yaml`` lists and a run's
    ``config.yaml`` records), without the ``fixed`` fields and the top-level sections in ``skip``."""
    out = {}
    for f in settable_fields(obj):
        if f.name in skip:
            continue
        v = getattr(obj, f.name)
        out[f.name] = user_dict(v) if dataclasses.is_dataclass(v) else (list(v) if isinstance(v, tuple) else v)
    return out


def count_keys(tree: dict) -> int:
    """The leaf keys of a nested dict."""
    return sum(count_keys(v) if isinstance(v, dict) else 1 for v in tree.values())
