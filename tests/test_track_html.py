"""The star-tracking section of the HTML report (issue 22, point 5): ``dualsight report --run <star_track run>
--html``, checked on the page's HTML (stdlib html.parser, tests/test_html_pages.py's ``Page``).

Independent truth: the ``star_frames`` rows read with pyarrow (not DuckDB, not the report's SQL) and counted with
numpy: availability over all frames and over the normal ones, frames per mode, frames per (event, lock reason,
mode), the least available sequences.  The figures are PNGs that decode, one panel per drawn sequence.
"""

from __future__ import annotations

import base64
import shlex

import cv2
import numpy as np
import pyarrow.dataset as pads
import pytest

from dualsight.jobs.cli.main import main
from dualsight.warehouse.cells import percent
from test_html_pages import RAW_FLOAT, Page

TOML = """
[sequence]
frames = 20
motion = "mixed"
rate_max_deg_s = 1.0
blinded = 1
dropped = 1
blank = 1
error_limit_arcsec = 3.0
"""
"""Events (so that normal frames differ from all frames) and a tight error limit (so that some valid attitudes are
false locks, and availability differs from the share of valid attitudes)."""
SECTIONS = ("Star tracking: targets (issue 22, point 6)", "Star tracking: campaign",
            "Star tracking: error and latency per mode", "Star tracking: lock reasons by frame event")


@pytest.fixture(scope="module")
def page(make_lake, tmp_path_factory):
    cfg = tmp_path_factory.mktemp("cfg") / "track.toml"
    cfg.write_text(TOML)
    root = make_lake("trackhtml", ["star", "track", "--preset", "paper", "--config", str(cfg), "--cases", "6",
                                   "--seed", "3", "--run", "tr"])
    out = root / "tr.html"
    assert main(["report", "--lake", str(root), "--run", "tr", "--html", str(out)]) == 0
    p = Page()
    text = out.read_text()
    p.feed(text)
    t = pads.dataset(f"{root}/star_frames/run=tr", format="parquet").to_table()
    f = {c: t.column(c).to_numpy(zero_copy_only=False) for c in ("case_id", "frame", "event", "mode", "lock_reason",
                                                                   "within_limit")}
    return root, p, text, f


def _table(p, sec) -> dict[str, list[str]]:
    (t,) = p.sections[sec]
    return {r[0]: r[1:] for r in t[1:]}


def test_availability_is_the_share_of_frame_rows_within_the_limit(page):
    _, p, _, f = page
    within = f["within_limit"].astype(bool)
    normal = f["event"] == "normal"
    valid = f["mode"] != "none"
    assert 0 < normal.sum() < len(within)              # events make the two availabilities different numbers
    assert np.sum(valid & ~within) > 0                 # a 3 arcsec limit: some valid attitudes are false locks
    camp = _table(p, "Star tracking: campaign")
    assert camp["availability, all frames"] == [percent(np.mean(within))]
    assert camp["availability, normal frames"] == [percent(np.mean(within[normal]))]
    assert camp["sequences"] == [str(len(np.unique(f["case_id"])))]
    tgt = _table(p, "Star tracking: targets (issue 22, point 6)")
    assert tgt["availability, normal frames (no blank/blinded/dropped)"][0] == percent(np.mean(within[normal]))
    assert tgt["availability (valid, within the limit), all frames"][0] == percent(np.mean(within))


def test_frames_per_mode_and_per_lock_reason(page):
    _, p, _, f = page
    modes = _table(p, "Star tracking: error and latency per mode")
    want = {m: int(np.sum(f["mode"] == m)) for m in np.unique(f["mode"])}
    assert {m: int(v[0]) for m, v in modes.items()} == want
    (t,) = p.sections["Star tracking: lock reasons by frame event"]
    got = {tuple(r[:3]): int(r[3]) for r in t[1:]}
    keys = list(zip(f["event"], f["lock_reason"], f["mode"]))
    assert got == {k: keys.count(k) for k in set(keys)}


def test_no_raw_float_and_figures_decode(page):
    root, p, text, f = page
    for sec in SECTIONS:
        for t in p.sections[sec]:
            for r in t:
                for c in r:
                    assert not RAW_FLOAT.search(c), (sec, r)
    by_id = {}
    for fg in p.figures:
        src = fg["src"]
        img = cv2.imdecode(np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[0] > 100 and img.std() > 5, fg["caption"]
        by_id[fg["section"]] = (fg, img)
    fg, img = by_id["Star tracking: error per axis against time"]
    n_seq = len(np.unique(f["case_id"]))
    assert f"of the {min(4, n_seq)} least available sequences" in fg["caption"]
    assert img.shape[0] > img.shape[1] * 0.6           # one panel per sequence, stacked
    assert "Star tracking: availability and latency by mode" in by_id
    lake = shlex.quote(str(root.resolve()))
    assert f"dualsight replay --lake {lake} --run tr --case N -o seqN.rrd" in text.replace("&#x27;", "'")
