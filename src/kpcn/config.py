"""One configuration system: dataclasses loaded from YAML, with ``--set`` overrides.

Every command (``train``, ``render dataset``, ``report``, ``bench ...``) and
every model describes its settings as a dataclass. This module turns YAML and
command-line assignments into those dataclasses, and checks them on the way:

* an unknown key is an error that names it and the nearest valid key;
* a value of the wrong type is an error that names the key, the expected type
  and the value (YAML 1.1 reads ``3e-3`` as a string: numbers given that way
  are converted, anything else is refused);
* errors are :class:`ConfigError` (a ``ValueError``) with one clear line.

Usage::

    cfg = load_config(RunConfig, "configs/small.yaml", ["train.lr=3e-4"])
    save_config(cfg, run_dir / "config.yaml")       # the resolved config, beside the results

    p = argparse.ArgumentParser(); add_config_args(p)
    cfg = config_from_args(ReportConfig, p.parse_args())  # --config FILE --set a.b=v

A dataclass field may be annotated with another dataclass (a section), a
scalar (``int``, ``float``, ``str``, ``bool``), ``X | None``, ``list[X]``,
``tuple[X, ...]``/``tuple[X, Y]``, ``dict`` (free-form, checked by whoever
uses it: e.g. a model's parameters are checked against the model's own config
dataclass) or ``Any``.
"""
from __future__ import annotations

import argparse
import dataclasses
import difflib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

__all__ = [
    "ConfigError",
    "from_dict",
    "to_dict",
    "apply_override",
    "set_value",
    "load_config",
    "save_config",
    "add_config_args",
    "config_from_args",
    "config_parser",
    "parse_config",
]

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value or key is wrong; the message names it."""


def _nearest(key: str, valid) -> str:
    valid = sorted(valid)
    near = difflib.get_close_matches(key, valid, n=1, cutoff=0.0)
    hint = f"; did you mean {near[0]!r}?" if near else ""
    return f"{hint} valid keys: {', '.join(valid)}"


def unknown_key_error(where: str, key: str, valid) -> ConfigError:
    """The error for ``key`` not among ``valid`` (names the nearest valid key)."""
    return ConfigError(f"{where}{key}: unknown key{_nearest(key, valid)}")


def _hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _type_name(tp) -> str:
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


def _coerce(value, tp, where: str):
    """``value`` checked against (and converted to) the annotation ``tp``."""
    if tp is Any or tp is object:
        return value
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if value is None:
            return tp()
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping of {tp.__name__} fields, got {value!r}")
        return from_dict(tp, value, where)
    if origin in (list, tuple) or tp in (list, tuple):
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)} ({value!r})")
            return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        item = args[0] if args else Any
        items = [_coerce(v, item, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if (origin is tuple or tp is tuple) else items
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, Path):
            return str(value)
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    if isinstance(tp, type) and isinstance(value, tp):
        return value
    raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")


def _prefix(where: str) -> str:
    return f"{where}." if where else ""


def from_dict(cls: type[T], data: dict | None, where: str = "") -> T:
    """Build the dataclass ``cls`` from a (YAML) mapping, checking keys and types.

    ``where`` prefixes error messages (a file name or a section path).
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where or cls.__name__}: expected a mapping, got {data!r}")
    hints = _hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init]
    kwargs = {}
    for key, value in data.items():
        if key not in names:
            raise unknown_key_error(_prefix(where), str(key), names)
        kwargs[key] = _coerce(value, hints[key], f"{_prefix(where)}{key}")
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where or cls.__name__}: {exc}") from None


def to_dict(obj) -> dict:
    """A dataclass as plain YAML-able data (tuples become lists)."""

    def plain(v):
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        if isinstance(v, Path):
            return str(v)
        return v

    return plain(obj)


def apply_override(cfg: T, assignment: str, where: str = "--set") -> T:
    """Apply ``a.b.c=value`` (value parsed as YAML) to a copy of ``cfg`` and return it.

    The whole config is rebuilt through :func:`from_dict`, so an override is
    checked exactly like a key of a YAML file.
    """
    if "=" not in assignment:
        raise ConfigError(f"{where} {assignment!r}: expected KEY=VALUE (e.g. train.lr=3e-4)")
    key, raw = assignment.split("=", 1)
    key = key.strip()
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{where} {key}: cannot parse {raw!r} ({exc.__class__.__name__})") from None
    return set_value(cfg, key, value, where)


def set_value(cfg: T, key: str, value, where: str = "--set") -> T:
    """A copy of ``cfg`` with the dotted ``key`` set to ``value`` (checked as a YAML key would be)."""
    data = to_dict(cfg)
    node: Any = data
    parts = key.split(".")
    cls: Any = type(cfg)
    for i, part in enumerate(parts[:-1]):
        here = ".".join(parts[: i + 1])
        if cls is not None and dataclasses.is_dataclass(cls):
            hints = _hints(cls)
            if part not in hints:
                raise unknown_key_error(_prefix(".".join(parts[:i])), part, [f.name for f in dataclasses.fields(cls)])
            cls = _section_type(hints[part])
        if not isinstance(node.get(part), dict):
            if node.get(part) is None and cls is not None:
                node[part] = {}
            else:
                raise ConfigError(f"{where} {key}: {here} is not a section")
        node = node[part]
    last = parts[-1]
    if cls is not None and dataclasses.is_dataclass(cls):
        valid = [f.name for f in dataclasses.fields(cls)]
        if last not in valid:
            raise unknown_key_error(_prefix(".".join(parts[:-1])), last, valid)
    node[last] = value
    return from_dict(type(cfg), data)


