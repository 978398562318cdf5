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
every package validates its configs the same way: the kernels (whose config dataclasses live beside their
kernels), scene, catalogs, nav and jobs.
"""

from __future__ import annotations

import dataclasses
import datetime
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
           "ANGLE_KEY_SUFFIXES", "dataclass_from_table", "dataclass_to_table", "check_range", "TrackingConfig",
           "TargetConfig", "SequenceConfig", "OutputConfig", "EnvironmentConfig",
           "ApproachEnvironmentConfig"]


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


# ============================================================================================ star tracking (issue 22)
_DEG = math.pi / 180.0
_TrackPx = typing.Annotated[float, pydantic.Field(gt=0, le=1000.0)]
_TrackStars = typing.Annotated[int, pydantic.Field(ge=2, le=1000)]
_TRACKING_UNITS = {"window_k_sigma": "sigma", "window_min_px": "px", "window_max_px": "px", "tight_window_px": "px",
                   "centroid_sigma_px": "px", "min_stars": "stars", "min_stars_tight": "stars",
                   "max_predicted": "stars", "residual_k_sigma": "sigma", "max_rms_sigma": "sigma",
                   "initial_cone_rad": "rad", "rate_sigma_rad_s": "rad/s", "max_sigma_rad": "rad",
                   "accel_steady_rad_s2": "rad/s^2", "accel_manoeuvre_rad_s2": "rad/s^2",
                   "filter_max_gap_s": "s", "jerk_rad_s3": "rad/s^3",
                   "smear_sigma_per_px": "px/px", "smear_cross_per_px": "px/px", "rate_jitter_rad_s": "rad/s",
                   "edge_margin_px": "px", "streak_psf_sigma_px": "px"}


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Options of star tracking over an image sequence (``nav/tracking.py``): predict the catalog stars from the
    previous attitude and the rate, match them in windows that follow the predicted uncertainty, solve and verify;
    the rules that lose lock (the caller then falls back to lost-in-space).

    Every field's range is part of its type, checked when the dataclass is built (ConfigError naming
    ``tracking.<field>``, the value and the range) and when a TOML table is validated (:func:`dataclass_from_table`,
    which also takes ``<name>_deg`` / ``<name>_arcsec`` for a ``<name>_rad`` field).

    window_k_sigma : window radius in predicted 1-sigma position uncertainties, in (0, 20] (default 5).
    window_min_px, window_max_px : bounds of a window's radius (px), in (0, 1000], min <= max (defaults 2, 50).
    tight_window_px : a prediction is *tight* when every window is at most this radius (px), in (0, 1000]
        (default 4): then ``min_stars_tight`` matched stars suffice (LOST #87: tracking with 2 stars).
    centroid_sigma_px : 1-sigma centroid error per axis (px) assumed when the detector states none, and the
        detection noise added to the predicted uncertainty, in (0, 1000] (default 0.3).
    min_stars : fewest matched stars for a lock, integer in [2, 1000] (default 3, tetra3rs' tracking).
    min_stars_tight : fewest matched stars for a lock under a tight prediction, in [2, 1000], <= min_stars
        (default 2).
    max_predicted : the brightest catalog stars predicted in the image, integer in [2, 1000] (default 40).
    edge_margin_px : a predicted star is matched only when its whole predicted streak (half its length either side
        of the predicted centroid, along its image motion; no length without smear) lies at least this far (px)
        inside the image, in [0, 1000] (default 1): a star or streak cut by the image's edge has its centroid pulled
        inwards, along the streak, by up to half its length, which a fit weighting the streak as whole cannot know
        (``nav.smear_weights.streak_inside``; on 10^5 frames at up to 1 deg/s, two of three false locks came from a
        streak cut by the edge).
    residual_k_sigma : a matched star whose post-fit residual exceeds this many of its centroid sigmas is dropped
        and the attitude solved again, in (0, 100] (default 5).
    max_rms_sigma : lock is lost when the post-fit residuals' RMS per degree of freedom exceeds this many sigmas
        (about 1 for correct matches), in (0, 100] (default 3).
    max_p_chance : lock is lost when the chance-match probability of the matches exceeds this, in (0, 1]
        (default 1e-3; ``nav/tracking.py: tracking_chance``).
    initial_cone_rad : 1-sigma attitude uncertainty per axis (rad) assumed for a previous attitude that comes
        without a covariance (a hint, an old solution), in (0, 10 deg] (default 0.05 deg).
    rate_sigma_rad_s : 1-sigma rate uncertainty per axis (rad/s) assumed when no rate is known (after a
        lost-in-space fix), in (0, 30 deg/s] (default 0.5 deg/s).
    max_sigma_rad : an attitude (tracking's or lost-in-space's) is output as valid only when its stated
        covariance, scaled by the fit's a posteriori variance factor ``max(1, rms^2)``, has every principal
        1-sigma at most this (rad), in (0, 10 deg]; a weaker one (a two-star or short-baseline solution's roll) is
        *degraded*: not output, not a prior (``nav/sequence.py``).  TOML also takes ``max_sigma_arcsec``.  The rule
        is only as honest as the centroid sigmas: set it where the detector states them (the ``realistic``
        preset's local detector: ``examples/star/track.toml`` uses 33 arcsec, a third of the reference's 100
        arcsec limit, so a valid attitude beyond the limit is a 3-sigma event on its weakest axis); the default,
        10 deg, withholds nothing (a detector without sigmas gets ``centroid_sigma_px``, an assumption, not a
        measurement).
        With ``attitude_filter`` the rule applies to the filtered attitude.
    attitude_filter : fuse every verified frame solution (tracking's or lost-in-space's, degraded ones too) in the
        gyroless attitude and rate filter of ``nav/attitude_filter.py`` and output the filtered attitude; the
        prediction of the next frame is the filter's (default true).  False: each frame's own solution, the rate
        from the last two fixes.
    accel_steady_rad_s2, accel_manoeuvre_rad_s2 : 1-sigma angular acceleration per axis (rad/s^2) of the filter's
        steady and manoeuvre models (constant rate with a random acceleration), in (0, 100 deg/s^2], steady <=
        manoeuvre (defaults 0.05 and 1 deg/s^2: the steady model follows most of a jitter of 2 arcsec at 2 Hz,
        0.09 deg/s^2 peak; the manoeuvre model a small satellite's slew acceleration, typically 0.1-1 deg/s^2).
    jerk_rad_s3 : 1-sigma angular jerk per axis (rad/s^3) of the filter's third model, a constant angular
        acceleration (a slew's acceleration phase), in (0, 1000 deg/s^3] (default 0.2 deg/s^3).
    model_switch_prob : probability per frame that the motion leaves its model (for one of the other two, equally),
        in (0, 2/3) (default 0.05).
    filter_gate : a verified solution whose normalised innovation squared (chi-square, 3 dof) against the filter's
        prediction exceeds this restarts the filter at it, in (0, 1e6] (default 25: p = 1.7e-5).
    filter_max_gap_s : frames further apart than this (s) are fused at a constant rate, without the models' random
        acceleration (which describes a spacecraft's attitude control over a fraction of a second, not a ground
        camera's frames 30 s apart), in (0, 1e6] (default 1).
    smear_sigma_per_px, smear_cross_per_px : centroid error (px, 1-sigma) per px of a star's streak along and
        across the streak, added in quadrature to the detector's sigma in tracking (the model error of a round-PSF
        fit to a streak; the streak's length and direction from the filter's rate and the sequence's exposure:
        ``nav/smear_weights.py``; the tracked attitude is then refined with each star's 2 x 2 covariance), in
        [0, 1] (defaults 0: off; ``examples/star/track.toml`` sets 0.02 and 0.003 for the ``realistic`` preset's
        local detector).
    streak_psf_sigma_px : the 1-sigma width (px) of a star's profile across its streak; with it, the detector's
        stated variance along a streak of L px grows by ``1 + L^2 / (12 s^2)`` (the streak's profile is wider
        along it: ``nav.smear_weights.along_gain``), in [0, 20] (default 0: off; ``examples/star/track.toml``
        sets 1.28, measured on the ``realistic`` preset's frames).
    rate_jitter_rad_s : 1-sigma per axis (rad/s) of the platform's rate jitter, faster than the filter follows,
        added to the filter's stated rate covariance (``rate_filter_cov``): the filter's rate is the rate averaged
        over its memory, the row's truth the rate at the frame, and they differ by the jitter's.  A sinusoid of
        amplitude a (rad) at f (Hz) per axis has an RMS rate of ``2 pi f a / sqrt(2)`` (``examples/star/track.toml``:
        2 arcsec at 2 Hz, 8.6e-5 rad/s).  In [0, 1 rad/s] (default 0: no jitter stated).
    """

    window_k_sigma: typing.Annotated[float, pydantic.Field(gt=0, le=20.0)] = 5.0
    window_min_px: _TrackPx = 2.0
    window_max_px: _TrackPx = 50.0
    tight_window_px: _TrackPx = 4.0
    centroid_sigma_px: _TrackPx = 0.3
    min_stars: _TrackStars = 3
    min_stars_tight: _TrackStars = 2
    max_predicted: _TrackStars = 40
    edge_margin_px: typing.Annotated[float, pydantic.Field(ge=0, le=1000.0)] = 1.0
    residual_k_sigma: typing.Annotated[float, pydantic.Field(gt=0, le=100.0)] = 5.0
    max_rms_sigma: typing.Annotated[float, pydantic.Field(gt=0, le=100.0)] = 3.0
    max_p_chance: typing.Annotated[float, pydantic.Field(gt=0, le=1.0)] = 1e-3
    initial_cone_rad: typing.Annotated[float, pydantic.Field(gt=0, le=10 * _DEG)] = 0.05 * _DEG
    rate_sigma_rad_s: typing.Annotated[float, pydantic.Field(gt=0, le=30 * _DEG)] = 0.5 * _DEG
    max_sigma_rad: typing.Annotated[float, pydantic.Field(gt=0, le=10 * _DEG)] = 10 * _DEG
    attitude_filter: bool = True
    accel_steady_rad_s2: typing.Annotated[float, pydantic.Field(gt=0, le=100 * _DEG)] = 0.05 * _DEG
    accel_manoeuvre_rad_s2: typing.Annotated[float, pydantic.Field(gt=0, le=100 * _DEG)] = 1.0 * _DEG
    jerk_rad_s3: typing.Annotated[float, pydantic.Field(gt=0, le=1000 * _DEG)] = 0.2 * _DEG
    model_switch_prob: typing.Annotated[float, pydantic.Field(gt=0, lt=2.0 / 3.0)] = 0.05
    filter_gate: typing.Annotated[float, pydantic.Field(gt=0, le=1e6)] = 25.0
    filter_max_gap_s: typing.Annotated[float, pydantic.Field(gt=0, le=1e6)] = 1.0
    smear_sigma_per_px: typing.Annotated[float, pydantic.Field(ge=0, le=1.0)] = 0.0
    smear_cross_per_px: typing.Annotated[float, pydantic.Field(ge=0, le=1.0)] = 0.0
    streak_psf_sigma_px: typing.Annotated[float, pydantic.Field(ge=0, le=20.0)] = 0.0
    rate_jitter_rad_s: typing.Annotated[float, pydantic.Field(ge=0, le=1.0)] = 0.0

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"tracking.{name}"), _TRACKING_UNITS)
        if self.accel_steady_rad_s2 > self.accel_manoeuvre_rad_s2:
            raise ConfigError(f"must be <= accel_manoeuvre_rad_s2 ({self.accel_manoeuvre_rad_s2:g} rad/s^2), got "
                              f"{self.accel_steady_rad_s2!r}", field="tracking.accel_steady_rad_s2")
        if self.window_min_px > self.window_max_px:
            raise ConfigError(f"must be <= window_max_px ({self.window_max_px:g} px), got {self.window_min_px!r}",
                              field="tracking.window_min_px")
        if self.min_stars_tight > self.min_stars:
            raise ConfigError(f"must be <= min_stars ({self.min_stars}), got {self.min_stars_tight!r}",
                              field="tracking.min_stars_tight")


