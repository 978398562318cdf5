"""Hostile input files: named pipes, devices, sockets and folders where a file is expected, images whose header
declares far more pixels than the file holds (decompression bombs), and files that make the decoding libraries
print.  Each must end the command within seconds and under 1 GB with one line naming the file and what is
allowed, exit status 2, no traceback and no lake.

The files are generated here; the CLI runs in a subprocess with a timeout and an address-space cap
(``RLIMIT_AS``), so a regression shows as a timeout or a memory error instead of a hung or swapping suite.
"""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import threading
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from dualsight import errors
from dualsight.errors import ImageError, InputError, read_user_file
from dualsight.scene.imageio import MAX_IMAGE_BYTES, MAX_IMAGE_PIXELS, ImageHeader, image_header, read_image
from helpers import ROOT, snapshot

CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
TIMEOUT_S = 20
MEMORY_CAP = int(1.5 * 2**30)
LIMITS = (f"{MAX_IMAGE_PIXELS / 1e6:.0f} Mpx", f"{MAX_IMAGE_BYTES // 2**20} MiB")


CAPPED = ["prlimit", f"--as={MEMORY_CAP}"]
"""Runs a command under the address-space cap: util-linux's prlimit sets it and execs, so no Python runs between
fork and exec of this multi-threaded test process (a preexec_fn there can hang on a lock another thread held)."""


