"""Typed configuration: dataclasses with their defaults, filled from TOML.

Every default lives once, in a dataclass field. ``param(default, "why")``
attaches a one-line reason that ``defaults_toml`` prints, which is what
``deepxpalm <node> --help`` shows. Unknown keys and wrong types are errors
that name the key, never silently ignored.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

from common.errors import ConfigError

T = TypeVar("T")

log = logging.getLogger(__name__)

#: Keys renamed since configs were written: the old name is still read, with a warning
#: (a session recorded before carries its config under the old names, and replays).
RENAMED_KEYS = {"baud": "baudrate", "control_rate_hz": "palm_step_rate_hz"}


def param(default: Any, doc: str = "", *, secret: bool = False, **kwargs: Any) -> Any:
    """A dataclass field with a default and a one-line reason for it.

    ``secret``: its value is never shown (``--print-config``, recordings'
    metadata), and a config file holding it must not be open to other users.
    """
    metadata = {"doc": doc, "secret": secret}
    if isinstance(default, (list, dict, set)) or dataclasses.is_dataclass(default):
        value = default
        return dataclasses.field(default_factory=lambda: _copy(value), metadata=metadata, **kwargs)
    return dataclasses.field(default=default, metadata=metadata, **kwargs)


def _copy(value: Any) -> Any:
    import copy

    return copy.deepcopy(value)


def load_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML: {e}") from None


def from_dict(cls: type[T], data: Mapping[str, Any] | None, *, where: str = "") -> T:
    """Build dataclass ``cls`` from a mapping, checking names and types."""
    data = {} if data is None else data
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where or cls.__name__} must be a table, not {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    data = _renamed_keys(data, fields, where or cls.__name__)
    unknown = set(data) - set(fields)
    if unknown:
        raise ConfigError(
            f"unknown key(s) {sorted(unknown)} in [{where or cls.__name__}]; "
            f"known keys are {sorted(fields)}"
        )
    kwargs = {}
    for name, value in data.items():
        key = f"{where}.{name}" if where else name
        kwargs[name] = _convert(hints[name], value, key)
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"[{where or cls.__name__}]: {e}") from None
    return obj


def _renamed_keys(
    data: Mapping[str, Any], fields: Mapping[str, Any], where: str
) -> Mapping[str, Any]:
    """``data`` with old key names (``RENAMED_KEYS``) read as their new ones, with a warning."""
    old = [k for k in data if k not in fields and RENAMED_KEYS.get(k) in fields]
    if not old:
        return data
    data = dict(data)
    for key in old:
        new = RENAMED_KEYS[key]
        if new in data:
            raise ConfigError(
                f"[{where}] sets both {key!r} and {new!r}: {key!r} is the old name; keep {new!r}"
            )
        log.warning("[%s] %s is deprecated: call it %s (read as that for now)", where, key, new)
        data[new] = data.pop(key)
    return data


def _convert(tp: Any, value: Any, key: str) -> Any:
    origin = get_origin(tp)
    args = get_args(tp)
    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where=key)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, key)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(f"{key} = {value!r} matches none of {tp}: {'; '.join(errors)}")
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{key} = {value!r} must be one of {list(args)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key} must be an array, not {value!r}")
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            items = [_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value)]
        elif origin is tuple and args:
            if len(value) != len(args):
                raise ConfigError(f"{key} must have {len(args)} items, not {len(value)}")
            items = [
                _convert(a, v, f"{key}[{i}]")
                for i, (a, v) in enumerate(zip(args, value, strict=True))
            ]
        else:
            inner = args[0] if args else Any
            items = [_convert(inner, v, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key} must be a table, not {value!r}")
        inner = args[1] if args else Any
        return {k: _convert(inner, v, f"{key}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, not {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key} must be an integer, not {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key} must be a number, not {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{key} must be finite, not {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key} must be a string, not {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, str):
            raise ConfigError(f"{key} must be a path string, not {value!r}")
        return Path(value)
    raise ConfigError(f"{key}: unsupported config type {tp}")


def to_dict(obj: Any) -> Any:
    """A dataclass as plain TOML-able data (tuples become lists, paths strings)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    if isinstance(obj, Path):
        return str(obj)
    return obj


