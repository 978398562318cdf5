"""Proximity-operations software-in-the-loop jobs: the range sweep and the trajectory (reference Sec. 2.3).

    case -> pose of the target (sweep: range x random orientation; trajectory: frame k of Table 2's motion)
         -> render (Taichi; ``paper`` point splatting or ``accurate`` analytic-coverage triangles)
         -> optional sensor effects -> blobber (COB, axes, axis ratio) -> range by Eq. 1 ("paper")
         and by dualsight's "subpixel" estimator, side by side -> one row per case in ``prox_cases``.

Case ``i`` draws its orientation (sweep) and its noise seed from ``default_rng([seed, i])`` only.

Spec (TOML; what is not given comes from the preset)::

    job = "sweep"                 # or "trajectory"
    seed = 1
    mode = "paper"                # renderer: "paper" (fixed surface resolution) | "accurate"
    satellite = "examples/satellites/cubesat_3u.toml"   # read when the spec is made; stored inline
    ranges_m = [1.0, ...]         # sweep: true ranges along the boresight
    orientations = 9              # sweep: random orientations per range (uniform on SO(3))
    frames = 50                   # trajectory: number of frames
    batch_size = 16
    [blobber]  threshold = 0.0, target = "largest", connectivity = 8
    [sensor]   psf_sigma_px = 0.0, read_noise = 0.0, gain = 1.0, bits = 0 (0 = no quantisation)
    [areas]    samples = 20000, bin_width = 0.05
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from dualsight.catalogs.areas import area_table
from dualsight.errors import ConfigError, InputError
from dualsight.config import validate
from dualsight.jobs.engine.runner import prepare, run_job
from dualsight.jobs.engine.specs import preset_and_config
from dualsight.kernels.digest import frame_digest, to_int64
from dualsight.kernels.points import render
from dualsight.kernels.prox_sensor import apply_sensor
from dualsight.nav.blobber import BlobberConfig, run_blobber
from dualsight.scene.attitude import quat_to_dcm, random_quaternions
from dualsight.scene.camera import read_toml
from dualsight.scene.motion import frame_poses, place_body
from dualsight.scene.satellite import satellite_from_dict
from dualsight.scene.units import angle_between

NAME = "prox"
PRIMARY = "prox_cases"
ESTIMATORS = ("paper", "subpixel")

REFERENCE_RANGES = [float(x) for x in np.logspace(0, 2, 11)]


def _example(name: str) -> Path:
    """An example file shipped in the repository's ``examples/`` folder."""
    here = Path(__file__).resolve().parents[2] / "examples" / name
    return here


PRESETS = {
    # Reference Sec. 2.3: Table 1 camera, 3U CubeSat, 11 ranges log-spaced 1-100 m x 9 random orientations.
    "paper": {"job": "sweep", "seed": 1, "mode": "paper", "satellite": "satellites/cubesat_3u.toml",
              "ranges_m": REFERENCE_RANGES, "orientations": 9, "frames": 50, "batch_size": 16,
              "blobber": {"threshold": 0.0, "target": "all", "connectivity": 8},
              "sensor": {"psf_sigma_px": 0.0, "read_noise": 0.0, "gain": 1.0, "bits": 0},
              "areas": {"samples": 20000, "bin_width": 0.05}},
}
# dualsight's best method on the same scenario: exact coverage rendering, hundreds of orientations.
PRESETS["accurate"] = {**PRESETS["paper"], "mode": "accurate", "orientations": 300}


@dataclass(frozen=True)
class SensorEffects:
    psf_sigma_px: float = 0.0
    read_noise: float = 0.0
    gain: float = 1.0
    bits: int = 0

    @property
    def any(self) -> bool:
        return self.psf_sigma_px > 0 or self.read_noise > 0 or self.bits > 0 or self.gain != 1.0


