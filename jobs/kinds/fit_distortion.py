"""``dualsight hil star IMAGES --camera F --fit-distortion -o CAMERA.toml [--force]``: focal length and lens
distortion from the sky.

The frames are solved lost in space with the ``hil star`` chain's own stages (jobs/kinds/hil_star.py: reading,
background, detection, back-projection; nav/star_solution.py: geometric voting, SVD attitude), then the camera
is fitted to every solved frame's identified stars by ``nav/distortion_fit.py`` (k1, k2 and one focal length
fx = fy, jointly with a small rotation correction per frame; principal point, p1, p2 and k3 held at the camera
file's values; Huber loss and rejection beyond 5 robust sigmas):

1. Bootstrap, only when the camera file has no distortion.  A strongly distorted wide lens (and a nominal
   focal length) moves the outer stars by many voting tolerances, so the frames are first solved from the
   stars of a central disc (``nav.distortion_fit.bootstrap_plan``: a disc holding ~10 catalog stars, voted
   with the tolerance that covers a 1 % focal error and a lens moving the corner by 3 % at its edge), k1 and
   the focal length are fitted from them (when at least :data:`MIN_STARS` stars remain and fit to under
   :data:`BOOTSTRAP_SIGMA_FRACTION` of the tolerance), and the disc grows by 1.5 per pass up to 70 % of the
   half-diagonal.  When the first disc gives no fit, the focal length is scaled by :data:`FOCAL_SEARCH` in turn.
2. Whole field, with the voting tolerance as given: solve with the current camera, fit k1, k2 and the focal
   length; re-solve with the fitted camera and fit again (at most :data:`FULL_ITERATIONS` fits; it stops
   when a pass identifies exactly the stars of the previous one).
3. A last solve with the fitted camera (frames solved and stars identified are reported), then the camera
   file is written by ``scene.calibration.write_camera_toml`` (tomli-w, written to a temporary name and
   renamed): the ``[camera]`` table of examples/cameras/*.toml, comments saying what was fitted from how many
   frames and stars and the rms residual before / after, and a ``[distortion_fit]`` table with the numbers.

"rms before" is the rms residual length (px) of the fitted stars under the input camera with each frame's
attitude re-fitted (the input camera's best case); "rms after" is that of the same stars, fitted.

Refusals (one line ``dualsight: error: ...``, exit status 2, nothing written): ``--fit-distortion`` without
``-o``; ``-o`` or ``--force`` without ``--fit-distortion``; ``-o`` naming an existing file without ``--force``,
a folder, or a file in a missing folder (these before any work); fewer than :data:`MIN_STARS` stars identified
by a whole-field pass.  Unreadable images are named on stderr and left out (exit status 1 after writing, as
``hil star``).  The fit runs in this process and writes nothing to the lake (``--lake``, ``--run``,
``--workers`` ... are not used); run ``dualsight hil star IMAGES --camera CAMERA.toml`` for the per-image report
and lake rows with the fitted camera.  Progress (one line per pass) goes to stderr, the summary to stdout;
``--json`` prints one JSON object instead (keys in :func:`summary_json`) and no progress.

Measured (tests/test_distortion_fit.py): 12 frames of a 30 deg field, k1 = -0.22, k2 = 0.05 (corners 15.4 px),
camera file without distortion and fx 1 % short: k1 fitted to 0.5 %, every frame solved with attitude errors
as with the true coefficients (median 1.2 arcsec), none solved without the fit; ~4 s.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualsight.errors import ImageError, InputError
from dualsight.nav import distortion_fit as dfit
from dualsight.nav.distortion_bootstrap import bootstrap_plan
from dualsight.scene.units import ARCSEC

__all__ = ["MIN_STARS", "FULL_ITERATIONS", "FOCAL_SEARCH", "FramePixels", "SolvePass", "FitReport", "check_output",
           "detect_all", "solve_pass", "identified_stars", "camera_with", "fit_from_spec", "summary_text",
           "summary_json", "write_fitted_camera", "cmd_fit_distortion"]

MIN_STARS = 30
"""Fewest identified stars (over all solved frames) the fit accepts: 60 residuals for the 3 camera parameters
and 3 rotation angles per frame, with a margin for the outliers; with fewer the command refuses."""
FULL_ITERATIONS = 3
"""Whole-field solve-and-fit passes at most (the first fit, then re-solved with the fitted camera twice)."""
BOOTSTRAP_SIGMA_FRACTION = 0.25
"""A central pass's fit is kept only when its robust residual sigma is under this fraction of the pass's
voting tolerance (px) and it keeps at least MIN_STARS stars: right identifications fit to the centroid noise
(~0.05-0.1 px), wrong ones made by chance within the tolerance only to a good fraction of it."""
FOCAL_SEARCH = (1.0, 0.98, 1.02, 0.96, 1.04)
"""Focal-length scales tried, in this order, in the first central pass until one identifies enough stars for
a fit: the bootstrap's tolerance covers a 1 % focal error (nav.distortion_fit.PLAUSIBLE_FOCAL_ERROR), so
2 % steps cover a nominal focal length up to ~5 % off."""
BOOTSTRAP_CONFIG = dfit.FitConfig(focal="common", fit_k1=True, fit_k2=False)
"""Fit of the central passes: k1 and the focal length (k2 is not determined by the centre of the field)."""
FULL_CONFIG = dfit.FitConfig(focal="common", fit_k1=True, fit_k2=True)
"""Fit of the whole-field passes: k1, k2 and one focal length (fx = fy); principal point held."""


# ============================================================================================ frames
@dataclass(frozen=True)
class FramePixels:
    """Detections of F frames, padded to (F, S), brightest first (``hil_star``'s ``max_obs`` per frame).

    x, y : (F, S) float64 centroids (col, row), px (NaN in padding); valid : (F, S) bool.
    errors : (F,) None or why the image could not be processed (then no detections).
    """

    x: np.ndarray
    y: np.ndarray
    valid: np.ndarray
    errors: tuple


def detect_all(spec, rt) -> FramePixels:
    """Read and detect every image of a ``hil_star`` spec, ``settings.batch_size`` frames at a time (the
    chain of jobs/kinds/hil_star.py: read_frame, detect_frames, observations)."""
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.nav.observations import observations

    F, bs = len(spec.images), spec.settings.batch_size
    errors: list = [None] * F
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
            obs = observations(det, len(good), rt.camera, max_obs=rt.settings.max_obs)
            parts.append((np.asarray(good), obs.x, obs.y, obs.valid))
    S = max([p[1].shape[1] for p in parts], default=1)
    x = np.full((F, S), np.nan)
    y = np.full((F, S), np.nan)
    valid = np.zeros((F, S), bool)
    for k, px, py, pv in parts:
        x[k, :px.shape[1]], y[k, :px.shape[1]], valid[k, :px.shape[1]] = px, py, pv
    return FramePixels(x, y, valid, tuple(errors))


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
    principal point (None = all): ``nav.star_solution.identify`` and ``solve``, as ``hil star``."""
    from dualsight.nav.observations import Observations
    from dualsight.nav.star_solution import identify, solve

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


def camera_with(camera, intr: dfit.Intrinsics):
    """``camera`` with the intrinsics ``intr`` (size, pixel pitch and bit depth kept)."""
    from dualsight.scene.camera import Camera

    return Camera(camera.width, camera.height, camera.pixel_pitch_m, intr.fx, intr.fy, intr.cx, intr.cy,
                  tuple(intr.distortion), camera.bit_depth)


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
    """Everything :func:`fit_from_spec` found (the camera file and the summary are made from it)."""

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


def _with_tolerance(voting, tol: float):
    """``voting`` with its tolerances (voting, verification, attitude check) scaled to ``tol`` (rad)."""
    import dataclasses

    k = tol / voting.tolerance_rad
    return dataclasses.replace(voting, tolerance_rad=tol, **{
        n: min(getattr(voting, n) * k, math.pi / 180) for n in ("verify_tolerance_rad", "attitude_tolerance_rad")
        if getattr(voting, n) is not None})


def _truth_errors(spec, sp: SolvePass) -> np.ndarray | None:
    """(solved frames,) rad: angle between each solved attitude and the spec's truth (None without truth)."""
    from dualsight.nav.errors import total_error_angle

    if not spec.truths:
        return None
    k = [i for i in np.flatnonzero(sp.solved) if spec.truth(int(i)).A is not None]
    if not k:
        return np.zeros(0)
    A_true = np.stack([spec.truth(int(i)).matrix("A") for i in k])
    return total_error_angle(sp.A[k], A_true)


def _too_few(n: int, sp: SolvePass, F: int) -> InputError:
    return InputError(f"only {n} stars identified in {int(sp.solved.sum())} solved of {F} frames; the fit needs at "
                      f"least {MIN_STARS} (give more frames, or a camera file closer to the lens)",
                      source="--fit-distortion")


def fit_from_spec(spec, log=None, warn=None) -> FitReport:
    """Solve, fit and re-solve the frames of a validated ``hil_star`` spec (module docstring, steps 1-3).

    ``log``: None or a callable taking one line of progress; ``warn``: None or a callable taking the message
    of an image that could not be processed.  Raises InputError (too few stars)."""
    from dualsight.jobs.kinds import hil_star as hs

    t0 = time.perf_counter()
    say = log or (lambda line: None)
    rt = hs.runtime(spec)
    ctx = hs.make_context(spec)
    cat, pairs, voting, bs = ctx.catalog, ctx.pairs, rt.voting, spec.settings.batch_size
    cam0 = rt.camera
    pix = detect_all(spec, rt)
    for e in pix.errors:
        if e and warn is not None:
            warn(e)
    F = len(spec.images)
    passes: list[PassLog] = []

    def run(cam, radius, cfg, vote=voting):
        sp = solve_pass(pix, cam, cat, pairs, vote, radius, bs)
        u, fr, px, _ = identified_stars(pix, sp, cat.unit)
        entry = PassLog(radius, cam.fx, int(sp.solved.sum()), len(u), None, _truth_errors(spec, sp))
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
        say(_pass_line(len(passes), entry, F))
        return sp, entry

    cam = cam0
    if not cam0.has_distortion:
        plan = bootstrap_plan(0.5 * math.hypot(cam0.width, cam0.height), 0.5 * (cam0.fx + cam0.fy),
                                   len(cat.unit), voting.tolerance_rad)
        boot = _with_tolerance(voting, plan.tolerance_rad)
        say(f"bootstrap: the camera file has no distortion; central passes vote with "
            f"{plan.tolerance_rad / ARCSEC:.0f} arcsec")
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
            raise _too_few(entry.stars, sp, F)
        u, fr, px, _ = identified_stars(pix, sp, cat.unit)
        fit = entry.fit = dfit.fit_camera(u, fr, px, sp.A, dfit.Intrinsics.of(cam), FULL_CONFIG)
        cam, prev, fit_sp = camera_with(cam, fit.intrinsics), key, sp
        say(f"  fitted {fit_line(fit)}")
    if final is None:
        final, _ = run(cam, None, None)
    # rms before: the fitted stars under the input camera, each frame's attitude re-fitted
    u, fr, px, _ = identified_stars(pix, fit_sp, cat.unit)
    keep = fit.inlier
    before = dfit.fit_camera(u[keep], fr[keep], px[keep], fit.A, dfit.Intrinsics.of(cam0),
                             dfit.FitConfig(focal="fixed", fit_k1=False, fit_k2=False, max_rounds=0))
    return FitReport(cam0, cam, fit, before.rms_px, final, passes, pix.errors, F,
                     _truth_errors(spec, final), time.perf_counter() - t0)


def fit_line(fit: dfit.FitResult) -> str:
    i, sd = fit.intrinsics, fit.std
    s = f"fx {i.fx:.2f}" + (f" +- {sd['fx']:.2f}" if "fx" in sd else "")
    if abs(i.fy - i.fx) > 1e-9:
        s += f", fy {i.fy:.2f}" + (f" +- {sd['fy']:.2f}" if "fy" in sd else "")
    s += f" px, k1 {i.distortion[0]:.5f}" + (f" +- {sd['k1']:.5f}" if "k1" in sd else "")
    s += f", k2 {i.distortion[1]:.5f}" + (f" +- {sd['k2']:.5f}" if "k2" in sd else "")
    return (s + f"; {fit.n_stars} stars in {fit.n_frames} frames, rms {fit.rms_px:.3f} px, "
            f"{int((~fit.inlier).sum())} rejected")


def _pass_line(n: int, p: PassLog, F: int) -> str:
    region = "whole field" if p.radius_px is None else f"r <= {p.radius_px:.0f} px, fx {p.fx:.1f} px"
    s = f"pass {n}: {region}: {p.solved}/{F} frames solved, {p.stars} stars identified"
    if p.attitude_err_rad is not None and p.attitude_err_rad.size:
        s += f", attitude error vs truth median {np.median(p.attitude_err_rad) / ARCSEC:.1f} arcsec"
    if p.fit is not None and p.radius_px is not None:
        s += f"; fitted k1 {p.fit.intrinsics.distortion[0]:.5f}, fx {p.fit.intrinsics.fx:.2f} px"
    if p.note:
        s += f"; {p.note}"
    return s


# ============================================================================================ output
def _what(cam0) -> str:
    return (f"k1, k2 and one focal length (fx = fy) jointly with each frame's attitude; principal point held at "
            f"({cam0.cx:g}, {cam0.cy:g}) px, p1, p2, k3 at {list(cam0.distortion[2:])}")


def summary_json(rep: FitReport, output: Path | None) -> dict:
    """One JSON object: output (path), images (count), errors [unreadable images], passes [{radius_px (null =
    whole field), fx_px, solved, stars, attitude_error (null or {median_arcsec, max_arcsec} against --truth)}],
    fitted {fx, fy, cx, cy, k1, k2, p1, p2, k3}, std {fx, fy, k1, k2} (one sigma), stars_used, frames_used,
    stars_rejected, rms_before_px, rms_after_px, sigma_px, final {solved, stars, attitude_error} (the re-solve
    with the fitted camera), seconds."""
    i, f = rep.fit.intrinsics, rep.final

    def err(a):
        return None if a is None or not a.size else {"median_arcsec": float(np.median(a) / ARCSEC),
                                                     "max_arcsec": float(np.max(a) / ARCSEC)}

    return {
        "output": None if output is None else str(output), "images": rep.n_images,
        "errors": [e for e in rep.errors if e],
        "passes": [{"radius_px": p.radius_px, "fx_px": p.fx, "solved": p.solved, "stars": p.stars,
                    "attitude_error": err(p.attitude_err_rad)} for p in rep.passes],
        "fitted": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy, **dict(zip(("k1", "k2", "p1", "p2", "k3"),
                                                                            i.distortion))},
        "std": rep.fit.std, "stars_used": rep.fit.n_stars, "frames_used": rep.fit.n_frames,
        "stars_rejected": int((~rep.fit.inlier).sum()), "rms_before_px": rep.rms_before_px,
        "rms_after_px": rep.fit.rms_px, "sigma_px": rep.fit.sigma_px,
        "final": {"solved": int(f.solved.sum()), "stars": int(f.stars.sum()),
                  "attitude_error": err(rep.final_attitude_err_rad)},
        "seconds": rep.seconds,
    }


