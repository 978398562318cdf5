"""The star report over a large run: per-shard summaries versus the full scan of ``star_cases`` (issue 13).

    python benchmarks/bench_report.py [--cases 1000000] [--cases 100000 1000000] [--replicate 10 100]
                                      [--reuse LAKE] [--lake DIR] [--keep] [--json FILE] [--with-results FILE]

For each case count N: runs N paper-preset cases (noise-free frames, V 5.5, tolerance 10 arcsec) in this one process
(in-process executor, one worker) into a fresh lake in a temporary folder (or under ``--lake DIR``), and prints the
run's total time, cases/s, peak resident memory (``resource.getrusage``, this process and its children), the lake's
size on disk per dataset, then the report both ways side by side:

* summaries (``jobs/star_report.open_summaries`` + ``warehouse/sql/star_summ_*.sql``): the fixed cost of reading the
  run's summary files once (journal check, load, case count), then each query;
* full scan (``warehouse/sql/star_*.sql``): the fixed cost of the views over the lake, then each query;

each the best of ``--repeat`` runs on a warm page cache (the full scan once from 5x10^6 rows), with the rows each query scanned and the bytes it read
(DuckDB's profiler), ``star_report.build`` all in both ways, and the whole ``dualsight star report`` process (its
time, and its peak RSS under ``/usr/bin/time -v`` when available).

``--replicate K ...`` also measures the report over a run K times larger made from the largest measured one without
computing it: every shard file is hard-linked K times under new shard numbers, with a journal and manifest to match
(so the lake reads like a K x N-case run: K x files, K x rows; case ids repeat, which no report query looks at).  The
per-file and per-row work of the report is real; the disk reads are not (the copies share the page cache, like the
warm-cache measurements of the real runs).

Extrapolation to 10^7 rows: from 10^5 cases up, a run has shards of 1,000 cases (``default_shard_size``), so files,
summary rows and case rows all grow linearly in N.  With two case counts below 10^7 the time of each quantity is
fitted as ``t = a + b N`` through the two largest (a = fixed part, b = cost per case) and evaluated at 10^7 (never
below the time at the larger N); the scaling exponent log(t2/t1) / log(N2/N1) is printed beside it, with the plain
linear scaling t2 x 10^7 / N2 (an upper bound) and, when measured, the replicated 10^7-row lake.  With one case count,
times are scaled linearly.  ``--json`` keeps the measurements and ``--with-results`` brings an earlier run's into the
fit, so case counts can be measured in separate sittings.  Conditions (cores, load average) are printed with them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")

TARGET = 10**7
RUN = "bench"
SCAN_ONCE_FROM = 5 * 10**6        # the full scan is timed once from this many rows (it takes minutes)


def _best(fn, repeat: int) -> float:
    out = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t)
    return out


def _peak_rss_mb() -> float:
    """Peak resident set size (MB): the larger of this process's and of its largest waited-for child's."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024           # Linux: kB
    child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return max(own, child)


def _size_mib(folder: Path) -> float:
    """Bytes on disk under ``folder`` (MiB); a hard-linked file counts once."""
    if not folder.exists():
        return 0.0
    seen, total = set(), 0
    for p in folder.rglob("*"):
        st = p.stat()
        if p.is_file() and (st.st_dev, st.st_ino) not in seen:
            seen.add((st.st_dev, st.st_ino))
            total += st.st_size
    return total / 2**20


def _profile(con, sql: str, params: dict) -> tuple[int, int]:
    """(rows scanned, bytes read) of one query, from DuckDB's profiler (connection not locked)."""
    con.execute(sql, params).fetchall()
    info = json.loads(con.get_profiling_information())
    return int(info["query"]["total_rows_scanned"]), int(info["io"]["total_bytes_read"])


def run_cases(n_cases: int, lake_dir: Path) -> dict:
    """Run ``n_cases`` paper-preset cases in this process into ``lake_dir``; the run's numbers."""
    from dualsight.jobs.engine import runner
    from dualsight.jobs.kinds import star
    from dualsight.warehouse.lake import Lake

    spec, n = star.resolve_spec("paper", None, seed=1, cases=n_cases)
    t0 = time.perf_counter()
    manifest = runner.run_job("star", spec, n_cases=n, lake=Lake(lake_dir), run_id=RUN, workers=1, progress=False)
    wall = time.perf_counter() - t0
    assert manifest["status"] == "complete", manifest["status"]
    return {"cases": n, "kind": "run", "wall_s": wall, "peak_rss_mb": _peak_rss_mb()}


