"""A large paper-preset star campaign, whole process: time, peak memory, lake size, and every report query.

    python benchmarks/bench_campaign.py [--cases 1000000] [--workers 1] [--lake DIR] [--keep]

Runs ``dualsight star run --preset paper`` (noise-free frames, V 5.5, tolerance 10 arcsec) as a child process
under ``/usr/bin/time -v`` when available (peak resident memory of the run), then times each star report query
(``warehouse/sql/star_*.sql``) over the lake, and prints the extrapolation to 10^7 cases (linear in cases for
the run; the measured query times scaled by rows).  Conditions (cores, case count) are printed with the numbers.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1_000_000)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--lake", type=Path, default=None, help="lake folder (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary lake")
    args = ap.parse_args()
    lake = args.lake or Path(tempfile.mkdtemp(prefix="bench-campaign-"))
    cmd = [sys.executable, "-m", "dualsight", "star", "run", "--preset", "paper", "--cases", str(args.cases),
           "--seed", "1", "--lake", str(lake), "--run", "campaign", "--workers", str(args.workers), "--no-progress"]
    timer = ["/usr/bin/time", "-v"] if Path("/usr/bin/time").exists() else []
    t0 = time.perf_counter()
    out = subprocess.run(timer + cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        print(out.stderr[-2000:], file=sys.stderr)
        return 1
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr)
    peak = int(m.group(1)) / 1024 if m else None
    size = sum(p.stat().st_size for p in lake.rglob("*") if p.is_file()) / 2**20

    from dualsight.warehouse.lake import Lake
    from dualsight.warehouse.query import connect, run_report

    t1 = time.perf_counter()
    con = connect(Lake(lake))
    t_connect = time.perf_counter() - t1
    q = {}
    for name in ("star_summary", "star_table5", "star_error_vs_observed", "star_status", "star_stage_times",
                 "star_robust"):
        t = time.perf_counter()
        run_report(con, name, run="campaign")
        q[name] = time.perf_counter() - t
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "dualsight", "star", "report", "--lake", str(lake), "--run",
                        "campaign"], capture_output=True, text=True)
    t_report = time.perf_counter() - t
    scale = 10**7 / args.cases
    print(f"cores {os.cpu_count()}, workers {args.workers}, {args.cases:,} noise-free paper-preset cases")
    print(f"run: {wall:.1f} s whole process ({args.cases / wall:,.0f} cases/s), peak RSS "
          f"{'%.0f MB' % peak if peak else 'n/a (no /usr/bin/time)'}, lake {size:,.0f} MiB")
    print(f"views: {t_connect:.2f} s; queries: " + ", ".join(f"{k} {v:.2f} s" for k, v in q.items()))
    print(f"`dualsight star report` whole process: {t_report:.2f} s (exit {r.returncode})")
    print(f"extrapolated to 10^7 cases: run {wall * scale / 60:.0f} min, lake {size * scale / 1024:.1f} GiB, "
          f"report queries {sum(q.values()) * scale:.0f} s")
    if args.lake is None and not args.keep:
        shutil.rmtree(lake, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
