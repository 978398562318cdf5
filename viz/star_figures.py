"""Figures of star-tracker runs: the reference's Figures 9 and 10 (mean error per axis and RSS error against the
number of stars observed), drawn from the star report's query results.  Never calls back into ``jobs``.
"""

from __future__ import annotations

from pathlib import Path

from dualsight.viz.figures import pyplot, save_figure

__all__ = ["error_vs_observed_fig", "error_vs_observed_figure"]


def error_vs_observed_fig(report: dict):
    """The matplotlib figure of :func:`error_vs_observed_figure` (open; the caller saves or closes it).

    Left: mean |error| per axis against stars observed (Fig. 9).  Right: mean RSS error per number of stars
    observed (Fig. 10) and, under it on the same x axis, the number of cases behind each bar as bars of their
    own (no count printed on the bars, which overlapped once the bars were narrower than their labels)."""
    plt = pyplot()
    rows = report["error_vs_stars_observed"]
    n = [r["stars_observed"] for r in rows]
    fig = plt.figure(figsize=(11, 4.6), constrained_layout=True)
    gs = fig.add_gridspec(2, 2, height_ratios=[3.0, 1.0])
    a = fig.add_subplot(gs[:, 0])
    b = fig.add_subplot(gs[0, 1])
    c = fig.add_subplot(gs[1, 1], sharex=b)
    for key, label in (("mean_err_x_arcsec", "x"), ("mean_err_y_arcsec", "y"), ("mean_err_z_arcsec", "z")):
        a.plot(n, [r[key] for r in rows], "o-", label=label)
    a.set_xlabel("stars observed")
    a.set_ylabel("mean |error| (arcsec)")
    a.set_title("Error per axis vs stars observed (cf. Fig. 9)")
    a.legend()
    b.bar(n, [r["mean_rss_arcsec"] for r in rows], color="tab:gray")
    b.set_ylabel("mean RSS error (arcsec)")
    b.set_title("RSS error vs stars observed (cf. Fig. 10)")
    b.tick_params(labelbottom=False)
    c.bar(n, [r["cases"] for r in rows], color="tab:blue")
    c.set_xlabel("stars observed")
    c.set_ylabel("cases")
    fig.suptitle(f"run {report['run']}: {report['cases']} cases")
    return fig


def error_vs_observed_figure(report: dict, path: Path) -> Path:
    """Figures 9 and 10 of the reference as one PNG ``path``.

    ``report``: the star report's JSON object (``run``, ``cases`` and ``error_vs_stars_observed``: rows of
    ``stars_observed``, ``cases``, ``mean_err_{x,y,z}_arcsec`` and ``mean_rss_arcsec``, warehouse/sql's
    ``star_error_vs_observed``)."""
    return save_figure(error_vs_observed_fig(report), path)
