"""Optional sensor effects on rendered proximity images (Taichi CPU), batched over B frames.

Order: Gaussian PSF blur (separable, ``blur_rows`` along x then y, edges clamped) -> scale by ``gain``
(image units to DN) -> additive Gaussian read noise (DN) -> quantisation to integers in [0, 2^bits - 1]
(``noise_quant``, one (frame, row) per task).

Read noise is counter-based (:mod:`dualsight.kernels.rng`): pixel (row, col) of a frame with seed ``s``
gets the Box-Muller normal of the uniforms of (key0, row * W + col) and (key1, row * W + col), with
key0 = ``stream_key(s, STREAM_PROX_READ, 0)`` and key1 = ``derived_key(key0)``, so a frame is the same
whatever batch, position or thread renders it (the prox replay relies on it).
"""

import math

import numpy as np
import taichi as ti

from dualsight.kernels import rng
from dualsight.kernels.taichi_runtime import KernelCache
from dualsight.kernels.prox_geometry import as_f32

__all__ = ["gaussian_weights", "apply_sensor"]

f32 = ti.f32
nd = ti.types.ndarray
_KERNELS = KernelCache()      # builders registered below


def _build_blur_rows(_dtype=None):
    @ti.kernel
    def blur_rows(src: nd(dtype=f32, ndim=3), dst: nd(dtype=f32, ndim=3), w: nd(dtype=f32, ndim=1),
                  axis: ti.i32):
        B, H, W = src.shape[0], src.shape[1], src.shape[2]
        r = (w.shape[0] - 1) // 2
        for b, y in ti.ndrange(B, H):
            for x in range(W):
                s = 0.0
                for k in range(-r, r + 1):
                    if axis == 1:
                        xx = ti.min(ti.max(x + k, 0), W - 1)
                        s += w[k + r] * src[b, y, xx]
                    else:
                        yy = ti.min(ti.max(y + k, 0), H - 1)
                        s += w[k + r] * src[b, yy, x]
                dst[b, y, x] = s
    return blur_rows


def _build_noise_quant(_dtype=None):
    @ti.kernel
    def noise_quant(img: nd(dtype=f32, ndim=3), seeds: nd(dtype=ti.u64, ndim=1), read_noise: f32,
                    gain: f32, maxdn: f32):
        B, H, W = img.shape[0], img.shape[1], img.shape[2]
        for b, y in ti.ndrange(B, H):
            key0 = rng.stream_key(seeds[b], rng.STREAM_PROX_READ, 0)
            key1 = rng.derived_key(key0)
            for x in range(W):
                v = img[b, y, x] * gain
                if read_noise > 0:
                    g = rng.normal_box_muller(key0, key1, y * W + x)
                    v += read_noise * ti.cast(g, f32)
                if maxdn > 0:
                    v = ti.min(ti.max(ti.round(v), 0.0), maxdn)
                img[b, y, x] = v
    return noise_quant


_KERNELS.builders.update({"blur_rows": _build_blur_rows, "noise_quant": _build_noise_quant})


def gaussian_weights(sigma_px: float) -> np.ndarray:
    """Normalised 1-D Gaussian taps for a PSF of standard deviation ``sigma_px`` (px): (2r+1,) float32,
    radius r = ceil(3 sigma) (at least 1)."""
    r = max(int(math.ceil(3.0 * sigma_px)), 1)
    k = np.arange(-r, r + 1, dtype=np.float64)
    w = np.exp(-0.5 * (k / sigma_px) ** 2)
    return (w / w.sum()).astype(np.float32)


def apply_sensor(images, *, psf_sigma_px: float = 0.0, read_noise: float = 0.0, gain: float = 1.0,
                 bits: int | None = None, seeds=None) -> np.ndarray:
    """Sensor effects on rendered images, returning a new array (the input is not changed).

    Parameters
    ----------
    images : (B, H, W) or (H, W) float image (image units, e.g. the Eq. 3 intensity of the renderers).
    psf_sigma_px : Gaussian PSF standard deviation (px); 0 = no blur.
    read_noise : read noise standard deviation (DN, after ``gain``); 0 = none.
    gain : DN per image unit.
    bits : quantise to integers in [0, 2^bits - 1] (None = no quantisation).
    seeds : (B,) or scalar uint64 per-frame seeds of the read noise (None = 0).

    Returns
    -------
    (B, H, W) float32 image in DN (see the module docstring for the order of the effects).
    """
    out = as_f32(np.array(images, dtype=np.float32, copy=True))
    if out.ndim == 2:
        out = out[None]
    B = out.shape[0]
    if psf_sigma_px > 0:
        w = gaussian_weights(psf_sigma_px)
        tmp = np.empty_like(out)
        blur = _KERNELS.get("blur_rows")
        blur(out, tmp, w, 1)
        blur(tmp, out, w, 0)
    if read_noise > 0 or bits or gain != 1.0:
        sd = np.zeros(B, np.uint64) if seeds is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(seeds, dtype=np.uint64), (B,)))
        maxdn = float(2 ** int(bits) - 1) if bits else 0.0
        _KERNELS.get("noise_quant")(out, sd, float(read_noise), float(gain), maxdn)
    return out
