"""Benchmark: star-field render + detect, sparse ideal path vs dense path vs an OpenCV peer.

B = 64 frames of 1024 x 768 with ~13 stars each (magnitudes 2-5.5, default SensorConfig: sigma 0.8 px,
5 e-/ADU, 12 bit), run with 1 and 2 Taichi threads (each thread count in its own spawned process,
since Taichi fixes its thread pool at initialisation).

Paths timed (wall clock, best and median of ``--repeats`` batches, after one warm-up batch):
  sparse   render_and_detect_ideal                      (patches around stars only, no frame)
  dense    render_star_fields (uint16) + detect_stars   (full frames)
  opencv   render_star_fields (uint16) + per frame: cv2.threshold + cv2.connectedComponentsWithStats
           + intensity-weighted centroids by np.bincount over the label image (the usual Python peer)
  ccws     cv2.connectedComponentsWithStats alone on pre-thresholded uint8 frames (labelling only)
  noisy    render_star_fields with shot + read + dark + sky noise + detect_stars (k-sigma threshold)

Also prints the centroid error of the ideal paths against the true star positions.

Usage:  python benchmarks/bench_kernels_stars.py [--batch 64] [--repeats 5] [--threads 1 2]
"""

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

W, H, STARS = 1024, 768, 13


def _cases(B, seed=1):
    rs = np.random.default_rng(seed)
    x = rs.uniform(0, W, (B, STARS))
    y = rs.uniform(0, H, (B, STARS))
    mag = rs.uniform(2.0, 5.5, (B, STARS))
    return x, y, mag


def _time(fn, repeats):
    fn()  # warm-up (compilation, page mapping)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts), float(np.median(ts))


def _opencv_detect(img, thr, bg):
    """Per-frame OpenCV labelling + weighted centroids (the peer of detect_stars)."""
    import cv2
    out = []
    for b in range(img.shape[0]):
        binary = (img[b] > thr).view(np.uint8)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8, ltype=cv2.CV_32S)
        w = np.where(lab > 0, img[b].astype(np.float64) - bg, 0.0).ravel()
        lf = lab.ravel()
        sw = np.bincount(lf, weights=w, minlength=n)
        r, c = np.divmod(np.arange(lf.size), W)
        sx = np.bincount(lf, weights=w * (c + 0.5), minlength=n)
        sy = np.bincount(lf, weights=w * (r + 0.5), minlength=n)
        keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= 2) + 1
        out.append((sx[keep] / sw[keep], sy[keep] / sw[keep]))
    return out


def _centroid_errors(det, x, y):
    """Error of each detection whose nearest true star is isolated (> 12 px from others, > 6 px from edges)."""
    d = np.hypot(x[det.case] - det.x[:, None], y[det.case] - det.y[:, None])
    j = d.argmin(axis=1)
    e = d[np.arange(len(j)), j]
    nn = np.hypot(x[:, :, None] - x[:, None, :], y[:, :, None] - y[:, None, :])
    nn[:, np.arange(x.shape[1]), np.arange(x.shape[1])] = np.inf
    iso = (nn.min(axis=2) > 12) & (x > 6) & (x < W - 6) & (y > 6) & (y < H - 6)
    return e[iso[det.case, j]]


