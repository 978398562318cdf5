"""Relative navigation over a rendezvous approach: the ``rendezvous`` job kind (issue 23, point 5): the engine's
contract and one approach from draw to rows.  The stages live one per module: the spec and its presets
(``rendezvous_spec``), the per-process state and ground calibrations (``rendezvous_context``), the draw and truth
(``rendezvous_truth``), what the camera measures (``rendezvous_measure``), the filter and its bias model
(``rendezvous_filter``), the rows (``rendezvous_tables``).

One case is one approach of a chaser to a target near a circular orbit::

    draw (default_rng([seed, i])): initial Hill state about the nominal, manoeuvre execution errors, the target's
        spin, pointing errors, attitude-knowledge errors, per-frame noise seeds
    -> truth by Clohessy-Wiltshire with the executed delta-v (scene/relative_orbit.propagate)
    -> per frame: the camera attitude (pointed at the target with an error, or held inertially)
    -> star camera ("camera = star"): stars + target in one frame (scene/target_in_field: target_frames,
       with_target), rendered and detected by the star job's chain (jobs/kinds/star.render_and_detect), resolved
       blobs kept out of the vote, star identification and attitude (nav/star_solution), the target's inertial
       bearing through that attitude (nav/target_bearing.inertial_bearing; a point-like target's centroid sigma
       at its measured flux from the camera's own calibration,
       :func:`~dualsight.jobs.kinds.rendezvous_context.point_centroid_calibration`)
       proximity camera (a camera file): the target alone, rendered as the prox job does (kernels/points.render,
       exact coverage), the blobber's centre of brightness and range with its [min, max] (nav/blobber.py,
       "subpixel" estimator); the attitude from the chaser's own star tracker (true attitude + a Gaussian error of
       ``attitude_sigma_arcsec`` per axis, the same sigma in the bearing's covariance)
    -> the EKF over the frames (nav/relative_filter.run: CW prediction, the known manoeuvres with their nominal
       delta-v and execution error, bearing and range updates; two Gauss-Markov states for the centre of
       brightness's residual that a target spinning about a fixed axis keeps from frame to frame,
       scene/photocentre_bias.py; the blobber's range with its bias removed and its spread as a fraction of the
       predicted range, both from a calibration of the blobber through the camera's own renderer,
       :func:`~dualsight.jobs.kinds.rendezvous_context.blobber_calibration`,
       nav/blobber_range_error.py; a blob cut by the frame's edge gives neither;
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
    [rendezvous]   ... (jobs/kinds/rendezvous_spec.py RendezvousConfig)

Presets: ``far`` (issue 23.6 e: V-bar hop 2 km -> 200 m with one known burn one orbit long, the star preset's
camera, paper sensor, bearings only) and ``close`` (issue 23.6 d: the paper's proximity camera and 3U CubeSat,
V-bar hop 50 m -> 2 m, bearings + blobber range).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from dualsight.jobs.engine.runner import prepare, run_job
from dualsight.jobs.kinds import star
from dualsight.jobs.kinds.rendezvous_tables import CASES_SCHEMA, FRAMES_SCHEMA, case_row, frames_table
from dualsight.nav import relative_filter as rf
from dualsight.jobs.kinds import rendezvous_context, rendezvous_spec
from dualsight.jobs.kinds.rendezvous_spec import RendezvousSpec, resolve_spec
from dualsight.jobs.kinds.rendezvous_context import PROX_CHUNK, RendezvousContext
from dualsight.jobs.kinds.rendezvous_truth import draw_case, frame_view, geometry, truth_trajectory
from dualsight.jobs.kinds.rendezvous_measure import bearing_scores, measure_prox, measure_star
from dualsight.jobs.kinds.rendezvous_filter import run_filter, burn_frames


NAME = "rendezvous"
PRIMARY = "rendezvous_cases"
SCHEMAS = {"rendezvous_cases": CASES_SCHEMA, "rendezvous_frames": FRAMES_SCHEMA}


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
    """Run (or resume) a planned campaign into ``lake`` with the engine's ``run_job``; returns the manifest.  On
    this machine (no ``scheduler``) a proximity spec's calibrations are made (or read from the cache) here first,
    once, with a line on stderr when they must be computed, not by every worker at once
    (``rendezvous_context.warm_calibrations``)."""
    if scheduler is None:
        rendezvous_context.warm_calibrations(
            spec_from_dict(plan.spec), (lambda msg: print(f"rendezvous: {msg}", file=sys.stderr)) if progress else None)
    return run_job(NAME, plan.spec, n_cases=plan.n_cases, lake=lake, run_id=plan.run_id, workers=workers,
                   scheduler=scheduler, shard_size=shard_size, progress=progress, label=f"rendezvous {plan.run_id}")


def spec_from_dict(d: dict, source: str = "spec") -> RendezvousSpec:
    """The engine's contract: a validated spec (:func:`dualsight.jobs.kinds.rendezvous_spec.spec_from_dict`, where
    the spec's models live)."""
    return rendezvous_spec.spec_from_dict(d, source)


def make_context(spec: RendezvousSpec) -> RendezvousContext:
    """The engine's contract: the per-process state (:func:`dualsight.jobs.kinds.rendezvous_context.make_context`)."""
    return rendezvous_context.make_context(spec)


def memory_estimate(spec: RendezvousSpec) -> int:
    """The star job's estimate (star camera) or the proximity chunk's frames (image and coverage, float32, x 4)."""
    if spec.is_star:
        return star.memory_estimate(spec.star)
    return int(PROX_CHUNK * spec.camera.width * spec.camera.height * 4 * 2 * 4 + 200e6)


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
    bearing_scores(m, geo)
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
