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
from dualsight.kernels.detect_passes import pixel_type_name
from dualsight.kernels.taichi_runtime import TASK_ITEMS, KernelCache

MAX_STAMP = 31
"""Largest stamp side (px) of the compiled fit (its per-axis profiles live in registers)."""


def _build_fit(dtype, fit_sigma: bool = False, serial: bool = False, frame: bool = False):
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

    @ti.func
    def run(st: ti.template(), w0: ti.template(), k, rk, ck, x0, y0, s0, nv, gain, iters, tol, n):
        """The fit of star k (its stamp st[k], weights w0[k], top-left pixel (rk, ck)) from (x0, y0, s0): the final
        parameters (x, y, A, b, s) and the normal matrix of (x, y, A, b) at them (the Fisher matrix)."""
        p = ti.Vector([x0, y0, f64(1.0), f64(0.0), s0], f64)
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
        if have == 0:                                          # the Fisher matrix of (x, y, A, b) at p
            H1, g1 = normal(st, w0, k, p, n, nv, gain, px, dpx, sx, py, dpy, sy)
            Hc = H1
        return p, Hc

    @ti.kernel
    def fit(st: ti.types.ndarray(dtype=f64, ndim=3), w0: ti.types.ndarray(dtype=f64, ndim=3),
            r0: ti.types.ndarray(dtype=ti.i64, ndim=1), c0: ti.types.ndarray(dtype=ti.i64, ndim=1),
            start: ti.types.ndarray(dtype=f64, ndim=2), noise: ti.types.ndarray(dtype=f64, ndim=1),
            gain: f64, iters: ti.i32, tol: f64,
            out: ti.types.ndarray(dtype=f64, ndim=2), fisher: ti.types.ndarray(dtype=f64, ndim=3)):
        n = st.shape[1]
        ti.loop_config(serialize=serial)
        for k in range(st.shape[0]):                     # one star per thread, its whole fit in registers
            p, Hc = run(st, w0, k, ti.cast(r0[k], ti.i32), ti.cast(c0[k], ti.i32), start[k, 0], start[k, 1],
                        start[k, 2], noise[k] * noise[k], gain, iters, tol, n)
            for a in ti.static(range(5)):
                out[k, a] = p[a]
            for a in ti.static(range(4)):
                for b in ti.static(range(4)):
                    fisher[k, a, b] = Hc[a, b]

    if not frame:
        return fit

    pt = getattr(ti, pixel_type_name(dtype))

    @ti.func
    def inverse4(M):
        """(M^-1 of the 4 x 4 upper-left block of M, its determinant, 1 when invertible): Gauss-Jordan elimination
        with partial pivoting (det = the pivots' product with the swaps' sign; 0 at the first zero pivot)."""
        A = ti.Matrix.zero(f64, 4, 4)
        E = ti.Matrix.identity(f64, 4)
        for a in ti.static(range(4)):
            for b in ti.static(range(4)):
                A[a, b] = M[a, b]
        det = f64(1.0)
        good = 1
        for c in ti.static(range(4)):
            piv = c
            best = ti.abs(A[c, c])
            for r in ti.static(range(c + 1, 4)):
                if ti.abs(A[r, c]) > best:
                    best = ti.abs(A[r, c])
                    piv = r
            if best == 0 or not (best == best):
                good = 0
            if good:
                if piv != c:
                    det = -det
                    for q in ti.static(range(4)):
                        t1 = A[c, q]
                        A[c, q] = A[piv, q]
                        A[piv, q] = t1
                        t2 = E[c, q]
                        E[c, q] = E[piv, q]
                        E[piv, q] = t2
                d = A[c, c]
                det *= d
                for q in ti.static(range(4)):
                    A[c, q] /= d
                    E[c, q] /= d
                for r in ti.static(range(4)):
                    if r != c:
                        f = A[r, c]
                        for q in ti.static(range(4)):
                            A[r, q] -= f * A[c, q]
                            E[r, q] -= f * E[c, q]
        if not good:
            det = f64(0.0)
        return E, det, good

    @ti.kernel
    def fit_frame(R: ti.types.ndarray(dtype=ti.f32, ndim=2), img: ti.types.ndarray(dtype=pt, ndim=2),
                  r0: ti.types.ndarray(dtype=ti.i64, ndim=1), c0: ti.types.ndarray(dtype=ti.i64, ndim=1),
                  hot: ti.types.ndarray(dtype=ti.u8, ndim=1), h: ti.i32, sat: f64, s: f64,
                  noise: ti.types.ndarray(dtype=f64, ndim=1), gain: f64, iters: ti.i32, tol: f64,
                  st: ti.types.ndarray(dtype=f64, ndim=3), w0: ti.types.ndarray(dtype=f64, ndim=3),
                  res: ti.types.ndarray(dtype=f64, ndim=2)):
        n = 2 * h + 1
        H, W = R.shape[0], R.shape[1]
        ti.loop_config(serialize=serial)
        for k in range(r0.shape[0]):
            rc = ti.cast(r0[k], ti.i32)
            cc = ti.cast(c0[k], ti.i32)
            rk, ck = rc - h, cc - h
            usable = f64(0.0)
            for i in range(n):                         # the stamp (detect_psf.cut_stamps) and its weights
                for j in range(n):
                    r = rk + i
                    c = ck + j
                    rr = ti.min(ti.max(r, 0), H - 1)
                    cl = ti.min(ti.max(c, 0), W - 1)
                    st[k, i, j] = ti.cast(R[rr, cl], f64)
                    w = f64(0.0)
                    if 0 <= r < H and 0 <= c < W and ti.cast(img[rr, cl], f64) < sat:
                        w = f64(1.0)
                    if hot[k] != 0 and i == h and j == h:
                        w = f64(0.0)
                    w0[k, i, j] = w
                    usable += w
            tot, sx, sy = f64(0.0), f64(0.0), f64(0.0)     # 3 x 3 intensity-weighted centroid: the start
            for i in ti.static(range(3)):
                for j in ti.static(range(3)):
                    v = ti.max(st[k, h - 1 + i, h - 1 + j], f64(0.0)) * w0[k, h - 1 + i, h - 1 + j]
                    tot += v
                    sx += v * ti.static(float(j - 1))
                    sy += v * ti.static(float(i - 1))
            dx, dy = f64(0.0), f64(0.0)
            if tot > 0:
                dx = sx / ti.max(tot, f64(1e-12))
                dy = sy / ti.max(tot, f64(1e-12))
            x0 = ti.cast(cc, f64) + f64(0.5) + dx
            y0 = ti.cast(rc, f64) + f64(0.5) + dy
            p, Hc = run(st, w0, k, rk, ck, x0, y0, s, noise[k] * noise[k], gain, iters, tol, n)
            C, det, good = inverse4(Hc)
            finite = 1
            for a in ti.static(range(4)):
                for b in ti.static(range(4)):
                    if not (ti.abs(Hc[a, b]) < f64(1e308)):
                        finite = 0
            half = f64(0.5) * ti.cast(n, f64)
            ok = finite and good and ti.abs(det) > 0 and p[2] > 0 and ti.abs(p[0]) < f64(1e308) \
                and ti.abs(p[1]) < f64(1e308) and ti.abs(p[0] - (ti.cast(ck, f64) + half)) < half - f64(0.5) \
                and ti.abs(p[1] - (ti.cast(rk, f64) + half)) < half - f64(0.5) and C[0, 0] > 0 and C[1, 1] > 0 \
                and usable >= 6
            for a in ti.static(range(5)):
                res[k, a] = p[a]
            res[k, 5] = C[0, 0]
            res[k, 6] = C[1, 1]
            res[k, 7] = ti.select(ok, f64(1.0), f64(0.0))
            res[k, 8] = x0
            res[k, 9] = y0
            res[k, 10] = tot

    return fit_frame


