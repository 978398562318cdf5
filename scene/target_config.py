"""A spacecraft in the star tracker's field (``[target]`` of a star spec; issue 23): :class:`TargetConfig`, read by
``scene/target_in_field.py`` and the star job, validated by ``dualsight/config.py``."""

from __future__ import annotations

import dataclasses
import math
import typing

import pydantic

from dualsight.config import check_fields
from dualsight.errors import ConfigError
from dualsight.scene.environment_config import EnvironmentConfig


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
