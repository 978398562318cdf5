"""``dualsight prox ...``: proximity sweep and trajectory runs, their reports, replay and video."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dualsight.errors import InputError
from dualsight.jobs.cli.args import add_lake_arg, add_run_args, latest_run, open_lake


def register(sub):
    prox = sub.add_parser("prox", help="proximity operations: range sweeps, trajectories, reports, replay")
    psub = prox.add_subparsers(dest="action", metavar="ACTION")

    p = psub.add_parser("sweep", help="ranges x random orientations Monte Carlo (reference Table 3)")
    add_run_args(p, cases=False)
    p.add_argument("--ranges", type=float, nargs="+", default=None, metavar="M",
                   help="true ranges in m (default: 11 log-spaced 1-100 m)")
    p.add_argument("--orientations", type=int, default=None, help="random orientations per range (paper: 9)")
    p.add_argument("--mode", choices=["paper", "accurate"], default=None,
                   help="renderer: paper (fixed surface resolution) or accurate (exact coverage)")
    p.add_argument("--satellite", type=Path, default=None, help="satellite TOML (default: the 3U CubeSat)")
    p.set_defaults(func=cmd_sweep, job="sweep")

    p = psub.add_parser("trajectory", help="the reference's trajectory (Table 2 motion), frame by frame")
    add_run_args(p, cases=False)
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: the satellite file's)")
    p.add_argument("--mode", choices=["paper", "accurate"], default=None)
    p.add_argument("--satellite", type=Path, default=None, help="satellite TOML (default: the 3U CubeSat)")
    p.add_argument("--video", type=Path, default=None, help="also write the frames as a video (.mp4 or .avi)")
    p.add_argument("--fps", type=float, default=10.0, help="video frame rate")
    p.set_defaults(func=cmd_trajectory, job="trajectory")

    p = psub.add_parser("report", help="Table 3 per true range (sweep) or per-axis errors (trajectory)")
    add_lake_arg(p)
    p.add_argument("--run", default=None, help="run id (default: the latest prox run)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--estimator", choices=["paper", "subpixel"], default=None,
                   help="estimator for the top-level JSON keys (default: paper for paper-mode runs, "
                        "subpixel for accurate-mode runs)")
    p.add_argument("--plot", type=Path, default=None, help="figure (Fig. 7 style for sweeps, Fig. 6 for trajectories)")
    p.set_defaults(func=cmd_report)

    p = psub.add_parser("resolvable", help="nearest and farthest resolvable range of a camera and object size")
    p.add_argument("--camera", type=Path, default=None, help="camera TOML (default: the reference's Table 1 camera)")
    p.add_argument("--size", type=float, default=0.1, help="characteristic object size h (m), default 0.1")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_resolvable)

    p = psub.add_parser("replay", help="re-render one case bit-identically and record it for rerun (.rrd)")
    add_lake_arg(p)
    p.add_argument("--run", required=True)
    p.add_argument("--case", type=int, required=True)
    p.add_argument("-o", "--output", type=Path, default=None)
    p.set_defaults(func=cmd_replay)
    prox.set_defaults(func=lambda a: (prox.print_help(), 0)[1])


def _run(args, job: str, **flags):
    """Plan and run (or resume) ``job`` ("sweep" or "trajectory") from the parsed options; returns the plan."""
    from dualsight.jobs.kinds import prox                                 # Taichi

    # plan_run and start_run are what dualsight.run("prox_sweep" / "prox_trajectory", ...) calls: same spec,
    # identity, run id and rows
    plan = prox.plan_run(args.preset, args.config, job=job, seed=args.seed, run_id=args.run, mode=args.mode,
                         satellite=args.satellite, **flags)
    lake = open_lake(args)
    m = prox.start_run(plan, lake, workers=args.workers, scheduler=args.scheduler, shard_size=args.shard_size,
                       progress=not args.no_progress)
    print(f"run {plan.run_id}: {m['status']}, {plan.n_cases} cases in {lake.root}", file=sys.stderr)
    print(f"report: dualsight prox report --lake {lake.root} --run {plan.run_id}", file=sys.stderr)
    return plan


def cmd_sweep(args) -> int:
    _run(args, "sweep", ranges_m=args.ranges, orientations=args.orientations)
    return 0


def cmd_trajectory(args) -> int:
    plan = _run(args, "trajectory", frames=args.frames)
    if args.video:
        from dualsight.jobs.replay.prox import write_trajectory_video    # pyarrow, OpenCV

        path = write_trajectory_video(plan.resolved, args.video, fps=args.fps)
        print(f"video: {path}", file=sys.stderr)
    return 0


def cmd_report(args) -> int:
    from dualsight.jobs.reports import prox as prox_report                # DuckDB

    lake = open_lake(args)
    run_id = args.run or latest_run(lake, ["prox_sweep", "prox_trajectory"])
    rep = prox_report.build_report(lake, run_id, args.estimator)
    if args.plot:
        from dualsight.viz.prox_figures import plot_sweep, plot_trajectory   # matplotlib

        (plot_sweep if rep["job"] == "sweep" else plot_trajectory)(rep, args.plot)
    if args.json:
        out = {k: v for k, v in rep.items() if k != "table"}
        print(json.dumps(out, indent=1, default=lambda o: None if o != o else float(o)))
    else:
        print(prox_report.report_text(rep))
        if args.plot:
            print(f"\nfigure: {args.plot}")
    return 0


def cmd_replay(args) -> int:
    from dualsight.jobs.replay.prox import replay_prox_case              # pyarrow, DuckDB

    out = replay_prox_case(open_lake(args), args.run, args.case, args.output)
    print(f"recording: {out}  (open with: rerun {out})")
    return 0


def cmd_resolvable(args) -> int:
    from dualsight.jobs.reports import prox as prox_report                # DuckDB

    if not (args.size > 0):
        raise InputError(f"must be > 0 m, got {args.size}", source="--size")
    out, text = prox_report.resolvable_report(args.camera, args.size)
    print(json.dumps(out, indent=1) if args.json else text)
    return 0
