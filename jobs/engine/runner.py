"""The one engine every job runs on: identity, plan, shards, executors, resume, faults, progress.

A *job kind* is a module listed in :data:`JOB_KINDS` (a fixed table, never a user-supplied dotted path)
that defines::

    NAME: str                          job name recorded in the manifest
    PRIMARY: str                       primary dataset: one row per case, int64 column ``case_id``
    SCHEMAS: dict[str, pa.Schema]      every dataset it writes, with its exact Arrow schema
    spec_from_dict(d, source) -> spec  validated spec (raises ConfigError); ``spec.to_dict()`` is canonical
    make_context(spec) -> ctx          per-process state (catalogs, tables), built once per worker process
    compute_shard(spec, case_ids, ctx) -> {dataset: pa.Table}
    optional: memory_estimate(spec) -> bytes, shard_summary(tables) -> {name: int}, progress_postfix(stats) -> str,
              datasets(spec) -> [names]: the datasets of SCHEMAS this spec writes (default: all),
              MAX_SHARD_CASES: int, cases per shard at most (a kind whose cases take seconds each)

Identity.  A run is its canonical spec: ``spec_hash`` is a SHA-256 over the kind, the canonical spec, the
number of cases and the code version (:func:`dualsight.version.code_version`).  The manifest and every
shard file carry it; resuming an id with another hash is refused.  Resume verifies every shard file it
keeps (:func:`dualsight.warehouse.lake.verify_shard`) and recomputes the others.

Determinism.  Case ``i`` draws everything from ``numpy.random.default_rng([seed, i])``, so a shard's rows
are the same whatever worker, executor or machine computes it: a recomputed shard replaces its files
under the same names, never adding rows.

Executors: in-process (``workers=1``), spawned local worker processes (a fork of an initialised Taichi
runtime hangs), or a Dask cluster (``scheduler``).  Shards are produced lazily and at most a few per
worker are in flight, so planning and coordinating a 10^9-case run takes memory independent of its size.
"""

from __future__ import annotations

import ast
import ctypes
import hashlib
import importlib
import inspect
import json
import math
import multiprocessing as mp
import os
import platform
import signal
import socket
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dualsight.errors import InputError
from dualsight.jobs.engine.dask_executor import connect, run_on_dask
from dualsight.jobs.engine.errors import EngineError
from dualsight.jobs.engine.specs import check_memory
from dualsight.version import code_version
from dualsight.warehouse.lake import Lake, LakeError
from dualsight.warehouse.paths import check_run_id, os_error_text
from dualsight.warehouse.shards import ShardInfo

JOB_KINDS = {
    "star": "dualsight.jobs.kinds.star",
    "prox_sweep": "dualsight.jobs.kinds.prox",
    "prox_trajectory": "dualsight.jobs.kinds.prox",
    "hil_star": "dualsight.jobs.kinds.hil_star",
    "hil_prox": "dualsight.jobs.kinds.hil_prox",
    "calibrate": "dualsight.jobs.kinds.calibrate",
    "selftest": "dualsight.jobs.kinds.selftest",
    "hil_star_sweep": "dualsight.jobs.kinds.hil_star_sweep",
    "peer_star": "dualsight.jobs.kinds.peer_star",
    "star_track": "dualsight.jobs.kinds.star_track",
    "rendezvous": "dualsight.jobs.kinds.rendezvous",
}
MAX_CASES = 10**9
MAX_SHARD_SIZE = 10**6
MAX_WORKERS = 512
WORKER_RESTARTS = 3
MANIFEST_EVERY_S = 2.0


def job_module(kind: str):
    """The module implementing job kind ``kind``."""
    if kind not in JOB_KINDS:
        raise InputError(f"unknown job kind {kind!r}; known: {', '.join(sorted(JOB_KINDS))}")
    return importlib.import_module(JOB_KINDS[kind])


