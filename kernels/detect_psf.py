"""PSF stage of the real-sensor detector (:mod:`dualsight.kernels.detect_local`): the pixel-integrated
Gaussian PSF (1-D kernels, sharpness limit for the hot-pixel test), the Cramér-Rao centroid bound, and the
batched weighted least-squares PSF fit of star stamps.  Pure numpy functions over arrays."""

import math

import numpy as np

from dualsight.kernels.detect_background import _Phi, _phi


# ============================================================================ PSF helpers
def psf_kernel_1d(sigma: float) -> np.ndarray:
    """Normalised 1-D pixel-integrated Gaussian, k_i = Phi((i + 1/2) / sigma) - Phi((i - 1/2) / sigma),
    |i| <= ceil(3 sigma)."""
    h = max(1, int(math.ceil(3.0 * sigma)))
    i = np.arange(-h, h + 1, dtype=np.float64)
    k = _Phi((i + 0.5) / sigma) - _Phi((i - 0.5) / sigma)
    return k / k.sum()


def sharpness_limit(sigma: float) -> float:
    """Largest ratio of a pixel-integrated Gaussian star's brightest pixel to the mean of its 4 neighbours
    (over sub-pixel positions: the star centred on a pixel), a0 / a1 (module docstring, step 4)."""
    u = np.linspace(-0.5, 0.5, 21)
    a0 = _Phi((0.5 - u) / sigma) - _Phi((-0.5 - u) / sigma)
    ap = _Phi((1.5 - u) / sigma) - _Phi((0.5 - u) / sigma)
    am = _Phi((-0.5 - u) / sigma) - _Phi((-1.5 - u) / sigma)
    # 2-D, offsets (u, v): peak a0(u) a0(v); neighbours a0(v)(ap(u) + am(u)) + a0(u)(ap(v) + am(v))
    A0 = a0[:, None] * a0[None, :]
    N4 = a0[None, :] * (ap + am)[:, None] + a0[:, None] * (ap + am)[None, :]
    return float((A0 / (N4 / 4.0)).max())


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
def _profiles(x, c0, n, s):
    """1-D pixel fractions and their derivatives (d/dx, d/ds) of stamps starting at pixel c0: (K, n) each."""
    c = c0[:, None] + np.arange(n)[None, :]
    a = (c - x[:, None]) / s[:, None]
    b = a + 1.0 / s[:, None]
    Pa, Pb, pa, pb = _Phi(a), _Phi(b), _phi(a), _phi(b)
    return Pb - Pa, -(pb - pa) / s[:, None], -(b * pb - a * pa) / s[:, None]