def summary_text(rep: FitReport, output: Path | None) -> str:
    f, fit = rep.final, rep.fit
    lines = [f"fitted   {fit_line(fit)}",
             f"         {_what(rep.camera_in)}",
             f"rms      {rep.rms_before_px:.3f} px with the input camera (attitudes re-fitted) -> {fit.rms_px:.3f} px "
             f"fitted (robust sigma {fit.sigma_px:.3f} px per axis; outliers: > "
             f"{FULL_CONFIG.reject_sigma:g} sigma and > {FULL_CONFIG.reject_floor_px:g} px)",
             f"re-solved with the fitted camera: {int(f.solved.sum())}/{rep.n_images} frames, "
             f"{int(f.stars.sum())} stars identified"]
    if rep.final_attitude_err_rad is not None and rep.final_attitude_err_rad.size:
        a = rep.final_attitude_err_rad / ARCSEC
        lines[-1] += f", attitude error vs truth median {np.median(a):.1f}, max {a.max():.1f} arcsec"
    if output is not None:
        lines.append(f"wrote {output}")
    return "\n".join(lines)


def write_fitted_camera(rep: FitReport, output: Path, camera_file: Path, images: list) -> Path:
    """The camera file (``[camera]`` + ``[distortion_fit]``, comments with what was fitted and the rms)."""
    from dualsight.scene import calibration as cal
    from dualsight.scene.camera import read_toml

    fit, cam0 = rep.fit, rep.camera_in
    src = read_toml(camera_file).get("camera", {})
    n_img = rep.n_images
    where = str(Path(images[0]).parent) if images else "?"
    comment = "\n".join([
        f"Fitted by `dualsight hil star --fit-distortion` from {fit.n_stars} identified stars in {fit.n_frames} "
        f"solved frames",
        f"  ({n_img} images in {where}; input camera file {camera_file}).",
        f"Fitted: {_what(cam0)}.",
        "  " + fit_line(fit) + ".",
        f"rms residual {rep.rms_before_px:.3f} px before (input camera, attitudes re-fitted), {fit.rms_px:.3f} px "
        f"after; {int((~fit.inlier).sum())} stars rejected as outliers (> {FULL_CONFIG.reject_sigma:g} sigma).",
        f"Re-solved with this camera: {int(rep.final.solved.sum())}/{n_img} frames, "
        f"{int(rep.final.stars.sum())} stars identified."])
    table = {"method": "nav/distortion_fit.py: Levenberg-Marquardt, OpenCV radial model, Huber + rejection",
             "input_camera": str(camera_file), "images": n_img, "frames_used": fit.n_frames,
             "stars_used": fit.n_stars, "stars_rejected": int((~fit.inlier).sum()),
             "fitted": ["fx=fy", "k1", "k2"], "std": fit.std, "rms_before_px": rep.rms_before_px,
             "rms_after_px": fit.rms_px, "sigma_px": fit.sigma_px, "reject_sigma": FULL_CONFIG.reject_sigma,
             "min_stars": MIN_STARS, "frames_solved_after": int(rep.final.solved.sum())}
    notes = f"k1, k2, fx = fy fitted from {fit.n_stars} stars in {fit.n_frames} frames (hil star --fit-distortion)"
    return cal.write_camera_toml(rep.camera, output, extra={"distortion_fit": table}, name=src.get("name"),
                                 notes=notes, comment=comment)


