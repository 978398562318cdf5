"""``dualsight replay`` of a star-tracking sequence (issue 22, point 5): every frame on rerun's ``frame`` time line,
read back with rerun's own reader (tests/test_replay.py's ``read_rrd``) and checked against the lake's rows read
with pyarrow: the image of every delivered frame, every detection, the mode, the errors as time series, and the
predicted match windows, whose centres must lie on the catalog stars projected with the *true* attitude (computed
here with the camera model, not by the tracker); a tampered stored metric or digest is refused with one line
naming the column."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute  # noqa: F401  (pa.compute)
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest

from dualsight.jobs.cli.main import main
from test_replay import column, read_rrd

TOML = """
[sequence]
frames = 16
motion = "constant"
rate_max_deg_s = 1.0
blinded = 1
dropped = 1
"""
CASE = 1


@pytest.fixture(scope="module")
def lake(make_lake, tmp_path_factory):
    cfg = tmp_path_factory.mktemp("cfg") / "track.toml"
    cfg.write_text(TOML)
    return make_lake("trackreplay", ["star", "track", "--preset", "paper", "--config", str(cfg), "--cases", "3",
                                     "--seed", "11", "--run", "r"])


def frame_rows(root: Path, case_id: int) -> dict[str, np.ndarray]:
    t = pads.dataset(f"{root}/star_frames/run=r", format="parquet").to_table()
    t = t.filter(pa.compute.equal(t.column("case_id"), case_id)).sort_by("frame")
    out = {c: np.array(t.column(c).to_pylist(), dtype=object) for c in t.column_names}
    out["A_true"] = np.array(t.column("A_true").to_pylist(), float).reshape(-1, 3, 3)
    return out


@pytest.fixture(scope="module")
def recording(lake, tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "seq.rrd"
    assert main(["replay", "--lake", str(lake), "--run", "r", "--case", str(CASE), "-o", str(out)]) == 0
    return out, read_rrd(out), frame_rows(lake, CASE)


def by_frame(rows: list[dict], suffix: str) -> dict[int, object]:
    return {r["frame"]: v for r in rows for k, v in r.items() if k.endswith(suffix) and v is not None}


def test_every_frame_is_on_the_time_line_with_its_row(recording):
    path, rec, f = recording
    assert path.read_bytes()[:4] == b"RRF2"
    T = len(f["frame"])
    delivered = f["event"] != "dropped"
    assert sorted(by_frame(rec["/camera/image"], "Image:buffer")) == list(np.flatnonzero(delivered))
    modes = by_frame(rec["/mode"], "TextLog:text")
    assert sorted(modes) == list(range(T))
    for k in range(T):
        assert modes[k][0].startswith(f"frame {k}: {f['mode'][k]} ({f['lock_reason'][k]}, event {f['event'][k]})")
    dets = by_frame(rec["/camera/image/detections"], "Points2D:positions")
    assert {k: len(v) for k, v in dets.items()} == {k: int(n) for k, n in enumerate(f["n_detections"]) if n}
    for a in "xyz":
        err = by_frame(rec[f"/metrics/err_{a}_arcsec"], "Scalars:scalars")
        want = {k: v for k, v in enumerate(f[f"err_{a}_arcsec"]) if v == v and v is not None}
        assert sorted(err) == sorted(want) and len(want) >= T - 3
        assert all(err[k][0] == pytest.approx(want[k], abs=1e-9) for k in want)


def true_pixels(A_true: np.ndarray) -> np.ndarray:
    """The catalog stars (V <= the paper preset's limit) projected with the true attitude by the pinhole model of
    the paper camera written out here: x = fx X/Z + cx, y = fy Y/Z + cy (no distortion in the paper preset)."""
    from dualsight.jobs.kinds import star_track

    spec = star_track.spec_from_dict(star_track.PRESETS["paper"])
    ctx = star_track.make_context(spec)
    cam = spec.star.camera
    v = ctx.catalog.unit @ np.asarray(A_true, float).reshape(3, 3).T
    v = v[v[:, 2] > 0]
    return np.stack([cam.fx * v[:, 0] / v[:, 2] + cam.cx, cam.fy * v[:, 1] / v[:, 2] + cam.cy], -1)


def test_predicted_windows_sit_on_the_true_stars(recording):
    _, rec, f = recording
    wins = by_frame(rec["/camera/image/windows"], "LineStrips2D:strips")
    ran = [k for k in range(len(f["frame"])) if f["n_predicted"][k] > 0]
    assert len(ran) >= 10 and sorted(wins) == ran
    for k in ran:
        strips = np.array([np.asarray(s, float) for s in wins[k]])              # (P, n + 1, 2)
        assert len(strips) == f["n_predicted"][k]
        centre = strips[:, :-1].mean(axis=1)
        radius = np.linalg.norm(strips[:, 0] - centre, axis=1)
        truth = true_pixels(f["A_true"][k])
        d = np.min(np.linalg.norm(centre[:, None] - truth[None], axis=-1), axis=1)
        inside = np.mean(d <= radius)
        assert inside >= 0.9, (k, f["mode"][k], inside, np.median(d), np.median(radius))


def _tamper_frame(root: Path, case_id: int, frame: int, name: str, value) -> None:
    """Rewrite one stored value of one star_frames row (and the journal's byte count, so the lake serves it)."""
    for fp in sorted((root / "star_frames" / "run=r").glob("*.parquet")):
        t = pq.read_table(fp)
        hit = np.flatnonzero((t.column("case_id").to_numpy() == case_id) & (t.column("frame").to_numpy() == frame))
        if not hit.size:
            continue
        col = t.column(name).to_pylist()
        col[int(hit[0])] = value
        i = t.schema.get_field_index(name)
        pq.write_table(t.set_column(i, t.schema.field(name), pa.array(col, t.schema.field(name).type)), fp)
        journal = root / "_manifests" / "r.shards.jsonl"
        lines = [json.loads(x) for x in journal.read_text().splitlines()]
        for e in lines:
            if e["case_start"] <= case_id < e["case_stop"]:
                e["bytes"]["star_frames"] = fp.stat().st_size
        journal.write_text("".join(json.dumps(e) + "\n" for e in lines))
        return
    raise AssertionError("frame not found")


@pytest.mark.parametrize("name,delta", [("err_y_arcsec", 1e-6), ("image_digest", 1), ("n_matched", 1)])
def test_a_tampered_frame_metric_is_refused_naming_it(lake, tmp_path, capsys, name, delta):
    root = tmp_path / "lake"
    shutil.copytree(lake, root)
    f = frame_rows(root, CASE)
    k = int(np.flatnonzero(f["mode"] == "tracking")[3])
    old = f[name][k]
    new = int(old) + delta if isinstance(delta, int) else float(old) + delta
    _tamper_frame(root, CASE, k, name, new)
    assert main(["replay", "--lake", str(root), "--run", "r", "--case", str(CASE), "-o", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert f"frame {k}: column {name} is {new!r} in the lake, {old!r} recomputed" in err
