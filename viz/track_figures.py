"""Figures of star-tracking runs (issue 22, point 5), drawn from query results over ``star_frames``: the error per
axis against time of a few sequences with the tracker's mode shaded behind it, and availability and latency by
mode.  Never calls back into ``jobs``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.viz.figures import pyplot, save_figure

__all__ = ["MODE_COLOURS", "mode_spans", "error_vs_time_fig", "error_vs_time_figure", "availability_latency_fig",
           "availability_latency_figure"]

MODE_COLOURS = {"tracking": "#cfe8cf", "lost_in_space": "#fde2b8", "none": "#f4c7c3"}
"""Background of each mode (``nav.sequence.MODE_NAMES``): tracking green, lost-in-space orange, no fix red."""
_AXES = (("x", "tab:red"), ("y", "tab:green"), ("z", "tab:blue"))


def mode_spans(t: np.ndarray, mode: np.ndarray) -> list[tuple[float, float, str]]:
    """Runs of equal mode as (start, end, mode) time spans: frame k covers [t_k - dt/2, t_k + dt/2) with dt the
    frame interval (the median step; 1 for a single frame).  t : (T,) s, increasing; mode : (T,) str."""
    t = np.asarray(t, dtype=np.float64)
    mode = np.asarray(mode, dtype=object)
    if t.size == 0:
        return []
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    cut = np.flatnonzero(mode[1:] != mode[:-1]) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [t.size]])
    return [(float(t[a] - dt / 2), float(t[b - 1] + dt / 2), str(mode[a])) for a, b in zip(starts, ends)]


def error_vs_time_fig(sequences: list[dict], limit_arcsec: float | None = None):
    """Error per axis against time, one panel per sequence, the mode shaded (:data:`MODE_COLOURS`); the open figure.

    sequences : [{"case_id": int, "title": str, "t_s": (T,) s, "mode": (T,) str, "err_x_arcsec", "err_y_arcsec",
    "err_z_arcsec": (T,) arcsec, NaN without an attitude}] (the rows of ``star_frames``; errors per axis by the
    reference's Eqs. 4-7, ``nav/errors.py``).  limit_arcsec : the campaign's error limit, drawn as dashed lines.
    The y axis is symmetric-log (linear within +-1 arcsec), so a lost-in-space fix and a tracked one both show."""
    plt = pyplot()
    n = max(len(sequences), 1)
    fig, axs = plt.subplots(n, 1, figsize=(11, 2.3 * n + 0.6), sharex=False, squeeze=False, constrained_layout=True)
    for ax, s in zip(axs[:, 0], sequences):
        for a, b, m in mode_spans(s["t_s"], s["mode"]):
            ax.axvspan(a, b, color=MODE_COLOURS.get(m, "#dddddd"), lw=0)
        for k, c in _AXES:
            ax.plot(s["t_s"], s[f"err_{k}_arcsec"], ".-", ms=3, lw=0.8, color=c, label=k)
        if limit_arcsec:
            for v in (-limit_arcsec, limit_arcsec):
                ax.axhline(v, color="0.4", ls="--", lw=0.7)
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_ylabel("error (arcsec)")
        ax.set_title(s["title"], fontsize=9, loc="left")
    axs[-1, 0].set_xlabel("time (s)")
    if sequences:
        handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in MODE_COLOURS.values()]
        lines = axs[0, 0].get_legend_handles_labels()[0]
        axs[0, 0].legend(lines + handles, ["x", "y", "z"] + [m.replace("_", " ") for m in MODE_COLOURS],
                         ncol=6, fontsize=8, loc="upper right")
    return fig


def error_vs_time_figure(sequences: list[dict], path: Path, limit_arcsec: float | None = None) -> Path:
    """:func:`error_vs_time_fig` as the PNG ``path``."""
    return save_figure(error_vs_time_fig(sequences, limit_arcsec), path)


def availability_latency_fig(per_frame: dict, modes: list[dict]):
    """Left: availability (share of the sequences valid and within the limit) at each frame against time.  Right:
    the tracker's latency per frame by mode (mean and 99th percentile, ms, log scale) with its stages (predict,
    match + solve + verify, lost-in-space) and the rendering + detection beside it; the open figure.

    per_frame : {"t_s": (T,) s, "availability": (T,) 0..1} (``star_track_error_vs_time``).
    modes : rows of ``star_track_modes`` (mode, frames, ms_per_frame, p99_ms_per_frame, predict_ms, track_ms,
    lost_in_space_ms, render_detect_ms; None where a stage did not run)."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    a.plot(per_frame["t_s"], 100.0 * np.asarray(per_frame["availability"], dtype=np.float64), ".-", color="tab:blue")
    a.set_ylim(-2, 102)
    a.set_xlabel("time (s)")
    a.set_ylabel("sequences available (%)")
    a.set_title("Availability at each frame (all sequences)", fontsize=10)
    keys = (("ms_per_frame", "tracker, mean"), ("p99_ms_per_frame", "tracker, 99th pct"), ("predict_ms", "predict"),
            ("track_ms", "match+solve+verify"), ("lost_in_space_ms", "lost in space"),
            ("render_detect_ms", "render+detect"))
    x = np.arange(len(modes))
    w = 0.8 / len(keys)
    for i, (k, lab) in enumerate(keys):
        v = np.array([np.nan if m.get(k) is None else float(m[k]) for m in modes])
        b.bar(x + (i - (len(keys) - 1) / 2) * w, np.where(v > 0, v, np.nan), w, label=lab)
    b.set_xticks(x, [f"{m['mode'].replace('_', ' ')}\n({m['frames']} frames)" for m in modes])
    b.set_yscale("log")
    b.set_ylabel("ms per frame")
    b.set_title("Latency per frame by mode", fontsize=10)
    b.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.2))     # below: never on a bar
    return fig


def availability_latency_figure(per_frame: dict, modes: list[dict], path: Path) -> Path:
    """:func:`availability_latency_fig` as the PNG ``path``."""
    return save_figure(availability_latency_fig(per_frame, modes), path)