def replicate(src: Path, dst: Path, k: int) -> dict:
    """A lake whose run ``RUN`` is ``k`` copies (hard links) of the one in ``src``, journal and manifest to match."""
    from dualsight.warehouse.lake import Lake

    a, b = Lake(src), Lake(dst)
    m = a.read_manifest(RUN)
    entries = a.read_journal(RUN)
    assert m["n_cases"] % m["shard_size"] == 0, "replicate a run of whole shards"
    out = []
    for j in range(k):
        for e in entries:
            s = j * m["n_shards"] + int(e["shard"])
            for d in m["datasets"]:
                p = b.shard_path(d, RUN, s)
                p.parent.mkdir(parents=True, exist_ok=True)
                os.link(a.shard_path(d, RUN, int(e["shard"])), p)
            off = j * m["n_cases"]
            out.append(dict(e, shard=s, case_start=e["case_start"] + off, case_stop=e["case_stop"] + off))
    b.reset_journal(RUN, out)
    b.write_manifest(dict(m, n_cases=k * m["n_cases"], n_shards=k * m["n_shards"], status="complete"))
    return {"cases": k * m["n_cases"], "kind": f"replicated x{k} from {m['n_cases']:,}"}


def measure_report(lake_dir: Path, repeat: int) -> dict:
    """Both report paths over run ``RUN`` of ``lake_dir``: fixed costs, each query, build, the CLI."""
    from dualsight.jobs.kinds import star
    from dualsight.jobs.reports import star as star_report
    from dualsight.jobs.kinds.star_summaries import DATASET
    from dualsight.warehouse.lake import Lake
    from dualsight.warehouse.query import connect, sql_text

    lake = Lake(lake_dir)
    m = lake.read_manifest(RUN)
    big = m["n_cases"] >= SCAN_ONCE_FROM
    res = {"n_shards": m["n_shards"], "lake_mib": _size_mib(lake_dir),
           "dataset_mib": {d: _size_mib(lake_dir / d) for d in star.SCHEMAS},
           "summary_files": len(lake.scan(RUN).files[DATASET]),
           "summary_rows": sum(int(e["rows"][DATASET]) for e in lake.read_journal(RUN)),
           "scan_repeat": 1 if big else repeat, "queries": {}}
    # the summaries path: the run's summary files read once (journal check, load, case count), then six queries
    res["load_s"] = _best(lambda: star_report.open_summaries(lake, RUN).close(), repeat)
    con_s = star_report.open_summaries(lake, RUN)
    res["merged_rows"] = con_s.execute(f"SELECT count(*) FROM {DATASET}").fetchone()[0]
    prof_s = star_report.open_summaries(lake, RUN, locked=False)
    # the full scan: views over the lake, then six queries over star_cases
    res["views_s"] = _best(lambda: connect(lake).close(), res["scan_repeat"])
    con_f = connect(lake)
    prof_f = connect(lake, locked=False)
    for p in (prof_s, prof_f):
        p.execute("SET enable_profiling = 'no_output'")
        p.execute("SET tracked_metrics = ['*']")
    for name in star_report.QUERIES:
        row = {}
        for source, con, prof in (("summaries", con_s, prof_s), ("scan", con_f, prof_f)):
            sql, params = sql_text(star_report.query_name(name, source)), {"run": RUN}
            row[f"{source}_s"] = _best(lambda: con.execute(sql, params).fetchall(),
                                       repeat if source == "summaries" else res["scan_repeat"])
            row[f"{source}_rows"], row[f"{source}_bytes"] = _profile(prof, sql, params)
        res["queries"][name] = row
    for c in (con_s, prof_s, con_f, prof_f):
        c.close()
    for source in ("summaries", "scan"):
        res[f"build_{source}_s"] = _best(lambda: star_report.build(lake, RUN, source=source),
                                         repeat if source == "summaries" else res["scan_repeat"])
    # the user's command, under /usr/bin/time -v when there is one (its own peak RSS: getrusage's children figure
    # can carry the forking parent's)
    timer = ["/usr/bin/time", "-v"] if Path("/usr/bin/time").exists() else []
    t = time.perf_counter()
    r = subprocess.run(timer + [sys.executable, "-m", "dualsight", "star", "report", "--lake", str(lake_dir),
                                "--run", RUN], capture_output=True, text=True)
    res["cli_report_s"] = time.perf_counter() - t
    res["cli_exit"] = r.returncode
    found = re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr)
    res["cli_peak_rss_mb"] = int(found.group(1)) / 1024 if found else float("nan")
    res["peak_rss_mb_after_report"] = _peak_rss_mb()
    return res


