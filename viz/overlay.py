"""Predicted versus observed stars on a real frame (the reference's Figure 11), as a PNG (matplotlib).

Left panel: the frame (square-root stretch, noise kept dark: :func:`_display`), every detection,
every identified star's observed centroid and its position predicted by the solved attitude (catalog
unit vector -> A_est -> camera model), the offset between them drawn ``error_scale`` times enlarged
(one pixel of a 35 mm / 6.9 um camera is ~40 arcsec and the offsets are a tenth of that, invisible at
true scale), HIP labels of the brightest identified stars, and optionally the catalog stars the attitude
puts in the field and the centroids of an independent solution (truth file).
Right panel: every identified star's offset (observed minus predicted) in arcseconds on the sky's
tangent plane at the star, i.e. pixel offset x the local plate scale, with its median circle.

Draws arrays only; never calls back into ``jobs`` (docs/architecture.md, Layers).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.viz.figures import pyplot, save_figure


def _display(image: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Square-root stretch from 1 noise sigma above the sky (median; sigma = 1.4826 MAD) to the
    99.95th percentile, so that the noise stays dark and faint stars show."""
    img = np.asarray(image, dtype=np.float32)
    sample = img[::4, ::4]
    med = float(np.median(sample))
    sig = 1.4826 * float(np.median(np.abs(sample - med)))
    lo = med + sig
    hi = max(float(np.percentile(img, 99.95)), lo + 20.0 * max(sig, 1e-6))
    return np.sqrt(np.clip((img - lo) / (hi - lo), 0.0, 1.0)), lo, hi


