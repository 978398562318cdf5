"""Benchmark: what the default (``local``) detector's passes over every pixel cost on ONE core with this project's
stack, against what the whole detector costs (issue 24, point 1: one frame end to end <= 5 ms).

The detector's maths (``kernels/detect_local.py``, steps 1-3) needs some passes over every pixel whatever the code
around them does: the tiles' quarter samples gathered and sorted, the level and noise maps interpolated from the
tiles, the background subtracted, the separable matched filter, Z = F / sigma, and the threshold scan; the PSF-width
pass repeats the binning and the filter on the 2 x 2-binned frame. This benchmark times each of them alone, with the
library call the detector uses (numpy, OpenCV), on the frames ``bench_hil_speed.py frame --rendered N`` renders (the
issue's sensor-noise frames), and sums them. The rest of the detector's time is per tile (the clipping windows) and
per candidate (hot-pixel tests, PSF fits, in two passes) and the numpy calls that orchestrate them. Then the matched
filter, the largest pass, written as a Taichi kernel (the project's compiled engine; row loops over an ndarray and
over a field): Taichi's CPU backend does not vectorise such a stencil, so a fused compiled pass (background, filter
and threshold in one kernel) would be slower than OpenCV's separate SIMD passes, not faster. Last, the detector
itself (``detect_real(frame, LocalDetectConfig(fit_engine="taichi"))``, what a batch of >= 1,024 images runs).

Wall time of the process on one thread (OMP / BLAS / Taichi threads and OpenCV at 1), median over the frames of the
mean of ``--repeats`` calls after one warm-up call. Read it as ratios: absolute times on a shared machine move
with its load (printed).

Usage:  python benchmarks/bench_detect_floor.py [--frames 20] [--repeats 20]
"""

# (no `from __future__ import annotations`: Taichi reads the kernels' annotations as objects)

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