# ============================================================================================ target in the star field (issue 23)
_TargetRange = typing.Annotated[float, pydantic.Field(ge=1.0, le=1e8)]
_TargetOffset = typing.Annotated[float, pydantic.Field(ge=-89.0, le=89.0)]
_TargetPhase = typing.Annotated[float, pydantic.Field(ge=0.0, le=180.0)]
_TargetUnit = typing.Annotated[float, pydantic.Field(ge=-1.0, le=1.0)]
_TARGET_UNITS = {"range_m": "m", "offset_deg": "deg", "phase_deg": "deg", "sun_keepout_deg": "deg"}


@dataclasses.dataclass(frozen=True)
class TargetConfig:
    """A spacecraft in the star tracker's field (``[target]`` of a star spec; issue 23): drawn per case, rendered
    into the same frame as the stars (it hides the stars behind it) with the stars' photometric zero point.

    Every field's range is part of its type, checked when the dataclass is built (ConfigError naming
    ``target.<field>``, the value and the range) and when a TOML table is validated (:func:`dataclass_from_table`).

    satellite : path of a satellite configuration file (``scene/satellite.py``); its ``[[component]]`` shapes,
        sizes, poses and Lambertian coefficients ``k_l`` (used as the diffuse reflectance) make the target; its
        camera and body parts are not used (1 to 4096 characters, relative to the working directory).
    range_m : [min, max] distance camera -> body origin (m), each in [1, 1e8], min <= max; drawn log-uniformly
        (min = max: a fixed range).
    offset_deg : [x, y] direction of the body origin from the boresight (deg, each in [-89, 89]: the camera-frame
        direction (tan x, tan y, 1)); absent = uniform over the inner 90 % of the image (per case).
    sun_icrs : unit vector (ICRS) towards the Sun, each component in [-1, 1], norm 1 +- 1e-3; absent = a random
        Sun at a phase angle drawn uniformly in ``phase_deg``.
    phase_deg : [min, max] Sun-target-camera phase angle (deg), each in [0, 180], min <= max (default [0, 90]).
    sun_keepout_deg : half-angle (deg) of the Sun exclusion cone about the boresight, in [0, 180] (default 30);
        each row says whether the Sun is inside it.
    probability : chance that a case has the target in its field, in [0, 1] (default 1).
    exclude_resolved : keep blobs larger than any star can make (the resolved target) out of star
        identification (``nav/resolved_blobs.py``; default True).
    phase_correction : with the Sun's direction known, also correct the measured centre of brightness for the
        phase angle (``scene/target_photometry.photocentre_table``: the target's mean photocentre over random
        attitudes at the range of the case, and ``photocentre_offset`` for its known attitude) and write the
        corrected bearings' errors against the body origin (``target_bearing_pc_*`` columns; default False).
    environment : ``[target.environment]`` (:class:`EnvironmentConfig`): an epoch and an orbit per case; the Sun
        then comes from the epoch (``sun_icrs`` and ``phase_deg`` unused) and each row gets the Earth, Moon and
        shadow columns; absent = the Sun as above and those columns null.
    """

    satellite: typing.Annotated[str, pydantic.Field(min_length=1, max_length=4096)]
    range_m: typing.Annotated[tuple[_TargetRange, _TargetRange], pydantic.Field(min_length=2, max_length=2)] = \
        (10000.0, 10000.0)
    offset_deg: typing.Annotated[tuple[_TargetOffset, _TargetOffset],
                                 pydantic.Field(min_length=2, max_length=2)] | None = None
    sun_icrs: typing.Annotated[tuple[_TargetUnit, _TargetUnit, _TargetUnit],
                               pydantic.Field(min_length=3, max_length=3)] | None = None
    phase_deg: typing.Annotated[tuple[_TargetPhase, _TargetPhase], pydantic.Field(min_length=2, max_length=2)] = \
        (0.0, 90.0)
    sun_keepout_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=180.0)] = 30.0
    probability: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 1.0
    exclude_resolved: bool = True
    phase_correction: bool = False
    environment: EnvironmentConfig | None = None

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"target.{name}"), _TARGET_UNITS)
        for name in ("range_m", "phase_deg"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ConfigError(f"must be [min, max] with min <= max, got {list(getattr(self, name))!r}",
                                  field=f"target.{name}")
        if self.sun_icrs is not None and abs(math.hypot(*self.sun_icrs) - 1.0) > 1e-3:
            raise ConfigError(f"must be a unit vector (norm 1 +- 1e-3), got {list(self.sun_icrs)!r} "
                              f"(norm {math.hypot(*self.sun_icrs):.6g})", field="target.sun_icrs")


# ============================================================================================ star sequences (issue 22)
_SeqRate = typing.Annotated[float, pydantic.Field(ge=0.0, le=30.0)]
_SeqCount = typing.Annotated[int, pydantic.Field(ge=0, le=10_000)]
_SeqPsdFreq = typing.Annotated[float, pydantic.Field(ge=0.0, le=500.0)]
_SeqPsd = typing.Annotated[float, pydantic.Field(ge=0.0, le=1e8)]
_SeqPsdAxis = typing.Annotated[float, pydantic.Field(ge=0.0, le=100.0)]
_SEQUENCE_UNITS = {"frames": "frames", "fps": "Hz", "exposure_s": "s", "rate_max_deg_s": "deg/s",
                   "slew_angle_max_deg": "deg", "slew_accel_deg_s2": "deg/s^2", "jitter_arcsec": "arcsec",
                   "jitter_freq_hz": "Hz", "jitter_psd_freq_hz": "Hz",
                   "jitter_psd_arcsec2_hz": "arcsec^2/Hz", "gyro_noise_deg_s": "deg/s", "gyro_bias_deg_s": "deg/s",
                   "blank": "frames", "blinded": "frames", "dropped": "frames", "max_coast_frames": "frames",
                   "lis_min_stars": "stars", "error_limit_arcsec": "arcsec", "bright_crossings": "crossings",
                   "crossing_frames": "frames", "crossing_vmag": "mag", "crossing_radius_px": "px"}


@dataclasses.dataclass(frozen=True)
class SequenceConfig:
    """One case of a star-tracking campaign (``[sequence]`` of a ``dualsight star track`` spec; issue 22): an
    image sequence, its attitude trajectory, gyro and events (``jobs/kinds/star_track.py``,
    ``scene/attitude_trajectory.py``, ``nav/sequence.py``).

    Every field's range is part of its type, checked when the dataclass is built (ConfigError naming
    ``sequence.<field>``, the value and the range) and when a TOML table is validated (:func:`dataclass_from_table`).

    frames : images per sequence, integer in [2, 10000] (default 50).  fps : frame rate (Hz), in (0, 1000]
        (default 10).  exposure_s : exposure of every frame (s), in (0, 10], at most 1 / fps (default 0.1);
        it replaces the sensor's ``exposure_s``.
    motion : "constant" (a constant body rate about a random axis, magnitude uniform in [0, rate_max_deg_s]),
        "slew" (a rest-to-rest eigenaxis slew of an angle uniform in [0, slew_angle_max_deg] about a random axis,
        rate limit ``rate_max_deg_s``, acceleration limit ``slew_accel_deg_s2``, starting in the first third of the
        sequence) or "mixed" (either, with equal chance per case) (default "constant").
    rate_max_deg_s : in [0, 30] deg/s (default 1).  slew_angle_max_deg : in [0, 180] (default 10).
    slew_accel_deg_s2 : in (0, 100] deg/s^2 (default 0.5).
    jitter_arcsec : amplitude per axis of a sinusoidal jitter (arcsec), in [0, 3600] (default 0: none);
        jitter_freq_hz : its frequency, in (0, 1000] Hz (default 2); phases from the case's generator.
    jitter_psd_freq_hz, jitter_psd_arcsec2_hz : a jitter with a given one-sided power spectral density, laid over
        the motion besides the sinusoid (default none): >= 2 strictly increasing frequencies in [0, fps / 2] Hz (the
        frame rate's Nyquist frequency: the renderer smears each frame along one straight chord, so faster jitter
        would only alias) and the PSD at each, arcsec^2/Hz in [0, 1e8], not all zero; piecewise linear between the
        points, zero outside (``scene/attitude_trajectory.jitter_from_psd_table``: each axis' variance is the PSD's
        integral).  jitter_psd_axes : the PSD's factor per camera axis [x, y, z], each in [0, 100] (default
        [1, 1, 1]: the same spectrum on every axis; [1, 1, 0]: no roll jitter).
    smear : render each frame smeared by its true body rate over the exposure (default True).
    gyro : the tracker gets a rate gyro's readings (default False): true rate + a constant bias drawn per axis
        with 1-sigma ``gyro_bias_deg_s`` (in [0, 10], default 0) + white noise ``gyro_noise_deg_s`` per sample
        (in [0, 10], default 0.01).
    blank, blinded, dropped : frames of each event per sequence, at random frames after the first (a blank frame:
        no star light; blinded: the Sun or the Earth saturates the background; dropped: no image), integers in
        [0, 10000] (defaults 0, 1, 1); together fewer than ``frames``.
    max_coast_frames : a fix older than this many frames is no prior for tracking, in [0, 10000] (default 10).
    lis_min_stars : fewest accepted stars of a verified lost-in-space fix, in [3, 100] (default 3).
    error_limit_arcsec : a valid attitude whose error exceeds this on any axis is a false lock, in (0, 36000]
        (default 100, the reference's limit).
    shadow_lost_in_space : also run lost-in-space on every frame, for the identities and the speed of both on the
        same frames (default False).
    bright_crossings : bright objects crossing the field per sequence, integer in [0, 10000] (default 0): each a
        planet or the Moon (not a catalog star) moving along a straight line across the image over
        ``crossing_frames`` consecutive frames (in [1, 10000], < frames; default 5), at a random start after the
        first frame, through a random point of the image's central half, covering the image's diagonal; its
        magnitude ``crossing_vmag`` in [-30, 30] (default -4, Venus) and radius ``crossing_radius_px`` in
        [0, 4096] px (default 0: a point with the star PSF; > 0: a uniform disk, the Moon ~ 0.0045 f).  Its frames
        have the event ``crossing`` (a frame with another event keeps that one).
    true_focal_error : the true focal length is the camera file's times (1 + this), in [-0.2, 0.2] (default 0):
        frames are rendered with it, the tracker starts from the file's.
    refine_focal : refine the focal length while tracking (``nav/focal_refine.py``: the least-squares focal
        length of every fix, fused over the frames; the tracker uses the fused value), default False.
    """

    frames: typing.Annotated[int, pydantic.Field(ge=2, le=10_000)] = 50
    fps: typing.Annotated[float, pydantic.Field(gt=0.0, le=1000.0)] = 10.0
    exposure_s: typing.Annotated[float, pydantic.Field(gt=0.0, le=10.0)] = 0.1
    motion: typing.Literal["constant", "slew", "mixed"] = "constant"
    rate_max_deg_s: _SeqRate = 1.0
    slew_angle_max_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=180.0)] = 10.0
    slew_accel_deg_s2: typing.Annotated[float, pydantic.Field(gt=0.0, le=100.0)] = 0.5
    jitter_arcsec: typing.Annotated[float, pydantic.Field(ge=0.0, le=3600.0)] = 0.0
    jitter_freq_hz: typing.Annotated[float, pydantic.Field(gt=0.0, le=1000.0)] = 2.0
    jitter_psd_freq_hz: tuple[_SeqPsdFreq, ...] = dataclasses.field(default=(), metadata={"omit_if_default": True})
    jitter_psd_arcsec2_hz: tuple[_SeqPsd, ...] = dataclasses.field(default=(), metadata={"omit_if_default": True})
    jitter_psd_axes: tuple[_SeqPsdAxis, _SeqPsdAxis, _SeqPsdAxis] = dataclasses.field(
        default=(1.0, 1.0, 1.0), metadata={"omit_if_default": True})
    smear: bool = True
    gyro: bool = False
    gyro_noise_deg_s: typing.Annotated[float, pydantic.Field(ge=0.0, le=10.0)] = 0.01
    gyro_bias_deg_s: typing.Annotated[float, pydantic.Field(ge=0.0, le=10.0)] = 0.0
    blank: _SeqCount = 0
    blinded: _SeqCount = 1
    dropped: _SeqCount = 1
    max_coast_frames: _SeqCount = 10
    lis_min_stars: typing.Annotated[int, pydantic.Field(ge=3, le=100)] = 3
    error_limit_arcsec: typing.Annotated[float, pydantic.Field(gt=0.0, le=36000.0)] = 100.0
    shadow_lost_in_space: bool = False
    bright_crossings: _SeqCount = dataclasses.field(default=0, metadata={"omit_if_default": True})
    crossing_frames: typing.Annotated[int, pydantic.Field(ge=1, le=10_000)] = dataclasses.field(
        default=5, metadata={"omit_if_default": True})
    crossing_vmag: typing.Annotated[float, pydantic.Field(ge=-30.0, le=30.0)] = dataclasses.field(
        default=-4.0, metadata={"omit_if_default": True})
    crossing_radius_px: typing.Annotated[float, pydantic.Field(ge=0.0, le=4096.0)] = dataclasses.field(
        default=0.0, metadata={"omit_if_default": True})
    true_focal_error: typing.Annotated[float, pydantic.Field(ge=-0.2, le=0.2)] = dataclasses.field(
        default=0.0, metadata={"omit_if_default": True})
    refine_focal: bool = dataclasses.field(default=False, metadata={"omit_if_default": True})

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"sequence.{name}"), _SEQUENCE_UNITS)
        if self.exposure_s > 1.0 / self.fps:
            raise ConfigError(f"must be <= 1 / fps ({1.0 / self.fps:g} s), got {self.exposure_s!r}",
                              field="sequence.exposure_s")
        f, S = self.jitter_psd_freq_hz, self.jitter_psd_arcsec2_hz
        if f or S:
            if len(f) < 2 or len(S) != len(f):
                raise ConfigError(f"needs >= 2 frequencies and one PSD value per frequency, got "
                                  f"{len(f)} frequencies and {len(S)} values", field="sequence.jitter_psd_arcsec2_hz")
            if any(b <= a for a, b in zip(f[:-1], f[1:])):
                raise ConfigError(f"must be strictly increasing, got {list(f)!r}", field="sequence.jitter_psd_freq_hz")
            if f[-1] > 0.5 * self.fps:
                raise ConfigError(f"must be <= fps / 2 ({0.5 * self.fps:g} Hz, the frames' Nyquist frequency), got "
                                  f"{f[-1]!r}", field="sequence.jitter_psd_freq_hz")
            if not any(v > 0 for v in S):
                raise ConfigError("must not be all zero (leave both keys out for no jitter)",
                                  field="sequence.jitter_psd_arcsec2_hz")
        if self.bright_crossings and self.crossing_frames >= self.frames:
            raise ConfigError(f"must be < frames ({self.frames}), got {self.crossing_frames!r}",
                              field="sequence.crossing_frames")
        if self.blank + self.blinded + self.dropped >= self.frames:
            raise ConfigError(f"blank + blinded + dropped must be < frames ({self.frames}), got "
                              f"{self.blank + self.blinded + self.dropped}", field="sequence.blinded")