def spec_hash(kind: str, spec_dict: dict, n_cases: int, code: str | None = None) -> str:
    """16 hex digits of SHA-256 over the canonical JSON of (kind, spec, n_cases, code version)."""
    doc = {"kind": kind, "spec": spec_dict, "n_cases": int(n_cases), "code": code or code_version()}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def default_run_id(kind: str, hash_hex: str) -> str:
    """The id of a run started without one (``run_job``'s default): ``<kind, dashes for underscores>-<hash_hex>``
    (the run's :func:`spec_hash`)."""
    return f"{kind.replace('_', '-')}-{hash_hex}"


def default_shard_size(n_cases: int, max_cases: int | None = None) -> int:
    """Cases per shard from the case count and the kind alone (never from the worker count, so a rerun on other
    hardware plans the same shards): 1/8 of the run within [25, 1000], at most ``max_cases`` (a kind's
    ``MAX_SHARD_CASES``: cases that take seconds each, so that a shard, the unit of progress and of work lost to a
    killed worker, stays near a minute), growing to 1/10^4 of the run beyond 10^7 cases so that no run has more
    than ~10^4 shards."""
    size = min(1000, max(25, math.ceil(n_cases / 8)))
    if max_cases is not None:
        size = min(size, max(1, int(max_cases)))
    return int(max(size, math.ceil(n_cases / 10**4)))


