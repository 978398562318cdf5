"""Where and when a case happens, for the Sun, Earth and Moon (issue 23, point 1): ``[target.environment]`` of a
star run (:class:`EnvironmentConfig`, ``scene/case_environment.py``) and ``[rendezvous.environment]`` of an
approach (:class:`ApproachEnvironmentConfig`, ``jobs/kinds/rendezvous_truth.frame_view``); the ISO UTC epochs
both take (:func:`utc_seconds`, within :data:`EPOCH_MIN` - :data:`EPOCH_MAX`: the low-precision ephemeris' span)."""

from __future__ import annotations

import dataclasses
import datetime
import typing

import pydantic

from dualsight.config import check_fields
from dualsight.errors import ConfigError


EPOCH_MIN, EPOCH_MAX = "1950-01-01T00:00:00", "2050-01-01T00:00:00"
ENV_UNITS = {"altitude_km": "km", "inclination_deg": "deg", "earth_keepout_deg": "deg", "moon_keepout_deg": "deg",
              "sun_keepout_deg": "deg"}
_EnvTime = typing.Annotated[str, pydantic.Field(min_length=10, max_length=40)]
_Keepout = typing.Annotated[float, pydantic.Field(ge=0.0, le=90.0)]      # a keep-out half-angle, deg


def utc_seconds(text: str) -> float | None:
    """POSIX seconds of an ISO UTC time ("2025-03-01T12:00:00", "Z" or "+00:00" allowed), None if malformed."""
    try:
        t = datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        return None
    return (t if t.tzinfo is not None else t.replace(tzinfo=datetime.timezone.utc)).timestamp()



def epoch_seconds(text: str, field: str) -> float:
    """POSIX seconds of an epoch ``text`` (:func:`utc_seconds`) that must lie within [:data:`EPOCH_MIN`,
    :data:`EPOCH_MAX`]; else ConfigError naming ``field``."""
    t = utc_seconds(text)
    if t is None or not utc_seconds(EPOCH_MIN) <= t <= utc_seconds(EPOCH_MAX):
        raise ConfigError(f"must be an ISO UTC time (YYYY-MM-DDTHH:MM:SS) within [{EPOCH_MIN}, {EPOCH_MAX}], got "
                          f"{text!r}", field=field)
    return t

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
    earth_keepout_deg: _Keepout = 20.0
    moon_keepout_deg: _Keepout = 10.0
    __pydantic_config__ = pydantic.ConfigDict(extra="forbid")      # a nested table: unknown keys refused too

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"target.environment.{name}"), ENV_UNITS)
        sec = [epoch_seconds(text, f"target.environment.epoch_utc[{i}]") for i, text in enumerate(self.epoch_utc)]
        if sec[0] > sec[1]:
            raise ConfigError(f"must be [first, last] with first <= last, got {list(self.epoch_utc)!r}",
                              field="target.environment.epoch_utc")

    @property
    def epoch_unix_s(self) -> tuple[float, float]:
        """(first, last) epochs as POSIX seconds (UTC)."""
        return utc_seconds(self.epoch_utc[0]), utc_seconds(self.epoch_utc[1])


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
    sun_keepout_deg: _Keepout = 30.0
    earth_keepout_deg: _Keepout = 20.0
    moon_keepout_deg: _Keepout = 10.0
    __pydantic_config__ = pydantic.ConfigDict(extra="forbid")      # a nested table: unknown keys refused too

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"rendezvous.environment.{name}"), ENV_UNITS)
        epoch_seconds(self.epoch_utc, "rendezvous.environment.epoch_utc")

    @property
    def epoch_unix_s(self) -> float:
        """The first frame's epoch as POSIX seconds (UTC)."""
        return utc_seconds(self.epoch_utc)
