"""Which object of a solved star frame is the target spacecraft (``hil star --target``; issue 23, point 3).

The rule, in order:

1. **Resolved**: the frame's largest blob (the blobber's, ``nav/blobber.run_blobber`` on the background-subtracted
   frame at ``k_sigma`` x the frame's noise) is the target when it has more pixels than any star can make
   (``nav/resolved_blobs.star_blob_limit`` of :func:`brightest_star_npix`: the brightest catalog star, V -1.46,
   through this frame's zero point, PSF width and threshold).  Its centre of brightness is the bearing and its
   pixel count gives the range by Eq. 1 with the target file's projected-area table (min / estimate / max).
2. **Point-like**: otherwise the brightest listed unknown object (``nav/unknown_objects.py``: a detection that no
   catalog star explains, at least ``mag_limit`` bright: fainter ones are mostly stars the catalog lacks); with a
   direction ``near`` (ICRS unit vector) and radius, the listed unknown object nearest that direction within the
   radius.
3. Otherwise none, with the reason.

A resolved blob's range (Eq. 1, ``nav/range.range_eq1``) needs the silhouette's pixels, but the blob above the
threshold t is the silhouette blurred by the PSF: a straight edge of a region of intensity I (ADU per pixel) blurred
by a Gaussian of width s lies above a level v out to ``d(v) = s Phi^-1(1 - v / I)`` px outside the edge (Phi the
standard normal CDF).  A target that outshines the stars saturates (I >> the saturation level L): the blob then
spreads ~3-5 s beyond the silhouette.  With the plateau's pixels N_L (>= L), the blob's N_t and its perimeter P_t,
Steiner's formula for convex shapes (N(d) = A0 + P0 d + pi d^2, P(d) = P0 + 2 pi d) gives the rim's width
``w = d(t) - d(L)`` from ``pi w^2 - P_t w + (N_t - N_L) = 0``, I from ``d(t; I) - d(L; I) = w`` (bisection; the
width falls monotonically with I) and the silhouette ``A0 = N_t - P_t d(t) + pi d(t)^2``
(:func:`silhouette_pixels`).  An unsaturated blob takes I from its brightest pixels.  The axis ratio of the
silhouette is the blob's with d(t) taken off each semi-axis (a uniform ellipse's semi-axis is 2 sqrt(lambda)).

A star's blob above a threshold t: a Gaussian PSF of width s (px) and total flux F has the pixel values
``F / (2 pi s^2) exp(-r^2 / (2 s^2))`` (well sampled), above t out to ``r^2 = 2 s^2 ln(F / (2 pi s^2 t))``: it
covers ``pi r^2`` pixels, saturated or not (saturation flattens the core, not the contour).

Units: px, ADU, rad.  Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

__all__ = ["BRIGHTEST_STAR_V", "brightest_star_npix", "FieldTarget", "pick_point_target", "edge_offset_px",
           "rim_intensity", "silhouette_pixels", "silhouette_axis_ratio"]

BRIGHTEST_STAR_V = -1.46
"""Sirius, the brightest star of the catalog (Hipparcos V)."""


def brightest_star_npix(zp_mag: float, psf_sigma_px: float, threshold_adu: float,
                        vmag: float = BRIGHTEST_STAR_V) -> float:
    """Pixels above ``threshold_adu`` (ADU above the background) of a star of magnitude ``vmag`` through the zero
    point ``zp_mag`` (V = zp - 2.5 log10 F) and a Gaussian PSF of width ``psf_sigma_px`` (module docstring); at
    least 1."""
    F = 10.0 ** (-0.4 * (vmag - zp_mag))
    s2 = float(psf_sigma_px) ** 2
    q = F / (2 * math.pi * s2 * float(threshold_adu))
    return max(1.0, 2 * math.pi * s2 * math.log(q)) if q > 1 else 1.0


@dataclass(frozen=True)
class FieldTarget:
    """The target of one frame: ``kind`` "resolved", "point" or None (not found, ``reason`` says why);
    ``xy`` (2,) centre of brightness (px); ``pixels`` its blob's pixels; ``sigma_px`` its centroid's 1-sigma per
    axis; ``index`` the unknown object it is (row of ``UnknownObjects``, -1 for a resolved blob);
    ``range_m``, ``range_min_m``, ``range_max_m`` (resolved only)."""

    kind: str | None
    reason: str | None = None
    xy: tuple[float, float] | None = None
    pixels: int | None = None
    sigma_px: float | None = None
    index: int = -1
    range_m: float | None = None
    range_min_m: float | None = None
    range_max_m: float | None = None


def pick_point_target(unknown_u: np.ndarray, flux: np.ndarray, near_u: np.ndarray | None = None,
                      radius_rad: float | None = None) -> tuple[int, str | None]:
    """(row of the chosen unknown object or -1, reason when none) for a point-like target (module docstring, 2).

    unknown_u (U, 3) ICRS directions of the unknown objects; flux (U,) their fluxes; near_u (3,) ICRS unit vector
    and radius_rad: choose the nearest within the radius instead of the brightest."""
    U = len(flux)
    if U == 0:
        return -1, "no unknown object in the image"
    if near_u is None:
        return int(np.argmax(np.asarray(flux, np.float64))), None
    u = np.asarray(unknown_u, np.float64).reshape(U, 3)
    ang = np.arccos(np.clip(u @ np.asarray(near_u, np.float64), -1.0, 1.0))
    j = int(np.argmin(ang))
    if ang[j] > radius_rad:
        return -1, (f"no unknown object within {math.degrees(radius_rad):g} deg of --target-near (nearest "
                    f"{math.degrees(ang[j]):.3f} deg)")
    return j, None


_PHI = NormalDist()


def edge_offset_px(level: float, intensity: float, psf_sigma_px: float) -> float:
    """How far (px) outside a straight edge of a region of ``intensity`` (ADU per pixel) blurred by a Gaussian PSF
    of width ``psf_sigma_px`` the blurred image stays above ``level``: ``s Phi^-1(1 - level / intensity)``
    (negative when level > intensity / 2: the contour lies inside the edge); 0 when level >= intensity."""
    if not intensity > level > 0:
        return 0.0
    return float(psf_sigma_px) * _PHI.inv_cdf(1.0 - level / intensity)


def rim_intensity(width_px: float, threshold: float, saturation: float, psf_sigma_px: float) -> float:
    """The intensity I (ADU per pixel) of a saturated region whose rim between the contours at ``threshold`` and
    ``saturation`` (both above the background) is ``width_px`` wide: ``d(t; I) - d(L; I) = width`` solved by
    bisection in log I over (L, 10^12 L] (module docstring)."""
    t, L, s = float(threshold), float(saturation), float(psf_sigma_px)

    def width(i):
        return edge_offset_px(t, i, s) - edge_offset_px(L, i, s)

    lo, hi = math.log(L * (1 + 1e-9)), math.log(L * 1e12)
    if width(math.exp(hi)) >= width_px:
        return math.exp(hi)
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if width(math.exp(mid)) > width_px else (lo, mid)
    return math.exp(0.5 * (lo + hi))


def silhouette_pixels(n_blob: int, perimeter_px: float, n_saturated: int, threshold: float, saturation: float,
                      psf_sigma_px: float, intensity: float | None = None) -> tuple[float, float, float]:
    """(silhouette pixels A0, the blur's reach d(t) px, the intensity I) of a resolved blob of ``n_blob`` pixels
    above ``threshold`` with perimeter ``perimeter_px`` and ``n_saturated`` pixels at ``saturation`` (levels above
    the background).  Saturated: I from the rim's width (:func:`rim_intensity`); else ``intensity`` (the blob's
    brightest pixels).  A0 = N - P d + pi d^2, at least 1."""
    N, P = float(n_blob), float(perimeter_px)
    if n_saturated > 0:
        disc = max(P * P - 4 * math.pi * (N - n_saturated), 0.0)
        w = (P - math.sqrt(disc)) / (2 * math.pi)
        intensity = rim_intensity(w, threshold, saturation, psf_sigma_px)
    d = edge_offset_px(threshold, float(intensity), psf_sigma_px) if intensity is not None else 0.0
    return max(1.0, N - P * d + math.pi * d * d), d, float(intensity) if intensity is not None else float("nan")


def silhouette_axis_ratio(lambda1: float, lambda2: float, d_px: float) -> float:
    """Axis ratio of the silhouette of a blob whose second moments are ``lambda1 >= lambda2`` (px^2) and whose
    outline the blur moved out by ``d_px``: (2 sqrt(l1) - d) / (2 sqrt(l2) - d), the minor semi-axis at least
    0.5 px."""
    a = 2 * math.sqrt(max(lambda1, 0.0)) - d_px
    b = max(2 * math.sqrt(max(lambda2, 0.0)) - d_px, 0.5)
    return max(a / b, 1.0)