def print_one(r: dict):
    n = r["cases"]
    print(f"\n== {n:,} cases ({r['kind']}), {r['n_shards']:,} shards ==")
    if r["kind"] == "run":
        print(f"run: {r['wall_s']:.1f} s in one process ({n / r['wall_s']:,.0f} cases/s), peak RSS "
              f"{r['peak_rss_mb']:.0f} MB (getrusage: this process and its children)")
    print(f"lake {r['lake_mib']:,.1f} MiB on disk (" + ", ".join(f"{d} {v:,.2f}" for d, v in r["dataset_mib"].items())
          + "); peak RSS of this process after both report paths " + f"{r['peak_rss_mb_after_report']:.0f} MB")
    print(f"summaries path, once per report: journal check + read {r['summary_files']:,} files "
          f"({r['summary_rows']:,} rows) summed per key into {r.get('merged_rows', '?')} rows + case count: "
          f"{r['load_s']:.3f} s")
    if r.get("scan_repeat") == 1:
        print("(scan path timed once at this size, summaries path best of the runs)")
    print(f"scan path, once per report: views over the lake {r['views_s']:.3f} s")
    print(f"{'query (best of runs)':<24}{'summaries s':>12}{'scan s':>10}{'speed-up':>10}{'rows (summ)':>13}"
          f"{'rows (scan)':>13}{'MiB read (scan)':>17}")
    for name, q in r["queries"].items():
        print(f"{name:<24}{q['summaries_s']:>12.4f}{q['scan_s']:>10.4f}{q['scan_s'] / q['summaries_s']:>9.0f}x"
              f"{q['summaries_rows']:>13,}{q['scan_rows']:>13,}{q['scan_bytes'] / 2**20:>17.2f}")
    tot_s = sum(q["summaries_s"] for q in r["queries"].values())
    tot_f = sum(q["scan_s"] for q in r["queries"].values())
    print(f"{'all six queries':<24}{tot_s:>12.4f}{tot_f:>10.4f}{tot_f / tot_s:>9.0f}x")
    print(f"star_report.build, all in: summaries {r['build_summaries_s']:.3f} s, scan {r['build_scan_s']:.3f} s; "
          f"`dualsight star report` whole process (auto: summaries) {r['cli_report_s']:.2f} s (exit {r['cli_exit']}), "
          f"peak RSS {r.get('cli_peak_rss_mb', float('nan')):.0f} MB")


def _keys(r: dict) -> dict:
    """Every timed quantity of one measurement, by name."""
    out = {f"{name} ({src})": q[f"{src}_s"] for name, q in r["queries"].items() for src in ("summaries", "scan")}
    out.update({"load summaries (once)": r["load_s"], "views (scan, once)": r["views_s"],
                "build, summaries": r["build_summaries_s"], "build, scan": r["build_scan_s"],
                "CLI star report (auto)": r["cli_report_s"]})
    if r["kind"] == "run":
        out["run (whole)"] = r["wall_s"]
    return out


