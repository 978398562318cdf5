"""Field checks of the frozen config dataclasses, declared once in their types.

A config dataclass states each field's allowed values in its annotation, e.g.
``psf_sigma_px: Annotated[float, Field(ge=0.05, le=50)] = 0.8`` or ``connectivity: Literal[4, 8] = 8``.
Two paths read those annotations and nothing else:

* a TOML/JSON table goes through :func:`validate` (pydantic ``TypeAdapter`` over the
  dataclass, strict JSON mode), which names the file and the dotted key;
* a dataclass built directly in Python calls :func:`check_fields` from its ``__post_init__``, which
  validates every field value against its own annotation with pydantic (strict; numpy scalars count as
  the Python numbers they hold) and raises one line naming the field, the value and the allowed range.

``__post_init__`` keeps by hand only the rules that tie several fields together.

It also holds :func:`validate` (a TOML/JSON table into a typed spec, strict, one-line errors naming the
file and key), :func:`plain_tree` (depth and value checks before pydantic sees a table), the table <-> dataclass
helpers (:func:`dataclass_from_table`, :func:`dataclass_to_table`: a table's keys are the dataclass's field
names, and an angle field ``<name>_rad`` may be written ``<name>_arcsec`` or ``<name>_deg``) and
:func:`check_range`.  It is the one configuration layer: this module imports pydantic and numpy only, so that
every package validates its configs the same way: the kernels, scene, catalogs, nav and jobs, whose config
dataclasses live beside the stages that read them (``kernels/sensor_config.py``, ``nav/voting_config.py``,
``nav/tracking_config.py``, ``nav/relative_filter.FilterConfig``, ``scene/target_config.py``,
``scene/environment_config.py``, a job kind's tables in its spec module).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import re
import types
import typing

import numpy as np
import pydantic

from dualsight.errors import ConfigError

__all__ = ["check_fields", "allowed_range", "validate", "plain_tree", "printable_key", "friendly_key", "MAX_DEPTH",
           "ANGLE_KEY_SUFFIXES", "dataclass_from_table", "dataclass_to_table", "check_range"]


@functools.lru_cache(maxsize=None)
def _field_adapters(cls) -> tuple:
    """((name, annotation, TypeAdapter), ...) for the init fields of dataclass ``cls``."""
    hints = typing.get_type_hints(cls, include_extras=True)
    return tuple((f.name, hints[f.name], pydantic.TypeAdapter(hints[f.name]))
                 for f in dataclasses.fields(cls) if f.init)


def _num(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def allowed_range(annotation) -> str:
    """The numeric range an annotation allows, e.g. ``"[0.05, 50]"``, ``"(0, 0.0174533]"`` or ``">= 0"``
    ('' when it states none); ``"None or ..."`` for an optional field."""
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        inner = [allowed_range(a) for a in args if a is not type(None)]
        rng = next((r for r in inner if r), "")
        return (f"None or {rng}" if type(None) in args else rng) if rng else ""
    if typing.get_origin(annotation) is not typing.Annotated:
        return ""
    lo = hi = None
    lo_open = hi_open = False
    for meta in args[1:]:
        for m in getattr(meta, "metadata", [meta]):   # annotated_types.Ge/Gt/Le/Lt from Field(ge=...)
            if getattr(m, "ge", None) is not None:
                lo, lo_open = m.ge, False
            if getattr(m, "gt", None) is not None:
                lo, lo_open = m.gt, True
            if getattr(m, "le", None) is not None:
                hi, hi_open = m.le, False
            if getattr(m, "lt", None) is not None:
                hi, hi_open = m.lt, True
    if lo is not None and hi is not None:
        return f"{'(' if lo_open else '['}{_num(lo)}, {_num(hi)}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {_num(lo)}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {_num(hi)}"
    return allowed_range(args[0])


def _plain(v):
    """numpy scalars (and tuples of them) as the Python values they hold; ``v`` itself when it holds none."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, tuple) and any(isinstance(x, np.generic) for x in v):
        return tuple(_plain(x) for x in v)
    return v


