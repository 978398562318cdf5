"""Bytes per case on disk, per dataset and per column, of a star run (issue 24 point 5: ``star_cases`` <= 100 B).

    python benchmarks/bench_lake_bytes.py [--cases 10000] [--preset paper] [--workers 2] [--lake DIR] [--keep]
    python benchmarks/bench_lake_bytes.py --measure LAKE --run RUN      # an existing run, nothing is computed

Runs ``dualsight star run`` (one file per 1,000 cases at this size) into a temporary lake, then prints, for every
dataset of the run, its files' bytes per case (whole files: pages, footers, metadata) and, per column, the
compressed column-chunk bytes per case read from the Parquet footers, largest first.  Conditions (preset, cases,
shard size) are printed with the numbers.
"""

from __future__ import annotations

import argparse
import collections
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")


def measure(lake: Path, run: str, columns: int) -> None:
    import pyarrow.parquet as pq

    cases = None
    for d in sorted(p for p in lake.iterdir() if p.is_dir() and not p.name.startswith("_")):
        files = sorted((d / f"run={run}").glob("part-*.parquet"))
        if not files:
            continue
        acc, rows, size = collections.Counter(), 0, 0
        for f in files:
            md = pq.ParquetFile(f).metadata
            rows, size = rows + md.num_rows, size + f.stat().st_size
            for g in range(md.num_row_groups):
                rg = md.row_group(g)
                for i in range(rg.num_columns):
                    acc[rg.column(i).path_in_schema] += rg.column(i).total_compressed_size
        if d.name == "star_cases":
            cases = rows
        n = cases or rows
        print(f"{d.name}: {len(files)} files, {rows:,} rows, {size / n:.1f} B per case on disk "
              f"(column chunks {sum(acc.values()) / n:.1f}, footers and metadata {(size - sum(acc.values())) / n:.1f})")
        for k, v in acc.most_common(columns):
            print(f"    {k:36s} {v / n:8.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10_000)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--lake", type=Path, default=None, help="lake folder (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary lake")
    ap.add_argument("--measure", type=Path, default=None, help="measure this lake's run --run only")
    ap.add_argument("--run", default="bytes")
    ap.add_argument("--columns", type=int, default=25, help="columns listed per dataset")
    args = ap.parse_args()
    if args.measure is not None:
        measure(args.measure, args.run, args.columns)
        return 0
    lake = args.lake or Path(tempfile.mkdtemp(prefix="bench-lake-bytes-"))
    cmd = [sys.executable, "-m", "dualsight", "star", "run", "--preset", args.preset, "--cases", str(args.cases),
           "--seed", "1", "--lake", str(lake), "--run", args.run, "--workers", str(args.workers), "--no-progress"]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        print(out.stderr[-2000:], file=sys.stderr)
        return 1
    print(f"preset {args.preset}, {args.cases:,} cases, seed 1, {args.workers} workers (default shard size)")
    measure(lake, args.run, args.columns)
    if args.lake is None and not args.keep:
        shutil.rmtree(lake, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
