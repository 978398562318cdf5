"""The Monte Carlo engine shared by every job: shards, executors, manifests, resume, progress.

A *job kind* (``dualsight.jobs.star``, ``dualsight.jobs.prox``, ...) is a module with

    NAME: str                      job name recorded in the manifest
    DATASETS: list[str]            datasets each shard writes; PRIMARY is written last
    PRIMARY: str
    spec_from_dict(d) -> spec      validated frozen spec (raises ConfigError)
    make_context(spec) -> ctx      per-process state (catalogs, buffers), built once per worker
    run_cases(spec, ctx, case_ids: np.ndarray) -> dict[dataset, pa.Table]

Case ``i`` draws everything from ``numpy.random.default_rng([seed, i])``, so a case's row is the same
whatever shard, batch, worker or machine computes it.  Shards are contiguous ranges of case ids; every
worker writes its own shard files (atomically, see :mod:`dualsight.warehouse.lake`) and reports a small
summary back; only the coordinating process writes the manifest.

Executors: in-process (``workers=1``), a pool of *spawned* local processes (default, one per core; a fork
of an initialised Taichi runtime hangs), or a Dask cluster when a scheduler address is given.
"""

from __future__ import annotations

import importlib
import json
import math
import multiprocessing as mp
import os
import platform
import socket
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualsight.errors import InputError
from dualsight.warehouse.lake import Lake, check_run_id

JOB_MODULES = {
    "star": "dualsight.jobs.star",
    "prox_sweep": "dualsight.jobs.prox",
    "prox_trajectory": "dualsight.jobs.prox",
}

_CONTEXTS: dict[str, object] = {}


def job_module(kind: str):
    """The module implementing job kind ``kind`` (a fixed table, not user-supplied dotted paths)."""
    if kind not in JOB_MODULES:
        raise InputError(f"unknown job kind {kind!r}; known: {sorted(JOB_MODULES)}")
    return importlib.import_module(JOB_MODULES[kind])


def _spec_key(kind: str, spec_dict: dict) -> str:
    return kind + ":" + json.dumps(spec_dict, sort_keys=True)


def get_context(kind: str, spec_dict: dict):
    """Per-process context cache (one entry: a worker serves one run at a time)."""
    key = _spec_key(kind, spec_dict)
    if key not in _CONTEXTS:
        _CONTEXTS.clear()
        mod = job_module(kind)
        _CONTEXTS[key] = (mod.spec_from_dict(spec_dict), mod.make_context(mod.spec_from_dict(spec_dict)))
    return _CONTEXTS[key]


def execute_shard(kind: str, spec_dict: dict, lake_root: str, run_id: str, shard: int,
                  start: int, stop: int) -> dict:
    """Compute cases [start, stop) and write them as shard ``shard``. Runs in any worker process."""
    mod = job_module(kind)
    spec, ctx = get_context(kind, spec_dict)
    t0 = time.perf_counter_ns()
    tables = mod.run_cases(spec, ctx, np.arange(start, stop, dtype=np.int64))
    t1 = time.perf_counter_ns()
    rows = Lake(Path(lake_root)).write_shard(run_id, shard, tables, primary=mod.PRIMARY)
    t2 = time.perf_counter_ns()
    summary = {"shard": shard, "cases": stop - start, "rows": rows, "compute_ns": t1 - t0, "write_ns": t2 - t1,
               "pid": os.getpid()}
    if hasattr(mod, "shard_summary"):
        summary["stats"] = mod.shard_summary(tables)
    return summary


def _init_worker(threads: int | None):
    if threads:
        os.environ["DUALSIGHT_TI_THREADS"] = str(threads)


@dataclass(frozen=True)
class RunPlan:
    run_id: str
    kind: str
    n_cases: int
    shard_size: int

    @property
    def n_shards(self) -> int:
        return math.ceil(self.n_cases / self.shard_size)

    def bounds(self, shard: int) -> tuple[int, int]:
        return shard * self.shard_size, min(self.n_cases, (shard + 1) * self.shard_size)