def _fit(stamp, w0, r0, c0, x, y, s, noise, gain, fit_sigma=False, iters=10):
    """Weighted least-squares fit of A P(x, y; s) + b to (K, n, n) stamps whose top-left pixel is (r0, c0).

    w0 : (K, n, n) 1 = usable pixel, 0 = excluded (saturated, hot, outside the frame).  x, y, s : initial
    values (K,).  Returns x, y, A, b, s, cov (K, 4, 4) of (x, y, A, b) (Fisher inverse), ok (K,)."""
    K, n, _ = stamp.shape
    x, y, s = x.astype(np.float64).copy(), y.astype(np.float64).copy(), s.astype(np.float64).copy()
    d = stamp.astype(np.float64)
    nv = noise.astype(np.float64)[:, None, None] ** 2
    px, _, _ = _profiles(x, c0, n, s)
    py, _, _ = _profiles(y, r0, n, s)
    P = py[:, :, None] * px[:, None, :]
    A = np.maximum((w0 * d * P).sum((1, 2)) / np.maximum((w0 * P * P).sum((1, 2)), 1e-12), 1e-3)
    b = np.zeros(K)
    npar = 5 if fit_sigma else 4
    lam = np.full(K, 1e-3)

    def model(i, x, y, A, b, s):          # stars i (index array) at parameters (x, y, A, b, s) of those stars
        px, dpx, spx = _profiles(x, c0[i], n, s)
        py, dpy, spy = _profiles(y, r0[i], n, s)
        P = py[:, :, None] * px[:, None, :]
        mu = A[:, None, None] * P + b[:, None, None]
        k = len(i)
        J = np.empty((k, n, n, npar))
        Ay = A[:, None] * py
        np.multiply(Ay[:, :, None], dpx[:, None, :], out=J[..., 0])
        np.multiply((A[:, None] * dpy)[:, :, None], px[:, None, :], out=J[..., 1])
        J[..., 2] = P
        J[..., 3] = 1.0
        if fit_sigma:
            J[..., 4] = A[:, None, None] * (spy[:, :, None] * px[:, None, :] + py[:, :, None] * spx[:, None, :])
        return mu, J.reshape(k, n * n, npar)

    def weights(i, mu, b):
        var = nv[i] + (np.maximum(mu - b[:, None, None], 0.0) / gain if gain else 0.0)
        return (w0[i] / var).reshape(len(i), -1)

    everyone = np.arange(K)
    dflat = d.reshape(K, -1)
    mu, J = model(everyone, x, y, A, b, s)
    W = weights(everyone, mu, b)
    chi = (W * (dflat - mu.reshape(K, -1)) ** 2).sum(1)
    eye = np.eye(npar)[None]
    active = everyone
    for _ in range(iters):          # Levenberg-Marquardt; a star leaves the loop when it has converged
        if active.size == 0:
            break
        i = active
        Ji, Wi = J[i], W[i]
        r = dflat[i] - mu[i].reshape(len(i), -1)
        JW = Ji * Wi[:, :, None]
        H = JW.transpose(0, 2, 1) @ Ji
        g = np.einsum("kpj,kp->kj", JW, r)
        diag = np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-12)
        Hd = H + lam[i, None, None] * eye * diag[:, :, None]
        try:
            step = np.linalg.solve(Hd, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.zeros_like(g)
            for k in range(len(i)):     # singular systems only (degenerate stamps); never per pixel
                step[k] = np.linalg.lstsq(Hd[k], g[k], rcond=None)[0]
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        if fit_sigma:
            step[:, 4] = np.clip(step[:, 4], -0.3 * s[i], 0.3 * s[i])
        xn, yn, An, bn = x[i] + step[:, 0], y[i] + step[:, 1], A[i] + step[:, 2], b[i] + step[:, 3]
        sn = np.clip(s[i] + step[:, 4], 0.2, 20.0) if fit_sigma else s[i]
        mun, Jn = model(i, xn, yn, An, bn, sn)
        Wn = weights(i, mun, bn)
        chin = (Wn * (dflat[i] - mun.reshape(len(i), -1)) ** 2).sum(1)
        better = np.isfinite(chin) & (chin <= chi[i])
        u = i[better]
        x[u], y[u], A[u], b[u], s[u] = xn[better], yn[better], An[better], bn[better], sn[better]
        mu[u], J[u], W[u], chi[u] = mun[better], Jn[better], Wn[better], chin[better]
        lam[i] = np.where(better, np.maximum(lam[i] / 10, 1e-6), lam[i] * 10)
        done = (better & (np.abs(step[:, :2]).max(1) < 1e-4)) | (lam[i] >= 1e4)
        active = i[~done]
    J4 = J[..., :4]
    H = (J4 * W[:, :, None]).transpose(0, 2, 1) @ J4
    ok = np.isfinite(H).all((1, 2)) & (np.abs(np.linalg.det(H)) > 0)
    cov = np.full((K, 4, 4), np.nan)
    if ok.any():
        cov[ok] = np.linalg.inv(H[ok])
    half = n / 2.0
    ok &= (A > 0) & np.isfinite(x) & np.isfinite(y) & (np.abs(x - (c0 + half)) < half - 0.5) \
        & (np.abs(y - (r0 + half)) < half - 0.5) & (np.diagonal(cov, axis1=1, axis2=2)[:, :2] > 0).all(1)
    return x, y, A, b, s, cov, ok


def _stamps(R, valid, r, c, h):
    """(K, n, n) stamps of R and of the usable pixels (inside the frame and ``valid``, None = all) centred on
    pixels (r, c), n = 2h + 1, and the stamps' first row and column."""
    H, W = R.shape
    n = 2 * h + 1
    rr = r[:, None] - h + np.arange(n)[None, :]
    cc = c[:, None] - h + np.arange(n)[None, :]
    ok = ((rr >= 0) & (rr < H))[:, :, None] & ((cc >= 0) & (cc < W))[:, None, :]
    rcl, ccl = np.clip(rr, 0, H - 1)[:, :, None], np.clip(cc, 0, W - 1)[:, None, :]
    st = R[rcl, ccl]
    if valid is not None:
        ok &= valid[rcl, ccl]
    return st, ok.astype(np.float64), rr[:, 0], cc[:, 0]
