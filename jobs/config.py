"""The one configuration layer: TOML tables validated by pydantic into typed specs, errors that name file,
key and allowed values.

A table's keys are the dataclass's field names.  Angles may be given at the edge in friendlier units:
a key ``<name>_arcsec`` or ``<name>_deg`` fills the field ``<name>_rad`` (converted), so configs read
``tolerance_arcsec = 20`` while the code keeps SI radians inside.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import typing
from pathlib import Path

import pydantic

from dualsight.errors import ConfigError, InputError

_ARCSEC = math.pi / (180 * 3600)
_UNIT_SUFFIX = {"_arcsec": _ARCSEC, "_deg": math.pi / 180}


MAX_DEPTH = 12
"""Deepest nesting a configuration may have (tables and arrays); deeper input is refused, not recursed into."""


def plain_tree(value, *, source: str, field: str = "", depth: int = 0):
    """Check that a TOML/JSON value holds only tables, arrays, strings, booleans and finite numbers,
    nested at most :data:`MAX_DEPTH` deep (iteratively bounded), and return it unchanged."""
    if depth > MAX_DEPTH:
        raise ConfigError(f"is nested more than {MAX_DEPTH} levels deep", source=source, field=field or None)
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise ConfigError(f"key {k!r} is not a string", source=source, field=field or None)
            plain_tree(v, source=source, field=f"{field}.{k}" if field else k, depth=depth + 1)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            plain_tree(v, source=source, field=f"{field}[{i}]", depth=depth + 1)
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise ConfigError(f"must be a finite number, got {value!r}", source=source, field=field or None)
    elif not (value is None or isinstance(value, (str, bool, int))):
        raise ConfigError(f"must be a table, array, string, boolean or number, got {type(value).__name__} "
                          f"{value!r}", source=source, field=field or None)
    return value


@functools.lru_cache(maxsize=None)
def _adapter(tp) -> pydantic.TypeAdapter:
    return pydantic.TypeAdapter(tp)


def validate(tp, raw, *, source: str, section: str | None = None):
    """Validate ``raw`` (TOML/JSON layout) into ``tp`` (a pydantic model or a dataclass) with pydantic in
    strict JSON mode: nested tables become the nested types, arrays become tuples, but "3" is not a number
    and 1.5 is not an integer.  The first problem becomes one ConfigError naming ``source``, the dotted field
    (prefixed by ``section``) and the allowed range or values."""
    plain_tree(raw, source=source, field=section or "")
    try:
        return _adapter(tp).validate_json(json.dumps(raw), strict=True)
    except pydantic.ValidationError as e:
        err = e.errors(include_url=False)[0]
        loc = ".".join(str(x) for x in err["loc"] if x != "__root__")
        fld = ".".join(x for x in (section, loc) if x) or None
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "unexpected_keyword_argument" or err["type"] == "extra_forbidden":
            allowed = _field_names(tp, err["loc"][:-1])
            msg = "unknown key" + (f"; allowed keys: {', '.join(allowed)}" if allowed else "")
            raise ConfigError(msg, source=source, field=fld) from None
        inp = err.get("input")
        got = "" if err["type"] in ("missing", "missing_argument") or isinstance(inp, (dict, list)) \
            else f", got {inp!r}"
        raise ConfigError(f"{msg}{got}", source=source, field=fld) from None


def _field_names(tp, loc) -> list[str]:
    """Friendly key names allowed at ``loc`` inside ``tp`` (for "unknown key" messages)."""
    for part in loc:
        hints = _hints(tp)
        if part not in hints:
            return []
        tp = hints[part]
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if args and (dataclasses.is_dataclass(args[0]) or isinstance(args[0], type)):
            tp = args[0]
    return sorted(_friendly(n) for n in _hints(tp))


def _hints(tp) -> dict:
    if isinstance(tp, type) and issubclass(tp, pydantic.BaseModel):
        return dict(tp.model_fields)
    if dataclasses.is_dataclass(tp):
        return {f.name: f.type for f in dataclasses.fields(tp) if f.init}
    return {}


def check_memory(nbytes: int, *, source: str, what: str = "this spec"):
    """Refuse a spec whose estimated peak memory per worker exceeds half the machine's RAM (or
    ``$DUALSIGHT_MAX_MEMORY_GB``), before anything is allocated."""
    import os

    limit_gb = os.environ.get("DUALSIGHT_MAX_MEMORY_GB")
    try:
        limit = float(limit_gb) * 2**30 if limit_gb else 0.5 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        limit = 8 * 2**30
    if nbytes > limit:
        raise ConfigError(f"{what} needs about {nbytes / 2**30:.1f} GiB per worker (frames x batch, star and pair "
                          f"catalogs), over the {limit / 2**30:.1f} GiB allowed; lower batch_size, the magnitude "
                          "limit or the field of view (or set DUALSIGHT_MAX_MEMORY_GB)", source=source)


def dataclass_from_table(cls, table: dict | None, *, source: str, section: str, base=None):
    """Build frozen dataclass ``cls`` from a TOML table through :func:`validate` (pydantic, strict).

    ``base``: an instance whose values replace the class defaults (e.g. a named method's settings).
    Keys ``<name>_arcsec`` / ``<name>_deg`` fill the field ``<name>_rad`` (converted to radians).
    """
    if table is not None and not isinstance(table, dict):
        raise ConfigError("must be a table", source=source, field=section)
    fields = {f.name for f in dataclasses.fields(cls) if f.init}
    merged = dataclass_to_table(base) if base is not None else {}
    for key, value in (table or {}).items():
        name, scale = key, 1.0
        if key not in fields:
            for suffix, factor in _UNIT_SUFFIX.items():
                if key.endswith(suffix) and key[: -len(suffix)] + "_rad" in fields:
                    name, scale = key[: -len(suffix)] + "_rad", factor
                    break
        if name not in fields:
            raise ConfigError(f"unknown key; allowed keys: {', '.join(sorted(_friendly(n) for n in fields))}",
                              source=source, field=f"{section}.{key}")
        if scale != 1.0:
            if not _is_number(value):
                raise ConfigError(f"must be a number, got {value!r}", source=source, field=f"{section}.{key}")
            value = value * scale
        merged[name] = value
    return validate(cls, merged, source=source, section=section)


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


__all__ = ["dataclass_from_table", "dataclass_to_table", "check_range", "ConfigError", "InputError"]
