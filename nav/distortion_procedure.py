"""Focal length and lens distortion from the sky: frames solved lost in space, the camera fitted to their
identified stars, the frames solved again (``dualsight hil star --fit-distortion``).

Input: every frame's detections (:class:`FramePixels`), a camera, the star and pair catalogs and the voting
settings.  The frames are solved lost in space (:func:`solve_pass`: nav/star_solution.py's geometric voting
and SVD attitude), then the camera is fitted to every solved frame's identified stars by
:func:`dualsight.nav.distortion_fit.fit_camera` (k1, k2 and one focal length fx = fy, jointly with a small
rotation correction per frame; principal point, p1, p2 and k3 held at the camera's values; Huber loss and
rejection beyond 5 robust sigmas).  :func:`fit_camera_from_sky` runs the procedure:

1. Bootstrap, only when the camera has no distortion.  A strongly distorted wide lens (and a nominal focal
   length) moves the outer stars by many voting tolerances, so the frames are first solved from the stars of a
   central disc (:func:`bootstrap_plan`: a disc holding ~10 catalog stars, voted with the
   tolerance that covers a 1 % focal error and a lens moving the corner by 3 % at its edge), k1 and the focal
   length are fitted from them (when at least :data:`MIN_STARS` stars remain and fit to under
   :data:`BOOTSTRAP_SIGMA_FRACTION` of the tolerance), and the disc grows by 1.5 per pass up to 70 % of the
   half-diagonal.  When the first disc gives no fit, the focal length is scaled by :data:`FOCAL_SEARCH` in turn.
2. Whole field, with the voting tolerance as given: solve with the current camera, fit k1, k2 and the focal
   length; re-solve with the fitted camera and fit again (at most :data:`FULL_ITERATIONS` fits; it stops when a
   pass identifies exactly the stars of the previous one).
3. A last solve with the fitted camera (frames solved and stars identified are reported).

"rms before" is the rms residual length (px) of the fitted stars under the input camera with each frame's
attitude re-fitted (the input camera's best case); "rms after" is that of the same stars, fitted.  A
whole-field pass that identifies fewer than :data:`MIN_STARS` stars raises :class:`TooFewStars`.

Units: pixels for centroids, radii and focal lengths; radians for tolerances and attitude errors.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from dualsight.nav import distortion_fit as dfit
from dualsight.nav.errors import total_error_angle
from dualsight.nav.observations import Observations
from dualsight.nav.star_solution import identify, solve
from dualsight.scene.camera import Camera

__all__ = ["MIN_STARS", "FULL_ITERATIONS", "BOOTSTRAP_SIGMA_FRACTION", "FOCAL_SEARCH", "BOOTSTRAP_CONFIG",
           "FULL_CONFIG", "PLAUSIBLE_CORNER_DISTORTION", "PLAUSIBLE_FOCAL_ERROR", "BOOTSTRAP_STARS", "BootstrapPlan",
           "model_error_px", "bootstrap_plan", "FramePixels", "SolvePass", "PassLog", "FitReport", "TooFewStars", "solve_pass",
           "identified_stars", "camera_with", "with_tolerance", "attitude_errors", "fit_camera_from_sky"]

MIN_STARS = 30
"""Fewest identified stars (over all solved frames) the fit accepts: 60 residuals for the 3 camera parameters
and 3 rotation angles per frame, with a margin for the outliers; with fewer the procedure refuses."""
FULL_ITERATIONS = 3
"""Whole-field solve-and-fit passes at most (the first fit, then re-solved with the fitted camera twice)."""
BOOTSTRAP_SIGMA_FRACTION = 0.25
"""A central pass's fit is kept only when its robust residual sigma is under this fraction of the pass's
voting tolerance (px) and it keeps at least MIN_STARS stars: right identifications fit to the centroid noise
(~0.05-0.1 px), wrong ones made by chance within the tolerance only to a good fraction of it."""
FOCAL_SEARCH = (1.0, 0.98, 1.02, 0.96, 1.04)
"""Focal-length scales tried, in this order, in the first central pass until one identifies enough stars for
a fit: the bootstrap's tolerance covers a 1 % focal error (:data:`PLAUSIBLE_FOCAL_ERROR`), so
2 % steps cover a nominal focal length up to ~5 % off."""
BOOTSTRAP_CONFIG = dfit.FitConfig(focal="common", fit_k1=True, fit_k2=False)
"""Fit of the central passes: k1 and the focal length (k2 is not determined by the centre of the field)."""
FULL_CONFIG = dfit.FitConfig(focal="common", fit_k1=True, fit_k2=True)
"""Fit of the whole-field passes: k1, k2 and one focal length (fx = fy); principal point held."""


# ============================================================================================ bootstrap plan
# the central regions and the widened tolerance of step 1 (pure functions of the camera's numbers)
PLAUSIBLE_CORNER_DISTORTION = 0.03
"""Radial displacement at the image corner of a strongly distorted wide lens, as a fraction of the
half-diagonal (3 %: e.g. 19 px of a 640 px half-diagonal)."""
PLAUSIBLE_FOCAL_ERROR = 0.01
"""Relative error of a nominal focal length (1 %: the ESA tetra3 frames' "35 mm" lens is 35.32 mm)."""
BOOTSTRAP_STARS = 10.0
"""Catalog stars expected, on average over the sky, in the first central disc (the robust voting verifies
an attitude with 4 stars; 10 leaves room for the sky's variations and for missed detections)."""


@dataclass(frozen=True)
class BootstrapPlan:
    """Central regions for solving frames with a camera model that lacks the distortion (and whose focal
    length is only nominal): radii_px (K,) px from the principal point, smallest first; tolerance_rad the
    voting tolerance of these passes (rad)."""

    radii_px: np.ndarray
    tolerance_rad: float


def model_error_px(r_px, half_diagonal_px: float, *, focal_error: float = PLAUSIBLE_FOCAL_ERROR,
                   corner_fraction: float = PLAUSIBLE_CORNER_DISTORTION):
    """How far (px) a star at radius ``r_px`` from the principal point can be from where an undistorted
    model with a nominal focal length puts it: ``focal_error * r + corner_fraction * R (r / R)^3``
    (the focal-length error scales the radius; the k1 term of a lens moving the corner, radius R =
    ``half_diagonal_px``, by ``corner_fraction * R``)."""
    r = np.asarray(r_px, np.float64)
    R = float(half_diagonal_px)
    return focal_error * r + corner_fraction * R * (r / R) ** 3


def bootstrap_plan(half_diagonal_px: float, focal_px: float, n_catalog: int, tolerance_rad: float, *,
                   stars: float = BOOTSTRAP_STARS, growth: float = 1.5, stop_fraction: float = 0.7,
                   max_tolerance_rad: float = math.pi / 180) -> BootstrapPlan:
    """The central regions of the bootstrap (``hil star --fit-distortion`` with a camera file without
    distortion), from the field size, the focal length (px), the catalog size and the voting tolerance.

    * First radius r0: the disc about the boresight that holds ``stars`` catalog stars on average
      (a cap of angular radius t holds n_catalog (1 - cos t) / 2 of them), r0 = f tan t, at most
      ``stop_fraction`` R (R = ``half_diagonal_px``).
    * Tolerance: the angle of an observed pair of stars in the disc is off by up to 2 e(r0) (two stars on
      opposite sides at r0; e = :func:`model_error_px`) and by about e(r0) for a typical pair (about r0
      apart); the passes vote with max(tolerance_rad, e(r0) / f), at most ``max_tolerance_rad`` (1 deg,
      VotingConfig's bound).  Twice that lets random coincidences through: on 12 frames of a 30 deg field
      with a 1 % focal error, 3 of 4 solutions at r0 were wrong at 2 e(r0) (444 arcsec), 0 of 3 at e(r0).
    * Then the radius grows by ``growth`` while it stays under ``stop_fraction`` R (a fit between passes
      removes most of the model error, so the same tolerance covers the wider disc); the whole field
      follows with the voting tolerance as given.
    """
    R, f = float(half_diagonal_px), float(focal_px)
    t = math.acos(max(-1.0, 1.0 - 2.0 * min(stars, n_catalog) / max(n_catalog, 1)))
    r0 = min(f * math.tan(min(t, 1.5)), stop_fraction * R)
    tol = min(max(tolerance_rad, float(model_error_px(r0, R)) / f), max_tolerance_rad)
    radii = [r0]
    while radii[-1] * growth < stop_fraction * R:
        radii.append(radii[-1] * growth)
    return BootstrapPlan(np.asarray(radii, np.float64), float(tol))


# ============================================================================================ frames
@dataclass(frozen=True)
class FramePixels:
    """Detections of F frames, padded to (F, S), brightest first.

    x, y : (F, S) float64 centroids (col, row), px (NaN in padding); valid : (F, S) bool.
    errors : (F,) None or why the image could not be processed (then no detections).
    psf_sigma_px : (F,) the PSF width each frame's detector used (px; NaN: none, e.g. the global detector), or ().
    """

    x: np.ndarray
    y: np.ndarray
    valid: np.ndarray
    errors: tuple
    psf_sigma_px: tuple = ()


@dataclass(frozen=True)
class SolvePass:
    """Lost-in-space solution of every frame with one camera (and optionally only the central stars).

    radius_px : None (whole field) or the radius (px from the principal point) of the stars used.
    A : (F, 3, 3) attitude (inertial -> camera), NaN where not solved; solved : (F,) bool.
    ids : (F, S) int catalog row (-1 = none); accepted : (F, S) bool identified and accepted.
    T : (F,) match threshold.
    """

    radius_px: float | None
    A: np.ndarray
    solved: np.ndarray
    ids: np.ndarray
    accepted: np.ndarray
    T: np.ndarray

    @property
    def stars(self) -> np.ndarray:
        """(F, S) bool: identified stars of solved frames."""
        return self.accepted & (self.ids >= 0) & self.solved[:, None]


def solve_pass(pix: FramePixels, camera, catalog, pairs, voting, radius_px: float | None = None,
               batch_size: int = 16) -> SolvePass:
    """Identify and solve every frame with ``camera`` from its detections within ``radius_px`` of the
    principal point (None = all): ``nav.star_solution.identify`` and ``solve``, as ``hil star``.

    ``catalog``: the star catalog (``unit`` (N, 3) ICRS unit vectors, ``vmag`` (N,)); ``pairs`` its pair
    catalog or the pair catalog's ``VotingIndex`` (as ``nav.star_solution.identify`` takes it); ``voting`` a
    ``VotingConfig``; ``batch_size`` frames per identification call."""
    F, S = pix.x.shape
    valid = pix.valid.copy()
    if radius_px is not None:
        valid &= np.hypot(pix.x - camera.cx, pix.y - camera.cy) <= radius_px
    vec = camera.backproject(np.stack([np.nan_to_num(pix.x), np.nan_to_num(pix.y)], -1))
    vec[~valid] = np.nan
    A = np.full((F, 3, 3), np.nan)
    solved = np.zeros(F, bool)
    ids = np.full((F, S), -1, np.int64)
    accepted = np.zeros((F, S), bool)
    T = np.zeros(F, np.int64)
    for s in range(0, F, batch_size):
        b = slice(s, min(F, s + batch_size))
        obs = Observations(vec[b], valid[b], pix.x[b], pix.y[b])
        ident = identify(obs, catalog.unit, pairs, voting, cat_vmag=catalog.vmag)
        sol = solve(obs, ident, catalog.unit, None)
        ok = sol.ok & (ident.T > 0)
        A[b], solved[b], T[b] = np.where(ok[:, None, None], sol.A_est, np.nan), ok, ident.T
        ids[b], accepted[b] = ident.ids, ident.accepted & ok[:, None]
    return SolvePass(radius_px, A, solved, ids, accepted, T)


def identified_stars(pix: FramePixels, sp: SolvePass, cat_unit: np.ndarray):
    """The fit's input from a pass: (u (N, 3) ICRS unit vectors, frame (N,) int, px (N, 2) centroids,
    cat_row (N,) int), N = identified stars of the solved frames."""
    f, s = np.nonzero(sp.stars)
    rows = sp.ids[f, s]
    return cat_unit[rows], f, np.stack([pix.x[f, s], pix.y[f, s]], -1), rows


def camera_with(camera, intr: dfit.Intrinsics) -> Camera:
    """``camera`` with the intrinsics ``intr`` (size, pixel pitch, bit depth and stated PSF width kept)."""
    return dataclasses.replace(camera, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy,
                               distortion=tuple(intr.distortion))


def with_tolerance(voting, tol: float):
    """``voting`` with its tolerances (voting, verification, attitude check) scaled to ``tol`` (rad); the
    scaled verification and attitude tolerances are capped at 1 deg."""
    k = tol / voting.tolerance_rad
    return dataclasses.replace(voting, tolerance_rad=tol, **{
        n: min(getattr(voting, n) * k, math.pi / 180) for n in ("verify_tolerance_rad", "attitude_tolerance_rad")
        if getattr(voting, n) is not None})


def attitude_errors(sp: SolvePass, A_true: np.ndarray | None) -> np.ndarray | None:
    """(solved frames with a truth,) rad: the angle between each solved attitude and its true one.

    ``A_true``: (F, 3, 3) true attitudes (inertial -> camera), NaN for a frame without truth; None when no
    frame has a truth (then None is returned)."""
    if A_true is None:
        return None
    k = np.flatnonzero(sp.solved & np.isfinite(A_true).all(axis=(1, 2)))
    if not k.size:
        return np.zeros(0)
    return total_error_angle(sp.A[k], A_true[k])


# ============================================================================================ the procedure
@dataclass
class PassLog:
    """One pass: the region, frames solved, stars identified, the fit made from them (None = none)."""

    radius_px: float | None
    fx: float
    solved: int
    stars: int
    fit: dfit.FitResult | None = None
    attitude_err_rad: np.ndarray | None = None      # (solved frames,) against the truth, when there is one
    note: str | None = None


@dataclass
class FitReport:
    """Everything :func:`fit_camera_from_sky` found (the camera file and the summary are made from it).

    camera_in, camera: the input and the fitted camera; fit: the last whole-field fit; rms_before_px (see the
    module); final: the solve with the fitted camera; passes: every pass in order; errors: (F,) None or why a
    frame could not be processed; n_images: F; final_attitude_err_rad: the final solve's attitude errors
    against the truth (None without); seconds: the time it all took (filled in by the caller)."""

    camera_in: object
    camera: object
    fit: dfit.FitResult
    rms_before_px: float
    final: SolvePass
    passes: list[PassLog] = field(default_factory=list)
    errors: tuple = ()
    n_images: int = 0
    final_attitude_err_rad: np.ndarray | None = None
    seconds: float = 0.0


class TooFewStars(ValueError):
    """A whole-field pass identified fewer than :data:`MIN_STARS` stars: ``stars`` of them in ``solved`` solved
    frames of ``frames``."""

    def __init__(self, stars: int, solved: int, frames: int):
        super().__init__(f"only {stars} stars identified in {solved} solved of {frames} frames; at least "
                         f"{MIN_STARS} are needed")
        self.stars, self.solved, self.frames = stars, solved, frames


def fit_camera_from_sky(pix: FramePixels, camera, catalog, pairs, voting, *, batch_size: int = 16,
                        A_true: np.ndarray | None = None, progress=None) -> FitReport:
    """Solve, fit and re-solve the frames ``pix`` (module docstring, steps 1-3); returns the :class:`FitReport`.

    ``camera``: the input camera; ``catalog``, ``pairs``, ``voting``, ``batch_size``: as :func:`solve_pass`;
    ``A_true``: as :func:`attitude_errors` (each pass's errors against the truth).  ``progress``: None or a
    callable ``progress(event, value)`` told ``("bootstrap", tolerance_rad)`` when the central passes start,
    ``("pass", (n, PassLog))`` after every pass (n from 1) and ``("fitted", FitResult)`` after every
    whole-field fit.  Raises :class:`TooFewStars`."""
    tell = progress or (lambda event, value: None)
    cam0 = camera
    F = pix.x.shape[0]
    passes: list[PassLog] = []

    def run(cam, radius, cfg, vote=voting):
        sp = solve_pass(pix, cam, catalog, pairs, vote, radius, batch_size)
        u, fr, px, _ = identified_stars(pix, sp, catalog.unit)
        entry = PassLog(radius, cam.fx, int(sp.solved.sum()), len(u), None, attitude_errors(sp, A_true))
        passes.append(entry)
        if cfg is not None and len(u) >= MIN_STARS:
            fit = dfit.fit_camera(u, fr, px, sp.A, dfit.Intrinsics.of(cam), cfg)
            # a central pass's fit is used only when it explains its stars to well within the tolerance
            # (right identifications fit to the centroid noise; chance coincidences only to ~ the tolerance)
            tol_px = vote.tolerance_rad * cam.fx
            if fit.n_stars >= MIN_STARS and fit.sigma_px <= BOOTSTRAP_SIGMA_FRACTION * tol_px:
                entry.fit = fit
            else:
                entry.note = (f"fit not used ({fit.n_stars} stars kept, sigma {fit.sigma_px:.2f} px > "
                              f"{BOOTSTRAP_SIGMA_FRACTION:g} x tolerance {tol_px:.2f} px)")
        tell("pass", (len(passes), entry))
        return sp, entry

    cam = cam0
    if not cam0.has_distortion:
        plan = bootstrap_plan(0.5 * math.hypot(cam0.width, cam0.height), 0.5 * (cam0.fx + cam0.fy),
                              len(catalog.unit), voting.tolerance_rad)
        boot = with_tolerance(voting, plan.tolerance_rad)
        tell("bootstrap", plan.tolerance_rad)
        for n, r in enumerate(plan.radii_px):
            # the first disc: the nominal focal length, then FOCAL_SEARCH's scales until one gives a fit
            for scale in FOCAL_SEARCH if n == 0 else (1.0,):
                trial = camera_with(cam, dfit.Intrinsics(cam.fx * scale, cam.fy * scale, cam.cx, cam.cy,
                                                         tuple(cam.distortion)))
                _, entry = run(trial, float(r), BOOTSTRAP_CONFIG, boot)
                if entry.fit is not None:
                    cam = camera_with(cam, entry.fit.intrinsics)
                    break
    prev = final = fit = fit_sp = None
    for _ in range(FULL_ITERATIONS):
        sp, entry = run(cam, None, None)
        key = sp.stars.copy(), np.where(sp.stars, sp.ids, -1)
        if prev is not None and all(np.array_equal(a, b) for a, b in zip(key, prev)):
            final = sp                              # the same stars as the last fit's: nothing would change
            break
        if entry.stars < MIN_STARS:
            raise TooFewStars(entry.stars, int(sp.solved.sum()), F)
        u, fr, px, _ = identified_stars(pix, sp, catalog.unit)
        fit = entry.fit = dfit.fit_camera(u, fr, px, sp.A, dfit.Intrinsics.of(cam), FULL_CONFIG)
        cam, prev, fit_sp = camera_with(cam, fit.intrinsics), key, sp
        tell("fitted", fit)
    if final is None:
        final, _ = run(cam, None, None)
    # rms before: the fitted stars under the input camera, each frame's attitude re-fitted
    u, fr, px, _ = identified_stars(pix, fit_sp, catalog.unit)
    keep = fit.inlier
    before = dfit.fit_camera(u[keep], fr[keep], px[keep], fit.A, dfit.Intrinsics.of(cam0),
                             dfit.FitConfig(focal="fixed", fit_k1=False, fit_k2=False, max_rounds=0))
    return FitReport(cam0, cam, fit, before.rms_px, final, passes, pix.errors, F, attitude_errors(final, A_true))
