"""Star tracking over image sequences: the ``star_track`` job kind (issue 22, point 1; orchestration only).

    draw a sequence (here, from default_rng([seed, i])): initial attitude, trajectory (scene.attitude_trajectory:
    constant rate, eigenaxis slew, jitter: a sinusoid and/or a given spectrum), gyro readings, events -> stars in the field of every frame
    (scene.starfield_geometry) -> render and detect each frame with the star job's chain (jobs.kinds.star:
    render_and_detect, smeared by the frame's true body rate) -> the tracker's state machine over the frames
    (nav.sequence: lost-in-space, tracking, fallback, rates) -> errors per axis (nav.errors) -> Arrow rows

One case is one sequence: one row per frame in ``star_frames`` and one row per sequence in ``star_sequences`` (the
primary dataset; :mod:`dualsight.jobs.kinds.star_track_tables`).  Case ``i`` draws everything from
``default_rng([seed, i])`` only, so a sequence never depends on its shard.

Spec (TOML): the star job's layout and presets (``ideal``, ``paper``, ``realistic``: camera, catalog, sensor,
detect, voting, robust; :mod:`dualsight.jobs.kinds.star`) plus::

    [sequence]   ... (SequenceConfig below: frames, fps, exposure_s, motion, rate_max_deg_s, ...)
    [tracking]   ... (nav/tracking_config.py TrackingConfig: windows, lock rules)

Lost-in-space is the star job's robust method (``[robust]``: its chance-match probability verifies a fix), or its
reference method with ``compare_robust = false``.  The sequence's exposure replaces the sensor's.

Smear: the renderer takes one body rate per call (``SensorConfig.rate_deg_s``), so frames are rendered in groups of
equal true rate (a constant-rate sequence: one group; a slew or jitter: one frame per call), each smeared by its
own instantaneous rate over the exposure (a straight chord, ``kernels/psf_models.py``).
"""

from __future__ import annotations

import typing
import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import pydantic
import numpy as np
import pyarrow as pa

from dualsight.config import check_fields
from dualsight.errors import ConfigError
from dualsight.config import dataclass_from_table, dataclass_to_table
from dualsight.nav.tracking_config import TrackingConfig
from dualsight.errors import InputError
from dualsight.jobs.engine.runner import prepare, run_job
from dualsight.jobs.engine.specs import preset_and_config, seed_and_case_count
from dualsight.jobs.kinds import star
from dualsight.jobs.kinds.star_track_tables import FRAMES_SCHEMA, SEQUENCES_SCHEMA, frames_table, sequence_row
from dualsight.kernels.digest import to_int64
from dualsight.kernels.sensor_config import flux_from_magnitude
from dualsight.nav.errors import axis_errors, total_error_angle
from dualsight.nav.focal_refine import FocalFuser
from dualsight.nav.sequence import NO_FIX, run_sequence
from dualsight.scene.attitude import euler123_to_dcm
from dualsight.nav.resolved_blobs import excluded_blobs
from dualsight.scene.attitude import unit_to_radec
from dualsight.scene.attitude_trajectory import (BLANK, BLINDED, CROSSING, DROPPED, NORMAL, add_jitter, constant_rate,
                                                 crossing_paths, eigenaxis_slew, gyro_rates, jitter_from_psd_table,
                                                 sinusoid_jitter)
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.starfield_geometry import FieldStars, stars_in_field
from dualsight.scene.units import ARCSEC, DEG


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

NAME = "star_track"
PRIMARY = "star_sequences"
MAX_SHARD_CASES = 25
"""A sequence (50 frames of the realistic sensor) takes 1-3 s on a core: 25 per shard keep a shard, the progress
bar's step and the work a killed worker loses, near a minute (``jobs/engine/runner.default_shard_size``)."""
SCHEMAS = {"star_sequences": SEQUENCES_SCHEMA, "star_frames": FRAMES_SCHEMA}
DEFAULT_CASES = 100

PRESETS = {name: {**star.PRESETS[name], "cases": DEFAULT_CASES, "sequence": {}, "tracking": {}}
           for name in ("ideal", "paper", "realistic")}
