"""The ``hil_star`` job kind's spec: pydantic models (frozen, unknown keys refused) and their normalisation.

``settings`` keeps the tables of the stages' dataclasses (``StarCatalogConfig``, ``DetectConfig``,
``VotingConfig``) as plain tables, completed by :func:`normalise_settings` so that the canonical spec lists
every field; ``truths`` embeds the per-image truth resolved when the run is planned (jobs/kinds/hil_truth.py).
Layout and defaults: jobs/kinds/hil_star.py.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from dualsight.catalogs.auto_limit import HIL_TARGET_PER_FIELD, auto_mag_limit, is_auto
from dualsight.catalogs.stars import StarCatalogConfig
from dualsight.errors import ConfigError
from dualsight.config import dataclass_from_table, dataclass_to_table, validate
from dualsight.jobs.kinds.hil_common import Frozen, ImageEntry, fixed_point
from dualsight.jobs.kinds.hil_prox import TargetSpec
from dualsight.jobs.kinds.hil_star_track import TrackSpec
from dualsight.kernels.detect import DetectConfig
from dualsight.kernels.detect_local import LocalDetectConfig
from dualsight.nav.unknown_objects import UnknownConfig
from dualsight.nav.voting_config import VotingConfig
from dualsight.scene.camera import Camera
from dualsight.scene.units import ARCSEC

__all__ = ["METHODS", "MAX_VOTE_CELLS", "StarSettings", "Matched", "StarTruth", "HilStarSpec", "normalise_settings",
           "settings_from_table", "spec_from_dict", "normalise_run",
           "COMPILED_DETECT_MIN_IMAGES", "resolve_fit_engine"]

METHODS = ("robust", "paper")
MAX_VOTE_CELLS = 4_000_000
"""4M int64 cells = 32 MB per vote table chunk: with 15.6k catalog stars x 25 voters that is ten frames at
a time, and 1M candidate pairs per expansion (the default 250k would vote one frame at a time)."""
HIL_FIRST_STARS = 12
"""The robust method's cheaper first round in ``hil star`` (``VotingConfig.first_stars``): the 12 brightest
detections vote first (about a quarter of the 25-star round's work) and a frame whose answer fails
verification votes again with the 25 brightest, then widens.  On the 8 ESA frames every answer is the same
as with 25 voters; on rendered frames with as many false stars as true ones, 12 voters alone identify 85 %
against 94 % with 20, which the second round recovers (docs/measurements.md)."""
_METHOD_CONFIG = {"robust": lambda tol, **kw: VotingConfig.robust(tol, **{"first_stars": HIL_FIRST_STARS, **kw}),
                  "paper": VotingConfig.paper}


# ============================================================================================ spec
class StarSettings(Frozen):
    """Everything that decides how a frame is processed (tables: the dataclasses' fields)."""

    method: Literal["robust", "paper"] = "robust"
    compare: bool = True
    catalog: dict[str, Any] = Field(default_factory=dict)
    detector: Literal["local", "global"] = "local"                # kernels.detect_local / kernels.detect
    detect: dict[str, Any] = Field(default_factory=dict)              # DetectConfig (detector "global")
    detect_local: dict[str, Any] = Field(default_factory=dict)        # LocalDetectConfig (detector "local")
    centroid_floor_px: float | None = Field(default=0.1, ge=0, le=100)  # attitude weights; None = equal
    voting: dict[str, Any] = Field(default_factory=dict)
    alt_voting: dict[str, Any] | None = None
    background_block_px: int = 32
    max_obs: int = Field(default=100, ge=2, le=1000)
    batch_size: int = Field(default=16, ge=1, le=1024)
    limit_arcsec: float | None = Field(default=None, gt=0)
    unknown: dict[str, Any] = Field(default_factory=dict)             # UnknownConfig (nav/unknown_objects.py)

    @field_validator("background_block_px")
    @classmethod
    def _block(cls, v: int) -> int:
        if not (v == 0 or 4 <= v <= 4096):
            raise ValueError("must be 0 (off) or an integer in [4, 4096] px")
        return v

    @property
    def alt_method(self) -> str | None:
        return next(m for m in METHODS if m != self.method) if self.compare else None


def check_rotation(v):
    """A row-major 3x3 rotation matrix given as 9 numbers (None passes); ValueError otherwise."""
    if v is None:
        return v
    if len(v) != 9:
        raise ValueError(f"must be 9 numbers (a 3x3 rotation matrix, row-major), got {len(v)}")
    R = np.asarray(v, np.float64).reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("must be a 3x3 rotation matrix (row-major), orthonormal with determinant +1")
    return v


class Matched(Frozen):
    """A truth file's matched stars: centroids (px, from the top-left corner) and catalog positions."""

    row: tuple[float, ...]
    col: tuple[float, ...]
    ra_deg: tuple[float, ...]
    dec_deg: tuple[float, ...]
    mag: tuple[float, ...]

    @model_validator(mode="after")
    def _same_length(self):
        if len({len(self.row), len(self.col), len(self.ra_deg), len(self.dec_deg), len(self.mag)}) != 1:
            raise ValueError("row, col, ra_deg, dec_deg and mag must have one entry per star")
        return self

    def arrays(self) -> dict:
        return {k: np.asarray(getattr(self, k), np.float64) for k in ("row", "col", "ra_deg", "dec_deg", "mag")}


class StarTruth(Frozen):
    """Truth of one image (jobs/kinds/hil_truth.py resolves it when the run is planned)."""

    source: Literal["file", "altaz", "none"] = "none"
    A: tuple[float, ...] | None = None
    ra_deg: float | None = None
    dec_deg: float | None = None
    matched: Matched | None = None
    altaz_A: tuple[float, ...] | None = None
    note: str | None = Field(default=None, max_length=1000)

    @field_validator("A", "altaz_A")
    @classmethod
    def _check_rotation(cls, v):
        return check_rotation(v)

    @model_validator(mode="after")
    def _consistent(self):
        if (self.source == "none") != (self.A is None):
            raise ValueError("A (the truth attitude) is given exactly when source is 'file' or 'altaz'")
        return self

    def matrix(self, name: str = "A") -> np.ndarray | None:
        v = getattr(self, name)
        return None if v is None else np.asarray(v, np.float64).reshape(3, 3)


class HilStarSpec(Frozen):
    """A validated ``hil_star`` run (module docstring)."""

    camera: dict[str, Any]
    settings: StarSettings = Field(default_factory=StarSettings)
    images: tuple[ImageEntry, ...] = Field(min_length=1, max_length=10_000_000)
    truths: tuple[StarTruth, ...] = ()
    track: TrackSpec | None = None          # hil star --track (jobs/kinds/hil_star_track.py); absent: no tracking
    target: TargetSpec | None = None        # hil star --target (jobs/kinds/hil_star_objects.py): the satellite's shape
    target_near: tuple[Annotated[float, Field(ge=0.0, lt=360.0)], Annotated[float, Field(ge=-90.0, le=90.0)],
                       Annotated[float, Field(gt=0.0, le=180.0)]] | None = None
    """--target-near RA,DEC,RADIUS (deg): the target is the unknown object nearest that direction within RADIUS."""

    def to_dict(self) -> dict:
        """Canonical dict; ``track``, ``target`` and ``target_near`` only when set (runs without them keep their
        canonical form)."""
        d = super().to_dict()
        for k in ("track", "target", "target_near"):
            if d[k] is None:
                del d[k]
        return d

    def truth(self, k: int) -> StarTruth:
        return self.truths[k] if self.truths else _NO_TRUTH


_NO_TRUTH = StarTruth()


def normalise_settings(s: StarSettings, *, source: str, section: str | None = None,
                       mag_limit: float | str | None = 7.0, epoch_jyear: float = 2000.0, tolerance_arcsec: float = 20.0,
                       max_stars: int = 25, k_sigma: float = 5.0, min_pixels: int = 3,
                       camera: Camera | None = None) -> StarSettings:
    """Settings with every table complete: the tables' keys over bases made from the flags (the
    method's voting with ``tolerance_arcsec``, ``max_stars`` and :data:`MAX_VOTE_CELLS`).

    ``mag_limit`` (the flag) or the catalog table's ``mag_limit`` = "auto" (or None): the limit follows
    ``camera`` (:func:`dualsight.catalogs.auto_limit.auto_mag_limit` with
    :data:`~dualsight.catalogs.auto_limit.HIL_TARGET_PER_FIELD` stars per field), resolved to a number
    here; without a camera it stays "auto" until :func:`spec_from_dict` (which has the camera) resolves it,
    so a stored spec always holds the number.  The local detector's ``psf_sigma_stated_px`` defaults to the
    camera's ``psf_sigma_px`` (its camera file's calibrated PSF width; the table's number wins, its None does not)."""
    def sec(name):
        return f"{section}.{name}" if section else name

    def checked(make, name):
        try:
            return make()
        except ConfigError:
            raise
        except (ValueError, TypeError) as e:
            raise ConfigError(str(e), source=source, field=sec(name)) from None

    cat_table, deferred = dict(s.catalog), False
    if is_auto(cat_table.get("mag_limit", mag_limit)):             # "auto": a number from the camera's field
        cat_table.pop("mag_limit", None)
        deferred = camera is None
        mag_limit = 7.0 if deferred else auto_mag_limit(camera, target_per_field=HIL_TARGET_PER_FIELD)
    elif is_auto(mag_limit):
        mag_limit = 7.0                                              # the table's number wins
    catalog = dataclass_from_table(StarCatalogConfig, cat_table, source=source, section=sec("catalog"),
                                   base=checked(lambda: StarCatalogConfig(mag_limit=mag_limit,
                                                                          epoch_jyear=epoch_jyear), "catalog"))
    detect = dataclass_from_table(DetectConfig, s.detect, source=source, section=sec("detect"),
                                  base=checked(lambda: DetectConfig(k_sigma=k_sigma, min_pixels=min_pixels),
                                               "detect"))
    stated = None if camera is None else camera.psf_sigma_px      # the camera file's calibrated PSF width
    dl_table = dict(s.detect_local)
    if dl_table.get("psf_sigma_stated_px", None) is None:          # unset (or None: a table completed before the
        dl_table.pop("psf_sigma_stated_px", None)                   # camera was known) takes the camera's
    detect_local = dataclass_from_table(LocalDetectConfig, dl_table, source=source, section=sec("detect_local"),
                                        base=checked(lambda: LocalDetectConfig(k_sigma=max(k_sigma, 1.0),
                                                                               psf_sigma_stated_px=stated),
                                                     "detect_local"))
    common = dict(max_stars=max_stars, max_vote_cells=MAX_VOTE_CELLS)
    base = checked(lambda: _METHOD_CONFIG[s.method](tolerance_arcsec * ARCSEC, **common), "voting")
    voting = dataclass_from_table(VotingConfig, s.voting, source=source, section=sec("voting"), base=base)
    alt = None
    if s.compare:
        alt_base = checked(lambda: _METHOD_CONFIG[s.alt_method](voting.tolerance_rad, **common), "alt_voting")
        alt = dataclass_to_table(dataclass_from_table(VotingConfig, s.alt_voting, source=source,
                                                      section=sec("alt_voting"), base=alt_base))
    catalog = {**dataclass_to_table(catalog), **({"mag_limit": "auto"} if deferred else {})}
    unknown = dataclass_from_table(UnknownConfig, s.unknown, source=source, section=sec("unknown"))
    return s.model_copy(update={"catalog": catalog, "detect": dataclass_to_table(detect),
                                "unknown": dataclass_to_table(unknown),
                                "detect_local": dataclass_to_table(detect_local),
                                "voting": dataclass_to_table(voting), "alt_voting": alt})


def settings_from_table(table: dict | None, *, source: str = "hil star", method: str | None = None,
                        compare: bool = True, detector: str | None = None, background_block_px: int = 32,
                        max_obs: int = 100,
                        batch_size: int = 16, limit_arcsec: float | None = None, **bases) -> StarSettings:
    """Settings from command-line values and an optional TOML table (keys ``method``, ``compare``,
    ``background_block_px``, ``max_obs``, ``batch_size``, ``limit_arcsec``, ``detector``,
    ``centroid_floor_px`` and tables ``catalog``, ``detect``, ``detect_local``, ``voting``, ``alt_voting``); the
    table's values win.  ``bases``: see
    :func:`normalise_settings` (``mag_limit="auto"`` or None: from ``camera=``, else resolved by
    :func:`spec_from_dict`).  Errors name ``source`` and the key."""
    top = {"method": method or "robust", "compare": compare, "detector": detector or "local",
           "background_block_px": background_block_px, "max_obs": max_obs, "batch_size": batch_size,
           "limit_arcsec": limit_arcsec}
    top.update(table or {})
    return normalise_settings(validate(StarSettings, top, source=source), source=source, **bases)


def spec_from_dict(d: dict, source: str = "spec") -> HilStarSpec:
    """Validate a spec dict (module docstring); every error is a ConfigError naming ``source`` and the key."""
    if not isinstance(d, dict):
        raise ConfigError("must be a table", source=source)
    m = validate(HilStarSpec, d, source=source)
    if m.truths and len(m.truths) != len(m.images):
        raise ConfigError(f"must be empty or have one entry per image ({len(m.images)}), got {len(m.truths)}",
                          source=source, field="truths")
    if m.target_near is not None and m.target is None:
        raise ConfigError("goes with a target (--target SAT.toml)", source=source, field="target_near")
    if m.track is not None and len(m.track.times_utc) != len(m.images):
        raise ConfigError(f"must have one time per image ({len(m.images)}), got {len(m.track.times_utc)}",
                          source=source, field="track.times_utc")
    cam, settings = normalise_run(m.camera, m.settings, source=source, n_images=len(m.images))
    return m.model_copy(update={"camera": cam, "settings": settings})


COMPILED_DETECT_MIN_IMAGES = 1024
"""Images of a ``hil star`` run from which the local detector's "auto" engine is "taichi" (:func:`resolve_fit_engine`)."""


def resolve_fit_engine(settings: StarSettings, n_images: int) -> StarSettings:
    """``settings`` with the local detector's ``fit_engine`` "auto" resolved for a run of ``n_images`` images:
    "taichi" from :data:`COMPILED_DETECT_MIN_IMAGES` images, else "numpy" (an engine the user chose stays).

    The compiled passes save ~4 ms per ESA frame (10-11 instead of 15-16 ms end to end, one core) but starting
    Taichi and building them costs ~2 s per process (one-image ``hil star`` 1.4 s with numpy, 3.4 s compiled;
    ``benchmarks/bench_hil_speed.py``, 2026-11-27, load ~6), so they repay their start after ~500 frames per
    process: 1,024 images over the default two workers.  The two engines agree to ~1e-6 px, not bit for bit, so
    the choice is made here, once, and stored in the run's spec (its replay and resume run the same engine)."""
    dl = settings.detect_local
    if dl.get("fit_engine", "auto") != "auto":
        return settings
    engine = "taichi" if n_images >= COMPILED_DETECT_MIN_IMAGES else "numpy"
    return settings.model_copy(update={"detect_local": {**dl, "fit_engine": engine}})


def normalise_run(camera: dict, settings: StarSettings, *, source: str = "spec",
                  n_images: int | None = None) -> tuple[dict, StarSettings]:
    """The canonical camera table and settings of a run, as :func:`spec_from_dict` stores them: the camera
    table at its fixed point through :class:`~dualsight.scene.camera.Camera`, the settings completed for that
    camera (:func:`normalise_settings`) and, given the run's ``n_images``, the local detector's engine resolved
    (:func:`resolve_fit_engine`).  ``dualsight.solve`` normalises a frame's camera and settings with it."""
    cam = fixed_point(lambda c: Camera.from_dict(c, source=source).to_dict(), dict(camera))
    settings = normalise_settings(settings, source=source, section="settings",
                                  camera=Camera.from_dict(cam, source=source))
    return cam, settings if n_images is None else resolve_fit_engine(settings, n_images)