for _v in ("DUALSIGHT_TI_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def per_call_ms(f, repeats: int) -> float:
    """Mean wall time of ``repeats`` calls of ``f`` after one unmeasured call, ms."""
    f()
    t0 = time.perf_counter()
    for _ in range(repeats):
        f()
    return (time.perf_counter() - t0) / repeats * 1e3


def taichi_filters(H: int, W: int, taps: int):
    """The separable matched filter as two Taichi kernels (interior only, as the detector's cost would be): row
    loops over ndarrays, and the same over fields. Returns (ndarray_kernel(R, k, T, F), field_kernel(k), fields)."""
    from dualsight.kernels.taichi_runtime import ensure_init

    ti = ensure_init()
    h = taps // 2

    @ti.kernel
    def sep_ndarray(R: ti.types.ndarray(dtype=ti.f32, ndim=2), k: ti.types.ndarray(dtype=ti.f32, ndim=1),
                    T: ti.types.ndarray(dtype=ti.f32, ndim=2), F: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        for r in range(H):                       # one task per row; the inner loop runs along the row
            for c in range(W - 2 * h):
                acc = 0.0
                for t in ti.static(range(taps)):
                    acc += k[t] * R[r, c + t]
                T[r, c + h] = acc
        for r in range(H - 2 * h):
            for c in range(W):
                acc = 0.0
                for t in ti.static(range(taps)):
                    acc += k[t] * T[r + t, c]
                F[r + h, c] = acc

    Rf, Tf, Ff = (ti.field(ti.f32, shape=(H, W)) for _ in range(3))
    kf = ti.field(ti.f32, shape=taps)

    @ti.kernel
    def sep_field():
        for r in range(H):
            for c in range(W - 2 * h):
                acc = 0.0
                for t in ti.static(range(taps)):
                    acc += kf[t] * Rf[r, c + t]
                Tf[r, c + h] = acc
        for r in range(H - 2 * h):
            for c in range(W):
                acc = 0.0
                for t in ti.static(range(taps)):
                    acc += kf[t] * Tf[r + t, c]
                Ff[r + h, c] = acc

    return sep_ndarray, sep_field, (Rf, Tf, Ff, kf)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20, help="rendered frames (default 20, as bench_hil_speed)")
    ap.add_argument("--repeats", type=int, default=20, help="timed calls per pass and frame (default 20)")
    a = ap.parse_args()

    import cv2
    import numpy as np

    cv2.setNumThreads(1)
    import bench_hil_speed
    from dualsight.kernels import detect_background as db
    from dualsight.kernels import detect_local as dl
    from dualsight.kernels.detect_psf import psf_kernel_1d

    print(f"cores {os.cpu_count()}, one thread; load average {os.getloadavg()[0]:.2f}")
    paths, _, _ = bench_hil_speed.rendered_frames(a.frames, 5.5)
    cfg = dl.LocalDetectConfig(fit_engine="taichi")
    tile = cfg.tile_px
    rows: dict[str, list[float]] = {}
    widths = []
    sep_nd = sep_fd = None
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        H, W = img.shape
        det = dl.detect_real(img[None], cfg, saturation_adu=float(np.iinfo(img.dtype).max))
        s = float(det.psf_sigma_px[0])                       # the width the frame's final pass uses
        widths.append(s)
        k = psf_kernel_1d(s).astype(np.float32)
        ny, nx = H // tile, W // tile
        level, sig = db.tile_background(img, tile, cfg.clip_sigma, cfg.clip_iters, cfg.mesh_filter, "taichi")
        inv_t = (1.0 / np.maximum(sig, cfg.noise_floor_adu)).astype(np.float32)
        bg = db.interpolate_tiles(level, tile, H, W)
        inv = db.interpolate_tiles(inv_t, tile, H, W)
        R = cv2.subtract(img, bg, dtype=cv2.CV_32F)
        F = cv2.sepFilter2D(R, cv2.CV_32F, k, k, borderType=cv2.BORDER_CONSTANT)
        Z = cv2.multiply(F, inv)
        h2, w2 = H // 2, W // 2
        Rb = cv2.resize(R, (w2, h2), interpolation=cv2.INTER_AREA)
        kb = psf_kernel_1d(0.5 * cfg.psf_sigma_init_px).astype(np.float32)
        samples = np.ascontiguousarray(
            img[::2, ::2].reshape(ny, tile // 2, nx, tile // 2).transpose(0, 2, 1, 3)).reshape(ny * nx, -1)
        passes = {
            "tiles: quarter samples gathered": lambda: np.ascontiguousarray(
                img[::2, ::2].reshape(ny, tile // 2, nx, tile // 2).transpose(0, 2, 1, 3)).reshape(ny * nx, -1),
            "tiles: samples sorted": lambda: np.sort(samples, axis=1, kind=db.row_sort_kind(img.dtype)),
            "level map interpolated": lambda: db.interpolate_tiles(level, tile, H, W),
            "noise map interpolated": lambda: db.interpolate_tiles(inv_t, tile, H, W),
            "background subtracted": lambda: cv2.subtract(img, bg, dtype=cv2.CV_32F),
            f"matched filter, OpenCV ({k.size} taps)": lambda: cv2.sepFilter2D(R, cv2.CV_32F, k, k,
                                                                               borderType=cv2.BORDER_CONSTANT),
            "Z = F x (1 / sigma)": lambda: cv2.multiply(F, inv),
            "threshold scan (Z > k)": lambda: np.flatnonzero(Z > cfg.k_sigma),
            "width pass: 2 x 2 binning": lambda: cv2.resize(R, (w2, h2), interpolation=cv2.INTER_AREA),
            "width pass: binned matched filter": lambda: cv2.sepFilter2D(Rb, cv2.CV_32F, kb, kb,
                                                                         borderType=cv2.BORDER_CONSTANT),
        }
        for name, f in passes.items():
            rows.setdefault(name, []).append(per_call_ms(f, a.repeats))
        if sep_nd is None:
            sep_nd, sep_fd, (Rf, Tf, Ff, kf) = taichi_filters(H, W, k.size)
            T_, F_ = np.zeros_like(R), np.zeros_like(R)
        if k.size == kf.shape[0]:                     # the kernels are compiled for the first frame's tap count
            kf.from_numpy(k)
            Rf.from_numpy(R)
            rows.setdefault("matched filter, Taichi ndarray", []).append(
                per_call_ms(lambda: sep_nd(R, k, T_, F_), max(3, a.repeats // 4)))
            rows.setdefault("matched filter, Taichi field", []).append(
                per_call_ms(sep_fd, max(3, a.repeats // 4)))
            hh = k.size // 2
            err = float(np.abs(F_[hh:-hh, hh:-hh] - F[hh:-hh, hh:-hh]).max())
            assert err < 1e-4 * float(np.abs(F).max()), f"the Taichi filter differs from OpenCV's by {err}"
        rows.setdefault("the detector, detect_real", []).append(
            per_call_ms(lambda: dl.detect_real(img[None], cfg, saturation_adu=float(np.iinfo(img.dtype).max)),
                        max(3, a.repeats // 4)))
    med = {name: statistics.median(v) for name, v in rows.items()}
    print(f"{len(paths)} rendered 1024 x 1024 frames (bench_hil_speed --rendered {a.frames}: sensor noise, hot "
          f"pixels); PSF width measured {min(widths):.2f}-{max(widths):.2f} px; ms per frame, one thread, median")
    floor = 0.0
    for name, v in med.items():
        if name.startswith("matched filter, Taichi") or name.startswith("the detector"):
            continue
        floor += v
        print(f"  {name:42s} {v:6.3f}")
    print(f"  {'sum: the passes over every pixel':42s} {floor:6.3f}")
    cv = next(v for n, v in med.items() if n.startswith("matched filter, OpenCV"))
    for name in ("matched filter, Taichi ndarray", "matched filter, Taichi field"):
        if name in med:
            print(f"  {name:42s} {med[name]:6.3f}  ({med[name] / cv:.1f}x OpenCV's)")
    print(f"  {'the detector, detect_real':42s} {med['the detector, detect_real']:6.3f}  "
          f"({med['the detector, detect_real'] / floor:.2f}x the passes' sum)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
