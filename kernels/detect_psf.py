"""The PSF of the real-sensor detector (:mod:`dualsight.kernels.detect_local`, steps 2, 4 and 5 of its
docstring): the pixel-integrated Gaussian PSF of standard deviation s (px) — its normal-distribution
arithmetic, the 1-D kernel of the matched filter (:func:`psf_kernel_1d`), the sharpness limit of the hot-pixel
test (:func:`sharpness_limit`), the flux fraction of the fallback centroid's box (:func:`flux_fraction_3x3`),
the Cramér-Rao centroid bound (:func:`crb_sigma_px`) — and stage 3, the batched weighted least-squares fit of
star stamps (:func:`cut_stamps`, :func:`psf_profiles`, :func:`fit_psf`).  Pure numpy functions over arrays;
positions in the continuous pixel convention (pixel (r, c) covers [c, c + 1) x [r, r + 1))."""

import functools
import math

import numpy as np


# ============================================================================ normal distribution
_SQRT2 = math.sqrt(2.0)


AS_P, AS_A = 0.3275911, (0.254829592, -0.284496736, 1.421413741, -1.453152027, 1.061405429)
"""Abramowitz & Stegun 7.1.26: erf(x) = 1 - (a1 t + ... + a5 t^5) exp(-x^2), t = 1 / (1 + p x), x >= 0,
|error| <= 1.5e-7; ``AS_A`` = (a1, ..., a5)."""


def _erf(x):
    """erf (Abramowitz & Stegun 7.1.26, :data:`AS_A`), vectorised."""
    a1, a2, a3, a4, a5 = AS_A
    x = np.asarray(x, np.float64)
    s = np.sign(x)
    a = np.abs(x)
    t = 1.0 / (1.0 + AS_P * a)
    y = 1.0 - (((((a5 * t + a4) * t) + a3) * t + a2) * t + a1) * t * np.exp(-a * a)
    return s * y


def _Phi(z):
    return 0.5 * (1.0 + _erf(np.asarray(z, np.float64) / _SQRT2))


def _phi(z):
    z = np.asarray(z, np.float64)
    return np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


# ============================================================================ PSF helpers
FILTER_SNR_EFFICIENCY = 0.999
"""The matched filter's kernel (:func:`psf_kernel_1d`) ends where it keeps this fraction of the untruncated filter's
SNR.  For a separable kernel k_ij = p_i p_j cut to |i|, |j| <= h (p: a pixel-centred star's pixel fractions) the
filtered star over the filtered white noise is F (sum_{|i|<=h} p_i^2) / sigma, so the fraction is
sum_{|i|<=h} p_i^2 / sum_i p_i^2: 0.1 % of SNR moves a Z = 5 star by 0.005, a sixth of the noise ratio's own
measurement error (``detect_candidates.NOISE_SAMPLE_STRIDE``).  Cut at |i| <= ceil(3 s) until 2026-11-28: at
s = 0.9 px 7 taps instead of 5 (SNR 0.99995 of the full filter's), which OpenCV's ``sepFilter2D`` runs at 0.59 ms
per 1024 x 1024 float32 frame instead of 0.35 (one core)."""


@functools.lru_cache(maxsize=256)
def psf_kernel_1d(sigma: float) -> np.ndarray:
    """Normalised 1-D pixel-integrated Gaussian of ``sigma`` px, k_i = Phi((i + 1/2) / sigma) - Phi((i - 1/2) /
    sigma), |i| <= h, h >= 1 the smallest half-width that keeps :data:`FILTER_SNR_EFFICIENCY` of the untruncated
    matched filter's SNR (h = 2 at 0.7-1.1 px, 3 at 1.2-1.5 px): (2h + 1,) float64 summing to 1 (the matched
    filter's kernel), read-only (computed once per width: a frame asks for it up to five times)."""
    n = max(2, int(math.ceil(8.0 * sigma)) + 1)
    i = np.arange(-n, n + 1, dtype=np.float64)
    p = _Phi((i + 0.5) / sigma) - _Phi((i - 0.5) / sigma)
    q = p * p
    kept = q[n] + 2.0 * np.cumsum(q[n + 1:])          # sum of p_i^2 over |i| <= h, h = 1 .. n
    h = 1 + int(np.argmax(kept >= FILTER_SNR_EFFICIENCY * q.sum()))
    k = p[n - h:n + h + 1]
    k = k / k.sum()
    k.flags.writeable = False
    return k


