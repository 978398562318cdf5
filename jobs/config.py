"""Reading frozen dataclass configs from TOML tables, with errors that name file, key and allowed values.

A table's keys are the dataclass's field names.  Angles may be given at the edge in friendlier units:
a key ``<name>_arcsec`` or ``<name>_deg`` fills the field ``<name>_rad`` (converted), so configs read
``tolerance_arcsec = 20`` while the code keeps SI radians inside.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from pathlib import Path

from dualsight.errors import ConfigError, InputError

_ARCSEC = math.pi / (180 * 3600)
_UNIT_SUFFIX = {"_arcsec": _ARCSEC, "_deg": math.pi / 180}


def dataclass_from_table(cls, table: dict | None, *, source: str, section: str, base=None):
    """Build frozen dataclass ``cls`` from a TOML table, validating key names and value types.

    ``base``: an instance whose values replace the class defaults (e.g. a named method's settings).

    Unknown keys, wrong types and values the dataclass rejects (its ``__post_init__`` raising
    ValueError) become :class:`ConfigError` naming ``source`` and ``section.key``.
    """
    table = dict(table or {})
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for key, value in table.items():
        name, scale = key, 1.0
        if key not in fields:
            for suffix, factor in _UNIT_SUFFIX.items():
                if key.endswith(suffix) and key[: -len(suffix)] + "_rad" in fields:
                    name, scale = key[: -len(suffix)] + "_rad", factor
                    break
        if name not in fields:
            allowed = sorted(_friendly(n) for n in fields)
            raise ConfigError(f"unknown key {key!r}; allowed keys: {', '.join(allowed)}", source=source,
                              field=f"{section}.{key}")
        kwargs[name] = _coerce(value * scale if scale != 1.0 and _is_number(value) else value,
                               hints.get(name), source, f"{section}.{key}")
    try:
        return dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)
    except ConfigError as e:
        fld = e.field or ""
        if not fld.startswith(section + ".") and fld != section:
            fld = f"{section}.{fld}".rstrip(".")
        raise ConfigError(e.detail, source=source, field=fld) from None
    except (ValueError, TypeError) as e:
        raise ConfigError(str(e), source=source, field=section) from None


def dataclass_to_table(obj) -> dict:
    """Plain dict of a (nested) frozen dataclass, suitable for TOML/JSON."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            v = dataclass_to_table(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


def _friendly(name: str) -> str:
    return name[:-4] + "_arcsec|_deg|_rad" if name.endswith("_rad") else name


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _coerce(value, hint, source, field):
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is None:
        return value
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        if value is None and type(None) in args:
            return None
        hint = next((a for a in args if a is not type(None)), hint)
        origin = typing.get_origin(hint)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"must be true or false, got {value!r}", source=source, field=field)
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"must be an integer, got {value!r}", source=source, field=field)
        return value
    if hint is float:
        if not _is_number(value) or not math.isfinite(float(value)):
            raise ConfigError(f"must be a finite number, got {value!r}", source=source, field=field)
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"must be a string, got {value!r}", source=source, field=field)
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"must be a list, got {value!r}", source=source, field=field)
        return tuple(value)
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"must be one of {list(args)}, got {value!r}", source=source, field=field)
        return value
    return value


def check_range(value, lo, hi, field: str, *, lo_open=False, hi_open=False, source: str | None = None):
    """Raise ConfigError unless lo <(=) value <(=) hi."""
    ok = (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        raise ConfigError(f"must be in {lb}{lo}, {hi}{rb}, got {value!r}", source=source, field=field)
    return value


def preset_and_config(presets: dict, preset: str | None, config: Path | str | None,
                      default: str = "paper") -> tuple[dict, str]:
    """The spec layers below the command-line flags: a preset, then a TOML file over it.

    A config file may name its own base with a top-level ``preset = "..."``.  Tables merge key by key
    (recursively); everything else replaces.  Returns (merged dict, source name for error messages).
    """
    from dualsight.scene.camera import read_toml

    name = preset or default
    if name not in presets:
        raise InputError(f"unknown preset {name!r}; known presets: {', '.join(sorted(presets))}", source="--preset")
    d = deep_merge(presets[name], {})
    source = f"preset {name!r}"
    if config is not None:
        user = read_toml(Path(config))
        source = str(config)
        if "preset" in user:
            if user["preset"] not in presets:
                raise ConfigError(f"unknown preset {user['preset']!r}; known: {sorted(presets)}", source=source,
                                  field="preset")
            d = deep_merge(presets[user["preset"]], {})
        d = deep_merge(d, {k: v for k, v in user.items() if k != "preset"})
    return d, source


def deep_merge(base: dict, over: dict) -> dict:
    """A new dict: ``base`` with ``over`` laid on top, tables merged recursively (inputs untouched)."""
    out = {k: (deep_merge(v, {}) if isinstance(v, dict) else v) for k, v in base.items()}
    for k, v in over.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else (
            deep_merge(v, {}) if isinstance(v, dict) else v)
    return out


def source_name(path: Path | str | None, preset: str | None) -> str:
    if path:
        return str(path)
    return f"preset {preset!r}" if preset else "defaults"


__all__ = ["dataclass_from_table", "dataclass_to_table", "check_range", "ConfigError", "InputError"]
