"""A star-tracking campaign against the issue's targets (issue 22, point 6), measured in one run.

    python benchmarks/bench_star_track.py [--config examples/star/track.toml] [--cases 100] [--seed 22]
        [--frames N] [--fps F] [--rate-max W] [--max-sigma-arcsec S] [--workers 2] [--lake DIR] [--run ID]
        [--shard-size N]

The campaign of ``--config`` (default ``examples/star/track.toml``: the ``realistic`` preset, the paper's star
camera with the realistic CMOS sensor and the local detector, catalog to V 6.5, constant rates and slews up to
1 deg/s, 10 fps, each frame smeared by its rate over the 0.1 s exposure, one blinded and one dropped frame per
sequence, the attitude filter and the streak weights), with lost-in-space run on every frame too
(``shadow_lost_in_space``: in a pass of its own after each sequence's tracking loop, ``nav/sequence.py``) so that both
are timed on the same frames in the same run, each in a loop of its own; ``--frames``, ``--fps``,
``--rate-max`` and ``--max-sigma-arcsec`` override the file.  Prints the campaign report (``dualsight star track
--report``: its speed row is tracking's predict + match + solve + verify against lost-in-space's identify + solve +
verify, mean ms) and the per-frame medians of tracking (the whole tracker on a tracked frame, and its predict +
match + solve + verify) and of lost-in-space on the same frames.

The run resumes: run the same command again after an interruption (the lake keeps completed shards).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import tomllib
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
ROOT = Path(__file__).resolve().parents[1]

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
    ap.add_argument("--config", type=Path, default=ROOT / "examples" / "star" / "track.toml")
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--fps", type=float, default=None)
    ap.add_argument("--rate-max", type=float, default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=None, help="run seed (default: the file's)")
    ap.add_argument("--lake", type=Path, default=None, help="lake folder (default: a new temporary folder)")
    ap.add_argument("--run", default=None)
    ap.add_argument("--shard-size", type=int, default=None, help="sequences per shard (default: the engine's)")
    ap.add_argument("--max-sigma-arcsec", type=float, default=None,
                    help="tracking.max_sigma_rad in arcsec: withhold attitudes whose stated 1-sigma exceeds it "
                         "(default: the file's; 36000 = off)")
    args = ap.parse_args()
    lake = Lake(args.lake or Path(tempfile.mkdtemp(prefix="bench_star_track_")))
    config = tomllib.loads(args.config.read_text())
    seq, trk = config.setdefault("sequence", {}), config.setdefault("tracking", {})
    seq["shadow_lost_in_space"] = True
    for key, value in (("frames", args.frames), ("fps", args.fps), ("rate_max_deg_s", args.rate_max)):
        if value is not None:
            seq[key] = value
    if args.fps is not None:
        seq["exposure_s"] = min(float(seq.get("exposure_s", 0.1)), 1.0 / args.fps)
    if args.max_sigma_arcsec is not None:
        trk["max_sigma_arcsec"] = args.max_sigma_arcsec
    plan = star_track.plan_run(None, config, seed=args.seed, cases=args.cases, run_id=args.run)
    t0 = time.perf_counter()
    m = star_track.start_run(plan, lake, workers=args.workers, shard_size=args.shard_size)
    wall = time.perf_counter() - t0
    print(f"conditions: {args.config} with lost-in-space on every frame, {args.cases} sequences, overrides "
          f"frames={args.frames} fps={args.fps} rate_max={args.rate_max} max_sigma_arcsec={args.max_sigma_arcsec} "
          f"(None: the file's), {args.workers} workers on {len(os.sched_getaffinity(0))} cores, load average "
          f"{os.getloadavg()[0]:.1f}; run {plan.run_id} ({m['status']}) in {lake.root}, {wall:.0f} s wall")
    print(report.text(report.build(lake, plan.run_id)))
    cols, rows = run_sql(lake, SPEED_SQL.format(run=plan.run_id))
    s = dict(zip(cols, rows[0]))
    if s["frames"]:
        print(f"\nper tracked frame ({s['frames']:,} frames, same frames for both): tracking median "
              f"{s['tracking_median_ms']:.3f} ms (mean {s['tracking_mean_ms']:.3f}; predict+match+solve+verify "
              f"median {s['predict_match_solve_median_ms']:.3f}), lost-in-space median {s['lis_median_ms']:.3f} ms "
              f"(mean {s['lis_mean_ms']:.3f}): the whole tracker {s['lis_median_ms'] / s['tracking_median_ms']:.1f}x, "
              f"predict + match + solve + verify {s['lis_median_ms'] / s['predict_match_solve_median_ms']:.1f}x "
              f"(medians)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