@functools.lru_cache(maxsize=256)
def sharpness_limit(sigma: float) -> float:
    """Largest ratio of a pixel-integrated Gaussian star's brightest pixel to the mean of its 4 neighbours
    (over sub-pixel positions: the star centred on a pixel), a0 / a1 (:mod:`dualsight.kernels.detect_local`,
    step 4); ``sigma`` in px."""
    u = np.linspace(-0.5, 0.5, 21)
    a0 = _Phi((0.5 - u) / sigma) - _Phi((-0.5 - u) / sigma)
    ap = _Phi((1.5 - u) / sigma) - _Phi((0.5 - u) / sigma)
    am = _Phi((-0.5 - u) / sigma) - _Phi((-1.5 - u) / sigma)
    # 2-D, offsets (u, v): peak a0(u) a0(v); neighbours a0(v)(ap(u) + am(u)) + a0(u)(ap(v) + am(v))
    A0 = a0[:, None] * a0[None, :]
    N4 = a0[None, :] * (ap + am)[:, None] + a0[:, None] * (ap + am)[None, :]
    return float((A0 / (N4 / 4.0)).max())


@functools.lru_cache(maxsize=256)
def filter_efficiency(s_filter: float, s_star: float) -> float:
    """Fraction of the optimal matched-filter SNR that a filter of PSF width ``s_filter`` (px) keeps on a star of
    width ``s_star`` (px), both pixel-integrated Gaussians, the star centred on a pixel, untruncated kernels: the
    filtered star over the filtered white noise is F <k, p> / (sigma ||k||) against the matched filter's
    F ||p|| / sigma, so the fraction is the normalised correlation <k, p> / (||k|| ||p||), for separable kernels
    the square of the 1-D one (Cauchy-Schwarz: 1 at s_filter = s_star).  For widths >= 0.8 px within 0.1 % of the
    continuous Gaussians' 2 a b / (a^2 + b^2) with a^2 = s_filter^2 + 1/12, b^2 = s_star^2 + 1/12 (the pixel's
    variance added; a sharper pixel-centred star is less Gaussian: 4 % off at 0.5 px)."""
    n = max(2, int(math.ceil(8.0 * max(s_filter, s_star))) + 1)
    i = np.arange(-n, n + 1, dtype=np.float64)
    k = _Phi((i + 0.5) / s_filter) - _Phi((i - 0.5) / s_filter)
    p = _Phi((i + 0.5) / s_star) - _Phi((i - 0.5) / s_star)
    return float((k @ p) ** 2 / ((k @ k) * (p @ p)))


@functools.lru_cache(maxsize=256)
def flux_fraction_3x3(sigma: float) -> float:
    """Fraction of a pixel-integrated Gaussian star's flux (PSF sigma ``sigma`` px) in the 3 x 3 pixels centred on
    it, (Phi(1.5 / s) - Phi(-1.5 / s))^2: the flux of a fallback 3 x 3 centroid is its box sum over this."""
    return float((_Phi(1.5 / sigma) - _Phi(-1.5 / sigma)) ** 2)


def crb_sigma_px(flux_adu, noise_adu, psf_sigma_px, gain_e_per_adu=None) -> np.ndarray:
    """Cramér-Rao bound (px, per axis) of the position of a pixel-integrated Gaussian star of total flux
    ``flux_adu`` centred on a pixel, on white noise ``noise_adu`` (+ its own shot noise with a gain), with
    flux and a constant background unknown: the same Fisher matrix as the fit's, on a 15 x 15 stamp."""
    shape = np.shape(flux_adu)
    f = np.atleast_1d(np.asarray(flux_adu, np.float64)).ravel()
    n = np.broadcast_to(np.asarray(noise_adu, np.float64), shape).ravel()
    s = float(psf_sigma_px)
    h = max(7, int(math.ceil(4 * s)))
    c = np.arange(-h, h + 1, dtype=np.float64)
    p = _Phi((c + 1 - 0.5) / s) - _Phi((c - 0.5) / s)
    dp = -(_phi((c + 1 - 0.5) / s) - _phi((c - 0.5) / s)) / s
    P = p[:, None] * p[None, :]
    Jx = p[:, None] * dp[None, :]
    Jy = dp[:, None] * p[None, :]
    out = np.empty(f.shape)
    for i in range(f.size):     # a handful of values (tests, reports): not a loop over pixels of a frame
        var = n[i] ** 2 + (np.maximum(f[i] * P, 0) / gain_e_per_adu if gain_e_per_adu else 0.0)
        J = np.stack([f[i] * Jx, f[i] * Jy, P, np.ones_like(P)], -1).reshape(-1, 4)
        I = J.T @ (J / var.reshape(-1, 1))
        out[i] = math.sqrt(np.linalg.inv(I)[0, 0])
    return out.reshape(shape)


