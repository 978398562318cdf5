"""Relative navigation over a rendezvous approach: the ``rendezvous`` job kind (issue 23, point 5; orchestration only).

One case is one approach of a chaser to a target near a circular orbit::

    draw (default_rng([seed, i])): initial Hill state about the nominal, manoeuvre execution errors, the target's
        spin, pointing errors, attitude-knowledge errors, per-frame noise seeds
    -> truth by Clohessy-Wiltshire with the executed delta-v (scene/relative_orbit.propagate)
    -> per frame: the camera attitude (pointed at the target with an error, or held inertially)
    -> star camera ("camera = star"): stars + target in one frame (scene/target_in_field: target_frames,
       with_target), rendered and detected by the star job's chain (jobs/kinds/star.render_and_detect), resolved
       blobs kept out of the vote, star identification and attitude (nav/star_solution), the target's inertial
       bearing through that attitude (nav/target_bearing.inertial_bearing; a point-like target's centroid sigma
       at its measured flux from the camera's own calibration, :func:`point_centroid_calibration`)
       proximity camera (a camera file): the target alone, rendered as the prox job does (kernels/points.render,
       exact coverage), the blobber's centre of brightness and range with its [min, max] (nav/blobber.py,
       "subpixel" estimator); the attitude from the chaser's own star tracker (true attitude + a Gaussian error of
       ``attitude_sigma_arcsec`` per axis, the same sigma in the bearing's covariance)
    -> the EKF over the frames (nav/relative_filter.run: CW prediction, the known manoeuvres with their nominal
       delta-v and execution error, bearing and range updates; two Gauss-Markov states for the centre of
       brightness's residual that a target spinning about a fixed axis keeps from frame to frame,
       scene/photocentre_bias.py; the blobber's range with its bias removed and its spread as a fraction of the
       predicted range, both from a calibration of the blobber through the camera's own renderer,
       :func:`blobber_range_calibration`, nav/blobber_range_error.py; a blob cut by the frame's edge gives neither;
       no process noise: the truth has none) -> Arrow rows (jobs/kinds/rendezvous_tables.py)

Target finding (``nav/target_finding.py``, issue 23.3): in a star frame every detection that matches no catalog
star through the frame's attitude, is not fixed on the sky (recurs in ICRS) nor on the detector (recurs on a pixel),
is a candidate; the filter takes the one nearest its predicted bearing inside a chi-square(2) gate (no bearing when
none is inside: identification or attitude failures stay out).  A proximity frame's candidate is the blobber's
resolved blob, gated the same way.  The truth only scores the pick afterwards (``target_found_true``).

Simplifications (stated, not hidden): no Earth shadow and no Earth or Moon in the field; the Sun is fixed in
ICRS; the proximity renderer uses the satellite file's ambient and directional light (``I_a``, ``I_l``) as the prox job does.

Spec (TOML)::

    seed = 1
    cases = 100
    [rendezvous]   ... (dualsight/config.py RendezvousConfig)

Presets: ``far`` (issue 23.6 e: V-bar hop 2 km -> 200 m with one known burn one orbit long, the star preset's
camera, paper sensor, bearings only) and ``close`` (issue 23.6 d: the paper's proximity camera and 3U CubeSat,
V-bar hop 50 m -> 2 m, bearings + blobber range).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from dualsight.config import FilterConfig, RendezvousConfig, TargetConfig, dataclass_from_table, dataclass_to_table, validate
from dualsight.errors import ConfigError, InputError
from dualsight.jobs.engine.runner import prepare, run_job
from dualsight.jobs.engine.specs import preset_and_config
from dualsight.jobs.kinds import star
from dualsight.jobs.kinds.rendezvous_tables import CASES_SCHEMA, FRAMES_SCHEMA, case_row, frames_table
from dualsight.kernels.digest import frame_digest, to_int64
from dualsight.kernels.sensor_config import flux_from_magnitude
from dualsight.nav import relative_filter as rf
from dualsight.nav.attitude import solve_identified
from dualsight.nav.blobber import BlobberConfig, run_blobber
from dualsight.nav.blobber_range_error import RangeRatioCalibration, range_ratio_at, range_ratio_statistics
from dualsight.nav.observations import observations
from dualsight.nav.resolved_blobs import excluded_blobs, without_excluded
from dualsight.nav.star_solution import centroid_weights, identify, solve
from dualsight.nav.target_finding import (FOUND_BY, chi2_gate_2dof, innovation_d2, pick, predicted_bearing,
                                          repeats, unmatched)
from dualsight.nav.target_bearing import (BLOB_SIGMA_FRAC_BY_DETECTOR, PointCentroidTable, attitude_covariance,
                                          bearing_error, blob_centroid_sigma, inertial_bearing, point_centroid_sigma,
                                          point_centroid_table, sphere_phase_correction)
from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.camera import Camera
from dualsight.scene.motion import place_body
from dualsight.scene.ephemeris import jd_tt_from_unix, moon_position, sun_position
from dualsight.scene.keepout import KeepOut, keep_out
from dualsight.scene.photocentre_bias import (PhotocentreStatistics, facet_materials, photocentre_statistics,
                                              shaded_photocentre_offset)
from dualsight.scene.relative_orbit import CircularOrbit, hill_to_icrs, propagate
from dualsight.scene.rotation_vector import frame_rotation
from dualsight.scene.example_files import shipped_path
from dualsight.scene.satellite import load_satellite
from dualsight.scene.starfield_geometry import FieldStars, stars_in_field
from dualsight.scene.target_in_field import TargetCases, diameter_px, target_frames, with_target
from dualsight.scene.target_photometry import photocentre_table, target_shape
from dualsight.scene.units import ARCSEC, DEG

NAME = "rendezvous"
PRIMARY = "rendezvous_cases"
SCHEMAS = {"rendezvous_cases": CASES_SCHEMA, "rendezvous_frames": FRAMES_SCHEMA}
DEFAULT_CASES = 100
STAR_CHUNK = 16
"""Star-camera frames rendered per call (full frames: 16 x 1024 x 768)."""
PROX_CHUNK = 8
"""Proximity frames rendered per call (8 x 1024 x 768 float32 image + coverage: ~50 MB)."""
GATE_PROB = 0.99999
"""Probability of the chi-square(2) validation gate on the bearing innovation (``nav/target_finding.py``): a
bearing farther from the filter's prediction than this (wrong identification or attitude, a false detection) is
not used.  The candidates are already the detections no catalog star explains that move against the stars, so the
gate guards against identification and attitude failures only; the true target's bearings had heavier tails than
a Gaussian (1.3-1.6 % of the far preset's frames beyond the 2-dof 99.73 % point against 0.27 %, seeds 1-4, before
the point target's centroid sigma came from its calibration: at most 0.14 % since, below 400 m 1.6-2 %), and a
filter without process noise (the truth has none) that rejects two or three of them in a row can stay locked out
(0.999: seed 2 case 83 and seed 4 case 89 gated out for 41 and 55 frames), so the gate is wide (d2 < 23.0)."""
MATCH_TOL_PX = 2.0
"""A detection within this many pixels' angle of a catalog star (through the frame's attitude) is that star."""
FIXED_SKY_TOL_PX = 2.0
"""An unmatched detection recurring within this many pixels' angle in ICRS in another frame is fixed on the sky."""
FIXED_PIXEL_TOL_PX = 1.5
"""An unmatched detection recurring within this many pixels in two other frames is fixed on the detector."""
BLOBBER = BlobberConfig(estimator="subpixel", threshold=0.0, target="all", connectivity=8)
"""The proximity frames' blobber (``nav/blobber.py``)."""
RANGE_FLOOR_FRAC = 0.005
"""Smallest 1-sigma of a blobber range given to the filter, as a fraction of the range (a [min, max] of zero width
would be an exact range)."""


