"""Strict YAML configs: a file loads into a frozen dataclass, and an unknown or missing key is
an error that names the file and the key (a typo must never pass silently)."""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path

import yaml

from .errors import TorchspecError

__all__ = ["ConfigError", "load_config", "from_mapping", "read_yaml"]


class ConfigError(TorchspecError):
    """A config file that cannot be read into its settings."""


def _convert(value, kind, where: str):
    origin = typing.get_origin(kind)
    args = typing.get_args(kind)
    if dataclasses.is_dataclass(kind):
        return from_mapping(value, kind, where)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(value, inner[0], where) if len(inner) == 1 else value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where} must be a list; got {value!r}.")
        item = args[0] if args else typing.Any
        items = [_convert(v, item, f"{where}[{k}]") for k, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number; got {value!r}.")
        return float(value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer; got {value!r}.")
        return value
    if kind is str and not isinstance(value, str):
        raise ConfigError(f"{where} must be a string; got {value!r}.")
    if kind is bool and not isinstance(value, bool):
        raise ConfigError(f"{where} must be true or false; got {value!r}.")
    return value


def from_mapping(data, cls, where: str = "config"):
    """Build the frozen dataclass ``cls`` from a mapping, recursively, rejecting unknown keys.

    Args:
        data: the mapping of keys (the fields of ``cls``) to values.
        cls: a dataclass; a field whose type is a dataclass reads a nested mapping. A class attribute
            ``MOVED`` (a key of an older layout: its place now, ``group.key``) has such a key refused
            with a message naming its place (unless the key is now a group's, given as a mapping).
        where: what ``data`` is (a file, or a file and a key), named by every error.

    Returns:
        ``cls(**data)``, each value converted to its field's type.

    Raises:
        ConfigError: ``data`` is not a mapping, a key is unknown, moved or missing, a value has the wrong type,
            or ``cls`` refuses a value (a ``ValueError`` of its ``__post_init__``); the message names
            ``where`` and the key.

    Example:
        >>> from dataclasses import dataclass
        >>> @dataclass(frozen=True)
        ... class Grid:
        ...     size: int = 8
        ...     step: float = 1.0
        >>> from_mapping({"size": 4}, Grid)
        Grid(size=4, step=1.0)
        >>> from_mapping({"sise": 4}, Grid, "grid.yaml")
        Traceback (most recent call last):
        ...
        torchspec.config.ConfigError: grid.yaml has unknown key(s) ['sise']; known keys are ['size', 'step'].
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a mapping of keys to values; got {type(data).__name__}.")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key, value in data.items():
        place = getattr(cls, "MOVED", {}).get(key)
        if place is not None and (key not in fields or not isinstance(value, dict)):
            group, name = place.split(".", 1)
            raise ConfigError(f"{where}: key {key!r} has moved: write it as {group}: {{{name}: ...}}.")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {unknown}; known keys are {sorted(fields)}.")
    values = {}
    for name, field in fields.items():
        if name in data:
            values[name] = _convert(data[name], hints[name], f"{where}.{name}")
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{where} is missing the key {name!r}.")
    try:
        return cls(**values)
    except ValueError as error:  # a value out of its domain, refused by cls (a TorchspecError is a ValueError)
        raise ConfigError(_name_key(str(error), cls, fields, where)) from error


def _name_key(message: str, cls, fields, where: str) -> str:
    """``message`` of a refused value, said of ``where``: ``Cls.key must ...`` (or a longer path,
    ``Outer.group.key must ...``, whose first key after the class is one of ``fields``) becomes
    ``where: key must ...``."""
    head, _, rest = message.partition(" ")
    parts = head.split(".")
    for k in range(1, len(parts)):
        if parts[k] in fields:
            return f"{where}: {'.'.join(parts[k:])} {rest}"
    return f"{where}: {message}"


def load_config(path: str | Path, cls):
    """Read the YAML file ``path`` into the frozen dataclass ``cls``.

    Raises:
        ConfigError: the file is missing or not YAML, a key is unknown or missing, or a value
            has the wrong type or is refused by ``cls``; the message names the file and the key.
    """
    path = Path(path)
    data = read_yaml(path)
    return from_mapping({} if data is None else data, cls, where=str(path))


def read_yaml(path: str | Path, *, what: str = "config", error: type[Exception] = ConfigError):
    """The YAML (or JSON) document in ``path``; ``error`` names the file (``what``) when it cannot
    be read or parsed."""
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise error(f"cannot read {what} {path}: {exc.strerror or exc}.") from None
    except yaml.YAMLError as exc:
        raise error(f"{what} {path} is not valid YAML: {exc}.") from None
