"""``dualsight star track``: star-tracking campaigns over image sequences (issue 22), and their report.

    dualsight star track [--preset paper] [--config FILE.toml] [--cases N] [--seed S] [--run ID] [--lake DIR]
                         [--workers W]                     run (or resume) a campaign into the lake
    dualsight star track --report [--run ID] [--lake DIR] [--json]
                                                           its report (default: the latest star_track run)

The parser stays light (no numpy): the job kind and the report are imported when the command runs.
"""

from __future__ import annotations

import argparse
import json

from dualsight.jobs.cli.args import add_run_args, latest_run, open_lake, print_run_end


def register(ssub) -> None:
    """Add ``track`` to the ``dualsight star`` sub-commands ``ssub``."""
    p = ssub.add_parser("track", help="star tracking over image sequences: run a campaign (or, with --report, "
                                      "report one): availability, re-acquisition, false locks, rate, latency")
    add_run_args(p)
    p.add_argument("--report", action="store_true", help="print the report of --run (default: the latest "
                                                         "star_track run) instead of running")
    p.add_argument("--json", action="store_true", help="with --report: one JSON object")
    p.set_defaults(func=cmd_star_track)


def cmd_star_track(args: argparse.Namespace) -> int:
    if args.report:
        from dualsight.jobs.reports import star_track as report

        lake = open_lake(args)
        rep = report.build(lake, args.run or latest_run(lake, ["star_track"]))
        print(json.dumps(rep["json"], indent=1) if args.json else report.text(rep))
        return 0
    from dualsight.jobs.kinds import star_track

    plan = star_track.plan_run(args.preset, args.config, seed=args.seed, cases=args.cases, run_id=args.run)
    lake = open_lake(args)
    m = star_track.start_run(plan, lake, workers=args.workers, scheduler=args.scheduler, shard_size=args.shard_size,
                             progress=not args.no_progress)
    print_run_end(m, plan.run_id, plan.n_cases, lake, "dualsight star track --report", unit="sequences",
                  rate_digits=2)
    return 0
