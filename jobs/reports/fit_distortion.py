"""What ``dualsight hil star --fit-distortion`` prints: the progress lines (one per pass, on stderr), the summary
(stdout) or its ``--json`` object, and the lines that describe a fit (also written as comments into the fitted
camera file).  Input: the :class:`~dualsight.nav.distortion_procedure.FitReport` of jobs/kinds/fit_distortion.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.nav.distortion_fit import FitResult
from dualsight.nav.distortion_procedure import FULL_CONFIG, FitReport, PassLog
from dualsight.scene.units import ARCSEC

__all__ = ["fit_line", "pass_line", "what_was_fitted", "progress_line", "summary_json", "summary_text"]


def fit_line(fit: FitResult) -> str:
    """The fitted intrinsics with their one-sigma uncertainties, the stars, frames, rms and rejections."""
    i, sd = fit.intrinsics, fit.std
    s = f"fx {i.fx:.2f}" + (f" +- {sd['fx']:.2f}" if "fx" in sd else "")
    if abs(i.fy - i.fx) > 1e-9:
        s += f", fy {i.fy:.2f}" + (f" +- {sd['fy']:.2f}" if "fy" in sd else "")
    s += f" px, k1 {i.distortion[0]:.5f}" + (f" +- {sd['k1']:.5f}" if "k1" in sd else "")
    s += f", k2 {i.distortion[1]:.5f}" + (f" +- {sd['k2']:.5f}" if "k2" in sd else "")
    return (s + f"; {fit.n_stars} stars in {fit.n_frames} frames, rms {fit.rms_px:.3f} px, "
            f"{int((~fit.inlier).sum())} rejected")


def pass_line(n: int, p: PassLog, n_frames: int) -> str:
    """Pass ``n``: its region, frames solved, stars identified, attitude error against the truth, central fit."""
    region = "whole field" if p.radius_px is None else f"r <= {p.radius_px:.0f} px, fx {p.fx:.1f} px"
    s = f"pass {n}: {region}: {p.solved}/{n_frames} frames solved, {p.stars} stars identified"
    if p.attitude_err_rad is not None and p.attitude_err_rad.size:
        s += f", attitude error vs truth median {np.median(p.attitude_err_rad) / ARCSEC:.1f} arcsec"
    if p.fit is not None and p.radius_px is not None:
        s += f"; fitted k1 {p.fit.intrinsics.distortion[0]:.5f}, fx {p.fit.intrinsics.fx:.2f} px"
    if p.note:
        s += f"; {p.note}"
    return s


def what_was_fitted(cam0) -> str:
    """Which parameters a whole-field fit frees and which it holds at the input camera ``cam0``'s values."""
    return (f"k1, k2 and one focal length (fx = fy) jointly with each frame's attitude; principal point held at "
            f"({cam0.cx:g}, {cam0.cy:g}) px, p1, p2, k3 at {list(cam0.distortion[2:])}")


def progress_line(event: str, value, n_frames: int) -> str:
    """The stderr line of a progress event of ``nav.distortion_procedure.fit_camera_from_sky``."""
    if event == "bootstrap":
        return (f"bootstrap: the camera file has no distortion; central passes vote with "
                f"{value / ARCSEC:.0f} arcsec")
    if event == "pass":
        return pass_line(value[0], value[1], n_frames)
    return f"  fitted {fit_line(value)}"


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
    """The summary printed on stdout: the fit, what it freed, the rms before and after, the re-solve."""
    f, fit = rep.final, rep.fit
    lines = [f"fitted   {fit_line(fit)}",
             f"         {what_was_fitted(rep.camera_in)}",
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