def check_output(args) -> Path:
    """The ``-o`` of ``--fit-distortion``, refused before any work when missing, a folder, in a missing folder,
    or an existing file without ``--force``."""
    out = args.output
    if out is None:
        raise InputError("needs -o/--output CAMERA.toml (the fitted camera file to write)", source="--fit-distortion")
    if out.is_dir():
        raise InputError("is a folder; give the camera file's name, e.g. fitted.toml", source=str(out))
    if not out.parent.is_dir():
        raise InputError(f"folder {out.parent} does not exist; create it first", source=str(out))
    if out.exists() and not args.force:
        raise InputError("exists; give --force to overwrite it", source=str(out))
    return out


def cmd_fit_distortion(args) -> int:
    """The ``--fit-distortion`` branch of ``dualsight hil star`` (module docstring)."""
    from dualsight.jobs.cli.hil_star import star_spec_from_args

    if not args.fit_distortion:
        raise InputError("-o/--output and --force go with --fit-distortion", source="hil star")
    if getattr(args, "sweep", None):
        raise InputError("fits one camera with one set of settings; drop --sweep", source="--fit-distortion")
    if args.overlay_dir is not None:
        raise InputError("draws no overlays; run hil star with the fitted camera for them", source="--fit-distortion")
    out = check_output(args)
    spec = star_spec_from_args(args)
    rep = fit_from_spec(spec, log=None if args.json else (lambda line: print(line, file=sys.stderr)),
                        warn=lambda e: print(f"dualsight: {e}; skipped, the other images go on", file=sys.stderr))
    try:
        write_fitted_camera(rep, out, args.camera, [e.path for e in spec.images])
    except OSError as e:
        raise InputError(f"cannot write the camera file ({e.strerror or e})", source=str(out)) from None
    print(json.dumps(summary_json(rep, out), indent=1) if args.json else summary_text(rep, out))
    return 1 if any(rep.errors) else 0
