"""``dualsight hil star IMAGES --camera F --fit-distortion -o CAMERA.toml [--force]``, its wiring: focal length
and lens distortion from the sky.

A validated ``hil_star`` spec's frames are read and their stars detected with the ``hil star`` chain's own stages
(jobs/kinds/hil_star.py: reading, background, detection; nav/observations.py: back-projection), ``batch_size``
frames at a time; then nav/distortion_procedure.py solves them lost in space, fits k1, k2 and the focal length
(fx = fy) to every solved frame's identified stars (nav/distortion_fit.py) and solves them again with the fitted
camera.  The command (jobs/cli/hil_star.py) writes the fitted camera file and prints the summary
(jobs/reports/fit_distortion.py).

The fit runs in this process and writes nothing to the lake.  Unreadable images are passed to ``warn`` and left
out; a whole-field pass with fewer than ``nav.distortion_procedure.MIN_STARS`` identified stars is an
InputError (``--fit-distortion``).

Measured (tests/test_distortion_fit.py): 12 frames of a 30 deg field, k1 = -0.22, k2 = 0.05 (corners 15.4 px),
camera file without distortion and fx 1 % short: k1 fitted to 0.5 %, every frame solved with attitude errors
as with the true coefficients (median 1.2 arcsec), none solved without the fit; ~4 s.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from dualsight.errors import ImageError, InputError
from dualsight.jobs.kinds import hil_star as hs
from dualsight.kernels.detect_local import frames_psf_width
from dualsight.nav.distortion_procedure import MIN_STARS, FitReport, FramePixels, TooFewStars, fit_camera_from_sky
from dualsight.nav.observations import observations

__all__ = ["detect_all", "true_attitudes", "fit_from_spec"]


def detect_all(spec, rt) -> FramePixels:
    """Read and detect every image of a ``hil_star`` spec, ``settings.batch_size`` frames at a time (the
    chain of jobs/kinds/hil_star.py: read_frame, detect_frames, observations); ``rt`` its runtime."""
    F, bs = len(spec.images), spec.settings.batch_size
    errors: list = [None] * F
    widths = [float("nan")] * F                      # the PSF width each frame's detector used (local detector)
    parts = []                                       # (frame indices, x, y, valid)
    for s in range(0, F, bs):
        good, frames = [], []
        for k in range(s, min(F, s + bs)):
            try:
                frames.append(hs.read_frame(spec.images[k], rt.camera)[0])
                good.append(k)
            except ImageError as e:
                errors[k] = str(e)
        if good:
            _, _, det = hs.detect_frames(np.stack(frames), rt.settings, rt.detect)
            if getattr(det, "psf_sigma_px", None) is not None:
                for k, w in zip(good, det.psf_sigma_px):
                    widths[k] = float(w)
            obs = observations(det, len(good), rt.camera, max_obs=rt.settings.max_obs)
            parts.append((np.asarray(good), obs.x, obs.y, obs.valid))
    S = max([p[1].shape[1] for p in parts], default=1)
    x = np.full((F, S), np.nan)
    y = np.full((F, S), np.nan)
    valid = np.zeros((F, S), bool)
    for k, px, py, pv in parts:
        x[k, :px.shape[1]], y[k, :px.shape[1]], valid[k, :px.shape[1]] = px, py, pv
    return FramePixels(x, y, valid, tuple(errors), tuple(widths))


def true_attitudes(spec) -> np.ndarray | None:
    """(F, 3, 3) the spec's true attitudes (inertial -> camera), NaN for an image without one; None when the
    spec has no truths."""
    if not spec.truths:
        return None
    A = np.full((len(spec.images), 3, 3), np.nan)
    for k in range(len(spec.images)):
        if spec.truth(k).A is not None:
            A[k] = spec.truth(k).matrix("A")
    return A


def fit_from_spec(spec, progress=None, warn=None) -> FitReport:
    """Read and detect the frames of a validated ``hil_star`` spec, then solve, fit and re-solve them
    (``nav.distortion_procedure.fit_camera_from_sky``, whose ``progress`` events this passes on).  When the input
    camera states no PSF width and the frames measured one (``kernels.detect_local.frames_psf_width``), the fitted
    camera states it (rounded to 0.001 px).

    ``warn``: None or a callable taking the message of an image that could not be processed.  Raises
    InputError (too few stars)."""
    t0 = time.perf_counter()
    rt = hs.runtime(spec)
    ctx = hs.make_context(spec)
    pix = detect_all(spec, rt)
    for e in pix.errors:
        if e and warn is not None:
            warn(e)
    try:
        rep = fit_camera_from_sky(pix, rt.camera, ctx.catalog, ctx.index, rt.voting,
                                  batch_size=spec.settings.batch_size, A_true=true_attitudes(spec), progress=progress)
    except TooFewStars as e:
        raise InputError(f"only {e.stars} stars identified in {e.solved} solved of {e.frames} frames; the fit needs "
                         f"at least {MIN_STARS} (give more frames, or a camera file closer to the lens)",
                         source="--fit-distortion") from None
    one = frames_psf_width(pix.psf_sigma_px) if rep.camera.psf_sigma_px is None else None
    if one is not None:        # the frames measured one PSF width: the fitted camera file states it too
        rep = dataclasses.replace(rep, camera=dataclasses.replace(rep.camera, psf_sigma_px=round(one[0], 3)))
    return dataclasses.replace(rep, seconds=time.perf_counter() - t0)