@dataclass(frozen=True)
class ProxSpec:
    job: str
    seed: int
    mode: str
    satellite_table: dict          # the satellite file's content (inline, so a run is replayable anywhere)
    satellite_source: str
    ranges_m: tuple
    orientations: int
    frames: int
    batch_size: int
    blobber: dict
    sensor: SensorEffects
    areas: dict
    satellite: object = field(default=None, compare=False)

    def to_dict(self) -> dict:
        return {"job": self.job, "seed": self.seed, "mode": self.mode, "satellite": self.satellite_table,
                "satellite_source": self.satellite_source, "ranges_m": list(self.ranges_m),
                "orientations": self.orientations, "frames": self.frames, "batch_size": self.batch_size,
                "blobber": dict(self.blobber), "sensor": self.sensor.__dict__.copy(), "areas": dict(self.areas)}

    @property
    def n_cases(self) -> int:
        return len(self.ranges_m) * self.orientations if self.job == "sweep" else self.frames

    def blobber_config(self, estimator: str) -> BlobberConfig:
        return BlobberConfig(estimator=estimator, threshold=float(self.blobber.get("threshold", 0.0)),
                             connectivity=int(self.blobber.get("connectivity", 8)),
                             target=self.blobber.get("target", "largest"))


class _Blobber(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    threshold: float = Field(0.0, ge=0, le=1e12)
    target: Literal["largest", "all"] = "largest"
    connectivity: Literal[4, 8] = 8


class _Sensor(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    psf_sigma_px: float = Field(0.0, ge=0, le=50)
    read_noise: float = Field(0.0, ge=0, le=1e6)
    gain: float = Field(1.0, gt=0, le=1e9)
    bits: int = Field(0, ge=0, le=32)


class _Areas(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    samples: int = Field(20000, ge=100, le=10**7)
    bin_width: float = Field(0.05, ge=1e-3, le=1.0)


class ProxTable(BaseModel):
    """The prox spec's TOML layout, validated by pydantic (ranges in m, counts, the sub-tables)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    job: Literal["sweep", "trajectory"] = "sweep"
    seed: int = Field(1, ge=0, le=2**63 - 1)
    mode: Literal["paper", "accurate"] = "paper"
    satellite: str | dict
    satellite_source: str | None = None
    ranges_m: tuple[Annotated[float, Field(gt=0, le=1e6)], ...] = Field(tuple(REFERENCE_RANGES), min_length=1,
                                                                         max_length=10_000)
    orientations: int = Field(9, ge=1, le=10**7)
    frames: int | None = Field(None, ge=1, le=10**7)
    batch_size: int = Field(16, ge=1, le=1024)
    blobber: _Blobber = _Blobber()
    sensor: _Sensor = _Sensor()
    areas: _Areas = _Areas()
    preset: str | None = None
    cases: int | None = Field(None, ge=1, le=10**9)


def spec_from_dict(d: dict, source: str = "spec") -> ProxSpec:
    """Validate a prox spec (pydantic, :func:`dualsight.config.validate`); errors name ``source`` and the key."""
    t = validate(ProxTable, d, source=source)
    sat = t.satellite
    if isinstance(sat, str):
        p = Path(sat)
        if not p.is_absolute() and not p.exists():
            p = _example(sat)
        sat = read_toml(p)
        sat_source = str(p)
    else:
        sat_source = t.satellite_source or source
    satellite = satellite_from_dict(sat, source=sat_source)
    radius = satellite.bounding_radius
    for r in t.ranges_m:
        if r <= radius:
            raise ConfigError(f"range {r} m puts the camera inside the body (bounding radius {radius:.3f} m); "
                              f"ranges must exceed it", source=source, field="ranges_m")
    frames = t.frames if t.frames is not None else satellite.frames
    try:
        BlobberConfig(threshold=t.blobber.threshold, target=t.blobber.target, connectivity=t.blobber.connectivity)
    except (ValueError, TypeError) as e:
        raise ConfigError(str(e), source=source, field="blobber") from None
    sensor = SensorEffects(**t.sensor.model_dump())
    return ProxSpec(t.job, t.seed, t.mode, sat, sat_source, tuple(t.ranges_m), t.orientations, int(frames),
                    t.batch_size, t.blobber.model_dump(), sensor, t.areas.model_dump(), satellite)


def resolve(preset: str | None, config: Path | str | dict | None, **overrides) -> ProxSpec:
    """Merge preset, config file (or a table of its layout) and flags (None = not given) into the validated spec;
    the one way from the command line to a spec (``spec.to_dict()`` is its canonical dict, what the engine stores)."""
    d, source = preset_and_config(PRESETS, preset, config)
    sat = d.get("satellite")
    if config is not None and not isinstance(config, dict) and isinstance(sat, str) and not Path(sat).is_absolute():
        cand = Path(config).parent / sat       # a satellite path in a config file is relative to that file
        if cand.exists():
            d["satellite"] = str(cand)
    for k, v in overrides.items():
        if v is not None:
            d[k] = v
    return spec_from_dict(d, source=source)


def resolve_spec(preset: str | None, config: Path | str | dict | None, **overrides) -> dict:
    """:func:`resolve` in the engine's form: ``spec.to_dict()``."""
    return resolve(preset, config, **overrides).to_dict()


# ------------------------------------------------------------------------------------------ a run
@dataclass(frozen=True)
class ProxRun:
    """A prox sweep or trajectory resolved and identified but not yet run (:func:`plan_run`, :func:`start_run`)."""

    kind: str                # the job kind: "prox_sweep" or "prox_trajectory"
    spec: dict               # the canonical spec dict (``resolved.to_dict()``)
    n_cases: int             # sweep: ranges x orientations; trajectory: frames
    run_id: str
    spec_hash: str           # 16 hex digits (jobs/engine/runner.py spec_hash)
    resolved: ProxSpec = field(repr=False, compare=False)    # the validated spec (the trajectory's video reads it)


def plan_run(preset: str | None = None, config: Path | str | dict | None = None, *, job: str,
             seed: int | None = None, cases: int | None = None, run_id: str | None = None, mode: str | None = None,
             satellite: Path | str | None = None, ranges_m: list[float] | None = None,
             orientations: int | None = None, frames: int | None = None) -> ProxRun:
    """Everything ``dualsight prox sweep`` (``job="sweep"``) and ``dualsight prox trajectory`` (``"trajectory"``)
    decide before the lake is touched, for them and ``dualsight.run``: the preset (default paper), the config
    file or table over it and the flags (None = not given) merged and validated (:func:`resolve`), the run's
    identity (``prepare`` of jobs/engine/runner.py) and its id (``run_id``, default
    ``prox-<job>-<mode>-<seed>-<cases>``).

    ``cases`` (``dualsight.run``'s; the commands have no such flag) sets the number of cases: a trajectory's
    frames, or a sweep's ranges x orientations, so a multiple of the number of ranges (orientations =
    cases / ranges).  InputError (source "cases") when it is not one."""
    over = {"job": job, "ranges_m": ranges_m, "orientations": orientations, "frames": frames}
    sat = str(satellite) if satellite else None
    s = resolve(preset, config, seed=seed, mode=mode, satellite=sat, **over)
    if cases is not None and cases != s.n_cases:
        if s.job == "sweep":
            per_range, rest = divmod(cases, len(s.ranges_m))
            if rest or not per_range:
                raise InputError(f"must be a multiple of the sweep's {len(s.ranges_m)} ranges (a prox sweep runs "
                                 f"ranges x orientations cases), got {cases}; for other ranges set ranges_m in the "
                                 "spec", source="cases")
            over["orientations"] = per_range
        else:
            over["frames"] = cases
        s = resolve(preset, config, seed=seed, mode=mode, satellite=sat, **over)
    n = s.n_cases
    kind = f"prox_{s.job}"
    spec_dict = s.to_dict()
    _, _, _, h = prepare(kind, spec_dict, n)
    return ProxRun(kind, spec_dict, n, run_id or f"prox-{s.job}-{s.mode}-{s.seed}-{n}", h, s)


def start_run(plan: ProxRun, lake, *, workers: int | None = None, scheduler: str | None = None,
              shard_size: int | None = None, progress: bool = True) -> dict:
    """Run (or resume) a planned prox sweep or trajectory into ``lake`` (a warehouse Lake) with the engine's
    ``run_job``; returns the final manifest.  Errors as ``run_job``'s (InputError, LakeError, EngineError,
    Interrupted)."""
    return run_job(plan.kind, plan.spec, n_cases=plan.n_cases, lake=lake, run_id=plan.run_id, workers=workers,
                   scheduler=scheduler, shard_size=shard_size, progress=progress,
                   label=f"prox {plan.resolved.job} {plan.run_id}")


# ------------------------------------------------------------------------------------------ context
@dataclass
class ProxContext:
    satellite: object
    geometry: object
    materials: np.ndarray
    table: object


def make_context(spec: ProxSpec) -> ProxContext:
    sat = spec.satellite
    geometry = sat.mesh() if spec.mode == "accurate" else sat.point_cloud()
    table = area_table(sat, n=spec.areas["samples"], bin_width=spec.areas["bin_width"])
    return ProxContext(sat, geometry, sat.materials(), table)


# ------------------------------------------------------------------------------------------ cases
def draw_cases(spec: ProxSpec, case_ids: np.ndarray) -> dict:
    """Pose inputs of each case.  Sweep: range index ``i // orientations``, orientation uniform on SO(3)
    from ``default_rng([seed, i])``, body origin on the boresight.  Trajectory: frame ``i`` of the file's motion."""
    B = len(case_ids)
    noise = np.empty(B, dtype=np.uint64)
    quat = np.full((B, 4), np.nan)
    for k, i in enumerate(case_ids):  # one generator per case: a case never depends on its batch
        rng = np.random.default_rng([spec.seed, int(i)])
        if spec.job == "sweep":
            quat[k] = random_quaternions(rng, 1)[0]
        noise[k] = rng.integers(0, 2**63, dtype=np.uint64)
    sat = spec.satellite
    if spec.job == "sweep":
        ridx = (np.asarray(case_ids) // spec.orientations).astype(np.int64)
        r = np.asarray(spec.ranges_m)[ridx]
        t = np.stack([np.zeros(B), np.zeros(B), r], -1)
        light = np.asarray(sat.camera.light_direction, dtype=np.float64)
        poses = place_body(sat, quat_to_dcm(quat), t, light, frames=0)
    else:
        ridx = np.full(B, -1, dtype=np.int64)
        poses = frame_poses(sat, np.asarray(case_ids, dtype=np.float64))
    return {"quat": quat, "noise_seed": noise, "range_index": ridx, "poses": poses}


def compute_batch(spec: ProxSpec, ctx: ProxContext, case_ids: np.ndarray, keep_images: bool = False) -> dict:
    """Render + blobber for a batch; every intermediate result and the Arrow table."""
    B = len(case_ids)
    t0 = time.perf_counter_ns()
    draw = draw_cases(spec, case_ids)
    P = draw["poses"]
    cam = ctx.satellite.camera
    t1 = time.perf_counter_ns()
    img, cov = render(spec.mode, ctx.geometry, ctx.materials, P.R, P.t, P.light, cam.camera, cam.I_a, cam.I_l)
    if spec.sensor.any:
        img = apply_sensor(img, psf_sigma_px=spec.sensor.psf_sigma_px, read_noise=spec.sensor.read_noise,
                           gain=spec.sensor.gain, bits=spec.sensor.bits or None, seeds=draw["noise_seed"])
    t2 = time.perf_counter_ns()
    results, t_blob = {}, {}
    for est in ESTIMATORS:
        tb = time.perf_counter_ns()
        results[est] = run_blobber(img, cam.camera, ctx.table, spec.blobber_config(est),
                                   coverage=cov if not spec.sensor.any else None)
        t_blob[est] = time.perf_counter_ns() - tb
    t_total = time.perf_counter_ns() - t0
    timing = {"t_sample_ns": t1 - t0, "t_render_ns": t2 - t1, "t_blob_paper_ns": t_blob["paper"],
              "t_blob_subpixel_ns": t_blob["subpixel"], "t_total_ns": t_total}
    draw = {**draw, "image_digest": frame_digest(img)}
    table = cases_table(spec, case_ids, draw, results, {k: v // max(B, 1) for k, v in timing.items()})
    out = {"draw": draw, "results": results, "tables": {"prox_cases": table}}
    if keep_images:
        out["images"], out["coverage"] = img, cov
    return out


def compute_shard(spec: ProxSpec, case_ids: np.ndarray, ctx: ProxContext) -> dict[str, pa.Table]:
    """The engine's contract: rows of ``case_ids`` (int64, ascending) in batches of ``spec.batch_size``."""
    parts = [compute_batch(spec, ctx, case_ids[s: s + spec.batch_size])["tables"]["prox_cases"]
             for s in range(0, len(case_ids), spec.batch_size)]
    return {"prox_cases": pa.concat_tables(parts) if parts else CASES_SCHEMA.empty_table()}


def memory_estimate(spec: ProxSpec) -> int:
    """Peak bytes of one worker: ``batch_size`` frames of the satellite file's camera, about six float32
    or int32 planes each (image, depth, coverage, labels, masks), plus the area table's samples."""
    cam = spec.satellite.camera.camera
    return int(6 * 4 * cam.width * cam.height * spec.batch_size + 64 * spec.areas["samples"])


def _est_fields(est: str) -> list:
    return [(f"{est}_{k}", pa.float64()) for k in ("axis_ratio", "n_blob", "range_min_m", "range_est_m",
                                                   "range_max_m", "x_m", "y_m", "z_m", "pos_err_m")]


CASES_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("job", pa.string()), ("mode", pa.string()), ("seed", pa.int64()),
    ("frame", pa.int64()), ("range_index", pa.int64()), ("true_range_m", pa.float64()),
    ("true_x_m", pa.float64()), ("true_y_m", pa.float64()), ("true_z_m", pa.float64()),
    ("R_body", pa.list_(pa.float64(), 9)), ("noise_seed", pa.uint64()), ("image_digest", pa.int64()),
    ("found", pa.bool_()),
    ("n_blobs", pa.int64()), ("n_pixels", pa.int64()), ("n_coverage", pa.float64()),
    ("cob_x_px", pa.float64()), ("cob_y_px", pa.float64()), ("axis_ratio", pa.float64()),
    ("major_px", pa.float64()), ("minor_px", pa.float64()), ("dir_err_rad", pa.float64()),
    *_est_fields("paper"), *_est_fields("subpixel"),
    ("t_sample_ns", pa.int64()), ("t_render_ns", pa.int64()), ("t_blob_paper_ns", pa.int64()),
    ("t_blob_subpixel_ns", pa.int64()), ("t_total_ns", pa.int64()),
])
SCHEMAS = {"prox_cases": CASES_SCHEMA}


def cases_table(spec: ProxSpec, case_ids, draw, results, timing) -> pa.Table:
    P = draw["poses"]
    B = len(case_ids)
    t = P.t_body
    true_r = np.linalg.norm(t, axis=-1)
    true_dir = t / true_r[:, None]
    cols = {
        "case_id": np.asarray(case_ids, dtype=np.int64), "job": np.full(B, spec.job, dtype=object),
        "mode": np.full(B, spec.mode, dtype=object), "seed": np.full(B, spec.seed, dtype=np.int64),
        "frame": np.asarray(case_ids, dtype=np.int64) if spec.job == "trajectory" else np.zeros(B, np.int64),
        "range_index": draw["range_index"], "true_range_m": true_r,
        "true_x_m": t[:, 0], "true_y_m": t[:, 1], "true_z_m": t[:, 2],
        "R_body": pa.FixedSizeListArray.from_arrays(pa.array(P.R_body.reshape(-1).astype(np.float64)), 9),
        "noise_seed": draw["noise_seed"], "image_digest": to_int64(draw["image_digest"]),
    }
    base = results["paper"]
    cols.update({"found": base.found, "n_blobs": base.n_blobs, "n_pixels": base.n_pixels,
                 "n_coverage": base.n_coverage, "cob_x_px": base.cob_px[:, 0], "cob_y_px": base.cob_px[:, 1],
                 "axis_ratio": base.axis_ratio, "major_px": base.major_px, "minor_px": base.minor_px,
                 "dir_err_rad": np.where(base.found, angle_between(base.unit, true_dir), np.nan)})
    for est, res in results.items():
        pos = res.position
        cols.update({f"{est}_axis_ratio": res.axis_ratio, f"{est}_n_blob": res.n_blob,
                     f"{est}_range_min_m": res.range_min, f"{est}_range_est_m": res.range_est,
                     f"{est}_range_max_m": res.range_max,
                     f"{est}_x_m": pos[:, 0], f"{est}_y_m": pos[:, 1], f"{est}_z_m": pos[:, 2],
                     f"{est}_pos_err_m": np.linalg.norm(pos - t, axis=-1)})
    for k, v in timing.items():
        cols[k] = np.full(B, v, dtype=np.int64)
    return pa.table({f.name: (cols[f.name] if isinstance(cols[f.name], pa.Array)
                              else pa.array(cols[f.name], type=f.type)) for f in CASES_SCHEMA}, schema=CASES_SCHEMA)


def shard_summary(tables: dict[str, pa.Table]) -> dict:
    t = tables["prox_cases"]
    found = t.column("found").to_numpy(zero_copy_only=False)
    r = t.column("true_range_m").to_numpy()
    e = np.abs(t.column("subpixel_range_est_m").to_numpy() - r) / r
    return {"cases": int(len(found)), "found": int(found.sum()), "sum_rel_err_subpixel": float(np.nansum(e))}


def progress_postfix(stats: dict) -> str:
    n = stats.get("found", 0)
    if not n:
        return ""
    return f"found {100 * n / max(stats.get('cases', 1), 1):.0f}%, subpixel rel err {100 * stats['sum_rel_err_subpixel'] / n:.1f}%"
