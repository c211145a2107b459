"""Typed parameters: a flat mapping (a launch file's ``params``, ``--set NAME=VALUE``) checked
against a dataclass's annotated fields and turned into an instance of it.

One rule set for every entry point, so a value that a launch file refuses is refused the same
way by ``olsplat aggregate --set``: a wrong name is refused with the closest known names, a
wrong type with the expected one. Accepted conversions are the lossless ones a YAML author
expects: an int where a float is asked for, a list where a tuple is asked for. Nothing else is
coerced (``"0.3"`` is not a float, ``1`` is not a bool, ``"0.6,0.4"`` is not a list).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import re
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any, Literal, TypeVar, Union

from .errors import ParameterError

T = TypeVar("T")


def field_types(cls: type) -> dict[str, Any]:
    """Name -> resolved annotation of every field of the dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def field_defaults(cls: type) -> dict[str, Any]:
    """Name -> default of every field of the dataclass ``cls`` (fields need defaults)."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
        else:
            raise TypeError(f"{cls.__name__}.{f.name} has no default")
    return out


def check_names(cls: type, names: Sequence[str], where: str, what: str = "parameter") -> None:
    """ParameterError for the first name that is not a field of ``cls``, with suggestions."""
    known = [f.name for f in dataclasses.fields(cls)]
    for name in names:
        if name not in known:
            close = difflib.get_close_matches(name, known, n=3, cutoff=0.6)
            hint = f"did you mean {' or '.join(close)}? " if close else ""
            raise ParameterError(f"{where}: unknown {what} {name!r}; {hint}known: {', '.join(sorted(known))}")


def parse_params(cls: type[T], raw: Mapping[str, Any], where: str) -> T:
    """An instance of the dataclass ``cls`` from ``raw`` (missing fields keep their defaults).
    ``where`` starts every error message (``replay.yaml: nodes[3] (accumulator).params``)."""
    check_names(cls, list(raw), where)
    types_ = field_types(cls)
    values = {name: convert(value, types_[name], f"{where}.{name}") for name, value in raw.items()}
    try:
        return cls(**values)
    except (ValueError, TypeError) as exc:  # the dataclass's own range checks
        raise ParameterError(f"{where}: {exc}") from exc


def convert(value: Any, hint: Any, where: str) -> Any:
    """``value`` as the annotation ``hint`` asks, or ParameterError naming ``where``."""
    ok, converted = _convert(value, hint)
    if not ok:
        raise ParameterError(f"{where}: expected {describe(hint)}, got {value!r}")
    return converted


def describe(hint: Any) -> str:
    """A reader's name of a type annotation (``a number``, ``a list of numbers or null``)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return "any value"
    if origin in (Union, types.UnionType):
        return " or ".join("null" if a is type(None) else describe(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (list, tuple):
        if origin is tuple and args and args[-1] is not Ellipsis:
            return f"a list of {len(args)} {_plural(args[0])}"
        return f"a list of {_plural(args[0]) if args else 'values'}"
    if origin is dict:
        return "a mapping"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(hint, str(hint))


def _plural(hint: Any) -> str:
    return {bool: "booleans", int: "integers", float: "numbers", str: "strings"}.get(hint, describe(hint))


def _convert(value: Any, hint: Any) -> tuple[bool, Any]:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True, value
    if origin in (Union, types.UnionType):
        if value is None:
            return type(None) in args, None
        for arg in args:
            if arg is not type(None):
                ok, converted = _convert(value, arg)
                if ok:
                    return True, converted
        return False, None
    if origin is Literal:
        return value in args, value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            return False, None
        if origin is tuple and args and args[-1] is not Ellipsis:
            item_types = list(args)
            if len(value) != len(item_types):
                return False, None
        else:
            item_types = [args[0] if args else Any] * len(value)
        items = [_convert(v, t) for v, t in zip(value, item_types, strict=True)]
        if not all(ok for ok, _ in items):
            return False, None
        return True, origin(v for _, v in items)
    if origin is dict or hint is dict:
        return isinstance(value, dict), value
    if hint is bool:
        return isinstance(value, bool), value
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        return ok, float(value) if ok else None
    if hint is str:
        return isinstance(value, str), value
    if isinstance(hint, type):
        return isinstance(value, hint), value
    raise TypeError(f"unsupported parameter annotation {hint!r}")


def load_yaml(text: str) -> Any:
    """``yaml.safe_load``, except that a number in exponent form without a point (``1e9``,
    ``2E-3``) is a float, as YAML 1.2 reads it (PyYAML's YAML 1.1 keeps it a string, and a user
    who writes ``--set refiner.fold_limit=1e9`` means a number)."""
    import yaml

    return yaml.load(text, Loader=_yaml_loader())  # a SafeLoader with one more float form: safe


@functools.cache
def _yaml_loader() -> type:
    """``load_yaml``'s loader class, made once (yaml is imported only when a value is read)."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    exponent = re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$")
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", exponent, list("-+0123456789."))
    return Loader


def parse_assignments(items: Sequence[str], where: str) -> dict[str, Any]:
    """``["tau_d=0.3", "beta=[1, 2]"]`` -> ``{"tau_d": 0.3, "beta": [1, 2]}``: each value read as a
    YAML scalar or flow collection (as launch files write it); an empty value is ``""``."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        name, eq, text = item.partition("=")
        if not eq or not name.strip():
            raise ParameterError(f"{where} {item!r}: expected NAME=VALUE")
        try:
            out[name.strip()] = load_yaml(text) if text.strip() else ""
        except yaml.YAMLError as exc:
            raise ParameterError(f"{where} {item!r}: the value is not valid YAML ({exc})") from exc
    return out
