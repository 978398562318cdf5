"""Benchmark: the default (``local``) star detector's CPU time per frame on ONE core, per stage, alternated with
the code of another commit (issue 24, point 1).

Frames: the 8 ESA tetra3 frames (1024 x 768 16-bit TIFFs, ~90-520 detections each) and N frames rendered as
``bench_hil_speed.py frame --rendered N`` makes them (1024 x 1024, 16-bit TIFFs, the noise of
examples/star/noisy_sensor.toml with hot pixels and glints, ~20-50 stars).  Each measurement runs in its own
process pinned to one core (``taskset -c CORE`` when available; OMP / BLAS / Taichi threads and OpenCV at 1),
``detect_real(frame, LocalDetectConfig())`` (the PSF width measured per frame, as ``hil star`` runs it), each
frame once unmeasured, then ``--repeats`` timed passes; CPU time of the process (``time.process_time``: on a
shared machine it does not count the time other processes take the core away).  Stages: each module function's
own time, nested calls excluded (``bench_hil_speed.Timers``).

``--against COMMIT`` (default: the commit before this benchmark's detector work, 00d8bee) checks that commit out
with ``git worktree add`` into a temporary folder and runs the same measurement there (its own package, by
PYTHONPATH), alternating the two ``--rounds`` times, so a ratio is measured under the same load.

``--taichi`` measures with ``LocalDetectConfig(fit_engine="taichi")`` where the tree has that setting (the PSF fits
as one Taichi kernel, ``kernels/detect_psf_fit.py``; the kernels' start is outside the timed passes); without it each
tree runs its default (since 822a98b the default is "taichi": fits, tile statistics and components compiled).

Usage:  python benchmarks/bench_detect_speed.py [--rounds 2] [--repeats 3] [--rendered 8] [--against 00d8bee] [--taichi]
        python benchmarks/bench_detect_speed.py --against none            # this tree only
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ESA = Path(os.environ.get("DUALSIGHT_SHARED", ROOT.parent / "shared")) / "data" / "real" / "esa_tetra3"
BEFORE = "00d8bee97d956bdd65ee9b4dff23fbe66ff661b8"

# module, function, stage label: each function's own time (the stages of detect_local's docstring)
STAGES = [("detect_local", "tile_background", "background"), ("detect_local", "interpolate_tiles", "background"),
          ("detect_local", "matched_filter", "filter"), ("detect_candidates", "robust_stats", "filter"),
          ("detect_candidates", "robust_std", "filter"),
          ("detect_local", "find_candidates", "candidates"),
          ("detect_local", "_measure", "hot pixels + fit"), ("detect_local", "fit_psf", "hot pixels + fit"),
          ("detect_local", "fit_psf_compiled", "hot pixels + fit"),
          ("detect_local", "cut_stamps", "hot pixels + fit")]

CHILD = r"""
import json, os, sys, time
for v in ("DUALSIGHT_TI_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[v] = "1"
import cv2
import numpy as np
cv2.setNumThreads(1)
sys.path.insert(0, sys.argv[1])
from bench_hil_speed import Timers
import importlib
stages, sets, repeats, taichi = json.loads(sys.argv[2]), json.loads(sys.argv[3]), int(sys.argv[4]), sys.argv[5] == "1"
dl = importlib.import_module("dualsight.kernels.detect_local")
import dataclasses
fit_taichi = taichi and "fit_engine" in {f.name for f in dataclasses.fields(dl.LocalDetectConfig)}
T = Timers()
for mod, name, label in stages:
    m = importlib.import_module("dualsight.kernels." + mod)
    if hasattr(m, name):
        T.wrap(m, name, label)
out = {"package": os.path.dirname(dl.__file__), "engine": getattr(dl.LocalDetectConfig(), "fit_engine", "numpy")}
for set_name, paths in sets.items():
    imgs = [cv2.imread(p, cv2.IMREAD_UNCHANGED) for p in paths]
    cfg = dl.LocalDetectConfig(fit_engine="taichi") if fit_taichi else dl.LocalDetectConfig()
    n = [len(dl.detect_real(im[None], cfg)) for im in imgs]
    per = {}
    for _ in range(repeats):
        for im in imgs:
            T.t.clear()
            with T.stage("other"):
                dl.detect_real(im[None], cfg)
            for k, v in T.t.items():
                per.setdefault(k, []).append(v)
            per.setdefault("total", []).append(sum(T.t.values()))
    out[set_name] = {"detections": n, **{k: float(np.median(v)) for k, v in per.items()},
                     "total_q": [float(q) for q in np.percentile(per["total"], [25, 75])]}
print(json.dumps(out))
"""


def measure(tree: Path, sets: dict, repeats: int, core: str | None, taichi: bool = False) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, "-c", CHILD, str(ROOT / "benchmarks"), json.dumps(STAGES), json.dumps(sets), str(repeats),
           "1" if taichi else "0"]
    if core is not None and shutil.which("taskset"):
        cmd = ["taskset", "-c", core, *cmd]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(tree))
    if r.returncode:
        raise SystemExit(f"measurement in {tree} failed: {r.stderr.strip()[-800:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def line(tag: str, res: dict, set_name: str) -> str:
    d = res[set_name]
    order = ["background", "filter", "candidates", "hot pixels + fit", "other"]
    q1, q3 = d["total_q"]
    return (f"  {tag:8s} " + ", ".join(f"{s} {1e3 * d[s]:.2f}" for s in order if s in d)
            + f" | total {1e3 * d['total']:.2f} ms (quartiles {1e3 * q1:.2f}-{1e3 * q3:.2f});"
            f" detections {d['detections']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=2, help="alternations of this tree and --against (default 2)")
    ap.add_argument("--repeats", type=int, default=3, help="timed passes over the frames per process (default 3)")
    ap.add_argument("--rendered", type=int, default=8, help="rendered 1024 x 1024 frames, 0 = none (default 8)")
    ap.add_argument("--against", default=BEFORE, help="commit to compare with, or 'none' (default 00d8bee)")
    ap.add_argument("--core", default="0", help="CPU the measuring processes are pinned to (default 0)")
    ap.add_argument("--taichi", action="store_true", help="LocalDetectConfig(fit_engine='taichi') where the tree "
                    "has that setting: the PSF fits as one Taichi kernel")
    a = ap.parse_args()
    if not 1 <= a.rounds <= 20 or not 1 <= a.repeats <= 50 or not 0 <= a.rendered <= 200:
        ap.error("--rounds in [1, 20], --repeats in [1, 50], --rendered in [0, 200]")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_hil_speed import conditions, rendered_frames

    sets = {"ESA 1024x768": [str(p) for p in sorted(ESA.glob("*.tiff"))]}
    if a.rendered:
        paths, _, _ = rendered_frames(a.rendered, 5.5)
        sets["rendered 1024x1024"] = [str(p) for p in paths]
    print(conditions())
    trees = [("this", ROOT)]
    tmp = None
    if a.against != "none":
        tmp = Path(tempfile.mkdtemp(prefix="bench-detect-old-"))
        old = tmp / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), a.against],
                       check=True, capture_output=True)
        trees.append((a.against[:7], old))
    try:
        results = {tag: [] for tag, _ in trees}
        for _ in range(a.rounds):
            for tag, tree in trees:
                results[tag].append(measure(tree, sets, a.repeats, a.core, a.taichi))
        print(f"detect_real CPU ms per frame, one core, median over frames x {a.repeats} repeats, "
              f"{a.rounds} alternated rounds (stage = own time of its functions)"
              + ("; fit_engine 'taichi' where the tree has it" if a.taichi else "; default settings: fit_engine "
                 + ", ".join(f"{tag} '{results[tag][0]['engine']}'" for tag, _ in trees)))
        for set_name in sets:
            print(set_name + ":")
            for i in range(a.rounds):
                for tag, _ in trees:
                    print(line(f"{tag}#{i + 1}", results[tag][i], set_name))
            if len(trees) == 2:
                r = [results["this"][i][set_name]["total"] / results[trees[1][0]][i][set_name]["total"]
                     for i in range(a.rounds)]
                print(f"  ratio this / {trees[1][0]}: " + ", ".join(f"{x:.2f}" for x in r)
                      + f" (median {statistics.median(r):.2f})")
    finally:
        if tmp is not None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tmp / "tree")],
                           capture_output=True)
            shutil.rmtree(tmp, ignore_errors=True)
    print(conditions())


if __name__ == "__main__":
    main()
