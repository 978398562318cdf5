"""Benchmark: star detection on noisy rendered frames — dualsight's local detector (``kernels/detect_local.py``)
against the global one (``kernels/detect.py``) and against ``sep`` (Source Extractor as a library).

Frames: the star job's own chain, ``jobs/kinds/star.py: compute_batch(spec, ctx, ids, keep_images=True)`` on the
noisy-sensor example (``examples/star/noisy_sensor.toml``: the reference's 1024 x 768 camera, PSF sigma 0.9 px,
catalog to V 5.5, 10 e- read noise, sky, dark, hot pixels, two glints per frame) and on harder variants
(more read noise and a deeper catalog: fainter stars; a sharper PSF: 1-2 px stars).  Truth: the returned
``field`` (x, y, inside, flux_e per case) and the glints (``kernels.starfield.false_star_lists``), which are
real point sources: a detection within 1.5 px of a catalog star or a glint is not false.

Scores per method and condition:
  complete      catalog stars whose centre is in the frame found within 1.5 px; SNR5-10: of the stars of
                integrated SNR 5-10 (SNR = F / (sigma sqrt(4 pi (s^2 + 1/12))), the matched-filter SNR)
  false/fr      detections farther than 1.5 px from every catalog star, glint and hot pixel, per frame
                (noise peaks, pieces of split stars)
  hot/fr        detections on hot pixels (the sensor's hot-pixel map: the same seeds rendered with every
                other effect off), per frame
  rms           centroid error (px, per axis) of the found stars: all, on the stars every method found
                ('comm'), and on those of SNR >= 10
  ms wall/cpu   time of detection alone on one core (cv2, BLAS and Taichi limited to one thread), best of
                ``--repeats``; CPU time of this process is the fairer number on a shared machine
  chain         the star job's identification (reference voting and robust voting) and SVD attitude on each
                detector's detections: success / confident-wrong rates and the attitude error
Methods:
  local         detect_real(frames, LocalDetectConfig(psf_sigma_px=<sensor's>, gain_e_per_adu=<sensor's>))
  local-auto    the same with the PSF width measured per frame (psf_sigma_px None), as in HIL; both with the
                default fit_engine "taichi" (PSF fits, tile statistics and components compiled:
                kernels/detect_psf_fit.py, kernels/detect_passes.py), and local-auto with fit_engine "numpy"
  local-stated  the width stated (psf_sigma_stated_px = the sensor's, as a camera file's psf_sigma_px gives it to
                hil star): one filter at it, the frame's width measured on that pass's bright stars
  global        detect_stars(frames, the spec's DetectConfig) (k 5, min_pixels 3)
  sep           sep.Background (32 px meshes, 3 x 3 filter) + sep.extract(matched filter = the pixel-
                integrated PSF, err = the background rms map, minarea 1) + sep.winpos (windowed centroid,
                sig = PSF sigma), at 5 sigma and at the lowest threshold of 4, 4.25, ..., 8 whose false
                detections per frame (hot pixels apart: sep keeps them all) do not exceed the local
                detector's ("same false-detection rate").

Usage:  python benchmarks/bench_detect.py [--frames 32] [--repeats 3] [--conditions noisy faint sharp]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
os.environ.setdefault("DUALSIGHT_TI_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOISY = os.path.join(ROOT, "examples", "star", "noisy_sensor.toml")

CONDITIONS = {
    "noisy": ("noisy_sensor.toml as is", {}, {}),
    "faint": ("read noise 30 e-, catalog to V 6.5", {"read_noise_e": 30.0}, {"mag_limit": 6.5}),
    "sharp": ("PSF sigma 0.5 px, read noise 30 e-, V 6.5", {"read_noise_e": 30.0, "psf_sigma_px": 0.5},
              {"mag_limit": 6.5}),
}


# ============================================================================ frames
def render(condition: str, n: int, seed: int = 11):
    """(images (n, H, W) uint16, truth dict, spec, compute_batch output, context) of ``n`` cases of a condition.

    truth: x, y, valid, inside, flux_e (n, S) of the catalog stars; glint_x, glint_y (n, G) of the glints; hot
    (n, H, W) bool, the hot pixels (the same seeds rendered with every other effect off)."""
    import dataclasses

    from dualsight.jobs.kinds import star as jstar
    from dualsight.jobs.engine.specs import preset_and_config
    from dualsight.kernels.starfield import false_star_lists, render_star_fields

    _, sensor_over, catalog_over = CONDITIONS[condition]
    d, source = preset_and_config(jstar.PRESETS, None, NOISY)
    d["seed"] = seed
    d["sensor"] = {**d.get("sensor", {}), **sensor_over}
    d["catalog"] = {**d.get("catalog", {}), **catalog_over}
    spec = jstar.spec_from_dict(d, source=source)
    ctx = jstar.make_context(spec)
    out = jstar.compute_batch(spec, ctx, np.arange(n, dtype=np.int64), keep_images=True)
    f = out["field"]
    seeds = out["draw"]["noise_seed"]
    W, H = spec.camera.width, spec.camera.height
    glints = false_star_lists(seeds, W, H, spec.sensor)
    hot_only = dataclasses.replace(spec.sensor, shot_noise=False, read_noise_e=0.0, sky_background_e=0.0,
                                   dark_current_e_per_s=0.0, false_stars_per_frame=0)
    z = np.zeros((n, 1))
    hot = render_star_fields(z, z, z, None, W, H, hot_only, seeds, psf=ctx.psf) > 0
    truth = {"x": f.x, "y": f.y, "valid": f.valid, "inside": f.inside & f.valid, "flux_e": f.flux_e,
             "glint_x": glints[0], "glint_y": glints[1], "hot": hot}
    return out["rendered"].images, truth, spec, out, ctx


def snr_of(truth, sensor) -> np.ndarray:
    """Integrated (matched-filter) SNR of each true star: F / (sigma sqrt(4 pi (s^2 + 1/12))), sigma the
    pixel noise in e- (sky + dark + read + quantisation), s the PSF sigma."""
    var = sensor.sky_background_e + sensor.dark_current_e_per_s * sensor.exposure_s + sensor.read_noise_e ** 2 \
        + sensor.gain_e_per_adu ** 2 / 12.0
    s2 = sensor.psf_sigma_px ** 2 + 1.0 / 12.0
    return truth["flux_e"] / math.sqrt(var * 4 * math.pi * s2)


# ============================================================================ scoring
def score(xs, ys, truth, snr, radius=1.5):
    """Match per-frame detections (lists of arrays, continuous pixel coordinates) to the truth.

    A detection within ``radius`` of a catalog star or a glint is real; of the others, those within
    ``radius`` of a hot pixel are counted apart (``hot_per_frame``), the rest are ``false_per_frame``."""
    B, S = truth["x"].shape
    found = np.zeros((B, S), bool)
    err = np.full((B, S, 2), np.nan)
    false = on_hot = 0
    for b in range(B):
        x, y = np.asarray(xs[b], np.float64), np.asarray(ys[b], np.float64)
        if x.size == 0:
            continue
        tx = np.where(truth["valid"][b], truth["x"][b], np.nan)
        ty = np.where(truth["valid"][b], truth["y"][b], np.nan)
        gx, gy = np.asarray(truth["glint_x"][b]), np.asarray(truth["glint_y"][b])
        d = np.hypot(x[:, None] - tx[None], y[:, None] - ty[None])
        d = np.where(np.isnan(d), np.inf, d)
        dg = np.hypot(x[:, None] - gx[None], y[:, None] - gy[None]).min(1) if gx.size else np.full(x.size, np.inf)
        hr, hc = np.nonzero(truth["hot"][b])
        dh = (np.hypot(x[:, None] - hc[None] - 0.5, y[:, None] - hr[None] - 0.5).min(1) if hr.size
              else np.full(x.size, np.inf))
        lone = (d.min(1) > radius) & (dg > radius)
        on_hot += int((lone & (dh <= radius)).sum())
        false += int((lone & (dh > radius)).sum())
        j = d.argmin(0)                                     # each true star: its nearest detection
        dj = d[j, np.arange(S)]
        ok = dj <= radius
        found[b, ok] = True
        err[b, ok, 0] = x[j[ok]] - tx[ok]
        err[b, ok, 1] = y[j[ok]] - ty[ok]
    ins = truth["inside"]
    mid = ins & (snr >= 5) & (snr < 10)
    return {"completeness": float(found[ins].mean()), "compl_5_10": float(found[mid].mean()) if mid.any() else np.nan,
            "false_per_frame": false / B, "hot_per_frame": on_hot / B, "found": found & ins, "err": err,
            "n_true": int(ins.sum()), "n_5_10": int(mid.sum())}


def rms(sc, mask):
    m = mask & sc["found"]
    return float(np.sqrt(np.nanmean(sc["err"][m] ** 2))) if m.any() else float("nan")


def per_frame(det):
    return ([det.x[det.offsets[b]:det.offsets[b + 1]] for b in range(det.n_frames)],
            [det.y[det.offsets[b]:det.offsets[b + 1]] for b in range(det.n_frames)])


# ============================================================================ methods
def run_local(images, sensor, auto=False, fit_engine=None, stated=False):
    from dualsight.kernels.detect_local import LocalDetectConfig, detect_real

    engine = {} if fit_engine is None else {"fit_engine": fit_engine}       # None: the default ("taichi")
    cfg = LocalDetectConfig(psf_sigma_px=None if auto or stated else sensor.psf_sigma_px,
                            psf_sigma_stated_px=sensor.psf_sigma_px if stated else None,
                            gain_e_per_adu=sensor.gain_e_per_adu, **engine)
    sat = min(sensor.full_well_e / sensor.gain_e_per_adu + sensor.bias_adu, sensor.max_adu) - 3 * (
        sensor.read_noise_e / sensor.gain_e_per_adu)
    det = detect_real(images, cfg, saturation_adu=sat)
    return per_frame(det), det


def run_global(images, detect_cfg):
    from dualsight.kernels.detect import detect_stars

    det = detect_stars(images, detect_cfg)
    return per_frame(det), det


def sep_kernel(sigma: float) -> np.ndarray:
    from dualsight.kernels.detect_psf import psf_kernel_1d

    k = psf_kernel_1d(sigma)
    return np.outer(k, k).astype(np.float32)


def run_sep(images, sigma, thresh, winpos=True):
    """sep per frame: background, matched-filter extraction, windowed centroids (0-based pixel centres -> +0.5)."""
    import sep

    kern = sep_kernel(sigma)
    xs, ys = [], []
    for b in range(images.shape[0]):
        data = np.ascontiguousarray(images[b], dtype=np.float32)
        bkg = sep.Background(data, bw=32, bh=32, fw=3, fh=3)
        sub = data - bkg.back()
        objs = sep.extract(sub, thresh, err=bkg.rms(), minarea=1, filter_kernel=kern, filter_type="matched")
        x, y = objs["x"].astype(np.float64), objs["y"].astype(np.float64)
        if winpos and x.size:
            xw, yw, flag = sep.winpos(sub, x, y, np.full(x.size, sigma))
            good = flag == 0
            x, y = np.where(good, xw, x), np.where(good, yw, y)
        xs.append(x + 0.5)
        ys.append(y + 0.5)
    return xs, ys


def best_time(fn, repeats):
    """(best wall time, best CPU time of this process) of ``repeats`` calls (s)."""
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


def chain(det, spec, ctx, out, weights=False):
    """The star job's identification and attitude on these detections: (success, confident wrong, median and
    95th percentile total error in arcsec) with the reference's voting and with the robust one."""
    from dualsight.nav.errors import STATUS_NAMES
    from dualsight.nav.observations import observations
    from dualsight.nav.star_solution import centroid_weights, identify, solve

    B = det.n_frames
    A_true = out["draw"]["A_true"]
    obs = observations(det, B, spec.camera)
    res = {}
    for name, voting in (("paper", spec.voting), ("robust", spec.robust)):
        if voting is None:
            continue
        ident = identify(obs, ctx.catalog.unit, ctx.pairs, voting)
        w = centroid_weights(det, obs, 0.02) if weights else None
        sol = solve(obs, ident, ctx.catalog.unit, A_true, spec.error_frame, weights=w)
        st = np.asarray(STATUS_NAMES, dtype=object)[sol.status]
        e = sol.total_err[st == "success"] * 206264.806
        res[name] = ((st == "success").mean(), (st == "confident_wrong").mean(),
                     float(np.median(e)) if e.size else np.nan, float(np.percentile(e, 95)) if e.size else np.nan)
    return res