# ============================================================================ PSF fit
def _Phi_phi(e):
    """(Phi(e), phi(e)) of a float64 array, one exp for both: Phi with erf as in :func:`_erf` (Abramowitz &
    Stegun 7.1.26, |error| <= 1.5e-7, written for |e|: erfc(|e| / sqrt 2) = t poly(t) exp(-e^2 / 2)),
    phi = exp(-e^2 / 2) / sqrt(2 pi)."""
    ex = e * e                                           # in place: small arrays, the calls dominate
    ex *= -0.5
    np.exp(ex, out=ex)
    t = np.abs(e)
    t *= AS_P / math.sqrt(2.0)
    t += 1.0
    np.reciprocal(t, out=t)
    q = t * AS_A[4]
    for c in AS_A[3::-1]:                                # a4 .. a1 (Horner)
        q += c
        q *= t
    q *= ex
    q *= 0.5                                             # Phi(-|e|)
    ex *= 1.0 / math.sqrt(2.0 * math.pi)
    return np.where(e >= 0, 1.0 - q, q), ex


def psf_profiles(x, c0, n, s, ds=True):
    """1-D pixel fractions and their derivatives (d/dx, d/ds; d/ds None unless ``ds``) of K stars at positions
    ``x`` (K,) (px) with PSF sigmas ``s`` (K,) (px) over n pixels starting at pixel ``c0`` (K,): (K, n) float64
    each (the fit's model, one axis; the 2-D model is the outer product of the two axes').

    Pixel j covers [c0 + j, c0 + j + 1): with edges e_j = (c0 + j - x) / s (j = 0..n, the n + 1 pixel edges,
    each evaluated once), P_j = Phi(e_{j+1}) - Phi(e_j), dP_j/dx = -(phi(e_{j+1}) - phi(e_j)) / s and
    dP_j/ds = -(e_{j+1} phi(e_{j+1}) - e_j phi(e_j)) / s."""
    inv = 1.0 / s[:, None]
    e = (c0[:, None] + np.arange(n + 1)[None, :] - x[:, None]) * inv
    Pe, pe = _Phi_phi(e)
    P, dP = Pe[:, 1:] - Pe[:, :-1], (pe[:, :-1] - pe[:, 1:]) * inv
    if not ds:
        return P, dP, None
    ep = e * pe
    return P, dP, (ep[:, :-1] - ep[:, 1:]) * inv


