"""The ``dualsight`` command line.

    dualsight star run     [--preset paper] [--config FILE.toml] [--cases N] [--seed S] [--lake DIR] [--run ID]
                           [--detections auto|on|off]
    dualsight star report  [--lake DIR] [--run ID] [--json] [--plot FILE.png]
    dualsight star replay  --run ID --case I [--lake DIR] [-o FILE.rrd]
    dualsight prox ...     (see ``dualsight prox --help``)
    dualsight hil ...      (see ``dualsight hil --help``)
    dualsight calibrate FOLDER --board 9x6 --square 0.025 [-o camera.toml]
    dualsight sql "SELECT ..." [--lake DIR] [--json | --csv] [--limit N] [--timeout S] [--memory-limit SIZE]
                                                                   read-only: SELECT / EXPLAIN only
    dualsight runs [--lake DIR] [--json]
    dualsight lake check [--lake DIR] [--repair] [--json]

Bad input prints one line naming the file, field and allowed range, exits with status 2 and leaves the
lake untouched.  The lake defaults to ``$DUALSIGHT_LAKE`` or ``./lake``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import sys
from pathlib import Path

from dualsight.errors import InputError
from dualsight.jobs.cli import cache as cli_cache
from dualsight.jobs.cli import calibrate as cli_calibrate
from dualsight.jobs.cli import hil_star as cli_hil_star
from dualsight.jobs.cli import nightly as cli_nightly
from dualsight.jobs.cli import peer as cli_peer
from dualsight.jobs.cli import prox as cli_prox
from dualsight.jobs.cli import rendezvous as cli_rendezvous
from dualsight.jobs.cli import star_track as cli_star_track
from dualsight.jobs.cli.args import (Parser, add_lake_arg, add_run_args, latest_run, open_lake, positive_int,
                                     print_run_end, run_id_arg)
from dualsight.jobs.engine.errors import Interrupted
from dualsight.jobs.kinds import star_output
from dualsight.version import __version__
from dualsight.warehouse.paths import os_error_text

# The one table from commands to job kinds (jobs/engine/runner.py JOB_KINDS maps kinds to modules).
COMMAND_KINDS = {
    ("star", "run"): "star",
    ("star", "track"): "star_track",
    ("prox", "sweep"): "prox_sweep",
    ("prox", "trajectory"): "prox_trajectory",
    ("hil", "star"): "hil_star",
    ("hil", "prox"): "hil_prox",
    ("calibrate",): "calibrate",
    ("selftest", "run"): "selftest",
    ("rendezvous", "run"): "rendezvous",
}


def build_parser() -> argparse.ArgumentParser:
    """The ``dualsight`` parser: every command and command group, each with its ``func``."""
    parser = Parser(prog="dualsight", description="End-to-end test bench for a dual-use "
                                     "(star tracker + proximity navigation) small-satellite camera.")
    parser.add_argument("--version", action="version", version=f"dualsight {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    star = sub.add_parser("star", help="star tracker: Monte Carlo runs, reports, replay")
    ssub = star.add_subparsers(dest="action", metavar="ACTION")
    p = ssub.add_parser("run", help="run (or resume) a star-tracker Monte Carlo into the lake")
    add_run_args(p)
    p.add_argument("--detections", choices=("auto", "on", "off"), default=None,
                   help="keep the per-star rows (star_detections): auto (the spec's [output], default: up to "
                        "100,000 cases), on or off; part of the run's identity")
    p.set_defaults(func=cmd_star_run)
    p = ssub.add_parser("report", help="reliability summary, Table 5, error vs stars observed")
    add_lake_arg(p)
    p.add_argument("--run", type=run_id_arg, default=None, help="run id (default: the latest star run)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", type=Path, default=None, help="write Figures 9-10 (error vs stars observed) as PNG")
    p.set_defaults(func=cmd_star_report)
    p = ssub.add_parser("replay", help="re-render one case bit-identically and record it for rerun (.rrd)")
    add_lake_arg(p)
    p.add_argument("--run", type=run_id_arg, required=True)
    p.add_argument("--case", type=positive_int(0, 10**9), required=True)
    p.add_argument("-o", "--output", type=Path, default=None, help="recording file (default: <run>-case<I>.rrd)")
    p.set_defaults(func=cmd_star_replay)
    cli_star_track.register(ssub)
    star.set_defaults(func=lambda a: _help(star))

    for register in (cli_prox.register, cli_rendezvous.register, cli_hil_star.register,
                     cli_calibrate.register_calibrate, cli_nightly.register,
                     cli_peer.register, cli_cache.register):    # the command groups of the other modules of jobs/cli
        register(sub)

    p = sub.add_parser("sql", help="DuckDB SQL over the lake's views (one per dataset)")
    p.add_argument("query", help="SQL text, e.g. \"SELECT status, count(*) FROM star_cases GROUP BY ALL\"")
    add_lake_arg(p)
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="rows as JSON objects")
    fmt.add_argument("--csv", action="store_true", help="CSV, every row (streamed) and whole cells")
    p.add_argument("--limit", type=positive_int(0, 10**12), default=None, metavar="N",
                   help="rows to print (default 1000; with --csv all); 0 for all")
    p.add_argument("--timeout", type=_nonneg_seconds, default=300.0, metavar="SECONDS",
                   help="stop the query after this long (default 300); 0 for no limit")
    p.add_argument("--memory-limit", default="1GiB", metavar="SIZE",
                   help="memory of the query and of this process beyond what it holds at start, e.g. 4GB or 25%% "
                        "of the RAM (default 1GiB); nothing spills to disk")
    p.set_defaults(func=cmd_sql)

    p = sub.add_parser("replay", help="replay cases of any run, chosen by --case or an SQL predicate, into rerun "
                                      "recordings; each case is verified against its row first")
    add_lake_arg(p)
    p.add_argument("--run", type=run_id_arg, required=True)
    sel = p.add_mutually_exclusive_group(required=True)
    sel.add_argument("--case", type=positive_int(0, 10**9), default=None)
    sel.add_argument("--where", default=None, help="SQL predicate over the run's primary dataset, e.g. "
                                                   "\"status <> 'success'\"")
    p.add_argument("--limit", type=positive_int(1, 1000), default=20, help="at most this many cases (default 20)")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="a .rrd file (every selected case in one recording, on the 'frame' time line: a "
                        "trajectory plays as a film) or a folder (one <run>-case<N>.rrd per case)")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("report", help="one self-contained HTML page for any run: tables, the reference's "
                                      "figures, worst cases with thumbnails and replay commands, spec, timings")
    add_lake_arg(p)
    p.add_argument("--run", type=run_id_arg, required=True)
    p.add_argument("--html", type=Path, required=True, help="page to write (its folder must exist)")
    p.set_defaults(func=cmd_report_html)

    p = sub.add_parser("runs", help="list the runs in the lake (damaged ones are named)")
    add_lake_arg(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_runs)

    p = sub.add_parser("selftest", help="engine self-test job (tiny, deterministic; for fault drills and "
                                        "benchmarks)")
    tsub = p.add_subparsers(dest="action", metavar="ACTION")
    p = tsub.add_parser("run", help="run the self-test job into the lake")
    add_run_args(p)
    p.add_argument("--sleep-ms", type=float, default=None, help="busy time per case, ms (default 0)")
    p.set_defaults(func=cmd_selftest_run)

    lake_p = sub.add_parser("lake", help="lake maintenance")
    lsub = lake_p.add_subparsers(dest="lake_action", metavar="ACTION")
    p = lsub.add_parser("check", help="verify every run (manifest, shard metadata, row counts, duplicate cases); "
                                      "with --repair recompute damaged or missing shards")
    add_lake_arg(p)
    p.add_argument("--repair", action="store_true", help="recompute damaged or missing shards, rebuild damaged "
                                                         "manifests from their spec copy")
    p.add_argument("--json", action="store_true")
    p.add_argument("--workers", type=positive_int(1, 512), default=None, help="workers for --repair")
    p.set_defaults(func=cmd_lake_check)
    lake_p.set_defaults(func=lambda a: _help(lake_p))
    return parser


def _help(p):
    p.print_help()
    return 0


def _on_sigterm(signum, frame):
    raise Interrupted(f"signal {signum}")


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:                  # --help, --version, or a one-line usage error (status 2)
        return int(e.code or 0)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return int(args.func(args) or 0)
    except InputError as e:
        print(f"dualsight: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        sig = "SIGTERM" if str(e).startswith("signal") else "Ctrl-C"
        print(f"dualsight: interrupted ({sig}); completed shards are kept, run the same command again to resume",
              file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except OSError as e:
        print(f"dualsight: error: {os_error_text(e)}", file=sys.stderr)
        return 2
    except MemoryError:
        print("dualsight: error: out of memory; lower the batch size, the case count per shard or the catalog "
              "depth", file=sys.stderr)
        return 2
    except Exception as e:                                    # a bug: one line, the traceback on request
        if os.environ.get("DUALSIGHT_DEBUG"):
            raise
        print(f"dualsight: internal error: {type(e).__name__}: {_one_line(e)} (set DUALSIGHT_DEBUG=1 for the "
              "traceback)", file=sys.stderr)
        return 3
    finally:
        signal.signal(signal.SIGTERM, previous)


def _one_line(e: Exception) -> str:
    return " ".join(str(e).split())


# ---------------------------------------------------------------------------------------------- star
def cmd_star_run(args) -> int:
    from dualsight.jobs.kinds import star

    # plan_run and start_run are what dualsight.run("star", ...) calls: same spec, identity, run id and rows
    plan = star.plan_run(args.preset, args.config, seed=args.seed, cases=args.cases, run_id=args.run,
                         detections=args.detections)
    run_id, n_cases = plan.run_id, plan.n_cases
    lake = open_lake(args)
    info = plan.catalog
    print(f"catalog: {info['stars']} stars to V {info['mag_limit']}, {info['pairs']:,} pairs closer than "
          f"{info['pair_max_angle_deg']:.2f} deg ({info['pair_catalog_bytes'] / 2**20:.2f} MiB, memory-mapped)",
          file=sys.stderr)
    manifest = star.start_run(plan, lake, workers=args.workers, scheduler=args.scheduler,
                              shard_size=args.shard_size, progress=not args.no_progress)
    print_run_end(manifest, run_id, n_cases, lake, "dualsight star report")
    if not star_output.kept(manifest):
        print(star_output.not_kept_note(manifest, "per-star detail"), file=sys.stderr)
    return 0


def cmd_selftest_run(args) -> int:
    from dualsight.jobs.kinds import selftest                     # pyarrow

    # plan_run and start_run are what dualsight.run("selftest", ...) calls
    plan = selftest.plan_run(args.preset, args.config, seed=args.seed, cases=args.cases, sleep_ms=args.sleep_ms,
                             run_id=args.run)
    m = selftest.start_run(plan, open_lake(args), workers=args.workers, scheduler=args.scheduler,
                           shard_size=args.shard_size, progress=not args.no_progress)
    print(f"run {m['run_id']}: {m['status']}, {m['n_cases']} cases", file=sys.stderr)
    return 0


def cmd_star_report(args) -> int:
    from dualsight.jobs.reports import star as star_report

    lake = open_lake(args)
    run_id = args.run or latest_run(lake, ["star"])
    rep = star_report.build(lake, run_id)
    if args.plot:
        from dualsight.viz.star_figures import error_vs_observed_figure   # matplotlib

        error_vs_observed_figure(rep["json"], args.plot)
    if args.json:
        print(json.dumps(rep["json"], indent=1))
    else:
        print(star_report.text(rep))
        if args.plot:
            print(f"\nfigure: {args.plot}")
    return 0


def cmd_star_replay(args) -> int:
    from dualsight.jobs.replay import cases as replay

    out = replay.replay_star_case(open_lake(args), args.run, args.case, args.output)
    print(f"recording: {out}  (open with: rerun {out})")
    return 0


# ---------------------------------------------------------------------------------------------- lake
def cmd_sql(args) -> int:
    """Read-only SQL with a time limit, a memory limit and a capped printout; Ctrl-C and SIGTERM stop the
    query (status 130 / 143, one line)."""
    from dualsight.warehouse import query

    try:
        limits = query.SqlLimits(args.timeout, args.memory_limit, timeout_name="--timeout SECONDS",
                                 memory_name="--memory-limit")
        if args.csv:
            with query.process_memory_cap(limits.memory_limit):
                return _sql_csv(query, args, limits)
        row_limit = query.DEFAULT_ROW_LIMIT if args.limit is None else (args.limit or None)
        with query.process_memory_cap(limits.memory_limit):
            cols, rows, total, cut = query.sql_rows(open_lake(args), args.query, limits, row_limit=row_limit)
        if args.json:
            print(json.dumps([dict(zip(cols, r)) for r in rows], default=str, indent=1))
        elif cols:
            print(query.format_table(cols, rows))
        if total is not None and total > len(rows):
            _sql_note(f"(showing {len(rows):,} of {total:,} rows; --limit / --csv for all)")
        if cut:
            _sql_note(f"(cells longer than {query.MAX_CELL_CHARS:,} characters are cut; --csv for whole cells)")
        return 0
    except KeyboardInterrupt as e:                      # Ctrl-C, or SIGTERM through main's handler
        sigterm = str(e).startswith("signal")
        print("dualsight: interrupted", file=sys.stderr)
        return 143 if sigterm else 130


def _sql_csv(query, args, limits) -> int:
    w = csv.writer(sys.stdout)
    n = query.sql_csv(open_lake(args), args.query, limits, w.writerow, w.writerows, row_limit=args.limit or None)
    if args.limit and n > args.limit:
        _sql_note(f"(showing the first {args.limit:,} rows; without --limit all)")
    return 0


def _sql_note(text: str) -> None:
    sys.stdout.flush()
    print(text, file=sys.stderr)


def _nonneg_seconds(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        x = -1.0
    if not 0 <= x < 1e9:
        raise argparse.ArgumentTypeError(f"{text!r} is not a time in seconds >= 0 (0: no limit)")
    return x


def cmd_report_html(args) -> int:
    from dualsight.jobs.reports.html import write_html

    out = write_html(open_lake(args), args.run, args.html)
    print(f"report: {out} ({out.stat().st_size / 2**20:.1f} MiB, self-contained)", file=sys.stderr)
    return 0


def cmd_replay(args) -> int:
    from dualsight.jobs.replay.run import replay_run

    outs, cases = replay_run(open_lake(args), args.run, case=args.case, where=args.where, limit=args.limit,
                             output=args.output)
    for o in outs:
        print(f"recording: {o}")
    what = f"{len(cases)} case" + ("s" if len(cases) != 1 else "")
    where = f"in {len(outs)} file" + ("s" if len(outs) != 1 else "")
    print(f"{what} verified and recorded {where}; open with: rerun {outs[0]}", file=sys.stderr)
    return 0


def cmd_runs(args) -> int:
    from dualsight.warehouse.lake import run_records
    from dualsight.warehouse.query import format_table

    lake = open_lake(args)
    rows, docs = [], []
    for r in run_records(lake):                        # what dualsight.Lake.runs() returns
        if r.damaged:
            rows.append((r.run_id, "?", None, "?", "DAMAGED", None, str(r.problems[0])[:60]))
            docs.append({"run_id": r.run_id, "status": "damaged", "problem": r.problems[0]})
            continue
        rows.append((r.run_id, r.kind, r.n_cases, r.shards, r.status, r.seed, r.spec_hash))
        docs.append(dict(r.manifest, problems=list(r.problems)))
    if args.json:
        print(json.dumps(docs, indent=1))
        return 0
    print(format_table(["run", "kind", "cases", "shards", "status", "seed", "spec hash"], rows) if rows
          else f"no runs in {lake.root}")
    lean = [d["run_id"] for d in docs if d.get("kind") == "star" and not star_output.kept(d)]
    if lean:
        print(f"star runs without per-star rows ({star_output.DATASET} not kept): {', '.join(lean)}")
    return 0


def cmd_lake_check(args) -> int:
    from dualsight.jobs.engine.lakecheck import check_lake, report_text

    rows = check_lake(open_lake(args), repair=args.repair, workers=args.workers)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        print(report_text(rows))
    return 0 if all(r["verdict"] in ("ok", "repaired") for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
