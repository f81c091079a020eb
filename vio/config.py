"""Strict YAML -> dataclass loading, shared by every component's config.

Each component owns a frozen dataclass of its parameters; there is no global
parameter object. ``from_dict`` builds one from a mapping and rejects unknown
keys and wrong types with a ``ConfigError`` naming the source and the key path.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from vio.errors import ConfigError

T = TypeVar("T")


def read_yaml(path: str | Path) -> Any:
    """Load a YAML file; tolerates the OpenCV ``%YAML:1.0`` directive EuRoC uses."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror})") from None
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML"):
        lines = lines[1:]  # PyYAML rejects the OpenCV-style directive
    try:
        return yaml.safe_load("\n".join(lines))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1 + (len(text.splitlines()) - len(lines))}" if mark else ""
        raise ConfigError(f"{path}{line}: invalid YAML ({getattr(exc, 'problem', exc)})") from None


def _convert(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
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
                return _convert(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"{where}: {value!r} is not one of {typing.get_args(tp)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} items, got {len(value)}")
            return tuple(_convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        inner = args[0] if args else Any
        items = [_convert(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0 (a clear usage error otherwise)."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (x > 0 and x < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return x


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (a clear usage error otherwise)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {n}")
    return n


def check_ranges(obj: Any, positive: tuple[str, ...] = (), fractions: tuple[str, ...] = (),
                 signed: tuple[str, ...] = ()) -> None:
    """Raise ``ValueError`` naming ``Class.field`` unless every numeric field of the
    dataclass ``obj`` is a number >= 0 (infinity allowed, NaN not; None skipped; ``signed``
    fields may be negative), the ``positive`` ones > 0 and the ``fractions`` in [0, 1]:
    a negative window or a zero sigma fails here, not as a solver error mid-run."""
    name = type(obj).__name__
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        if v != v:
            raise ValueError(f"{name}.{f.name} must be a number, got {v!r}")
        if f.name in positive and not v > 0:
            raise ValueError(f"{name}.{f.name} must be > 0, got {v!r}")
        if f.name in fractions and not 0 <= v <= 1:
            raise ValueError(f"{name}.{f.name} must be in [0, 1], got {v!r}")
        if f.name not in signed and v < 0:
            raise ValueError(f"{name}.{f.name} must be >= 0, got {v!r}")


def from_dict(cls: type[T], data: Any, where: str = "config") -> T:
    """Build dataclass ``cls`` from a mapping; unknown keys are an error.

    Missing keys take the dataclass defaults; nested dataclasses recurse.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping for {cls.__name__}, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown} for {cls.__name__}; "
                          f"valid keys: {sorted(fields)}")
    kwargs = {k: _convert(v, hints[k], f"{where}.{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def load(cls: type[T], path: str | Path, section: str | None = None) -> T:
    """Load ``cls`` from a YAML file (optionally from one top-level ``section``)."""
    data = read_yaml(path)
    if section is not None:
        data = (data or {}).get(section)
    return from_dict(cls, data, f"{path}" + (f":{section}" if section else ""))


def to_dict(obj: Any) -> dict:
    """Dataclass -> plain dict (tuples become lists), for writing YAML."""
    def plain(v: Any) -> Any:
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v
    return {k: (to_dict(v) if dataclasses.is_dataclass(v) else plain(v))
            for k, v in dataclasses.asdict(obj).items()}
