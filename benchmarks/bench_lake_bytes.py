"""Bytes per case on disk, per dataset and per column, of a star run (issue 24 point 5: ``star_cases`` <= 100 B),
and of every job kind that writes datasets (``--all-kinds``: the README's table).

    python benchmarks/bench_lake_bytes.py [--cases 10000] [--preset paper] [--workers 2] [--lake DIR] [--keep]
    python benchmarks/bench_lake_bytes.py --all-kinds [--workers 2]      # one run of each kind, the table
    python benchmarks/bench_lake_bytes.py --measure LAKE --run RUN      # an existing run, nothing is computed

Runs ``dualsight star run`` (one file per 1,000 cases at this size) into a temporary lake, then prints, for every
dataset of the run, its files' bytes per case (whole files: pages, footers, metadata) and, per column, the
compressed column-chunk bytes per case read from the Parquet footers, largest first.  Conditions (preset, cases,
shard size) are printed with the numbers.

``--all-kinds`` runs, into one temporary lake, each command below (:data:`KIND_RUNS`: its preset, case count and
noise) and prints one Markdown row per dataset: bytes per case (a case = one row of the kind's primary dataset:
a star case, a star-track sequence, a prox orientation or frame, a HIL image) and per row.  ``star_detections``
is on at this size; ``--detections off`` (above 100,000 cases by default) leaves that dataset out.
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


SHARED = Path(os.environ.get("DUALSIGHT_SHARED", Path(__file__).resolve().parents[2] / "shared"))
ESA = SHARED / "data" / "real" / "esa_tetra3"
ROOT = Path(__file__).resolve().parents[1]

KIND_RUNS = [
    # (run id, conditions, argv after `dualsight`)
    ("star", "paper preset, 10,000 cases, noise-free", ["star", "run", "--preset", "paper", "--cases", "10000",
                                                        "--detections", "on"]),
    ("star-noisy", "noisy preset (shot, read, sky, dark noise), 1,000 cases",
     ["star", "run", "--preset", "noisy", "--cases", "1000", "--detections", "on"]),
    ("track", "paper preset, 200 sequences of 50 frames (default motion and events)",
     ["star", "track", "--preset", "paper", "--cases", "200"]),
    ("sweep", "paper preset, 11 ranges x 100 orientations", ["prox", "sweep", "--orientations", "100"]),
    ("traj", "paper preset, 500 frames", ["prox", "trajectory", "--frames", "500"]),
    ("hil", "8 ESA TIFFs (shared data), default settings",
     ["hil", "star", *[str(p) for p in sorted(ESA.glob("*.tiff"))], "--camera",
      str(ROOT / "examples" / "cameras" / "esa_tetra3.toml")]),
]


def dataset_bytes(lake: Path, run: str) -> list[tuple[str, int, int, int]]:
    """(dataset, files, rows, bytes on disk) of every dataset of ``run`` in ``lake``, primary first."""
    import json

    m = json.loads((lake / "_manifests" / f"{run}.json").read_text())
    out = []
    for d in [m["primary"]] + [x for x in m["datasets"] if x != m["primary"]]:
        import pyarrow.parquet as pq

        files = sorted((lake / d / f"run={run}").glob("part-*.parquet"))
        rows = sum(pq.ParquetFile(f).metadata.num_rows for f in files)
        out.append((d, len(files), rows, sum(f.stat().st_size for f in files)))
    return out


def all_kinds(workers: int, lake: Path) -> int:
    print(f"one lake, seed 1, {workers} workers, default shard sizes; {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.1f}")
    print("| job kind (command) | run | dataset | B per case | B per row | rows per case | cases per file |")
    print("|---|---|---|---:|---:|---:|---:|")
    for run, cond, argv in KIND_RUNS:
        if argv[:2] == ["hil", "star"] and not ESA.is_dir():
            print(f"| {' '.join(argv[:2])} | {cond} | (no {ESA}) | | | |")
            continue
        cmd = [sys.executable, "-m", "dualsight", *argv, "--lake", str(lake), "--run", run, "--workers",
               str(workers)] + ([] if argv[0] == "hil" else ["--seed", "1", "--no-progress"])
        out = subprocess.run(cmd, capture_output=True, text=True)
        if out.returncode != 0:
            print(f"{' '.join(argv[:2])}: failed: {out.stderr.strip()[-300:]}", file=sys.stderr)
            continue
        sizes = dataset_bytes(lake, run)
        cases = sizes[0][2]
        for d, files, rows, size in sizes:
            print(f"| `{' '.join(argv[:2])}` | {cond} | `{d}` | {size / cases:.1f} | "
                  f"{size / max(rows, 1):.1f} | {rows / cases:.2f} | {cases / max(files, 1):,.0f} |", flush=True)
    return 0


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
    ap.add_argument("--all-kinds", action="store_true", help="one run of every job kind: the README's table")
    args = ap.parse_args()
    if args.all_kinds:
        lake = args.lake or Path(tempfile.mkdtemp(prefix="bench-lake-bytes-"))
        try:
            return all_kinds(args.workers, lake)
        finally:
            if args.lake is None and not args.keep:
                shutil.rmtree(lake, ignore_errors=True)
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
