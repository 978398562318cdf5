"""End-to-end star-tracker throughput, stage shares and peak memory (run by hand or nightly).

    .venv/bin/python benchmarks/bench_star.py                      # 10,000 cases, 2 workers and 1 worker
    .venv/bin/python benchmarks/bench_star.py --cases 10000 100000 # memory must not grow with cases

Each run is a fresh ``dualsight star run`` process (the user's command) into a temporary lake.  While it runs,
the resident memory of its whole process group (coordinator + spawned workers) is sampled every 0.1 s from
/proc; the peak is reported.  Throughput is cases / wall time of the whole command (start-up included) and,
from the manifest, of the compute phase.  Stage shares come from the lake's per-stage timings (SQL).
The peer is the same command with one worker, in the same session, so the speed-up is a ratio measured
side by side on this machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

PAGE = os.sysconf("SC_PAGE_SIZE")


def group_rss_bytes(pgid: int) -> int:
    total = 0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[2]) != pgid:
                continue
            total += int((d / "statm").read_text().split()[1]) * PAGE
        except (OSError, ValueError, IndexError):
            continue
    return total


def run_one(cases: int, workers: int, seed: int = 11) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "dualsight", "star", "run", "--preset", "paper", "--cases", str(cases),
               "--seed", str(seed), "--lake", tmp, "--run", "bench", "--workers", str(workers), "--no-progress"]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        peak = [0]
        stop = threading.Event()

        def sample():
            while not stop.is_set():
                peak[0] = max(peak[0], group_rss_bytes(proc.pid))
                time.sleep(0.1)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        _, err = proc.communicate()
        wall = time.perf_counter() - t0
        stop.set()
        th.join()
        if proc.returncode != 0:
            raise SystemExit(f"run failed: {err.decode()[-2000:]}")
        manifest = json.loads((Path(tmp) / "_manifests" / "bench.json").read_text())
        compute = manifest["executions"][-1]["elapsed_s"]
        from dualsight.warehouse.query import connect, run_report

        con = connect(tmp)
        cols, rows = run_report(con, "star_stage_times", run="bench")
        _, srow = run_report(con, "star_summary", run="bench")
        scols = run_report(con, "star_summary", run="bench")[0]
        summ = dict(zip(scols, srow[0]))
        return {"cases": cases, "workers": workers, "wall_s": wall, "compute_s": compute,
                "cases_per_s_wall": cases / wall, "cases_per_s_compute": cases / compute,
                "peak_rss_mb": peak[0] / 2**20, "stages": {r[0]: {"ms_per_case": r[1], "share": r[2]} for r in rows},
                "success_rate": summ["success_rate"], "confident_wrong_rate": summ["confident_wrong_rate"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, nargs="+", default=[10000])
    ap.add_argument("--workers", type=int, nargs="+", default=[2, 1])
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args()
    print(f"cores: {os.cpu_count()}")
    results = []
    for n in args.cases:
        for w in args.workers:
            r = run_one(n, w)
            results.append(r)
            print(f"{n:>7} cases, {w} worker(s): {r['cases_per_s_wall']:.0f} cases/s wall "
                  f"({r['cases_per_s_compute']:.0f} compute), {r['wall_s']:.1f} s, peak RSS {r['peak_rss_mb']:.0f} MB, "
                  f"success {100 * r['success_rate']:.2f} %, confident-wrong {100 * r['confident_wrong_rate']:.2f} %")
            for stage, v in r["stages"].items():
                if v["ms_per_case"] is None:              # a stage this run did not time (e.g. no comparison)
                    print(f"    {stage:>14}: -")
                    continue
                print(f"    {stage:>14}: {v['ms_per_case']:.3f} ms/case/worker  ({100 * v['share']:.1f} %)")
    by = {(r["cases"], r["workers"]): r for r in results}
    for n in args.cases:
        if (n, 1) in by and (n, 2) in by:
            print(f"speed-up 2 workers / 1 worker at {n} cases: "
                  f"{by[(n, 2)]['cases_per_s_wall'] / by[(n, 1)]['cases_per_s_wall']:.2f}x")
    for w in args.workers:                                 # steady state: start-up cancels in the difference
        runs = sorted((r for r in results if r["workers"] == w), key=lambda r: r["cases"])
        if len(runs) >= 2 and runs[-1]["wall_s"] > runs[0]["wall_s"]:
            rate = (runs[-1]["cases"] - runs[0]["cases"]) / (runs[-1]["wall_s"] - runs[0]["wall_s"])
            print(f"steady state, {w} worker(s): {rate:.0f} cases/s "
                  f"(({runs[-1]['cases']} - {runs[0]['cases']}) cases / difference of the wall times)")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
