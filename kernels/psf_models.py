"""Sensor realism for the dense star renderer: PSF models, motion smear and bright extended objects.

Used by :func:`dualsight.kernels.starfield.render_star_fields` whenever the sensor asks for more than the
Gaussian PSF of :mod:`dualsight.kernels.star_psf` (``SensorConfig.psf_model != "gaussian"``, a body rate
``rate_deg_s`` or ``bright_objects``).  Every light source (star, false star, bright object) is rendered as
the sum of *sub-sources*, each added exactly over the pixels it touches, in a fixed order, one case per
thread (no atomics: a case's float sums do not depend on scheduling):

* **Gaussian** (``psf_model = "gaussian"``): one pixel-integrated Gaussian of ``psf_sigma_px`` (exact; the
  values of :func:`dualsight.kernels.star_psf.splat_star`, computed by :func:`splat_gauss`).
* **Defocus disk** (``psf_model = "defocus"``): a uniform disk of radius R = ``defocus_radius_px``.
  Without ``defocus_gaussian`` every pixel gets the exact area of its intersection with the disk
  (closed form, :func:`disk_g`), so the image is the disk integrated exactly over the pixels.  With
  ``defocus_gaussian`` the disk is convolved with the Gaussian of ``psf_sigma_px``: the disk is replaced by a
  ring quadrature (:func:`defocus_quadrature`: two Gauss-Legendre rings in r^2 per equal-area annulus,
  >= 5 equally spaced points per ring, point spacing ~ max(0.4 min(sigma, R), 0.1) px) of pixel-integrated
  Gaussians.  The quadrature keeps every moment of the disk up to order 4 exactly (flux, centroid,
  R^2 / 4 and R^4 / 8 per axis); what remains is the Gaussian-smoothed residue of the point spacing.
* **Measured PSF image** (``psf_model = "image"``, ``psf_image = "file"``): an odd-sized (<= 64 px per
  side) array of non-negative numbers sampled on the sensor's own pixel grid (so already pixel-integrated),
  normalised to unit sum, centred on its middle pixel.  A star at (x, y) gets the image bilinearly
  resampled at its subpixel position: pixel (r, c) = F * P(c + 0.5 - x + hx, r + 0.5 - y + hy) with P
  bilinear between the image's samples (zero outside).  Bilinear weights sum to one, so the flux and the
  centroid are kept exactly; a second moment grows by phi (1 - phi) per axis (phi = the subpixel
  phase, 1/6 on average), none at integer phase.  The renderer is handed the image as an array (the
  ``psf`` argument, checked by :func:`dualsight.kernels.psf_image.check_psf`); it reads no file (the scene
  layer does: :func:`dualsight.scene.psf_file.sensor_psf`, once per process).
* **Bright extended objects** (``bright_objects`` with ``radius_px > 0``, e.g. the Moon): uniform disks,
  exact pixel areas as the defocus disk; the PSF (a few px) is neglected at their limb.  Bright points
  (``radius_px = 0``, planets) use the star PSF with a window of :data:`BRIGHT_WINDOW_SIGMA` sigma (their
  wings would otherwise be cut where they are still above the noise).  Saturation is the sensor's
  (``full_well_e`` then the ADC); blooming into neighbouring pixels is not modelled.

**Motion smear** (``rate_deg_s``, body rates w in the camera frame): a fixed inertial direction moves in the
camera frame as du/dt = -w x u.  The star positions handed to the renderer are those at *mid-exposure*;
each source's path over ``exposure_s`` = T is taken as the straight segment through its mid-exposure
position with the length and direction of the chord D = p(T/2) - p(-T/2) (both ends exactly rotated and
projected through the camera model, distortion included).  Approximation: the true path (a conic in a
pinhole image, a circle about the principal point for a pure roll) deviates from that segment by its
sagitta, about L^2 |cot beta| / (8 f) px for a path of length L (beta: angle between the star and the rate
axis, f: focal length in px); for a pure roll that is L^2 / (8 r), r the star's distance from the principal
point (e.g. L = 10 px: 0.125 px at r = 100 px for a roll, < 1e-3 px for cross-boresight rates anywhere in
the reference camera's field, f = 3656 px: checked against the exactly rotated and projected path).  The
rate is constant over the exposure.  The segment is rendered as K equally weighted sub-positions
p + c_k D, c_k = (k - (K - 1) / 2) / sqrt(K^2 - 1), k = 0..K-1, K = 1 + ceil(L / :data:`SMEAR_STEP_PX`)
(at most :data:`MAX_SMEAR_STEPS`): their mean is p and their variance along D is exactly L^2 / 12, the
uniform segment's (first and second moments exact, sub-position spacing < 0.2 px).  A roll about the
boresight gives each star its own length (L = |w_z| T r).

Taichi is initialised lazily (``dualsight.kernels.taichi_runtime``) on the first kernel call.
"""

