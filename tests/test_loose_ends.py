"""Loose ends: replay outputs that cannot be written, unknown tables in camera files, bounded skip summaries of
``calibrate`` and ``hil star``, and a script that starts a run with workers outside ``if __name__ == "__main__":``.
Each test was seen failing with the old behaviour planted back."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from dualsight.jobs.cli.main import main
from dualsight.jobs.replay.cases import compare_rows
from dualsight.warehouse.query import run_sql

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------- 1. replay output paths
@pytest.fixture(scope="module")
def star_lake(make_lake):
    return make_lake("lake", ["star", "run", "--preset", "paper", "--cases", "4", "--seed", "3", "--run", "s"])


def _unwritable(tmp_path: Path) -> list[Path]:
    (tmp_path / "plain").write_text("a file")
    return [Path("/proc/x.rrd"), Path("/sys/x.rrd"), tmp_path / "plain" / "x.rrd"]


@pytest.mark.parametrize("command", [["star", "replay"], ["replay"]])
def test_replay_to_an_unwritable_path_is_one_line_naming_it(star_lake, tmp_path, capsys, command):
    for out in _unwritable(tmp_path):
        assert main([*command, "--lake", str(star_lake), "--run", "s", "--case", "0", "-o", str(out)]) == 2, out
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("dualsight: error: ") and "internal error" not in err
        assert str(out) in err or str(out.parent) in err
        assert not out.exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only folder")
def test_replay_into_a_read_only_folder_is_refused(star_lake, tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        for command in (["star", "replay"], ["replay"]):
            assert main([*command, "--lake", str(star_lake), "--run", "s", "--case", "0", "-o",
                         str(ro / "x.rrd")]) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and str(ro / "x.rrd") in err
    finally:
        ro.chmod(0o755)


def test_replay_to_a_pipe_or_device_is_refused_without_blocking(star_lake, tmp_path):
    fifo = tmp_path / "pipe.rrd"
    os.mkfifo(fifo)
    for out, command in ((fifo, ["star", "replay"]), (fifo, ["replay"]), (Path("/dev/null"), ["star", "replay"])):
        p = subprocess.run([sys.executable, "-m", "dualsight", *command, "--lake", str(star_lake), "--run", "s",
                            "--case", "0", "-o", str(out)], capture_output=True, text=True, timeout=60)
        assert p.returncode == 2, p.stderr
        assert p.stderr.count("\n") == 1 and str(out) in p.stderr and "not a regular file" in p.stderr


def test_replay_to_a_writable_path_still_records(star_lake, tmp_path, capsys):
    assert main(["star", "replay", "--lake", str(star_lake), "--run", "s", "--case", "1", "-o",
                 str(tmp_path / "one.rrd")]) == 0
    assert capsys.readouterr().out == f"recording: {tmp_path / 'one.rrd'}  (open with: rerun {tmp_path / 'one.rrd'})\n"
    assert main(["replay", "--lake", str(star_lake), "--run", "s", "--where", "case_id < 2", "-o",
                 str(tmp_path / "many")]) == 0
    assert sorted(p.name for p in (tmp_path / "many").iterdir()) == ["s-case0.rrd", "s-case1.rrd"]


# ------------------------------------------------------------------------------- 2. camera file tables
CAMERA_TEXT = (ROOT / "examples" / "cameras" / "paper_star.toml").read_text()


@pytest.mark.parametrize("extra, name, what", [("[bogus]\nx = 1\n", "bogus", "table"),
                                               ("[provenance]\ntool = 'x'\n", "provenance", "table"),
                                               ("[[views]]\nimage = 'a.png'\n", "views", "key")])
def test_an_unknown_table_of_a_camera_file_is_refused_with_the_allowed_names(tmp_path, capsys, extra, name, what):
    from dualsight.errors import ConfigError
    from dualsight.scene.camera import Camera

    f = tmp_path / "cam.toml"
    f.write_text(CAMERA_TEXT + "\n" + extra)
    with pytest.raises(ConfigError) as e:
        Camera.from_toml(f)
    assert str(e.value) == (f"{f} [{name}]: unknown {what}; a camera file holds only the tables calibration, camera, "
                            "distortion_fit, source")
    assert main(["hil", "star", str(tmp_path / "x.png"), "--camera", str(f), "--no-lake"]) == 2
    assert capsys.readouterr().err == f"dualsight: error: {e.value}\n"


def test_a_top_level_key_of_a_camera_file_is_refused(tmp_path):
    from dualsight.errors import ConfigError
    from dualsight.scene.camera import Camera

    f = tmp_path / "cam.toml"
    f.write_text("width = 1024\n" + CAMERA_TEXT)
    with pytest.raises(ConfigError, match=r"\[width\]: unknown key; a camera file holds only the tables"):
        Camera.from_toml(f)
    f.write_text(CAMERA_TEXT.replace("[camera]", "calibration = 3\n[camera]"))
    with pytest.raises(ConfigError, match=r"\[calibration\]: must be a table"):
        Camera.from_toml(f)


def test_every_camera_file_dualsight_writes_or_ships_is_read(tmp_path):
    from dualsight.errors import ConfigError
    from dualsight.scene.camera import Camera
    from dualsight.scene.camera_file import read_camera_toml, write_camera_toml

    files = sorted((ROOT / "examples" / "cameras").glob("*.toml"))
    assert len(files) >= 4
    for f in files:
        Camera.from_toml(f)
    cam = Camera.pinhole(1024, 768, 4.65e-6, 17e-3)
    calibrated = CAMERA_TEXT + "\n[calibration]\nrms_px = 0.2\n[[calibration.views]]\nimage = 'a.png'\n"
    (tmp_path / "cal.toml").write_text(calibrated)                            # the layout `calibrate` writes
    assert read_camera_toml(tmp_path / "cal.toml")[1]["rms_px"] == 0.2
    out = write_camera_toml(cam, tmp_path / "fit.toml", extra={"distortion_fit": {"stars_used": 600}})
    assert Camera.from_toml(out) == cam                                        # --fit-distortion's layout
    out = write_camera_toml(cam, tmp_path / "src.toml", extra={"source": {"images": "x"}})
    assert Camera.from_toml(out) == cam
    with pytest.raises(ConfigError, match=r"extra \[bogus\] is not a table a camera file may hold"):
        write_camera_toml(cam, tmp_path / "bad.toml", extra={"bogus": {"a": 1}})   # nothing a reader refuses
    assert not (tmp_path / "bad.toml").exists()


# ------------------------------------------------------------------------------- 4. an unguarded script with workers
SCRIPT = """import dualsight
rid = dualsight.run("star", "paper", cases=400, workers=2, lake={lake!r})
print(rid)
"""


def _star_rows(lake: Path, run_id: str) -> list[dict]:
    cols, rows = run_sql(lake, f"SELECT * EXCLUDE (run) FROM star_cases WHERE run = '{run_id}' ORDER BY case_id")
    return [{c: v for c, v in zip(cols, r) if not c.startswith("t_")} for r in rows]


def test_a_script_without_the_main_guard_runs_in_process_with_one_warning(tmp_path):
    plain = tmp_path / "plain.py"
    plain.write_text(SCRIPT.format(lake=str(tmp_path / "lake1")))
    guarded = tmp_path / "guarded.py"
    guarded.write_text("import dualsight\n\nif __name__ == \"__main__\":\n" + "".join(
        f"    {line}\n" for line in SCRIPT.format(lake=str(tmp_path / "lake2")).splitlines()[1:]))
    env = {k: v for k, v in os.environ.items() if k != "DUALSIGHT_LAKE"}
    p = subprocess.run([sys.executable, str(plain)], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                       env=env)
    assert p.returncode == 0, p.stderr
    assert p.stderr == (f"dualsight: warning: {plain} starts this run at import time, outside `if __name__ == "
                        "\"__main__\":`, where spawned workers would run the script again; the run goes on in this "
                        "process instead (same rows); put the call under `if __name__ == \"__main__\":` to use 2 "
                        "workers\n")
    run_id = p.stdout.strip()
    g = subprocess.run([sys.executable, str(guarded)], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                       env=env)
    assert g.returncode == 0 and "warning" not in g.stderr, g.stderr
    assert g.stdout.strip() == run_id
    rows, spawned = _star_rows(tmp_path / "lake1", run_id), _star_rows(tmp_path / "lake2", run_id)
    assert len(rows) == len(spawned) == 400
    assert all(compare_rows(a, b) == [] and a.keys() == b.keys() for a, b in zip(rows, spawned))   # NaN == NaN


# ------------------------------------------------------------------------------- 3. many bad images: bounded summaries
def _bad_images(folder: Path, n: int = 30) -> Path:
    folder.mkdir()
    for i in range(n):      # non-empty garbage: an empty file refuses the whole run at planning (scene/imageio.py)
        (folder / f"img{i:02d}.png").write_bytes(b"garbage %d" % i if i % 2 else os.urandom(64) + b"x")
    return folder


def _sql_rows(capsys, line: str) -> list:
    """Run the ``dualsight sql "..." --lake L`` command of a printed line and return its JSON rows."""
    import json
    import shlex

    argv = shlex.split(line[line.index("dualsight sql"):].strip().rstrip(")"))[1:]
    capsys.readouterr()
    assert main([*argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("keep", [True, False])
def test_calibrating_many_bad_images_names_five_and_says_where_the_rest_are(tmp_path, capsys, keep):
    folder = _bad_images(tmp_path / "photos")
    lake = ["--lake", str(tmp_path / "lake")] if keep else ["--no-lake"]
    assert main(["calibrate", str(folder), "--no-progress", *lake]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("dualsight: error: chessboard 9x6 found in 0 of 30 images; "
                                                   "need >= 3; unreadable 30 images: img00.png (")
    assert "img04.png (" in err and "img05.png" not in err and "; and 25 more (" in err
    if keep:
        rows = _sql_rows(capsys, err)
        assert len(rows) == 30 and all(r["error"] and not r["found"] for r in rows)
    else:
        assert err.endswith("and 25 more (run without --no-lake to keep every photo's reason in the lake)\n")


def test_a_calibration_summary_names_five_unusable_photos(tmp_path):
    from dualsight.scene.calibration import format_summary
    from dualsight.scene.camera import Camera

    class Result:   # the fields format_summary reads
        camera = Camera.pinhole(640, 480, 4.65e-6, 6e-3)
        board, square_m, views, rms_px, std, pixel_pitch_known, focal_length_mm = (9, 6), 0.025, (), 0.1, {}, True, 6.0
        not_found = tuple(Path(f"n{i}.png") for i in range(12))
        unreadable = tuple((Path(f"u{i}.png"), "truncated") for i in range(20))

    text = format_summary(Result(), "every photo's reason: here")
    assert "board not found in 12 images: n0.png, n1.png, n2.png, n3.png, n4.png, and 7 more (every photo's " \
           "reason: here)" in text
    lines = text.splitlines()
    assert [x for x in lines if x.startswith("unreadable")] == [f"unreadable: u{i}.png: truncated" for i in range(5)] \
        + ["unreadable: 15 more images (20 in all); every photo's reason: here"]
    Result.not_found, Result.unreadable = Result.not_found[:2], Result.unreadable[:5]     # few: as before
    lines = format_summary(Result(), "where").splitlines()
    assert lines[-6:] == ["board not found in: n0.png, n1.png"] + [f"unreadable: u{i}.png: truncated" for i in range(5)]


CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"


@pytest.mark.parametrize("keep", [True, False])
def test_hil_star_over_many_bad_images_names_five_and_says_where_the_rest_are(tmp_path, capsys, keep):
    folder = _bad_images(tmp_path / "frames")
    lake = ["--lake", str(tmp_path / "lake")] if keep else ["--no-lake"]
    assert main(["hil", "star", str(folder), "--camera", str(CAMERA), "--no-progress", *lake]) == 1
    cap = capsys.readouterr()
    err = cap.err.splitlines()
    skipped = [x for x in err if "skipped" in x]
    assert len(skipped) == 6
    # the report prints the summary lines of the first 20 images and says where the other 10 are; the table
    # below it has one row per image
    assert [x.split(":")[0] for x in cap.out.splitlines() if ": ERROR " in x] == [f"img{i:02d}.png" for i in range(20)]
    assert "of 10 more images: --json" in cap.out
    assert sum(1 for x in cap.out.splitlines() if x.lstrip().startswith("img")) == 20 + 30
    assert all(x.startswith(f"dualsight: {folder / f'img{i:02d}.png'}: ") and
               x.endswith("; skipped, the other images go on") for i, x in enumerate(skipped[:5]))
    assert skipped[5].startswith("dualsight: 25 more images skipped (30 in all); every image's reason: ")
    if keep:
        rows = _sql_rows(capsys, skipped[5])
        assert len(rows) == 30 and all(r["error"] for r in rows)
    else:
        assert skipped[5].endswith("every image's reason: --json (or run without --no-lake to keep the rows)")


def test_hil_star_over_a_few_bad_images_prints_each_as_before(tmp_path, capsys):
    folder = _bad_images(tmp_path / "frames", n=3)
    assert main(["hil", "star", str(folder), "--camera", str(CAMERA), "--no-progress", "--no-lake"]) == 1
    skipped = [x for x in capsys.readouterr().err.splitlines() if "skipped" in x]
    assert len(skipped) == 3 and all(x.endswith("; skipped, the other images go on") for x in skipped)
