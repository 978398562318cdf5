"""Range against binary threshold on real photos (the reference's Figure 8), as a PNG (matplotlib).

Top panel: for every threshold, every image's range estimate with its minimum/maximum range as error bars
(images spread slightly along the threshold axis so that their bars do not hide each other), the mean
estimate over the images as a line, and the true range (one dashed line when every image has the same
truth, else a marker per image).  Bottom panel: the average relative error (%) and the share of images
whose true range lies inside the min/max bars (%), per threshold.

Draws arrays (:func:`threshold_sweep_figure`) or a run's query results (:func:`hil_prox_figure`); never calls
back into ``jobs`` (docs/architecture.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.viz.figures import pyplot, save_figure

__all__ = ["threshold_sweep_figure", "hil_prox_figure"]


def threshold_sweep_figure(path: str | Path, thresholds, range_m, range_min_m, range_max_m, truth_m=None, *,
                           labels=None, sweep: list[dict] | None = None, title: str = "", dpi: int = 110) -> Path:
    """Write the figure.

    Parameters
    ----------
    thresholds : (T,) thresholds.
    range_m, range_min_m, range_max_m : (N, T) estimates and bars per image and threshold (NaN: no blob).
    truth_m : (N,) true ranges (NaN / None: unknown).
    labels : N image names (legend when there are at most 12 images).
    sweep : optional rows with ``threshold``, ``avg_rel_error_pct`` and ``within_min_max_pct`` (the run's
        warehouse/sql/hil_prox_sweep.sql); without them the bottom panel is computed from the arrays.
    """
    plt = pyplot()
    th = np.asarray(thresholds, dtype=float)
    est = np.atleast_2d(np.asarray(range_m, dtype=float))
    lo = np.atleast_2d(np.asarray(range_min_m, dtype=float))
    hi = np.atleast_2d(np.asarray(range_max_m, dtype=float))
    n = est.shape[0]
    truth = np.full(n, np.nan) if truth_m is None else np.array([np.nan if t is None else t for t in truth_m], float)
    labels = list(labels) if labels is not None else [f"image {i}" for i in range(n)]
    step = float(np.min(np.diff(th))) if th.size > 1 else 1.0
    spread = 0.5 * step / max(n, 1)

    has_truth = np.isfinite(truth).any()
    fig, axes = plt.subplots(2 if has_truth else 1, 1, figsize=(9, 7 if has_truth else 4.5), sharex=True,
                             constrained_layout=True, squeeze=False)
    a = axes[0, 0]
    cmap = plt.get_cmap("tab20" if n > 10 else "tab10")
    for i in range(n):
        x = th + (i - (n - 1) / 2) * spread
        ok = np.isfinite(est[i])
        yerr = np.vstack([est[i] - lo[i], hi[i] - est[i]])[:, ok]
        a.errorbar(x[ok], est[i, ok], yerr=yerr, fmt="o", ms=3, capsize=2, lw=0.8, color=cmap(i % cmap.N),
                   label=labels[i] if n <= 12 else None)
    with np.errstate(invalid="ignore"):
        mean = np.array([np.nanmean(c) if np.isfinite(c).any() else np.nan for c in est.T])
    a.plot(th, mean, "k-", lw=1.5, label="mean estimate")
    if has_truth:
        ft = truth[np.isfinite(truth)]
        if np.allclose(ft, ft[0]):
            a.axhline(ft[0], color="tab:red", ls="--", lw=1.2, label=f"true range {ft[0]:.4g} m")
        else:
            for i in range(n):
                if np.isfinite(truth[i]):
                    a.plot(th + (i - (n - 1) / 2) * spread, np.full(th.size, truth[i]), "_", ms=6,
                           color=cmap(i % cmap.N))
            a.plot([], [], "_", color="gray", label="true range (per image)")
    a.set_ylabel("range (m): estimate with min/max bars")
    a.set_title(title or "Range against binary threshold (cf. reference Fig. 8)")
    a.legend(fontsize=7, ncol=2 if n > 6 else 1, loc="best")
    a.grid(alpha=0.3)

    if has_truth:
        b = axes[1, 0]
        if sweep:
            sx = np.array([s["threshold"] for s in sweep], float)
            rel = np.array([np.nan if s.get("avg_rel_error_pct") is None else s["avg_rel_error_pct"] for s in sweep])
            within = np.array([np.nan if s.get("within_min_max_pct") is None else s["within_min_max_pct"]
                               for s in sweep])
        else:
            sx = th
            with np.errstate(invalid="ignore"):
                rel = np.nanmean(np.abs(est - truth[:, None]) / truth[:, None], axis=0) * 100
                inside = (truth[:, None] >= lo) & (truth[:, None] <= hi)
                within = 100.0 * inside[np.isfinite(truth)].mean(axis=0)
        b.plot(sx, rel, "o-", color="tab:blue", label="average relative error (%)")
        b.set_ylabel("average relative error (%)", color="tab:blue")
        b.grid(alpha=0.3)
        c = b.twinx()
        c.plot(sx, within, "s--", color="tab:green", label="true range inside [min, max] (%)")
        c.set_ylabel("true range inside [min, max] (%)", color="tab:green")
        c.set_ylim(-5, 105)
        if np.isfinite(rel).any():
            k = int(np.nanargmin(rel))
            b.annotate(f"oracle (with truth) {sx[k]:g}: {rel[k]:.1f} %", (sx[k], rel[k]), textcoords="offset points",
                       xytext=(5, 8), fontsize=8)
        b.set_xlabel("binary threshold")
    else:
        a.set_xlabel("binary threshold")
    return save_figure(fig, path, dpi=dpi)


def hil_prox_figure(data: dict, path: str | Path, title: str = "") -> Path:
    """:func:`threshold_sweep_figure` of a ``hil_prox`` run from its query results: ``data["cases"]`` (one row per
    image: ``case_id``, ``image``, ``error``, ``truth_range_m``; warehouse/sql/hil_prox_case_rows.sql),
    ``data["rows"]`` (image x threshold: ``case_id``, ``threshold``, ``range_m``, ``range_min_m``,
    ``range_max_m``; hil_prox_rows.sql) and ``data["sweep"]`` (hil_prox_sweep.sql).  Images that could not be
    read are left out."""
    th = np.array(sorted({r["threshold"] for r in data["rows"] if r["threshold"] is not None}))
    good = [c for c in data["cases"] if not c["error"]]
    by_case: dict = {}
    for r in data["rows"]:
        by_case.setdefault(r["case_id"], []).append(r)
    idx = {t: i for i, t in enumerate(th)}
    est, lo, hi = (np.full((len(good), len(th)), np.nan) for _ in range(3))
    for i, c in enumerate(good):
        for row in by_case.get(c["case_id"], []):
            j = idx[row["threshold"]]
            for arr, key in ((est, "range_m"), (lo, "range_min_m"), (hi, "range_max_m")):
                arr[i, j] = np.nan if row[key] is None else row[key]
    truth = np.array([np.nan if c["truth_range_m"] is None else c["truth_range_m"] for c in good])
    return threshold_sweep_figure(path, th, est, lo, hi, truth, labels=[c["image"] for c in good],
                                  sweep=data["sweep"], title=title)
