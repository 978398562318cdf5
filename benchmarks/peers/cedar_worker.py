"""cedar-solve as a peer solver: runs INSIDE the benchmark's own venv (benchmarks/.venv-cedar), never in dualsight's.

    benchmarks/.venv-cedar/bin/python benchmarks/peers/cedar_worker.py JOB.json ANSWERS.json

Talks to ``benchmarks/bench_peers.py`` through files only (no pickles): the job is JSON, every frame is a
``.npy`` array of ADC counts (H, W) that the benchmark decoded with dualsight's own reader (so both solvers see
the very same pixels and decoding is excluded from both timings), and the answers are JSON in the layout
that ``dualsight.jobs.kinds.peer_star`` reads.

Job (JSON)::

    {"frames": [{"path": "/abs/image.tiff", "npy": "/tmp/.../0000.npy"}, ...],
     "database": "default_database" (the one cedar-solve ships) or a path to a .npz,
     "fov_estimate_deg": 11.42, "fov_max_error_deg": 0.5 | null, "distortion": 0.0 | [min, max] | null,
     "centroid_kwargs": {...}   (tetra3.get_centroids_from_image; default: its own defaults),
     "solve_kwargs": {...}      (Tetra3.solve_from_centroids),
     "warmup": true, "repeats": 1}

Per frame the timed part is cedar-solve's own centroider ``get_centroids_from_image`` then
``Tetra3.solve_from_centroids`` on that frame, after one untimed warm-up run on the first frame; with
``repeats`` > 1 the median over the repeats is kept.

Conventions of the answers (dualsight's, converted here from tetra3's):
  * ``ra_deg``, ``dec_deg``: boresight (the image centre), ICRS;
  * ``roll_deg``: dualsight's roll (scene/pointing.py): position angle of the image's "up" (decreasing row)
    from celestial north through east.  tetra3's ``Roll`` is the angle of north from "up", counter-clockwise,
    so roll_deg = (-Roll) mod 360 (checked on the eight ESA frames' truth.json: equal to 0.02 deg);
  * ``A``: 9 numbers, row-major ICRS -> camera matrix with dualsight's camera axes (+x increasing column,
    +y increasing row, +z boresight).  tetra3's frame is (boresight, -x, -y); A is rebuilt from RA/Dec/roll.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from importlib.metadata import version

import numpy as np


def attitude_from_tetra3(ra_deg: float, dec_deg: float, roll_tetra_deg: float) -> tuple[float, list[float]]:
    """(dualsight roll in deg, A as 9 floats row-major) from tetra3's RA, Dec and Roll (degrees)."""
    a, d = math.radians(ra_deg), math.radians(dec_deg)
    phi = math.radians((-roll_tetra_deg) % 360.0)
    b = np.array([math.cos(d) * math.cos(a), math.cos(d) * math.sin(a), math.sin(d)])
    east = np.array([-math.sin(a), math.cos(a), 0.0])
    north = np.array([-math.sin(d) * math.cos(a), -math.sin(d) * math.sin(a), math.cos(d)])
    up = math.cos(phi) * north + math.sin(phi) * east            # camera -y on the sky
    left = math.cos(phi) * east - math.sin(phi) * north          # camera -x on the sky
    A = np.stack([-left, -up, b])
    return float((-roll_tetra_deg) % 360.0), [float(x) for x in A.ravel()]


STATUS = {1: "MATCH_FOUND", 2: "NO_MATCH", 3: "TIMEOUT", 4: "CANCELLED", 5: "TOO_FEW"}