"""The star job's presets (camera, catalog, sensor, detection, voting) with the default sequence and tracking."""


@dataclass(frozen=True)
class StarTrackSpec:
    """A validated star-tracking campaign: the star job's spec (its sensor's exposure = the sequence's), the
    sequence and the tracking options."""

    star: star.StarSpec
    sequence: SequenceConfig
    tracking: TrackingConfig

    @property
    def seed(self) -> int:
        return self.star.seed

    def to_dict(self) -> dict:
        return {**self.star.to_dict(), "sequence": dataclass_to_table(self.sequence),
                "tracking": dataclass_to_table(self.tracking)}


def spec_from_dict(d: dict, source: str = "spec") -> StarTrackSpec:
    """Validate a spec dict (TOML layout); every error names ``source`` and the key."""
    if not isinstance(d, dict):
        raise InputError("a star-track spec must be a table", source=source)
    seq = dataclass_from_table(SequenceConfig, d.get("sequence"), source=source, section="sequence")
    trk = dataclass_from_table(TrackingConfig, d.get("tracking"), source=source, section="tracking")
    sp = star.spec_from_dict({k: v for k, v in d.items() if k not in ("sequence", "tracking")}, source=source)
    sp = dataclasses.replace(sp, sensor=dataclasses.replace(sp.sensor, exposure_s=seq.exposure_s))
    return StarTrackSpec(sp, seq, trk)


def resolve_spec(preset: str | None, config, *, seed: int | None = None, cases: int | None = None) -> tuple[dict, int]:
    """The preset (default paper), the ``--config`` TOML over it and the flags, validated: (canonical spec dict,
    number of cases)."""
    d, source = preset_and_config(PRESETS, preset, config)
    n = seed_and_case_count(d, seed, cases, DEFAULT_CASES, source)
    spec = spec_from_dict(d, source=source)
    return spec.to_dict(), int(n)


@dataclass(frozen=True)
class StarTrackRun:
    """A star-tracking campaign resolved and identified but not yet run (:func:`plan_run`, :func:`start_run`)."""

    spec: dict
    n_cases: int
    run_id: str
    spec_hash: str
    source: str


def plan_run(preset: str | None = None, config: Path | str | dict | None = None, *, seed: int | None = None,
             cases: int | None = None, run_id: str | None = None) -> StarTrackRun:
    """Everything ``dualsight star track`` decides before the lake is touched: the spec, the run's identity and
    its id (default ``star_track-<seed>-<cases>-<first 8 digits of the spec hash>``)."""
    spec_dict, n = resolve_spec(preset, config, seed=seed, cases=cases)
    source = (("config table" if isinstance(config, dict) else str(config)) if config is not None
              else f"preset {preset or 'paper'}")
    _, _, _, h = prepare(NAME, spec_dict, n, source=source)
    return StarTrackRun(spec_dict, n, run_id or f"star_track-{spec_dict['seed']}-{n}-{h[:8]}", h, source)


def start_run(plan: StarTrackRun, lake, *, workers: int | None = None, scheduler: str | None = None,
              shard_size: int | None = None, progress: bool = True) -> dict:
    """Run (or resume) a planned campaign into ``lake`` with the engine's ``run_job``; returns the manifest."""
    return run_job(NAME, plan.spec, n_cases=plan.n_cases, lake=lake, run_id=plan.run_id, workers=workers,
                   scheduler=scheduler, shard_size=shard_size, progress=progress, label=f"star track {plan.run_id}")


def make_context(spec: StarTrackSpec) -> star.StarContext:
    """The star job's context; with bright crossings also the most pixels a star's blob may have (the crossing
    object's larger blob is kept out of tracking and lost-in-space: ``nav/resolved_blobs.py``)."""
    ctx = star.make_context(spec.star)
    if spec.sequence.bright_crossings and ctx.star_blob_limit is None:
        ctx = dataclasses.replace(ctx, star_blob_limit=star.brightest_star_blob_limit(
            spec.star, float(np.min(ctx.catalog.vmag)), ctx.psf))
    return ctx