def default_shard_size(n_cases: int, workers: int) -> int:
    """Enough shards to balance the workers and show progress, few enough to keep files large."""
    return int(min(1000, max(25, math.ceil(n_cases / (4 * max(1, workers))))))


def versions() -> dict:
    out = {"python": platform.python_version()}
    for name in ("dualsight", "numpy", "taichi", "pyarrow", "duckdb", "astropy", "cv2"):
        try:
            m = importlib.import_module(name) if name != "taichi" else None
            if name == "taichi":
                from importlib.metadata import version
                out[name] = version("taichi")
            else:
                out[name] = getattr(m, "__version__", "?")
        except Exception:  # a missing optional package is recorded as absent
            out[name] = None
    return out


def run_job(kind: str, spec_dict: dict, *, n_cases: int, lake: Lake, run_id: str, workers: int | None = None,
            threads_per_worker: int | None = None, shard_size: int | None = None, scheduler: str | None = None,
            progress: bool = True, label: str | None = None, extra: dict | None = None) -> dict:
    """Run (or resume) ``n_cases`` cases of a job into ``lake`` as run ``run_id``; returns the manifest.

    Everything is validated before the lake is touched.  An existing run with the same kind, spec and
    number of cases is resumed (only its incomplete shards run); a different one is refused.
    """
    mod = job_module(kind)
    check_run_id(run_id)
    if not isinstance(n_cases, (int, np.integer)) or n_cases < 1 or n_cases > 10**9:
        raise InputError(f"number of cases must be an integer in [1, 1e9], got {n_cases!r}", source="--cases")
    spec = mod.spec_from_dict(spec_dict)           # validates; raises ConfigError naming the field
    spec_dict = spec.to_dict()                     # canonical form
    workers = int(workers or os.cpu_count() or 1)
    if workers < 1:
        raise InputError(f"workers must be >= 1, got {workers}", source="--workers")

    existing = lake.read_manifest(run_id)
    if existing is not None:
        if existing.get("kind") != kind or existing.get("spec") != json.loads(json.dumps(spec_dict)) \
                or existing.get("n_cases") != n_cases:
            diffs = [k for k in ("kind", "n_cases") if existing.get(k) != {"kind": kind, "n_cases": n_cases}[k]]
            if existing.get("spec") != json.loads(json.dumps(spec_dict)):
                diffs.append("spec")
            raise InputError(f"run {run_id!r} already exists in {lake.root} with a different {', '.join(diffs)}; "
                             f"resume it with the same settings or choose another --run", source="--run")
        plan = RunPlan(run_id, kind, n_cases, int(existing["shard_size"]))
        manifest = existing
    else:
        plan = RunPlan(run_id, kind, n_cases, int(shard_size or default_shard_size(n_cases, workers)))
        manifest = {"run_id": run_id, "kind": kind, "job": mod.NAME, "label": label, "spec": spec_dict,
                    "seed": spec_dict.get("seed"), "n_cases": n_cases, "shard_size": plan.shard_size,
                    "n_shards": plan.n_shards, "datasets": mod.DATASETS, "primary": mod.PRIMARY,
                    "versions": versions(), "host": socket.gethostname(), "created_unix": time.time(),
                    "shards_done": [], "status": "running", "stats": {}, **(extra or {})}
    lake.remove_stale_temps(run_id, mod.DATASETS)
    done = lake.complete_shards(run_id, mod.DATASETS)
    done = {s for s in done if s < plan.n_shards}
    manifest["shards_done"] = sorted(done)
    todo = [s for s in range(plan.n_shards) if s not in done]
    manifest["status"] = "running" if todo else "complete"
    manifest.setdefault("executions", []).append(
        {"started_unix": time.time(), "workers": workers, "scheduler": scheduler, "resumed_shards": len(done),
         "pid": os.getpid()})
    lake.write_manifest(manifest)
    if not todo:
        return manifest

    bar = _progress(plan, done, progress, label or f"{kind} {run_id}")
    stats = manifest.get("stats") or {}
    t_start = time.perf_counter()
    cases_run = 0
    try:
        for summary in _execute(plan, kind, spec_dict, lake, todo, workers, threads_per_worker, scheduler):
            done.add(summary["shard"])
            cases_run += summary["cases"]
            manifest["shards_done"] = sorted(done)
            for k, v in (summary.get("stats") or {}).items():
                stats[k] = stats.get(k, 0) + v
            manifest["stats"] = stats
            lake.write_manifest(manifest)
            if bar is not None:
                bar.update(summary["cases"])
                if hasattr(mod, "progress_postfix"):
                    bar.set_postfix_str(mod.progress_postfix(stats))
    except KeyboardInterrupt:
        manifest["status"] = "interrupted"
        lake.write_manifest(manifest)
        if bar is not None:
            bar.close()
        raise
    if bar is not None:
        bar.close()
    manifest["status"] = "complete" if len(done) == plan.n_shards else "incomplete"
    manifest["executions"][-1]["elapsed_s"] = time.perf_counter() - t_start
    manifest["executions"][-1]["cases_run"] = cases_run
    lake.write_manifest(manifest)
    return manifest


