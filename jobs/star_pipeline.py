"""Wiring of the star-tracker stages, shared by the simulated (SIL) and real-image (HIL) jobs.

Each function is one stage over a batch of B cases, arrays in and arrays out; the stages themselves
live in ``catalogs``, ``kernels`` and ``nav``.  Padded per-case arrays are (B, S) with a ``valid``
mask, ordered brightest first.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from dualsight.kernels import detect as kdetect
from dualsight.kernels import starfield as kstar
from dualsight.nav.attitude import solve_identified
from dualsight.nav.errors import axis_errors, classify, total_error_angle
from dualsight.nav.starid import identify as vote_identify
from dualsight.scene.attitude import angle_between


# ---------------------------------------------------------------------------------------- field
@dataclass(frozen=True)
class FieldStars:
    """Catalog stars to render, per case, padded to (B, S), brightest first.

    x, y : (B, S) float64 pixel coordinates (col, row; top-left corner convention).
    flux_e : (B, S) float32 electrons.
    valid : (B, S) bool.
    cat_row : (B, S) int64 catalog row (-1 = padding).
    inside : (B, S) bool, the star's centre is inside the image (counts as "generated").
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

    Returns (valid (B,S), [packed arrays...], cols (B,S) column index in N or -1).  Order within a
    row is kept (so catalog order = brightness order survives).
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
    """Half-angle (rad) of a cone about +z that holds the whole image grown by ``margin_px`` (distortion
    included: the corners and edge midpoints are back-projected), with 2 % to spare."""
    w, h, m = camera.width, camera.height, margin_px
    xs, ys = np.array([-m, w / 2, w + m]), np.array([-m, h / 2, h + m])
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    z = camera.backproject(pts)[:, 2]
    return float(min(np.arccos(np.clip(z.min(), -1, 1)) * 1.02 + 1e-4, np.pi / 2))


def stars_in_field(A: np.ndarray, catalog, camera, sensor) -> FieldStars:
    """Project the catalog through each case's attitude and keep the stars that light the image.

    A : (B, 3, 3) inertial -> camera.  Stars up to ``sensor.psf_margin_px`` outside the frame are kept
    for rendering (their light spills in) but do not count as generated.
    """
    margin = float(sensor.psf_window_sigma * sensor.psf_sigma_px + 1.0)
    # cheap cone test first (one BLAS product), then project only the candidates
    half = field_half_angle(camera, margin)
    z = A[:, 2, :] @ catalog.unit.T                                     # (B, N) cos(angle to boresight)
    b, n = np.nonzero(z > np.cos(min(half, np.pi / 2)))
    v = np.einsum("kij,kj->ki", A[b], catalog.unit[n])                  # (K, 3) camera frame
    px, front = camera.project(v)
    x, y = px[:, 0], px[:, 1]
    with np.errstate(invalid="ignore"):
        near_k = front & (x > -margin) & (x < camera.width + margin) & (y > -margin) & (y < camera.height + margin)
        inside_k = front & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
    B, N = z.shape
    near = np.zeros((B, N), dtype=bool)
    near[b[near_k], n[near_k]] = True
    dense = {}
    for name, vals in (("x", x), ("y", y)):
        a = np.zeros((B, N))
        a[b[near_k], n[near_k]] = vals[near_k]
        dense[name] = a
    ins = np.zeros((B, N), dtype=bool)
    ins[b[inside_k], n[inside_k]] = True
    flux = kstar.flux_from_magnitude(catalog.vmag.astype(np.float64), sensor)
    valid, (xp, yp, fp, ip), cols = pack_rows(near, dense["x"], dense["y"], flux, ins, fill=0)
    inside = ins
    return FieldStars(xp, yp, fp.astype(np.float32), valid, cols, ip & valid, inside.sum(axis=1))


# ---------------------------------------------------------------------------------------- images
@dataclass(frozen=True)
class Rendered:
    detections: object          # kernels.detect.Detections
    images: np.ndarray | None   # (B, H, W) when kept (replay), else None
    t_render_ns: int
    t_detect_ns: int | None     # None: detection did not run as its own stage (fused into the sparse render)


def render_and_detect(field_: FieldStars, noise_seeds: np.ndarray, camera, sensor, detect_cfg, buffers: dict,
                      keep_images: bool = False) -> Rendered:
    """Render the batch's star fields and detect/centroid the stars (Taichi kernels)."""
    t0 = time.perf_counter_ns()
    if sensor.is_ideal and not keep_images:
        # noise-free frames: render and label only the windows around stars (same blobs as full frames)
        det = kdetect.render_and_detect_ideal(field_.x, field_.y, field_.flux_e, field_.valid, camera.width,
                                              camera.height, sensor, detect_cfg, noise_seeds)
        t1 = time.perf_counter_ns()
        return Rendered(det, None, t1 - t0, None)
    images = kstar.render_star_fields(field_.x, field_.y, field_.flux_e, field_.valid, camera.width,
                                      camera.height, sensor, noise_seeds)
    t1 = time.perf_counter_ns()
    det = kdetect.detect_stars(images, detect_cfg)
    t2 = time.perf_counter_ns()
    return Rendered(det, images if keep_images else None, t1 - t0, t2 - t1)


# ---------------------------------------------------------------------------------------- nav
@dataclass(frozen=True)
class Observations:
    """Detections back-projected to camera-frame unit vectors, padded (B, S), brightest first."""

    vec: np.ndarray      # (B, S, 3)
    valid: np.ndarray    # (B, S)
    x: np.ndarray        # (B, S) centroid col
    y: np.ndarray        # (B, S) centroid row