# ============================================================================================ star-run output (issue 24.5)
@dataclasses.dataclass(frozen=True)
class OutputConfig:
    """What a star run stores beside its one row per case (``[output]`` of a star spec; issue 24, point 5).

    detections : the per-star detail (dataset ``star_detections``, one row per detection, ~420 B per case of the
        paper preset against ~94 B in ``star_cases``): "on" always, "off" never, "auto" (default) only when the
        run has at most ``detections_max_cases`` cases.  Every report number but the blob breakdown comes from
        ``star_cases``; a replay recomputes a case's detections from its row whether they were kept or not.
    detections_max_cases : the largest run "auto" keeps the detections of, an integer in [0, 1e9] (default 100,000:
        ~42 MB of detections for the paper preset).

    What a run keeps is part of its identity (``jobs/kinds/star.py`` stores the resolved choice in the canonical
    spec when the detections are dropped), so a resume never mixes shards with and without them.
    """

    detections: typing.Literal["auto", "on", "off"] = "auto"
    detections_max_cases: typing.Annotated[int, pydantic.Field(ge=0, le=10**9)] = 100_000

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"output.{name}"))

    def keeps_detections(self, n_cases: int) -> bool:
        """True when a run of ``n_cases`` cases stores ``star_detections`` under these settings."""
        return self.detections == "on" or (self.detections == "auto" and n_cases <= self.detections_max_cases)


