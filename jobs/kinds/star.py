"""Star-tracker software-in-the-loop job: the whole chain for a batch of cases (orchestration only).

    draw attitudes (here) -> stars in the field (scene.starfield_geometry) -> render and detect/centroid
    (kernels.starfield, kernels.detect) -> back-project (nav.observations) -> geometric voting + T and
    SVD attitude + Eqs. 4-7 (nav.star_solution) -> truth of the detections (nav.truth_match) -> Arrow rows

One row per case in ``star_cases`` and one row per detection in ``star_detections``.  Case ``i`` draws
its attitude and its sensor-noise seed from ``default_rng([seed, i])`` only.

Spec (TOML; every table optional, defaults = preset ``paper``)::

    seed = 1
    cases = 200
    batch_size = 64               # frames per kernel batch
    attitudes = "euler123"        # reference: 3 angles uniform in [-180, 180) deg, 1-2-3; or "uniform" (SO(3))
    error_frame = "camera"        # axes of Eqs. 4-7: "camera" (x, y across the boresight, z roll) or "inertial"
    detector = "auto"             # "global" (the reference's one threshold), "local" (kernels/detect_local.py,
                                  # as hil star), "auto": local when the sensor has stray light or bright objects
    compare_robust = true         # dualsight's robust identification beside the reference's on every case
    [camera]   ... (scene/camera.py)
    [catalog]  mag_limit = 5.5, epoch_jyear = 2000.0
    [sensor]   ... (kernels/sensor_config.py SensorConfig)
    [detect]   ... (kernels/detect.py DetectConfig)
    [voting]   ... (nav/starid.py VotingConfig; angles as *_arcsec)
    [robust]   ... (the same keys, for the robust method)
    [target]   ... (scene/target_config.py TargetConfig: a spacecraft in the field, issue 23; absent = none, and the
                   run is exactly the run of the same spec before [target] existed, with the target columns null)
    [output]   detections = "auto" (or "on", "off"), detections_max_cases = 100000 (OutputConfig below;
               jobs/kinds/star_output.py: whether star_detections is written, part of the identity)
"""

from __future__ import annotations

import dataclasses
import math
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pydantic
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from dualsight.catalogs.pair_cache import load_pair_catalog
from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
from dualsight.errors import ConfigError
from dualsight.jobs.kinds import star_summaries
from dualsight.jobs.kinds.star_tables import CASES_SCHEMA, DETECTIONS_SCHEMA, cases_table, detections_table
from dualsight.jobs.kinds.star_output import with_case_count
from dualsight.jobs.engine.runner import prepare, run_job
from dualsight.config import check_fields, dataclass_from_table, dataclass_to_table, validate
from dualsight.scene.target_config import TargetConfig
from dualsight.jobs.engine.specs import preset_and_config, seed_and_case_count
from dualsight.kernels import detect as kdetect
from dualsight.kernels import starfield as kstar
from dualsight.kernels.detect import DetectConfig
from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
from dualsight.nav.errors import STATUS_NAMES
from dualsight.nav.resolved_blobs import excluded_blobs, star_blob_limit, without_excluded
from dualsight.nav.observations import observations
from dualsight.nav.pair_index import VotingIndex
from dualsight.nav.star_solution import centroid_weights, identify, solve
from dualsight.nav.truth_match import match_truth
from dualsight.nav.voting_config import VotingConfig
from dualsight.scene.attitude import euler123_to_dcm, quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.camera import Camera
from dualsight.scene.case_rng import streams as case_streams
from dualsight.scene.psf_file import sensor_psf, with_psf_digest
from dualsight.scene.case_environment import CaseEnvironment, draw_environment
from dualsight.scene.satellite import load_satellite
from dualsight.scene.starfield_geometry import FieldStars, stars_in_field
from dualsight.scene.target_in_field import MAX_WINDOW_PX, diameter_px, draw_targets, target_frames, with_target
from dualsight.scene.target_photometry import photocentre_table, target_shape
from dualsight.jobs.kinds.star_target import environment_columns, target_bearing_columns, target_columns

NAME = "star"
PRIMARY = "star_cases"