def run(job: dict) -> dict:
    import tetra3

    log = logging.getLogger("tetra3.Tetra3")       # a handler of our own: Tetra3() then adds none at INFO
    handler = logging.StreamHandler()
    handler.setLevel(logging.WARNING)
    log.addHandler(handler)
    log.setLevel(logging.WARNING)
    t0 = time.perf_counter()
    t3 = tetra3.Tetra3(load_database=job.get("database", "default_database"))
    t_db = (time.perf_counter() - t0) * 1e3
    props = t3.database_properties
    fov_range = (props.get("min_fov"), props.get("max_fov"))
    fov0 = job.get("fov_estimate_deg")
    if fov0 is not None and None not in fov_range and not fov_range[0] <= fov0 <= fov_range[1]:
        raise SystemExit(f"cedar_worker: the database {job.get('database', 'default_database')} covers fields of "
                         f"{fov_range[0]:g}-{fov_range[1]:g} deg, the frames are {fov0:.2f} deg wide; give a "
                         "database generated for this field (--cedar-database)")
    ckw = dict(job.get("centroid_kwargs") or {})
    skw = dict(job.get("solve_kwargs") or {})
    fov = job.get("fov_estimate_deg")
    fov_err = job.get("fov_max_error_deg")
    dist = job.get("distortion", 0.0)
    if isinstance(dist, list):
        dist = tuple(dist)
    repeats = max(1, int(job.get("repeats", 1)))

    def once(px):
        ta = time.perf_counter_ns()
        cents = tetra3.get_centroids_from_image(px, **ckw)
        tb = time.perf_counter_ns()
        sol = t3.solve_from_centroids(cents, px.shape[:2], fov_estimate=fov, fov_max_error=fov_err,
                                      distortion=dist, **skw)
        tc = time.perf_counter_ns()
        return cents, sol, (tb - ta) / 1e6, (tc - tb) / 1e6

    frames = job["frames"]
    pixels = [np.load(f["npy"], allow_pickle=False) for f in frames]
    if job.get("warmup", True) and pixels:
        once(pixels[0])
    out = []
    for f, px in zip(frames, pixels):
        runs = [once(px) for _ in range(repeats)]
        k = int(np.argsort([r[2] + r[3] for r in runs])[len(runs) // 2])     # the median run
        cents, sol, t_det, t_sol = runs[k]
        status = STATUS.get(sol.get("status"), str(sol.get("status")))
        row = {"path": f["path"], "solved": sol.get("RA") is not None, "status": status,
               "stars_detected": int(len(cents)), "time_ms": t_det + t_sol, "detect_ms": t_det, "solve_ms": t_sol}
        if row["solved"]:
            roll, A = attitude_from_tetra3(float(sol["RA"]), float(sol["Dec"]), float(sol["Roll"]))
            row.update(ra_deg=float(sol["RA"]), dec_deg=float(sol["Dec"]), roll_deg=roll, A=A,
                       stars_matched=int(sol["Matches"]), prob_false_match=float(sol["Prob"]),
                       fov_deg=float(sol["FOV"]), residual_rms_arcsec=float(sol["RMSE"]))
        out.append(row)
    return {
        "method": "cedar-solve",
        "method_version": version("cedar-solve"),
        "settings": {"database": str(job.get("database", "default_database")),
                     "database_properties": {k: (v.tolist() if hasattr(v, "tolist") else v)
                                             for k, v in props.items()},
                     "fov_estimate_deg": fov, "fov_max_error_deg": fov_err, "distortion": job.get("distortion", 0.0),
                     "centroid_kwargs": ckw, "solve_kwargs": skw, "repeats": repeats,
                     "warmup": bool(job.get("warmup", True))},
        "environment": {"python": sys.version.split()[0], "numpy": np.__version__, "scipy": version("scipy"),
                        "threads": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                                                  "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")},
                        "database_load_ms": t_db},
        "frames": out,
    }


def _clean(v):
    """JSON has no NaN: the database's unset ranges become null.  (dualsight.jobs.nightly.text.json_safe does the
    same; this venv has no dualsight to import it from.)"""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print("usage: cedar_worker.py JOB.json ANSWERS.json", file=sys.stderr)
        return 2
    with open(argv[0]) as fh:
        job = json.load(fh)
    doc = _clean(run(job))
    tmp = argv[1] + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(doc, fh, indent=1, allow_nan=False)
    os.replace(tmp, argv[1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
