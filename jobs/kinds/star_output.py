"""Whether a star run keeps its per-star detail (``star_detections``), and how readers learn it (issue 24, point 5).

The spec's ``[output]`` table (``jobs/kinds/star.py`` ``OutputConfig``): ``detections = "auto" | "on" | "off"``,
``detections_max_cases = 100000``; the command line's ``dualsight star run --detections`` overrides the first.
"auto" is resolved against the run's case count when the spec is resolved (:func:`with_case_count`); a run that
drops the detections stores ``output = {detections = "off"}`` in its canonical spec (so in its spec hash and its
default id: a resume never mixes shards with and without them) and leaves ``star_detections`` out of its manifest's
``datasets``.  Every report number but the blob breakdown comes from ``star_cases``; a replay recomputes a case's
detections from its row (``jobs/replay/cases.py``), kept or not.
"""

from __future__ import annotations

DATASET = "star_detections"


def with_case_count(d: dict, n_cases: int, detections: str | None = None) -> dict:
    """A copy of spec table ``d`` (TOML layout) whose ``cases`` is the run's ``n_cases`` (what ``[output] detections
    = "auto"`` is resolved against in ``star.spec_from_dict``) and whose ``output.detections`` is ``detections``
    when given (the command line's ``--detections``: "auto", "on" or "off", validated with the table).  A
    malformed ``output`` (not a table) is left for the validation to name."""
    out = dict(d, cases=int(n_cases))
    if detections is not None and (out.get("output") is None or isinstance(out.get("output"), dict)):
        out["output"] = dict(out.get("output") or {}, detections=detections)
    return out


def kept(manifest: dict) -> bool:
    """True when the star run of ``manifest`` stored its per-star detail (``star_detections`` among its datasets;
    runs made before the switch always did)."""
    return DATASET in (manifest.get("datasets") or [DATASET])


def not_kept_note(manifest: dict, what: str = "per-star numbers") -> str:
    """The one line a report prints where it needs per-star rows of a run that did not keep them."""
    rid = manifest.get("run_id", "?")
    return (f"{what}: not kept for run {rid} ({DATASET} off for {manifest.get('n_cases', '?'):,} cases); replay a "
            f"case (dualsight replay --run {rid} --case N) or rerun with --detections on")
