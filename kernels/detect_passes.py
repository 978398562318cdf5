"""The real-sensor detector's full-frame passes as compiled Taichi kernels (:mod:`dualsight.kernels.detect_local`
with ``fit_engine`` "taichi", the default), reading the frame in its own dtype (uint8, uint16, float32, float64):

* :func:`tile_window_sums`: the last sigma-clipping window of every background tile
  (:func:`dualsight.kernels.detect_background.tile_background`, step 1 of the detector's docstring): per tile, the
  count, sum and sum of squares of d = v - level over the pixels with |d| <= clip sigma, accumulated in float64, in
  one pass over the frame as it lies in memory (the numpy path, ``_last_window``: a tile-major copy of the frame and
  eight float32 passes over it; 1.06 ms against 0.43 ms on a 1024 x 768 16-bit frame, one core, 2026-11-27).

Only passes a compiled loop does faster than numpy/OpenCV's vectorised calls live here: the bilinear background
and noise maps and the residual (OpenCV's ``resize`` and one subtraction, ~0.36 ms) took 4.2 ms as a Taichi loop
with the interpolation per pixel (measured 2026-11-27), the matched filter is OpenCV's ``sepFilter2D`` (SIMD).
Each kernel runs its loop serially (one frame is ~0.3-0.4 ms of work: a parallel launch's round trip through
Taichi's thread pool, ~0.1 ms, costs more than a second thread gains; frames run in parallel in the workers).
Equal to the numpy path up to rounding (float64 sums here, float32 there; tests/test_detect_passes.py)."""

import numpy as np

from dualsight.kernels.taichi_runtime import KernelCache

_PIXEL = {np.dtype(np.uint8).str: "u8", np.dtype(np.uint16).str: "u16", np.dtype(np.float32).str: "f32",
          np.dtype(np.float64).str: "f64"}


def pixel_dtype_supported(dtype) -> bool:
    """Whether the kernels read frames of ``dtype`` directly (uint8, uint16, float32, float64)."""
    return np.dtype(dtype).str in _PIXEL


def _build_window(dtype):
    import taichi as ti   # here, not at import: the CLI imports this module without running a kernel

    pt = getattr(ti, _PIXEL[np.dtype(dtype).str])
    f64 = ti.f64

    @ti.kernel
    def window(a: ti.types.ndarray(dtype=pt, ndim=2), level: ti.types.ndarray(dtype=f64, ndim=1),
               sig: ti.types.ndarray(dtype=f64, ndim=1), clip: f64, tile: ti.i32, nx: ti.i32,
               out: ti.types.ndarray(dtype=f64, ndim=2)):
        ti.loop_config(serialize=True)
        for k in range(level.shape[0]):
            r0 = (k // nx) * tile
            c0 = (k % nx) * tile
            c = level[k]
            w = clip * sig[k]
            n, s1, s2 = f64(0.0), f64(0.0), f64(0.0)
            for i in range(tile):
                for j in range(tile):
                    d = ti.cast(a[r0 + i, c0 + j], f64) - c
                    m = ti.abs(d) <= w
                    n += ti.select(m, f64(1.0), f64(0.0))
                    s1 += ti.select(m, d, f64(0.0))
                    s2 += ti.select(m, d * d, f64(0.0))
            out[k, 0] = n
            out[k, 1] = s1
            out[k, 2] = s2

    return window


_KERNELS = KernelCache({"window": _build_window})    # each built on first use


def tile_window_sums(a: np.ndarray, level: np.ndarray, sig: np.ndarray, clip: float, tile: int) -> np.ndarray:
    """Per tile of the (ny tile, nx tile) frame ``a`` (uint8, uint16, float32 or float64; ADU; C-contiguous), tiles
    numbered row-major: (T, 3) float64 (count, sum of d, sum of d^2) over its pixels with |d| <= ``clip`` x ``sig``,
    d = v - ``level`` ((T,) each, ADU): one window of the tile's sigma clipping
    (:func:`dualsight.kernels.detect_background.tile_background`)."""
    ny, nx = a.shape[0] // tile, a.shape[1] // tile
    out = np.zeros((ny * nx, 3))
    _KERNELS.get("window", a.dtype)(np.ascontiguousarray(a), np.ascontiguousarray(level, np.float64),
                                    np.ascontiguousarray(sig, np.float64), float(clip), int(tile), int(nx), out)
    return out

