"""Figures of star-tracker runs: the reference's Figures 9 and 10 (mean error per axis and RSS error against the
number of stars observed), drawn from the star report's query results.  Never calls back into ``jobs``.
"""

from __future__ import annotations

from pathlib import Path

from dualsight.viz.figures import pyplot, save_figure

__all__ = ["error_vs_observed_figure"]


def error_vs_observed_figure(report: dict, path: Path) -> Path:
    """Figures 9 and 10 of the reference as one PNG ``path``.

    ``report``: the star report's JSON object (``run``, ``cases`` and ``error_vs_stars_observed``: rows of
    ``stars_observed``, ``cases``, ``mean_err_{x,y,z}_arcsec`` and ``mean_rss_arcsec``, warehouse/sql's
    ``star_error_vs_observed``)."""
    plt = pyplot()
    rows = report["error_vs_stars_observed"]
    n = [r["stars_observed"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for key, label in (("mean_err_x_arcsec", "x"), ("mean_err_y_arcsec", "y"), ("mean_err_z_arcsec", "z")):
        a.plot(n, [r[key] for r in rows], "o-", label=label)
    a.set_xlabel("stars observed")
    a.set_ylabel("mean |error| (arcsec)")
    a.set_title("Error per axis vs stars observed (cf. Fig. 9)")
    a.legend()
    b.bar(n, [r["mean_rss_arcsec"] for r in rows], color="tab:gray")
    for x, r in zip(n, rows):
        b.annotate(str(r["cases"]), (x, r["mean_rss_arcsec"]), ha="center", va="bottom", fontsize=7)
    b.set_xlabel("stars observed (label: cases)")
    b.set_ylabel("mean RSS error (arcsec)")
    b.set_title("RSS error vs stars observed (cf. Fig. 10)")
    fig.suptitle(f"run {report['run']}: {report['cases']} cases")
    return save_figure(fig, path)