@dataclass(frozen=True)
class Plan:
    run_id: str
    kind: str
    n_cases: int
    shard_size: int
    spec_hash: str

    @property
    def n_shards(self) -> int:
        return -(-self.n_cases // self.shard_size)

    def info(self, shard: int) -> ShardInfo:
        start = shard * self.shard_size
        return ShardInfo(self.run_id, self.spec_hash, shard, start, min(self.n_cases, start + self.shard_size))


@dataclass(frozen=True)
class ShardTask:
    """Everything a worker needs for one shard (small, picklable, no project objects)."""

    kind: str
    spec_json: str
    code_version: str
    lake_root: str
    info: ShardInfo


_CONTEXT: dict = {}


def _context(kind: str, spec_json: str):
    """(spec, ctx) for this process; one entry (a worker serves one run at a time)."""
    key = (kind, spec_json)
    if key not in _CONTEXT:
        _CONTEXT.clear()
        mod = job_module(kind)
        spec = mod.spec_from_dict(json.loads(spec_json), "spec")
        _CONTEXT[key] = (spec, mod.make_context(spec))
    return _CONTEXT[key]


def execute_shard(task: ShardTask) -> dict:
    """Compute one shard and write its files (any process); returns its journal entry plus timings."""
    if task.code_version != code_version():
        raise RuntimeError(f"worker {socket.gethostname()} runs dualsight {code_version()}, the run needs "
                           f"{task.code_version}; install the same code on every worker")
    mod = job_module(task.kind)
    spec, ctx = _context(task.kind, task.spec_json)
    info = task.info
    t0 = time.perf_counter_ns()
    tables = mod.compute_shard(spec, np.arange(info.case_start, info.case_stop, dtype=np.int64), ctx)
    t1 = time.perf_counter_ns()
    entry = Lake(Path(task.lake_root)).write_shard(info, tables, mod.PRIMARY, mod.SCHEMAS)
    entry.update(compute_ns=t1 - t0, write_ns=time.perf_counter_ns() - t1, pid=os.getpid())
    if hasattr(mod, "shard_summary"):
        entry["stats"] = mod.shard_summary(tables)
    return entry


def versions() -> dict:
    """Versions of Python and the main packages, for the manifest."""
    out = {"python": platform.python_version(), "dualsight": code_version()}
    for name in ("numpy", "taichi", "pyarrow", "duckdb", "astropy", "opencv-python-headless"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


def _check_int(value, lo, hi, flag):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise InputError(f"must be an integer in [{lo}, {hi:,}], got {value!r}", source=flag)
    return int(value)


def prepare(kind: str, spec_dict: dict, n_cases: int, *, source: str = "spec"):
    """Validate everything that decides a run, before the lake is touched: (module, spec, canonical dict, hash)."""
    mod = job_module(kind)
    n_cases = _check_int(n_cases, 1, MAX_CASES, "--cases")
    spec = mod.spec_from_dict(spec_dict, source)
    canonical = json.loads(json.dumps(spec.to_dict(), sort_keys=True))
    if hasattr(mod, "memory_estimate"):
        check_memory(mod.memory_estimate(spec), source=source)
    return mod, spec, canonical, spec_hash(kind, canonical, n_cases)


def run_job(kind: str, spec_dict: dict, *, n_cases: int, lake: Lake, run_id: str | None = None,
            workers: int | None = None, threads_per_worker: int | None = None, shard_size: int | None = None,
            scheduler: str | None = None, progress: bool = True, label: str | None = None,
            extra: dict | None = None, source: str = "spec") -> dict:
    """Run (or resume) ``n_cases`` cases of job ``kind`` into ``lake``; returns the final manifest.

    Everything is validated before the lake is touched.  ``run_id`` None means ``<kind>-<spec hash>``.
    Raises InputError (bad input, another spec under this id), LakeError (lake not writable, run locked,
    damaged manifest), EngineError (workers or scheduler lost) or :class:`Interrupted`; in every case
    the shards completed so far stay in the lake and the same call resumes.
    """
    mod, spec, canonical, h = prepare(kind, spec_dict, n_cases, source=source)
    run_id = check_run_id(run_id if run_id is not None else default_run_id(kind, h))
    workers = _check_int(workers if workers is not None else (os.cpu_count() or 1), 1, MAX_WORKERS, "--workers")
    if shard_size is not None:
        shard_size = _check_int(shard_size, 1, MAX_SHARD_SIZE, "--shard-size")
    if scheduler is not None and (not isinstance(scheduler, str) or not scheduler.strip()):
        raise InputError(f"must be a Dask scheduler address such as tcp://host:8786, got {scheduler!r}",
                         source="--scheduler")
    datasets = list(mod.datasets(spec) if hasattr(mod, "datasets") else mod.SCHEMAS)   # a kind may drop some
    existing = lake.read_manifest(run_id)          # refuse a conflicting id before touching anything
    if existing is not None:
        _refuse_other(existing, kind, canonical, n_cases, h, lake, run_id)
    client = connect(scheduler) if scheduler else None      # no scheduler answering: nothing written
    try:
        return _run_job_locked(mod, kind, canonical, h, n_cases, lake, run_id, datasets, shard_size, label, extra,
                               workers, threads_per_worker, scheduler, progress, client)
    finally:
        if client is not None:
            try:
                client.close(timeout=5)
            except Exception:      # noqa: BLE001 - the scheduler may already be gone
                pass


def _run_job_locked(mod, kind, canonical, h, n_cases, lake, run_id, datasets, shard_size, label, extra, workers,
                    threads_per_worker, scheduler, progress, client):
    with lake.lock(run_id):
        existing = lake.read_manifest(run_id)
        if existing is not None:
            _refuse_other(existing, kind, canonical, n_cases, h, lake, run_id)
            if shard_size is not None and shard_size != existing["shard_size"]:
                raise InputError(f"run {run_id!r} was planned with {existing['shard_size']} cases per shard; "
                                 f"omit --shard-size or give {existing['shard_size']}", source="--shard-size")
            plan = Plan(run_id, kind, n_cases, existing["shard_size"], h)
            manifest = existing
        else:
            foreign = lake.foreign_spec_hashes(run_id, datasets, h)
            if foreign:
                raise InputError(f"run {run_id!r} has no manifest but its shards belong to another spec "
                                 f"(hash {sorted(foreign)[0]}, this one {h}); choose another --run, or remove "
                                 "the old run with `dualsight lake check --repair`", source="--run")
            plan = Plan(run_id, kind, n_cases,
                        shard_size or default_shard_size(n_cases, getattr(mod, "MAX_SHARD_CASES", None)), h)
            manifest = {"run_id": run_id, "kind": kind, "job": mod.NAME, "label": label, "spec": canonical,
                        "spec_hash": h, "code_version": code_version(), "seed": canonical.get("seed"),
                        "n_cases": n_cases, "shard_size": plan.shard_size, "n_shards": plan.n_shards,
                        "datasets": datasets, "primary": mod.PRIMARY, "versions": versions(),
                        "host": socket.gethostname(), "created_unix": time.time(), "status": "running",
                        "stats": {}, **(extra or {})}
        try:
            return _run_locked(mod, plan, manifest, lake, datasets, workers, threads_per_worker, scheduler,
                               progress, label or f"{kind} {run_id}", client)
        except OSError as e:
            raise LakeError(f"cannot write to the lake ({os_error_text(e)}); the shards completed before are "
                            "intact, free space or fix permissions and run the same command to resume",
                            source=str(lake.root)) from None


def _refuse_other(existing, kind, canonical, n_cases, h, lake, run_id):
    if existing["spec_hash"] == h:
        return
    diffs = []
    if existing.get("kind") != kind:
        diffs.append(f"kind {existing.get('kind')} -> {kind}")
    if existing.get("n_cases") != n_cases:
        diffs.append(f"cases {existing.get('n_cases')} -> {n_cases}")
    old = existing.get("spec") or {}
    keys = sorted(k for k in set(old) | set(canonical) if old.get(k) != canonical.get(k))
    if keys:
        diffs.append("spec keys " + ", ".join(keys[:6]))
    if existing.get("code_version") != code_version():
        diffs.append(f"code version {existing.get('code_version')} -> {code_version()}")
    raise InputError(f"run {run_id!r} in {lake.root} was made with other settings ({'; '.join(diffs) or 'spec'}); "
                     f"resume it with the same settings, or choose a new id, e.g. --run {run_id}-2", source="--run")


def _run_locked(mod, plan: Plan, manifest: dict, lake: Lake, datasets, workers, threads_per_worker, scheduler,
                progress, desc, client=None) -> dict:
    lake.remove_stale_temps(plan.run_id, datasets)
    done, entries, recomputed = set(), [], []
    for s in sorted(lake.shard_indices_on_disk(plan.run_id, datasets)):
        problem = lake.verify_shard(plan.info(s), datasets, mod.PRIMARY) if s < plan.n_shards else "beyond the plan"
        if problem is None:
            done.add(s)
            entries.append(lake.shard_entry(plan.info(s), datasets))
        else:
            lake.remove_shard(plan.run_id, s, datasets)
            recomputed.append(s)
            print(f"dualsight: run {plan.run_id} shard {s}: {problem}; it will be recomputed", file=sys.stderr)
    lake.reset_journal(plan.run_id, entries)
    lake.write_spec_copy(manifest)
    stats = {}
    for e in entries:
        for k, v in (e.get("stats") or {}).items():
            stats[k] = stats.get(k, 0) + v
    manifest.update(status="running", stats=manifest.get("stats") or {}, shards_done=len(done))
    execution = {"started_unix": time.time(), "workers": workers, "scheduler": scheduler, "pid": os.getpid(),
                 "resumed_shards": len(done), "recomputed_shards": len(recomputed), "host": socket.gethostname()}
    manifest.setdefault("executions", []).append(execution)
    lake.write_manifest(manifest)
    n_todo = plan.n_shards - len(done)
    if n_todo == 0:
        manifest["status"] = "complete"
        lake.write_manifest(manifest)
        return manifest

    tasks = (ShardTask(plan.kind, json.dumps(manifest["spec"], sort_keys=True), manifest["code_version"],
                       str(lake.root.resolve()), plan.info(s)) for s in range(plan.n_shards) if s not in done)
    bar = _progress(plan, done, progress, desc)
    t_start, last_write, cases_run = time.perf_counter(), time.monotonic(), 0
    status = "interrupted"
    try:
        for entry in _execute(tasks, plan, lake, workers, threads_per_worker, scheduler, n_todo, client):
            lake.append_journal(plan.run_id, {k: entry[k] for k in ("shard", "case_start", "case_stop", "rows",
                                                                     "bytes")} | {"stats": entry.get("stats")})
            done.add(entry["shard"])
            n = entry["case_stop"] - entry["case_start"]
            cases_run += n
            for k, v in (entry.get("stats") or {}).items():
                stats[k] = stats.get(k, 0) + v
            if time.monotonic() - last_write > MANIFEST_EVERY_S:
                manifest.update(shards_done=len(done), stats=stats)
                lake.write_manifest(manifest)
                last_write = time.monotonic()
            if bar is not None:
                bar.update(n)
                if hasattr(mod, "progress_postfix"):
                    bar.set_postfix_str(mod.progress_postfix(stats), refresh=False)
        status = "complete" if len(done) == plan.n_shards else "incomplete"
    except EngineError:
        status = "failed"
        raise
    finally:
        if bar is not None:
            bar.close()
        execution.update(elapsed_s=time.perf_counter() - t_start, cases_run=cases_run, ended=status)
        manifest.update(status=status, shards_done=len(done), stats=stats)
        try:
            lake.write_manifest(manifest)
        except OSError:
            pass        # the lake is full or read-only: the caller reports it; the old manifest is intact
    return manifest


def _progress(plan: Plan, done: set[int], enabled: bool, desc: str):
    if not enabled:
        return None
    already = sum(plan.info(s).case_stop - plan.info(s).case_start for s in done)
    return tqdm(total=plan.n_cases, initial=already, desc=desc, unit="case", dynamic_ncols=True, file=sys.stderr,
                smoothing=0.1, mininterval=0.5)


# ============================================================================================ executors
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "DUALSIGHT_TI_THREADS",
                "OPENCV_FOR_THREADS_NUM")
"""Thread-pool sizes a spawned worker reads at start (BLAS/OpenMP, Taichi, OpenCV's parallel_for)."""


def _execute(tasks, plan, lake, workers, threads_per_worker, scheduler, n_todo, client=None):
    """Yield journal entries of completed shards from the chosen executor."""
    if scheduler:
        yield from run_on_dask(tasks, plan, lake, scheduler, execute_shard, client)
        return
    script = unguarded_main_call() if workers > 1 and n_todo > 1 else None
    if script is not None:
        print(f"dualsight: warning: {script} starts this run at import time, outside `if __name__ == \"__main__\":`, "
              "where spawned workers would run the script again; the run goes on in this process instead (same "
              f"rows); put the call under `if __name__ == \"__main__\":` to use {workers} workers", file=sys.stderr)
    if workers == 1 or n_todo == 1 or script is not None:
        if threads_per_worker:
            os.environ["DUALSIGHT_TI_THREADS"] = str(threads_per_worker)
        for task in tasks:
            yield execute_shard(task)
        return
    threads = threads_per_worker or max(1, (os.cpu_count() or 1) // workers)
    # spawned workers inherit the environment at start: cap their BLAS/OpenMP/Taichi pools, or W workers each
    # running a pool of all cores oversubscribe the machine
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: str(worker_threads(saved[k], threads)) for k in _THREAD_VARS})
    try:
        yield from _local_pool(tasks, min(workers, n_todo))
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def worker_threads(current: str | None, share: int) -> int:
    """A spawned worker's pool size: its ``share`` of the cores (cores // workers), or less when the variable
    already asks for less (the BLAS pools default to 1 thread, ``dualsight/__init__.py``)."""
    try:
        n = int(current) if current is not None else share
    except ValueError:
        n = share
    return max(1, min(n, share)) if n > 0 else share