# ============================================================================ main
def bench(condition, frames, repeats, out=print, sil=True):
    import cv2

    cv2.setNumThreads(1)
    images, truth, spec, run, ctx = render(condition, frames)
    sensor = spec.sensor
    snr = snr_of(truth, sensor)
    B = images.shape[0]
    rows = []
    (lx, ly), ldet = run_local(images, sensor)
    rows.append(["local", score(lx, ly, truth, snr), best_time(lambda: run_local(images, sensor), repeats)])
    (ax, ay), adet = run_local(images, sensor, auto=True)
    rows.append(["local-auto", score(ax, ay, truth, snr),
                 best_time(lambda: run_local(images, sensor, auto=True), repeats)])
    (cx, cy), _ = run_local(images, sensor, stated=True)
    rows.append(["local-stated", score(cx, cy, truth, snr),
                 best_time(lambda: run_local(images, sensor, stated=True), repeats)])
    (tx, ty), _ = run_local(images, sensor, auto=True, fit_engine="numpy")
    rows.append(["local-auto, numpy engine", score(tx, ty, truth, snr),
                 best_time(lambda: run_local(images, sensor, auto=True, fit_engine="numpy"), repeats)])
    (gx, gy), gdet = run_global(images, spec.detect)
    rows.append([f"global (k {spec.detect.k_sigma:g}, min_px {spec.detect.min_pixels})", score(gx, gy, truth, snr),
                 best_time(lambda: run_global(images, spec.detect), repeats)])
    try:
        import sep  # noqa: F401
    except ImportError:
        out("sep not installed (pip install sep): its rows are skipped")
    else:
        s = sensor.psf_sigma_px
        target = rows[0][1]["false_per_frame"]
        t_sep = best_time(lambda: run_sep(images, s, 5.0), repeats)
        sx, sy = run_sep(images, s, 5.0)
        rows.append(["sep k=5", score(sx, sy, truth, snr), t_sep])
        for th in np.arange(4.0, 8.01, 0.25):       # same false-detection rate (hot pixels counted apart)
            sc = score(*run_sep(images, s, float(th)), truth, snr)
            if sc["false_per_frame"] <= target:
                rows.append([f"sep k={th:.2f}", sc, t_sep])
                break
    common = np.logical_and.reduce([r[1]["found"] for r in rows])
    desc = CONDITIONS[condition][0]
    noise_e = math.sqrt(sensor.sky_background_e + sensor.dark_current_e_per_s * sensor.exposure_s
                        + sensor.read_noise_e ** 2)
    out(f"\n{condition}: {desc}; {B} frames {spec.camera.width}x{spec.camera.height} uint16, PSF sigma "
        f"{sensor.psf_sigma_px} px, noise {noise_e:.1f} e- ({noise_e / sensor.gain_e_per_adu:.2f} ADU), "
        f"{rows[0][1]['n_true']} catalog stars in frame ({rows[0][1]['n_5_10']} of SNR 5-10), "
        f"{truth['hot'].sum() / B:.1f} hot pixels/frame, cores=1")
    out(f"{'method':24s} {'complete':>8s} {'SNR5-10':>8s} {'false/fr':>8s} {'hot/fr':>7s} {'rms all':>8s} "
        f"{'rms comm':>8s} {'rms>=10':>8s} {'ms wall':>8s} {'ms cpu':>7s}")
    for name, sc, (tw, tc) in rows:
        out(f"{name:24s} {sc['completeness']:8.3f} {sc['compl_5_10']:8.3f} {sc['false_per_frame']:8.2f} "
            f"{sc['hot_per_frame']:7.2f} {rms(sc, sc['found']):8.4f} {rms(sc, common):8.4f} "
            f"{rms(sc, common & (snr >= 10)):8.4f} {1e3 * tw / B:8.1f} {1e3 * tc / B:7.1f}")
    out("  (rms: centroid error per axis, px; 'comm' = on the stars every method found; hot/fr: detections on "
        "hot pixels)")
    if sil:
        out("  star chain on these detections (success / confident wrong / median, p95 error arcsec):")
        for name, det, w in (("global", gdet, False), ("local", ldet, False), ("local + weights", ldet, True)):
            r = chain(det, spec, ctx, run, weights=w)
            out("    " + f"{name:16s}" + "  ".join(f"{k}: {v[0]:.3f} / {v[1]:.3f} / {v[2]:.2f}, {v[3]:.2f}"
                                                  for k, v in r.items()))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=list(CONDITIONS))
    ap.add_argument("--no-chain", action="store_true", help="skip identification/attitude on the detections")
    a = ap.parse_args(argv)
    for c in a.conditions:
        bench(c, a.frames, a.repeats, sil=not a.no_chain)
    return 0


if __name__ == "__main__":
    sys.exit(main())