def truth_camera(spec: StarTrackSpec):
    """The camera the frames are rendered with: the spec's, its focal length times ``1 + true_focal_error``."""
    e = spec.sequence.true_focal_error
    cam = spec.star.camera
    return cam if e == 0 else dataclasses.replace(cam, fx=cam.fx * (1.0 + e), fy=cam.fy * (1.0 + e))


def frame_sensor(spec: StarTrackSpec, draw: dict, k: int, rates_deg_s: np.ndarray):
    """The sensor frame ``k`` is rendered with: the spec's, smeared by the frame's true rate ``rates_deg_s[k]``
    (deg/s), the background at twice the full well on a blinded frame, and on a crossing frame the bright objects
    at their positions of that frame (``draw["crossing_*"]``)."""
    seq = spec.sequence
    sensor = dataclasses.replace(spec.star.sensor, rate_deg_s=tuple(float(v) for v in rates_deg_s[k]))
    ev = int(draw["events"][k])
    if ev == BLINDED:                       # the Sun or the Earth in the field: the background saturates
        sensor = dataclasses.replace(sensor, sky_background_e=2.0 * sensor.full_well_e)
    elif ev == CROSSING:
        on = np.flatnonzero(draw["crossing_frame"] == k)
        rd = draw["crossing_radec_deg"][on]
        sensor = dataclasses.replace(sensor, bright_objects=tuple(
            {"ra_deg": float(r % 360.0), "dec_deg": float(d), "vmag": float(seq.crossing_vmag),
             "radius_px": float(seq.crossing_radius_px)} for r, d in rd))
    return sensor


def memory_estimate(spec: StarTrackSpec) -> int:
    """The star job's estimate (frames are rendered at most ``batch_size`` at a time)."""
    return star.memory_estimate(spec.star)