def star_overlay(path: str | Path, image: np.ndarray, *, detections: np.ndarray | None,
                 identified: list[tuple], field_xy: np.ndarray | None = None, field_vmag: np.ndarray | None = None,
                 truth_xy: np.ndarray | None = None, title: str = "", info: list[str] | None = None,
                 credit: str | None = None, error_scale: float = 100.0, arcsec_per_px: float | None = None,
                 max_labels: int = 25, dpi: int = 110) -> Path:
    """Write the overlay picture of one frame.

    Parameters
    ----------
    path : output PNG.
    image : (H, W) frame (any numeric dtype; a background-subtracted frame shows faint stars best).
    detections : (K, 2) all detected centroids (col, row; top-left corner convention), or None.
    identified : per identified star ``(obs_col, obs_row, pred_col, pred_row, hip, vmag, error_arcsec)``.
    field_xy, field_vmag : catalog stars projected with the solved attitude (col, row) and their V.
    truth_xy : (G, 2) centroids of an independent solution's matched stars.
    title, info : figure title and lines of numbers under it.
    credit : attribution printed at the bottom (required by the ESA frames' licence).
    error_scale : enlargement of the observed-predicted offsets in the left panel.
    arcsec_per_px : plate scale for the right panel; None = derived from each star's pixel offset and
        its error (error / |offset|, median over the stars), i.e. the panel shows the offsets' directions
        with their true angular lengths.
    """
    plt = pyplot()
    disp, _, _ = _display(image)
    H, W = disp.shape[:2]
    fig = plt.figure(figsize=(13.2, 6.9), dpi=dpi)
    gs = fig.add_gridspec(1, 2, width_ratios=[2.75, 1.0], wspace=0.16, left=0.05, right=0.985, top=0.86,
                          bottom=0.09)
    ax = fig.add_subplot(gs[0])
    ax.imshow(disp, cmap="gray", origin="upper", extent=(0, W, H, 0), interpolation="nearest")
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")

    handles = []
    if field_xy is not None and len(field_xy):
        v = np.asarray(field_vmag, float) if field_vmag is not None else np.full(len(field_xy), 6.0)
        size = np.clip(400.0 * 10 ** (-0.25 * (v - 3.0)), 30, 400)
        h = ax.scatter(field_xy[:, 0], field_xy[:, 1], s=size, facecolors="none", edgecolors="#4d8dff",
                       linewidths=0.8, alpha=0.9, label="catalog stars in the field (solved attitude; size ~ V)")
        handles.append(h)
    if truth_xy is not None and len(truth_xy):
        h = ax.scatter(truth_xy[:, 0], truth_xy[:, 1], s=150, marker="s", facecolors="none",
                       edgecolors="#ffd21f", linewidths=0.8, label="independent solution's stars")
        handles.append(h)
    if detections is not None and len(detections):
        h = ax.scatter(detections[:, 0], detections[:, 1], s=14, marker="o", facecolors="none",
                       edgecolors="#ff5a5a", linewidths=0.6, label="detections")
        handles.append(h)
    ids = np.asarray([t[:4] for t in identified], float).reshape(-1, 4)
    if len(ids):
        obs, pred = ids[:, :2], ids[:, 2:4]
        tip = pred + error_scale * (obs - pred)
        for (px, py), (tx, ty) in zip(pred, tip):
            ax.plot([px, tx], [py, ty], color="#3cff5a", lw=1.2)
        h1 = ax.scatter(obs[:, 0], obs[:, 1], s=70, marker="o", facecolors="none", edgecolors="#3cff5a",
                        linewidths=1.3, label="observed (identified)")
        h2 = ax.scatter(pred[:, 0], pred[:, 1], s=70, marker="+", color="#ff3cf0", linewidths=1.3,
                        label=f"predicted from attitude (offset x{error_scale:g})")
        handles += [h1, h2]
        order = np.argsort([t[5] for t in identified])[:max_labels]
        for k in order:
            ox, oy, _, _, hip, vmag, err = identified[k]
            ax.annotate(f"HIP {hip}\nV {vmag:.1f}, {err:.0f}\"", (ox, oy), xytext=(7, 5), textcoords="offset points",
                        fontsize=6.5, color="white", alpha=0.9)
    right = gs[1].subgridspec(2, 1, height_ratios=[3.0, 1.25], hspace=0.3)
    leg = fig.add_subplot(right[1])                   # the legend sits under the error panel, off the image
    leg.axis("off")
    leg.legend(handles=handles, loc="center", fontsize=7.5, framealpha=0.9, markerscale=0.8)

    # --- right: offsets on the sky
    ax2 = fig.add_subplot(right[0])
    if len(ids):
        d = ids[:, :2] - ids[:, 2:4]
        dn = np.hypot(d[:, 0], d[:, 1])
        err = np.array([t[6] for t in identified], float)
        scale = arcsec_per_px
        if scale is None:
            good = dn > 1e-6
            scale = float(np.median(err[good] / dn[good])) if good.any() else 1.0
        da = d * scale
        ax2.axhline(0, color="0.7", lw=0.6)
        ax2.axvline(0, color="0.7", lw=0.6)
        ax2.scatter(da[:, 0], da[:, 1], c=[t[5] for t in identified], cmap="viridis_r", s=28, zorder=3)
        for k in np.argsort(err)[::-1][:6]:
            ax2.annotate(str(identified[k][4]), (da[k, 0], da[k, 1]), xytext=(4, 3), textcoords="offset points",
                         fontsize=6.5)
        med = float(np.median(err))
        ax2.add_patch(plt.Circle((0, 0), med, fill=False, ls="--", color="tab:red",
                                 label=f"median {med:.1f}\""))
        lim = max(5.0, 1.15 * float(np.max(np.abs(da))))
        ax2.set_xlim(-lim, lim)
        ax2.set_ylim(lim, -lim)
        ax2.legend(loc="upper right", fontsize=8)
    else:
        ax2.text(0.5, 0.5, "no identified stars", ha="center", va="center", transform=ax2.transAxes)
    ax2.set_aspect("equal")
    ax2.set_xlabel("observed - predicted, along columns (arcsec)")
    ax2.set_ylabel("along rows (arcsec)")
    ax2.set_title("per-star error (colour: V mag)", fontsize=9)

    fig.suptitle(title, fontsize=11, x=0.04, ha="left", y=0.985)
    if info:
        fig.text(0.04, 0.93, "\n".join(info), fontsize=8.5, va="top", ha="left", family="monospace")
    if credit:
        fig.text(0.985, 0.012, credit, fontsize=7, ha="right", va="bottom", color="0.3")
    return save_figure(fig, path, dpi=dpi)
