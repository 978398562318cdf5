"""An HTML report worth forwarding (issue 25, point 11), checked on the page's HTML (stdlib html.parser, no
browser): the subtitle, times as ISO UTC, no raw float in a table, every failure of the run (counted from the lake
rows with pyarrow) listed with a replay command that runs, the spec as a definition table holding every leaf of
the manifest's spec, crops whose marked detections are the lake's detection rows and whose sky is not black, and
Fig. 10 without overlapping labels.  The browser checks (page width, figures) are in tests/test_html_report.py."""

from __future__ import annotations

import base64
import datetime as dt
import json
import re
import shlex
from html.parser import HTMLParser

import numpy as np
import pyarrow.dataset as pads
import pytest

from dualsight.jobs.cli.main import main
from dualsight.warehouse.lake import Lake

RAW_FLOAT = re.compile(r"(?<![\w.])-?\d+\.\d{6,}(?![\w.])|\d(?:\.\d+)?e\+\d+")


class Page(HTMLParser):
    """Sections (h2 text -> list of tables, each a list of rows of cell texts), figures (attributes, caption,
    img src), the h1 and the subtitle paragraph."""

    def __init__(self):
        super().__init__()
        self.sections: dict[str, list] = {}
        self.figures: list[dict] = []
        self.texts: dict[str, str] = {}
        self._h2 = None
        self._tag = None
        self._buf = ""
        self._row = None
        self._cell = None
        self._fig = None
        self._first_p = True

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag in ("h1", "h2", "figcaption") or (tag == "p" and self._first_p):
            self._tag, self._buf = tag, ""
        elif tag == "table":
            self.sections.setdefault(self._h2, []).append([])
        elif tag == "tr":
            self._row = []
        elif tag in ("td", "th"):
            self._cell = ""
        elif tag == "figure":
            self._fig = {"attrs": a, "caption": "", "src": None, "section": self._h2}
        elif tag == "img" and self._fig is not None:
            self._fig["src"] = a.get("src")

    def handle_endtag(self, tag):
        if tag == self._tag:
            if tag == "h2":
                self._h2 = self._buf.strip()
            elif tag == "figcaption" and self._fig is not None:
                self._fig["caption"] = self._buf.strip()
            elif tag in ("h1", "p"):
                self.texts[tag] = self._buf.strip()
                self._first_p = self._first_p and tag != "p"
            self._tag = None
        elif tag in ("td", "th") and self._row is not None:
            self._row.append(self._cell)
            self._cell = None
        elif tag == "tr" and self._row is not None:
            self.sections[self._h2][-1].append(self._row)
            self._row = None
        elif tag == "figure" and self._fig is not None:
            self.figures.append(self._fig)
            self._fig = None

    def handle_data(self, data):
        if self._tag:
            self._buf += data
        if self._cell is not None:
            self._cell += data


def rows(root, ds: str, run: str) -> dict[str, np.ndarray]:
    t = pads.dataset(f"{root}/{ds}/run={run}", format="parquet").to_table()
    return {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}


@pytest.fixture(scope="module")
def page(make_lake, tmp_path_factory):
    """A 40-case star run with a shallow catalog (V <= 4.5: about a third of the attitudes fail) and its page."""
    cfg = tmp_path_factory.mktemp("cfg") / "faint.toml"
    cfg.write_text("[catalog]\nmag_limit = 4.5\n")
    root = make_lake("htmlpages", ["star", "run", "--config", str(cfg), "--cases", "40", "--seed", "2", "--run", "f"])
    out = root / "f.html"
    assert main(["report", "--lake", str(root), "--run", "f", "--html", str(out)]) == 0
    p = Page()
    text = out.read_text()
    p.feed(text)
    return root, p, text


