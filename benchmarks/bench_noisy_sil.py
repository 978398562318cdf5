"""Benchmark: the sensor-noise star SIL as a user runs it (issue 24, point 3), this code against another tree.

    .venv/bin/python benchmarks/bench_noisy_sil.py                                   # this tree only
    .venv/bin/python benchmarks/bench_noisy_sil.py --old /tmp/M_old --repeats 3      # alternated with an old tree
    .venv/bin/python benchmarks/bench_noisy_sil.py --new /tmp/M_new --old /tmp/M_old   # two frozen worktrees
    .venv/bin/python benchmarks/bench_noisy_sil.py --cases 2000 6000 --workers 2 1

Workload: ``examples/star/noisy_sensor.toml`` (the reference's 1024 x 768 camera; shot, read and dark noise, sky,
hot pixels, two false stars per frame; the global detector), run by ``jobs/engine/runner.run_job`` exactly as
``dualsight star run --config examples/star/noisy_sensor.toml`` runs it: default workers (one per core, spawned,
each with its share of the threads) and ``--workers 1`` (in this process, Taichi's default thread count).

Each measurement is a fresh process that first runs an untimed 32-case job (imports, catalogs, kernel
compilation), then ``N1`` and ``N2`` cases; steady state = (N2 - N1) / (t(N2) - t(N1)), so what every run pays once
(spawning the workers, their start-up, the lake's files) cancels.  Besides wall time it reports the CPU time of
the whole job (this process and its reaped workers, ``getrusage``), per case in steady state: when two workers
need more CPU per case than one, they contend (memory bandwidth, caches); when they need the same CPU but take
longer, the cores were busy with something else (the machine is shared: the load average is printed).

``--old DIR``: the same measurement with dualsight imported from DIR (a ``git worktree`` of the code before a
change: ``DIR/dualsight/kernels`` ...), alternated run by run with this tree, so both see the same machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOISY = os.path.join(ROOT, "examples", "star", "noisy_sensor.toml")

_JOB = r"""
import json, resource, tempfile, time
from pathlib import Path
from dualsight.jobs.kinds import star
from dualsight.jobs.engine.runner import run_job
from dualsight.warehouse.lake import Lake
spec, _ = star.resolve_spec(None, Path({cfg!r}))
def cpu():
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime
res = []
for n in [32] + {sizes!r}:  # the first, untimed: this process's imports, catalogs and kernel compilation
    with tempfile.TemporaryDirectory() as tmp:
        c0, t0 = cpu(), time.perf_counter()
        run_job("star", spec, n_cases=n, lake=Lake(tmp), workers={workers!r}, progress=False, run_id="bench")
        res.append((n, time.perf_counter() - t0, cpu() - c0))
print(json.dumps(res[1:]))
"""


def job(tree: str | None, workers: int | None, sizes: list[int], one_thread: bool = False
        ) -> list[tuple[int, float, float]]:
    """[(cases, wall s, CPU s of all the job's processes)] in one fresh process importing dualsight from ``tree``
    (None: the installed package); ``one_thread``: every thread pool of the process at one thread."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "DUALSIGHT_TI_THREADS",
             "OPENCV_FOR_THREADS_NUM")
    env = {k: v for k, v in os.environ.items() if k not in names and k != "PYTHONPATH"}
    if one_thread:
        env.update(dict.fromkeys(names, "1"))
    if tree:
        env["PYTHONPATH"] = tree
    code = _JOB.format(cfg=NOISY, sizes=list(sizes), workers=workers)
    return job_script_rows(code, env)


def job_script_rows(code: str, env: dict) -> list[tuple]:
    """The rows (tuples) a job script prints as JSON on its last line, run in a fresh ``python -c`` process with
    ``env`` (also used by bench_noise_path.py); retried when another engineer's edit changed the code version
    under the running job; SystemExit with its stderr when it fails."""
    for _attempt in range(4):
        p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd="/tmp")
        if p.returncode == 0 or "install the same code on every worker" not in p.stderr:
            break
    if p.returncode != 0:
        raise SystemExit(f"job failed: {p.stderr[-3000:]}")
    return [tuple(r) for r in json.loads(p.stdout.strip().splitlines()[-1])]


def label(w: str) -> str:
    return {"0": "default", "1t": "1 (1 thread)"}.get(w, w)


def load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, nargs=2, default=[1000, 3000], metavar=("N1", "N2"))
    ap.add_argument("--workers", nargs="+", default=["0", "1", "1t"], choices=["0", "1", "2", "1t"],
                    help="what to measure: 0 the default workers (one per core), 1 one worker (in this process, "
                         "Taichi's default threads), 1t one worker with one thread (one core: the unit of scaling)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--old", default=None, help="also measure dualsight imported from this folder, alternated")
    ap.add_argument("--new", default=None,
                    help="import this code from this folder (a frozen copy: a worktree at the commit to measure), "
                         "not from the installed tree, which others' edits change under a running job")
    ap.add_argument("--json", default=None, help="also write the results here")
    args = ap.parse_args()
    n1, n2 = args.cases
    trees = {"new": args.new} | ({"old": args.old} if args.old else {})
    print(f"cores {os.cpu_count()}, cases {n1} and {n2} (steady state = the difference), load average {load()}")
    rates: dict = {}
    for rep in range(args.repeats):
        order = list(trees.items()) if rep % 2 == 0 else list(trees.items())[::-1]
        for name, tree in order:
            for w in args.workers:
                (a, ta, ca), (b, tb, cb) = job(tree, int(w.rstrip("t")) or None, [n1, n2], w.endswith("t"))
                r, cpu_ms = (b - a) / (tb - ta), 1e3 * (cb - ca) / (b - a)
                key = (name, w)
                rates.setdefault(key, []).append((r, cpu_ms))
                print(f"  {name} workers {label(w)}: {n1} cases {ta:.1f} s, {n2} cases {tb:.1f} s -> "
                      f"{r:6.1f} cases/s, CPU {cpu_ms:.2f} ms/case (load {load()})", flush=True)
    print(f"\nsteady state, median [min-max] of {args.repeats}:")
    med = {}
    for (name, w), v in rates.items():
        med[(name, w)] = statistics.median(x[0] for x in v)
        print(f"  {name} workers {label(w):>10}: {med[(name, w)]:7.1f} cases/s [{min(x[0] for x in v):.1f}-"
              f"{max(x[0] for x in v):.1f}], CPU {statistics.median(x[1] for x in v):.2f} ms/case")
    for name in trees:
        for one in ("1", "1t"):
            if (name, "0") in med and (name, one) in med:
                print(f"  {name}: default workers / {label(one)} = {med[(name, '0')] / med[(name, one)]:.2f}x")
    if args.old:
        for w in args.workers:
            print(f"  workers {label(w)}: new / old = {med[('new', w)] / med[('old', w)]:.2f}x")
    print(f"load average after: {load()}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({f"{k[0]}_w{k[1]}": v for k, v in rates.items()}, fh, indent=1)


if __name__ == "__main__":
    main()