def worker(B, repeats):
    import cv2
    from dualsight.kernels import taichi_runtime
    from dualsight.kernels.detect import DetectConfig, detect_stars, render_and_detect_ideal
    from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
    from dualsight.kernels.starfield import render_star_fields

    threads = int(os.environ.get("DUALSIGHT_TI_THREADS", "0")) or os.cpu_count()
    cv2.setNumThreads(threads)
    taichi_runtime.ensure_init()
    x, y, mag = _cases(B)
    cfg = SensorConfig()
    f = flux_from_magnitude(mag, cfg)
    dc = DetectConfig()
    res = {"threads": threads, "B": B}

    res["sparse"] = _time(lambda: render_and_detect_ideal(x, y, f, None, W, H, cfg, dc), repeats)
    out = np.empty((B, H, W), np.uint16)
    res["render_dense"] = _time(lambda: render_star_fields(x, y, f, None, W, H, cfg, out=out), repeats)
    img = render_star_fields(x, y, f, None, W, H, cfg)
    res["detect_dense"] = _time(lambda: detect_stars(img, dc), repeats)
    res["dense"] = _time(lambda: detect_stars(render_star_fields(x, y, f, None, W, H, cfg, out=out), dc), repeats)
    res["opencv"] = _time(lambda: _opencv_detect(render_star_fields(x, y, f, None, W, H, cfg, out=out), 0, 0.0),
                          repeats)
    binary = (img > 0).view(np.uint8) if img.dtype == np.bool_ else (img > 0).astype(np.uint8)
    res["ccws"] = _time(lambda: [cv2.connectedComponentsWithStats(binary[b], connectivity=8)
                                 for b in range(B)], repeats)
    noisy = SensorConfig(read_noise_e=5.0, dark_current_e_per_s=50.0, sky_background_e=20.0, shot_noise=True,
                         bias_adu=10.0)
    seeds = np.arange(B, dtype=np.uint64)
    res["noisy"] = _time(lambda: detect_stars(render_star_fields(x, y, f, None, W, H, noisy, seeds, out=out), dc),
                         max(1, repeats // 2))

    # accuracy of the ideal paths (they agree blob for blob)
    sp = render_and_detect_ideal(x, y, f, None, W, H, cfg, dc)
    de = detect_stars(render_star_fields(x, y, f, None, W, H, cfg), dc)
    res["same_detections"] = bool(np.array_equal(sp.npix, de.npix) and np.array_equal(sp.x, de.x)
                                  and np.array_equal(sp.y, de.y) and np.array_equal(sp.flux, de.flux))
    e = _centroid_errors(sp, x, y)
    res["n_blobs"] = int(len(sp))
    res["n_stars"] = int(x.size)
    res["n_isolated"] = int(e.size)
    res["centroid_err_px"] = {"rms": float(np.sqrt(np.mean(e ** 2))), "p95": float(np.quantile(e, 0.95)),
                              "max": float(e.max())}
    print(json.dumps(res))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        worker(a.batch, a.repeats)
        return
    print(f"B={a.batch} frames of {W}x{H}, {STARS} stars/frame; load average {os.getloadavg()[0]:.2f}")
    print(f"{'threads':>7} {'path':<44} {'ms/frame best':>14} {'median':>8} {'frames/s':>9}")
    labels = [("sparse", "ideal sparse: render_and_detect_ideal"),
              ("dense", "ideal dense: render_star_fields + detect_stars"),
              ("render_dense", "  of which render_star_fields (uint16)"),
              ("detect_dense", "  of which detect_stars"),
              ("opencv", "peer: render + OpenCV CCWS + bincount moments"),
              ("ccws", "  OpenCV connectedComponentsWithStats only"),
              ("noisy", "noisy: render (shot+read+dark+sky) + detect")]
    for t in a.threads:
        env = dict(os.environ, DUALSIGHT_TI_THREADS=str(t), OMP_NUM_THREADS=str(t))
        p = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", "--batch", str(a.batch),
                            "--repeats", str(a.repeats)], env=env, capture_output=True, text=True)
        if p.returncode != 0:
            print(p.stderr)
            raise SystemExit(p.returncode)
        r = json.loads(p.stdout.strip().splitlines()[-1])
        B = r["B"]
        for key, label in labels:
            best, med = r[key]
            print(f"{t:>7} {label:<44} {1e3 * best / B:>14.3f} {1e3 * med / B:>8.3f} {B / best:>9.0f}")
        ce = r["centroid_err_px"]
        print(f"{t:>7} sparse == dense detections: {r['same_detections']}; {r['n_blobs']} blobs from "
              f"{r['n_stars']} stars; centroid error over {r['n_isolated']} isolated stars (px): "
              f"rms {ce['rms']:.4f} p95 {ce['p95']:.4f} max {ce['max']:.4f}")


if __name__ == "__main__":
    main()
