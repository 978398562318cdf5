"""Thread pools on a busy machine (issue 24 point 2): `dualsight hil star` over the 8 ESA frames, whole
processes at their default settings, against the same command with numpy's BLAS/OpenMP pool at one thread per
core (what every process had before `dualsight/__init__.py` set the BLAS pools to one thread), alternated in one
run, each in a fresh lake.  Prints the median per-frame time of each run (the `ms` column: decoding, detection,
identification, attitude) and the whole-process wall time, with the load average.

    python benchmarks/bench_thread_pools.py [--repeats 4] [--busy 2]

``--busy N`` starts N spinning processes for the duration (a loaded machine, as when other jobs share it).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ESA = Path(os.environ.get("DUALSIGHT_SHARED", ROOT.parent / "shared")) / "data" / "real" / "esa_tetra3"


def spin(stop_at: float) -> None:
    while time.time() < stop_at:
        pass


def one(variant: str, lake: Path) -> tuple[float, float]:
    env = dict(os.environ)
    for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(k, None)
        if variant == "pool":
            env[k] = str(os.cpu_count() or 1)
    shutil.rmtree(lake, ignore_errors=True)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "dualsight", "hil", "star", *sorted(map(str, ESA.glob("*.tiff"))),
                        "--camera", str(ROOT / "examples" / "cameras" / "esa_tetra3.toml"), "--lake", str(lake),
                        "--no-compare", "--json"], env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    doc = json.loads(p.stdout)
    images = doc["images"] if isinstance(doc, dict) else doc
    return statistics.median(i["runtime_ms"] for i in images if i.get("runtime_ms")), wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--busy", type=int, default=0, help="spinning processes to start (default 0)")
    a = ap.parse_args()
    if not ESA.is_dir():
        print(f"needs the ESA frames in {ESA}", file=sys.stderr)
        return 2
    spinners = [mp.get_context("spawn").Process(target=spin, args=(time.time() + 3600,), daemon=True)
                for _ in range(a.busy)]
    for s in spinners:
        s.start()
    res = {"default": [], "pool": []}
    with tempfile.TemporaryDirectory() as d:
        for _ in range(a.repeats):
            for v in ("pool", "default"):
                res[v].append(one(v, Path(d) / "lake"))
    for s in spinners:
        s.terminate()
    print(f"{os.cpu_count()} cores, {a.busy} spinning processes, load average {os.getloadavg()[0]:.1f}")
    for v, label in (("pool", f"BLAS pool of {os.cpu_count()} threads"), ("default", "default (BLAS 1 thread)")):
        ms = [r[0] for r in res[v]]
        wall = [r[1] for r in res[v]]
        print(f"{label:32s} median frame {statistics.median(ms):6.1f} ms (runs {min(ms):.1f}-{max(ms):.1f}), "
              f"whole process {statistics.median(wall):.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