def fit_psf(stamp, w0, r0, c0, x, y, s, noise, gain, fit_sigma=False, iters=10, tol_px=1e-3):
    """Weighted least-squares fit of A P(x, y; s) + b to (K, n, n) stamps (ADU) whose top-left pixel is (r0, c0)
    (:mod:`dualsight.kernels.detect_local`, step 5); P the pixel-integrated Gaussian (:func:`psf_profiles`).

    w0 : (K, n, n) 1 = usable pixel, 0 = excluded (saturated, hot, outside the frame).  x, y, s : initial
    values (K,).  Levenberg-Marquardt (Marquardt's diagonal scaling, lambda from 1e-3, / 10 (down to 1e-6)
    after a step that does not raise chi^2, x 10 after one that does, which is then not taken; position steps
    clipped to +-0.5 px, width steps to +-0.3 s).  A star stops when its proposed position step is under
    ``tol_px`` on both axes (fitting the width: and its width step too), i.e. its parameters are within
    ~``tol_px`` of the minimum, when lambda reaches 1e4, or after ``iters`` steps; its iterations depend on
    its own stamp only (a batch equals the per-star fits: finished stars are frozen, then dropped).
    noise : (K,) pixel noise sigma (ADU); gain : e-/ADU for the stars' shot noise in the weights, None = none;
    fit_sigma : also fit the PSF width (else ``s`` is kept).
    Returns x, y (K,) px, A (K,) total flux (ADU), b (K,) background (ADU), s (K,) px, cov (K, 4, 4) of
    (x, y, A, b) (Fisher inverse at the final parameters), ok (K,) bool."""
    K, n, _ = stamp.shape
    m = n * n
    npar = 5 if fit_sigma else 4
    d = stamp.astype(np.float64).reshape(K, m)
    wf = np.asarray(w0, np.float64).reshape(K, m)
    nv = noise.astype(np.float64) ** 2
    s_in = s.astype(np.float64)
    p = np.empty((K, npar))                        # parameters x, y, A, b (, s)
    p[:, 0], p[:, 1], p[:, 2], p[:, 3] = x, y, 1.0, 0.0
    if fit_sigma:
        p[:, 4] = s_in
    out = p.copy()
    H4 = np.empty((K, 4, 4))

    def model(p, s2, st):               # A P (k, m) and J (k, npar, m) of k stars; st = [c0; r0], s2 = [s; s]
        k = p.shape[0]
        if fit_sigma:
            s2 = np.concatenate([p[:, 4], p[:, 4]])
        P1, D1, S1 = psf_profiles(p[:, :2].T.ravel(), st, n, s2, fit_sigma)
        px, py, dpx, dpy = P1[:k], P1[k:], D1[:k], D1[k:]
        J = np.empty((k, npar, n, n))      # parameter-major: each derivative image contiguous
        A = p[:, 2:3]
        np.multiply(py[:, :, None], px[:, None, :], out=J[:, 2])
        np.multiply((A * py)[:, :, None], dpx[:, None, :], out=J[:, 0])
        np.multiply((A * dpy)[:, :, None], px[:, None, :], out=J[:, 1])
        J[:, 3] = 1.0
        if fit_sigma:
            J[:, 4] = A[:, :, None] * (S1[k:, :, None] * px[:, None, :] + py[:, :, None] * S1[:k, None, :])
        J = J.reshape(k, npar, m)
        return A * J[:, 2], J

    def weights(AP, wf, nv):
        return wf / (nv[:, None] + np.maximum(AP, 0.0) / gain) if gain else wf / nv[:, None]

    st0 = np.concatenate([c0, r0])
    s2 = np.concatenate([s_in, s_in])
    P, J = model(p, s2, st0)
    p[:, 2] = np.maximum((wf * d * P).sum(1) / np.maximum((wf * P * P).sum(1), 1e-12), 1e-3)   # A at b = 0
    AP = p[:, 2:3] * P
    W = weights(AP, wf, nv)
    J[:, 0] *= p[:, 2:3]                  # J was evaluated with A = 1: its A-proportional rows rescaled
    J[:, 1] *= p[:, 2:3]
    if fit_sigma:
        J[:, 4] *= p[:, 2:3]
    r = d - AP                            # residual (b = 0)
    chi = (W * r * r).sum(1)
    lam = np.full(K, 1e-3)
    act = np.arange(K)                     # the stars still in the arrays (compressed now and then)
    frozen = np.zeros(K, bool)             # finished: no longer updated, written out when dropped
    for it in range(iters + 1):
        if it < iters and not frozen.all():
            JW = J * W[:, None, :]
            Hd = JW @ J.transpose(0, 2, 1)
            g = (JW @ r[:, :, None])[..., 0]
            dg = Hd.reshape(-1, npar * npar)[:, ::npar + 1]         # the diagonal (a view)
            dg += lam[:, None] * np.maximum(dg, 1e-12)
            try:
                step = np.linalg.solve(Hd, g[..., None])[..., 0]
            except np.linalg.LinAlgError:
                step = np.zeros_like(g)
                for k in range(act.size):     # singular systems only (degenerate stamps); never per pixel
                    step[k] = np.linalg.lstsq(Hd[k], g[k], rcond=None)[0]
            np.clip(step[:, :2], -0.5, 0.5, out=step[:, :2])
            small = np.abs(step[:, :2]).max(1) < tol_px
            pn = p + step
            if fit_sigma:
                ds = np.clip(step[:, 4], -0.3 * p[:, 4], 0.3 * p[:, 4])
                small &= np.abs(ds) < tol_px
                pn[:, 4] = np.clip(p[:, 4] + ds, 0.2, 20.0)
            APn, Jn = model(pn, s2, st0)
            rn = d - APn
            rn -= pn[:, 3:4]
            Wn = weights(APn, wf, nv) if gain else W
            chin = (Wn * rn * rn).sum(1)
            better = np.isfinite(chin) & (chin <= chi) & ~frozen
            bc = better[:, None]
            p, r, chi = np.where(bc, pn, p), np.where(bc, rn, r), np.where(better, chin, chi)
            J = np.where(bc[:, :, None], Jn, J)
            if gain:
                W = np.where(bc, Wn, W)
            lam = np.where(better, np.maximum(lam * 0.1, 1e-6), lam * 10)
            frozen |= small | (lam >= 1e4)
        last = it == iters or frozen.all()
        if last or frozen.sum() * 4 >= act.size:    # write the finished stars out (their state has not changed
            u = np.ones(act.size, bool) if last else frozen          # since they finished) and drop them
            out[act[u]] = p[u]
            J4 = J[u][:, :4]
            H4[act[u]] = (J4 * W[u][:, None, :]) @ J4.transpose(0, 2, 1)      # Fisher matrix of (x, y, A, b)
            if last:
                break
            keep = ~frozen
            act, p, r, J, W, chi, lam, d, wf, nv = (a[keep] for a in (act, p, r, J, W, chi, lam, d, wf, nv))
            st0 = np.concatenate([c0[act], r0[act]])
            s2 = np.concatenate([s_in[act], s_in[act]])
            frozen = frozen[keep]
    return fit_outcome(out, H4, r0, c0, n, out[:, 4] if fit_sigma else s_in.copy())


