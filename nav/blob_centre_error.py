"""How far a resolved target's silhouette centre (``nav/blobber.py``'s ``centre_px``: the blob's pixels weighted by
their coverage, whatever their brightness) lies from the projection of the body's origin, as a function of what the
blobber saw: its summed coverage ``n_blob`` (issue 23, points 4 and 6 c).

Why a silhouette and not the centre of brightness: the centre of brightness of a lit body leans towards the Sun by
a fraction of its size (the 3U CubeSat under the proximity renderer's shading at 90 deg of phase: 14 mm mean and
8 mm spread over attitudes, from 50 m to 2 m), and what a mean phase correction leaves of it is heavy-tailed over
spin axes and aliased by the spin from frame to frame (docs/rendezvous.md).  The silhouette of a centrally
symmetric convex body (a cuboid, a cylinder) in orthographic projection is centrally symmetric about the projection
of its centre, so its area centroid is that projection exactly (a centrally symmetric plane figure's centroid is its
centre of symmetry); what is left is the pixel sampling of the silhouette's edge and, close in, the perspective
(the near faces drawn larger): 0.2-0.6 mm at 10-60 m and 1.3 / 4.4 mm at 5-10 / 2-5 m for the 3U CubeSat (seed 1,
30 approaches of the close preset, 2026-11-28).  It needs the faces turned away from the Sun to be seen: the
proximity renderer's ambient term (the reference's Eq. 3) lights every visible facet.

:class:`CentreErrorCalibration` holds the errors of renders of the target through the camera's own renderer and
blobber (``jobs/kinds/rendezvous_context.blobber_calibration``) and gives their root mean square along a new blob's
axes by a Gaussian kernel in log10 n_blob and the axis ratio (Nadaraya 1964; Watson 1964).  Units: pixels.

The error is not the same along every direction: it lies along the silhouette's own long axis.  Perspective draws
the near end of the body larger, and the foreshortened long axis of a body seen near end-on carries it (the 3U
CubeSat along the close preset's approach, 2-15 m: a mean square 1.7-2.0 times the per-axis one along the blob's
major axis, 0.07-0.09 times across it; 4-7 times along it where the observed axis ratio is 1.3-2.0, 0.6-1.3 where
it is 2-4; 2026-11-28).  So :meth:`CentreErrorCalibration.cov_px` gives the error along the new blob's major and
minor axes (its angle from the blobber's second moments) from the samples' errors along theirs, kernel-weighted in
log10 n_blob and the observed axis ratio: what the blobber sees of the body's attitude sets the error's size and
direction frame by frame.  A filter that took one isotropic sigma per coverage was right on average over attitudes
but not for an approach whose spin keeps the long axis foreshortened: those approaches made the close preset's
mean NEES exceed its bounds (issue 23 c: the worst approaches' mean NEES 16-25 at the last frames).

The error of a spinning target is not white from frame to frame: it is a function of the body's attitude seen
from the camera, so frames taken every dt of a spin at rate omega sample it at spin phases omega dt apart (96 deg a
frame in the close preset: every 4th frame nearly repeats), and the observer's turn about the target changes it
slowly, most along the turn's axis.  A filter that takes it as white is overconfident by the low-frequency content
of those sequences: :func:`sequence_gain` measures it on rendered sequences (the 3U CubeSat at 96 deg of spin and
6.1 deg of turn a frame, each frame's error over the stated sigma on its axis: 2.07 along the turn axis, 1.33
across, 1,200 sequences of 48 frames; ``jobs/kinds/rendezvous_context.silhouette_sequence_gain``) and the rendezvous
filter takes the white error's covariance scaled by it on those two axes.  Modelling the
sequence instead (the spin average as Gauss-Markov states, the first two harmonics of the spin phase as damped
rotating state pairs: 0.20, 0.35 and 0.36 of the error's mean square at 3-25 m) left the filter overconfident at
4-10 m (mean NEES 7.9 at the last frames, 100 approaches; 9.3 white; 2026-11-28): the observer's turn shifts each
harmonic's phase by an amount the unknown spin axis sets."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dualsight.nav.blobber_range_error import kernel_means

__all__ = ["CentreErrorCalibration", "CENTRE_SIGMA_FLOOR_PX", "sequence_gain"]

CENTRE_SIGMA_FLOOR_PX = 1e-3
"""Smallest 1-sigma per axis (px) :meth:`CentreErrorCalibration.axes_px` gives (a noise-free render of a large
blob centres to ~1e-3 px: the grid's exact coverage; the floor keeps a bearing's covariance positive)."""


@dataclass(frozen=True)
class CentreErrorCalibration:
    """Silhouette-centre errors ``err_px`` (M, 2) (measured minus the projection of the body's origin, col and row,
    px) of renders whose blobs had summed coverage ``n_blob`` (M,) px, observed axis ratio ``axis_ratio`` (M,) and
    major-axis direction ``angle_rad`` (M,) (from +col towards +row, ``nav/blobber.BlobResult``); non-finite samples
    are ignored.  :meth:`axes_px` gives the error's root mean square along a new blob's major and minor axes (bias
    included): the samples' errors along their own major and minor axes, weighted by a Gaussian kernel of widths
    ``bw_log_n`` (decades of n_blob) and ``bw_ratio`` (axis ratio) around the new blob's coverage and axis ratio
    (module docstring: the error lies along the silhouette's long axis); :meth:`cov_px` turns them to its angle."""

    n_blob: np.ndarray
    err_px: np.ndarray
    axis_ratio: np.ndarray
    angle_rad: np.ndarray
    bw_log_n: float = 0.1
    bw_ratio: float = 0.05
    chunk: int = 256
    _samples: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        n = np.asarray(self.n_blob, np.float64).ravel()
        e = np.asarray(self.err_px, np.float64).reshape(-1, 2)
        r = np.asarray(self.axis_ratio, np.float64).ravel()
        a = np.asarray(self.angle_rad, np.float64).ravel()
        ok = np.isfinite(n) & (n > 0) & np.isfinite(e).all(1) & np.isfinite(r) & np.isfinite(a)
        if not ok.any():
            raise ValueError("CentreErrorCalibration: no finite sample (n_blob > 0, a finite error, axis ratio and "
                             "angle)")
        c, s = np.cos(a[ok]), np.sin(a[ok])
        e = e[ok]
        e2 = np.stack([(e[:, 0] * c + e[:, 1] * s) ** 2, (e[:, 1] * c - e[:, 0] * s) ** 2], -1)   # (M, 2)
        object.__setattr__(self, "_samples", (n[ok], r[ok], e2))

    def axes_px(self, n_blob, axis_ratio) -> np.ndarray:
        """(B, 2) 1-sigma (px) of the silhouette centre along the blob's major and minor axis at summed coverage
        ``n_blob`` (B,) px and axis ratio (B,), at least :data:`CENTRE_SIGMA_FLOOR_PX`; NaN where an input is not
        finite or n_blob <= 0."""
        n_s, r_s, e2 = self._samples
        ms, _ = kernel_means(n_blob, axis_ratio, n_s, r_s, e2, self.bw_log_n, self.bw_ratio, self.chunk)
        return np.where(np.isfinite(ms), np.maximum(np.sqrt(ms), CENTRE_SIGMA_FLOOR_PX), np.nan)

    def cov_px(self, n_blob, axis_ratio, angle_rad) -> np.ndarray:
        """(B, 2, 2) px^2 covariance of the silhouette centre in (col, row) of blobs of summed coverage ``n_blob``,
        axis ratio ``axis_ratio`` and major axis at ``angle_rad`` (B,) (from +col towards +row): R diag(a^2, b^2)
        R^T with (a, b) = :meth:`axes_px` and R the rotation by the angle; NaN where an input is not finite."""
        ab = self.axes_px(n_blob, axis_ratio)
        t = np.asarray(angle_rad, np.float64).ravel()
        R = np.stack([np.stack([np.cos(t), -np.sin(t)], -1), np.stack([np.sin(t), np.cos(t)], -1)], -2)
        C = R * (ab ** 2)[:, None, :] @ np.swapaxes(R, -1, -2)
        return np.where(np.isfinite(t)[:, None, None], C, np.nan)


def sequence_gain(z: np.ndarray, max_frames: int | None = None) -> np.ndarray:
    """How much more the running sums of a correlated error spread than a white error's of the same variance:
    ``max over N <= max_frames of E[(z_1 + ... + z_N)^2] / N`` per axis, from sequences ``z`` (S, L, A) of
    unit-variance errors (S sequences of L frames, A axes; NaN frames count as 0), N up to ``max_frames`` (default
    L).  1 for a white error; N for one held constant; for a first-order Gauss-Markov error of correlation a per
    frame, 1 + 2 sum_{l=1}^{N-1} (1 - l/N) a^l at each N (Bendat & Piersol, *Random Data*, 4th ed., 2010,
    Sec. 8.2.1).  A filter that takes the error as white with its variance times this gain is, over every window up
    to ``max_frames`` frames, no more confident than the error's running sums allow."""
    z = np.nan_to_num(np.asarray(z, np.float64))
    S, L, A = z.shape
    n_max = L if max_frames is None else min(int(max_frames), L)
    c = np.cumsum(z, axis=1)[:, :n_max]                                  # (S, N, A) running sums
    return np.max(np.mean(c ** 2, axis=0) / np.arange(1, n_max + 1)[:, None], axis=0)