def unguarded_main_call() -> str | None:
    """The file of the main script when it is calling now from its module-level code outside ``if __name__ ==
    "__main__":`` and spawned workers would run that code again (``multiprocessing``'s spawn re-runs the main
    module as ``__mp_main__`` in every worker, so an unguarded run would start again in each and the workers
    die); otherwise None.  Nothing is re-run when the main module is interactive, ``-c`` or a package's
    ``__main__`` (``python -m dualsight``); the guard is found in the script's syntax tree around the calling
    line (a script whose source cannot be read counts as guarded)."""
    main = sys.modules.get("__main__")
    spec_name = getattr(getattr(main, "__spec__", None), "name", None)
    if main is None or (spec_name is not None and spec_name.rpartition(".")[2] == "__main__") \
            or (spec_name is None and getattr(main, "__file__", None) is None):
        return None
    frame = inspect.currentframe()
    while frame is not None and not (frame.f_globals is vars(main) and frame.f_code.co_name == "<module>"):
        frame = frame.f_back
    if frame is None:                       # the script's module code has finished: a worker would not call
        return None
    path, line = frame.f_code.co_filename, frame.f_lineno
    del frame
    try:
        tree = ast.parse(Path(path).read_bytes(), filename=path)
    except (OSError, SyntaxError, ValueError):
        return None
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and _is_main_test(node.test) \
                and node.body[0].lineno <= line <= (node.body[-1].end_lineno or node.body[-1].lineno):
            return None
    return path