# ------------------------------------------------------------------------------------------ one sequence
def draw_sequence(spec: StarTrackSpec, case_id: int) -> dict:
    """Truth of sequence ``case_id`` from ``default_rng([seed, case_id])`` alone.

    Returns dict: t (T,) s; A_true (T, 3, 3); omega (T, 3) rad/s true body rate; events (T,) int8
    (``scene.attitude_trajectory.EVENT_NAMES``); gyro (T, 3) rad/s or None; motion str; rate_deg_s (peak rate);
    noise_seeds (T,) uint64 per-frame sensor seeds; crossing_frame (C,), crossing_xy (C, 2) px (true camera),
    crossing_radec_deg (C, 2): the bright crossing objects (``scene.attitude_trajectory.crossing_paths``; a frame
    keeps another event it has, and then shows no object).  Draw order: 3 Euler angles, motion choice, axis (3 normals),
    rate or slew angle and start, jitter phases (the sinusoid's, then the PSD's ``PSD_BINS`` per axis when
    set), gyro bias and noise, event frames, noise seeds, crossings (when set).
    """
    seq = spec.sequence
    rng = np.random.default_rng([spec.seed, int(case_id)])
    T = seq.frames
    t = np.arange(T) / seq.fps
    A0 = euler123_to_dcm(rng.uniform(-np.pi, np.pi, 3)[None])[0]
    motion = seq.motion if seq.motion != "mixed" else ("constant" if rng.random() < 0.5 else "slew")
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if motion == "constant":
        rate = rng.uniform(0.0, seq.rate_max_deg_s)
        A, omega = constant_rate(t, A0, axis * rate * DEG)
    else:
        angle = rng.uniform(0.0, seq.slew_angle_max_deg) * DEG
        t0 = rng.uniform(0.0, t[-1] / 3.0)
        A1 = frame_rotation(axis * angle) @ A0
        if seq.rate_max_deg_s > 0:
            A, omega = eigenaxis_slew(t, A0, A1, seq.rate_max_deg_s * DEG, seq.slew_accel_deg_s2 * DEG, t0)
        else:
            A, omega = constant_rate(t, A0, np.zeros(3))
        rate = min(seq.rate_max_deg_s, math.degrees(math.sqrt(angle * seq.slew_accel_deg_s2 * DEG)))
    if seq.jitter_arcsec > 0:
        d, dd = sinusoid_jitter(t, np.array([seq.jitter_freq_hz]), np.full((1, 3), seq.jitter_arcsec * ARCSEC), rng)
        A, omega = add_jitter(A, omega, d, dd)
    if seq.jitter_psd_freq_hz:            # a jitter of a given spectrum (rad^2/Hz per camera axis)
        S = np.outer(seq.jitter_psd_arcsec2_hz, seq.jitter_psd_axes) * ARCSEC ** 2
        d, dd = jitter_from_psd_table(t, np.array(seq.jitter_psd_freq_hz), S, rng)
        A, omega = add_jitter(A, omega, d, dd)
    gyro = None
    if seq.gyro:
        bias = rng.normal(size=3) * seq.gyro_bias_deg_s * DEG
        gyro, _ = gyro_rates(omega, 1.0 / seq.fps, rng, bias=bias, noise_rad_s=seq.gyro_noise_deg_s * DEG)
    events = np.zeros(T, np.int8)
    n_ev = seq.blank + seq.blinded + seq.dropped
    if n_ev:
        where = rng.choice(np.arange(1, T), size=n_ev, replace=False)
        events[where] = np.repeat(np.array([BLANK, BLINDED, DROPPED], np.int8), [seq.blank, seq.blinded, seq.dropped])
    noise = rng.integers(0, 2**63 - 1, size=T, dtype=np.int64).astype(np.uint64)
    cam = truth_camera(spec)
    cf, cxy, _ = crossing_paths(T, seq.bright_crossings, seq.crossing_frames, cam.width, cam.height, rng)
    u = np.einsum("cji,cj->ci", A[cf], cam.backproject(cxy)) if cf.size else np.zeros((0, 3))   # A^T: to ICRS
    ra, dec = unit_to_radec(u) if cf.size else (np.zeros(0), np.zeros(0))
    events[cf[events[cf] == NORMAL]] = CROSSING
    return {"t": t, "A_true": A, "omega": omega, "events": events, "gyro": gyro, "motion": motion,
            "rate_deg_s": float(rate), "noise_seeds": noise, "crossing_frame": cf, "crossing_xy": cxy,
            "crossing_radec_deg": np.degrees(np.stack([ra, dec], axis=1)) if cf.size else np.zeros((0, 2))}


def _take(f: FieldStars, idx: np.ndarray) -> FieldStars:
    return FieldStars(*(getattr(f, k.name)[idx] for k in dataclasses.fields(FieldStars)))


