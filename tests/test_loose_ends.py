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