def extrapolate(results: list[dict]):
    by_n = {}
    for r in results:         # one measurement per case count: a run computed here beats a replicated or reused one
        if r["cases"] < TARGET and (r["cases"] not in by_n or r["kind"] == "run"):
            by_n[r["cases"]] = r
    below = [by_n[k] for k in sorted(by_n)]
    at = [r for r in results if r["cases"] == TARGET]
    measured = _keys(at[-1]) if at else {}
    print(f"\n== extrapolation to {TARGET:,} rows ==")
    if not below:
        return
    if len(below) == 1:
        r = below[0]
        k = TARGET / r["cases"]
        print(f"one case count: every time scaled linearly by {k:g} (an upper bound: the fixed part is scaled too)")
        for name, t in _keys(r).items():
            extra = f"   measured (replicated): {measured[name]:.2f} s" if name in measured else ""
            print(f"  {name:<34}{t:>10.3f} s -> {t * k:>10.2f} s{extra}")
        return
    a, b = below[-2], below[-1]
    n1, n2 = a["cases"], b["cases"]
    print(f"fit t = t0 + c N through N = {n1:,} ({a['kind']}) and {n2:,} ({b['kind']}): files, summary rows and case "
          f"rows all grow as N ({a['n_shards']:,} -> {b['n_shards']:,} shards); exponent = log(t2/t1) / log(N2/N1)")
    print(f"  {'quantity':<34}{'t(' + format(n1, ',') + ')':>12}{'t(' + format(n2, ',') + ')':>13}{'exponent':>10}"
          f"{'10^7: fit':>11}{'linear':>9}{'measured':>10}")
    ka, kb = _keys(a), _keys(b)
    for name in kb:
        if name not in ka:
            continue
        t1, t2 = ka[name], kb[name]
        c = (t2 - t1) / (n2 - n1)
        fit = max(t2 + c * (TARGET - n2), t2)     # a time that did not grow from N1 to N2 is kept, not lowered
        expo = math.log(t2 / t1) / math.log(n2 / n1) if t1 > 0 and t2 > 0 else float("nan")
        meas = f"{measured[name]:>10.2f}" if name in measured else f"{'-':>10}"
        print(f"  {name:<34}{t1:>12.4f}{t2:>13.4f}{expo:>10.2f}{fit:>11.2f}{t2 * TARGET / n2:>9.2f}{meas}")
    if at:
        print(f"  (measured: the report over the {at[-1]['kind']} lake of {TARGET:,} rows)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, nargs="+", default=[1_000_000], help="one or more case counts to run")
    ap.add_argument("--replicate", type=int, nargs="*", default=[],
                    help="also measure the report over the largest run replicated K times (hard links), per K")
    ap.add_argument("--reuse", type=Path, default=None,
                    help="lake of an earlier run of this script (its run 'bench'): measure its report instead of "
                         "running cases, and replicate it")
    ap.add_argument("--lake", type=Path, default=None, help="parent folder of the lakes (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary lakes")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each query; the best is printed")
    ap.add_argument("--json", type=Path, default=None, help="also write the measurements to this JSON file")
    ap.add_argument("--with-results", type=Path, action="append", default=[],
                    help="JSON file of an earlier run of this script (--json) whose measurements join the "
                         "extrapolation (e.g. 10^5 measured before 10^6)")
    args = ap.parse_args()
    if any(n < 1 for n in args.cases + args.replicate) or args.repeat < 1:
        ap.error("--cases, --replicate and --repeat must be positive")
    parent = args.lake or Path(tempfile.mkdtemp(prefix="bench-report-"))
    print(f"cores {os.cpu_count()}, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} at start; "
          f"paper preset, seed 1, in-process executor (1 worker); lakes under {parent}")
    earlier = [r for f in args.with_results for r in json.loads(f.read_text())]
    for r in earlier:
        print_one(r)
    results = []
    try:
        largest = None
        if args.reuse is not None:
            from dualsight.warehouse.lake import Lake

            n = Lake(args.reuse).read_manifest(RUN)["n_cases"]
            r = {"cases": n, "kind": f"reused {args.reuse}"}
            r.update(measure_report(args.reuse, args.repeat))
            results.append(r)
            print_one(r)
            largest = (n, args.reuse)
        for n in (args.cases if args.reuse is None else []):
            lake_dir = parent / f"cases-{n}"
            if lake_dir.exists():
                print(f"{lake_dir} exists; give another --lake", file=sys.stderr)
                return 2
            r = run_cases(n, lake_dir)
            r.update(measure_report(lake_dir, args.repeat))
            results.append(r)
            print_one(r)
            if largest is None or n >= largest[0]:
                largest = (n, lake_dir)
        for k in args.replicate:
            dst = parent / f"replicated-{k}"
            r = replicate(largest[1], dst, k)
            r.update(measure_report(dst, args.repeat))
            results.append(r)
            print_one(r)
            if args.lake is None and not args.keep:
                shutil.rmtree(dst, ignore_errors=True)
        extrapolate(results + earlier)
        print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} at the end")
        if args.json:
            args.json.write_text(json.dumps(results, indent=1))
    finally:
        if args.lake is None and not args.keep:
            shutil.rmtree(parent, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