def _build_fit5(dtype, serial: bool = False):
    return _build_fit(dtype, fit_sigma=True, serial=serial)


def _build_frame4(dtype, serial: bool = False):
    return _build_fit(dtype, serial=serial, frame=True)


def _build_frame5(dtype, serial: bool = False):
    return _build_fit(dtype, fit_sigma=True, serial=serial, frame=True)


_KERNELS = KernelCache({"fit4": _build_fit, "fit5": _build_fit5, "frame4": _build_frame4,
                        "frame5": _build_frame5})    # each built on first use


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


def fit_frame_compiled(R, img, r, c, hot, h, sat, s, noise, gain, fit_sigma=False, iters=10, tol_px=1e-3):
    """The PSF fits of K candidates of one frame in one kernel launch, cut from the frame in the kernel: the
    (2h + 1)^2 stamps of the residual ``R`` ((H, W) float32, ADU) centred on pixels (r, c) ((K,) int) with their
    usable pixels (inside the frame, ``img`` < ``sat``: not saturated; ``hot`` (K,) bool: the centre pixel excluded)
    as :func:`dualsight.kernels.detect_psf.cut_stamps`, the start at the 3 x 3 intensity-weighted centroid of the
    positive residual, then :func:`fit_psf_compiled`'s fit from width ``s`` (px), and the Fisher matrix inverted in
    the kernel (Gauss-Jordan, partial pivoting) instead of ``numpy.linalg``: the steps of ``detect_local._measure``
    for stamps of at most :data:`MAX_STAMP` a side (the caller checks) without numpy between them.

    ``img``: the frame (uint8, uint16, float32 or float64, ADU); ``sat``: the saturation level (ADU) or None;
    ``noise`` (K,): pixel noise sigma (ADU); ``gain``: e-/ADU or None.  Returns a dict of (K,) float64 arrays
    ``x``, ``y`` (px), ``A`` (ADU), ``b`` (ADU), ``s`` (px; the input width unless ``fit_sigma``), ``cxx``, ``cyy``
    (px^2, the Cramér-Rao variances), ``x0``, ``y0`` (the start, px), ``tot`` (ADU: the start's 3 x 3 positive sum),
    and ``ok`` (K,) bool: :func:`dualsight.kernels.detect_psf.fit_outcome`'s conditions and at least 6 usable
    pixels."""
    K = int(np.size(r))
    n = 2 * int(h) + 1
    res = np.zeros((K, 11))
    if K:
        kern = _KERNELS.get("frame5" if fit_sigma else "frame4", img.dtype, serial=K < 2 * TASK_ITEMS)
        kern(np.ascontiguousarray(R, np.float32), np.ascontiguousarray(img), np.ascontiguousarray(r, np.int64),
             np.ascontiguousarray(c, np.int64), np.ascontiguousarray(hot, np.uint8), int(h),
             float("inf") if sat is None else float(sat), float(s), np.ascontiguousarray(noise, np.float64),
             float(gain or 0.0), int(iters), float(tol_px), np.empty((K, n, n)), np.empty((K, n, n)), res)
    out = {name: res[:, i] for i, name in enumerate(("x", "y", "A", "b", "s", "cxx", "cyy"))}
    out.update(ok=res[:, 7] > 0, x0=res[:, 8], y0=res[:, 9], tot=res[:, 10])
    if not fit_sigma:
        out["s"] = np.full(K, float(s))
    return out
