"""Benchmark: the sensor-noise star path (issue 13, point 2), stage by stage and as a whole job.

    .venv/bin/python benchmarks/bench_noise_path.py                       # stages + workers 1 vs 2
    .venv/bin/python benchmarks/bench_noise_path.py --batch 16 --repeats 5 --skip-job
    .venv/bin/python benchmarks/bench_noise_path.py --skip-stages --job-cases 200 600

Workload: ``examples/star/noisy_sensor.toml`` (the reference's 1024 x 768 camera; shot, read and dark noise, sky,
hot pixels, two false stars per frame).

Part 1, stages (in this process, one Taichi thread, one BLAS/OpenMP thread): the chain of
``jobs/kinds/star.py: compute_batch`` cut into its stages, each timed on its own over the same batches, reported in ms
per case (median over ``--repeats`` passes over ``--batches`` batches of ``--batch`` cases; min-max spread too):

  sample      draw_cases + stars_in_field (attitudes, projection)
  render      render_star_fields with every random effect off (PSF splat + the ADC pass over every pixel)
  noise       render_star_fields of the noisy sensor minus ``render`` (shot, read, hot pixels in the same pass;
              with the frame digest summed in that pass, ``digest=True``, where the code has it: issue 24.3)
  digest      frame_digest_taichi of the frames: the job's separate pass before issue 24.3 (0 where the render
              pass sums the digest itself)
  background  estimate_background (strided sample: median, MAD, clipped sigma)
  threshold   _levels + native_threshold (per-frame numbers)
  labelling   label_frames (run-length union-find: every pixel read once or twice)
  centroids   _from_components (moment sums of the kept components, sort, cap)
  detect      detect_stars as a whole (background + threshold + labelling + centroids)
  voting      observations + identify (Taichi voting)
  attitude    solve (SVD, errors)
  tables      match_truth + cases_table + detections_table (Arrow rows)
  lake write  Lake.write_shard of the batch's tables (Parquet, fsync, rename)
  total       compute_batch as the job calls it, plus the lake write

Part 2, whole job: ``jobs/runner.run_job("star", spec, n_cases=N, lake=Lake(tmp), workers=W)`` in a fresh
process per measurement (so each process starts its own Taichi with the thread count the runner gives it).
Each process first runs an untimed 32-case job (imports, catalogs, kernel compilation); steady-state
throughput = (N2 - N1) / (t(N2) - t(N1)), so what every run pays once (the spawn of the workers and their
start-up, the lake's files) cancels.  ``--workers 1`` runs in-process with Taichi's default thread count (all cores);
"1w1t" is the same with DUALSIGHT_TI_THREADS=1 (one core: the unit of the scaling ratio).  Repeated
``--job-repeats`` times; the median and the spread are printed.  The machine is shared: the load average is
printed before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
os.environ.setdefault("DUALSIGHT_TI_THREADS", "1")

import numpy as np  # noqa: E402

from bench_noisy_sil import job_script_rows  # noqa: E402  (this folder: the script's own)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOISY = os.path.join(ROOT, "examples", "star", "noisy_sensor.toml")

STAGES = ("sample", "render", "noise", "digest", "background", "threshold", "labelling", "centroids", "detect",
          "voting", "attitude", "tables", "lake write", "total")


def load_spec(batch: int | None = None) -> tuple[dict, int]:
    from pathlib import Path

    from dualsight.jobs.kinds import star

    d, n = star.resolve_spec(None, Path(NOISY))
    if batch is not None:
        d["batch_size"] = int(batch)
    return d, n


CLOCK = time.perf_counter_ns  # --clock cpu: time.process_time_ns (this process's CPU time, all its threads)


def _ms(t0: int) -> float:
    return (CLOCK() - t0) / 1e6


def stage_times(batch: int, batches: int, repeats: int) -> dict:
    """{stage: [ms per case per repeat]} for ``batches`` batches of ``batch`` cases, ``repeats`` passes."""
    import dataclasses

    from dualsight.jobs.kinds import star
    from dualsight.kernels import detect as kd
    from dualsight.kernels import starfield as sf
    from dualsight.kernels.digest import frame_digest_taichi as frame_digest
    from dualsight.kernels.labelling import label_frames, native_threshold
    from dualsight.kernels.sensor_config import flux_from_magnitude
    from dualsight.nav.observations import observations
    from dualsight.nav.star_solution import identify, solve
    from dualsight.nav.truth_match import match_truth
    from dualsight.scene.starfield_geometry import stars_in_field
    from dualsight.warehouse.lake import Lake
    from dualsight.warehouse.shards import ShardInfo

    import inspect

    fused = "digest" in inspect.signature(sf.render_star_fields).parameters   # the code after issue 24.3
    d, _ = load_spec(batch)
    spec = star.spec_from_dict(d)
    ctx = star.make_context(spec)
    cam, sen, dcfg = spec.camera, spec.sensor, spec.detect
    quiet = dataclasses.replace(sen, shot_noise=False, read_noise_e=0.0, hot_pixel_fraction=0.0)
    cat = ctx.catalog
    ids_all = [np.arange(i * batch, (i + 1) * batch, dtype=np.int64) for i in range(batches)]
    # warm-up: compile every kernel
    star.compute_batch(spec, ctx, ids_all[0])
    sf.render_star_fields(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)), None, cam.width, cam.height, quiet,
                          np.zeros(1, np.uint64), psf=ctx.psf)
    out = {s: [] for s in STAGES}
    with tempfile.TemporaryDirectory() as tmp:
        lake = Lake(tmp)
        for rep in range(repeats):
            acc = dict.fromkeys(STAGES, 0.0)
            for bi, ids in enumerate(ids_all):
                t = CLOCK()
                draw = star.draw_cases(spec, ids)
                flux = flux_from_magnitude(cat.vmag.astype(np.float64), sen)
                fld = stars_in_field(draw["A_true"], cat.unit, flux, cam, star.psf_margin_px(sen, cam, ctx.psf))
                acc["sample"] += _ms(t)
                args = (fld.x, fld.y, fld.flux_e, fld.valid, cam.width, cam.height)
                t = CLOCK()
                sf.render_star_fields(*args, quiet, draw["noise_seed"], psf=ctx.psf)
                acc["render"] += _ms(t)
                t = CLOCK()
                if fused:
                    img, _ = sf.render_star_fields(*args, sen, draw["noise_seed"], psf=ctx.psf, digest=True)
                else:
                    img = sf.render_star_fields(*args, sen, draw["noise_seed"], psf=ctx.psf)
                acc["noise"] += _ms(t)
                t = CLOCK()
                if not fused:
                    frame_digest(img, np.asarray(sen.empty_pixel_adu()).astype(img.dtype))
                acc["digest"] += _ms(t)
                B = img.shape[0]
                t = CLOCK()
                bg_e, sig_e = kd.estimate_background(img, dcfg.background_step)
                acc["background"] += _ms(t)
                t = CLOCK()
                bg, thr = kd._levels(dcfg, B, bg_e, sig_e)
                native_threshold(thr, img.dtype)
                acc["threshold"] += _ms(t)
                t = CLOCK()
                comp = label_frames(img, thr, offset=bg, connectivity=dcfg.connectivity)
                acc["labelling"] += _ms(t)
                t = CLOCK()
                kd._from_components(comp, np.arange(B), B, dcfg, bg, thr)
                acc["centroids"] += _ms(t)
                t = CLOCK()
                det = kd.detect_stars(img, dcfg)
                acc["detect"] += _ms(t)
                t = CLOCK()
                obs = observations(det, B, cam)
                ident = identify(obs, cat.unit, ctx.pairs, spec.voting, cat_vmag=cat.vmag)
                acc["voting"] += _ms(t)
                t = CLOCK()
                sol = solve(obs, ident, cat.unit, draw["A_true"], spec.error_frame)
                acc["attitude"] += _ms(t)
                t = CLOCK()
                res = star.compute_batch(spec, ctx, ids)
                t_batch = _ms(t)
                t = CLOCK()
                truth = match_truth(det, fld, obs, cat.hip)
                per = {k: np.zeros(B, np.int64) for k in ("sample", "render", "detect", "identify", "attitude")}
                star.cases_table(ids, spec, draw, fld, det, obs, ident, sol, truth, per, None, np.zeros(B, np.uint64))
                star.detections_table(ids, det, obs, ident, sol, truth, cat)
                acc["tables"] += _ms(t)
                t = CLOCK()
                info = ShardInfo("bench", "0" * 64, rep * batches + bi, int(ids[0]), int(ids[-1]) + 1)
                lake.write_shard(info, res["tables"], star.PRIMARY, star.SCHEMAS)
                acc["lake write"] += _ms(t)
                acc["total"] += t_batch + _ms(t)
            n = batch * batches
            acc["noise"] -= acc["render"]
            for s in STAGES:
                out[s].append(acc[s] / n)
    return out


_JOB = r"""
import json, tempfile, time
from pathlib import Path
from dualsight.jobs.kinds import star
from dualsight.jobs.engine.runner import run_job
from dualsight.warehouse.lake import Lake
spec, _ = star.resolve_spec(None, Path({cfg!r}))
if {batch!r} is not None:
    spec["batch_size"] = {batch!r}