def _section_type(tp):
    """The dataclass inside an annotation (``X`` or ``X | None``), or None for free-form mappings."""
    if dataclasses.is_dataclass(tp):
        return tp
    for a in typing.get_args(tp):
        if dataclasses.is_dataclass(a):
            return a
    return None


def load_config(cls: type[T], path: str | Path | None = None, overrides=(), defaults: dict | None = None) -> T:
    """Read ``path`` (YAML; None: the dataclass defaults) into ``cls`` and apply ``overrides``.

    ``defaults`` are applied before the file (e.g. a run name taken from the file name).
    Errors name the file and the key.
    """
    data: dict = dict(defaults or {})
    where = ""
    if path is not None:
        p = Path(path)
        where = str(p)
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        try:
            loaded = yaml.safe_load(p.read_text())
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            at = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
            raise ConfigError(f"{p}: not valid YAML{at}: {getattr(exc, 'problem', exc)}") from None
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise ConfigError(f"{p}: expected a mapping at the top level, got {type(loaded).__name__}")
        data.update(loaded)
    try:
        cfg = from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}" if where else str(exc)) from None
    for o in overrides or ():
        cfg = apply_override(cfg, o)
    return cfg


def save_config(cfg, path: str | Path) -> None:
    """Write the resolved config as YAML, atomically."""
    from .io import atomic_write

    text = yaml.safe_dump(to_dict(cfg), sort_keys=False)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def add_config_args(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add ``--config FILE`` and repeatable ``--set KEY=VALUE`` to a parser."""
    p.add_argument("--config", "-c", help="YAML config file (see configs/)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config key, e.g. train.lr=3e-4 or spp=[2,4] (value parsed as YAML); may be repeated")
    return p


def config_from_args(cls: type[T], args: argparse.Namespace, flags: dict | None = None, defaults: dict | None = None) -> T:
    """``cls`` from ``--config`` and ``--set``, then ``flags`` (key -> value, None values ignored).

    Command-specific flags (``--spp 2 4 8``) are overrides like ``--set``: they
    are applied last and checked the same way.
    """
    cfg = load_config(cls, getattr(args, "config", None), getattr(args, "overrides", ()), defaults)
    for key, value in (flags or {}).items():
        if value is None:
            continue
        cfg = set_value(cfg, key, to_dict(value), where="option")
    return cfg


def _flag_kwargs(f: dataclasses.Field, tp) -> dict:
    """argparse keyword arguments for the field ``f`` of annotation ``tp`` (defaults stay in the dataclass)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        tp = inner[0] if len(inner) == 1 else str
        origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is bool:
        return {"action": "store_const", "const": not f.default}
    if origin in (list, tuple):
        item = args[0] if args else str
        nargs = len(args) if origin is tuple and args and args[-1] is not Ellipsis else "+"
        return {"nargs": nargs, "type": item if item in (int, float, str) else str}
    return {"type": tp if tp in (int, float, str) else str}


def _default_text(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        v = f.default
    elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        v = f.default_factory()  # type: ignore[misc]
    else:
        return ""
    if v is None:
        return ""
    if isinstance(v, (list, tuple)):
        v = " ".join(str(x) for x in v)
    return f" (default: {v})"


def config_parser(cls, prog: str, description: str = "") -> argparse.ArgumentParser:
    """A parser with ``--config``, ``--set`` and one flag per field of the dataclass ``cls``.

    ``field_name`` becomes ``--field-name`` (a boolean that defaults to true
    becomes ``--no-field-name``); the help text is the field's ``metadata["help"]``.
    Flags left out keep the value from the file, ``--set`` or the dataclass.
    """
    p = argparse.ArgumentParser(prog=prog, description=description)
    add_config_args(p)
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        kw = _flag_kwargs(f, hints[f.name])
        flag = f.name.replace("_", "-")
        if kw.get("action") == "store_const" and kw["const"] is False:
            flag = f"no-{flag}"
        help_text = f.metadata.get("help", "")
        if kw.get("action") != "store_const":
            help_text += _default_text(f)
        p.add_argument(f"--{flag}", dest=f.name, default=None, help=help_text, **kw)
    return p


def parse_config(cls: type[T], argv, prog: str, description: str = "") -> T:
    """``cls`` from a command line built by :func:`config_parser`; a bad value exits with one line (code 2)."""
    p = config_parser(cls, prog, description)
    args = p.parse_args(argv)
    try:
        return config_from_args(cls, args, {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)})
    except ConfigError as exc:
        p.exit(2, f"{prog}: {exc}\n")
