"""One night of ``dualsight nightly`` (the command: jobs/cli/nightly.py): run a suite into the lake, compare every
metric with the accepted baseline, keep the verdicts.

Every invocation is a new night ``<UTC date and time>`` (jobs/nightly/store.py): each job of the suite
(jobs/nightly/suite.py) runs through the engine (``run_job``) as ``nightly-<night>-<job>`` with its fixed seed
and, for the Monte Carlo kinds, as ``nightly-<night>-<job>.fresh`` with a seed from the clock (recorded in the
manifest and the verdicts); then jobs/nightly/compare.py compares it with the accepted baseline by SQL over the
lake's read-only views, jobs/nightly/stats.py tests the differences, and the verdicts are written as the dataset
``nightly_verdicts`` (run ``nightly-<night>-verdicts``).  ``accept`` makes this night the baseline
(``<lake>/_nightly/baseline.json``).

The night's exit status: 0 green (every verdict identical, ok, improved, info or skipped; or the night was
accepted), 1 red (a REGRESSION, or a job "not comparable" / without baseline), 2 the night could not run or be
compared (a job failed, no baseline accepted yet).
"""

from __future__ import annotations

import sys
import time

from dualsight.errors import InputError
from dualsight.jobs.engine.runner import run_job
from dualsight.jobs.nightly import store
from dualsight.jobs.nightly.compare import MetricSource, compare_job, decide_all
from dualsight.jobs.nightly.stats import RED
from dualsight.jobs.nightly.suite import Suite, load_suite
from dualsight.jobs.nightly.text import short_verdict
from dualsight.warehouse.lake import LakeError
from dualsight.warehouse.query import connect


def _say(msg: str):
    print(msg, file=sys.stderr, flush=True)


# ============================================================================================ one night
def run_nightly(suite, lake, *, accept: bool = False, workers: int | None = None, fresh_seed: int | None = None,
                progress: bool = False, log=_say) -> dict:
    """Run ``suite`` into ``lake`` as a new night and compare it; returns the night's summary.  ``suite``: a
    ``Suite``, or what ``load_suite`` takes (standard, quick or a suite TOML file).

    Keys: night, suite, exit (0/1/2), message, verdicts (rows), runs {job: {...}}, failed {job: reason},
    alpha (per test), tests (m), family_alpha, elapsed_s, baseline (night or None), accepted (path or None).
    """
    if not isinstance(suite, Suite):
        suite = load_suite(suite)
    t0 = time.perf_counter()
    baseline = store.read_baseline(lake)
    if baseline is not None and not accept and baseline.get("suite") not in (None, suite.name):
        # every job would be "not comparable" (or without baseline): say so before running anything
        raise InputError(f"the baseline (night {baseline.get('night')}) was accepted from suite "
                         f"{baseline.get('suite')!r}, tonight's suite is {suite.name!r}; run this suite once with "
                         f"--accept to make it the baseline, or run --suite {baseline.get('suite')}",
                         source=str(store.baseline_path(lake)))
    night = store.night_id(lake)
    seed = int(fresh_seed) if fresh_seed is not None else time.time_ns() % (2**63 - 1)
    runs, failed, timings = {}, {}, {}
    log(f"nightly {night}: suite {suite.name} ({len(suite.jobs)} jobs) into {lake.root}; fresh seed {seed}")
    for job in suite.jobs:
        if job.skip:
            runs[job.name] = {"kind": job.kind, "fixed": None, "skipped": job.skip}
            log(f"  {job.name}: skipped ({job.skip})")
            continue
        entry = {"kind": job.kind, "fixed": None, "fresh": None, "fresh_seed": seed if job.fresh_cases else None}
        variants = [("fixed", None, None)] + ([("fresh", seed, job.fresh_cases)] if job.fresh_cases else [])
        for variant, s, n in variants:
            spec, n_cases = job.make(s, n)
            rid = store.run_id(night, job.name, fresh=variant == "fresh")
            t1 = time.perf_counter()
            try:
                m = run_job(job.kind, spec, n_cases=n_cases, lake=lake, run_id=rid, workers=workers,
                            progress=progress, label=f"nightly {job.name} {variant}",
                            extra={"nightly": {"night": night, "job": job.name, "variant": variant}})
            except (LakeError, KeyboardInterrupt):
                raise
            except Exception as e:                       # a failed job: named, the others still run
                failed[job.name] = f"{variant} run {rid}: {type(e).__name__}: {' '.join(str(e).split())}"
                log(f"  {job.name}: FAILED ({failed[job.name]})")
                break
            if m.get("status") != "complete":
                failed[job.name] = f"{variant} run {rid} ended {m.get('status')}"
                break
            entry[variant] = rid
            timings[rid] = time.perf_counter() - t1
            log(f"  {job.name} {variant}: {n_cases} cases in {timings[rid]:.1f} s ({rid})")
        runs[job.name] = entry

    rows = []
    con = connect(lake, warn=lambda msg: log(f"  warning: {msg}"))
    try:
        src = MetricSource(con, lake)
        for job in suite.jobs:
            r = runs[job.name]
            if r.get("skipped"):
                rows.append({"job": job.name, "kind": job.kind, "comparison": "-", "metric": "-", "verdict": "skipped",
                             "test": "", "note": r["skipped"]})
            elif job.name in failed:
                rows.append({"job": job.name, "kind": job.kind, "comparison": "-", "metric": "-", "verdict": "failed",
                             "test": "", "note": failed[job.name], "now_run": r.get("fixed")})
            else:
                rows += compare_job(src, lake, job, r, (baseline or {}).get("jobs", {}).get(job.name),
                                    store.throughput_history(baseline, job.name), suite.throughput_min_s)
    finally:
        con.close()
    alpha, m = decide_all(rows, suite.alpha)

    red = [r for r in rows if r["verdict"] in RED]
    if failed:
        code, msg = 2, f"{len(failed)} job(s) could not run: " + "; ".join(f"{k}: {v}" for k, v in failed.items())
    elif baseline is None and not accept:
        code, msg = 2, (f"no accepted baseline in {store.baseline_path(lake)}; run `dualsight nightly --accept` once "
                        "to make a night the baseline")
    elif accept:
        code, msg = 0, f"accepted night {night} as the baseline"
    elif red:
        code, msg = 1, f"RED: {len(red)} verdict(s) " + "; ".join(short_verdict(r) for r in red[:8])
    else:
        code, msg = 0, f"GREEN: {len(rows)} verdicts, none red"
    summary = {"night": night, "suite": suite.name, "exit": code, "message": msg, "fresh_seed": seed,
               "family_alpha": suite.alpha, "alpha": alpha, "tests": m,
               "baseline": baseline["night"] if baseline else None, "failed": failed,
               "runs": runs, "run_seconds": timings, "elapsed_s": time.perf_counter() - t0,
               "accepted": bool(accept and not failed)}
    if accept and failed:
        summary["message"] = msg + "; the night was NOT accepted"
    store.write_verdicts(lake, night, suite.name, rows, {k: v for k, v in summary.items() if k != "runs"})
    if summary["accepted"]:
        summary["accepted"] = str(store.accept(lake, night, suite.name, runs, baseline))
    summary["verdicts"] = rows
    summary["elapsed_s"] = time.perf_counter() - t0
    return summary