def test_subtitle_and_times(page):
    root, p, text = page
    assert "lake lake" not in text
    assert p.texts["p"].endswith(f"read from the lake folder {root.resolve()}"), p.texts["p"]
    (ex,) = p.sections["Executions (timings)"]
    m = Lake(root).read_manifest("f")
    started = [e["started_unix"] for e in m["executions"]]
    want = [dt.datetime.fromtimestamp(s, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ") for s in started]
    assert [r[0] for r in ex[1:]] == want
    assert not re.search(r"\d\.\d+e\+\d", text.split("<h2>Spec</h2>")[0])     # no 1.796e+09 anywhere above


def test_no_table_cell_prints_a_raw_float(page):
    _, p, _ = page
    for sec, tables in p.sections.items():
        if sec in ("Spec", "Versions"):          # the spec's numbers in full: they reproduce the run
            continue
        for t in tables:
            for r in t:
                for c in r:
                    assert not RAW_FLOAT.search(c) or c.startswith("dualsight "), (sec, r)


def test_every_failure_is_listed_with_a_replay_command_that_runs(page, tmp_path):
    root, p, text = page
    c = rows(root, "star_cases", "f")
    failed = sorted(int(i) for i, s in zip(c["case_id"], c["status"]) if s != "success")
    assert len(failed) >= 5
    (t,) = p.sections["Every failure, with its replay command"]
    listed = [int(r[0]) for r in t[1:]]
    assert listed == failed
    lake = shlex.quote(str(root.resolve()))
    for r in t[1:]:
        assert r[-1] == f"dualsight star replay --lake {lake} --run f --case {r[0]} -o case{r[0]}.rrd"
    assert f"<h2>Worst cases: 6 of {len(failed)} failures drawn</h2>" in text
    argv = shlex.split(t[1][-1])[1:]
    argv[argv.index("-o") + 1] = str(tmp_path / "x.rrd")
    assert main(argv) == 0 and (tmp_path / "x.rrd").stat().st_size > 1000


def _flat(d, prefix=""):
    """Independent flattening of the manifest's spec: dotted keys of the leaves."""
    if isinstance(d, dict):
        return {k2: v2 for k, v in d.items() for k2, v2 in _flat(v, f"{prefix}{k}.").items()}
    if isinstance(d, list) and d and all(isinstance(x, dict) for x in d):
        return {k2: v2 for i, v in enumerate(d) for k2, v2 in _flat(v, f"{prefix}{i}.").items()}
    return {prefix[:-1]: d}


def test_spec_is_a_definition_table_of_its_leaves(page):
    root, p, text = page
    (t,) = p.sections["Spec"]
    got = {r[0]: r[1] for r in t[1:]}
    want = _flat(Lake(root).read_manifest("f")["spec"])
    assert set(got) == set(want) and len(want) > 40
    for k, v in want.items():
        g = got[k]
        if isinstance(v, bool):
            assert g == str(v).lower(), k
        elif v is None:
            assert g == "none", k
        elif isinstance(v, (int, float)):
            assert float(g) == float(v), k
        elif isinstance(v, list) and all(isinstance(x, (int, float)) for x in v):
            assert json.loads(g) == v, k
        else:
            assert g == str(v) or isinstance(v, list), k
    assert '"camera": {' not in text                       # no JSON dump


def test_crops_mark_the_lake_detections_on_a_stretched_frame(page):
    import cv2

    root, p, _ = page
    d = rows(root, "star_detections", "f")
    crops = [f for f in p.figures if "data-marks" in f["attrs"]]
    assert len(crops) == 6
    marked = 0
    for f in crops:
        case = int(re.match(r"case (\d+):", f["caption"]).group(1))
        mk = json.loads(f["attrs"]["data-marks"])
        sel = d["case_id"] == case
        x0, y0 = mk["box"][:2]
        sx, sy = mk["scale"]
        want = np.stack([(d["x_px"][sel] - x0) * sx, (d["y_px"][sel] - y0) * sy], 1)      # lake rows -> crop px
        got = np.asarray(mk["detections"], float).reshape(-1, 2)
        assert len(got) == len(want)
        marked += len(got) > 0
        assert np.allclose(np.sort(got, 0), np.sort(want, 0), atol=0.01), (case, got, want)
        png = base64.b64decode(f["src"].split(",", 1)[1])
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        w, h = mk["size"]
        frame = img[:h, :w]
        assert 25 <= np.median(frame) <= 90, np.median(frame)        # stretched: the sky is grey, not black
        for u, v in got:       # a circle is drawn around each detection: coloured pixels on its ring (radius 9)
            ring = [(int(round(u + 9 * np.cos(a))), int(round(v + 9 * np.sin(a)))) for a in np.linspace(0, 6.2, 24)]
            ring = [(x, y) for x, y in ring if 0 <= x < w and 0 <= y < h]
            px = np.array([frame[y, x] for x, y in ring], int)
            coloured = np.ptp(px, axis=1) > 60                        # far from grey
            assert coloured.mean() > 0.5, (case, u, v)
    assert marked >= 3


def test_fig10_labels_do_not_overlap():
    from dualsight.viz.figures import pyplot
    from dualsight.viz.star_figures import error_vs_observed_fig

    n = np.arange(3, 60)
    rep = {"run": "x", "cases": 100000, "error_vs_stars_observed": [
        {"stars_observed": int(k), "cases": int(1000 + 37 * k), "mean_err_x_arcsec": 1.0, "mean_err_y_arcsec": 1.0,
         "mean_err_z_arcsec": 5.0, "mean_rss_arcsec": 5.0 + (k % 3)} for k in n]}
    fig = error_vs_observed_fig(rep)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    texts = [fig._suptitle] if fig._suptitle is not None else []
    for ax in fig.axes:
        texts += [ax.title, ax.xaxis.label, ax.yaxis.label, *ax.texts]
        if ax.get_legend():
            texts += ax.get_legend().get_texts()
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            texts += [t.label1 for t in axis.get_major_ticks()            # the tick labels that are drawn
                      if lo - 1e-9 <= t.get_loc() <= hi + 1e-9 and t.label1.get_visible()]
    boxes = [(t.get_text(), t.get_window_extent(r)) for t in texts if t.get_visible() and t.get_text().strip()]
    assert len(boxes) > 20
    for i, (ta, a) in enumerate(boxes):
        for tb, b in boxes[i + 1:]:
            assert not a.overlaps(b), (ta, tb)
    pyplot().close(fig)


def test_flatten_matches_an_independent_flattening():
    from dualsight.viz.html_page import flatten

    spec = {"images": [{"path": "a.tiff", "bytes": 3}, {"path": "b.tiff", "bytes": 4}], "camera": {"fx": 1.5,
            "distortion": [0.0, 0.1]}, "seed": None, "robust": {"x": {"y": True}}}
    assert dict(flatten(spec)) == _flat(spec)
