"""``dualsight hil star IMAGES --track`` (issue 22, point 4): the images' times (scene/frame_times.py) against
hand-written truth and files written by independent writers (Pillow's EXIF, astropy's FITS), and the frames solved
as one ordered sequence (nav/sequence.py) against the sidereal rate of a fixed ground camera."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pytest

from dualsight.errors import InputError
from dualsight.scene import frame_times as ft


def _utc(*a):
    return datetime(*a, tzinfo=timezone.utc)


# ============================================================================================ times
def test_file_name_times():
    assert ft.filename_time("2019-07-29T204726_Alt40_Azi-135_Try1.tiff") == _utc(2019, 7, 29, 20, 47, 26)
    assert ft.filename_time("/x/night_2021-01-02T03:04:05.25.png") == _utc(2021, 1, 2, 3, 4, 5, 250000)
    assert ft.filename_time("20210102T030405.fits") == _utc(2021, 1, 2, 3, 4, 5)
    assert ft.filename_time("2021-01-02_030405.jpg") == _utc(2021, 1, 2, 3, 4, 5)
    for bad in ("frame_0001.tiff", "2021-13-02T030405.png", "12021-01-02T030405.png"):
        assert ft.filename_time(bad) is None, bad


def test_times_csv_and_its_errors(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("image,utc\n# comment\n\na.png,2020-01-01T00:00:10.5Z\n/some/dir/b.png, 2020-01-01T01:00:00+01:00\n")
    assert ft.read_times_csv(f) == {"a.png": _utc(2020, 1, 1, 0, 0, 10, 500000), "b.png": _utc(2020, 1, 1)}
    for text, needle in (("name,time\na.png,2020-01-01T00:00:00\n", "line 1: the header must be image,utc"),
                         ("image,utc\na.png\n", "line 2: needs two fields"),
                         ("image,utc\n,2020-01-01T00:00:00\n", "line 2: field image is empty"),
                         ("image,utc\na.png,2020-01-01T00:00:00\n\na.png,2020-01-01T00:00:01\n",
                          "line 4: field image 'a.png' is listed twice"),
                         ("image,utc\na.png,yesterday\n", "line 2: field utc is not an ISO 8601 time"),
                         ("", "is empty")):
        f.write_text(text)
        with pytest.raises(InputError) as e:
            ft.read_times_csv(f)
        assert str(e.value).startswith(str(f)) and needle in str(e.value), (text, str(e.value))
    with pytest.raises(InputError, match="is not a file"):
        ft.read_times_csv(tmp_path / "missing.csv")


def test_exif_times_written_by_pillow(tmp_path):
    Image = pytest.importorskip("PIL.Image")
    img = Image.new("L", (16, 8), 7)
    cases = [("a.jpg", {0x9003: "2022:03:04 05:06:07"}, _utc(2022, 3, 4, 5, 6, 7)),
             ("b.jpg", {0x9003: "2022:03:04 05:06:07", 0x9291: "25", 0x9011: "+02:00"},
              _utc(2022, 3, 4, 3, 6, 7, 250000)),
             ("c.tiff", {0x9003: "2022:03:04 05:06:07", 0x9291: "5", 0x9011: "-01:30"},
              _utc(2022, 3, 4, 6, 36, 7, 500000)),
             ("d.jpg", {}, None)]
    for name, tags, truth in cases:
        exif = Image.Exif()
        exif[0x0110] = "test camera"
        if tags:
            exif.get_ifd(0x8769).update(tags)
        if name.endswith(".tiff"):          # Pillow's TIFF writer drops the Exif IFD: its EXIF block is a TIFF
            (tmp_path / name).write_bytes(exif.tobytes()[6:])
        else:
            img.save(tmp_path / name, exif=exif)
        assert ft.exif_datetime(tmp_path / name) == truth, name
    assert ft.exif_datetime(tmp_path / "missing.jpg") is None


def test_fits_date_obs_and_the_order_of_sources(tmp_path):
    fits = pytest.importorskip("astropy.io.fits")
    hdu = fits.PrimaryHDU(np.zeros((4, 4), np.uint16))
    hdu.header["DATE-OBS"] = "2023-05-06T07:08:09.125"
    hdu.writeto(tmp_path / "2000-01-01T000000_x.fits")
    p_fits = tmp_path / "2000-01-01T000000_x.fits"
    p_name = tmp_path / "2001-02-03T040506_y.png"
    p_none = tmp_path / "z.png"
    for p in (p_name, p_none):
        p.write_bytes(b"")
    got = ft.frame_times([p_fits, p_name])
    assert [(t.utc, t.source) for t in got] == [(_utc(2023, 5, 6, 7, 8, 9, 125000), "fits"),
                                                (_utc(2001, 2, 3, 4, 5, 6), "file_name")]
    assert got[0].iso == "2023-05-06T07:08:09.125000Z"
    csv = tmp_path / "t.csv"
    csv.write_text("image,utc\nz.png,2024-01-01T00:00:00Z\n2000-01-01T000000_x.fits,2024-01-01T00:00:01Z\n")
    got = ft.frame_times([p_fits, p_none, p_name], csv)
    assert [t.source for t in got] == ["times_file", "times_file", "file_name"]
    assert ft.time_order(got) == [2, 1, 0]
    assert ft.seconds_since([got[i] for i in (1, 0)]) == [0.0, 1.0]
    with pytest.raises(InputError) as e:
        ft.frame_times([p_name, p_none])
    assert str(e.value).startswith("--track: z.png: no time") and "--times FILE" in str(e.value)
    with pytest.raises(InputError, match=r"^--times: z.png: no time \(not listed in"):
        ft.frame_times([p_none], tmp_path / "empty.csv") if (tmp_path / "empty.csv").write_text(
            "image,utc\n") else None


def test_time_order_is_stable_for_equal_times():
    t = [ft.FrameTime(_utc(2020, 1, 1, 0, 0, s), "file_name") for s in (5, 1, 5, 0)]
    assert ft.time_order(t) == [3, 1, 0, 2]