# ============================================================================================ rendezvous (issue 23, point 5)
_RdvPos = typing.Annotated[float, pydantic.Field(ge=-1e5, le=1e5)]
_RdvVel = typing.Annotated[float, pydantic.Field(ge=-100.0, le=100.0)]
_RdvDv = typing.Annotated[float, pydantic.Field(ge=-10.0, le=10.0)]
_RdvTime = typing.Annotated[float, pydantic.Field(gt=0.0, le=1e6)]
_RdvDispP = typing.Annotated[float, pydantic.Field(ge=0.0, le=1e4)]
_RdvDispV = typing.Annotated[float, pydantic.Field(ge=0.0, le=10.0)]
_RdvPriorP = typing.Annotated[float, pydantic.Field(gt=0.0, le=1e5)]
_RdvPriorV = typing.Annotated[float, pydantic.Field(gt=0.0, le=100.0)]
_RDV_UNITS = {"altitude_km": "km", "inclination_deg": "deg", "raan_deg": "deg", "arg_lat_deg": "deg",
              "position_m": "m", "velocity_m_s": "m/s", "dispersion_position_m": "m",
              "dispersion_velocity_m_s": "m/s", "duration_s": "s", "frame_interval_s": "s",
              "manoeuvre_times_s": "s", "manoeuvre_dv_m_s": "m/s", "dv_error_m_s": "m/s",
              "pointing_error_deg": "deg", "target_rate_deg_s": "deg/s", "attitude_sigma_arcsec": "arcsec",
              "cob_sigma_frac": "of the diameter", "prior_position_m": "m", "prior_velocity_m_s": "m/s",
              "accel_psd": "m^2/s^3", "converged_after_frames": "frames"}


