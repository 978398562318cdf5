"""What ``dualsight nightly`` and ``dualsight nightly history`` print: one line per verdict (a job whose metrics
are all identical shares one line), the trend table of the last nights, and the JSON-safe form of a night's
summary.  Input: verdict rows as jobs/nightly/compare.py makes them and jobs/nightly/store.py keeps them.
"""

from __future__ import annotations

import math

__all__ = ["short_verdict", "verdict_line", "verdicts_text", "history_text", "json_safe"]


def short_verdict(r: dict) -> str:
    """``<job> <comparison> <metric> <verdict>`` (the night's message names its red verdicts so)."""
    return f"{r['job']} {r['comparison']} {r['metric']} {r['verdict']}"


def _num(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}" if v == v else "nan"
    return str(v)


def verdict_line(r: dict) -> str:
    """One line per verdict: job, comparison, metric, baseline -> now, the test and its p-value or threshold."""
    if r["verdict"] in ("skipped", "failed"):
        return f"{r['job']:<22} {r['verdict']}: {r.get('note', '')}"
    if r.get("alpha") is not None and r.get("threshold") is not None:
        thr = f"p={r['threshold']:.2g} (alpha {r['alpha']:.2g})"
    elif r.get("threshold") is not None:
        thr = f"threshold {_num(r['threshold'])}"
    else:
        thr = ""
    note = f"  [{r['note']}]" if r.get("note") else ""
    return (f"{r['job']:<22} {r['comparison']:<10} {r['metric']:<30} {_num(r.get('baseline')):>10} -> "
            f"{_num(r.get('now')):<10} {r['verdict']:<14} {r.get('test') or ''} {thr}{note}")


def verdicts_text(rows: list[dict]) -> str:
    """Every verdict line, except that a job's metrics that are all "identical" share one line."""
    out = []
    for r in rows:
        if r["verdict"] == "identical" and r["metric"] != "rows":
            continue
        if r["metric"] == "rows" and r["verdict"] == "identical":
            n = sum(1 for x in rows if x["job"] == r["job"] and x["comparison"] == "fixed"
                    and x["verdict"] == "identical" and x["metric"] != "rows")
            out.append(f"{r['job']:<22} {'fixed':<10} {n} metrics identical: {int(r['now']):,} rows equal to the "
                       f"baseline's ({r['test']}, {int(r['threshold'] or 0)} differ)")
            continue
        out.append(verdict_line(dict(r, note=r["note"] if not str(r.get("note", "")).startswith("fresh seed")
                                      else r["note"].partition("; ")[2])))
    return "\n".join(out)


def history_text(trends: list[dict], nights: list[dict], last_n: int = 8) -> str:
    """The last ``last_n`` nights (exit, counts of verdicts) and every metric's values over them, oldest first."""
    lines = [f"{len(nights)} night(s); the last {min(len(nights), last_n)}:"]
    lines += [f"  {n['night']}: exit {n.get('exit', '?')}{' (accepted)' if n.get('accepted') else ''}, "
              f"{n['regressions']} regressions, {n['not_comparable']} not comparable / no baseline / failed, "
              f"{n['identical']} identical, {n['ok']} ok, {n['improved']} improved" for n in nights[-last_n:]]
    lines.append(f"{'job':<22} {'comparison':<10} {'metric':<30} values, oldest -> newest (last {last_n})  "
                 "last verdict")
    for t in trends:
        pts = t["points"][-last_n:]
        vals = " ".join(f"{_num(p['now']):>9}" for p in pts)
        lines.append(f"{t['job']:<22} {t['comparison']:<10} {t['metric']:<30} {vals}  {pts[-1]['verdict']}")
    return "\n".join(lines)


def json_safe(v):
    """``v`` with every NaN and infinity (in nested dicts, lists and tuples) replaced by None."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [json_safe(x) for x in v]
    return v
