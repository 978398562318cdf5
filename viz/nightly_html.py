"""The nightly's page: one self-contained HTML file (no network) with the night's verdict table, the nights'
summary and every metric's trend, drawn with matplotlib and embedded as a base64 PNG; the same figure is
saved as ``<page>.png`` beside the page.  Input: verdict rows as the nightly_verdicts dataset holds them
(jobs/nightly/store.py), never the jobs themselves.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

from dualsight.viz.figures import pyplot, save_figure

RED = ("REGRESSION", "not comparable", "no baseline", "failed")
COLOURS = {"identical": "#2e7d32", "ok": "#43a047", "improved": "#1e88e5", "info": "#9e9e9e",
           "skipped": "#9e9e9e", "changed": "#fb8c00"}


def _colour(verdict: str) -> str:
    if verdict == "REGRESSION" or verdict == "failed":
        return "#d32f2f"
    if verdict in RED:                  # not comparable, no baseline: a suite or spec change to accept
        return "#8e24aa"
    return COLOURS.get(verdict, "#616161")


def trend_figure(rows: list[dict], path: Path, max_panels: int = 120):
    """Small multiples: per (job, metric) the fixed-seed and fresh-seed values over the nights, the baseline
    as a grey step line, each point coloured by its verdict (red: regression / not comparable)."""
    plt = pyplot()
    nights = sorted({r["night"] for r in rows})
    xi = {n: i for i, n in enumerate(nights)}
    panels: dict = {}
    for r in rows:
        if r["comparison"] not in ("fixed", "fresh", "throughput") or r["metric"] in ("-", "rows"):
            continue
        panels.setdefault((r["job"], r["metric"]), []).append(r)
    keys = sorted(panels)[:max_panels]
    ncol = 4                    # 4 panels across: readable at the page's width (1200 px)
    nrow = max(1, math.ceil(len(keys) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.4 * ncol, 2.3 * nrow + 0.8), squeeze=False)
    for ax in axes.ravel()[len(keys):]:
        ax.axis("off")
    for ax, key in zip(axes.ravel(), keys):
        pts = panels[key]
        for comp, style in (("fixed", "-o"), ("throughput", "-o"), ("fresh", "--s")):
            p = sorted((r for r in pts if r["comparison"] == comp and r["now"] is not None), key=lambda r: r["night"])
            if not p:
                continue
            x = [xi[r["night"]] for r in p]
            ax.plot(x, [r["now"] for r in p], style, color="#455a64", lw=1, ms=0, label=comp)
            ax.scatter(x, [r["now"] for r in p], c=[_colour(r["verdict"]) for r in p], s=22, zorder=3,
                       marker="o" if comp != "fresh" else "s")
            if comp != "fresh":                 # the accepted baseline's value at each night: grey bars
                b = [(xi[r["night"]], r["baseline"]) for r in p if r["baseline"] is not None]
                if b:
                    ax.plot([v[0] for v in b], [v[1] for v in b], "_", color="#9e9e9e", ms=16, mew=3, zorder=1)
        ys = [r[k] for r in pts for k in ("now", "baseline") if r.get(k) is not None and r[k] == r[k]]
        if ys and max(ys) - min(ys) <= 1e-9 * max(1.0, abs(max(ys))):     # constant: no offset notation
            c = ys[0]
            ax.set_ylim(c - 0.05 * (abs(c) or 1.0), c + 0.05 * (abs(c) or 1.0))
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_title(f"{key[0]}\n{key[1]}", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_xticks(range(len(nights)))
        ax.set_xticklabels([night_label(n, short=True) for n in nights], fontsize=6.5)
        ax.grid(alpha=0.3)
    fig.suptitle("dualsight nightly: metric per night (circles: fixed seeds, squares: fresh seeds, grey bars: "
                 "baseline;\ngreen identical/ok, blue improved, red regression, purple not comparable / no baseline, "
                 "grey info)", fontsize=10, y=1 - 0.08 / (2.3 * nrow + 0.8), va="top")
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.45 / (2.3 * nrow + 0.8)))
    save_figure(fig, path, dpi=90)


def night_label(night: str, short: bool = False) -> str:
    """A night id (``20261127T123449Z``) as ISO 8601 UTC (``2026-11-27 12:34:49 UTC``; ``short``: ``11-27\n12:34:49``);
    anything else unchanged."""
    n = str(night)
    if len(n) != 16 or n[8] != "T" or not n.endswith("Z") or not (n[:8] + n[9:15]).isdigit():
        return n
    if short:
        return f"{n[4:6]}-{n[6:8]}\n{n[9:11]}:{n[11:13]}:{n[13:15]}"
    return f"{n[:4]}-{n[4:6]}-{n[6:8]} {n[9:11]}:{n[11:13]}:{n[13:15]} UTC"


def _cell(v, col: str = "") -> str:
    if col == "night":
        return html.escape(night_label(v))
    if v is None:
        return "-"
    if isinstance(v, float):
        return "nan" if v != v else f"{v:.4g}"
    return html.escape(str(v))


def write_page(path: Path, night_rows: list[dict], all_rows: list[dict], nights: list[dict], title: str,
               outcome: tuple[int, str] | None = None) -> Path:
    """Write the HTML page and ``<page>.png`` (the trend figure); returns the PNG's path.  ``outcome``: the
    night's exit status and message, when known (an accepted first night is green though it has no baseline)."""
    path = Path(path)
    png = path.with_suffix(".png")
    trend_figure(all_rows, png)
    data = base64.b64encode(png.read_bytes()).decode("ascii")
    night = night_rows[0]["night"] if night_rows else "-"
    red = [r for r in night_rows if r["verdict"] in RED]
    code = outcome[0] if outcome else (1 if red else 0)
    status = {0: "GREEN", 1: "RED", 2: "COULD NOT RUN"}.get(code, str(code))
    message = html.escape(outcome[1]) if outcome else ""
    order = sorted(night_rows, key=lambda r: (r["verdict"] not in RED, r["job"], r["comparison"], r["metric"]))
    cols = ("job", "comparison", "metric", "baseline", "now", "test", "threshold_or_p", "alpha", "verdict", "note")
    trs = []
    for r in order:
        tds = "".join(f"<td>{_cell(r.get(c))}</td>" for c in cols)
        trs.append(f'<tr style="background:{"#ffebee" if r["verdict"] in RED else "white"}">{tds}</tr>')
    ncols = ("night", "exit", "accepted", "verdicts", "regressions", "not_comparable", "identical", "ok", "improved")
    ntrs = "".join("<tr>" + "".join(f"<td>{_cell(n.get(c), c)}</td>" for c in ncols) + "</tr>" for n in nights)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em auto; max-width: 1240px; padding: 0 12px; }}
table {{ border-collapse: collapse; font-size: 12px; }}
td, th {{ border: 1px solid #ccc; padding: 2px 6px; text-align: left; overflow-wrap: anywhere; }}
th {{ background: #eceff1; }}
.status {{ font-size: 20px; font-weight: bold; color: {"#2e7d32" if code == 0 else "#d32f2f"}; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<p class="status">night {html.escape(night_label(night))}: {status} ({len(red)} red of {len(night_rows)} verdicts)</p>
<p>{message}</p>
<h2>Nights</h2>
<table><tr><th>night</th><th>exit (0 green, 1 red, 2 could not run)</th><th>accepted as baseline</th>
<th>verdicts</th><th>regressions</th><th>not comparable / no baseline / failed</th>
<th>identical</th><th>ok</th><th>improved</th></tr>{ntrs}</table>
<h2>Trends</h2>
<img alt="metric trends" src="data:image/png;base64,{data}" style="max-width:100%">
<h2>Verdicts of night {html.escape(night_label(night))}</h2>
<table><tr>{"".join(f"<th>{c}</th>" for c in cols)}</tr>
{"".join(trs)}
</table>
</body></html>
"""
    path.write_text(page, encoding="utf-8")
    return png
