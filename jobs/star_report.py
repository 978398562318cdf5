"""The star-tracker report: every number comes out of the SQL files in ``warehouse/sql``."""

from __future__ import annotations

from pathlib import Path

from dualsight.errors import InputError
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import connect, format_table, run_report

REFERENCE = {"success_rate": 191 / 200, "confident_wrong_rate": 2 / 200, "mean_stars_generated": 11.4607,
             "mean_stars_observed": 10.1152, "mean_T": 8.6230,
             "mean_error_arcsec": {"x": 10.6237, "y": 7.7998, "z": 6.4789}}


def build(lake: Lake, run_id: str) -> dict:
    """Run the star report queries for ``run_id``; returns tables and the JSON summary."""
    if "star_cases" not in lake.datasets():
        raise InputError(f"no star_cases dataset in {lake.root}", source="--lake")
    con = connect(lake)
    cols, rows = run_report(con, "star_summary", run=run_id)
    s = dict(zip(cols, rows[0]))
    if not s["cases"]:
        raise InputError(f"run {run_id!r} has no star cases in {lake.root}", source="--run")
    tables = {name: run_report(con, name, run=run_id)
              for name in ("star_table5", "star_error_vs_observed", "star_status", "star_stage_times",
                           "star_robust")}
    js = {
        "run": run_id,
        "cases": int(s["cases"]),
        "success_rate": s["success_rate"],
        "confident_wrong_rate": s["confident_wrong_rate"],
        "no_solution_rate": s["no_solution_rate"],
        "identification_rate": s["identification_rate"],
        "robust": {"success_rate": s["robust_success_rate"],
                   "confident_wrong_rate": s["robust_confident_wrong_rate"],
                   "no_solution_rate": s["robust_no_solution_rate"],
                   "identification_rate": s["robust_identification_rate"]},
        "mean_stars_generated": s["mean_stars_generated"],
        "mean_stars_observed": s["mean_stars_observed"],
        "mean_T": s["mean_T"],
        "mean_error_arcsec": {"x": s["mean_err_x_arcsec"], "y": s["mean_err_y_arcsec"], "z": s["mean_err_z_arcsec"]},
        "mean_stars_generated_all_cases": s["mean_stars_generated_all"],
        "sky_share_ge3_stars": s["sky_share_ge3_stars"],
        "sky_share_ge4_stars": s["sky_share_ge4_stars"],
        "mean_ms_per_case": s["mean_ms_per_case"],
        "error_vs_stars_observed": [dict(zip(tables["star_error_vs_observed"][0], r))
                                    for r in tables["star_error_vs_observed"][1]],
        "reference": REFERENCE,
    }
    return {"summary": s, "tables": tables, "json": js}


def _pct(x):
    return "-" if x is None else f"{100 * x:.2f} %"


def text(rep: dict) -> str:
    j = rep["json"]
    ref = REFERENCE
    lines = [
        f"star-tracker run {j['run']}: {j['cases']} cases",
        "",
        "reliability                        dualsight      reference",
        f"  success (all axes <= 100 arcsec)  {_pct(j['success_rate']):>10}   {_pct(ref['success_rate']):>10}",
        f"  confident but wrong (T > 0)       {_pct(j['confident_wrong_rate']):>10}   "
        f"{_pct(ref['confident_wrong_rate']):>10}",
        f"  no confident solution (T <= 0)    {_pct(j['no_solution_rate']):>10}",
        f"  identification right (ids)        {_pct(j['identification_rate']):>10}",
        f"  sky limit: attitudes with >= 3 / >= 4 catalog stars in the field: "
        f"{_pct(j['sky_share_ge3_stars'])} / {_pct(j['sky_share_ge4_stars'])}",
        "",
        "Reference method beside dualsight's robust voting (unique maxima, consistent set, attitude check)",
        format_table(*rep["tables"]["star_robust"]),
        "",
        "Table 5 (averages over the successful cases)",
        format_table(*rep["tables"]["star_table5"]),
        "",
        "Error vs stars observed (Figures 9-10), successful cases",
        format_table(*rep["tables"]["star_error_vs_observed"], floatfmt="{:.2f}"),
        "",
        "Outcomes",
        format_table(*rep["tables"]["star_status"], floatfmt="{:.2f}"),
        "",
        "Time per case by stage",
        format_table(*rep["tables"]["star_stage_times"], floatfmt="{:.3f}"),
    ]
    return "\n".join(lines)


def plot(rep: dict, path: Path) -> Path:
    """Figures 9 and 10 of the reference: mean error per axis and RSS against stars observed."""
    from dualsight.viz.prox_figures import _plt, save_figure

    plt = _plt()
    rows = rep["json"]["error_vs_stars_observed"]
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
    fig.suptitle(f"run {rep['json']['run']}: {rep['json']['cases']} cases")
    return save_figure(fig, path)
