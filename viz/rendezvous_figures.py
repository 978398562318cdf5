"""Figures of rendezvous runs (issue 23, point 5), drawn from query results over ``rendezvous_frames``: the
relative-position error against range and against time with the filter's 3-sigma envelope (the reference's Fig. 7
over time), and the mean NEES per frame against its 95 % chi-square bounds; and the rerun film of one approach
(:func:`log_rendezvous_frame`: the image and the relative trajectory in 3-D).  Never calls back into ``jobs``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.viz.figures import pyplot, save_figure

__all__ = ["error_vs_range_fig", "error_vs_range_figure", "nees_fig", "nees_figure", "log_rendezvous_frame"]


def error_vs_range_fig(per_frame: dict, approaches: list[dict]):
    """Left: position error against range (log-log); right: the same against time; the open figure.

    per_frame : {"t_s", "range_mean_m", "pos_err_rms_m", "sigma_pos_rms_m": (T,)} over all approaches
    (``rendezvous_nees.sql``): the RMS error (black) and 3 x the filter's RMS sqrt(trace P_rr) (thick grey).
    approaches : [{"case_id", "t_s", "range_m", "pos_err_m", "sigma_pos_m": (T,)}] a few single approaches, each
    with its own 3-sigma envelope (dashed, same colour).  m, s."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.4), constrained_layout=True)
    for ax, xk, xa in ((axs[0], "range_mean_m", "range_m"), (axs[1], "t_s", "t_s")):
        x = np.asarray(per_frame[xk], np.float64)
        ax.plot(x, 3 * np.asarray(per_frame["sigma_pos_rms_m"], np.float64), color="0.6", lw=3.0, alpha=0.6,
                label="3 sigma (filter, RMS)")          # a line: the range is not monotonic (a hop overshoots)
        ax.plot(x, per_frame["pos_err_rms_m"], "k.-", lw=1.2, ms=3, label="error RMS (all approaches)")
        for i, a in enumerate(approaches):
            c = f"C{i}"
            ax.plot(a[xa], a["pos_err_m"], "-", color=c, lw=0.8, label=f"approach {a['case_id']}")
            ax.plot(a[xa], 3 * np.asarray(a["sigma_pos_m"], np.float64), "--", color=c, lw=0.7)
        ax.set_yscale("log")
        ax.set_ylabel("relative-position error (m)")
    axs[0].set_xscale("log")
    axs[0].invert_xaxis()
    axs[0].set_xlabel("range (m), approaching ->")
    axs[0].set_title("Error against range", fontsize=10)
    axs[1].set_xlabel("time (s)")
    axs[1].set_title("Error against time", fontsize=10)
    axs[1].legend(fontsize=7, loc="upper right")
    return fig


def error_vs_range_figure(per_frame: dict, approaches: list[dict], path: Path) -> Path:
    """:func:`error_vs_range_fig` as the PNG ``path``."""
    return save_figure(error_vs_range_fig(per_frame, approaches), path)


