"""Figures of proximity runs: Fig. 7 (range estimates with min/max bars per true range), Fig. 6 (trajectory: true
vs estimated position per axis) and Fig. 1 (the target's projected-area curves).  Never calls back into ``jobs``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.viz.figures import pyplot, save_figure

__all__ = ["plot_sweep", "plot_trajectory", "areas_figure"]


def plot_sweep(rep: dict, path: Path) -> Path:
    plt = pyplot()
    r = np.array([x["true_range_m"] for x in rep["ranges"]])
    fig, ax = plt.subplots(figsize=(7.5, 5), constrained_layout=True)
    ax.plot(r, r, "k-", lw=1, label="true range")
    for est, color, dx in (("paper", "tab:red", 0.97), ("subpixel", "tab:green", 1.03)):
        est_m = np.array([x[est]["avg_est_m"] for x in rep["ranges"]], dtype=float)
        ax.plot(r * dx, est_m, "o", color=color, label=f"{est}: mean estimate")
    ref = [x["reference"].get("avg_est_m") for x in rep["ranges"]]
    if any(v is not None for v in ref):
        ax.plot(r, np.array([np.nan if v is None else v for v in ref], dtype=float), "s", mfc="none", color="gray",
                label="reference Table 3")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("true range (m)")
    ax.set_ylabel("estimated range (m)")
    ax.set_title(f"Range sweep {rep['run']} (renderer: {rep['mode']})")
    ax.legend()
    return save_figure(fig, path)


def plot_trajectory(rep: dict, path: Path) -> Path:
    plt = pyplot()
    fr = rep["frames"]
    k = np.array([f["frame"] for f in fr])
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True, constrained_layout=True)
    for ax, c in zip(axes, "xyz"):
        ax.plot(k, [f[f"true_{c}_m"] for f in fr], "k-", label="true")
        ax.plot(k, np.array([f[f"paper_{c}_m"] for f in fr], dtype=float), "r.", label="paper (Eq. 1)")
        ax.plot(k, np.array([f[f"subpixel_{c}_m"] for f in fr], dtype=float), "g.", label="subpixel")
        ax.set_ylabel(f"{c} (m)")
    axes[0].legend()
    axes[-1].set_xlabel("frame")
    fig.suptitle(f"Trajectory {rep['run']} (renderer: {rep['mode']})")
    return save_figure(fig, path)


def areas_figure(table, path: Path) -> Path:
    """Figure 1: projected area over the smallest face against axis ratio (min, mean, max curves).

    ``table``: a projected-area table (``catalogs.areas.area_table``: ``samples_ratio``, ``samples_area`` of
    the random orientations, and per axis-ratio bin ``ratio``, ``a_min``, ``a_mean``, ``a_max``)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    ax.plot(table.samples_ratio, table.samples_area, ".", ms=1.5, color="0.75", label="random orientations")
    for name, style in (("a_min", "b--"), ("a_mean", "k-"), ("a_max", "r--")):
        ax.plot(table.ratio, getattr(table, name), style, label=name.replace("a_", "A ") + " / A0")
    ax.set_xlabel("silhouette axis ratio (major / minor)")
    ax.set_ylabel("projected area / smallest face A0")
    ax.set_title("Projected-area curves (cf. reference Figure 1)")
    ax.legend()
    return save_figure(fig, path)