def _progress(plan: RunPlan, done: set[int], enabled: bool, desc: str):
    if not enabled:
        return None
    from tqdm import tqdm

    already = sum(plan.bounds(s)[1] - plan.bounds(s)[0] for s in done)
    return tqdm(total=plan.n_cases, initial=already, desc=desc, unit="case", dynamic_ncols=True,
                file=sys.stderr, smoothing=0.1)


def _execute(plan: RunPlan, kind: str, spec_dict: dict, lake: Lake, todo: list[int], workers: int,
             threads_per_worker: int | None, scheduler: str | None):
    """Yield shard summaries as shards complete, from the chosen executor."""
    root = str(lake.root.resolve())
    if scheduler:
        yield from _execute_dask(plan, kind, spec_dict, root, todo, scheduler)
        return
    if workers == 1 or len(todo) == 1:
        if threads_per_worker:
            _init_worker(threads_per_worker)
        for s in todo:
            yield execute_shard(kind, spec_dict, root, plan.run_id, s, *plan.bounds(s))
        return
    threads = threads_per_worker or max(1, (os.cpu_count() or 1) // workers)
    ctx = mp.get_context("spawn")
    # spawned workers inherit the environment at start: cap their BLAS/OpenMP pools too, or W workers each
    # running a pool of all cores oversubscribe the machine (measured: 2 workers slower than 1 without it)
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: str(threads) for k in _THREAD_VARS})
    try:
        yield from _pool(plan, kind, spec_dict, root, todo, workers, threads, ctx)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "DUALSIGHT_TI_THREADS")


def _pool(plan, kind, spec_dict, root, todo, workers, threads, ctx):
    with ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=ctx, initializer=_init_worker,
                             initargs=(threads,)) as pool:
        futures = [pool.submit(execute_shard, kind, spec_dict, root, plan.run_id, s, *plan.bounds(s))
                   for s in todo]
        try:
            for f in as_completed(futures):
                yield f.result()
        except BaseException:
            for f in futures:
                f.cancel()
            raise


def _execute_dask(plan: RunPlan, kind: str, spec_dict: dict, root: str, todo: list[int], scheduler: str):
    try:
        from dask.distributed import Client, as_completed as dask_completed
    except ImportError:
        raise InputError("--scheduler needs Dask: pip install 'dualsight[cluster]'", source="--scheduler") from None
    with Client(scheduler) as client:
        futures = [client.submit(execute_shard, kind, spec_dict, root, plan.run_id, s, *plan.bounds(s),
                                 pure=False, key=f"{plan.run_id}-shard-{s}") for s in todo]
        for f in dask_completed(futures):
            yield f.result()