def nees_fig(per_frame: dict, bounds: list[tuple[str, float, float, str]], converged_after: int,
             band: tuple[str, float, float] | None = None):
    """Mean NEES (6 dof) per frame against time with the two-sided 95 % chi-square bounds of its mean; frames
    before ``converged_after`` shaded.  per_frame : {"t_s": (T,), series name: (T,) ...}; bounds : [(series name,
    lower, upper, label)] one line pair per series; band : optional (series name, lower, upper), that series'
    simultaneous 95 % band over the frames (``nav/nees_band.py``), dotted in its colour; the open figure."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(11, 4.0), constrained_layout=True)
    t = np.asarray(per_frame["t_s"], np.float64)
    if 0 < converged_after <= t.size:
        ax.axvspan(t[0], t[converged_after - 1] if converged_after > 0 else t[0], color="0.92", lw=0,
                   label="before convergence")
    for i, (key, lo, hi, lab) in enumerate(bounds):
        c = f"C{i}"
        ax.plot(t, np.asarray(per_frame[key], np.float64), ".-", color=c, lw=1.0, ms=3, label=lab)
        for v in (lo, hi):
            ax.axhline(v, color=c, ls="--", lw=0.8)
    keys = [b[0] for b in bounds]
    if band is not None and band[0] in keys:
        c = f"C{keys.index(band[0])}"
        for i, v in enumerate(band[1:]):
            ax.axhline(v, color=c, ls=":", lw=1.2, label=None if i else "simultaneous 95 % band over the frames")
    ax.axhline(6.0, color="0.4", lw=0.6)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mean NEES (6 dof)")
    ax.set_title("Filter consistency: mean NEES per frame, its one-frame 95 % bounds (dashed)"
                 + (" and the simultaneous band (dotted)" if band is not None else ""), fontsize=10)
    ax.legend(fontsize=8, loc="lower right", ncol=2)   # the curves sit near 6, above the lower bounds
    return fig


def nees_figure(per_frame: dict, bounds: list, converged_after: int, path: Path, band=None) -> Path:
    """:func:`nees_fig` as the PNG ``path``."""
    return save_figure(nees_fig(per_frame, bounds, converged_after, band), path)


def log_rendezvous_frame(rec, *, frame: int, image: np.ndarray, target_xy, truth_xy, truth_path: np.ndarray,
                         est_path: np.ndarray, sigma3: np.ndarray, info_md: str, scalars: dict):
    """Log one frame of an approach at ``frame`` on the ``frame`` time line of the rerun recording ``rec``.

    image : (H, W) the frame as rendered; target_xy : (2,) the target's measured centre (col, row; NaN: none),
    drawn green; truth_xy : (2,) the target's true projection (blue).  truth_path, est_path : (k + 1, 3) the
    chaser's true and estimated Hill positions (m) up to this frame (entity ``hill``: the target at the origin, x
    radial, y along-track, z cross-track); sigma3 : (3,) 3 x the filter's sigma per Hill axis, drawn as an
    axis-aligned ellipsoid about the estimate (the covariance diagonal).  scalars : numbers as time series
    ``metrics/<name>`` (None and NaN skipped).  info_md : markdown of the frame (entity ``case``)."""
    import rerun as rr                                        # rerun: only when recording

    rec.set_time("frame", sequence=frame)
    img = np.asarray(image, dtype=np.float32)
    hi = float(np.percentile(img, 99.9)) or float(img.max()) or 1.0
    rec.log("camera/image", rr.Image((np.sqrt(np.clip(img / hi, 0, 1)) * 255).astype(np.uint8)))
    for name, xy, colour in (("measured", target_xy, [40, 220, 40]), ("truth", truth_xy, [80, 140, 255])):
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        if np.all(np.isfinite(xy)):
            rec.log(f"camera/image/target_{name}", rr.Points2D(xy, radii=5.0, colors=[colour]))
        else:
            rec.log(f"camera/image/target_{name}", rr.Clear(recursive=False))
    rec.log("hill/target", rr.Points3D([[0.0, 0.0, 0.0]], radii=0.5, colors=[[250, 210, 40]], labels=["target"]))
    rec.log("hill/truth", rr.LineStrips3D([truth_path], colors=[[80, 140, 255]]))
    rec.log("hill/estimate", rr.LineStrips3D([est_path], colors=[[240, 120, 40]]))
    rec.log("hill/chaser", rr.Points3D([truth_path[-1], est_path[-1]], radii=0.3,
                                       colors=[[80, 140, 255], [240, 120, 40]], labels=["chaser (truth)", "estimate"]))
    rec.log("hill/sigma3", rr.Ellipsoids3D(centers=[est_path[-1]], half_sizes=[np.asarray(sigma3, np.float64)],
                                           colors=[[240, 120, 40]]))
    for k, v in scalars.items():
        if v is not None and np.isfinite(v):
            rec.log(f"metrics/{k}", rr.Scalars(float(v)))
    rec.log("case", rr.TextDocument(info_md, media_type=rr.MediaType.MARKDOWN))
