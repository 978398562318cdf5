"""The options of star tracking over an image sequence (``[tracking]``; issue 22): :class:`TrackingConfig`, read by
``nav/tracking.py`` and ``nav/sequence.py``, validated by ``dualsight/config.py``."""

from __future__ import annotations

import dataclasses
import math
import typing

import pydantic

from dualsight.config import check_fields
from dualsight.errors import ConfigError


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
