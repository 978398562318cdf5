"""Observation times of real images as catalog epochs (Julian years).

The star catalog's positions are moved by proper motion to the images' epoch: HIP 114622 (V 5.5) moves
50 arcsec between J2000 and the ESA tetra3 frames (2019.6), more than the 40 arcsec re-identification
radius of the robust voting.
"""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from dualsight.errors import ConfigError, InputError
from dualsight.scene.skytruth import altaz_from_filename

__all__ = ["julian_year", "observation_epoch"]


def julian_year(time_utc: str) -> float:
    """Julian epoch (J2000.0 + days / 365.25) of an ISO UTC time such as "2019-07-29T20:47:26" (UTC ~ TT
    to a minute, immaterial for proper motion).  InputError (``--time``) for a malformed time."""
    try:
        t = datetime.fromisoformat(str(time_utc).replace("Z", "+00:00"))
    except ValueError:
        raise InputError(f"not an ISO time (YYYY-MM-DDTHH:MM:SS): {time_utc!r}", source="--time") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    jd = t.timestamp() / 86400.0 + 2440587.5
    return 2000.0 + (jd - 2451545.0) / 365.25


def observation_epoch(paths, time_utc: str | None = None) -> float | None:
    """Catalog epoch for a set of images: the Julian year of ``time_utc`` if given, else the median
    of the times in the file names (``scene.skytruth.altaz_from_filename``) when every name has one;
    rounded to 0.1 yr (proper motions reach ~1 arcsec/yr for a few V < 7 stars, so 0.05 yr is
    negligible, and the catalog cache is reused).  None when the time is unknown.
    """
    if time_utc is not None:
        return round(julian_year(time_utc), 1)
    years = []
    for p in paths:
        try:
            years.append(julian_year(altaz_from_filename(Path(p))[0]))
        except (ConfigError, InputError):
            return None
    return round(float(np.median(years)), 1) if years else None