@dataclasses.dataclass(frozen=True)
class RendezvousConfig:
    """One approach of a rendezvous campaign (``[rendezvous]`` of a ``dualsight rendezvous run`` spec; issue 23,
    point 5; ``jobs/kinds/rendezvous.py``).  Every field's range is part of its type, checked when the dataclass is
    built (ConfigError naming ``rendezvous.<field>``, the value and the range) and when a TOML table is validated.

    Reference orbit (the target's, circular; ``scene/relative_orbit.CircularOrbit``): altitude_km in [150, 40000]
        (default 500), inclination_deg in [0, 180] (51.6), raan_deg and arg_lat_deg in [0, 360] (30, 0).
    Initial relative state of the chaser in the target's Hill frame (x radial, y along-track, z cross-track):
        position_m (3 values, each in [-1e5, 1e5] m; default [0, -2000, 0]: 2 km behind on V-bar), velocity_m_s
        (each in [-100, 100] m/s; default 0); per-case dispersion (1-sigma per Hill axis x, y, z, Gaussian):
        dispersion_position_m 3 values in [0, 1e4] m (default [2, 100, 2]), dispersion_velocity_m_s 3 values in
        [0, 10] m/s (default 1e-4 each).
    Frames: duration_s in (0, 1e6] s (default 6300), frame_interval_s in (0, 1e4] s (default 100); frames at
        0, dt, 2 dt, ... <= duration, at most 10000.
    Known manoeuvres: manoeuvre_times_s (up to 16 times in (0, duration]) and manoeuvre_dv_m_s (as many [dvx, dvy,
        dvz] in the Hill frame, each in [-10, 10] m/s); the executed delta-v carries a Gaussian error per axis of
        dv_error_frac x |dv| (in [0, 1], default 0.01) and dv_error_m_s (in [0, 1], default 0), both known to the
        filter.
    Pointing: "target" (boresight on the true target with a Gaussian pointing error of pointing_error_deg per axis,
        in [0, 10], default 0.5, drawn per frame) or "inertial" (held on the target's initial nominal direction).
    camera: "star" (the star preset's camera and ``sensor`` preset: stars give the attitude) or the path of a
        camera file (a proximity camera: no stars are rendered, the attitude comes from the chaser's own star
        tracker with attitude_sigma_arcsec per axis, in (0, 3600], default 10).
    sensor: star sensor preset "ideal", "paper" (default) or "realistic" (``jobs/kinds/star.py``).
    satellite: the target's satellite file (1 to 4096 characters); it spins at target_rate_deg_s about an axis
        drawn per case (in [0, 30], default 1).
    sun_icrs: unit vector towards the Sun (ICRS, norm 1 +- 1e-3); absent = the epoch's Sun with ``environment``,
        else the reference orbit's normal.
    environment: ``[rendezvous.environment]`` (:class:`ApproachEnvironmentConfig`): the approach's start epoch and
        keep-out half-angles; each frame gets the Sun, Earth and Moon columns (absent: null).
    range_source: "blobber" (a range from every resolved blob: ``nav/blobber.py``, its [min, max] the
        uncertainty) or "none" (bearings only).
    phase_correction: move each bearing from the centre of brightness to the centre by the target's mean
        photocentre offset over random attitudes at the measured phase angle, at the predicted range, and add its
        spread over attitudes to the bearing's covariance (``scene/target_photometry.photocentre_table``; default
        True).
    cob_sigma_frac: a further 1-sigma of the centre of brightness about the body's centre, as a fraction of the
        bounding sphere's diameter, at the predicted range (in [0, 1], default 0.1).
    Filter (``nav/relative_filter.py``): prior_position_m 3 values in (0, 1e5] m and prior_velocity_m_s 3 values in
        (0, 100] m/s (1-sigma per Hill axis about the nominal state; defaults: the dispersion's), accel_psd in
        [0, 1e-3] m^2/s^3 (default 1e-12), iterations in [1, 20] (default 3).
    converged_after_frames: frames after which the report holds the filter to its chi-square bounds, in [0, 10000]
        (default 10).
    """

    altitude_km: typing.Annotated[float, pydantic.Field(ge=150.0, le=40000.0)] = 500.0
    inclination_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=180.0)] = 51.6
    raan_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=360.0)] = 30.0
    arg_lat_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=360.0)] = 0.0
    position_m: typing.Annotated[tuple[_RdvPos, _RdvPos, _RdvPos], pydantic.Field(min_length=3, max_length=3)] = \
        (0.0, -2000.0, 0.0)
    velocity_m_s: typing.Annotated[tuple[_RdvVel, _RdvVel, _RdvVel], pydantic.Field(min_length=3, max_length=3)] = \
        (0.0, 0.0, 0.0)
    dispersion_position_m: typing.Annotated[tuple[_RdvDispP, _RdvDispP, _RdvDispP],
                                            pydantic.Field(min_length=3, max_length=3)] = (2.0, 100.0, 2.0)
    dispersion_velocity_m_s: typing.Annotated[tuple[_RdvDispV, _RdvDispV, _RdvDispV],
                                              pydantic.Field(min_length=3, max_length=3)] = (1e-4, 1e-4, 1e-4)
    duration_s: _RdvTime = 6300.0
    frame_interval_s: typing.Annotated[float, pydantic.Field(gt=0.0, le=1e4)] = 100.0
    manoeuvre_times_s: typing.Annotated[tuple[_RdvTime, ...], pydantic.Field(max_length=16)] = ()
    manoeuvre_dv_m_s: typing.Annotated[tuple[tuple[_RdvDv, _RdvDv, _RdvDv], ...], pydantic.Field(max_length=16)] = ()
    dv_error_frac: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 0.01
    dv_error_m_s: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 0.0
    pointing: typing.Literal["target", "inertial"] = "target"
    pointing_error_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=10.0)] = 0.5
    camera: typing.Annotated[str, pydantic.Field(min_length=1, max_length=4096)] = "star"
    sensor: typing.Literal["ideal", "paper", "realistic"] = "paper"
    attitude_sigma_arcsec: typing.Annotated[float, pydantic.Field(gt=0.0, le=3600.0)] = 10.0
    satellite: typing.Annotated[str, pydantic.Field(min_length=1, max_length=4096)] = \
        "examples/satellites/cubesat_3u.toml"
    target_rate_deg_s: typing.Annotated[float, pydantic.Field(ge=0.0, le=30.0)] = 1.0
    sun_icrs: typing.Annotated[tuple[_TargetUnit, _TargetUnit, _TargetUnit],
                               pydantic.Field(min_length=3, max_length=3)] | None = None
    range_source: typing.Literal["blobber", "none"] = "none"
    phase_correction: bool = True
    cob_sigma_frac: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 0.1
    prior_position_m: typing.Annotated[tuple[_RdvPriorP, _RdvPriorP, _RdvPriorP],
                                       pydantic.Field(min_length=3, max_length=3)] = (2.0, 100.0, 2.0)
    prior_velocity_m_s: typing.Annotated[tuple[_RdvPriorV, _RdvPriorV, _RdvPriorV],
                                         pydantic.Field(min_length=3, max_length=3)] = (1e-4, 1e-4, 1e-4)
    accel_psd: typing.Annotated[float, pydantic.Field(ge=0.0, le=1e-3)] = 1e-12
    iterations: typing.Annotated[int, pydantic.Field(ge=1, le=20)] = 3
    converged_after_frames: typing.Annotated[int, pydantic.Field(ge=0, le=10_000)] = 10
    environment: ApproachEnvironmentConfig | None = dataclasses.field(default=None,
                                                                      metadata={"omit_if_default": True})

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"rendezvous.{name}"), _RDV_UNITS)
        frames = int(math.floor(self.duration_s / self.frame_interval_s + 1e-9)) + 1
        if frames > 10_000 or frames < 2:
            raise ConfigError(f"duration_s / frame_interval_s must give 2 to 10000 frames, got {frames}",
                              field="rendezvous.frame_interval_s")
        if len(self.manoeuvre_times_s) != len(self.manoeuvre_dv_m_s):
            raise ConfigError(f"must have one [dvx, dvy, dvz] per manoeuvre time ({len(self.manoeuvre_times_s)}), "
                              f"got {len(self.manoeuvre_dv_m_s)}", field="rendezvous.manoeuvre_dv_m_s")
        for i, t in enumerate(self.manoeuvre_times_s):
            if t > self.duration_s:
                raise ConfigError(f"must lie in (0, duration_s = {self.duration_s:g}] s, got {t!r}",
                                  field=f"rendezvous.manoeuvre_times_s[{i}]")
        if self.sun_icrs is not None and abs(math.hypot(*self.sun_icrs) - 1.0) > 1e-3:
            raise ConfigError(f"must be a unit vector (norm 1 +- 1e-3), got {list(self.sun_icrs)!r}",
                              field="rendezvous.sun_icrs")

    @property
    def frames(self) -> int:
        """Frames per approach: t = 0, dt, ... <= duration_s."""
        return int(math.floor(self.duration_s / self.frame_interval_s + 1e-9)) + 1