def render_sequence(spec: StarTrackSpec, ctx: star.StarContext, draw: dict) -> dict:
    """Render and detect every delivered frame of one sequence (the star job's ``render_and_detect``), in groups of
    at most ``batch_size`` frames of one event kind and one true body rate (the smear).

    Frames are rendered with :func:`truth_camera` and :func:`frame_sensor`.  On a frame with bright objects the
    blobs larger than any star's (``ctx.star_blob_limit``, :func:`make_context`) are dropped before tracking.
    Returns dict: xy (K, 2), sigma_px (K,) or None, offsets (T + 1,), n_generated (T,), digest (T,) int64 (0 for
    dropped frames), t_render_ns, t_detect_ns (T,) int64 (the group's time shared equally; -1 where none),
    n_excluded (T,) int32 blobs dropped as no star's.
    """
    sp, seq = spec.star, spec.sequence
    cat = ctx.catalog
    T = seq.frames
    ev = draw["events"]
    rates = np.degrees(draw["omega"]) if seq.smear else np.zeros((T, 3))
    s_max = dataclasses.replace(sp.sensor, rate_deg_s=tuple(float(v) for v in rates[np.argmax(
        np.linalg.norm(rates, axis=1))])) if seq.smear else sp.sensor
    flux = flux_from_magnitude(cat.vmag.astype(np.float64), sp.sensor)
    cam = truth_camera(spec)
    field = stars_in_field(draw["A_true"], cat.unit, flux, cam, star.psf_margin_px(s_max, cam, ctx.psf))
    blank = ev == BLANK
    field = dataclasses.replace(field, valid=field.valid & ~blank[:, None]) if blank.any() else field
    per_frame = [None] * T
    sig_frame = [None] * T
    digest = np.zeros(T, np.int64)
    t_r, t_d = np.full(T, -1, np.int64), np.full(T, -1, np.int64)
    alone = np.where(ev == CROSSING, np.arange(T), -1)          # a crossing frame is rendered alone (its objects)
    keys = np.concatenate([ev[:, None].astype(np.float64), rates, alone[:, None]], axis=1)
    todo = np.flatnonzero(ev != DROPPED)
    _, group = np.unique(keys[todo], axis=0, return_inverse=True)
    has_sigma = False
    n_excl = np.zeros(T, np.int32)
    for g in range(int(group.max()) + 1 if todo.size else 0):
        frames = todo[group.reshape(-1) == g]
        sensor = frame_sensor(spec, draw, int(frames[0]), rates)
        for s in range(0, len(frames), sp.batch_size):
            fr = frames[s: s + sp.batch_size]
            r = star.render_and_detect(_take(field, fr), draw["noise_seeds"][fr], cam, sensor, sp.detect,
                                       attitude=draw["A_true"][fr], detector=sp.detector, psf=ctx.psf)
            det = r.detections
            if ctx.star_blob_limit is not None and sensor.bright_objects:   # blobs no star can make: out
                det = _without(det, excluded_blobs(det.npix, ctx.star_blob_limit))
                n_excl[fr] = np.asarray(r.detections.offsets[1:] - r.detections.offsets[:-1]
                                        - (det.offsets[1:] - det.offsets[:-1]), np.int32)
            t_r[fr] = r.t_render_ns // len(fr)
            if r.t_detect_ns is not None:
                t_d[fr] = r.t_detect_ns // len(fr)
            digest[fr] = to_int64(r.digest) if r.digest is not None else 0
            for j, k in enumerate(fr):
                a, b = int(det.offsets[j]), int(det.offsets[j + 1])
                per_frame[k] = np.stack([det.x[a:b], det.y[a:b]], axis=1)
                if det.sigma_px is not None:
                    has_sigma = True
                    sig_frame[k] = np.asarray(det.sigma_px[a:b], np.float64)
    counts = np.array([0 if p is None else len(p) for p in per_frame], np.int64)
    off = np.concatenate([[0], np.cumsum(counts)])
    xy = np.concatenate([p for p in per_frame if p is not None] or [np.zeros((0, 2))])
    sigma = None
    if has_sigma:
        sigma = np.concatenate([s if s is not None else np.full(c, np.nan) for s, c in zip(sig_frame, counts)]
                               or [np.zeros(0)])
        # the star job's weights: the detector's Cramér-Rao bound with a 0.02 px floor for the PSF model's error
        sigma = np.sqrt(sigma ** 2 + 0.02 ** 2)
    return {"xy": xy, "sigma_px": sigma, "offsets": off, "n_generated": np.asarray(field.n_generated, np.int32),
            "digest": digest, "t_render_ns": t_r, "t_detect_ns": t_d, "n_excluded": n_excl}


def _without(det, drop: np.ndarray):
    """``det`` (``kernels.detect.Detections``) without the blobs ``drop`` (K,) bool, its ragged layout kept."""
    keep = ~np.asarray(drop, bool)
    if keep.all():
        return det
    per = {f.name: (getattr(det, f.name)[keep] if f.name in ("case", "x", "y", "flux", "npix", "sigma_px",
                                                             "saturated") and getattr(det, f.name) is not None
                    else getattr(det, f.name)) for f in dataclasses.fields(det)}
    B = len(det.offsets) - 1
    per["offsets"] = np.concatenate([[0], np.cumsum(np.bincount(det.case[keep], minlength=B))]).astype(np.int64)
    return dataclasses.replace(det, **per)