def _dualsight(argv, cwd: Path, cap: bool = True) -> subprocess.CompletedProcess:
    """``dualsight <argv>`` in a subprocess: 20 s at most, 1.5 GB of address space (``cap``; a run that goes on
    to its DuckDB summary needs more address space than it uses: DuckDB reserves ahead)."""
    env = dict(os.environ, DUALSIGHT_LAKE=str(cwd / "lake"))
    return subprocess.run([*(CAPPED if cap else []), sys.executable, "-m", "dualsight", *map(str, argv)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=TIMEOUT_S)


def _refused(argv, cwd: Path, *needles) -> str:
    """Run, expect exit 2 and one stderr line containing every ``needle``; the lake never appears."""
    lake = cwd / "lake"
    before = snapshot(lake)
    r = _dualsight(argv, cwd)
    lines = r.stderr.splitlines()
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1, r.stderr[-2000:]
    assert lines[0].startswith("dualsight: error: "), lines[0]
    for n in needles:
        assert str(n) in lines[0], (n, lines[0])
    assert snapshot(lake) == before == {}
    return lines[0]


# ------------------------------------------------------------------------------------------------ file makers
def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png(width: int, height: int, depth: int = 8, colour: int = 0, idat: bytes | None = None) -> bytes:
    """A PNG whose IHDR (correct CRC) declares ``width`` x ``height``; ``idat`` defaults to a few zero rows."""
    if idat is None:
        idat = zlib.compress(bytes(1 + width * depth // 8) * 2)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0))
            + _chunk(b"IDAT", idat) + _chunk(b"IEND", b""))


def _png_bomb(width: int, height: int) -> bytes:
    """A complete 8-bit grey PNG of zeros: ~1000:1, 389 KB for 20000 x 20000 (the issue's file)."""
    z = zlib.compressobj(9)
    rows, step = [], 500
    for _ in range(0, height, step):
        rows.append(z.compress(bytes((width + 1) * step)))
    return _png(width, height, idat=b"".join(rows) + z.flush())


def _tiff(width: int, height: int, bits: int = 16, samples: int = 1, order: str = "<", big: bool = False) -> bytes:
    """A TIFF header and first IFD (no strips) declaring ``width`` x ``height``; classic or BigTIFF."""
    mark = b"II" if order == "<" else b"MM"
    tags = [(256, 4, width), (257, 4, height), (258, 3, bits), (259, 3, 1), (262, 3, 1), (277, 3, samples)]
    if big:
        head = mark + struct.pack(order + "HHHQ", 43, 8, 0, 16)
        ifd = struct.pack(order + "Q", len(tags)) + b"".join(
            struct.pack(order + "HHQ", t, typ, 1) + (struct.pack(order + "I" if typ == 4 else order + "H", v)
                                                     .ljust(8, b"\0")) for t, typ, v in tags)
        return head + ifd + struct.pack(order + "Q", 0)
    head = mark + struct.pack(order + "HI", 42, 8)
    ifd = struct.pack(order + "H", len(tags)) + b"".join(
        struct.pack(order + "HHI", t, typ, 1) + (struct.pack(order + "I" if typ == 4 else order + "H", v)
                                                 .ljust(4, b"\0")) for t, typ, v in tags)
    return head + ifd + struct.pack(order + "I", 0)


def _jpeg(width: int, height: int, comps: int = 3) -> bytes:
    """SOI, a JFIF APP0, an EXIF-like APP1, a baseline SOF0 declaring ``width`` x ``height``, EOI."""
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\0\x01\x01\0\0\x01\0\x01\0\0"
    app1 = b"\xff\xe1" + struct.pack(">H", 2 + 1000) + b"Exif\0\0" + bytes(994)
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 8 + 3 * comps, 8, height, width, comps) + b"".join(
        bytes([i + 1, 0x11, 0]) for i in range(comps))
    return b"\xff\xd8" + app0 + app1 + b"\xff\xff" + sof + b"\xff\xd9"


def _fits(width: int, height: int, bitpix: int = 16, extension: bool = False) -> bytes:
    """A FITS header (no data) declaring NAXIS1 x NAXIS2; with ``extension`` an empty primary HDU and an IMAGE
    extension holding the declaration."""
    def header(cards):
        text = "".join(c.ljust(80) for c in cards + ["END"])
        return text.ljust(-(-len(text) // 2880) * 2880).encode("ascii")

    image = [f"BITPIX  = {bitpix:20d}", "NAXIS   =                    2", f"NAXIS1  = {width:20d}",
             f"NAXIS2  = {height:20d}"]
    if extension:
        return (header(["SIMPLE  =                    T", "BITPIX  =                    8", "NAXIS   =                    0",
                        "EXTEND  =                    T"])
                + header(["XTENSION= 'IMAGE   '"] + image + ["PCOUNT  =                    0",
                                                            "GCOUNT  =                    1"]))
    return header(["SIMPLE  =                    T"] + image)


# ------------------------------------------------------------------------------------------------ named pipes
def test_fifo_image_is_refused_without_opening(tmp_path):
    fifo = tmp_path / "frame.png"
    os.mkfifo(fifo)
    _refused(["hil", "star", fifo, "--camera", CAMERA], tmp_path, fifo, "named pipe", "image file")


def test_fifo_camera_file_is_refused(tmp_path):
    fifo = tmp_path / "camera.toml"
    os.mkfifo(fifo)
    img = tmp_path / "frame.png"
    cv2.imwrite(str(img), np.zeros((8, 8), np.uint8))
    _refused(["hil", "star", img, "--camera", fifo], tmp_path, fifo, "named pipe", "TOML file")


def test_fifo_config_is_refused(tmp_path):
    fifo = tmp_path / "star.toml"
    os.mkfifo(fifo)
    _refused(["star", "run", "--config", fifo, "--cases", "2", "--no-progress"], tmp_path, fifo, "named pipe",
             "TOML file")


def test_fifo_in_a_calibration_folder_is_no_image(tmp_path):
    """A folder's listing keeps regular files only: a pipe there is never opened."""
    folder = tmp_path / "photos"
    folder.mkdir()
    os.mkfifo(folder / "board.jpg")
    _refused(["calibrate", folder], tmp_path, folder, "no images")


@pytest.mark.parametrize("kind", ["device", "socket"])
def test_devices_and_sockets_are_refused(tmp_path, kind):
    if kind == "device":
        path, what = Path("/dev/zero"), "character device"
    else:
        path, what = tmp_path / "frame.tiff", "socket"
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(path))
    try:
        _refused(["hil", "star", path, "--camera", CAMERA], tmp_path, path, what, "image file")
        _refused(["star", "run", "--config", path, "--cases", "2"], tmp_path, path, what, "TOML file")
    finally:
        if kind == "socket":
            s.close()


def test_folder_as_config_is_refused(tmp_path):
    (tmp_path / "conf.toml").mkdir()
    _refused(["star", "run", "--config", tmp_path / "conf.toml"], tmp_path, "conf.toml", "folder", "TOML file")


def test_a_pipe_swapped_in_after_the_stat_cannot_block(tmp_path, monkeypatch):
    """The race: os.stat saw a regular file, a FIFO is there by open(); the non-blocking open returns and the
    fstat refuses it (run in a thread; a blocked open is released by opening the pipe's write end)."""
    fifo, regular = tmp_path / "c.toml", tmp_path / "r.toml"
    os.mkfifo(fifo)
    regular.write_text("a = 1\n")
    real_stat = os.stat
    monkeypatch.setattr(errors.os, "stat", lambda p, *a, **k: real_stat(regular if Path(p) == fifo else p, *a, **k))
    out = []

    def read():
        try:
            read_user_file(fifo, what="TOML file")
        except InputError as e:
            out.append(str(e))

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(5)
    blocked = t.is_alive()
    if blocked:                                    # release the reader so the thread can end
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        t.join(5)
    assert not blocked, "open() blocked on a named pipe"
    assert out and "named pipe" in out[0] and str(fifo) in out[0], out


# ------------------------------------------------------------------------------------------------ image size
def test_png_bomb_is_refused_by_calibrate_before_decoding(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    bomb = folder / "board.png"
    bomb.write_bytes(_png_bomb(20000, 20000))
    assert bomb.stat().st_size < 500_000
    _refused(["calibrate", folder, "--no-progress"], tmp_path, bomb, "20000 x 20000 px", *LIMITS)


HEADERS = {
    "png 16-bit": ("frame.png", lambda: _png(32000, 32000, depth=16), "32000 x 32000 px of 1 x 16-bit"),
    "png rgba": ("frame.png", lambda: _png(12000, 12000, colour=6), "12000 x 12000 px of 4 x 8-bit"),
    "tiff II": ("frame.tiff", lambda: _tiff(32000, 32000), "32000 x 32000 px of 1 x 16-bit"),
    "tiff MM": ("frame.tif", lambda: _tiff(32000, 32000, order=">"), "32000 x 32000 px of 1 x 16-bit"),
    "bigtiff II": ("frame.tiff", lambda: _tiff(32000, 32000, big=True), "32000 x 32000 px of 1 x 16-bit"),
    "bigtiff MM": ("frame.tiff", lambda: _tiff(32000, 32000, order=">", big=True), "32000 x 32000 px of 1 x 16-bit"),
    "tiff rgb": ("frame.tiff", lambda: _tiff(10000, 10000, bits=8, samples=3), "10000 x 10000 px of 3 x 8-bit"),
    "jpeg": ("frame.jpg", lambda: _jpeg(30000, 30000), "30000 x 30000 px of 3 x 8-bit"),
    "fits": ("frame.fits", lambda: _fits(30000, 30000), "30000 x 30000 px of 1 x 16-bit"),
    "fits extension": ("frame.fits", lambda: _fits(30000, 30000, -32, extension=True), "30000 x 30000 px of 1 x -32-bit"),
}


@pytest.mark.parametrize("case", list(HEADERS))
def test_oversized_header_is_refused_by_hil_star(tmp_path, case):
    name, make, declared = HEADERS[case]
    img = tmp_path / name
    img.write_bytes(make())
    _refused(["hil", "star", img, "--camera", CAMERA], tmp_path, img, declared, *LIMITS)


@pytest.mark.parametrize("case", ["png 16-bit", "tiff MM", "jpeg", "fits"])
def test_oversized_header_is_refused_by_read_image(tmp_path, case):
    name, make, declared = HEADERS[case]
    img = tmp_path / name
    img.write_bytes(make())
    with pytest.raises(ImageError, match="declares") as e:
        read_image(img)
    assert declared in str(e.value) and str(img) in str(e.value)


def _decoded(img: np.ndarray) -> tuple[int, int, int]:
    return img.shape[1], img.shape[0], 1 if img.ndim == 2 else img.shape[2]


@pytest.mark.parametrize("ext,dtype,channels", [(".png", np.uint8, 1), (".png", np.uint16, 3), (".png", np.uint8, 4),
                                                (".tiff", np.uint16, 1), (".tiff", np.uint8, 3), (".jpg", np.uint8, 1),
                                                (".jpg", np.uint8, 3)])
def test_header_of_real_files_matches_their_pixels(tmp_path, ext, dtype, channels):
    """The parser reads what OpenCV's writers write: the header's size is the decoded size."""
    shape = (37, 53) if channels == 1 else (37, 53, channels)
    p = tmp_path / f"x{ext}"
    assert cv2.imwrite(str(p), np.random.default_rng(0).integers(0, 200, shape).astype(dtype))
    with open(p, "rb") as fh:
        h = image_header(fh, {".png": "PNG", ".tiff": "TIFF", ".jpg": "JPEG"}[ext])
    assert (h.width, h.height, h.channels) == _decoded(cv2.imread(str(p), cv2.IMREAD_UNCHANGED))
    assert h.bits == 8 * np.dtype(dtype).itemsize


def test_header_of_a_fits_file_and_a_real_tiff(tmp_path):
    from astropy.io import fits

    p = tmp_path / "x.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros((3, 21, 34), np.float32))]).writeto(p)
    with open(p, "rb") as fh:
        assert image_header(fh, "FITS") == ImageHeader(34, 21, 3, -32)
    esa = sorted((ROOT.parent / "shared" / "data" / "real" / "esa_tetra3").glob("*.tiff"))[:1]
    for f in esa:                   # the real frames, when present
        with open(f, "rb") as fh:
            h = image_header(fh, "TIFF")
        assert (h.width, h.height, h.channels) == _decoded(read_image(f).pixels)


def test_unknown_headers_keep_todays_path(tmp_path):
    """A header the parser cannot read is left to the decoder (its own one-line error)."""
    p = tmp_path / "odd.tiff"
    p.write_bytes(b"II*\x00" + struct.pack("<I", 1 << 30))            # first IFD far beyond the end
    with open(p, "rb") as fh:
        assert image_header(fh, "TIFF") is None
    with pytest.raises(ImageError, match="cannot decode TIFF"):
        read_image(p)


# ------------------------------------------------------------------------------------------------ library noise
def _truncated_png() -> bytes:
    """A well-formed 64 x 64 PNG whose one IDAT holds half the compressed rows (CRCs correct): libpng says
    "Not enough image data" on stderr."""
    ok = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (64, 64), dtype=np.uint8))[1].tobytes()
    pos, idat = 33, b""
    while pos < len(ok):
        n, kind = struct.unpack(">I4s", ok[pos:pos + 8])
        idat += ok[pos + 8:pos + 8 + n] if kind == b"IDAT" else b""
        pos += 12 + n
    return ok[:33] + _chunk(b"IDAT", idat[:len(idat) // 2]) + _chunk(b"IEND", b"")


def test_truncated_png_gives_dualsights_line_only_with_libpngs_reason(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    bad = folder / "board.png"
    bad.write_bytes(_truncated_png())
    line = _refused(["calibrate", folder, "--no-progress", "--no-lake"], tmp_path, "board.png", "truncated or corrupt",
                    "Not enough image data")
    assert "libpng" in line
    # hil star goes on past a bad image (exit 1): its stderr is its own per-image line and its summary
    r = _dualsight(["hil", "star", bad, "--camera", CAMERA, "--no-lake", "--no-progress"], tmp_path, cap=False)
    lines = r.stderr.splitlines()
    assert r.returncode == 1, r.stderr
    assert len(lines) == 2, r.stderr
    assert lines[0].startswith(f"dualsight: {bad}: cannot decode PNG data") and "Not enough image data" in lines[0]
    assert lines[1].startswith("1 images: 0 identified, 1 could not be processed")


def test_libjpeg_warnings_of_a_readable_jpeg_stay_off_the_terminal(tmp_path):
    """A JPEG with junk before its end marker decodes; libjpeg's "Corrupt JPEG data" never reaches fd 2."""
    ok = cv2.imencode(".jpg", np.random.default_rng(1).integers(0, 255, (64, 64), dtype=np.uint8))[1].tobytes()
    p = tmp_path / "x.jpg"
    p.write_bytes(ok[:len(ok) // 2] + bytes(50) + ok[len(ok) // 2 + 50:])
    code = f"from dualsight.scene.imageio import read_image; print(read_image({str(p)!r}).pixels.shape)"
    r = subprocess.run([*CAPPED, sys.executable, "-c", code], capture_output=True, text=True, timeout=TIMEOUT_S)
    assert r.returncode == 0 and r.stdout.strip() == "(64, 64)" and r.stderr == "", r.stderr
