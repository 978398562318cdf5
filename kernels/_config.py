"""Validation helpers of the kernels' frozen config dataclasses: one-line errors naming the field and its
allowed range (DESIGN.md: bad input gets a one-line error)."""

import math


def is_finite_number(v) -> bool:
    """True for a finite int or float (bool excluded)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def is_int(v) -> bool:
    """True for an int (bool excluded)."""
    return isinstance(v, int) and not isinstance(v, bool)


def reject(cfg, name: str, allowed: str):
    """Raise ``ValueError("<Class>.<name> must be <allowed>, got <value>")``."""
    raise ValueError(f"{type(cfg).__name__}.{name} must be {allowed}, got {getattr(cfg, name)!r}")
