"""Proximity pipeline speed: render + blobber frames/s for the reference's 3U CubeSat (Table 1 camera,
1024 x 768) at 1, 10 and 100 m, both render modes, 1 and 2 Taichi threads, plus the labelling step
against its peer, OpenCV's ``connectedComponentsWithStats``.

Run by hand (never a timed test):

    .venv/bin/python benchmarks/bench_prox.py            # both thread counts (one subprocess each)
    .venv/bin/python benchmarks/bench_prox.py --threads 2 --batch 32 --repeats 5

Each configuration renders ``--batch`` frames of random orientations (uniform on SO(3)) at the
given range, runs the blobber (paper estimator for paper images, subpixel for accurate images),
and reports the best of ``--repeats`` timings (the machine may be shared) as frames per second,
with the split render / blobber.  Target: >= 100 frames/s for render + blobber.

Labelling peer: ``label ms`` is dualsight's threshold + labelling + moments (kernels/blobs.py) per
frame; ``cv2 ms`` is ``cv2.connectedComponentsWithStats`` alone on the already-thresholded uint8
frame (labels + areas/boxes/centroids, no second moments).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RANGES = (1.0, 10.0, 100.0)


def _best(fn, repeats):
    ts = []
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def run_one(batch: int, repeats: int) -> dict:
    import cv2

    from dualsight.catalogs.areas import area_table
    from dualsight.kernels import points as KP
    from dualsight.kernels.taichi_runtime import ensure_init
    from dualsight.kernels.blobs import label_blobs
    from dualsight.nav.blobber import BlobberConfig, run_blobber
    from dualsight.scene.attitude import quat_to_dcm, random_quaternions
    from dualsight.scene.motion import place_body
    from dualsight.scene.satellite import load_satellite

    ensure_init()
    cfg = load_satellite(ROOT / "examples" / "satellites" / "cubesat_3u.toml")
    cam = cfg.camera.camera
    geom = {"paper": cfg.point_cloud(), "accurate": cfg.mesh()}
    mat = cfg.materials()
    table = area_table(cfg)
    rng = np.random.default_rng(0)
    Rb = quat_to_dcm(random_quaternions(rng, batch))
    rows = []
    for r in RANGES:
        fp = place_body(cfg, Rb, np.tile([0.0, 0.0, r], (batch, 1)), cfg.camera.light_direction)
        for mode in ("paper", "accurate"):
            est = "paper" if mode == "paper" else "subpixel"
            bcfg = BlobberConfig(estimator=est)

            def render():
                return KP.render(mode, geom[mode], mat, fp.R, fp.t, fp.light, cam)

            img, cov = render()                                   # warm-up (compilation)
            run_blobber(img, cam, table, bcfg, coverage=cov)
            t_render, (img, cov) = _best(render, repeats)
            t_blob, res = _best(lambda: run_blobber(img, cam, table, bcfg, coverage=cov), repeats)
            t_all, _ = _best(lambda: _pipeline(render, run_blobber, cam, table, bcfg), repeats)
            # labelling step alone vs OpenCV
            t_lab, _ = _best(lambda: label_blobs(img, 0.0, None, 8), repeats)

            masks = (img > 0).astype(np.uint8)                    # thresholded outside the timing

            def opencv():
                for b in range(batch):                           # OpenCV labels one frame per call
                    cv2.connectedComponentsWithStats(masks[b], connectivity=8)

            t_cv, _ = _best(opencv, repeats)
            rel = np.nanmean(np.abs(res.range_est - r) / r)
            rows.append(dict(range_m=r, mode=mode, estimator=est, fps=batch / t_all,
                             render_ms=1e3 * t_render / batch, blobber_ms=1e3 * t_blob / batch,
                             label_ms=1e3 * t_lab / batch, opencv_label_ms=1e3 * t_cv / batch,
                             blob_px=float(np.mean(res.n_pixels)), range_rel_err=float(rel)))
    return dict(threads=os.environ.get("DUALSIGHT_TI_THREADS", "all"), batch=batch, rows=rows)


def _pipeline(render, run_blobber, cam, table, bcfg):
    img, cov = render()
    return run_blobber(img, cam, table, bcfg, coverage=cov)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json", help="also write the results to this JSON file")
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(run_one(a.batch, a.repeats)))
        return 0
    results = []
    for th in a.threads:  # Taichi's thread count is fixed at init: one process per setting
        env = dict(os.environ, DUALSIGHT_TI_THREADS=str(th))
        p = subprocess.run([sys.executable, __file__, "--child", "--batch", str(a.batch), "--repeats",
                            str(a.repeats)], env=env, capture_output=True, text=True, check=True)
        results.append(json.loads(p.stdout.strip().splitlines()[-1]))
    print(f"3U CubeSat, 1024x768, batch {a.batch}, best of {a.repeats}; fps = render + blobber")
    print(f"{'thr':>3} {'range':>6} {'mode':>8} {'fps':>7} {'render ms':>9} {'blobber ms':>10} {'label ms':>8} "
          f"{'cv2 ms':>7} {'blob px':>8} {'range err':>9}")
    for res in results:
        for r in res["rows"]:
            print(f"{res['threads']:>3} {r['range_m']:6.0f} {r['mode']:>8} {r['fps']:7.0f} {r['render_ms']:9.2f} "
                  f"{r['blobber_ms']:10.2f} {r['label_ms']:8.2f} {r['opencv_label_ms']:7.2f} {r['blob_px']:8.0f} "
                  f"{100 * r['range_rel_err']:8.1f}%")
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
