"""Engine overhead and executors, measured side by side in one run (never a timed test).

1. Per-shard overhead: the self-test job (microseconds of work per case) with shards of 1, 10 and 100
   cases, in-process; overhead per shard = (time per shard) - (time per case x cases per shard), which is
   writing two Parquet files with metadata, fsync, rename, the journal line and the verification-ready footer.
2. Throughput of the paper-preset star job on: one in-process worker, 2 spawned local workers, and a
   loopback Dask cluster (``dask scheduler`` + 2 ``dask worker`` processes, 1 thread each, on 127.0.0.1).
   Whole-call times including start-up; the ratio to the in-process run is the number to read.

    python benchmarks/bench_engine.py [--cases 4000] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=4000, help="star cases per executor (default 4000)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    from dualsight.jobs.kinds import star
    from dualsight.jobs.engine.runner import run_job
    from dualsight.warehouse.lake import Lake

    out = {"cores": os.cpu_count()}
    tmp = Path(tempfile.mkdtemp(prefix="bench-engine-"))
    try:
        rows = []
        n = 2000
        for shard in (1, 10, 100, 1000):
            lake = Lake(tmp / f"ov{shard}")
            el = timed(lambda: run_job("selftest", {"seed": 1}, n_cases=n, lake=lake, run_id="o", workers=1,
                                       shard_size=shard, progress=False))
            rows.append({"shard_size": shard, "shards": -(-n // shard), "seconds": round(el, 3),
                         "ms_per_shard": round(1000 * el / -(-n // shard), 3)})
        base = rows[-1]["seconds"] / n                     # per-case cost with 2 shards: ~pure compute
        for r in rows:
            r["overhead_ms_per_shard"] = round(1000 * (r["seconds"] - base * n) / r["shards"], 3)
        out["per_shard"] = rows

        spec, _ = star.resolve_spec("paper", None, seed=11)
        star_rows = []
        for name, kw in (("in-process, 1 worker", {"workers": 1}), ("local, 2 spawned workers", {"workers": 2})):
            lake = Lake(tmp / name.replace(" ", "_").replace(",", ""))
            el = timed(lambda: run_job("star", spec, n_cases=args.cases, lake=lake, run_id="s", progress=False,
                                       **kw))
            star_rows.append({"executor": name, "cases": args.cases, "seconds": round(el, 2),
                              "cases_per_s": round(args.cases / el)})
        from test_cluster import Cluster

        (tmp / "dask").mkdir()
        t0 = time.perf_counter()
        c = Cluster(tmp / "dask", workers=2)
        start_s = time.perf_counter() - t0
        try:
            lake = Lake(tmp / "dask_lake")
            el = timed(lambda: run_job("star", spec, n_cases=args.cases, lake=lake, run_id="s", progress=False,
                                       scheduler=c.address))
        finally:
            c.close()
        star_rows.append({"executor": "loopback Dask, 2 workers x 1 thread", "cases": args.cases,
                          "seconds": round(el, 2), "cases_per_s": round(args.cases / el),
                          "cluster_start_s": round(start_s, 2)})
        ref = star_rows[0]["seconds"]
        for r in star_rows:
            r["speedup_vs_in_process"] = round(ref / r["seconds"], 2)
        out["star_paper"] = star_rows
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        from dualsight.warehouse.query import format_table

        print(f"cores: {out['cores']}\n\nper-shard overhead (selftest, {n} cases, in-process)")
        print(format_table(list(out["per_shard"][0]), [tuple(r.values()) for r in out["per_shard"]]))
        print(f"\nstar paper preset, {args.cases} cases, whole call")
        keys = list(out["star_paper"][-1])
        print(format_table(keys, [tuple(r.get(k) for k in keys) for r in out["star_paper"]]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
