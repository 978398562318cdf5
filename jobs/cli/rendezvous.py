"""``dualsight rendezvous``: relative navigation over approaches to a target (issue 23, point 5).

    dualsight rendezvous run    [--preset far|close] [--config FILE.toml] [--cases N] [--seed S] [--run ID]
                                [--lake DIR] [--workers W]      run (or resume) a campaign into the lake
    dualsight rendezvous report [--run ID] [--lake DIR] [--json] [--html PAGE]
                                                                its report (default: the latest rendezvous run)
    dualsight rendezvous replay --run ID --case I [--lake DIR] [-o FILE.rrd]
                                                                re-render one approach, verify it, record it

The parser stays light (no numpy): the job kind, the report and the replay are imported when the command runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dualsight.jobs.cli.args import (add_lake_arg, add_run_args, latest_run, open_lake, positive_int, print_run_end,
                                     run_id_arg)


def register(sub) -> None:
    """Add the ``dualsight rendezvous`` command group to the top-level sub-commands ``sub``."""
    g = sub.add_parser("rendezvous", help="relative navigation over approaches to a target: star camera bearings, "
                                          "blobber ranges, EKF; campaigns, reports, replay")
    rsub = g.add_subparsers(dest="action", metavar="ACTION")
    p = rsub.add_parser("run", help="run (or resume) a rendezvous campaign into the lake (presets: far, close)")
    add_run_args(p, default_preset="far", presets=("far", "close"))
    p.set_defaults(func=cmd_run)
    p = rsub.add_parser("report", help="NEES against its chi-square bounds, range and velocity errors, position "
                                       "error one orbit after the burn, bearing error, availability")
    add_lake_arg(p)
    p.add_argument("--run", type=run_id_arg, default=None, help="run id (default: the latest rendezvous run)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--html", type=Path, default=None, help="also write the run's HTML page (its folder must exist)")
    p.set_defaults(func=cmd_report)
    p = rsub.add_parser("replay", help="re-render one approach bit-identically, verify its rows, record it (.rrd)")
    add_lake_arg(p)
    p.add_argument("--run", type=run_id_arg, required=True)
    p.add_argument("--case", type=positive_int(0, 10**9), required=True)
    p.add_argument("-o", "--output", type=Path, default=None, help="recording file (default: <run>-case<I>.rrd)")
    p.set_defaults(func=cmd_replay)
    g.set_defaults(func=lambda a: (g.print_help(), 2)[1])


def cmd_run(args: argparse.Namespace) -> int:
    from dualsight.jobs.kinds import rendezvous

    plan = rendezvous.plan_run(args.preset, args.config, seed=args.seed, cases=args.cases, run_id=args.run)
    lake = open_lake(args)
    m = rendezvous.start_run(plan, lake, workers=args.workers, scheduler=args.scheduler, shard_size=args.shard_size,
                             progress=not args.no_progress)
    print_run_end(m, plan.run_id, plan.n_cases, lake, "dualsight rendezvous report", unit="approaches",
                  rate_digits=2)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from dualsight.jobs.reports import rendezvous as report

    lake = open_lake(args)
    run = args.run or latest_run(lake, ["rendezvous"])
    rep = report.build(lake, run)
    print(json.dumps(rep["json"], indent=1) if args.json else report.text(rep))
    if args.html is not None:
        from dualsight.jobs.reports.html import write_html

        out = write_html(lake, run, args.html)
        print(f"report: {out} ({out.stat().st_size / 2**20:.1f} MiB, self-contained)", file=sys.stderr)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from dualsight.jobs.replay.run import replay_run

    outs, _ = replay_run(open_lake(args), args.run, case=args.case, where=None, limit=1, output=args.output)
    print(f"recording: {outs[0]}")
    print(f"case {args.case} verified and recorded; open with: rerun {outs[0]}", file=sys.stderr)
    return 0