res = []
for n in [32] + {sizes!r}:  # the first, untimed: this process's imports, catalogs and kernel compilation
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        run_job("star", spec, n_cases=n, lake=Lake(tmp), workers={workers!r}, progress=False, run_id="bench")
        res.append((n, time.perf_counter() - t0))
print(json.dumps(res[1:]))
"""


PYTHONPATH = None  # --pythonpath: import dualsight from a frozen copy of the package (see main)


def job_time(workers: int, sizes: list[int], batch: int | None, ti_threads: str | None) -> list[tuple[int, float]]:
    """[(cases, wall s)] of whole jobs in one fresh process (its own Taichi start and thread count)."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "DUALSIGHT_TI_THREADS")
    env = {k: v for k, v in os.environ.items() if k not in names}
    if ti_threads:
        env.update(dict.fromkeys(names, ti_threads))
    code = _JOB.format(cfg=NOISY, batch=batch, sizes=list(sizes), workers=workers)
    if PYTHONPATH:
        env["PYTHONPATH"] = PYTHONPATH
    return job_script_rows(code, env)


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=None, help="cases per batch (default: the config's batch_size)")
    ap.add_argument("--batches", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-stages", action="store_true")
    ap.add_argument("--skip-job", action="store_true")
    ap.add_argument("--job-cases", type=int, nargs=2, default=[200, 800], metavar=("N1", "N2"))
    ap.add_argument("--job-repeats", type=int, default=2)
    ap.add_argument("--json", default=None, help="also write the results here")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="stage clock: wall time or this process's CPU time (fairer on a loaded machine)")
    ap.add_argument("--pythonpath", default=None,
                    help="whole jobs import dualsight from this folder (a frozen copy of the package: "
                         "<dir>/dualsight/{kernels,jobs,...}), so edits elsewhere in the tree do not disturb them")
    args = ap.parse_args()
    global CLOCK, PYTHONPATH
    CLOCK = time.process_time_ns if args.clock == "cpu" else time.perf_counter_ns
    PYTHONPATH = args.pythonpath
    batch = args.batch or load_spec()[0]["batch_size"]
    result = {"cores": os.cpu_count(), "batch": batch, "load_before": load()}
    print(f"cores {os.cpu_count()}, batch {batch}, load average {result['load_before']}")
    if not args.skip_stages:
        st = stage_times(batch, args.batches, args.repeats)
        result["stages_ms_per_case"] = st
        print(f"\nstages, ms per case ({args.clock} clock, 1 Taichi thread, 1 BLAS thread; median [min-max] of {args.repeats} x "
              f"{args.batches} batches of {batch}):")
        for s in STAGES:
            v = st[s]
            print(f"  {s:>11}: {statistics.median(v):8.3f}  [{min(v):.3f}-{max(v):.3f}]")
    if not args.skip_job:
        n1, n2 = args.job_cases
        runs = {"1w": (1, None), "1w1t": (1, "1"), "2w": (2, None)}
        rates = {k: [] for k in runs}
        for _ in range(args.job_repeats):
            for name, (w, th) in runs.items():
                (a, ta), (b, tb) = job_time(w, [n1, n2], args.batch, th)
                rates[name].append((b - a) / (tb - ta))
                print(f"  {name:>5}: {n1} cases {ta:.1f} s, {n2} cases {tb:.1f} s -> {rates[name][-1]:.1f} cases/s "
                      f"steady (load {load()})", flush=True)
        result["job_cases_per_s"] = rates
        med = {k: statistics.median(v) for k, v in rates.items()}
        print(f"\nwhole job, steady state ({n2} - {n1} cases), median [min-max] of {args.job_repeats}:")
        for k, v in rates.items():
            print(f"  {k:>5}: {med[k]:7.1f} cases/s  [{min(v):.1f}-{max(v):.1f}]")
        print(f"  ratio 2 workers / 1 worker (default threads): {med['2w'] / med['1w']:.2f}x")
        print(f"  ratio 2 workers / 1 worker (1 thread):        {med['2w'] / med['1w1t']:.2f}x")
    result["load_after"] = load()
    print(f"load average after: {result['load_after']}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    main()
