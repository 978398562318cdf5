"""The ``dualsight`` command line.

    dualsight star run     [--preset paper] [--config FILE.toml] [--cases N] [--seed S] [--lake DIR] [--run ID]
    dualsight star report  [--lake DIR] [--run ID] [--json] [--plot FILE.png]
    dualsight star replay  --run ID --case I [--lake DIR] [-o FILE.rrd]
    dualsight prox ...     (see ``dualsight prox --help``)
    dualsight hil ...      (see ``dualsight hil --help``)
    dualsight calibrate FOLDER --board 9x6 --square 0.025 [-o camera.toml]
    dualsight sql "SELECT ..." [--lake DIR] [--json | --csv]
    dualsight runs [--lake DIR]

Bad input prints one line naming the file, field and allowed range, exits with status 2 and leaves the
lake untouched.  The lake defaults to ``$DUALSIGHT_LAKE`` or ``./lake``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dualsight.errors import InputError


def _lake_arg(p: argparse.ArgumentParser):
    from dualsight.warehouse.lake import default_lake

    p.add_argument("--lake", type=Path, default=None,
                   help=f"lake folder (default: $DUALSIGHT_LAKE or ./lake, now {default_lake()})")


def _lake(args):
    from dualsight.warehouse.lake import Lake, default_lake

    return Lake(args.lake if args.lake is not None else default_lake())


def add_run_args(p: argparse.ArgumentParser, *, cases: bool = True):
    """Options shared by every Monte Carlo command."""
    p.add_argument("--preset", default=None, help="named preset (default: paper)")
    p.add_argument("--config", type=Path, default=None, help="TOML file overriding the preset")
    if cases:
        p.add_argument("--cases", type=int, default=None, help="number of cases (default: the preset's)")
    p.add_argument("--seed", type=int, default=None, help="run seed: case i draws from default_rng([seed, i])")
    _lake_arg(p)
    p.add_argument("--run", default=None, help="run id (default: <job>-<seed>-<cases>); an existing id resumes")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: one per core)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786) to run shards on "
                   "a cluster; the lake must be on storage every worker can write")
    p.add_argument("--shard-size", type=int, default=None, help="cases per shard file (default: automatic)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    from dualsight import __version__

    parser = argparse.ArgumentParser(prog="dualsight", description="End-to-end test bench for a dual-use "
                                     "(star tracker + proximity navigation) small-satellite camera.")
    parser.add_argument("--version", action="version", version=f"dualsight {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    star = sub.add_parser("star", help="star tracker: Monte Carlo runs, reports, replay")
    ssub = star.add_subparsers(dest="action", metavar="ACTION")
    p = ssub.add_parser("run", help="run (or resume) a star-tracker Monte Carlo into the lake")
    add_run_args(p)
    p.set_defaults(func=cmd_star_run)
    p = ssub.add_parser("report", help="reliability summary, Table 5, error vs stars observed")
    _lake_arg(p)
    p.add_argument("--run", default=None, help="run id (default: the latest star run)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", type=Path, default=None, help="write Figures 9-10 (error vs stars observed) as PNG")
    p.set_defaults(func=cmd_star_report)
    p = ssub.add_parser("replay", help="re-render one case bit-identically and record it for rerun (.rrd)")
    _lake_arg(p)
    p.add_argument("--run", required=True)
    p.add_argument("--case", type=int, required=True)
    p.add_argument("-o", "--output", type=Path, default=None, help="recording file (default: <run>-case<I>.rrd)")
    p.set_defaults(func=cmd_star_replay)
    star.set_defaults(func=lambda a: _help(star))

    for register in _optional_registrations():
        register(sub)

    p = sub.add_parser("sql", help="DuckDB SQL over the lake's views (one per dataset)")
    p.add_argument("query", help="SQL text, e.g. \"SELECT status, count(*) FROM star_cases GROUP BY ALL\"")
    _lake_arg(p)
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="rows as JSON objects")
    fmt.add_argument("--csv", action="store_true", help="CSV")
    p.set_defaults(func=cmd_sql)

    p = sub.add_parser("runs", help="list the runs in the lake")
    _lake_arg(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_runs)
    return parser


def _optional_registrations():
    """Command groups of the other jobs (each module adds its own sub-commands)."""
    from dualsight.jobs import calibrate_cli, cli_hil, cli_prox

    return [cli_prox.register, cli_hil.register, calibrate_cli.register_calibrate]


def _help(p):
    p.print_help()
    return 0


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except InputError as e:
        print(f"dualsight: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("dualsight: interrupted; completed shards are kept, run the same command again to resume",
              file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


# ---------------------------------------------------------------------------------------------- star
def cmd_star_run(args) -> int:
    from dualsight.jobs import star
    from dualsight.jobs.runner import run_job

    spec_dict, n_cases = star.resolve_spec(args.preset, args.config, seed=args.seed, cases=args.cases)
    run_id = args.run or f"star-{spec_dict['seed']}-{n_cases}"
    lake = _lake(args)
    info = star.catalog_info(spec_dict)
    print(f"catalog: {info['stars']} stars to V {info['mag_limit']}, {info['pairs']:,} pairs closer than "
          f"{info['pair_max_angle_deg']:.2f} deg ({info['pair_catalog_bytes'] / 2**20:.2f} MiB in memory)",
          file=sys.stderr)
    manifest = run_job("star", spec_dict, n_cases=n_cases, lake=lake, run_id=run_id, workers=args.workers,
                       scheduler=args.scheduler, shard_size=args.shard_size, progress=not args.no_progress,
                       label=f"star {run_id}", extra={"catalog": info})
    ex = manifest["executions"][-1]
    el = ex.get("elapsed_s")
    rate = f", {ex.get('cases_run', n_cases) / el:.0f} cases/s" if el else ""
    print(f"run {run_id}: {manifest['status']}, {n_cases} cases in {lake.root}{rate}", file=sys.stderr)
    print(f"report: dualsight star report --lake {lake.root} --run {run_id}", file=sys.stderr)
    return 0


def _latest_run(lake, kinds) -> str:
    runs = [m for m in lake.list_manifests() if m.get("kind") in kinds]
    if not runs:
        raise InputError(f"no {'/'.join(kinds)} run in {lake.root}; run one first", source="--run")
    return max(runs, key=lambda m: m.get("created_unix", 0))["run_id"]


def cmd_star_report(args) -> int:
    from dualsight.jobs import star_report

    lake = _lake(args)
    run_id = args.run or _latest_run(lake, ["star"])
    rep = star_report.build(lake, run_id)
    if args.plot:
        star_report.plot(rep, args.plot)
    if args.json:
        print(json.dumps(rep["json"], indent=1))
    else:
        print(star_report.text(rep))
        if args.plot:
            print(f"\nfigure: {args.plot}")
    return 0


def cmd_star_replay(args) -> int:
    from dualsight.jobs import replay

    out = replay.replay_star_case(_lake(args), args.run, args.case, args.output)
    print(f"recording: {out}  (open with: rerun {out})")
    return 0


# ---------------------------------------------------------------------------------------------- lake
def cmd_sql(args) -> int:
    from dualsight.warehouse.query import format_table, run_sql

    cols, rows = run_sql(_lake(args), args.query)
    if args.json:
        print(json.dumps([dict(zip(cols, r)) for r in rows], default=str, indent=1))
    elif args.csv:
        import csv

        w = csv.writer(sys.stdout)
        w.writerow(cols)
        w.writerows(rows)
    elif cols:
        print(format_table(cols, rows))
    return 0


def cmd_runs(args) -> int:
    from dualsight.warehouse.query import format_table

    ms = _lake(args).list_manifests()
    if args.json:
        print(json.dumps(ms, indent=1))
        return 0
    rows = [(m["run_id"], m.get("kind"), m.get("n_cases"), f"{len(m.get('shards_done', []))}/{m.get('n_shards')}",
             m.get("status"), m.get("seed")) for m in ms]
    print(format_table(["run", "kind", "cases", "shards", "status", "seed"], rows) if rows else "no runs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
