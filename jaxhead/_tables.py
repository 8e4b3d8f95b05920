"""TOML tables to frozen dataclasses: types checked, unknown keys named with the closest valid one.

Used by every config that is read from TOML (`jaxhead.run.config` for run configs, the study's
SegmentConfig overrides), so a table is validated the same way wherever it is written.
"""

import collections.abc
import dataclasses
import difflib
import types
import typing
from typing import Any, Literal


def suggest(key: str, valid: list[str]) -> str:
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.5)
    return f" Did you mean `{close[0]}`?" if close else f" Valid keys: {', '.join(sorted(valid))}."


def convert(value: Any, tp: Any, where: str) -> Any:
    """Convert a TOML value to the annotated type (dataclass, tuple, Literal, mapping, scalar)."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise ValueError(f"`{where}` must be a table, got {value!r}.")
        return from_dict(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return convert(value, arg, where)
            except (ValueError, TypeError) as e:
                errors.append(str(e))
        raise ValueError(f"`{where}` = {value!r} does not fit {tp}: {'; '.join(errors)}")
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ValueError(f"`{where}` = {value!r}; choose one of {list(choices)}.")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"`{where}` must be a list, got {value!r}.")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(convert(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ValueError(f"`{where}` needs {len(args)} entries, got {len(value)}.")
        return tuple(convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if origin in (dict, collections.abc.Mapping) or tp in (dict,):
        if not isinstance(value, dict):
            raise ValueError(f"`{where}` must be a table, got {value!r}.")
        kt, vt = (typing.get_args(tp) + (Any, Any))[:2]
        return {convert(k, kt, f"{where} key"): convert(v, vt, f"{where}.{k}") for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"`{where}` must be a number, got {value!r}.")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"`{where}` must be an integer, got {value!r}.")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"`{where}` must be true or false, got {value!r}.")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ValueError(f"`{where}` must be a string, got {value!r}.")
        return value
    if isinstance(tp, type) and hasattr(tp, "parse"):  # e.g. Tissue keys given by name
        return tp.parse(value)
    return value


def fields_from_dict(cls: type, data: dict, where: str = "") -> dict:
    """The keyword arguments of dataclass `cls` that `data` gives, each converted to its annotated
    type; an unknown key raises ValueError naming the table (`where`) and the closest valid key."""
    if not isinstance(data, dict):
        raise ValueError(f"`{where or 'the table'}` must be a table, got {data!r}.")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    kwargs = {}
    for key, value in data.items():
        name = f"{where}.{key}" if where else key
        if key not in fields:
            section = f"[{where}]" if where else "the top level"
            raise ValueError(f"unknown key `{key}` in {section}.{suggest(key, list(fields))}")
        kwargs[key] = convert(value, hints[key], name)
    return kwargs


def from_dict(cls: type, data: dict, where: str = "") -> Any:
    """Build the frozen dataclass `cls` from a dict, rejecting unknown keys with a suggestion."""
    kwargs = fields_from_dict(cls, data, where)
    try:
        return cls(**kwargs)
    except TypeError as e:
        raise ValueError(f"[{where or 'top level'}]: {e}") from None