import math

import numpy as np
import taichi as ti

from dualsight.kernels import star_psf
from dualsight.kernels.taichi_runtime import KernelCache
from dualsight.kernels.psf_image import check_psf

__all__ = ["SMEAR_STEP_PX", "MAX_SMEAR_STEPS", "BRIGHT_WINDOW_SIGMA", "defocus_quadrature", "smear_vectors",
           "smear_steps", "bright_object_sources", "Sources", "prepare_sources", "splat_sources"]

SMEAR_STEP_PX = 0.2
"""Largest spacing (px) of the sub-positions along a smear path."""
MAX_SMEAR_STEPS = 4096
"""Most sub-positions per smeared source (longer paths get a wider spacing; bounds the render's cost)."""
BRIGHT_WINDOW_SIGMA = 10.0
"""Gaussian window (sigma) of bright point objects: 2 Phi(-10) ~ 1.5e-23 of their flux falls outside."""
QUAD_SPACING_SIGMA = 0.4
"""Point spacing of the defocus ring quadrature in units of min(sigma, R)."""
QUAD_MIN_SPACING_PX = 0.1
"""Smallest point spacing (px) of the defocus ring quadrature."""
QUAD_MAX_POINTS = 16384
"""Sets the defocus quadrature's largest spacing, R sqrt(pi / QUAD_MAX_POINTS) (~1.4x as many points at most)."""

MODEL_GAUSSIAN, MODEL_DEFOCUS, MODEL_IMAGE = 0, 1, 2
_MODEL_IDS = {"gaussian": MODEL_GAUSSIAN, "defocus": MODEL_DEFOCUS, "image": MODEL_IMAGE}


