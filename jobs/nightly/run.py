"""``dualsight nightly``: run a suite into the lake, compare every metric with the accepted baseline, keep verdicts.

    dualsight nightly [--suite standard|quick|FILE.toml] [--lake DIR] [--accept] [--html FILE] [--json]
                      [--workers N] [--fresh-seed S] [--no-progress]
    dualsight nightly history [--lake DIR] [--json] [--html FILE]

Every invocation is a new night ``<UTC date and time>`` (jobs/nightly/store.py): each job of the suite
(jobs/nightly/suite.py) runs through the engine (``run_job``) as ``nightly-<night>-<job>`` with its fixed seed
and, for the Monte Carlo kinds, as ``nightly-<night>-<job>.fresh`` with a seed from the clock (recorded in the
manifest and the verdicts); then jobs/nightly/compare.py compares it with the accepted baseline by SQL over the
lake's read-only views, jobs/nightly/stats.py tests the differences, and the verdicts are printed and written
as the dataset ``nightly_verdicts`` (run ``nightly-<night>-verdicts``).  ``--accept`` makes this night the
baseline (``<lake>/_nightly/baseline.json``).

Exit status: 0 green (every verdict identical, ok, improved, info or skipped; or the night was accepted),
1 red (a REGRESSION, or a job "not comparable" / without baseline: accept the new suite deliberately),
2 the night could not run or be compared (bad suite, a job failed, no baseline accepted yet, lake unusable).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

from dualsight.errors import InputError
from dualsight.jobs.nightly import store
from dualsight.jobs.nightly.stats import RED


def register(sub) -> None:
    """Add the ``nightly`` command (and ``nightly history``) to the top-level sub-parsers."""
    from dualsight.jobs.cli.args import _lake_arg, positive_int

    p = sub.add_parser("nightly", help="run the nightly suite, compare with the accepted baseline, keep verdicts",
                       description="Run a suite of jobs into the lake as a new night, compare every metric with "
                                   "the accepted baseline (identical rows, Fisher exact tests of rates, bootstrap "
                                   "tests of error distributions, throughput ratio) and store the verdicts as the "
                                   "dataset nightly_verdicts.  Exit 0 green, 1 regression, 2 could not run.")
    p.add_argument("--suite", default="standard",
                   help="standard (built-in, default), quick (examples/nightly/quick.toml) or a suite TOML file")
    _lake_arg(p)
    p.add_argument("--accept", action="store_true", help="make this night the accepted baseline")
    p.add_argument("--html", type=Path, default=None, help="write a self-contained HTML page (verdicts, trends) and "
                                                           "the trend figure as PNG beside it")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the verdict lines")
    p.add_argument("--workers", type=positive_int(1, 512), default=None,
                   help="local worker processes per job (default: one per core)")
    p.add_argument("--fresh-seed", type=positive_int(0, 2**63 - 1), default=None,
                   help="seed of the fresh samples (default: from the clock; recorded either way)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_nightly)
    hsub = p.add_subparsers(dest="nightly_action", metavar="ACTION")
    h = hsub.add_parser("history", help="every metric's trend over the nights (from nightly_verdicts, by SQL)")
    _lake_arg(h)
    h.add_argument("--json", action="store_true", help="print one JSON object")
    h.add_argument("--html", type=Path, default=None, help="write the self-contained HTML page (and its PNG)")
    h.set_defaults(func=cmd_history)


def _lake(args):
    from dualsight.jobs.cli.args import _lake as cli_lake

    return cli_lake(args)


def _say(msg: str):
    print(msg, file=sys.stderr, flush=True)


# ============================================================================================ one night
def run_nightly(suite, lake, *, accept: bool = False, workers: int | None = None, fresh_seed: int | None = None,
                progress: bool = False, log=_say) -> dict:
    """Run ``suite`` into ``lake`` as a new night and compare it; returns the night's summary.

    Keys: night, suite, exit (0/1/2), message, verdicts (rows), runs {job: {...}}, failed {job: reason},
    alpha (per test), tests (m), family_alpha, elapsed_s, baseline (night or None), accepted (path or None).
    """
    from dualsight.jobs.nightly.compare import MetricSource, compare_job, decide_all
    from dualsight.jobs.engine.runner import run_job
    from dualsight.warehouse.lake import LakeError
    from dualsight.warehouse.query import connect

    t0 = time.perf_counter()
    baseline = store.read_baseline(lake)
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
        src = MetricSource(con)
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
        code, msg = 1, f"RED: {len(red)} verdict(s) " + "; ".join(_short(r) for r in red[:8])
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


def _short(r: dict) -> str:
    return f"{r['job']} {r['comparison']} {r['metric']} {r['verdict']}"


def _num(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}" if v == v else "nan"
    return str(v)


def verdict_line(r: dict) -> str:
    """One line per verdict: job, comparison, metric, baseline -> now, the test and its p-value or threshold."""
    if r["verdict"] in ("skipped", "failed"):
        return f"{r['job']:<22} {r['verdict']}: {r.get('note', '')}"
    if r.get("alpha") is not None and r.get("threshold") is not None:
        thr = f"p={r['threshold']:.2g} (alpha {r['alpha']:.2g})"
    elif r.get("threshold") is not None:
        thr = f"threshold {_num(r['threshold'])}"
    else:
        thr = ""
    note = f"  [{r['note']}]" if r.get("note") else ""
    return (f"{r['job']:<22} {r['comparison']:<10} {r['metric']:<30} {_num(r.get('baseline')):>10} -> "
            f"{_num(r.get('now')):<10} {r['verdict']:<14} {r.get('test') or ''} {thr}{note}")


def verdicts_text(rows: list[dict]) -> str:
    """Every verdict line, except that a job's metrics that are all "identical" share one line."""
    out = []
    for r in rows:
        if r["verdict"] == "identical" and r["metric"] != "rows":
            continue
        if r["metric"] == "rows" and r["verdict"] == "identical":
            n = sum(1 for x in rows if x["job"] == r["job"] and x["comparison"] == "fixed"
                    and x["verdict"] == "identical" and x["metric"] != "rows")
            out.append(f"{r['job']:<22} {'fixed':<10} {n} metrics identical: {int(r['now']):,} rows equal to the "
                       f"baseline's ({r['test']}, {int(r['threshold'] or 0)} differ)")
            continue
        out.append(verdict_line(dict(r, note=r["note"] if not str(r.get("note", "")).startswith("fresh seed")
                                      else r["note"].partition("; ")[2])))
    return "\n".join(out)


