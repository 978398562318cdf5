"""What assembles a job's spec below its validation: the preset, then a TOML file (or table) over it, then the
command line's flags (:func:`preset_and_config`, :func:`deep_merge`), and the memory check of the result
(:func:`check_memory`).  Validation itself, the table <-> dataclass helpers and the angle-unit keys are the one
configuration layer, ``dualsight/config.py``.
"""

from __future__ import annotations

import os
from pathlib import Path

from dualsight.errors import ConfigError, InputError
from dualsight.scene.camera import read_toml

__all__ = ["check_memory", "preset_and_config", "deep_merge"]


def check_memory(nbytes: int, *, source: str, what: str = "this spec"):
    """Refuse a spec whose estimated peak memory per worker exceeds half the machine's RAM (or
    ``$DUALSIGHT_MAX_MEMORY_GB``), before anything is allocated."""
    limit_gb = os.environ.get("DUALSIGHT_MAX_MEMORY_GB")
    try:
        limit = float(limit_gb) * 2**30 if limit_gb else 0.5 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        limit = 8 * 2**30
    if nbytes > limit:
        raise ConfigError(f"{what} needs about {nbytes / 2**30:.1f} GiB per worker (frames x batch, star and pair "
                          f"catalogs), over the {limit / 2**30:.1f} GiB allowed; lower batch_size, the magnitude "
                          "limit or the field of view (or set DUALSIGHT_MAX_MEMORY_GB)", source=source)


def preset_and_config(presets: dict, preset: str | None, config: Path | str | dict | None,
                      default: str = "paper") -> tuple[dict, str]:
    """The spec layers below the command-line flags: a preset, then a TOML file over it.

    A config file may name its own base with a top-level ``preset = "..."``.  Tables merge key by key
    (recursively); everything else replaces.  ``config`` may also be a table of the file's layout (a dict
    given in code, ``dualsight.run``; named "config table" in errors).  Returns (merged dict, source name
    for error messages).
    """
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


def seed_and_case_count(d: dict, seed: int | None, cases: int | None, default_cases: int, source: str) -> int:
    """The command-line flags over a merged spec dict ``d`` (:func:`preset_and_config`): ``seed`` replaces
    ``d["seed"]`` (in place) when given; returns the case count, ``cases`` when given, else the spec's ``cases``,
    else ``default_cases``: an integer in [1, 1e9] (InputError naming ``--cases`` or the spec's ``source``)."""
    if seed is not None:
        d["seed"] = seed
    n = cases if cases is not None else d.get("cases", default_cases)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1 or n > 10**9:
        raise InputError(f"number of cases must be an integer in [1, 1e9], got {n!r}",
                         source="--cases" if cases is not None else source)
    return int(n)


def deep_merge(base: dict, over: dict) -> dict:
    """A new dict: ``base`` with ``over`` laid on top, tables merged recursively (inputs untouched)."""
    out = {k: (deep_merge(v, {}) if isinstance(v, dict) else v) for k, v in base.items()}
    for k, v in over.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else (
            deep_merge(v, {}) if isinstance(v, dict) else v)
    return out
