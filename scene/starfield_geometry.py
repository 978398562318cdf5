"""Catalog stars through an attitude and the camera model: which stars light each case's image, and where.

Stage 5 of docs/architecture.md.  Pure functions of arrays (numpy only); the flux of each catalog star
and the PSF margin are inputs, computed by the caller from the sensor model (``kernels.starfield``).

Conventions (docs/architecture.md): ``A`` maps inertial (ICRS) unit vectors into the camera frame (+z out through
the lens); pixel coordinates are (col, row) measured from the image's top-left corner, so the top-left
pixel's centre is (0.5, 0.5).  Per-case results are padded to (B, S) with a ``valid`` mask, in catalog
order (the catalog is sorted brightest first, so the padding keeps brightness order).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

__all__ = ["FieldStars", "pack_rows", "field_half_angle", "stars_in_field", "catalog_in_image"]


@dataclass(frozen=True)
class FieldStars:
    """Catalog stars to render, per case, padded to (B, S), in catalog (= brightness) order.

    x, y : (B, S) float64 pixel coordinates (col, row; top-left corner convention), 0 in padding.
    flux_e : (B, S) float32 electrons per exposure.
    valid : (B, S) bool, a real star (False = padding).
    cat_row : (B, S) int64 catalog row (-1 = padding).
    inside : (B, S) bool, the star's centre is inside the image (it counts as "generated").
    n_generated : (B,) int, stars whose centre is inside the image.
    """

    x: np.ndarray
    y: np.ndarray
    flux_e: np.ndarray
    valid: np.ndarray
    cat_row: np.ndarray
    inside: np.ndarray
    n_generated: np.ndarray


def pack_rows(mask: np.ndarray, *arrays, fill=0):
    """Pack the True entries of each row of ``mask`` (B, N) to the left of (B, S) arrays.

    Each of ``arrays`` is (B, N) (taken per entry) or (N,) (the same value for every row).
    Returns (valid (B, S) bool, [packed (B, S) arrays, dtype kept, ``fill`` in padding],
    cols (B, S) int64 column index in N or -1), with S = max(1, most True entries in a row).  Order
    within a row is kept (so catalog order = brightness order survives).
    """
    B = mask.shape[0]
    counts = mask.sum(axis=1)
    S = max(1, int(counts.max()) if B else 1)
    b, n = np.nonzero(mask)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(len(b)) - starts[b]
    valid = np.zeros((B, S), dtype=bool)
    valid[b, pos] = True
    cols = np.full((B, S), -1, dtype=np.int64)
    cols[b, pos] = n
    out = []
    for a in arrays:
        p = np.full((B, S), fill, dtype=a.dtype)
        p[b, pos] = a[b, n] if a.ndim == 2 else a[n]
        out.append(p)
    return valid, out, cols


def field_half_angle(camera, margin_px: float = 0.0) -> float:
    """Half-angle (rad) of a cone about +z that holds the whole image grown by ``margin_px`` on every side.

    The corners and edge midpoints are back-projected through the camera model (distortion included);
    the widest of them, with 2 % and 1e-4 rad to spare, capped at pi/2.  Memoised per (camera, margin):
    the back-projection iterates the distortion model and costs about 1 ms.
    """
    try:
        return _half_angle(camera, float(margin_px))
    except TypeError:           # an unhashable camera-like object: compute it
        return _half_angle.__wrapped__(camera, float(margin_px))


@functools.lru_cache(maxsize=64)
def _half_angle(camera, margin_px: float) -> float:
    w, h, m = camera.width, camera.height, margin_px
    xs, ys = np.array([-m, w / 2, w + m]), np.array([-m, h / 2, h + m])
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    z = camera.backproject(pts)[:, 2]
    return float(min(np.arccos(np.clip(z.min(), -1, 1)) * 1.02 + 1e-4, np.pi / 2))


def stars_in_field(A: np.ndarray, cat_unit: np.ndarray, flux_e: np.ndarray, camera, margin_px: float) -> FieldStars:
    """Project the catalog through each case's attitude and keep the stars that light the image.

    Parameters
    ----------
    A : (B, 3, 3) inertial -> camera rotation of each case.
    cat_unit : (N, 3) float64 ICRS unit vectors of the catalog stars (brightest first).
    flux_e : (N,) float64 electrons of each catalog star per exposure.
    camera : ``scene.camera.Camera`` (pinhole + Brown-Conrady).
    margin_px : stars up to this far outside the frame are kept for rendering (their PSF spills in)
        but do not count as generated.

    A cheap cone test (one matrix product, :func:`field_half_angle`) selects candidates; only those are
    projected with ``camera.project``.
    """
    margin = float(margin_px)
    half = field_half_angle(camera, margin)
    z = A[:, 2, :] @ cat_unit.T                                         # (B, N) cos(angle to boresight)
    b, n = np.nonzero(z > np.cos(min(half, np.pi / 2)))
    v = np.einsum("kij,kj->ki", A[b], cat_unit[n])                      # (K, 3) camera frame
    px, front = camera.project(v)
    x, y = px[:, 0], px[:, 1]
    with np.errstate(invalid="ignore"):
        near_k = front & (x > -margin) & (x < camera.width + margin) & (y > -margin) & (y < camera.height + margin)
        inside_k = front & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
    B = z.shape[0]
    # pack the kept stars of each case to the left, in catalog order (np.nonzero is row-major), as
    # pack_rows would, without (B, N) intermediates
    bk, nk = b[near_k], n[near_k]
    counts = np.bincount(bk, minlength=B)
    S = max(1, int(counts.max()) if B else 1)
    pos = np.arange(bk.size) - (np.cumsum(counts) - counts)[bk]
    valid = np.zeros((B, S), dtype=bool)
    valid[bk, pos] = True
    cols = np.full((B, S), -1, dtype=np.int64)
    cols[bk, pos] = nk
    xp, yp, ip = np.zeros((B, S)), np.zeros((B, S)), np.zeros((B, S), dtype=bool)
    xp[bk, pos], yp[bk, pos], ip[bk, pos] = x[near_k], y[near_k], inside_k[near_k]
    fp = np.zeros((B, S), dtype=np.float32)
    fp[bk, pos] = np.asarray(flux_e)[nk]
    return FieldStars(xp, yp, fp, valid, cols, ip, np.bincount(b[inside_k], minlength=B))


def catalog_in_image(A: np.ndarray, cat_unit: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """Catalog stars that one attitude puts inside the image (e.g. the prediction of a solved attitude).

    A : (3, 3) inertial -> camera; cat_unit : (N, 3) ICRS unit vectors.
    Returns (xy (M, 2) float64 pixel positions (col, row), rows (M,) int64 catalog rows), catalog order.
    """
    px, front = camera.project(cat_unit @ np.asarray(A, np.float64).T)
    inside = front & camera.in_image(np.nan_to_num(px, nan=-1.0))
    return px[inside], np.flatnonzero(inside)
