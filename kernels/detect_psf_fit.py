"""The real-sensor detector's PSF fit (:mod:`dualsight.kernels.detect_local`, step 5) as one compiled Taichi kernel:
:func:`fit_psf_compiled` is :func:`dualsight.kernels.detect_psf.fit_psf` — the same model (pixel-integrated Gaussian
A P(x, y; s) + b, the same Abramowitz & Stegun erf), the same weights, Levenberg-Marquardt rules (lambda from 1e-3,
/ 10 down to 1e-6 after a step that does not raise chi^2, x 10 after one that does, which is not taken; position
steps clipped to +-0.5 px, width steps to +-0.3 s and the width to [0.2, 20]; a star stops when its proposed
position (and width) step is under ``tol_px``, when lambda reaches 1e4, or after ``iters`` steps) and the same
Fisher matrix at the final parameters — with each star's whole fit in one thread's registers: its profiles (n + 1
pixel edges per axis), its normal equations summed over the stamp and solved by Gaussian elimination with
partial pivoting, instead of ~40 numpy calls per step over the batch (the numpy fit costs ~1 us per star and step
plus ~0.1 ms per step for the calls: 0.6-0.7 ms for 25 stars, 1.8 ms for 340).  The stars are independent: one
thread per star, parallel over the batch.

Differences from the numpy fit: a singular system gives a zero step here (numpy solves every star of the batch by
least squares then); sums are accumulated in a different order (the positions agree to ~1e-12 px where both take
the same steps; tests/test_detect_psf_fit.py).  Stamps up to :data:`MAX_STAMP` pixels a side (larger ones: the
numpy fit)."""

import math

import numpy as np

from dualsight.kernels.detect_psf import AS_A, AS_P, fit_outcome, fit_psf
from dualsight.kernels.taichi_runtime import TASK_ITEMS, KernelCache

MAX_STAMP = 31
"""Largest stamp side (px) of the compiled fit (its per-axis profiles live in registers)."""