# ============================================================================ geometry helpers (numpy)
def defocus_quadrature(radius: float, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point quadrature of a uniform disk of ``radius`` R px, for convolution with a Gaussian of ``sigma`` px.

    A uniform disk is uniform in s = r^2 on [0, R^2] and in angle.  s is cut into n = ceil(R / 2h) equal
    intervals (equal-area annuli), h = max(0.4 min(sigma, R), 0.1 px, R sqrt(pi / 16384)), each with its two
    Gauss-Legendre nodes s = s_mid -+ ds / (2 sqrt 3) (weight ds / (2 R^2) each); a ring of radius sqrt(s)
    carries max(5, ceil(2 pi r / h)) equally spaced points (each ring turned by the golden angle).  The
    quadrature is exact for polynomials of degree <= 3 in s (radial moments up to r^6) and, with >= 5
    points per ring, for every moment of order <= 4 in (x, y): flux 1, centroid 0, sum w x^2 = R^2 / 4,
    sum w x^4 = R^4 / 8, no odd moments, isotropic (to rounding).  Pixel values of the convolved disk,
    against a 40 x 256-node Gauss-Legendre x trapezoid reference: within 3e-4 of the peak for R = 2.5,
    sigma = 0.7 px, 1e-4 for R = 1.5, sigma = 0.5, 1.5e-3 for R = 3, sigma = 0.3 or R = 5, sigma = 1, but 1.5e-2
    for sigma = 0.1 px (the 0.1 px floor of the spacing): for sigma << 1 px prefer the exact disk
    (``defocus_gaussian = false``).  Points: ~pi R^2 / h^2, 255 for R = 1.5, sigma = 0.5, at most ~22k (the
    last term of h takes over for R > 7.2 px when sigma <= 0.25 px, for R > 29 px at sigma = 1 px).
    Returns (dx, dy, w) float64 arrays.
    """
    R = float(radius)
    h = max(QUAD_SPACING_SIGMA * min(float(sigma), R), QUAD_MIN_SPACING_PX, R * math.sqrt(math.pi / QUAD_MAX_POINTS))
    n = max(1, math.ceil(R / (2.0 * h) - 1e-9))
    edges = np.linspace(0.0, R * R, n + 1)
    xs, ys, ws = [], [], []
    golden = math.pi * (3.0 - math.sqrt(5.0))
    k = 0
    for lo, hi in zip(edges[:-1], edges[1:]):  # a few rings (<= 2 R / h, 500 with the bounds), not pixels or stars
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        for sgn in (-1.0, 1.0):
            rk = math.sqrt(mid + sgn * half / math.sqrt(3.0))
            m = max(5, math.ceil(2.0 * math.pi * rk / h))
            th = k * golden + 2.0 * math.pi * np.arange(m) / m
            xs.append(rk * np.cos(th))
            ys.append(rk * np.sin(th))
            ws.append(np.full(m, half / (R * R) / m))
            k += 1
    return (np.ascontiguousarray(np.concatenate(xs)), np.ascontiguousarray(np.concatenate(ys)),
            np.ascontiguousarray(np.concatenate(ws)))


def _rotate(u: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Vectors u (..., 3) rotated by the rotation vector phi (3,) (Rodrigues)."""
    th = float(np.linalg.norm(phi))
    if th == 0.0:
        return u
    k = phi / th
    return (u * math.cos(th) + np.cross(k, u) * math.sin(th)
            + k * (u @ k)[..., None] * (1.0 - math.cos(th)))


def smear_vectors(x, y, rate_deg_s, exposure_s: float, camera) -> tuple[np.ndarray, np.ndarray]:
    """Smear chords (Dx, Dy) (px, each the shape of x) of sources at mid-exposure pixel positions (x, y).

    The camera turns at the constant body rate w (deg/s, camera frame) for ``exposure_s`` = T; a fixed
    inertial direction u moves as du/dt = -w x u, so at t = +-T/2 it is u rotated by -+w T/2.  Both ends
    are projected with ``camera.project`` (``camera``: anything with ``backproject`` and ``project`` as
    ``dualsight.scene.camera.Camera``); D = p(T/2) - p(-T/2).  Non-finite inputs or ends behind the
    camera give D = 0.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    w = np.radians(np.asarray(rate_deg_s, np.float64))
    fin = np.isfinite(x) & np.isfinite(y) & (np.abs(x) < 1e7) & (np.abs(y) < 1e7)
    px = np.stack([np.where(fin, x, 0.0), np.where(fin, y, 0.0)], axis=-1)
    u = camera.backproject(px)
    half = w * (0.5 * float(exposure_s))
    p1, f1 = camera.project(_rotate(u, -half))
    p0, f0 = camera.project(_rotate(u, half))
    d = p1 - p0
    good = fin & f0 & f1 & np.all(np.isfinite(d), axis=-1)
    return np.where(good, d[..., 0], 0.0), np.where(good, d[..., 1], 0.0)


def smear_steps(dx, dy) -> np.ndarray:
    """Sub-positions per source: 1 + ceil(L / SMEAR_STEP_PX) for a chord of L > 0 px (at most
    MAX_SMEAR_STEPS), 1 for L = 0; int32 of the shape of dx."""
    L = np.hypot(dx, dy)
    k = 1 + np.ceil(np.minimum(L, SMEAR_STEP_PX * MAX_SMEAR_STEPS) / SMEAR_STEP_PX)
    return np.ascontiguousarray(np.where(L > 0, np.minimum(k, MAX_SMEAR_STEPS), 1).astype(np.int32))


def bright_object_sources(objects, cfg, camera, attitude):
    """Pixel positions and fluxes of ``cfg.bright_objects`` in every case's frame.

    objects : sequence of dicts with ra_deg, dec_deg (ICRS), vmag, radius_px.
    attitude : (B, 3, 3) inertial -> camera rotation of each case.
    Returns (x, y, flux_e, radius_px, ok uint8), each (B, K); objects behind the camera are not ok.
    Flux: ``flux_from_magnitude`` (the sensor's zero point and exposure).
    """
    A = np.asarray(attitude, np.float64)
    if A.ndim != 3 or A.shape[1:] != (3, 3) or not np.all(np.isfinite(A)):
        raise ValueError(f"attitude must be a finite (B, 3, 3) array, got shape {A.shape}")
    ra = np.radians([o["ra_deg"] for o in objects])
    dec = np.radians([o["dec_deg"] for o in objects])
    u = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)   # (K, 3)
    v = np.einsum("bij,kj->bki", A, u)
    px, front = camera.project(v)
    B, K = v.shape[:2]
    vmag = np.array([o["vmag"] for o in objects], np.float64)
    flux = np.broadcast_to(cfg.zero_mag_rate_e_per_s * np.power(10.0, -0.4 * vmag) * cfg.exposure_s, (B, K))
    rad = np.broadcast_to(np.array([o["radius_px"] for o in objects], np.float64), (B, K))
    ok = front & np.all(np.isfinite(px), axis=-1)
    return (np.where(ok, px[..., 0], 0.0), np.where(ok, px[..., 1], 0.0), np.ascontiguousarray(flux),
            np.ascontiguousarray(rad), ok.astype(np.uint8))


class Sources:
    """Every light source of a batch for :func:`splat_sources`: (B, S) float64 x, y, flux, radius (px, > 0 =
    exact uniform disk), wsig (Gaussian window, sigma), dx, dy (smear chord, px); (B, S) uint8 ok and int32
    nsub (sub-positions); the PSF model's id, quadrature (qx, qy, qw) and image."""

    def __init__(self, x, y, flux, ok, radius, wsig, dx, dy, nsub, model, qx, qy, qw, img):
        c = np.ascontiguousarray
        self.x, self.y, self.flux, self.ok = c(x, np.float64), c(y, np.float64), c(flux, np.float64), c(ok, np.uint8)
        self.radius, self.wsig = c(radius, np.float64), c(wsig, np.float64)
        self.dx, self.dy, self.nsub = c(dx, np.float64), c(dy, np.float64), c(nsub, np.int32)
        self.model, self.qx, self.qy, self.qw, self.img = model, c(qx), c(qy), c(qw), c(img, np.float64)

    def rows(self, sl: slice) -> tuple:
        return tuple(a[sl] for a in (self.x, self.y, self.flux, self.ok, self.radius, self.wsig, self.dx, self.dy,
                                     self.nsub))


def prepare_sources(x, y, f, ok, cfg, camera=None, attitude=None, psf: np.ndarray | None = None) -> Sources:
    """The :class:`Sources` of validated star arrays (B, S) (stars and false stars), with the sensor's
    bright objects appended and smear chords computed (``camera`` needed for a rate or bright objects,
    ``attitude`` (B, 3, 3) for bright objects; ``psf``, the measured PSF as a (ny, nx) float64 array of unit
    sum (fraction of a star's electrons per pixel, odd sides <= 64 px), for ``cfg.psf_model = "image"``,
    else ignored)."""
    B, S = x.shape
    model = _MODEL_IDS[cfg.psf_model]
    star_rad = cfg.defocus_radius_px if (model == MODEL_DEFOCUS and not cfg.defocus_gaussian) else 0.0
    rad = np.full((B, S), star_rad)
    wsig = np.full((B, S), float(cfg.psf_window_sigma))
    if cfg.bright_objects:
        if camera is None or attitude is None:
            raise ValueError("SensorConfig.bright_objects needs the camera and each case's attitude "
                             "(render_star_fields(..., camera=, attitude=))")
        bx, by, bf, br, bok = bright_object_sources(cfg.bright_objects, cfg, camera, attitude)
        if bx.shape[0] != B:
            raise ValueError(f"attitude must have one (3, 3) matrix per case ({B}), got {bx.shape[0]}")
        x, y, f, ok = (np.concatenate([a, b], axis=1) for a, b in ((x, bx), (y, by), (f, bf), (ok, bok)))
        rad = np.concatenate([rad, np.where(br > 0, br, star_rad)], axis=1)
        wsig = np.concatenate([wsig, np.full(br.shape, BRIGHT_WINDOW_SIGMA)], axis=1)
    if cfg.has_smear:
        if camera is None:
            raise ValueError("SensorConfig.rate_deg_s needs the camera model (render_star_fields(..., camera=))")
        dx, dy = smear_vectors(x, y, cfg.rate_deg_s, cfg.exposure_s, camera)
    else:
        dx = dy = np.zeros(x.shape)
    if model == MODEL_DEFOCUS and cfg.defocus_gaussian:
        qx, qy, qw = defocus_quadrature(cfg.defocus_radius_px, cfg.psf_sigma_px)
    else:
        qx, qy, qw = np.zeros(1), np.zeros(1), np.ones(1)
    img = check_psf(psf, cfg.psf_model)   # a (1, 1) zero placeholder for the other models
    return Sources(x, y, f, ok, rad, wsig, dx, dy, smear_steps(dx, dy), model, qx, qy, qw, img)


# ============================================================================ Taichi funcs
@ti.func
def _circle_integral(s, R):
    """Integral of sqrt(R^2 - t^2) dt from 0 to s, 0 <= s <= R (f64)."""
    return ti.f64(0.5) * (s * ti.sqrt(ti.max(R * R - s * s, ti.f64(0.0)))
                          + R * R * ti.asin(ti.min(s / R, ti.f64(1.0))))


@ti.func
def disk_g(x, y, R):
    """Signed area of {0 <= s <= x, 0 <= t <= y, s^2 + t^2 <= R^2} (negative for x or y < 0; f64).

    The area of a rectangle [x0, x1] x [y0, y1] intersected with the disk of radius R about the origin is
    g(x1, y1) - g(x0, y1) - g(x1, y0) + g(x0, y0).
    """
    ax = ti.min(ti.abs(x), R)
    ay = ti.min(ti.abs(y), R)
    g = ax * ay
    if ax * ax + ay * ay > R * R:  # the corner is outside: the arc crosses the rectangle
        xc = ti.sqrt(ti.max(R * R - ay * ay, ti.f64(0.0)))
        g = xc * ay + _circle_integral(ax, R) - _circle_integral(xc, R)
    if x < ti.f64(0.0):
        g = -g
    if y < ti.f64(0.0):
        g = -g
    return g


@ti.func
def splat_disk(buf: ti.template(), b, xc, yc, flux, R, W, H):
    """Add a uniform disk (radius R px, ``flux`` e-) centred at (xc, yc), each pixel its exact area share."""
    c0 = ti.max(ti.cast(ti.floor(xc - R), ti.i32), 0)
    c1 = ti.min(ti.cast(ti.floor(xc + R), ti.i32) + 1, W)
    r0 = ti.max(ti.cast(ti.floor(yc - R), ti.i32), 0)
    r1 = ti.min(ti.cast(ti.floor(yc + R), ti.i32) + 1, H)
    dens = flux / (ti.f64(math.pi) * R * R)
    for r in range(r0, r1):
        ylo = ti.cast(r, ti.f64) - yc
        yhi = ylo + ti.f64(1.0)
        xl = ti.cast(c0, ti.f64) - xc
        glo = disk_g(xl, ylo, R)
        ghi = disk_g(xl, yhi, R)
        for c in range(c0, c1):
            xr = ti.cast(c + 1, ti.f64) - xc
            glo_r = disk_g(xr, ylo, R)
            ghi_r = disk_g(xr, yhi, R)
            a = ghi_r - ghi - glo_r + glo
            # pixels wholly outside or inside the disk: exactly 0 or 1 (no rounding residue of the g's)
            nx_ = ti.max(ti.max(xr - ti.f64(1.0), -xr), ti.f64(0.0))   # distance to the pixel's nearest point
            ny_ = ti.max(ti.max(ylo, -yhi), ti.f64(0.0))
            fx_ = ti.max(ti.abs(xr - ti.f64(1.0)), ti.abs(xr))         # ... and to its farthest corner
            fy_ = ti.max(ti.abs(ylo), ti.abs(yhi))
            if nx_ * nx_ + ny_ * ny_ >= R * R:
                a = ti.f64(0.0)
            elif fx_ * fx_ + fy_ * fy_ <= R * R:
                a = ti.f64(1.0)
            glo = glo_r
            ghi = ghi_r
            if a > ti.f64(0.0):
                buf[b, r, c] = buf[b, r, c] + ti.cast(dens * a, ti.f32)


@ti.func
def splat_gauss(buf: ti.template(), b, col: ti.template(), xc, yc, flux, sigma, c0, c1, r0, r1):
    """Add a pixel-integrated Gaussian over the window [c0,c1) x [r0,r1): the same values as
    :func:`dualsight.kernels.star_psf.splat_star`, with the column factors computed once into
    ``col[b, :]`` (c1 - c0 erf differences instead of one set per row)."""
    inv = ti.f64(1.0) / sigma
    px_lo = star_psf.phi((ti.cast(c0, ti.f64) - xc) * inv)
    for c in range(c0, c1):
        px_hi = star_psf.phi((ti.cast(c + 1, ti.f64) - xc) * inv)
        col[b, c - c0] = px_hi - px_lo
        px_lo = px_hi
    py_lo = star_psf.phi((ti.cast(r0, ti.f64) - yc) * inv)
    for r in range(r0, r1):
        py_hi = star_psf.phi((ti.cast(r + 1, ti.f64) - yc) * inv)
        fy = flux * (py_hi - py_lo)
        py_lo = py_hi
        for c in range(c0, c1):
            buf[b, r, c] = buf[b, r, c] + ti.cast(fy * col[b, c - c0], ti.f32)


@ti.func
def _img_at(img: ti.template(), j, i, ny, nx):
    v = ti.f64(0.0)
    if j >= 0 and j < ny and i >= 0 and i < nx:
        v = img[j, i]
    return v


@ti.func
def splat_image(buf: ti.template(), b, xc, yc, flux, img: ti.template(), W, H):
    """Add the unit-sum PSF image ``img`` (ny, nx odd) bilinearly resampled with its middle pixel's centre at
    (xc, yc): pixel (r, c) = flux * P(c + 0.5 - xc + nx // 2, r + 0.5 - yc + ny // 2)."""
    ny = img.shape[0]
    nx = img.shape[1]
    ux = ti.f64(0.5) - xc + ti.cast(nx // 2, ti.f64)
    vy = ti.f64(0.5) - yc + ti.cast(ny // 2, ti.f64)
    fsx = ti.floor(ux)
    fsy = ti.floor(vy)
    fu = ux - fsx
    fv = vy - fsy
    ish = ti.cast(fsx, ti.i32)  # image column i0 = c + ish, row j0 = r + jsh
    jsh = ti.cast(fsy, ti.i32)
    c0 = ti.max(-1 - ish, 0)
    c1 = ti.min(nx - ish, W)
    r0 = ti.max(-1 - jsh, 0)
    r1 = ti.min(ny - jsh, H)
    for r in range(r0, r1):
        j0 = r + jsh
        for c in range(c0, c1):
            i0 = c + ish
            top = (ti.f64(1.0) - fu) * _img_at(img, j0, i0, ny, nx) + fu * _img_at(img, j0, i0 + 1, ny, nx)
            bot = (ti.f64(1.0) - fu) * _img_at(img, j0 + 1, i0, ny, nx) + fu * _img_at(img, j0 + 1, i0 + 1, ny, nx)
            v = flux * ((ti.f64(1.0) - fv) * top + fv * bot)
            buf[b, r, c] = buf[b, r, c] + ti.cast(v, ti.f32)


# ============================================================================ kernel (built lazily)
_KERNELS = KernelCache()


def _build_splat_sources(_dtype=None):
    @ti.kernel
    def splat_src(x: ti.types.ndarray(dtype=ti.f64, ndim=2), y: ti.types.ndarray(dtype=ti.f64, ndim=2),
                  flux: ti.types.ndarray(dtype=ti.f64, ndim=2), ok: ti.types.ndarray(dtype=ti.u8, ndim=2),
                  rad: ti.types.ndarray(dtype=ti.f64, ndim=2), wsig: ti.types.ndarray(dtype=ti.f64, ndim=2),
                  dx: ti.types.ndarray(dtype=ti.f64, ndim=2), dy: ti.types.ndarray(dtype=ti.f64, ndim=2),
                  nsub: ti.types.ndarray(dtype=ti.i32, ndim=2), buf: ti.types.ndarray(dtype=ti.f32, ndim=3),
                  sigma: ti.f64, model: ti.i32, qx: ti.types.ndarray(dtype=ti.f64, ndim=1),
                  qy: ti.types.ndarray(dtype=ti.f64, ndim=1), qw: ti.types.ndarray(dtype=ti.f64, ndim=1),
                  img: ti.types.ndarray(dtype=ti.f64, ndim=2), col: ti.types.ndarray(dtype=ti.f64, ndim=2)):
        W = buf.shape[2]
        H = buf.shape[1]
        lim = ti.f64(1.0e7)
        for b in range(x.shape[0]):  # parallel over cases; sources, sub-positions, quadrature points in order
            for s in range(x.shape[1]):
                f = flux[b, s]
                xs = x[b, s]
                ys = y[b, s]
                ddx = dx[b, s]
                ddy = dy[b, s]
                # comparisons are False for NaN: NaN positions, fluxes or chords skip the source
                if (ok[b, s] != 0 and f > ti.f64(0.0) and f < ti.f64(1.0e300) and ti.abs(xs) < lim
                        and ti.abs(ys) < lim and ti.abs(ddx) < lim and ti.abs(ddy) < lim):
                    K = ti.max(nsub[b, s], 1)
                    fk = f / ti.cast(K, ti.f64)
                    cs = ti.f64(0.0)
                    if K > 1:
                        cs = ti.f64(1.0) / ti.sqrt(ti.cast(K * K - 1, ti.f64))
                    R = rad[b, s]
                    ws = wsig[b, s]
                    for k in range(K):
                        t = (ti.cast(k, ti.f64) - ti.f64(0.5) * ti.cast(K - 1, ti.f64)) * cs
                        xk = xs + t * ddx
                        yk = ys + t * ddy
                        if R > ti.f64(0.0):
                            splat_disk(buf, b, xk, yk, fk, R, W, H)
                        elif model == MODEL_IMAGE:
                            splat_image(buf, b, xk, yk, fk, img, W, H)
                        else:
                            for m in range(qx.shape[0]):
                                xm = xk + qx[m]
                                ym = yk + qy[m]
                                fm = fk * qw[m]
                                c0, c1, r0, r1 = star_psf.star_window(xm, ym, fm, 1, sigma, ws, W, H)
                                if c1 > c0:
                                    splat_gauss(buf, b, col, xm, ym, fm, sigma, c0, c1, r0, r1)
    return splat_src


_KERNELS.builders.update({"splat_sources": _build_splat_sources})


def splat_sources(src: Sources, sl: slice, buf: np.ndarray, sigma_px: float) -> None:
    """Add the light of cases ``sl`` of ``src`` to ``buf`` ((n, H, W) float32 signal, e-, in place)."""
    x, y, f, ok, rad, wsig, dx, dy, nsub = src.rows(sl)
    width = 2 * math.ceil(float(wsig.max(initial=1.0)) * float(sigma_px) + 1.0) + 3   # widest Gaussian window (+2:
    col = np.empty((x.shape[0], max(1, min(width, buf.shape[2]))), np.float64)          # rounding); per-case factors
    _KERNELS.get("splat_sources")(x, y, f, ok, rad, wsig, dx, dy, nsub, buf, float(sigma_px), int(src.model),
                                  src.qx, src.qy, src.qw, src.img, col)
