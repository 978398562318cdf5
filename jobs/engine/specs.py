"""The one configuration layer: TOML tables validated by pydantic into typed specs, errors that name file,
key and allowed values.

A table's keys are the dataclass's field names.  Angles may be given at the edge in friendlier units:
a key ``<name>_arcsec`` or ``<name>_deg`` fills the field ``<name>_rad`` (converted), so configs read
``tolerance_arcsec = 20`` while the code keeps SI radians inside.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from dualsight.scene.units import ARCSEC, DEG
from dualsight.config import MAX_DEPTH, _friendly, plain_tree, printable_key, validate  # noqa: F401 (re-exported)

from dualsight.errors import ConfigError, InputError

_UNIT_SUFFIX = {"_arcsec": ARCSEC, "_deg": DEG}


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
            for suffix, factor in _UNIT_SUFFIX.items():
                if key.endswith(suffix) and key[: -len(suffix)] + "_rad" in fields:
                    name, scale = key[: -len(suffix)] + "_rad", factor
                    break
        if name not in fields:
            raise ConfigError(f"unknown key; allowed keys: {', '.join(sorted(_friendly(n) for n in fields))}",
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
            raise ConfigError(f"{detail} ({key.rsplit('_', 1)[1]}), got {value!r}", source=source,
                              field=f"{section}.{key}") from None
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


def preset_and_config(presets: dict, preset: str | None, config: Path | str | dict | None,
                      default: str = "paper") -> tuple[dict, str]:
    """The spec layers below the command-line flags: a preset, then a TOML file over it.

    A config file may name its own base with a top-level ``preset = "..."``.  Tables merge key by key
    (recursively); everything else replaces.  ``config`` may also be a table of the file's layout (a dict
    given in code, ``dualsight.run``; named "config table" in errors).  Returns (merged dict, source name
    for error messages).
    """
    from dualsight.scene.camera import read_toml

    name = preset or default
    if name not in presets:
        raise InputError(f"unknown preset {name!r}; known presets: {', '.join(sorted(presets))}", source="--preset")
    d = deep_merge(presets[name], {})
    source = f"preset {name!r}"
    if config is not None:
        if isinstance(config, dict):
            user, source = config, "config table"
        else:
            user, source = read_toml(Path(config)), str(config)
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