PRESETS = {
    # The reference's star SIL (section 3.2-3.3): 1024x768, 4.65 um, 17 mm (19.9 deg diagonal),
    # catalog to V 5.5, ideal images, slight defocus; 200 random 1-2-3 attitudes.
    "paper": {
        # batch 256: the sparse path's kernel launches and per-batch Python amortised over more cases
        # (in-process, one thread: ~1.4x the cases/s of batch 64; results do not depend on the batch)
        "seed": 1, "cases": 200, "batch_size": 256, "attitudes": "euler123", "error_frame": "camera",
        "camera": {"width": 1024, "height": 768, "pixel_pitch_um": 4.65, "focal_length_mm": 17.0},
        "catalog": {"mag_limit": 5.5, "epoch_jyear": 2000.0},
        "sensor": {},
        "detect": {},
        # The reference gives no voting tolerance; 10 arcsec (0.18 px of this camera) is ~10x the pair-angle
        # error of its noise-free centroids and keeps chance votes rare (measured: 5-20 arcsec all work).
        "voting": {"tolerance_arcsec": 10.0},
        "compare_robust": True,
        "robust": {},
    },
}
PRESETS["noisy"] = {**PRESETS["paper"], "batch_size": 16,           # full frames: 16 x 1024 x 768 per batch
                   "sensor": {"shot_noise": True, "read_noise_e": 10.0,
                              "sky_background_e": 50.0, "dark_current_e_per_s": 20.0}}
# Sensor presets on the reference's camera (kernels/sensor_config.py SensorConfig; "paper" above: ideal images,
# slight defocus, 12-bit ADC that saturates the brightest stars at 20 ke-).
# "ideal": the paper's sensor without saturation (full well never reached, 16-bit ADC): optics and algorithms only.
PRESETS["ideal"] = {**PRESETS["paper"], "sensor": {"full_well_e": 1e12, "bit_depth": 16}}
# "realistic": a small-satellite CMOS star camera (examples/star/realistic_sensor.toml has the same numbers).
PRESETS["realistic"] = {
    **PRESETS["paper"], "batch_size": 16,        # full frames are rendered: 16 x 1024 x 768 per batch
    "sensor": {
        # PSF: star trackers defocus so a star covers ~3x3 to 5x5 px for sub-pixel centroids (Liebe 2002,
        # IEEE TAES 38(2) 587): a 1.5 px radius disk blurred by a 0.5 px Gaussian (lens, charge diffusion).
        "psf_model": "defocus", "defocus_radius_px": 1.5, "defocus_gaussian": True, "psf_sigma_px": 0.5,
        "psf_window_sigma": 5.0,
        "exposure_s": 0.1,                       # typical star-tracker exposures: 50-200 ms
        # Detector: CMOSIS (ams) CMV4000 datasheet, a CMOS sensor flown in CubeSat star trackers: full well
        # 13.5 ke-, dark (read) noise 13 e- rms, dark current 125 e-/s at 25 C, 12-bit ADC.
        "full_well_e": 13500.0, "read_noise_e": 13.0, "dark_current_e_per_s": 125.0, "bit_depth": 12,
        "gain_e_per_adu": 3.3,                   # full well / 4095 ADU: the ADC spans the well
        "bias_adu": 32.0,                        # black level: > 8 sigma of the read noise (3.9 ADU) above 0
        "shot_noise": True,
        # Sky: zodiacal + diffuse galactic light ~V 22 mag/arcsec^2 (Leinert et al. 1998, A&AS 127, 1) over a
        # 56 arcsec pixel (4.65 um / 17 mm) = V 13.2 per pixel: 0.8 e- in 0.1 s at the default zero point.
        "sky_background_e": 0.8,
        # Hot pixels: assumed order of magnitude for a CMOS sensor after ~1 year in LEO (1e-4 of the pixels,
        # 20 ke-/s each), one fixed map (a property of the sensor).
        "hot_pixel_fraction": 1e-4, "hot_pixel_e": 2000.0, "hot_pixel_seed": 1,
    },
    "detect": {"k_sigma": 5.0, "min_pixels": 3},
    "voting": {"tolerance_arcsec": 20.0},        # noisy centroids: as examples/star/noisy_sensor.toml
    "detector": "local",                         # what `hil star` runs on real frames: SIL predicts HIL
}


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


@dataclass(frozen=True)
class StarSpec:
    """A validated star-tracker job."""

    camera: Camera
    catalog: StarCatalogConfig
    sensor: SensorConfig
    detect: DetectConfig
    voting: VotingConfig
    robust: VotingConfig | None = None
    seed: int = 1
    batch_size: int = 64
    attitudes: Literal["euler123", "uniform"] = "euler123"
    error_frame: Literal["camera", "inertial"] = "camera"
    detector: Literal["global", "local"] = "global"     # "auto" in a TOML is resolved by auto_detector()
    source: str = field(default="defaults", compare=False)
    target: TargetConfig | None = None                  # issue 23: a spacecraft in the field
    keep_detections: bool = True                        # issue 24.5: [output] detections, resolved (OutputConfig)

    def to_dict(self) -> dict:
        d = {"seed": self.seed, "batch_size": self.batch_size, "attitudes": self.attitudes,
             "error_frame": self.error_frame, "detector": self.detector, "camera": self.camera.to_dict(),
             "catalog": dataclass_to_table(self.catalog), "sensor": _sensor_table(self.sensor),
             "detect": dataclass_to_table(self.detect), "voting": dataclass_to_table(self.voting),
             "compare_robust": self.robust is not None,
             "robust": dataclass_to_table(self.robust) if self.robust is not None else {}}
        if self.target is not None:      # only then: the canonical spec of a run without a target is unchanged
            d["target"] = {k: v for k, v in dataclass_to_table(self.target).items() if v is not None}
        if not self.keep_detections:     # only then: a run that keeps them has the canonical spec it always had
            d["output"] = {"detections": "off"}
        return d