# ============================================================================================ Sun, Earth, Moon (issue 23, point 1)
_ENV_EPOCH_MIN, _ENV_EPOCH_MAX = "1950-01-01T00:00:00", "2050-01-01T00:00:00"
_ENV_UNITS = {"altitude_km": "km", "inclination_deg": "deg", "earth_keepout_deg": "deg", "moon_keepout_deg": "deg",
              "sun_keepout_deg": "deg"}
_EnvTime = typing.Annotated[str, pydantic.Field(min_length=10, max_length=40)]


def _utc_seconds(text: str) -> float | None:
    """POSIX seconds of an ISO UTC time ("2025-03-01T12:00:00", "Z" or "+00:00" allowed), None if malformed."""
    try:
        t = datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        return None
    return (t if t.tzinfo is not None else t.replace(tzinfo=datetime.timezone.utc)).timestamp()


@dataclasses.dataclass(frozen=True)
class EnvironmentConfig:
    """Where and when each case of a star run with a target is (``[target.environment]``; issue 23, point 1;
    ``scene/case_environment.py``): an epoch and a position on a circular orbit per case, from which the Sun,
    Earth and Moon directions, their keep-out flags and the Earth's shadow follow (``scene/ephemeris.py``,
    ``scene/keepout.py``).  Every field's range is part of its type, checked when the dataclass is built
    (ConfigError naming ``target.environment.<field>``, the value and the range) and when a TOML table is validated.

    epoch_utc : [first, last] ISO UTC times ("2025-01-01T00:00:00"), first <= last, both within 1950-2050 (the
        low-precision ephemeris' span); each case's epoch uniform between them (default the year 2025).
    altitude_km : circular orbit altitude in [150, 40000] km (default 500); inclination_deg in [0, 180] (default
        97.4, Sun-synchronous at 500 km); each case a uniform right ascension of the node and argument of latitude.
    earth_keepout_deg : half-angle (deg) of the cone about the boresight that the Earth's limb must stay out of, in
        [0, 90] (default 20); moon_keepout_deg : the Moon's, in [0, 90] (default 10).  The Sun's is
        ``target.sun_keepout_deg``.  Defaults chosen as the usual order of small star trackers' exclusion angles,
        not a particular data sheet's.
    """

    epoch_utc: typing.Annotated[tuple[_EnvTime, _EnvTime], pydantic.Field(min_length=2, max_length=2)] = \
        ("2025-01-01T00:00:00", "2026-01-01T00:00:00")
    altitude_km: typing.Annotated[float, pydantic.Field(ge=150.0, le=40000.0)] = 500.0
    inclination_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=180.0)] = 97.4
    earth_keepout_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=90.0)] = 20.0
    moon_keepout_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=90.0)] = 10.0
    __pydantic_config__ = pydantic.ConfigDict(extra="forbid")      # a nested table: unknown keys refused too

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"target.environment.{name}"), _ENV_UNITS)
        lo, hi = _utc_seconds(_ENV_EPOCH_MIN), _utc_seconds(_ENV_EPOCH_MAX)
        sec = []
        for i, text in enumerate(self.epoch_utc):
            t = _utc_seconds(text)
            if t is None or not lo <= t <= hi:
                raise ConfigError(f"must be an ISO UTC time (YYYY-MM-DDTHH:MM:SS) within [{_ENV_EPOCH_MIN}, "
                                  f"{_ENV_EPOCH_MAX}], got {text!r}", field=f"target.environment.epoch_utc[{i}]")
            sec.append(t)
        if sec[0] > sec[1]:
            raise ConfigError(f"must be [first, last] with first <= last, got {list(self.epoch_utc)!r}",
                              field="target.environment.epoch_utc")

    @property
    def epoch_unix_s(self) -> tuple[float, float]:
        """(first, last) epochs as POSIX seconds (UTC)."""
        return _utc_seconds(self.epoch_utc[0]), _utc_seconds(self.epoch_utc[1])