def _is_main_test(test) -> bool:
    """``__name__ == "__main__"`` (either way round)."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return False
    sides = [test.left, test.comparators[0]]
    return (any(isinstance(x, ast.Name) and x.id == "__name__" for x in sides)
            and any(isinstance(x, ast.Constant) and x.value == "__main__" for x in sides))


def _worker_init(parent_pid: int):
    """In each spawned worker: leave Ctrl-C to the parent, and die with it (Linux PR_SET_PDEATHSIG)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:      # the parent died before prctl took effect
        os._exit(1)


def _kill_pool(pool: ProcessPoolExecutor):
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        try:
            p.kill()
        except (OSError, AttributeError):
            pass
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        p.join(timeout=5)


def _local_pool(tasks, workers: int):
    """Run tasks on ``workers`` spawned processes, at most 2 per worker in flight.

    A worker that dies (killed, out of memory) breaks the pool: its in-flight shards are recomputed on a
    fresh pool, up to :data:`WORKER_RESTARTS` times; then :class:`EngineError`.  Any exception here
    (Ctrl-C, SIGTERM, an error) kills every worker before it propagates.
    """
    ctx = mp.get_context("spawn")
    retry: list[ShardTask] = []
    restarts = 0
    exhausted = False
    while True:
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                                   initargs=(os.getpid(),))
        inflight: dict = {}
        broken = None
        try:
            while True:
                while len(inflight) < 2 * workers and (retry or not exhausted):
                    if retry:
                        t = retry.pop()
                    else:
                        t = next(tasks, None)
                        if t is None:
                            exhausted = True
                            break
                    inflight[pool.submit(execute_shard, t)] = t
                if not inflight:
                    pool.shutdown(wait=True)
                    return
                finished, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
                for f in finished:
                    t = inflight.pop(f)
                    try:
                        yield f.result()
                    except BrokenProcessPool as e:
                        broken = e
                        retry.append(t)
                    except OSError:
                        raise
                    except Exception as e:          # a bug or bad data inside a shard: name it, keep the lake
                        raise EngineError(f"shard {t.info.shard} (cases {t.info.case_start}-{t.info.case_stop - 1}) "
                                          f"failed: {type(e).__name__}: {e}") from None
                if broken is not None:
                    retry.extend(inflight.values())
                    inflight.clear()
                    break
        except BaseException:
            _kill_pool(pool)
            raise
        _kill_pool(pool)
        restarts += 1
        if restarts > WORKER_RESTARTS:
            raise EngineError(f"a worker process died {restarts} times ({broken}); the completed shards are kept, "
                              "run the same command again to resume")
        print(f"dualsight: a worker process died; recomputing {len(retry)} shard(s) on new workers "
              f"(restart {restarts}/{WORKER_RESTARTS})", file=sys.stderr)
