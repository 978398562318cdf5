"""Does Taichi's CPU backend use more than one core in one process on this machine, and for which loops?

    .venv/bin/python benchmarks/bench_taichi_threads.py [--threads 1 2 4] [--work 2000000]

(prints the launch costs too)

For each ``cpu_max_num_threads`` (one child process each: Taichi starts once per process) it runs two
kernels doing the same 256 independent work items of pure arithmetic (no memory traffic), and reads every
thread's CPU time from ``/proc/self/task/*/stat`` around each: the number of threads that did the work, the
wall time and the process CPU time.

* ``plain``: ``for i in range(256)``.
* ``spread``: ``for t in range(256 * TASK_ITEMS)``, working where ``t % TASK_ITEMS == 0`` (the form
  :data:`dualsight.kernels.taichi_runtime.TASK_ITEMS` documents; the vote kernel's per-thread slots use it).

A last check runs two Python threads of numpy sorts in one process, to tell a machine limit (cgroup,
affinity) from Taichi's own scheduling.

``--launch`` (also in the default run): the fixed cost of one kernel launch, per thread setting: a kernel
whose loop over 1 item is parallel (the default) or serial (``ti.loop_config(serialize=True)``), with 2
and with 10 numpy-array arguments; median microseconds of 2,000 launches.  This is what
:class:`dualsight.kernels.taichi_runtime.KernelCache`'s serial variants and the packed argument tables of
:mod:`dualsight.kernels.labelling` save on a single frame.  Measured (same VM, 2026-11-24, load 2.3): a
parallel loop adds ~80-100 us per launch at 1 and at 2 threads (the thread pool's round trip), each array
argument ~8.5 us (Taichi's Python launcher): 2 arguments 30-31 us serial, 108-131 us parallel; 10 arguments
97-102 us serial, 179-188 us parallel.  The same kernels through
:class:`dualsight.kernels.taichi_runtime.FastKernel` (what every dualsight kernel is called through) are the
``FastKernel`` rows.

Measured on this project's 2-core VM (taichi 1.7.4, Linux, 2026-11-24): ``plain`` runs on ONE thread at
every setting (Taichi hands a range-for out in tasks of >= 512 iterations, so 256 iterations are one
task; ``loop_config(block_dim=...)`` and ``cpu_block_dim_adaptive=False`` do not change it), while
``spread`` with 2 threads runs on two threads at half the wall time (cpu/wall ~2).  Loops over >= 1024
iterations (pixels, large batches) are split without help.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

from dualsight.kernels.taichi_runtime import TASK_ITEMS

CHILD = r"""
import json, os, sys, time
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
import taichi as ti
n_threads, work, S = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
ti.init(arch=ti.cpu, cpu_max_num_threads=n_threads, offline_cache=False, log_level=ti.WARN)
x = ti.field(ti.f64, shape=256)

@ti.func
def item(i, w):
    acc = ti.cast(0.0, ti.f64)
    for j in range(w):
        acc = acc * 0.999999 + ti.cast((j ^ i) & 7, ti.f64)
    x[i] = acc

@ti.kernel
def plain(w: ti.i32):
    for i in range(256):
        item(i, w)

@ti.kernel
def spread(w: ti.i32):
    for t in range(256 * S):
        if t % S == 0:
            item(t // S, w)

def per_thread():
    out = {}
    for t in os.listdir("/proc/self/task"):
        f = open(f"/proc/self/task/{t}/stat").read().rsplit(")", 1)[1].split()
        out[t] = (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    return out

res = []
for name, k in (("plain", plain), ("spread", spread)):
    k(16)
    a, t0, c0 = per_thread(), time.perf_counter(), time.process_time()
    k(work)
    wall, cpu, b = time.perf_counter() - t0, time.process_time() - c0, per_thread()
    busy = sorted((round(b[t] - a.get(t, 0.0), 2) for t in b if b[t] - a.get(t, 0.0) > 0.05 * wall),
                  reverse=True)
    res.append({"loop": name, "threads": n_threads, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
                "busy_threads": busy})
print(json.dumps(res))
"""

LAUNCH = r"""
import json, os, statistics, sys, time
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
import numpy as np
import taichi as ti
ti.init(arch=ti.cpu, cpu_max_num_threads=int(sys.argv[1]), offline_cache=False, log_level=ti.WARN)
A = ti.types.ndarray(dtype=ti.i32, ndim=1)

@ti.kernel
def par2(a: A, b: A):
    for i in range(a.shape[0] - 1):
        b[i] = a[i]

@ti.kernel
def ser2(a: A, b: A):
    ti.loop_config(serialize=True)
    for i in range(a.shape[0] - 1):
        b[i] = a[i]

@ti.kernel
def par10(a: A, b: A, c: A, d: A, e: A, f: A, g: A, h: A, i2: A, j: A):
    for i in range(a.shape[0] - 1):
        b[i] = a[i]

@ti.kernel
def ser10(a: A, b: A, c: A, d: A, e: A, f: A, g: A, h: A, i2: A, j: A):
    ti.loop_config(serialize=True)
    for i in range(a.shape[0] - 1):
        b[i] = a[i]

from dualsight.kernels.taichi_runtime import FastKernel   # dualsight's short launcher, same kernels, same process

x = [np.zeros(2, np.int32) for _ in range(10)]
out = {}
kernels = (("parallel, 2 args", par2, 2), ("serial, 2 args", ser2, 2), ("parallel, 10 args", par10, 10),
           ("serial, 10 args", ser10, 10))
for name, k, n in kernels + tuple((f"FastKernel {name}", FastKernel(k), n) for name, k, n in kernels):
    k(*x[:n])
    ts = []
    for _ in range(20):
        t0 = time.perf_counter()
        for _ in range(100):
            k(*x[:n])
        ts.append((time.perf_counter() - t0) / 100 * 1e6)
    out[name] = round(statistics.median(ts), 1)
print(json.dumps(out))
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
        r = subprocess.run([sys.executable, child, str(n), str(args.work), str(TASK_ITEMS)],
                           capture_output=True, text=True)
        if r.returncode != 0:
            print(f"threads {n}: failed: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode}")
            continue
        for d in json.loads(r.stdout.strip().splitlines()[-1]):
            print(f"taichi cpu_max_num_threads {n}, {d['loop']:6s} loop: wall {d['wall_s']:.2f} s, "
                  f"cpu {d['cpu_s']:.2f} s (cpu/wall {d['cpu_s'] / max(d['wall_s'], 1e-9):.2f}), "
                  f"threads doing the work: {len(d['busy_threads'])} {d['busy_threads']}")
    launch = os.path.join(tmp, "launch.py")
    with open(launch, "w") as f:
        f.write(LAUNCH)
    for n in args.threads:
        r = subprocess.run([sys.executable, launch, str(n)], capture_output=True, text=True)
        if r.returncode != 0:
            print(f"launch, threads {n}: failed: {r.stderr.strip()[-300:]}")
            continue
        d = json.loads(r.stdout.strip().splitlines()[-1])
        print(f"taichi cpu_max_num_threads {n}, us per launch (loop over 1 item): "
              + ", ".join(f"{k} {v:.0f}" for k, v in d.items()))
    shutil.rmtree(tmp, ignore_errors=True)
    r = subprocess.run([sys.executable, "-c", NUMPY], capture_output=True, text=True)
    wall, cpu = map(float, r.stdout.split())
    print(f"two numpy threads in one process: wall {wall:.2f} s, cpu {cpu:.2f} s (cpu/wall {cpu / wall:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