def _hop_preset(altitude_km: float, start_m: float, end_m: float, frames_before: int, frames_orbit: int,
                **extra) -> dict:
    """A V-bar hop from ``start_m`` to ``end_m`` behind the target (y < 0) with one along-track burn
    ``dv_y = (start - end) n / (6 pi)`` (CW: one orbit later the chaser is at ``end_m``, Curtis Sec. 7.5), fired
    at frame ``frames_before``; frames every period / ``frames_orbit`` until one orbit after the burn."""
    orbit = CircularOrbit(altitude_km * 1e3)
    dt = orbit.period_s / frames_orbit
    t_burn = frames_before * dt
    dv = -(abs(start_m) - abs(end_m)) * orbit.mean_motion / (6.0 * math.pi)
    return {"altitude_km": altitude_km, "position_m": [0.0, -abs(start_m), 0.0], "velocity_m_s": [0.0, 0.0, 0.0],
            "frame_interval_s": dt, "duration_s": t_burn + orbit.period_s + 1e-6 * dt,
            "manoeuvre_times_s": [t_burn], "manoeuvre_dv_m_s": [[0.0, dv, 0.0]], **extra}


PRESETS = {
    # issue 23.6 (e): 2 km -> 200 m on V-bar, one known burn (executed to 0.3 % per axis: the benchmark
    # benchmarks/bench_relative_nav.py shows a 1 % burn error leaves ~1.8 % of range), star camera and the paper
    # sensor, bearings only; 64 frames (~99.6 s apart), the burn at frame 6.  The truth moves by CW exactly, its
    # burn error is the filter's dv_error_frac, so the filter has no process noise (accel_psd 0; the earlier 1e-14
    # stood in for the photocentre's bias, now states of the filter: target_selector); the photocentre's spread is
    # the target's own (scene/photocentre_bias.py), so no further cob_sigma_frac.
    "far": {"seed": 1, "cases": DEFAULT_CASES, "rendezvous": _hop_preset(
        500.0, 2000.0, 200.0, 6, 57, camera="star", sensor="paper", range_source="none", dv_error_frac=0.003,
        dispersion_position_m=[2.0, 50.0, 2.0], dispersion_velocity_m_s=[1e-4] * 3,
        prior_position_m=[2.0, 50.0, 2.0], prior_velocity_m_s=[1e-4] * 3, pointing_error_deg=0.5,
        cob_sigma_frac=0.0, accel_psd=0.0)},
    # issue 23.6 (d): the paper's proximity camera and 3U CubeSat, 50 m -> 2 m on V-bar in one orbit, bearings and
    # the blobber's range every frame the target is resolved; 61 frames (~96 s apart), the burn at frame 1.  No
    # process noise (as far); the centre of brightness corrected by the renderer's own shading's mean photocentre
    # (prox_photocentre: ambient + diffuse + specular, ~1.4 cm towards the Sun at 90 deg phase, which the bearings
    # carried uncorrected before) with its bias states; the blobber's range with its known bias removed
    # (range_model).
    "close": {"seed": 1, "cases": DEFAULT_CASES, "rendezvous": _hop_preset(
        500.0, 50.0, 2.0, 1, 59, camera="examples/cameras/paper_prox.toml", range_source="blobber",
        dv_error_frac=0.01, dispersion_position_m=[0.1, 2.5, 0.1], dispersion_velocity_m_s=[1e-4] * 3,
        prior_position_m=[0.1, 2.5, 0.1], prior_velocity_m_s=[1e-4] * 3, pointing_error_deg=0.5,
        phase_correction=True, cob_sigma_frac=0.0, accel_psd=0.0)},
}