def check_fields(obj, error=None, units: dict | None = None):
    """Validate every field of the dataclass instance ``obj`` against its annotation (pydantic, strict).

    numpy scalars are accepted as the Python numbers they hold and stored as those (so a config stays
    JSON-serialisable); NaN and infinities are refused in every float field.  ``error(field, message)``
    builds the exception to raise (``field`` is the field name, with ``[i]`` for an element of a
    tuple); default: ``ValueError("<Class>.<field>: <message>")``.  The message is pydantic's, the
    allowed range and the value, e.g. ``"Input should be less than or equal to 50 (allowed [0.05, 50]),
    got 80.0"``.  ``units`` maps field names to the unit appended to their range (e.g. ``"px"``).
    """
    for name, annotation, adapter in _field_adapters(type(obj)):
        value = getattr(obj, name)
        plain = _plain(value)
        try:
            bad = _non_finite(plain)
            if bad is not None:
                where, msg = name + bad, "Input should be a finite number"
            else:
                adapter.validate_python(plain, strict=True)
                if plain is not value:
                    object.__setattr__(obj, name, plain)
                continue
        except pydantic.ValidationError as e:
            err = e.errors(include_url=False)[0]
            where = name + "".join(f"[{x}]" if isinstance(x, int) else "" for x in err["loc"])
            msg = err["msg"].removeprefix("Value error, ")
        rng = allowed_range(annotation)
        if rng and units and name in units:
            rng += f" {units[name]}"
        msg = f"{msg}{f' (allowed {rng})' if rng else ''}, got {value!r}"
        if error is None:
            raise ValueError(f"{type(obj).__name__}.{where}: {msg}") from None
        raise error(where, msg) from None


def _non_finite(v) -> str | None:
    """'' if ``v`` is a non-finite float, '[i]' for the first non-finite element of a tuple, else None."""
    if isinstance(v, float) and not math.isfinite(v):
        return ""
    if isinstance(v, tuple):
        for i, x in enumerate(v):
            if isinstance(x, float) and not math.isfinite(x):
                return f"[{i}]"
    return None


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
            k = printable_key(k)
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
        loc = ".".join(printable_key(x) for x in err["loc"] if x != "__root__")
        fld = ".".join(x for x in (section, loc) if x) or None
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "unexpected_keyword_argument" or err["type"] == "extra_forbidden":
            allowed = _field_names(tp, err["loc"][:-1])
            msg = "unknown key" + (f"; allowed keys: {', '.join(allowed)}" if allowed else "")
            raise ConfigError(msg, source=source, field=fld) from None
        inp = err.get("input")
        got = "" if err["type"] in ("missing", "missing_argument") or isinstance(inp, (dict, list)) \
            else f", got {inp!r}"
        rng = allowed_range(_annotation_at(tp, err["loc"])) if err["type"] in _RANGE_ERRORS else ""
        raise ConfigError(f"{msg}{f' (allowed {rng})' if rng else ''}{got}", source=source, field=fld) from None


_RANGE_ERRORS = ("greater_than", "greater_than_equal", "less_than", "less_than_equal")
"""pydantic's error types of a number outside its field's range (the message then states the whole range)."""


def _annotation_at(tp, loc):
    """The annotation (with its ``Annotated`` range) of the field at pydantic error location ``loc`` inside
    ``tp``, following nested tables; None where ``loc`` leads nowhere (a tuple element, an unknown key)."""
    ann = None
    for part in loc:
        if not isinstance(part, str):
            continue                                   # an element of a tuple: its tuple's annotation
        if isinstance(tp, type) and issubclass(tp, pydantic.BaseModel) and part in tp.model_fields:
            f = tp.model_fields[part]
            ann = typing.Annotated[(f.annotation, *f.metadata)] if f.metadata else f.annotation
        elif dataclasses.is_dataclass(tp):
            ann = typing.get_type_hints(tp, include_extras=True).get(part)
        else:
            return None
        inner = [a for a in typing.get_args(typing.get_args(ann)[0] if typing.get_origin(ann) is typing.Annotated
                                            else ann) if a is not type(None)] or [ann]
        tp = next((a for a in inner if isinstance(a, type)), inner[0])
    return ann


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
    return sorted(friendly_key(n) for n in _hints(tp))


