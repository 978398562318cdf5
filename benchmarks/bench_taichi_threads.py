"""Does Taichi's CPU backend use more than one core in one process on this machine?

    .venv/bin/python benchmarks/bench_taichi_threads.py [--threads 1 2 4] [--work 2000000]

For each ``cpu_max_num_threads`` (one child process each: Taichi starts once per process) it runs one kernel,
a range-for of 256 independent iterations of pure arithmetic (no memory traffic), and reads every thread's
CPU time from ``/proc/self/task/*/stat`` before and after: the number of threads that did the work, the wall
time and the process CPU time.  A second check runs two Python threads of numpy sorts in the same process, to
tell a machine limit (cgroup, affinity) from Taichi's own scheduling.

Measured on this project's 2-core VM (taichi 1.7.4, Linux): every setting ran the kernel on ONE thread
(CPU time = wall time, one worker thread busy), while the two numpy threads used both cores (CPU ~2x wall).
So in-process Taichi kernels give no parallel speed-up here; dualsight's parallelism is its worker
processes (``--workers``: 2 workers = 2.0x one on the paper preset, 2.4x on the noise path).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

CHILD = r"""
import json, os, sys, time
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
import taichi as ti
n_threads, work = int(sys.argv[1]), int(sys.argv[2])
ti.init(arch=ti.cpu, cpu_max_num_threads=n_threads, offline_cache=False, log_level=ti.WARN)
x = ti.field(ti.f64, shape=256)

@ti.kernel
def k(w: ti.i32):
    for i in range(256):
        acc = 0.0
        for j in range(w):
            acc = acc * 0.999999 + ti.cast((j ^ i) & 7, ti.f64)
        x[i] = acc

def per_thread():
    out = {}
    for t in os.listdir("/proc/self/task"):
        f = open(f"/proc/self/task/{t}/stat").read().rsplit(")", 1)[1].split()
        out[t] = (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    return out

k(16)
a, t0, c0 = per_thread(), time.perf_counter(), time.process_time()
k(work)
wall, cpu, b = time.perf_counter() - t0, time.process_time() - c0, per_thread()
busy = sorted((round(b[t] - a.get(t, 0.0), 2) for t in b if b[t] - a.get(t, 0.0) > 0.05 * wall), reverse=True)
print(json.dumps({"threads": n_threads, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "busy_threads": busy}))
"""

NUMPY = r"""
import threading, time, numpy as np
a = [np.random.default_rng(i).random(8_000_000) for i in range(2)]
def w(x):
    for _ in range(3):
        np.sort(x)
t0, c0 = time.perf_counter(), time.process_time()
ts = [threading.Thread(target=w, args=(x,)) for x in a]
[t.start() for t in ts]; [t.join() for t in ts]
print(f"{time.perf_counter() - t0:.3f} {time.process_time() - c0:.3f}")
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--work", type=int, default=2_000_000, help="inner iterations per outer iteration")
    args = ap.parse_args()
    print(f"cores {os.cpu_count()}, affinity {sorted(os.sched_getaffinity(0))}, load {os.getloadavg()[0]:.2f}")
    tmp = tempfile.mkdtemp(prefix="bench-ti-threads-")
    child = os.path.join(tmp, "child.py")          # Taichi reads a kernel's source: a file, not ``-c``
    with open(child, "w") as f:
        f.write(CHILD)
    for n in args.threads:
        r = subprocess.run([sys.executable, child, str(n), str(args.work)], capture_output=True, text=True)
        if r.returncode != 0:
            print(f"threads {n}: failed: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode}")
            continue
        d = json.loads(r.stdout.strip().splitlines()[-1])
        print(f"taichi cpu_max_num_threads {n}: wall {d['wall_s']:.2f} s, cpu {d['cpu_s']:.2f} s "
              f"(cpu/wall {d['cpu_s'] / max(d['wall_s'], 1e-9):.2f}), threads doing the work: "
              f"{len(d['busy_threads'])} {d['busy_threads']}")
    shutil.rmtree(tmp, ignore_errors=True)
    r = subprocess.run([sys.executable, "-c", NUMPY], capture_output=True, text=True)
    wall, cpu = map(float, r.stdout.split())
    print(f"two numpy threads in one process: wall {wall:.2f} s, cpu {cpu:.2f} s (cpu/wall {cpu / wall:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