class RendezvousTable(BaseModel):
    """The top level of a rendezvous spec's TOML layout (pydantic); ``[rendezvous]`` becomes a RendezvousConfig."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    seed: int = Field(1, ge=0, le=2**63 - 1)
    cases: int | None = Field(None, ge=1, le=10**9)
    preset: str | None = None
    rendezvous: dict = {}
    camera_table: dict | None = None


@dataclass(frozen=True)
class RendezvousSpec:
    """A validated rendezvous campaign: the approach (``RendezvousConfig``), the camera (the star preset's or the
    camera file's, stored inline so a run replays without the file) and, with the star camera, the star job's spec
    of the sensor preset with the target."""

    seed: int
    cfg: RendezvousConfig
    camera: Camera
    star: object = None                   # star.StarSpec (camera = "star") or None
    source: str = field(default="spec", compare=False)

    @property
    def is_star(self) -> bool:
        return self.cfg.camera == "star"

    @property
    def orbit(self) -> CircularOrbit:
        c = self.cfg
        return CircularOrbit(c.altitude_km * 1e3, c.inclination_deg * DEG, c.raan_deg * DEG, c.arg_lat_deg * DEG)

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.cfg.frames) * self.cfg.frame_interval_s

    def to_dict(self) -> dict:
        d = {"seed": self.seed, "rendezvous": dataclass_to_table(self.cfg)}
        if not self.is_star:
            d["camera_table"] = self.camera.to_dict()
        return d


def spec_from_dict(d: dict, source: str = "spec") -> RendezvousSpec:
    """Validate a spec dict (TOML layout); every error names ``source`` and the key."""
    top = validate(RendezvousTable, d, source=source)
    cfg = dataclass_from_table(RendezvousConfig, d.get("rendezvous"), source=source, section="rendezvous")
    last = (cfg.frames - 1) * cfg.frame_interval_s
    for i, t in enumerate(cfg.manoeuvre_times_s):
        if t > last + 1e-9:
            raise ConfigError(f"must lie in (0, {last:g}] s (the last frame's time), got {t!r}", source=source,
                              field=f"rendezvous.manoeuvre_times_s[{i}]")
    load_satellite(cfg.satellite)                 # errors name that file and its key
    if cfg.camera == "star":
        if cfg.range_source != "none":
            raise ConfigError("the star camera gives bearings only: must be 'none' with camera = 'star' (a range "
                              "needs a proximity camera file)", source=source, field="rendezvous.range_source")
        sd = {k: v for k, v in star.PRESETS[cfg.sensor].items() if k != "cases"}
        sd = {**sd, "seed": int(top.seed), "target": {"satellite": cfg.satellite}}
        sp = star.spec_from_dict(sd, source=source)
        return RendezvousSpec(int(top.seed), cfg, sp.camera, sp, source)
    if top.camera_table is not None:
        camera = Camera.from_dict(top.camera_table, source=source)
    else:
        cam_path = shipped_path(cfg.camera)
        if not cam_path.is_file():
            raise ConfigError(f"no such camera file: {cfg.camera} ('star' or a camera file)", source=source,
                              field="rendezvous.camera")
        camera = Camera.from_toml(cam_path)
    return RendezvousSpec(int(top.seed), cfg, camera, None, source)


def resolve_spec(preset: str | None, config, *, seed: int | None = None, cases: int | None = None) -> tuple[dict, int]:
    """The preset (default far), the ``--config`` TOML over it and the flags, validated: (canonical spec dict,
    number of cases)."""
    d, source = preset_and_config(PRESETS, preset, config, default="far")
    if seed is not None:
        d["seed"] = seed
    n = cases if cases is not None else d.get("cases", DEFAULT_CASES)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1 or n > 10**9:
        raise InputError(f"number of cases must be an integer in [1, 1e9], got {n!r}",
                         source="--cases" if cases is not None else source)
    return spec_from_dict(d, source=source).to_dict(), int(n)


@dataclass(frozen=True)
class RendezvousRun:
    """A rendezvous campaign resolved and identified but not yet run (:func:`plan_run`, :func:`start_run`)."""

    spec: dict
    n_cases: int
    run_id: str
    spec_hash: str
    source: str


def plan_run(preset: str | None = None, config: Path | str | dict | None = None, *, seed: int | None = None,
             cases: int | None = None, run_id: str | None = None) -> RendezvousRun:
    """Everything ``dualsight rendezvous run`` decides before the lake is touched: the spec, the run's identity and
    its id (default ``rendezvous-<seed>-<cases>-<first 8 digits of the spec hash>``)."""
    spec_dict, n = resolve_spec(preset, config, seed=seed, cases=cases)
    source = (("config table" if isinstance(config, dict) else str(config)) if config is not None
              else f"preset {preset or 'far'}")
    _, _, _, h = prepare(NAME, spec_dict, n, source=source)
    return RendezvousRun(spec_dict, n, run_id or f"rendezvous-{spec_dict['seed']}-{n}-{h[:8]}", h, source)


def start_run(plan: RendezvousRun, lake, *, workers: int | None = None, scheduler: str | None = None,
              shard_size: int | None = None, progress: bool = True) -> dict:
    """Run (or resume) a planned campaign into ``lake`` with the engine's ``run_job``; returns the manifest."""
    return run_job(NAME, plan.spec, n_cases=plan.n_cases, lake=lake, run_id=plan.run_id, workers=workers,
                   scheduler=scheduler, shard_size=shard_size, progress=progress, label=f"rendezvous {plan.run_id}")


@dataclass(frozen=True)
class RendezvousContext:
    """Per-process state: the target's satellite file and photometric shape, and either the star job's context
    (catalogs, voting index, star blob limit) or the proximity renderer's mesh, materials and area table."""

    sat: object
    shape: object
    photocentre: tuple = ()                # photocentre_table(shape)
    photocentre_bias: PhotocentreStatistics | None = None   # photocentre_statistics(shape, spinning)
    star: object = None
    mesh: object = None
    materials: np.ndarray | None = None
    table: object = None
    range_ratio: tuple = ()                # (bin centres, m_q, s_q): nav/blobber_range_error on ``table``
    centroid: PointCentroidTable | None = None   # star camera: point_centroid_calibration(spec)
    range_calibration: RangeRatioCalibration | None = None   # proximity: blobber_range_calibration(...)


def make_context(spec: RendezvousSpec) -> RendezvousContext:
    sat = load_satellite(spec.cfg.satellite)
    shape = target_shape(sat.components)
    spinning = spec.cfg.target_rate_deg_s > 0
    if spec.is_star:
        pc = photocentre_table(shape)
        pb = photocentre_statistics(shape, spinning=spinning)
        sctx = star.make_context(spec.star)
        return RendezvousContext(sat, shape, pc, pb, star=sctx, centroid=point_centroid_calibration(spec, sctx.psf))
    from dualsight.catalogs.areas import area_table        # pyarrow

    pc, pb = prox_photocentre(sat, shape, spinning)
    table = area_table(sat, n=20000, bin_width=0.05)
    mq, sq = range_ratio_statistics(table.samples_ratio, table.samples_area, table.ratio_lo, table.ratio_hi,
                                    table.curve(BLOBBER.curve))
    mesh, materials = sat.mesh(), sat.materials()
    cal = blobber_range_calibration(sat, mesh, materials, table, spec.camera) if spec.cfg.range_source == "blobber" \
        else None
    return RendezvousContext(sat, shape, pc, pb, mesh=mesh, materials=materials, table=table,
                             range_ratio=(table.ratio, mq, sq), range_calibration=cal)


RANGE_CALIB_SPANS = ((10.0, 80.0, 12000), (0.4, 10.0, 6000))
"""Ranges (m) of :func:`blobber_range_calibration`'s renders: (low, high, count) log-uniform; more where the blob
is small (its observed axis ratio is poor and q's mean moves with it) than where the table alone is right."""
RANGE_CALIB_POINTING_DEG = 0.5
"""1-sigma per axis of the calibration target's offset from the boresight (the presets' pointing error)."""


def blobber_range_calibration(sat, mesh, materials, table, camera: Camera) -> RangeRatioCalibration:
    """The proximity camera's blobber range against the truth, by Monte Carlo of the camera's own renderer
    (``kernels/points.render``, "accurate", the satellite file's light) and blobber (:data:`BLOBBER`, the area
    table ``table``): the target at ranges log-uniform in each of :data:`RANGE_CALIB_SPANS`, off the boresight by
    :data:`RANGE_CALIB_POINTING_DEG`, orientations uniform on SO(3), the Sun from a uniform direction; a blob that
    touches the image's edge is not a range (:func:`touches_edge`) and is left out.  Returns the samples as
    ``nav/blobber_range_error.RangeRatioCalibration`` (q = range_est / range against n_blob and the observed axis
    ratio).  Deterministic (its own generator, not the run's seed): a ground calibration of the blobber on the
    target's model, as :func:`point_centroid_calibration` is of the star camera.  ~10 s for the 3U CubeSat and the
    paper's proximity camera (one process, 2 shared cores)."""
    from dualsight.kernels.points import render              # Taichi

    rng = np.random.default_rng([23, 6, 4])
    r = np.concatenate([np.exp(rng.uniform(math.log(lo), math.log(hi), n)) for lo, hi, n in RANGE_CALIB_SPANS])
    M = r.size
    u = rng.random((M, 3))
    R_body = quat_to_dcm(quaternions_from_uniforms(u[:, 0], u[:, 1], u[:, 2]))
    off = rng.normal(size=(M, 2)) * RANGE_CALIB_POINTING_DEG * DEG
    los = np.stack([np.tan(off[:, 0]), np.tan(off[:, 1]), np.ones(M)], -1)
    pos = los / np.linalg.norm(los, axis=1, keepdims=True) * r[:, None]
    sun = rng.normal(size=(M, 3))
    sun /= np.linalg.norm(sun, axis=1, keepdims=True)
    q, n_blob, ratio = np.full(M, np.nan), np.full(M, np.nan), np.full(M, np.nan)
    light = sat.camera
    for s in range(0, M, PROX_CHUNK):
        i = np.arange(s, min(M, s + PROX_CHUNK))
        poses = place_body(sat, R_body[i], pos[i], sun[i])
        img, cov = render("accurate", mesh, materials, poses.R, poses.t, poses.light, camera, light.I_a, light.I_l)
        b = run_blobber(img, camera, table, BLOBBER, coverage=cov)
        ok = b.found & ~touches_edge(b.box, camera) & np.isfinite(b.range_est)
        q[i] = np.where(ok, b.range_est / r[i], np.nan)
        n_blob[i] = np.where(ok, b.n_blob, np.nan)
        ratio[i] = np.where(ok, b.axis_ratio, np.nan)
    return RangeRatioCalibration(n_blob, ratio, q)


def touches_edge(box: np.ndarray, camera: Camera) -> np.ndarray:
    """(B,) whether a blob's inclusive bounding box (B, 4) [x0, y0, x1, y1] reaches the image's first or last row
    or column: the target is cut by the frame, its pixel count and centre of brightness are the visible part's."""
    box = np.asarray(box)
    return (box[:, 0] <= 0) | (box[:, 1] <= 0) | (box[:, 2] >= camera.width - 1) | (box[:, 3] >= camera.height - 1)


def prox_photocentre(sat, shape, spinning: bool) -> tuple[tuple, PhotocentreStatistics | None]:
    """The proximity camera's photocentre correction and statistics: under the renderer's own shading (the
    satellite file's ``I_a``, ``I_l`` and each component's ``k_a``, ``k_l``, ``k_s``, ``n``:
    ``scene/photocentre_bias.shaded_photocentre_offset``; its ambient light pulls the photocentre towards the
    silhouette's centre, to about a third of the Lambertian table's offset for the 3U CubeSat at 90 deg phase),
    as (alpha, mean offset towards the Sun, total spread) in ``photocentre_table``'s layout and the statistics;
    a target with spheres keeps the Lambertian table and no statistics (not modelled)."""
    try:
        mats = facet_materials(sat.components)
    except ValueError:
        return photocentre_table(shape), None
    light = sat.camera

    def offset(R_body, sun, obs):
        return shaded_photocentre_offset(shape, mats, light.I_a, light.I_l, R_body, sun, obs)

    pb = photocentre_statistics(shape, spinning=spinning, offset=offset)
    spread = np.sqrt(pb.spread_white ** 2 + 0.5 * (pb.sigma_sun ** 2 + pb.sigma_cross ** 2))
    return (pb.alpha, pb.mean_sun, spread), pb


CALIB_LEVELS = np.logspace(3.0, 11.0, 321)
"""Electrons per exposure of the point sources of :func:`point_centroid_calibration` (40 levels per decade: the
saturated centroid's error oscillates with the flux, a period of about a quarter decade for the paper sensor)."""
CALIB_PHASES = 64
"""Renders per level of :func:`point_centroid_calibration` (uniform sub-pixel positions; each level's sigma is
then known to about 1 / sqrt(2 x 64) = 9 %, and the many levels a campaign's targets span average that out)."""
CALIB_WINDOW_PX = 64
"""Side of the window the calibration renders in (the point source near its centre; the sensor, PSF, detector and
distortion of the star camera)."""


def point_centroid_calibration(spec: RendezvousSpec, psf=None) -> PointCentroidTable:
    """The star camera's centroid error for a point source against its measured flux, by Monte Carlo of the
    camera's own render and detector (``jobs/kinds/star.render_and_detect``: the spec's sensor, with its noise if
    any, its detector and PSF) on :data:`CALIB_WINDOW_PX`-pixel windows, one source per window at a uniform
    sub-pixel position, :data:`CALIB_PHASES` renders at each of :data:`CALIB_LEVELS`; the table of
    ``nav/target_bearing.point_centroid_table``.  Deterministic (its own generator, not the run's seed): a ground
    calibration of the camera, as a flight star tracker's centroid error model is.  ~0.5 s noise-free (sparse
    path), longer with noise (full windows)."""
    sp = spec.star
    w = CALIB_WINDOW_PX
    c0 = 0.5 * w
    cam = replace(sp.camera, width=w, height=w, cx=c0, cy=c0)
    L, K = len(CALIB_LEVELS), CALIB_PHASES
    rng = np.random.default_rng([23, 6, 3])
    x = c0 + rng.random(L * K)
    y = c0 + rng.random(L * K)
    e = np.repeat(CALIB_LEVELS, K).astype(np.float32)
    level = np.repeat(np.arange(L), K)
    seeds = rng.integers(0, 2**63 - 1, size=L * K, dtype=np.int64).astype(np.uint64)
    flux = np.full(L * K, np.nan)
    err = np.full((L * K, 2), np.nan)
    chunk = 4096 if (sp.sensor.is_ideal and sp.detector == "global") else 512
    for s in range(0, L * K, chunk):
        i = np.arange(s, min(L * K, s + chunk))
        n = len(i)
        fs = FieldStars(x[i, None], y[i, None], e[i, None], np.ones((n, 1), bool), np.zeros((n, 1), np.int64),
                        np.ones((n, 1), bool), np.ones(n, np.int64))
        det = star.render_and_detect(fs, seeds[i], cam, sp.sensor, sp.detect, keep_images=False,
                                     attitude=np.broadcast_to(np.eye(3), (n, 3, 3)), detector=sp.detector,
                                     psf=psf).detections
        case = np.asarray(det.case, np.int64)
        d2 = (det.x - x[i][case]) ** 2 + (det.y - y[i][case]) ** 2
        o = np.lexsort((d2, case))                            # each window's detection nearest the source
        first = o[np.unique(case[o], return_index=True)[1]]
        near = first[d2[first] < 9.0]
        b = i[case[near]]
        flux[b] = det.flux[near]
        err[b] = np.stack([det.x[near] - x[b], det.y[near] - y[b]], -1)
    return point_centroid_table(level, flux, err)


def memory_estimate(spec: RendezvousSpec) -> int:
    """The star job's estimate (star camera) or the proximity chunk's frames (image and coverage, float32, x 4)."""
    if spec.is_star:
        return star.memory_estimate(spec.star)
    return int(PROX_CHUNK * spec.camera.width * spec.camera.height * 4 * 2 * 4 + 200e6)


# ------------------------------------------------------------------------------------------ one approach
def draw_case(spec: RendezvousSpec, case_id: int) -> dict:
    """Inputs of approach ``case_id`` from ``default_rng([seed, case_id])`` alone, always in this order whatever
    the options: initial-state dispersion (6 normals), manoeuvre execution errors (M x 3 normals), the target's spin
    axis (3 normals) and initial attitude (3 uniforms), pointing errors (T x 3 normals), attitude-knowledge errors
    (T x 3 normals), per-frame sensor noise seeds (T).

    Returns dict: x0 (6,) true initial Hill state; x0_nominal (6,); dv_nominal, dv_exec (M, 3) m/s; spin_axis (3,);
    q0 (4,); pointing_err, attitude_err (T, 3) rad; noise_seeds (T,) uint64."""
    c = spec.cfg
    T, M = c.frames, len(c.manoeuvre_times_s)
    rng = np.random.default_rng([spec.seed, int(case_id)])
    nominal = np.array(list(c.position_m) + list(c.velocity_m_s), np.float64)
    disp = np.array(list(c.dispersion_position_m) + list(c.dispersion_velocity_m_s))
    x0 = nominal + rng.normal(size=6) * disp
    dv_nom = np.asarray(c.manoeuvre_dv_m_s, np.float64).reshape(M, 3)
    dv_sig = np.sqrt((c.dv_error_frac * np.linalg.norm(dv_nom, axis=1)) ** 2 + c.dv_error_m_s ** 2)
    dv_exec = dv_nom + rng.normal(size=(M, 3)) * dv_sig[:, None]
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    u = rng.random(3)
    q0 = quaternions_from_uniforms(u[0:1], u[1:2], u[2:3])[0]
    pe = rng.normal(size=(T, 3)) * c.pointing_error_deg * DEG
    ae = rng.normal(size=(T, 3)) * c.attitude_sigma_arcsec * ARCSEC
    noise = rng.integers(0, 2**63 - 1, size=T, dtype=np.int64).astype(np.uint64)
    return {"x0": x0, "x0_nominal": nominal, "dv_nominal": dv_nom, "dv_exec": dv_exec, "spin_axis": axis, "q0": q0,
            "pointing_err": pe, "attitude_err": ae, "noise_seeds": noise}


def truth_trajectory(spec: RendezvousSpec, draw: dict) -> np.ndarray:
    """(T, 6) true Hill states at the frame times: CW from the drawn initial state with the executed manoeuvres."""
    c = spec.cfg
    return propagate(draw["x0"][None], spec.times, spec.orbit.mean_motion, dv_times=np.asarray(c.manoeuvre_times_s),
                     dv=draw["dv_exec"][None] if len(c.manoeuvre_times_s) else None)[0]


def sun_icrs(spec: RendezvousSpec) -> np.ndarray:
    """(3,) unit vector towards the Sun: the spec's, else the first frame's epoch's (``[rendezvous.environment]``,
    ``scene/ephemeris.py``, from the Earth's centre: 10 arcsec from the chaser's), else the reference orbit's
    normal."""
    if spec.cfg.sun_icrs is not None:
        s = np.asarray(spec.cfg.sun_icrs, np.float64)
        return s / np.linalg.norm(s)
    if spec.cfg.environment is not None:
        s = sun_position(jd_tt_from_unix(spec.cfg.environment.epoch_unix_s))
        return s / np.linalg.norm(s)
    return hill_to_icrs(spec.orbit, [0.0])[0][:, 2]


def look_at(los: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(T, 3, 3) attitudes (ICRS -> camera) with the boresight +z along ``los`` (T, 3) (unit) and +x along
    ``up x los`` (``up`` (T, 3); where it is within 1e-6 of the boresight, ICRS x or y instead)."""
    z = np.asarray(los, np.float64)
    up = np.asarray(up, np.float64)
    x = np.cross(up, z)
    bad = np.linalg.norm(x, axis=-1) < 1e-6
    if bad.any():
        alt = np.where(np.abs(z[bad, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
        x[bad] = np.cross(alt, z[bad])
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], -2)


def geometry(spec: RendezvousSpec, draw: dict, truth: np.ndarray) -> dict:
    """Per frame: true camera attitude A_true (T, 3, 3) (ICRS -> camera), the Hill rotation R (T, 3, 3), the true
    line of sight u_true (T, 3) chaser -> target (ICRS), and the target's geometry in the camera frame as
    ``scene/target_in_field.TargetCases`` (present = in front of the camera and inside the image)."""
    c = spec.cfg
    t = spec.times
    R = hill_to_icrs(spec.orbit, t)
    rho_i = np.einsum("tij,tj->ti", R, truth[:, :3])
    rng_m = np.linalg.norm(rho_i, axis=1)
    u_true = -rho_i / rng_m[:, None]
    up = R[:, :, 2]                                              # the orbit normal: camera +x along-track-ish
    if c.pointing == "target":
        A_nom = look_at(u_true, up)
    else:
        x0n = draw["x0_nominal"][:3]
        u0 = -(R[0] @ x0n) / np.linalg.norm(x0n)
        A_nom = np.broadcast_to(look_at(u0[None], up[:1])[0], (len(t), 3, 3))
    A = frame_rotation(draw["pointing_err"]) @ A_nom
    pos_cam = np.einsum("tij,tj->ti", A, u_true * rng_m[:, None])
    R_icrs = frame_rotation(draw["spin_axis"][None] * (c.target_rate_deg_s * DEG * t)[:, None]) @ \
        quat_to_dcm(draw["q0"][None])[0]                      # body -> ICRS (passive rotation of the body's axes)
    R_body = A @ R_icrs
    s = sun_icrs(spec)
    sun_cam = np.einsum("tij,j->ti", A, s)
    o = -pos_cam / rng_m[:, None]                                # target -> camera
    phase = np.arccos(np.clip(np.einsum("tk,tk->t", sun_cam, o), -1.0, 1.0))
    xy, _ = spec.camera.project(pos_cam)
    inside = (pos_cam[:, 2] > 0) & np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & \
        (xy[:, 0] < spec.camera.width) & (xy[:, 1] >= 0) & (xy[:, 1] < spec.camera.height)
    tc = TargetCases(inside, rng_m, pos_cam, R_body, sun_cam, np.broadcast_to(s, (len(t), 3)).copy(), phase)
    return {"A_true": A, "R": R, "u_true": u_true, "targets": tc}


def frame_view(spec: RendezvousSpec, geo: dict, truth: np.ndarray) -> KeepOut | None:
    """Each frame's Sun, Earth and Moon along the true boresight (``geo["A_true"]`` row 2) with
    ``[rendezvous.environment]`` (``scene/keepout.py``), else None.  Frame k at the epoch + t_k; the chaser at the
    reference orbit's position plus its Hill offset ``truth[:, :3]`` (km, GCRS); the Sun and Moon of
    ``scene/ephemeris.py`` at each frame's time."""
    env = spec.cfg.environment
    if env is None:
        return None
    jd = jd_tt_from_unix(env.epoch_unix_s + spec.times)
    R = geo["R"]
    r_km = (spec.orbit.radius_m * R[:, :, 0] + np.einsum("tij,tj->ti", R, truth[:, :3])) / 1e3
    return keep_out(r_km, geo["A_true"][:, 2, :], sun_position(jd), moon_position(jd),
                    sun_half_rad=math.radians(env.sun_keepout_deg), earth_half_rad=math.radians(env.earth_keepout_deg),
                    moon_half_rad=math.radians(env.moon_keepout_deg))


def _empty_meas(T: int) -> dict:
    nan = np.full(T, np.nan)
    return {"attitude": np.zeros(T, np.int8), "n_stars": np.zeros(T, np.int64), "in_field": np.zeros(T, bool),
            "detected": np.zeros(T, bool), "resolved": np.zeros(T, bool), "pixels": np.full(T, -1, np.int64),
            "vmag": nan.copy(), "phase": nan.copy(), "u": np.full((T, 3), np.nan), "C": np.zeros((T, 3, 3)),
            "bearing_used": np.zeros(T, bool), "bearing_err": nan.copy(), "bearing_sigma": nan.copy(),
            "range": nan.copy(), "range_min": nan.copy(), "range_max": nan.copy(), "range_used": np.zeros(T, bool),
            "range_sigma": nan.copy(), "digest": np.zeros(T, np.int64), "t_render_ns": np.zeros(T, np.int64),
            "u_used": np.full((T, 3), np.nan), "C_used": np.zeros((T, 3, 3)), "bearing_raw_err": nan.copy(),
            "target_xy": np.full((T, 2), np.nan), "found_by": np.zeros(T, np.int8), "found_true": np.zeros(T, bool),
            "axis_ratio": nan.copy(), "range_filter": nan.copy(), "cand": None, "n_blob": nan.copy(), "range_sigma_frac": nan.copy(),
            "cut": np.zeros(T, bool)}


def _candidates(frame, u, C, xy, true) -> dict:
    """The target candidates of a sequence: frame (K,), ICRS lines of sight u (K, 3) and covariances C (K, 3, 3),
    pixel positions xy (K, 2), and whether each is the true target's detection (``true`` (K,), for scoring only)."""
    return {"frame": np.asarray(frame, np.int64), "u": np.asarray(u, np.float64).reshape(-1, 3),
            "C": np.asarray(C, np.float64).reshape(-1, 3, 3), "xy": np.asarray(xy, np.float64).reshape(-1, 2),
            "true": np.asarray(true, bool)}


def measure_star(spec: RendezvousSpec, ctx: RendezvousContext, draw: dict, geo: dict, keep_images: bool = False):
    """Star camera: stars and target in one frame, detection, identification, attitude, the target's bearing.
    Returns (measurements dict, images (T, H, W) or None)."""
    sp, sc = spec.star, ctx.star
    cat = sc.catalog
    tc = geo["targets"]
    T = len(tc.range_m)
    m = _empty_meas(T)
    m["phase"] = tc.phase_rad
    m["in_field"] = tc.present.copy()
    flux = flux_from_magnitude(cat.vmag.astype(np.float64), sp.sensor)
    A_true = geo["A_true"]
    field_ = stars_in_field(A_true, cat.unit, flux, sp.camera, star.psf_margin_px(sp.sensor, sp.camera, sc.psf))
    tcfg = TargetConfig(satellite=spec.cfg.satellite)
    tf = target_frames(tcfg, ctx.sat, ctx.shape, tc, field_, sp.camera, sp.sensor)
    render_field, _ = with_target(field_, tf)
    m["resolved"], m["pixels"], m["vmag"] = tf.resolved.copy(), tf.pixels.copy(), tf.vmag.copy()
    voting = sp.robust if sp.robust is not None else sp.voting
    f = max(sp.camera.fx, sp.camera.fy)
    images = [] if keep_images else None
    parts = []
    A_all = np.tile(np.eye(3), (T, 1, 1))
    bs = min(sp.batch_size, STAR_CHUNK)
    for s in range(0, T, bs):
        fr = np.arange(s, min(T, s + bs))
        sub = _take_field(render_field, fr)
        # full frames always (keep_images=True): the sparse path renders windows sized for stars, which would cut
        # the wings of a target brighter than any star (and the replay re-renders whole frames)
        r = star.render_and_detect(sub, draw["noise_seeds"][fr], sp.camera, sp.sensor, sp.detect,
                                   keep_images=True, attitude=A_true[fr], detector=sp.detector, psf=sc.psf)
        if keep_images:
            images.append(r.images)
        m["t_render_ns"][fr] = (r.t_render_ns + (r.t_detect_ns or 0)) // len(fr)
        m["digest"][fr] = to_int64(r.digest)
        det = r.detections
        obs = observations(det, len(fr), sp.camera)
        obs = without_excluded(obs, det.case, det.offsets, excluded_blobs(det.npix, sc.star_blob_limit))
        ident = identify(obs, cat.unit, sc.index, voting, cat_vmag=cat.vmag)
        sol = solve(obs, ident, cat.unit, A_true[fr], sp.error_frame, weights=centroid_weights(det, obs, 0.02))
        used = ident.accepted & (ident.ids >= 0) & obs.valid
        n_used = used.sum(1)
        _, ok, cov_unit = solve_identified(obs.vec, ident.ids, used, cat.unit, return_cov=True)
        att_ok = ok & sol.ok
        s2 = attitude_covariance(np.ones((len(fr), 1, 1)), sol.residual, n_used,
                                 floor_rad=float(np.min(ctx.centroid.sigma_px)) / f)[:, 0, 0]
        P_att = np.where(att_ok[:, None, None], cov_unit, 0.0) * s2[:, None, None]
        # every detection of a frame with an attitude is a candidate until the catalog and its motion say
        # otherwise (nav/target_finding.py); the truth only scores the pick afterwards (target_detection)
        kt = star.target_detection(det, _take_tf(tf, fr))
        case = np.asarray(det.case, np.int64)
        kk = np.flatnonzero(att_ok[case])
        cl = case[kk]
        npix = np.asarray(det.npix)[kk]
        resolved = npix > sc.star_blob_limit
        # a blob a star could make: the camera's own centroid error at its measured flux (pixel phase, saturation,
        # noise: point_centroid_calibration); a larger one: the star's scatter plus the partly lit, saturated
        # body's share of its size (nav/target_bearing.blob_centroid_sigma, the spec's detector's fraction)
        sig_pt = point_centroid_sigma(np.asarray(det.flux)[kk], ctx.centroid)
        sig_res = blob_centroid_sigma(npix, np.sqrt(s2)[cl] * f, True,
                                      frac_resolved=BLOB_SIGMA_FRAC_BY_DETECTOR[sp.detector][1])
        sig_px = np.where(resolved, sig_res, sig_pt)
        xy = np.stack([det.x[kk], det.y[kk]], -1)
        u, C = inertial_bearing(sol.A_est[cl], P_att[cl], xy, sig_px, sp.camera)
        parts.append((fr[cl], u, C, xy, kk == kt[cl]))
        A_all[fr[att_ok]] = sol.A_est[att_ok]
        m["attitude"][fr] = np.where(att_ok, 1, 0)
        m["n_stars"][fr] = np.where(att_ok, n_used, 0)
        m["detected"][fr] = kt >= 0
    cand = _candidates(*(np.concatenate([p[i] for p in parts]) for i in range(5)))
    pix = 1.0 / f
    keep = unmatched(cand["frame"], cand["u"], A_all[:, 2, :], cat.unit, MATCH_TOL_PX * pix,
                     0.5 * sp.camera.fov_rad[2])
    keep &= ~repeats(cand["frame"], cand["u"], FIXED_SKY_TOL_PX * pix, min_frames=2)
    keep &= ~repeats(cand["frame"], cand["xy"], FIXED_PIXEL_TOL_PX, min_frames=3)
    m["cand"] = {k: v[keep] for k, v in cand.items()}
    return m, (np.concatenate(images) if keep_images else None)


def _take_field(f, idx):
    return type(f)(*(getattr(f, k)[idx] for k in f.__dataclass_fields__))


def _take_tf(tf, idx):
    return type(tf)(*(getattr(tf, k)[idx] for k in tf.__dataclass_fields__))


def _bearing_scores(m: dict, geo: dict) -> None:
    """Fill the errors against the true direction to the body origin of the measured (``bearing_raw_err``) and the
    used bearing (after the filter's adjustment), and the used one's stated 1-sigma per axis, where a bearing was
    used."""
    ok = m["bearing_used"]
    if ok.any():
        m["bearing_raw_err"][ok] = bearing_error(m["u"][ok], geo["u_true"][ok])
        m["bearing_err"][ok] = bearing_error(m["u_used"][ok], geo["u_true"][ok])
        m["bearing_sigma"][ok] = np.sqrt(np.trace(m["C_used"][ok], axis1=1, axis2=2) / 2)


def measure_prox(spec: RendezvousSpec, ctx: RendezvousContext, draw: dict, geo: dict, keep_images: bool = False):
    """Proximity camera: the target rendered alone (exact coverage), the blobber's centre of brightness and range,
    the bearing through the chaser's star-tracker attitude (truth + ``attitude_err``).  Returns (measurements,
    images (T, H, W) or None)."""
    from dualsight.kernels.points import render              # Taichi

    c = spec.cfg
    cam = spec.camera
    tc = geo["targets"]
    T = len(tc.range_m)
    m = _empty_meas(T)
    m["phase"], m["in_field"] = tc.phase_rad, tc.present.copy()
    m["attitude"][:] = 2
    light = ctx.sat.camera
    bcfg = BLOBBER
    A_true = geo["A_true"]
    A_est = frame_rotation(draw["attitude_err"]) @ A_true
    sa = c.attitude_sigma_arcsec * ARCSEC
    diam = diameter_px(ctx.shape.bounding_radius, tc.range_m, cam)
    m["resolved"] = tc.present & (diam >= 3.0)
    images = [] if keep_images else None
    for s in range(0, T, PROX_CHUNK):
        fr = np.arange(s, min(T, s + PROX_CHUNK))
        t0 = time.perf_counter_ns()
        poses = place_body(ctx.sat, tc.R_body[fr], tc.pos_cam[fr], tc.sun_cam[fr])
        img, cov = render("accurate", ctx.mesh, ctx.materials, poses.R, poses.t, poses.light, cam, light.I_a,
                          light.I_l)
        img = np.where(tc.present[fr, None, None], img, np.float32(0.0))
        cov = np.where(tc.present[fr, None, None], cov, np.float32(0.0))
        m["t_render_ns"][fr] = (time.perf_counter_ns() - t0) // len(fr)
        m["digest"][fr] = to_int64(frame_digest(img))
        if keep_images:
            images.append(img)
        b = run_blobber(img, cam, ctx.table, bcfg, coverage=cov)
        found = b.found & tc.present[fr]
        m["detected"][fr] = found
        m["pixels"][fr] = np.where(found, np.nan_to_num(b.n_pixels), -1).astype(np.int64)
        xy = np.where(found[:, None], b.cob_px, 0.5 * np.array([cam.width, cam.height]))
        m["target_xy"][fr] = np.where(found[:, None], xy, np.nan)
        sig_px = np.full(len(fr), star.CENTROID_FLOOR_PX)
        u, C = inertial_bearing(A_est[fr], np.broadcast_to(sa ** 2 * np.eye(3), (len(fr), 3, 3)), xy, sig_px, cam)
        m["u"][fr] = np.where(found[:, None], u, np.nan)        # the candidates (the one blob), picked by the gate
        m["C"][fr] = np.where(found[:, None, None], C, 0.0)
        rok = found & m["resolved"][fr] & np.isfinite(b.range_est) & (b.range_est > 0)
        m["range"][fr] = np.where(rok, b.range_est, np.nan)
        m["range_min"][fr] = np.where(rok, b.range_min, np.nan)
        m["range_max"][fr] = np.where(rok, b.range_max, np.nan)
        m["axis_ratio"][fr] = np.where(rok, b.axis_ratio, np.nan)
        m["n_blob"][fr] = np.where(rok, b.n_blob, np.nan)
        m["cut"][fr] = found & touches_edge(b.box, cam)
    # a blob the frame's edge cuts gives neither a bearing (its centre of brightness is the visible part's) nor a
    # range (its pixels are): the target is too close or off the boresight (:func:`touches_edge`)
    m["range"][m["cut"]] = np.nan
    k = np.flatnonzero(m["detected"] & ~m["cut"])
    m["cand"] = _candidates(k, m["u"][k], m["C"][k], m["target_xy"][k], np.ones(len(k), bool))
    m["u"][:], m["C"][:] = np.nan, 0.0
    rok = np.isfinite(m["range"]) & (c.range_source == "blobber")
    m["range_used"] = rok
    range_model(ctx, m)
    return m, (np.concatenate(images) if keep_images else None)


def range_model(ctx: RendezvousContext, m: dict) -> None:
    """The filter's blobber range (``m["range_filter"]``) and its 1-sigma (``m["range_sigma"]``) where
    ``m["range_used"]``: the blobber's known bias removed and its spread as the sigma, ``range / m_q`` and
    ``range s_q / m_q^2`` (``nav/blobber_range_error.py``), at least :data:`RANGE_FLOOR_FRAC` of the range; the
    filter takes the sigma as the fraction ``m["range_sigma_frac"]`` = s_q / m_q of its predicted range
    (``relative_filter.run``'s ``range_sig_frac``: a sigma scaled by the measured range biases the estimate short).  m_q and
    s_q are the calibration's (``ctx.range_calibration``: q's mean and spread over renders at the blob's summed
    coverage ``m["n_blob"]`` and observed axis ratio, :func:`blobber_range_calibration`), else the area table's
    at the observed axis ratio (``ctx.range_ratio``: exact silhouettes, no pixel sampling)."""
    rok = m["range_used"]
    if ctx.range_calibration is not None:
        mq, sq, _ = ctx.range_calibration.at(m["n_blob"], m["axis_ratio"])
    else:
        mq, sq = range_ratio_at(m["axis_ratio"], *ctx.range_ratio)
    m["range_filter"] = np.where(rok, m["range"] / mq, np.nan)
    m["range_sigma_frac"] = np.where(rok, np.maximum(sq / mq, RANGE_FLOOR_FRAC), np.nan)
    m["range_sigma"] = m["range_sigma_frac"] * m["range_filter"]


def filter_config(cfg: RendezvousConfig) -> FilterConfig:
    """The EKF's settings of a spec."""
    return FilterConfig(accel_psd=cfg.accel_psd, dv_sigma_frac=cfg.dv_error_frac, dv_sigma_m_s=cfg.dv_error_m_s,
                           iterations=cfg.iterations)


COB_BIAS_STATES = 2
"""Bias states of the filter (``nav/relative_filter.py``): the centre of brightness's correlated offset along the
Sun's direction in the plane of the sky and across it (``scene/photocentre_bias.py``)."""


def cob_axes(u: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(K, 3, 2) unit vectors across lines of sight u (K, 3): the Sun's direction s (3,) projected across u, and
    u x that (any pair across u where the Sun is along u)."""
    d = s[None] - (u @ s)[:, None] * u
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    alt = rf.tangent_basis(u)[:, 0]
    d = np.where(n > 1e-9, d / np.where(n > 1e-9, n, 1.0), alt)
    return np.stack([d, np.cross(u, d)], -1)


@dataclass(frozen=True)
class CobBias:
    """A model of what the mean phase correction leaves of the centre of brightness, as ``n`` unit-variance bias
    states of the filter (``nav/relative_filter.run``'s ``n_bias``).  ``columns(k, v, D, alpha, r) -> (G, white)``
    for frame k's candidates: G (K, 3, n) m per unit state (``bearing_update``'s ``bias``) and white (K, 2) m the
    1-sigma of the rest along D's two axes, from their corrected lines of sight v (K, 3), the axes D (K, 3, 2) of
    :func:`cob_axes` (the Sun's side across v, and v x that), the phase angles alpha (K,) rad and the predicted range
    r m; ``decay(k, x, R_k) -> (1, n)`` the states' correlation with frame k - 1 and ``start(x, R_k)`` its first
    line of sight (:func:`cob_bias_decay`).  The product's is :func:`gauss_markov_cob`;
    ``benchmarks/bench_rendezvous_bias_models.py`` compares others."""

    n: int
    columns: Callable
    decay: Callable
    start: Callable


def gauss_markov_cob(spec: RendezvousSpec, ctx: RendezvousContext) -> CobBias | None:
    """The filter's model (:func:`target_selector`'s docstring): :data:`COB_BIAS_STATES` first-order Gauss-Markov
    states, ``sigma_sun`` and ``sigma_cross`` at the phase angle, decaying as :func:`cob_bias_decay`; the scatter
    about the spin average white.  None where :func:`cob_bias_states` is 0."""
    nb = cob_bias_states(spec, ctx)
    if not nb:
        return None
    pb = ctx.photocentre_bias

    def columns(k, v, D, alpha, r):
        s_sun, s_cross, w_sun, w_cross, _, _ = pb.at(alpha)
        return D * np.stack([s_sun, s_cross], -1)[:, None, :], np.stack([w_sun, w_cross], -1)

    decay, start = cob_bias_decay(spec, ctx)
    return CobBias(nb, columns, decay, start)


def cob_states(spec: RendezvousSpec, ctx: RendezvousContext, cob: CobBias | None) -> tuple[CobBias | None, int]:
    """The bias model the filter runs with (``cob``, or the product's :func:`gauss_markov_cob` for None) and its
    number of states (0 without ``phase_correction``: the photocentre's whole spread is then white)."""
    cob = gauss_markov_cob(spec, ctx) if cob is None else cob
    return cob, (cob.n if (cob is not None and spec.cfg.phase_correction) else 0)


def target_selector(spec: RendezvousSpec, ctx: RendezvousContext, m: dict, cob: CobBias | None = None):
    """The filter's ``select`` hook (``nav/relative_filter.run``): at frame k, each of the frame's candidates
    (``m["cand"]``: the moving unmatched detections of a star frame, the resolved blob of a proximity frame) is
    corrected for the centre of brightness at the predicted range r = |rho_pred| (with ``phase_correction``: moved
    towards the body's centre by the target's mean photocentre offset over attitudes at the phase angle between the
    Sun and its line of sight, :func:`photocentre_table` / ``nav/target_bearing.sphere_phase_correction``), then
    the one nearest the predicted bearing inside the chi-square(2) gate of probability :data:`GATE_PROB` is the
    target (``nav/target_finding.py``).

    What the correction leaves (``scene/photocentre_bias.py``): the spin-averaged photocentre's offset from the
    mean, correlated from frame to frame, goes to the filter's :data:`COB_BIAS_STATES` bias states (the third
    element returned: G (1, 3, 2) = the Sun's projection across the line of sight and its perpendicular, times
    ``sigma_sun`` and ``sigma_cross`` at the phase angle; propagated by :func:`cob_bias_decay`), and only the
    scatter about the spin average (``white_sun``, ``white_cross`` along the same two axes) joins the bearing's
    white covariance, with
    ``(cob_sigma_frac x 2 bounding_radius / r)^2`` in any case.  Without ``phase_correction`` the mean offset is
    not removed and the table's whole spread is white (no bias states: :func:`cob_bias_states`).

    Records per frame the raw and used bearing and covariance (``u``, ``C``, ``u_used``, ``C_used``),
    ``bearing_used``, ``found_by`` (``FOUND_BY`` code) and ``found_true`` (the pick is the true target's
    detection: scored after the pick).  ``cob``: another model of those bias states (:class:`CobBias`; None: the
    product's, :func:`gauss_markov_cob`)."""
    c = spec.cfg
    extra = c.cob_sigma_frac * 2.0 * ctx.shape.bounding_radius
    s = sun_icrs(spec)
    grid, mean, spread = ctx.photocentre
    cob, nb = cob_states(spec, ctx, cob)
    cand = m["cand"]
    gate = chi2_gate_2dof(GATE_PROB)
    hit_code = 1 if spec.is_star else FOUND_BY.index("resolved_blob")

    def select(k, x, P, R_k):
        u_out, C_out, G_out = np.full((1, 3), np.nan), np.zeros((1, 3, 3)), np.zeros((1, 3, max(nb, 1)))
        idx = np.flatnonzero(cand["frame"] == k)
        if idx.size == 0:
            return u_out, C_out, G_out
        u, C = cand["u"][idx], cand["C"][idx]
        r = float(np.linalg.norm(x[0, :3]))
        var = np.full(len(u), extra ** 2)
        v = u
        G = np.zeros((len(u), 3, max(nb, 1)))
        if c.phase_correction:
            alpha = np.arccos(np.clip(-(u @ s), -1.0, 1.0))          # Sun - target - chaser
            v = sphere_phase_correction(u, np.broadcast_to(s, u.shape), np.interp(alpha, grid, mean), r)
            if nb:
                D = cob_axes(v, s)
                G, white = cob.columns(k, v, D, alpha, r)
                Dw = D * white[:, None, :] / r
                C = C + Dw @ np.swapaxes(Dw, -1, -2)
            else:
                var = var + np.interp(alpha, grid, spread) ** 2
        Cv = C + rf.isotropic_bearing_cov(v, np.sqrt(var) / r)
        up, Cp = predicted_bearing(x[:1], P[:1], R_k)
        if nb:                                       # the bias's part of the prediction (its current estimate)
            Gb = G @ P[0, 6:6 + nb, 6:6 + nb] @ np.swapaxes(G, -1, -2) / r ** 2
            proj = np.eye(3) - up[0][:, None] * up[0][None, :]
            Cp = Cp + proj @ Gb[0] @ proj
            off = G[:1] @ x[0, 6:6 + nb] / r
            up = up + off - (off @ up[0])[:, None] * up
            up = up / np.linalg.norm(up, axis=-1, keepdims=True)
        j, code = pick(innovation_d2(v, Cv, up[0], Cp[0]), gate)
        m["found_by"][k] = hit_code if code == 1 else code
        if j < 0:
            return u_out, C_out, G_out
        m["u"][k], m["C"][k], m["u_used"][k], m["C_used"][k] = u[j], C[j], v[j], Cv[j]
        m["target_xy"][k] = cand["xy"][idx[j]]
        m["bearing_used"][k] = True
        m["found_true"][k] = cand["true"][idx[j]]
        return v[j:j + 1], Cv[j:j + 1], G[j:j + 1]

    return select


def cob_bias_states(spec: RendezvousSpec, ctx: RendezvousContext) -> int:
    """:data:`COB_BIAS_STATES` where the mean phase correction is applied and the photocentre statistics are known,
    else 0 (then the table's whole spread is white, as before the bias states)."""
    return COB_BIAS_STATES if (spec.cfg.phase_correction and ctx.photocentre_bias is not None) else 0


def cob_bias_decay(spec: RendezvousSpec, ctx: RendezvousContext):
    """The filter's ``bias_decay`` hook: the correlation ``exp(-dpsi / psi_c)`` of the two bias states between
    frame k - 1 and k, dpsi the angle between the predicted lines of sight of the two frames (ICRS; the target's
    spin axis is fixed in ICRS, so this is the turn of the viewing direction relative to the body's spin) and
    psi_c the correlation's integral scale along the Sun and across at the phase angle
    (``scene/photocentre_bias.correlation_angle``; its 1/e angle is ~3x longer and made the filter
    underconfident on 4 of 6 seeds of the far preset, docs/rendezvous.md).  The statistics turn the observer
    about the Sun; a turn of another axis is taken as the same turn."""
    s = sun_icrs(spec)
    pb = ctx.photocentre_bias
    turn, start = line_of_sight_turn()

    def decay(k, x, R_k):
        dpsi, u = turn(x, R_k)
        if dpsi is None:
            return np.ones((1, COB_BIAS_STATES))
        alpha = float(np.arccos(np.clip(-(u @ s), -1.0, 1.0)))
        *_, c_sun, c_cross = pb.at(alpha)
        return np.exp(-dpsi / np.array([[c_sun, c_cross]]))

    return decay, start


def line_of_sight_turn():
    """A pair ``(turn(x, R_k) -> (dpsi, u), start(x, R_k))`` following the predicted line of sight u = -R_k rho /
    |rho| (ICRS; x (1, >= 3) the predicted state, R_k Hill -> ICRS) from call to call: dpsi the angle (rad) it
    turned since the last call (None at the first, unless ``start`` gave one)."""
    last = {}

    def los(x, R_k):
        rho = x[0, :3]
        return -(R_k @ rho) / np.linalg.norm(rho)

    def turn(x, R_k):
        u = los(x, R_k)
        prev = last.get("u")
        last["u"] = u
        if prev is None:
            return None, u
        return float(np.arctan2(np.linalg.norm(np.cross(prev, u)), prev @ u)), u

    return turn, lambda x, R_k: last.__setitem__("u", los(x, R_k))


def run_filter(spec: RendezvousSpec, ctx: RendezvousContext, draw: dict, m: dict,
               cob: CobBias | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(T, 6) estimates and (T, 6, 6) covariances of the EKF (one approach) from the nominal initial state and the
    spec's prior, with the measurements ``m`` (the target picked and its bearing corrected by
    :func:`target_selector`, its centre-of-brightness bias states by ``cob``, None: the product's) and the nominal
    manoeuvres."""
    c = spec.cfg
    P0 = np.diag(np.array(list(c.prior_position_m) + list(c.prior_velocity_m_s)) ** 2)
    rng = np.where(m["range_used"], m["range_filter"], np.nan)
    cob, nb = cob_states(spec, ctx, cob)
    if nb:
        cob.start(draw["x0_nominal"][None], hill_to_icrs(spec.orbit, spec.times[:1])[0])
    xs, Ps = rf.run(draw["x0_nominal"][None], P0[None], spec.times, spec.orbit, filter_config(c), ranges=rng[None],
                    range_sig_frac=np.nan_to_num(m["range_sigma_frac"], nan=1.0)[None],
                    dv_times=np.asarray(c.manoeuvre_times_s), dv=draw["dv_nominal"] if len(c.manoeuvre_times_s)
                    else None, select=target_selector(spec, ctx, m, cob), n_bias=nb,
                    bias_decay=cob.decay if nb else None)
    return xs[0], Ps[0]


def burn_frames(spec: RendezvousSpec) -> tuple[np.ndarray, int]:
    """(time since the first manoeuvre per frame (s; -1 before it or without one), the frame nearest one orbital
    period after it (-1: none, or beyond the last frame by more than half a frame))."""
    t = spec.times
    c = spec.cfg
    if not c.manoeuvre_times_s:
        return np.full(len(t), -1.0), -1
    t_b = min(c.manoeuvre_times_s)
    since = np.where(t >= t_b, t - t_b, -1.0)
    k = int(np.argmin(np.abs(t - (t_b + spec.orbit.period_s))))
    return since, (k if abs(t[k] - t_b - spec.orbit.period_s) <= 0.5 * c.frame_interval_s else -1)


def compute_case(spec: RendezvousSpec, ctx: RendezvousContext, case_id: int, keep_images: bool = False) -> dict:
    """Draw, simulate, measure and filter one approach; returns every intermediate result with its rows
    (``frames``: a pa.Table, ``case``: a dict)."""
    t0 = time.perf_counter_ns()
    draw = draw_case(spec, case_id)
    truth = truth_trajectory(spec, draw)
    geo = geometry(spec, draw, truth)
    m, images = (measure_star if spec.is_star else measure_prox)(spec, ctx, draw, geo, keep_images)
    t1 = time.perf_counter_ns()
    xs, Ps = run_filter(spec, ctx, draw, m)
    _bearing_scores(m, geo)
    nees = rf.nees(xs, Ps, truth)
    nees_pos = rf.nees(xs[:, :3], Ps[:, :3, :3], truth[:, :3])
    since, k = burn_frames(spec)
    t2 = time.perf_counter_ns()
    out = {"draw": draw, "camera": spec.camera, "times": spec.times, "truth": truth, "geo": geo, "meas": m, "est": xs,
           "cov": Ps,
           "nees": nees, "nees_pos": nees_pos, "t_since_burn": since, "orbit_frame": k,
           "dv_nominal": draw["dv_nominal"], "dv_exec": draw["dv_exec"], "t_nav_ns": t2 - t1, "t_total_ns": t2 - t0,
           "images": images}
    out["view"] = frame_view(spec, geo, truth)          # [rendezvous.environment] (issue 23 point 1), else None
    out["frames"] = frames_table(case_id, out)
    out["case"] = case_row(case_id, spec.seed, "star" if spec.is_star else "proximity",
                           spec.cfg.converged_after_frames, out)
    return out


def compute_shard(spec: RendezvousSpec, case_ids: np.ndarray, ctx: RendezvousContext) -> dict[str, pa.Table]:
    """The engine's contract: one ``rendezvous_cases`` row and ``frames`` ``rendezvous_frames`` rows per case."""
    frames, rows = [], []
    for i in np.asarray(case_ids, np.int64):
        o = compute_case(spec, ctx, int(i))
        frames.append(o["frames"])
        rows.append(o["case"])
    cases = pa.Table.from_pylist(rows, schema=CASES_SCHEMA) if rows else CASES_SCHEMA.empty_table()
    fr = pa.concat_tables(frames) if frames else FRAMES_SCHEMA.empty_table()
    return {"rendezvous_cases": cases, "rendezvous_frames": fr}


def shard_summary(tables: dict[str, pa.Table]) -> dict:
    f = tables["rendezvous_frames"]
    used = f.column("bearing_used").to_numpy(zero_copy_only=False)
    return {"frames": int(f.num_rows), "bearings": int(np.sum(used))}


def progress_postfix(stats: dict) -> str:
    n = stats.get("frames", 0)
    return f"bearings {100 * stats.get('bearings', 0) / n:.1f}% of frames" if n else ""