def _sensor_table(sensor: SensorConfig) -> dict:
    """The sensor's spec table; ``psf_image_sha256`` only with a PSF image, so the canonical spec of every other
    sensor (and the nightly's comparison of specs) is what it was before that key existed."""
    t = dataclass_to_table(sensor)
    if t.get("psf_image_sha256") is None:
        t.pop("psf_image_sha256", None)
    return t


class StarTable(BaseModel):
    """The top level of a star spec's TOML layout (pydantic); the sections are validated into their
    dataclasses by :func:`dualsight.config.dataclass_from_table`."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    seed: int = Field(1, ge=0, le=2**63 - 1)
    cases: int | None = Field(None, ge=1, le=10**9)
    batch_size: int = Field(64, ge=1, le=4096)
    attitudes: Literal["euler123", "uniform"] = "euler123"
    error_frame: Literal["camera", "inertial"] = "camera"
    detector: Literal["auto", "global", "local"] = "auto"
    compare_robust: bool = True
    preset: str | None = None
    camera: dict
    catalog: dict = {}
    sensor: dict = {}
    detect: dict = {}
    voting: dict = {}
    robust: dict = {}
    target: dict | None = None
    output: dict = {}


def spec_from_dict(d: dict, source: str = "spec") -> StarSpec:
    """Validate a spec dict (TOML layout); every error names ``source`` and the key."""
    top = validate(StarTable, d, source=source)
    camera = Camera.from_dict(top.camera, source=source)
    seed, bs, att, frame, cmp_ = top.seed, top.batch_size, top.attitudes, top.error_frame, top.compare_robust
    catalog = dataclass_from_table(StarCatalogConfig, d.get("catalog"), source=source, section="catalog")
    sensor = with_psf_digest(dataclass_from_table(SensorConfig, d.get("sensor"), source=source, section="sensor"),
                             error=lambda msg: ConfigError(msg, source=source, field="sensor"))
    detect = dataclass_from_table(DetectConfig, d.get("detect"), source=source, section="detect")
    voting = dataclass_from_table(VotingConfig, d.get("voting"), source=source, section="voting",
                                  base=VotingConfig.paper())
    robust = (dataclass_from_table(VotingConfig, d.get("robust"), source=source, section="robust",
                                   base=VotingConfig.robust(tolerance_rad=voting.tolerance_rad))
              if cmp_ else None)
    target = target_from_table(d.get("target"), camera, source) if top.target is not None else None
    # "auto" against the table's case count (resolve() puts the run's there; none: kept)
    out = dataclass_from_table(OutputConfig, d.get("output"), source=source, section="output")
    return StarSpec(camera=camera, catalog=catalog, sensor=sensor, detect=detect, voting=voting, robust=robust,
                    seed=int(seed), batch_size=int(bs), attitudes=att, error_frame=frame,
                    detector=auto_detector(sensor) if top.detector == "auto" else top.detector, source=source,
                    target=target, keep_detections=out.keeps_detections(top.cases or 0))


def target_from_table(table: dict, camera: Camera, source: str) -> TargetConfig:
    """The ``[target]`` table validated (``TargetConfig``), its satellite file read and checked
    (``scene/satellite.load_satellite``: errors name that file and key), and its nearest range checked against the
    largest window a resolved target may take (``scene/target_in_field.MAX_WINDOW_PX``)."""
    cfg = dataclass_from_table(TargetConfig, table, source=source, section="target")
    sat = load_satellite(cfg.satellite)
    diam = float(diameter_px(target_shape(sat.components).bounding_radius, cfg.range_m[0], camera))
    if diam > MAX_WINDOW_PX - 8:
        raise ConfigError(f"the target ({cfg.satellite}) is {diam:.0f} px across at {cfg.range_m[0]:g} m; the "
                          f"nearest range must keep it under {MAX_WINDOW_PX - 8} px",
                          source=source, field="target.range_m")
    return cfg


def auto_detector(sensor: SensorConfig) -> Literal["global", "local"]:
    """The detector that ``detector = "auto"`` (the default) resolves to, stored in the spec.

    "global" (the reference's one threshold per frame, kernels/detect.py) where its assumption holds: one
    background level over the frame (the ideal, paper and noisy presets; its 3-pixel minimum blob size drops
    hot pixels and pairs of them); "local" (kernels/detect_local.py, what ``hil star`` uses on real frames)
    when the background varies over the frame: stray-light gradients (measured on the realistic preset plus
    200 e- of stray light rising to ~430 e- at a corner: the global detector finds 12 % of the stars with
    SNR >= 10, the local one 99 %) or bright objects (the Moon).  The ``realistic`` preset asks for "local"
    itself, so that SIL frames go through the detector HIL uses."""
    real = sensor.has_stray_light or bool(sensor.bright_objects)
    return "local" if real else "global"


def resolve(preset: str | None, config: Path | str | dict | None, *, seed: int | None = None,
            cases: int | None = None, detections: str | None = None) -> tuple[StarSpec, int]:
    """Merge preset, config file and flags into the validated spec; returns (spec, number of cases).

    The one way from the command line to a spec: ``spec.to_dict()`` is its canonical dict (what the
    engine stores).  The catalog is built (or read from the cache) here, so a magnitude limit that leaves
    too few stars fails before anything touches the lake."""
    d, source = preset_and_config(PRESETS, preset, config)
    n = seed_and_case_count(d, seed, cases, 200, source)
    d = with_case_count(d, n, detections)
    spec = spec_from_dict(d, source=source)
    load_star_catalog(spec.catalog)
    return spec, int(n)


def resolve_spec(preset: str | None, config: Path | str | dict | None, *, seed: int | None = None,
                 cases: int | None = None, detections: str | None = None) -> tuple[dict, int]:
    """:func:`resolve` in the engine's form: (``spec.to_dict()``, number of cases)."""
    spec, n = resolve(preset, config, seed=seed, cases=cases, detections=detections)
    return spec.to_dict(), n


def catalog_info(spec: StarSpec | dict) -> dict:
    """Size of the run's star and pair catalogs (built or read from the cache, as the workers load them).

    ``spec``: the spec, or its dict form (validated by :func:`spec_from_dict`)."""
    if not isinstance(spec, StarSpec):
        spec = spec_from_dict(spec)
    ctx = make_context(spec)
    return {"stars": len(ctx.catalog.hip), "mag_limit": spec.catalog.mag_limit, "pairs": len(ctx.pairs.angle),
            "pair_max_angle_deg": math.degrees(pair_angle(spec.camera)),
            "pair_catalog_bytes": int(ctx.pairs.nbytes), "star_catalog_bytes": int(ctx.catalog.nbytes)}


# ------------------------------------------------------------------------------------------ a run
@dataclass(frozen=True)
class StarRun:
    """A star Monte Carlo resolved and identified but not yet run (:func:`plan_run`, :func:`start_run`)."""

    spec: dict               # the canonical spec dict (``spec.to_dict()``)
    n_cases: int
    run_id: str
    spec_hash: str           # 16 hex digits (jobs/engine/runner.py spec_hash)
    source: str              # where the settings came from, for messages
    catalog: dict            # catalog_info(spec), stored in the manifest


def plan_run(preset: str | None = None, config: Path | str | dict | None = None, *, seed: int | None = None,
             cases: int | None = None, run_id: str | None = None, detections: str | None = None) -> StarRun:
    """Everything ``dualsight star run`` decides before the lake is touched, for it and ``dualsight.run``:
    the preset (default paper), the config file or table over it and the flags merged and validated
    (:func:`resolve_spec`), the run's identity (``prepare`` of jobs/engine/runner.py), its id (``run_id``, default
    ``star-<seed>-<cases>-<first 8 digits of the spec hash>``) and the catalog sizes (:func:`catalog_info`)."""
    spec_dict, n = resolve_spec(preset, config, seed=seed, cases=cases, detections=detections)
    source = (("config table" if isinstance(config, dict) else str(config)) if config is not None
              else f"preset {preset or 'paper'}")
    _, _, _, h = prepare(NAME, spec_dict, n, source=source)
    return StarRun(spec_dict, n, run_id or f"star-{spec_dict['seed']}-{n}-{h[:8]}", h, source,
                   catalog_info(spec_dict))


def start_run(plan: StarRun, lake, *, workers: int | None = None, scheduler: str | None = None,
              shard_size: int | None = None, progress: bool = True) -> dict:
    """Run (or resume) a planned star Monte Carlo into ``lake`` (a warehouse Lake) with the engine's ``run_job``;
    returns the final manifest.  Errors as ``run_job``'s (InputError, LakeError, EngineError, Interrupted)."""
    return run_job(NAME, plan.spec, n_cases=plan.n_cases, lake=lake, run_id=plan.run_id, workers=workers,
                   scheduler=scheduler, shard_size=shard_size, progress=progress, label=f"star {plan.run_id}",
                   extra={"catalog": plan.catalog})


# ------------------------------------------------------------------------------------------ context
@dataclass(frozen=True)
class StarContext:
    """Per-process state: the star catalog, its pair catalog (read from the cache), the pair catalog's voting
    index (its derived arrays mapped from the cache, written there first if missing: ``VotingIndex.load_or_build``)
    and the sensor's measured PSF, read once per process (``psf``: a read-only (ny, nx) float64 array of unit
    sum, the fraction of a star's electrons per pixel, with ``psf_model = "image"``; else None)."""

    catalog: object
    pairs: object
    index: object
    psf: np.ndarray | None = None
    target_sat: object = None          # with [target]: its SatelliteConfig ...
    target_shape: object = None        # ... its photometric elements (scene/target_photometry.TargetShape) ...
    star_blob_limit: int | None = None  # ... and the most pixels a star's blob may have (nav/resolved_blobs.py)
    target_photocentre: tuple = ()      # with phase_correction: scene/target_photometry.photocentre_table(shape)


def pair_angle(camera: Camera) -> float:
    """Largest angle (rad) between two stars of one image: the field's diagonal (the pair catalog's limit)."""
    return camera.fov_rad[2]


def make_context(spec: StarSpec) -> StarContext:
    cat = load_star_catalog(spec.catalog)
    pairs = load_pair_catalog(cat, pair_angle(spec.camera))
    psf = sensor_psf(spec.sensor, error=lambda msg: ConfigError(msg, source=spec.source, field="sensor"))
    if spec.target is None:
        return StarContext(cat, pairs, VotingIndex.load_or_build(pairs), psf)
    sat = load_satellite(spec.target.satellite)
    shape = target_shape(sat.components)
    return StarContext(cat, pairs, VotingIndex.load_or_build(pairs), psf, sat, shape,
                       brightest_star_blob_limit(spec, float(np.min(cat.vmag)), psf),
                       photocentre_table(shape) if spec.target.phase_correction else ())


BLOB_PROBES = 8
"""Sub-pixel positions at which :func:`brightest_star_blob_limit` renders the brightest star."""


def brightest_star_blob_limit(spec: StarSpec, vmag: float, psf: np.ndarray | None = None) -> int:
    """The most pixels a star's blob may have under this spec (``nav/resolved_blobs.star_blob_limit``): a star of
    ``vmag`` (the catalog's brightest) rendered alone at :data:`BLOB_PROBES` sub-pixel positions near the image
    centre through the spec's own sensor and detector (noise seeds 1..n), its largest blob measured."""
    cam, n = spec.camera, BLOB_PROBES
    k = np.arange(n)
    x = (cam.width // 2 + (k % 4) / 4.0 + 0.125)[:, None]
    y = (cam.height // 2 + (k // 4) / 2.0 + 0.25)[:, None]
    flux = np.full((n, 1), float(flux_from_magnitude(vmag, spec.sensor)), np.float32)
    one = np.ones((n, 1), bool)
    fs = FieldStars(x, y, flux, one, np.zeros((n, 1), np.int64), one, np.ones(n, np.int64))
    r = render_and_detect(fs, np.arange(1, n + 1, dtype=np.uint64), cam, spec.sensor, spec.detect,
                          attitude=np.tile(np.eye(3), (n, 1, 1)), detector=spec.detector, psf=psf)
    npix = r.detections.npix
    return star_blob_limit(npix if len(npix) else np.ones(1))


# ------------------------------------------------------------------------------------------ cases
def draw_cases(spec: StarSpec, case_ids: np.ndarray) -> dict:
    """Inputs of each case from ``default_rng([seed, case_id])``: attitude and the sensor-noise seed.

    Returns dict of arrays: angles (B,3) rad (NaN for "uniform"), quat (B,4), A_true (B,3,3), noise_seed (B,) uint64.
    """
    B = len(case_ids)
    angles = np.full((B, 3), np.nan)
    quat = np.full((B, 4), np.nan)
    # one generator per case, default_rng([seed, i]), all stepped at once (scene/case_rng.py: the same
    # draws bit for bit), so a case never depends on its batch
    rng = case_streams(spec.seed, np.asarray(case_ids, np.int64))
    if spec.attitudes == "euler123":
        angles = np.stack([rng.uniform(-np.pi, np.pi) for _ in range(3)], axis=-1)
    else:
        quat = quaternions_from_uniforms(rng.random(), rng.random(), rng.random())
    noise = rng.integers_63()
    A = euler123_to_dcm(angles) if spec.attitudes == "euler123" else quat_to_dcm(quat)
    return {"angles": angles, "quat": quat, "A_true": A, "noise_seed": noise}


def compute_shard(spec: StarSpec, case_ids: np.ndarray, ctx: StarContext) -> dict[str, pa.Table]:
    """The engine's contract: rows of ``case_ids`` (int64, ascending) in kernel batches of ``spec.batch_size``,
    and the shard's exact partial aggregates for the report (``star_summaries``, :mod:`dualsight.jobs.kinds.star_summaries`)."""
    parts = {d: [] for d in datasets(spec) if d != star_summaries.DATASET}
    for s in range(0, len(case_ids), spec.batch_size):
        out = compute_batch(spec, ctx, case_ids[s: s + spec.batch_size])["tables"]
        for d in parts:
            parts[d].append(out[d])
    tables = {d: pa.concat_tables(parts[d]) if parts[d] else SCHEMAS[d].empty_table() for d in parts}
    tables[star_summaries.DATASET] = star_summaries.summarize(tables["star_cases"])
    return tables


def catalog_bytes(mag_limit: float, pair_angle_rad: float) -> int:
    """Estimated bytes of the star catalog to ``mag_limit`` and its pair catalog to ``pair_angle_rad``.

    Stars from the Hipparcos count-magnitude relation log10 N = 0.52 V + 0.1 (fit to V 5.5: 2.9k, V 7: 16k,
    V 9: 120k), ~200 bytes each; pairs ~ N^2/2 x (1 - cos d)/2 (the sky fraction of a cap of radius d),
    24 bytes each (angle, two indices), twice for sorting scratch.
    """
    n_stars = 10 ** (0.52 * mag_limit + 0.1)
    pairs = n_stars ** 2 / 2 * (1 - math.cos(min(pair_angle_rad, math.pi))) / 2
    return int(2 * 24 * pairs + 200 * n_stars)


def memory_estimate(spec: StarSpec) -> int:
    """Peak bytes one worker needs for this spec, estimated before anything is allocated.

    Frames: ``batch_size`` x width x height float32 images (three planes) when the dense path runs (noise-free
    frames take the sparse path: windows around stars only), and there the digest's weight table (8 bytes per
    pixel, ``kernels/starfield.digest_weights``); plus :func:`catalog_bytes` for the magnitude limit and the
    field diagonal.
    """
    w, h = spec.camera.width, spec.camera.height
    frames = (3 * 4 * spec.batch_size + 8) * w * h if not spec.sensor.is_ideal else 0
    return frames + catalog_bytes(spec.catalog.mag_limit, pair_angle(spec.camera))


# ------------------------------------------------------------------------------------------ render
@dataclass(frozen=True)
class Rendered:
    """The batch's frames through the render and detection kernels.

    detections : ``kernels.detect.Detections``; images : (B, H, W) float32 when kept (replay), else None;
    t_render_ns, t_detect_ns : wall time of the stages (t_detect_ns None: detection ran fused into the
    sparse render, not as its own stage).
    digest : (B,) uint64 digest of each full frame (:mod:`dualsight.kernels.digest`, sky = the sensor's
        empty-sky level), the same whether the frame was rendered whole or only around its stars.
    """

    detections: object
    images: np.ndarray | None
    t_render_ns: int
    t_detect_ns: int | None
    digest: np.ndarray


def psf_margin_px(sensor: SensorConfig, camera: Camera | None = None, psf: np.ndarray | None = None) -> float:
    """How far outside the frame (px) a star still puts light into it: the PSF's reach
    (``SensorConfig.psf_reach_px``: Gaussian window, defocus disk or PSF image) plus, with an angular rate
    and a camera, the longest smear over the field, ``|w| t (f (1 + (r/f)^2) + r)`` with r the half
    diagonal (the image motion of a star at radius r under a rate w about any axis, small-angle).
    ``psf``: the measured PSF ((ny, nx) float64, unit sum: ``StarContext.psf``), needed with
    ``psf_model = "image"``."""
    reach = float(sensor.psf_reach_px(psf))
    rate = getattr(sensor, "rate_deg_s", None)
    if rate is not None and camera is not None and any(rate):
        w = math.radians(math.hypot(*rate))
        f = max(camera.fx, camera.fy)
        r = 0.5 * math.hypot(camera.width, camera.height)
        reach += w * sensor.exposure_s * (f * (1.0 + (r / f) ** 2) + r)
    return reach


def local_detect_config(sensor: SensorConfig, detect_cfg: DetectConfig):
    """The real-sensor detector's settings for a simulated sensor: its threshold (``k_sigma``), the
    Gaussian PSF width it was rendered with (measured per frame for other PSF models), its gain (for the
    stars' own shot noise in the centroid uncertainty) and its ADC full scale (saturation)."""
    from dualsight.kernels.detect_local import LocalDetectConfig

    return LocalDetectConfig(k_sigma=max(1.0, detect_cfg.k_sigma),
                             psf_sigma_px=(max(0.2, sensor.psf_sigma_px) if sensor.psf_model == "gaussian"
                                           else None),
                             gain_e_per_adu=sensor.gain_e_per_adu)


def render_and_detect(field_: FieldStars, noise_seeds: np.ndarray, camera: Camera, sensor: SensorConfig,
                      detect_cfg: DetectConfig, keep_images: bool = False, attitude: np.ndarray | None = None,
                      detector: str = "global", psf: np.ndarray | None = None) -> Rendered:
    """Render the batch's star fields and detect/centroid the stars (Taichi kernels).

    attitude : (B, 3, 3) true attitudes (inertial -> camera), for the effects that need them (motion
    smear, bright objects: kernels/psf_models.py).  Noise-free frames that need not be kept take the
    sparse path (render and label only the windows around stars: the same blobs as full frames).
    detector : "global" (kernels/detect.py: one level per frame, the reference's thresholding) or "local"
    (kernels/detect_local.py, as for real frames: tiled background, matched filter, PSF-fit centroids with
    their uncertainty; always on full frames).
    psf : the measured PSF, (ny, nx) float64 of unit sum (fraction of a star's electrons per pixel:
    ``StarContext.psf``), needed with ``sensor.psf_model = "image"``, else ignored."""
    t0 = time.perf_counter_ns()
    if sensor.is_ideal and not keep_images and detector == "global":
        det, digest = kdetect.render_and_detect_ideal(field_.x, field_.y, field_.flux_e, field_.valid, camera.width,
                                                      camera.height, sensor, detect_cfg, noise_seeds, digest=True)
        return Rendered(det, None, time.perf_counter_ns() - t0, None, digest)
    # the frames' digests are summed inside the render pass (no second pass over the frames)
    images, digest = kstar.render_star_fields(field_.x, field_.y, field_.flux_e, field_.valid, camera.width,
                                              camera.height, sensor, noise_seeds, camera=camera, attitude=attitude,
                                              psf=psf, digest=True)
    t1 = time.perf_counter_ns()
    if detector == "local":
        from dualsight.kernels.detect_local import detect_real

        det = detect_real(images, local_detect_config(sensor, detect_cfg), saturation_adu=float(sensor.max_adu))
    else:
        det = kdetect.detect_stars(images, detect_cfg)
    t2 = time.perf_counter_ns()
    return Rendered(det, images if keep_images else None, t1 - t0, t2 - t1, digest)


def compute_batch(spec: StarSpec, ctx: StarContext, case_ids: np.ndarray, keep_images: bool = False) -> dict:
    """The whole chain for a batch; returns every intermediate result and the Arrow tables.

    Keys: draw, field, rendered (detections, images if ``keep_images``), obs, ident, sol, alt, truth, tables.
    """
    B = len(case_ids)
    t = {}
    t0 = time.perf_counter_ns()
    draw = draw_cases(spec, case_ids)
    cat = ctx.catalog
    flux = flux_from_magnitude(cat.vmag.astype(np.float64), spec.sensor)
    field_ = stars_in_field(draw["A_true"], cat.unit, flux, spec.camera,
                            psf_margin_px(spec.sensor, spec.camera, ctx.psf))
    render_field, tcases, tf, env = field_, None, None, None
    if spec.target is not None:      # issue 23: the target's light joins the stars', the stars behind it dim
        env = case_environment(spec, case_ids, draw["A_true"])      # [target.environment] (issue 23), else None
        tcases = draw_targets(spec.target, spec.seed, case_ids, draw["A_true"], spec.camera,
                              sun_icrs=env.sun_dir if env is not None else None)
        if env is not None:     # a target in the Earth's umbra is dark (within 10 km it shares the camera's shadow)
            tcases = dataclasses.replace(tcases, present=tcases.present & ~env.view.umbra)
        tf = target_frames(spec.target, ctx.target_sat, ctx.target_shape, tcases, field_, spec.camera, spec.sensor)
        render_field, field_ = with_target(field_, tf)
    t["sample"] = time.perf_counter_ns() - t0

    r = render_and_detect(render_field, draw["noise_seed"], spec.camera, spec.sensor, spec.detect,
                          keep_images=keep_images, attitude=draw["A_true"], detector=spec.detector, psf=ctx.psf)
    t["render"], t["detect"] = r.t_render_ns, r.t_detect_ns

    t1 = time.perf_counter_ns()
    obs = observations(r.detections, B, spec.camera)
    excluded = None
    if spec.target is not None and spec.target.exclude_resolved:   # blobs no star can make never vote
        excluded = excluded_blobs(r.detections.npix, ctx.star_blob_limit)
        obs = without_excluded(obs, r.detections.case, r.detections.offsets, excluded)
    # the reference's method: its chance probability is not stored (p_chance is the robust method's)
    ident = identify(obs, cat.unit, ctx.index, spec.voting, cat_vmag=cat.vmag, chance=False)
    t["identify"] = time.perf_counter_ns() - t1

    t2 = time.perf_counter_ns()
    # centroid uncertainties as attitude weights when the detector states them (local detector; a 0.02 px
    # floor for the PSF model's own error), else equal weights
    weights = centroid_weights(r.detections, obs, 0.02)
    sol = solve(obs, ident, cat.unit, draw["A_true"], spec.error_frame, weights=weights)
    t["attitude"] = time.perf_counter_ns() - t2

    alt = None
    if spec.robust is not None:   # dualsight's method beside the reference's, on the same detections
        t3 = time.perf_counter_ns()
        ident_r = identify(obs, cat.unit, ctx.index, spec.robust, cat_vmag=cat.vmag)
        alt = (ident_r, solve(obs, ident_r, cat.unit, draw["A_true"], spec.error_frame, weights=weights))
        t["robust"] = time.perf_counter_ns() - t3

    truth = match_truth(r.detections, field_, obs, cat.hip)
    per_case = {k: (np.full(B, v // max(B, 1), dtype=np.int64) if v is not None else None) for k, v in t.items()}
    tcols = (target_columns(tcases, tf, r.detections, obs, ident, alt, excluded,
                            bearing=target_bearing_columns(spec, tf, tcases, r.detections, obs, ident, sol, alt,
                                                           cat.unit, draw["A_true"], ctx))
             if tf is not None else None)
    tables = {"star_cases": cases_table(case_ids, spec, draw, field_, r.detections, obs, ident, sol, truth, per_case,
                                        alt, r.digest, target=tcols[0] if tcols else None,
                                        environment=environment_columns(env)),
              "star_detections": detections_table(case_ids, r.detections, obs, ident, sol, truth, ctx.catalog,
                                                  target=tcols[1] if tcols else None)}
    return {"draw": draw, "field": field_, "rendered": r, "obs": obs, "ident": ident, "sol": sol, "alt": alt,
            "truth": truth, "tables": tables, "target": tf, "target_cases": tcases, "excluded": excluded,
            "environment": env}


def case_environment(spec: StarSpec, case_ids: np.ndarray, A_true: np.ndarray) -> CaseEnvironment | None:
    """Each case's epoch, place in orbit and view of the Sun, Earth and Moon with ``[target.environment]``
    (``scene/case_environment.py``; the Sun's keep-out half-angle is ``[target] sun_keepout_deg``), else None."""
    if spec.target is None or spec.target.environment is None:
        return None
    return draw_environment(spec.target.environment, spec.seed, case_ids, A_true,
                            math.radians(spec.target.sun_keepout_deg))


# ------------------------------------------------------------------------------------------ tables
SCHEMAS = {"star_cases": CASES_SCHEMA, "star_detections": DETECTIONS_SCHEMA,
           star_summaries.DATASET: star_summaries.SCHEMA}


def datasets(spec: StarSpec) -> list[str]:
    """The datasets a run of ``spec`` writes (the engine's optional hook): :data:`SCHEMAS` without
    ``star_detections`` when the spec drops them (``[output] detections``, issue 24.5)."""
    return [d for d in SCHEMAS if spec.keep_detections or d != "star_detections"]


# ------------------------------------------------------------------------------------------ progress
def shard_summary(tables: dict[str, pa.Table]) -> dict:
    st = tables["star_cases"].column("status").to_numpy(zero_copy_only=False)
    return {name: int((st == name).sum()) for name in STATUS_NAMES}


def progress_postfix(stats: dict) -> str:
    n = sum(stats.get(k, 0) for k in STATUS_NAMES)
    if not n:
        return ""
    return f"success {100 * stats.get('success', 0) / n:.1f}%, conf-wrong {100 * stats.get('confident_wrong', 0) / n:.1f}%"