def fit_outcome(params, fisher, r0, c0, n, s):
    """What :func:`fit_psf` returns from the final parameters ``params`` (K, >= 4) (x, y, A, b, ...) and the Fisher
    matrices ``fisher`` (K, 4, 4) of (x, y, A, b) of stamps of n x n pixels from (r0, c0), the widths ``s`` (K,):
    (x, y, A, b, s, cov, ok), cov the Fisher inverse, ok where the matrix is invertible, A > 0, the position finite,
    inside the stamp by more than half a pixel, and its variances positive."""
    K = params.shape[0]
    x, y, A, b = params[:, 0], params[:, 1], params[:, 2], params[:, 3]
    ok = np.isfinite(fisher).all((1, 2)) & (np.abs(np.linalg.det(fisher)) > 0)
    cov = np.full((K, 4, 4), np.nan)
    if ok.any():
        cov[ok] = np.linalg.inv(fisher[ok])
    half = n / 2.0
    ok &= (A > 0) & np.isfinite(x) & np.isfinite(y) & (np.abs(x - (c0 + half)) < half - 0.5) \
        & (np.abs(y - (r0 + half)) < half - 0.5) & (np.diagonal(cov, axis1=1, axis2=2)[:, :2] > 0).all(1)
    return x, y, A, b, s, cov, ok


def cut_stamps(R, valid, r, c, h, img=None, sat=None):
    """(K, n, n) stamps of the (H, W) image R centred on pixels (r, c) ((K,) int), n = 2h + 1, with their usable
    pixels ((K, n, n) float64, 1 = usable: inside the frame, ``valid`` ((H, W) bool, None = all) and, with ``img``
    and ``sat``, img < sat: not saturated) and the stamps' first row and column ((K,) int; pixels outside the
    frame repeat the nearest edge pixel's value, unusable)."""
    H, W = R.shape
    n = 2 * h + 1
    rr = r[:, None] - h + np.arange(n)[None, :]
    cc = c[:, None] - h + np.arange(n)[None, :]
    ok = ((rr >= 0) & (rr < H))[:, :, None] & ((cc >= 0) & (cc < W))[:, None, :]
    rcl, ccl = np.clip(rr, 0, H - 1)[:, :, None], np.clip(cc, 0, W - 1)[:, None, :]
    st = R[rcl, ccl]
    if valid is not None:
        ok &= valid[rcl, ccl]
    if img is not None and sat is not None:
        ok &= img[rcl, ccl] < sat
    return st, ok.astype(np.float64), rr[:, 0], cc[:, 0]