def defaults_toml(cls: type, section: str = "") -> str:
    """Every default of ``cls`` as commented TOML, nested tables included."""
    return config_toml(cls(), section)


def config_toml(obj: Any, section: str = "", *, redact: bool = True) -> str:
    """A config instance as commented TOML (what --print-config shows).

    ``redact`` (the default): a secret setting that is set shows as a comment
    (loaded back, it is unset: a fresh token), and a URL's ``?token=`` is
    removed, so the text can go to a terminal, a log or a recording. Only
    a config written for a node to run (the demo's robot.toml) needs
    ``redact=False``.
    """
    lines: list[str] = []
    _emit(obj, section, lines, redact)
    return "\n".join(lines).strip() + "\n"


def _emit(obj: Any, section: str, lines: list[str], redact: bool) -> None:
    scalars, tables = [], []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            tables.append((f, value))
        else:
            scalars.append((f, value))
    if section and scalars:
        lines.append(f"\n[{section}]")
    for f, value in scalars:
        doc = f.metadata.get("doc", "")
        if redact and f.metadata.get("secret") and value:
            lines.append(f"# {f.name} = (set; not shown)" + (f"  # {doc}" if doc else ""))
            continue
        rendered = _toml_value(to_dict(value), redact)
        if rendered is None:
            lines.append(f"# {f.name} = (unset)" + (f"  # {doc}" if doc else ""))
        else:
            lines.append(f"{f.name} = {rendered}" + (f"  # {doc}" if doc else ""))
    for f, value in tables:
        _emit(value, f"{section}.{f.name}" if section else f.name, lines, redact)


def secret_values(obj: Any) -> list[tuple[str, str]]:
    """(dotted name, value) of every secret setting set in ``obj``, and of every URL setting
    carrying a ``?token=`` (that value being the token)."""
    from common.web.web_token import from_query

    found: list[tuple[str, str]] = []

    def walk(value: Any, name: str, secret: bool) -> None:
        if dataclasses.is_dataclass(value):
            for f in dataclasses.fields(value):
                walk(
                    getattr(value, f.name),
                    f"{name}.{f.name}" if name else f.name,
                    bool(f.metadata.get("secret")),
                )
        elif isinstance(value, dict):
            for k, v in value.items():
                walk(v, f"{name}.{k}", False)
        elif isinstance(value, (list, tuple)):
            for i, v in enumerate(value):
                walk(v, f"{name}[{i}]", False)
        elif isinstance(value, str) and value:
            if secret:
                found.append((name, value))
            elif "://" in value and (token := from_query(value)):
                found.append((name, token))

    walk(obj, "", False)
    return found


def check_secret_file(path: str | Path, config: Any) -> None:
    """Refuse a config file that holds a secret setting of ``config`` and that other users
    can read; warn when its group can. (A token from the environment or a token_file is
    not in the file, and needs nothing here.)"""
    path = Path(path)
    try:
        text = path.read_text()
        mode = path.stat().st_mode
    except OSError:
        return  # the loader has said why it cannot be read
    held = [name for name, value in secret_values(config) if value in text]
    if not held:
        return
    names = ", ".join(held)
    if mode & 0o007:
        raise ConfigError(
            f"config file {path} holds a secret ({names}) and other users can read it "
            f"(mode {mode & 0o777:o}): chmod 600 {path} (owned by the user the node runs as), "
            "or move the secret out of it (a token_file, or the environment)"
        )
    if mode & 0o070:
        log.warning(
            "config file %s holds a secret (%s) and its group can read it (mode %o): "
            "chmod 600 %s unless every member of the group may steer the robot",
            path,
            names,
            mode & 0o777,
            path,
        )


def _toml_value(v: Any, redact: bool = False) -> str | None:
    if v is None:
        return None
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        if redact and "://" in v and "token=" in v:
            from common.web.web_token import without_token

            v = without_token(v)
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x, redact) or '""' for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x, redact)}" for k, x in v.items()) + " }"
    return repr(v)