MAX_OBS = 100


def observations(det, B: int, camera, max_obs: int = MAX_OBS) -> Observations:
    """Back-project the (flux-sorted) detections of each case; keep at most ``max_obs`` per case."""
    counts = np.diff(det.offsets)
    S = int(max(1, min(max_obs, counts.max() if B else 1)))
    case = det.case.astype(np.int64)
    rank = np.arange(len(case)) - det.offsets[case]
    keep = rank < S
    valid = np.zeros((B, S), dtype=bool)
    x = np.full((B, S), np.nan)
    y = np.full((B, S), np.nan)
    valid[case[keep], rank[keep]] = True
    x[case[keep], rank[keep]] = det.x[keep]
    y[case[keep], rank[keep]] = det.y[keep]
    vec = camera.backproject(np.stack([np.nan_to_num(x), np.nan_to_num(y)], axis=-1))
    vec[~valid] = np.nan
    return Observations(vec, valid, x, y)


def identify(obs: Observations, catalog, pairs, voting):
    """Geometric voting on the observed unit vectors (nav.starid)."""
    return vote_identify(obs.vec, obs.valid, catalog.unit, pairs.i, pairs.j, pairs.angle, voting)


@dataclass(frozen=True)
class Solution:
    A_est: np.ndarray        # (B, 3, 3) NaN where no attitude
    ok: np.ndarray           # (B,)
    axis_err: np.ndarray     # (B, 3) rad (NaN without truth or attitude)
    total_err: np.ndarray    # (B,) rad
    status: np.ndarray       # (B,) int8 codes of nav.errors.STATUS_NAMES
    residual: np.ndarray     # (B, S) rad, angle between each identified star and its predicted position


def solve(obs: Observations, ident, catalog, A_true: np.ndarray | None, error_frame: str = "camera") -> Solution:
    """SVD attitude from the accepted stars; Eqs. 4-7 errors and status when the truth is known."""
    A, ok = solve_identified(obs.vec, ident.ids, ident.accepted, catalog.unit)
    B = A.shape[0]
    ids = ident.ids
    pred = np.einsum("bij,bsj->bsi", A, catalog.unit[np.maximum(ids, 0)])
    residual = np.where((ids >= 0) & obs.valid, angle_between(pred, obs.vec), np.nan)
    if A_true is None:
        nan3 = np.full((B, 3), np.nan)
        return Solution(A, ok, nan3, np.full(B, np.nan), np.zeros(B, np.int8), residual)
    err = axis_errors(A, A_true, frame=error_frame)
    tot = total_error_angle(A, A_true)
    return Solution(A, ok, err, tot, classify(err, tot, ident.T), residual)


# ---------------------------------------------------------------------------------------- truth
@dataclass(frozen=True)
class Truth:
    """Which catalog star each detection is (nearest rendered star within ``radius``), and id checks."""

    true_row: np.ndarray     # (K,) catalog row of each detection, -1 = none (false star / merged far)
    hip_true: np.ndarray     # (K,) HIP id or -1
    dist_px: np.ndarray      # (K,) distance to that star (px), NaN if none
    obs_true_row: np.ndarray  # (B, S_obs) the same, laid out like Observations

    def _assigned(self, ident, obs):
        S = min(ident.ids.shape[1], self.obs_true_row.shape[1])
        ids = ident.ids[:, :S]
        acc = ident.accepted[:, :S] & (ids >= 0)
        return ids, acc, self.obs_true_row[:, :S]

    def n_correct(self, ident, obs) -> np.ndarray:
        ids, acc, tr = self._assigned(ident, obs)
        return (acc & (ids == tr)).sum(axis=1)

    def n_wrong(self, ident, obs) -> np.ndarray:
        ids, acc, tr = self._assigned(ident, obs)
        return (acc & (ids != tr)).sum(axis=1)

    def id_correct(self, ident, obs) -> np.ndarray:
        """(B,) every accepted identity is right and there are at least two of them."""
        ids, acc, tr = self._assigned(ident, obs)
        return (acc.sum(1) >= 2) & ~(acc & (ids != tr)).any(axis=1)


def match_truth(det, field_: FieldStars, obs: Observations, catalog, radius_px: float = 2.0) -> Truth:
    """Nearest rendered star (same case) of each detection, within ``radius_px``."""
    case = det.case.astype(np.int64)
    dx = det.x[:, None] - field_.x[case]
    dy = det.y[:, None] - field_.y[case]
    d2 = np.where(field_.valid[case], dx * dx + dy * dy, np.inf)
    k = np.argmin(d2, axis=1) if d2.shape[1] else np.zeros(len(case), dtype=np.int64)
    dist = np.sqrt(d2[np.arange(len(case)), k]) if len(case) else np.zeros(0)
    hit = dist <= radius_px
    row = np.where(hit, field_.cat_row[case, k] if len(case) else 0, -1)
    hip = np.where(row >= 0, catalog.hip[np.maximum(row, 0)], -1)
    B, S = obs.valid.shape
    rank = np.arange(len(case)) - det.offsets[case]
    keep = rank < S
    otr = np.full((B, S), -2, dtype=np.int64)   # -2 never equals an id (unmatched detections are wrong)
    otr[case[keep], rank[keep]] = np.where(row[keep] >= 0, row[keep], -2)
    return Truth(row, hip, np.where(hit, dist, np.nan), otr)
