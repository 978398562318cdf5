"""``dualsight replay`` of several star-tracking sequences into one ``.rrd`` (issue 22, point 5): each sequence gets
its own stretch of the ``frame`` time line (sequence i's frame k at i * frames + k), so no two sequences' frames
collide; sequences with a bright object crossing the field and a refined focal length replay too (their frames
re-rendered with the same objects and camera, their windows rebuilt with the refined focal length).

Independent truth: the lake's rows read with pyarrow; the recording read back with rerun's own reader
(tests/test_replay.py's ``read_rrd``)."""

from __future__ import annotations

import numpy as np
import pyarrow.dataset as pads
import pytest

from dualsight.jobs.cli.main import main
from test_replay import read_rrd

FRAMES = 10
TOML = f"""
[sequence]
frames = {FRAMES}
rate_max_deg_s = 0.5
blinded = 1
dropped = 1
bright_crossings = 1
crossing_frames = 4
true_focal_error = 0.0003
refine_focal = true
"""


@pytest.fixture(scope="module")
def lake(make_lake, tmp_path_factory):
    cfg = tmp_path_factory.mktemp("cfg") / "track.toml"
    cfg.write_text(TOML)
    return make_lake("trackmany", ["star", "track", "--preset", "paper", "--config", str(cfg), "--cases", "3",
                                   "--seed", "12", "--run", "m"])


def test_three_sequences_in_one_recording_do_not_collide(lake, tmp_path):
    out = tmp_path / "all.rrd"
    assert main(["replay", "--lake", str(lake), "--run", "m", "--where", "case_id >= 0", "-o", str(out)]) == 0
    rec = read_rrd(out)
    t = pads.dataset(f"{lake}/star_frames/run=m", format="parquet").to_table().sort_by([("case_id", "ascending"),
                                                                                        ("frame", "ascending")])
    case, frame = np.array(t.column("case_id").to_pylist()), np.array(t.column("frame").to_pylist())
    mode, event = t.column("mode").to_pylist(), t.column("event").to_pylist()
    assert sorted(set(case.tolist())) == [0, 1, 2] and "crossing" in event
    assert t.column("focal_px").null_count < t.num_rows                 # the focal length was refined
    texts = {r["frame"]: v[0] for r in rec["/mode"] for k, v in r.items() if k.endswith("TextLog:text") and v}
    # one mode line per frame of every sequence, each at its own time: no two sequences share a frame number
    assert sorted(texts) == list(range(3 * FRAMES))
    for c, k, m, e in zip(case, frame, mode, event):
        assert texts[int(c) * FRAMES + int(k)].startswith(f"frame {k}: {m} ("), (c, k)
        assert f"event {e})" in texts[int(c) * FRAMES + int(k)]
    images = [r["frame"] for r in rec["/camera/image"] for k, v in r.items() if k.endswith("Image:buffer") and v]
    delivered = case[np.array(event) != "dropped"] * FRAMES + frame[np.array(event) != "dropped"]
    assert sorted(images) == sorted(delivered.tolist())
