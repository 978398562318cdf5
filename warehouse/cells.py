"""How a report prints one number: by what its column measures (issue 25, point 10).

Every text and HTML table of the reports passes its cells through :func:`cell` with the column's name, so that the
same kind of number reads the same everywhere and no cell shows a raw float (``0.123456789``) or a time as
``1.796e+09``.  Rules, from the column name (SQL names such as ``mean_err_x_arcsec`` or printed headers such as
``bore err "``):

======================================  =====================================================================
column                                  printed as
======================================  =====================================================================
``*_rate``, ``share``, ``sky_share_*``  a fraction, printed as percent with one decimal (``0.955`` -> ``95.5 %``)
``*_pct``, ``%``                        already percent: one decimal
``arcsec``, ``"``                       arcseconds: two decimals below 10, one above (``0.87``, ``56.3``)
``ms``                                  milliseconds: whole above 100, one decimal above 1, else two significant
``px``                                  pixels: two decimals
``deg``                                 degrees: four decimals
``_m``, `` m``                          metres: three significant digits or whole metres above 1000
``s``, ``elapsed``, ``_s``              seconds: three decimals below 1, two below 10, one below 100, else whole
``unix``                                seconds since 1970: ISO 8601 UTC (``2026-11-27T12:33:05Z``)
anything else (float)                   four significant digits; thousands separators from 1e4 (never an
                                        exponent there); below 0.01 two significant digits with an exponent
======================================  =====================================================================

Integers, strings, booleans print as they are; None and NaN as ``-``.  Pure functions of (name, value).
"""

from __future__ import annotations

import datetime as _dt
import math
import re

__all__ = ["cell", "percent", "iso_utc", "row_cells", "table_cells", "formatted", "verdict"]


def percent(fraction, nd: int = 1) -> str:
    """``fraction`` (0..1) as percent with ``nd`` decimals (``0.955`` -> ``95.5 %``); None/NaN -> ``-``."""
    if fraction is None or (isinstance(fraction, float) and math.isnan(fraction)):
        return "-"
    return f"{100.0 * float(fraction):.{nd}f} %"


def formatted(v, fmt: str = "{:.3f}") -> str:
    """``v`` through ``fmt``; None -> ``-`` (a report's cell whose format the report chooses)."""
    return "-" if v is None else fmt.format(v)


def verdict(ok) -> str:
    """A target's verdict cell: ``met``, ``NOT met``, or ``-`` when it could not be judged (None)."""
    return "-" if ok is None else ("met" if ok else "NOT met")


def iso_utc(seconds) -> str:
    """Unix time (s) as ISO 8601 UTC to the second (``2026-11-27T12:33:05Z``); None -> ``-``."""
    if seconds is None:
        return "-"
    return _dt.datetime.fromtimestamp(float(seconds), tz=_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _general(v: float) -> str:
    a = abs(v)
    if a >= 1e4:
        return f"{v:,.0f}"
    if 0 < a < 0.01:
        return f"{v:.2e}"          # a small probability or residual: its size matters, not its sixth decimal
    return f"{v:.4g}"


def _seconds(v: float) -> str:
    a = abs(v)
    return f"{v:.3f}" if a < 1 else f"{v:.2f}" if a < 10 else f"{v:.1f}" if a < 100 else f"{v:,.0f}"


def _ms(v: float) -> str:
    a = abs(v)
    if a >= 100:
        return f"{v:.0f}"
    if a >= 1:
        return f"{v:.1f}"
    return f"{v:.2g}" if a >= 1e-3 else f"{v:.3f}"


def _arcsec(v: float) -> str:
    return f"{v:.2f}" if abs(v) < 10 else f"{v:.1f}"


def _metres(v: float) -> str:
    return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}" if abs(v) >= 1 else f"{v:.3f}"


_WORD = re.compile(r"[a-z%\"]+")


def _kind(name: str) -> str:
    n = str(name).lower()
    words = set(_WORD.findall(n.replace("_", " ")))
    if "unix" in words or n.startswith("started"):
        return "time"
    if n.endswith("_pct") or "%" in n or "pct" in words or "percent" in words:
        return "pct"
    if n.endswith("rate") or "share" in words or n.startswith("sky_share") or "fraction" in words:
        return "rate"
    if "arcsec" in words or '"' in n:
        return "arcsec"
    if "ms" in words or n.endswith("_ms") or "ms/image" in n or "ms_per" in n:
        return "ms"
    if words & {"s", "seconds", "elapsed"} or n.endswith("_s"):
        return "s"
    if "px" in words:
        return "px"
    if "deg" in words:
        return "deg"
    if n.endswith("_m") or " m" in f" {n} " or words & {"m"}:
        return "m"
    return "float"


def cell(name: str, v) -> str:
    """The printed form of value ``v`` in the column named ``name`` (rules: the module's table)."""
    if v is None:
        return "-"
    if isinstance(v, bool) or isinstance(v, str):
        return str(v)
    if isinstance(v, int):
        if _kind(name) == "time":
            return iso_utc(v)
        return str(v)
    if not isinstance(v, float):
        try:
            v = float(v)                       # numpy / Decimal scalars
        except (TypeError, ValueError):
            return str(v)
    if math.isnan(v):
        return "-"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    k = _kind(name)
    if k == "time":
        return iso_utc(v)
    if k == "rate":
        return percent(v)
    if k == "pct":
        return f"{v:.1f}"
    if k == "arcsec":
        return _arcsec(v)
    if k == "ms":
        return _ms(v)
    if k == "s":
        return _seconds(v)
    if k == "px":
        return f"{v:.2f}"
    if k == "deg":
        return f"{v:.4f}"
    if k == "m":
        return _metres(v)
    return _general(v)


def row_cells(cols, row) -> list[str]:
    """One row's cells, each by its column's rule."""
    return [cell(c, v) for c, v in zip(cols, row)]


def table_cells(cols, rows) -> list[list[str]]:
    """Every row's cells (see :func:`row_cells`)."""
    return [row_cells(cols, r) for r in rows]