def _hints(tp) -> dict:
    if isinstance(tp, type) and issubclass(tp, pydantic.BaseModel):
        return dict(tp.model_fields)
    if dataclasses.is_dataclass(tp):
        return {f.name: f.type for f in dataclasses.fields(tp) if f.init}
    return {}


def friendly_key(name: str) -> str:
    """A field name as a table may write it: ``<name>_rad`` -> ``<name>_arcsec|_deg|_rad`` (for "allowed keys")."""
    return name[:-4] + "_arcsec|_deg|_rad" if name.endswith("_rad") else name


def printable_key(key) -> str:
    """A key as it may appear in a one-line message (control characters escaped)."""
    k = str(key)
    return k if k.isprintable() else repr(k)[1:-1]


# ============================================================================================ tables <-> dataclasses
ANGLE_KEY_SUFFIXES = {"_arcsec": math.pi / (180.0 * 3600.0), "_deg": math.pi / 180.0}
"""Key suffixes that fill a field ``<name>_rad`` with their factor to radians: the same values as
``scene/units.py``'s ARCSEC and DEG (this root module imports no project package)."""


def dataclass_from_table(cls, table: dict | None, *, source: str, section: str, base=None):
    """Build frozen dataclass ``cls`` from a TOML table through :func:`validate` (pydantic, strict).

    ``base``: an instance whose values replace the class defaults (e.g. a named method's settings).
    Keys ``<name>_arcsec`` / ``<name>_deg`` fill the field ``<name>_rad`` (converted to radians); an error
    about such a field names the key and the value as the user wrote them.
    """
    if table is not None and not isinstance(table, dict):
        raise ConfigError("must be a table", source=source, field=section)
    fields = {f.name for f in dataclasses.fields(cls) if f.init}
    merged = dataclass_to_table(base) if base is not None else {}
    written = {}                                   # field -> (key as written, scale)
    for key, value in (table or {}).items():
        name, scale = key, 1.0
        if key not in fields:
            for suffix, factor in ANGLE_KEY_SUFFIXES.items():
                if key.endswith(suffix) and key[: -len(suffix)] + "_rad" in fields:
                    name, scale = key[: -len(suffix)] + "_rad", factor
                    break
        if name not in fields:
            raise ConfigError(f"unknown key; allowed keys: {', '.join(sorted(friendly_key(n) for n in fields))}",
                              source=source, field=f"{section}.{printable_key(key)}")
        if scale != 1.0:
            if not _is_number(value):
                raise ConfigError(f"must be a number, got {value!r}", source=source, field=f"{section}.{key}")
            written[name] = (key, scale, value)
            value = value * scale
        merged[name] = value
    try:
        return validate(cls, merged, source=source, section=section)
    except ConfigError as e:
        fld = (e.field or "").removeprefix(section + ".")
        if fld in written:
            key, scale, value = written[fld]
            detail = e.detail.split(", got ")[0]
            detail = re.sub(r"(-?\d+(?:\.\d+)?(?:e-?\d+)?)", lambda m: f"{float(m.group(1)) / scale:.6g}", detail)
            unit = key.rsplit('_', 1)[1]
            detail = (re.sub(r"\(allowed (.*)\)$", rf"(allowed \1 {unit})", detail) if detail.endswith(")")
                      and "(allowed " in detail else f"{detail} ({unit})")
            raise ConfigError(f"{detail}, got {value!r}", source=source, field=f"{section}.{key}") from None
        raise


def dataclass_to_table(obj) -> dict:
    """Plain dict of a (nested) frozen dataclass, suitable for TOML/JSON.  Fields whose metadata has
    ``omit_if_default`` are left out while they hold their default (a run's stored spec, and so its
    identity, does not change when such an option is added)."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if f.metadata.get("omit_if_default") and v == f.default:
            continue                       # a newer option left at its default: older tables stay the same
        if dataclasses.is_dataclass(v):
            v = dataclass_to_table(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


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