def compute_sequence(spec: StarTrackSpec, ctx: star.StarContext, case_id: int, keep_predictions: bool = False) -> dict:
    """Draw, render, track and score one sequence; returns dict(draw, rendered, result, err (T, 3) rad,
    total_err (T,) rad, valid (T,), within (T,), t_sample_ns, focal (the ``nav.focal_refine.FocalFuser`` with
    ``refine_focal``, else None), frames table, sequence row).  keep_predictions: the result keeps every tracked
    frame's prediction (``SequenceResult.predictions``, for replay)."""
    seq, sp = spec.sequence, spec.star
    c0 = time.perf_counter_ns()
    draw = draw_sequence(spec, case_id)
    t_sample = time.perf_counter_ns() - c0
    r = render_sequence(spec, ctx, draw)
    cat = ctx.catalog
    voting = sp.robust if sp.robust is not None else sp.voting
    focal = FocalFuser(sp.camera, seq.frames) if seq.refine_focal else None
    res = run_sequence(draw["t"], r["xy"], r["sigma_px"], r["offsets"], sp.camera, cat.unit, ctx.index, voting,
                       spec.tracking, available=draw["events"] != DROPPED, gyro=draw["gyro"],
                       gyro_sigma_rad_s=math.hypot(seq.gyro_noise_deg_s, seq.gyro_bias_deg_s) * DEG,
                       cat_vmag=cat.vmag, max_coast_frames=seq.max_coast_frames, lis_min_stars=seq.lis_min_stars,
                       shadow_lis=seq.shadow_lost_in_space, focal=focal, exposure_s=sp.sensor.exposure_s,
                       keep_predictions=keep_predictions)
    err = axis_errors(res.A, draw["A_true"], frame=sp.error_frame)
    tot = total_error_angle(res.A, draw["A_true"])
    valid = res.mode != NO_FIX
    lim = seq.error_limit_arcsec * ARCSEC
    with np.errstate(invalid="ignore"):
        within = valid & np.all(np.abs(err) <= lim, axis=1) & (tot <= math.sqrt(3.0) * lim)
    out = {"draw": draw, "rendered": r, "result": res, "err": err, "total_err": tot, "valid": valid,
           "within": within, "t_sample_ns": t_sample, "focal": focal}
    out["frames"] = frames_table(case_id, spec, out)
    out["sequence"] = sequence_row(case_id, spec, out)
    return out


def compute_shard(spec: StarTrackSpec, case_ids: np.ndarray, ctx: star.StarContext) -> dict[str, pa.Table]:
    """The engine's contract: one ``star_sequences`` row and ``frames`` ``star_frames`` rows per case."""
    frames, rows = [], []
    for i in np.asarray(case_ids, np.int64):
        o = compute_sequence(spec, ctx, int(i))
        frames.append(o["frames"])
        rows.append(o["sequence"])
    seqs = pa.Table.from_pylist(rows, schema=SEQUENCES_SCHEMA) if rows else SEQUENCES_SCHEMA.empty_table()
    fr = pa.concat_tables(frames) if frames else FRAMES_SCHEMA.empty_table()
    return {"star_sequences": seqs, "star_frames": fr}


def shard_summary(tables: dict[str, pa.Table]) -> dict:
    f = tables["star_frames"]
    mode = f.column("mode").to_numpy(zero_copy_only=False)
    within = f.column("within_limit").to_numpy(zero_copy_only=False)
    return {"frames": int(f.num_rows), "available": int(np.sum(within == True)),  # noqa: E712 (nulls)
            "tracking": int(np.sum(mode == "tracking")),
            "false_locks": int(np.sum(f.column("false_lock").to_numpy(zero_copy_only=False) == True))}  # noqa: E712


def progress_postfix(stats: dict) -> str:
    n = stats.get("frames", 0)
    if not n:
        return ""
    return (f"available {100 * stats.get('available', 0) / n:.1f}%, tracking {100 * stats.get('tracking', 0) / n:.1f}%, "
            f"false locks {stats.get('false_locks', 0)}")