def _clean(v):
    """JSON-safe: NaN and infinities become null."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def cmd_nightly(args) -> int:
    from dualsight.jobs.nightly.suite import load_suite

    if args.html is not None and not Path(args.html).parent.is_dir():
        raise InputError(f"folder {Path(args.html).parent} does not exist", source="--html")
    suite = load_suite(args.suite)
    lake = _lake(args)
    s = run_nightly(suite, lake, accept=args.accept, workers=args.workers, fresh_seed=args.fresh_seed,
                    progress=not args.no_progress and sys.stderr.isatty())
    if args.html is not None:
        png = _write_html(lake, args.html, night=s["night"])
        _say(f"page: {args.html} (figure {png})")
    if args.json:
        print(json.dumps(_clean(s), indent=1, default=str))
    else:
        print(f"night {s['night']} (suite {s['suite']}, baseline {s['baseline'] or 'none'}, fresh seed "
              f"{s['fresh_seed']}; {s['tests']} tests at alpha {s['alpha']:.2g} each, family-wise "
              f"<= {s['family_alpha']:g})")
        print(verdicts_text(s["verdicts"]))
        print(s["message"])
    _say(f"nightly {s['night']}: exit {s['exit']} after {s['elapsed_s']:.0f} s; "
         f"history: dualsight nightly history --lake {lake.root}")
    return s["exit"]


# ============================================================================================ history
def _write_html(lake, path: Path, night: str | None = None) -> Path:
    from dualsight.viz.nightly_html import write_page

    rows, nights = store.history(lake)
    last = night or (nights[-1]["night"] if nights else None)
    m = lake.read_manifest(store.run_id(last, "verdicts")) if last else None
    info = (m or {}).get("nightly") or {}
    outcome = (info["exit"], info.get("message", "")) if "exit" in info else None
    return write_page(Path(path), [r for r in rows if r["night"] == last], rows, nights,
                      title=f"dualsight nightly, {lake.root}", outcome=outcome)


def history_text(trends: list[dict], nights: list[dict], last_n: int = 8) -> str:
    lines = [f"{len(nights)} night(s); the last {min(len(nights), last_n)}:"]
    lines += [f"  {n['night']}: exit {n.get('exit', '?')}{' (accepted)' if n.get('accepted') else ''}, "
              f"{n['regressions']} regressions, {n['not_comparable']} not comparable / no baseline / failed, "
              f"{n['identical']} identical, {n['ok']} ok, {n['improved']} improved" for n in nights[-last_n:]]
    lines.append(f"{'job':<22} {'comparison':<10} {'metric':<30} values, oldest -> newest (last {last_n})  "
                 "last verdict")
    for t in trends:
        pts = t["points"][-last_n:]
        vals = " ".join(f"{_num(p['now']):>9}" for p in pts)
        lines.append(f"{t['job']:<22} {t['comparison']:<10} {t['metric']:<30} {vals}  {pts[-1]['verdict']}")
    return "\n".join(lines)


def cmd_history(args) -> int:
    if args.html is not None and not Path(args.html).parent.is_dir():
        raise InputError(f"folder {Path(args.html).parent} does not exist", source="--html")
    lake = _lake(args)
    rows, nights = store.history(lake)
    trends = store.trends(rows)
    if args.html is not None:
        png = _write_html(lake, args.html)
        _say(f"page: {args.html} (figure {png})")
    if args.json:
        print(json.dumps(_clean({"nights": nights, "trends": trends}), indent=1, default=str))
    else:
        print(history_text(trends, nights))
    return 0