# ============================================================================================ relative-navigation EKF (issue 23)
_FILTER_UNITS = {"accel_psd": "m^2/s^3", "dv_sigma_m_s": "m/s", "dv_sigma_frac": "of |dv|"}


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Noise settings of the relative-navigation EKF (``nav/relative_filter.py``; a rendezvous spec's filter comes
    from its ``RendezvousConfig``: ``jobs/kinds/rendezvous_filter.filter_config``).  Checked when built (ConfigError naming
    ``filter.<field>``, the value and the range).

    accel_psd : white acceleration noise spectral density per Hill axis, in [0, 1e-3] m^2/s^3 (1e-12 ~ 1 um/s^2
        over 1 s; default 1e-12).
    dv_sigma_frac : 1-sigma execution error of a manoeuvre per axis, as a fraction of |dv|, in [0, 1] (default 0).
    dv_sigma_m_s : 1-sigma execution error of a manoeuvre per axis, in [0, 1] m/s, added in quadrature (default 0).
    iterations : linearisations per measurement update, in [1, 20] (1: the EKF; more: the iterated EKF, which stays
        consistent when the first bearings meet a prior whose error across the line of sight is a large angle)."""

    accel_psd: typing.Annotated[float, pydantic.Field(ge=0.0, le=1e-3)] = 1e-12
    dv_sigma_frac: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 0.0
    dv_sigma_m_s: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 0.0
    iterations: typing.Annotated[int, pydantic.Field(ge=1, le=20)] = 1

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"filter.{name}"), _FILTER_UNITS)


@dataclasses.dataclass(frozen=True)
class ApproachEnvironmentConfig:
    """When a rendezvous approach happens and what its camera must not look at (``[rendezvous.environment]``;
    issue 23, point 1; ``jobs/kinds/rendezvous_truth.frame_view``): frame k is at ``epoch_utc`` + t_k on the reference
    orbit, the chaser beside the target; the Sun, Earth and Moon seen along its boresight and the Earth's shadow
    go into every frame's row (``scene/keepout.py``).

    epoch_utc : ISO UTC time of the first frame, within 1950-2050 (default "2025-03-20T12:00:00").
    sun_keepout_deg, earth_keepout_deg, moon_keepout_deg : half-angles (deg) of the keep-out cones about the
        boresight (the Earth's from its limb), each in [0, 90] (defaults 30, 20, 10: chosen, the usual order of
        small star trackers' exclusion angles, not a particular data sheet's).
    """

    epoch_utc: _EnvTime = "2025-03-20T12:00:00"
    sun_keepout_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=90.0)] = 30.0
    earth_keepout_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=90.0)] = 20.0
    moon_keepout_deg: typing.Annotated[float, pydantic.Field(ge=0.0, le=90.0)] = 10.0
    __pydantic_config__ = pydantic.ConfigDict(extra="forbid")      # a nested table: unknown keys refused too

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"rendezvous.environment.{name}"), _ENV_UNITS)
        t = _utc_seconds(self.epoch_utc)
        if t is None or not _utc_seconds(_ENV_EPOCH_MIN) <= t <= _utc_seconds(_ENV_EPOCH_MAX):
            raise ConfigError(f"must be an ISO UTC time (YYYY-MM-DDTHH:MM:SS) within [{_ENV_EPOCH_MIN}, "
                              f"{_ENV_EPOCH_MAX}], got {self.epoch_utc!r}", field="rendezvous.environment.epoch_utc")

    @property
    def epoch_unix_s(self) -> float:
        """The first frame's epoch as POSIX seconds (UTC)."""
        return _utc_seconds(self.epoch_utc)