def _build_fit(dtype, fit_sigma: bool = False, serial: bool = False):
    import taichi as ti   # here, not at import: the CLI imports this module without any kernel to run

    f64 = ti.f64
    a1, a2, a3, a4, a5 = (float(a) for a in AS_A)
    pc = float(AS_P) / math.sqrt(2.0)
    inv_sqrt2pi = 1.0 / math.sqrt(2.0 * math.pi)
    NV = MAX_STAMP + 1
    npar = 5 if fit_sigma else 4

    @ti.func
    def profiles(c0, x, s, n):
        """P, dP/dx, dP/ds of pixels c0 .. c0 + n - 1 (detect_psf.psf_profiles)."""
        P = ti.Vector.zero(f64, NV)
        D = ti.Vector.zero(f64, NV)
        S = ti.Vector.zero(f64, NV)
        inv = f64(1.0) / s
        e_prev, Phi_prev, phi_prev = f64(0.0), f64(0.0), f64(0.0)
        for j in range(n + 1):
            e = (ti.cast(c0 + j, f64) - x) * inv
            ex = ti.exp(f64(-0.5) * e * e)
            t = f64(1.0) / (f64(1.0) + ti.abs(e) * f64(pc))
            q = t * f64(a5)
            q += f64(a4)
            q *= t
            q += f64(a3)
            q *= t
            q += f64(a2)
            q *= t
            q += f64(a1)
            q *= t
            q *= ex
            q *= f64(0.5)
            Phi = f64(1.0) - q if e >= 0 else q
            phi = ex * f64(inv_sqrt2pi)
            if j > 0:
                P[j - 1] = Phi - Phi_prev
                D[j - 1] = (phi_prev - phi) * inv
                S[j - 1] = (e_prev * phi_prev - e * phi) * inv
            e_prev, Phi_prev, phi_prev = e, Phi, phi
        return P, D, S

    @ti.func
    def weight(w, ap, nv, gain):
        out = w / nv
        if gain > 0:
            out = w / (nv + ti.max(ap, f64(0.0)) / gain)
        return out

    @ti.func
    def chi2(st: ti.template(), w0: ti.template(), k, p, n, nv, gain, px, py):
        """chi^2 at p, whose profiles are px, py."""
        chi = f64(0.0)
        for i in range(n):
            for j in range(n):
                ap = p[2] * py[i] * px[j]
                r = st[k, i, j] - ap - p[3]
                chi += weight(w0[k, i, j], ap, nv, gain) * r * r
        return chi

    @ti.func
    def normal(st: ti.template(), w0: ti.template(), k, p, n, nv, gain, px, dpx, sx, py, dpy, sy):
        """H (5 x 5), g (5) of the weighted least squares at p (the first npar rows used), whose profiles and their
        derivatives are px, dpx, sx (columns) and py, dpy, sy (rows)."""
        H = ti.Matrix.zero(f64, 5, 5)
        g = ti.Vector.zero(f64, 5)
        for i in range(n):
            for j in range(n):
                P = py[i] * px[j]
                ap = p[2] * P
                W = weight(w0[k, i, j], ap, nv, gain)
                r = st[k, i, j] - ap - p[3]
                J = ti.Vector([p[2] * py[i] * dpx[j], p[2] * dpy[i] * px[j], P, f64(1.0),
                               p[2] * (sy[i] * px[j] + py[i] * sx[j])], f64)
                for a in ti.static(range(npar)):
                    g[a] += W * J[a] * r
                    for b in ti.static(range(a, npar)):       # the upper triangle; mirrored below
                        H[a, b] += W * J[a] * J[b]
        for a in ti.static(range(npar)):
            for b in ti.static(range(a)):
                H[a, b] = H[b, a]
        return H, g

    @ti.func
    def solve(H, g):
        """H^-1 g of the first npar rows (Gaussian elimination, partial pivoting); 0 when singular."""
        M = H
        v = g
        good = 1
        for c in ti.static(range(npar)):
            piv = c
            best = ti.abs(M[c, c])
            for r in ti.static(range(c + 1, npar)):
                if ti.abs(M[r, c]) > best:
                    best = ti.abs(M[r, c])
                    piv = r
            if best == 0 or not (best == best):
                good = 0
            else:
                if piv != c:      # swap rows c and piv
                    for q in ti.static(range(npar)):
                        tmp = M[c, q]
                        M[c, q] = M[piv, q]
                        M[piv, q] = tmp
                    tmp = v[c]
                    v[c] = v[piv]
                    v[piv] = tmp
                for r in ti.static(range(c + 1, npar)):
                    f = M[r, c] / M[c, c]
                    for q in ti.static(range(npar)):
                        M[r, q] -= f * M[c, q]
                    v[r] -= f * v[c]
        x = ti.Vector.zero(f64, 5)
        if good:
            for c in ti.static(range(npar - 1, -1, -1)):
                acc = v[c]
                for q in ti.static(range(c + 1, npar)):
                    acc -= M[c, q] * x[q]
                x[c] = acc / M[c, c]
        return x

    @ti.kernel
    def fit(st: ti.types.ndarray(dtype=f64, ndim=3), w0: ti.types.ndarray(dtype=f64, ndim=3),
            r0: ti.types.ndarray(dtype=ti.i64, ndim=1), c0: ti.types.ndarray(dtype=ti.i64, ndim=1),
            start: ti.types.ndarray(dtype=f64, ndim=2), noise: ti.types.ndarray(dtype=f64, ndim=1),
            gain: f64, iters: ti.i32, tol: f64,
            out: ti.types.ndarray(dtype=f64, ndim=2), fisher: ti.types.ndarray(dtype=f64, ndim=3)):
        n = st.shape[1]
        ti.loop_config(serialize=serial)
        for k in range(st.shape[0]):                     # one star per thread, its whole fit in registers
            nv = noise[k] * noise[k]
            rk = ti.cast(r0[k], ti.i32)
            ck = ti.cast(c0[k], ti.i32)
            p = ti.Vector([start[k, 0], start[k, 1], f64(1.0), f64(0.0), start[k, 2]], f64)
            # the profiles at p, evaluated once per position (a step's trial profiles become p's when it is taken)
            px, dpx, sx = profiles(ck, p[0], p[4], n)
            py, dpy, sy = profiles(rk, p[1], p[4], n)
            num, den = f64(0.0), f64(0.0)
            for i in range(n):
                for j in range(n):
                    P = py[i] * px[j]
                    num += w0[k, i, j] * st[k, i, j] * P
                    den += w0[k, i, j] * P * P
            p[2] = ti.max(num / ti.max(den, f64(1e-12)), f64(1e-3))     # A at b = 0
            chi = chi2(st, w0, k, p, n, nv, gain, px, py)
            lam = f64(1e-3)
            Hc = ti.Matrix.zero(f64, 5, 5)     # the normal equations at p, kept while p is (a rejected step)
            gc = ti.Vector.zero(f64, 5)
            have = 0
            for it in range(iters):
                if have == 0:
                    H0, g0 = normal(st, w0, k, p, n, nv, gain, px, dpx, sx, py, dpy, sy)
                    Hc = H0
                    gc = g0
                    have = 1
                H = Hc
                g = gc
                for a in ti.static(range(npar)):
                    H[a, a] += lam * ti.max(H[a, a], f64(1e-12))
                step = solve(H, g)
                step[0] = ti.min(ti.max(step[0], f64(-0.5)), f64(0.5))
                step[1] = ti.min(ti.max(step[1], f64(-0.5)), f64(0.5))
                small = ti.max(ti.abs(step[0]), ti.abs(step[1])) < tol
                pn = p + step
                if ti.static(fit_sigma):
                    ds = ti.min(ti.max(step[4], f64(-0.3) * p[4]), f64(0.3) * p[4])
                    small = small and ti.abs(ds) < tol
                    pn[4] = ti.min(ti.max(p[4] + ds, f64(0.2)), f64(20.0))
                else:
                    pn[4] = p[4]
                qx, dqx, sqx = profiles(ck, pn[0], pn[4], n)
                qy, dqy, sqy = profiles(rk, pn[1], pn[4], n)
                chin = chi2(st, w0, k, pn, n, nv, gain, qx, qy)
                better = (chin == chin) and ti.abs(chin) < f64(1e300) and chin <= chi
                if better:
                    p = pn
                    px, dpx, sx, py, dpy, sy = qx, dqx, sqx, qy, dqy, sqy
                    chi = chin
                    lam = ti.max(lam * f64(0.1), f64(1e-6))
                    have = 0
                else:
                    lam = lam * f64(10.0)
                if small or lam >= f64(1e4):
                    break
            for a in ti.static(range(5)):
                out[k, a] = p[a]
            if have == 0:                                          # the Fisher matrix of (x, y, A, b) at p
                H1, g1 = normal(st, w0, k, p, n, nv, gain, px, dpx, sx, py, dpy, sy)
                Hc = H1
            for a in ti.static(range(4)):
                for b in ti.static(range(4)):
                    fisher[k, a, b] = Hc[a, b]

    return fit


