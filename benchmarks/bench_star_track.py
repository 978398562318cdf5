"""A star-tracking campaign against the issue's targets (issue 22, point 6), measured in one run.

    python benchmarks/bench_star_track.py [--cases 1000] [--frames 50] [--fps 10] [--rate-max 1] [--workers 2]
        [--lake DIR] [--run ID] [--seed 22] [--shard-size N]

The ``realistic`` preset (the paper's star camera, 1024 x 768, 17 mm, catalog to V 5.5, with the realistic CMOS
sensor: defocused PSF, shot/read/dark noise, hot pixels, the local detector), sequences of ``--frames`` frames at
``--fps`` with constant body rates uniform in [0, ``--rate-max``] deg/s about random axes, each frame smeared by its
rate over the 0.1 s exposure, one blinded and one dropped frame per sequence, and lost-in-space run beside tracking
on every frame (``shadow_lost_in_space``) so that both are timed on the same frames in the same run.  Prints the
campaign report (``dualsight star track --report``) and the per-frame medians of tracking (the tracker's whole time
on a tracked frame: propagate, predict, match, solve, verify, rates) and of lost-in-space on the same frames.

The run resumes: run the same command again after an interruption (the lake keeps completed shards).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")

from dualsight.jobs.kinds import star_track  # noqa: E402
from dualsight.jobs.reports import star_track as report  # noqa: E402
from dualsight.warehouse.lake import Lake  # noqa: E402
from dualsight.warehouse.query import run_sql  # noqa: E402

SPEED_SQL = """
SELECT count(*) AS frames,
       quantile_cont(t_nav_ns, 0.5) / 1e6 AS tracking_median_ms, avg(t_nav_ns) / 1e6 AS tracking_mean_ms,
       quantile_cont(t_shadow_lis_ns, 0.5) / 1e6 AS lis_median_ms, avg(t_shadow_lis_ns) / 1e6 AS lis_mean_ms,
       quantile_cont(t_predict_ns + t_track_ns, 0.5) / 1e6 AS predict_match_solve_median_ms
FROM star_frames WHERE run = '{run}' AND mode = 'tracking' AND t_shadow_lis_ns IS NOT NULL
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--rate-max", type=float, default=1.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=22)
    ap.add_argument("--lake", type=Path, default=None, help="lake folder (default: a new temporary folder)")
    ap.add_argument("--run", default=None)
    ap.add_argument("--shard-size", type=int, default=None, help="sequences per shard (default: the engine's)")
    ap.add_argument("--max-sigma-arcsec", type=float, default=25.0,
                    help="tracking.max_sigma_rad in arcsec: withhold attitudes whose stated 1-sigma exceeds it "
                         "(examples/star/track.toml's 25; 36000 = off)")
    args = ap.parse_args()
    lake = Lake(args.lake or Path(tempfile.mkdtemp(prefix="bench_star_track_")))
    config = {"sequence": {"frames": args.frames, "fps": args.fps, "exposure_s": min(0.1, 1.0 / args.fps),
                           "motion": "constant", "rate_max_deg_s": args.rate_max, "blinded": 1, "dropped": 1,
                           "shadow_lost_in_space": True},
              "tracking": {"max_sigma_arcsec": args.max_sigma_arcsec}}
    plan = star_track.plan_run("realistic", config, seed=args.seed, cases=args.cases, run_id=args.run)
    t0 = time.perf_counter()
    m = star_track.start_run(plan, lake, workers=args.workers, shard_size=args.shard_size)
    wall = time.perf_counter() - t0
    print(f"conditions: {args.cases} sequences x {args.frames} frames at {args.fps:g} fps, realistic preset (paper "
          f"camera, realistic sensor, local detector), constant rates uniform in [0, {args.rate_max:g}] deg/s, "
          f"smear on, 1 blinded + 1 dropped frame per sequence, attitudes withheld above "
          f"{args.max_sigma_arcsec:g} arcsec stated 1-sigma, {args.workers} workers on "
          f"{len(os.sched_getaffinity(0))} cores, load average {os.getloadavg()[0]:.1f}; run {plan.run_id} "
          f"({m['status']}) in {lake.root}, {wall:.0f} s wall")
    print(report.text(report.build(lake, plan.run_id)))
    cols, rows = run_sql(lake, SPEED_SQL.format(run=plan.run_id))
    s = dict(zip(cols, rows[0]))
    if s["frames"]:
        print(f"\nper tracked frame ({s['frames']:,} frames, same frames for both): tracking median "
              f"{s['tracking_median_ms']:.3f} ms (mean {s['tracking_mean_ms']:.3f}; predict+match+solve+verify "
              f"median {s['predict_match_solve_median_ms']:.3f}), lost-in-space median {s['lis_median_ms']:.3f} ms "
              f"(mean {s['lis_mean_ms']:.3f}): {s['lis_median_ms'] / s['tracking_median_ms']:.1f}x (medians)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