def _build_fit5(dtype, serial: bool = False):
    return _build_fit(dtype, fit_sigma=True, serial=serial)


_KERNELS = KernelCache({"fit4": _build_fit, "fit5": _build_fit5})    # each built on first use


def fit_psf_compiled(stamp, w0, r0, c0, x, y, s, noise, gain, fit_sigma=False, iters=10, tol_px=1e-3):
    """:func:`dualsight.kernels.detect_psf.fit_psf` (same arguments and returns) in one Taichi kernel (module
    docstring); stamps larger than :data:`MAX_STAMP` a side go to the numpy fit."""
    K, n, _ = stamp.shape
    if n > MAX_STAMP or K == 0:
        return fit_psf(stamp, w0, r0, c0, x, y, s, noise, gain, fit_sigma=fit_sigma, iters=iters, tol_px=tol_px)
    st = np.ascontiguousarray(stamp, np.float64)
    w = np.ascontiguousarray(w0, np.float64)
    r0 = np.ascontiguousarray(r0, np.int64)
    c0 = np.ascontiguousarray(c0, np.int64)
    start = np.ascontiguousarray(np.stack([x, y, s], axis=1), np.float64)
    out = np.zeros((K, 5))
    fisher = np.zeros((K, 4, 4))
    # under 2 TASK_ITEMS stars Taichi runs the loop on one thread anyway: the serial variant skips the thread pool's
    # round trip (~0.1 ms per launch; taichi_runtime.KernelCache); the stars are independent, the results the same
    kern = _KERNELS.get("fit5" if fit_sigma else "fit4", np.float64, serial=K < 2 * TASK_ITEMS)
    kern(st, w, r0, c0, start, np.ascontiguousarray(noise, np.float64), float(gain or 0.0), int(iters),
         float(tol_px), out, fisher)
    s_out = out[:, 4].copy() if fit_sigma else np.asarray(s, np.float64).copy()
    return fit_outcome(out, fisher, r0, c0, n, s_out)
