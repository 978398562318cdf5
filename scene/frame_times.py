"""When each real image was taken: the times that order ``dualsight hil star --track``'s frames into one sequence.

Sources, first that answers (issue 22, point 4):

1. ``--times FILE``: a CSV file with a header ``image,utc`` and one line per image (the file name, or a path whose
   file name is matched, and an ISO 8601 UTC time such as ``2019-07-29T20:47:26.250`` or ``...Z``).
2. FITS ``DATE-OBS`` (astropy's header reader; ISO, UTC assumed as the FITS standard's default ``TIMESYS``).
3. EXIF ``DateTimeOriginal`` (tag 0x9003 of the Exif IFD), with ``SubSecTimeOriginal`` (0x9291) and
   ``OffsetTimeOriginal`` (0x9011) when present, read from a TIFF or from a JPEG's APP1 segment by the minimal
   reader below (no imaging library); EXIF times without an offset are taken as UTC.
4. A time in the file name: ``YYYY-MM-DDTHHMMSS`` (the ESA tetra3 frames: ``2019-07-29T204726_Alt40_...``),
   ``YYYY-MM-DDTHH:MM:SS`` or ``YYYYMMDDTHHMMSS``, each with optional fractional seconds (``.250``).

No time from any source: :func:`frame_times` raises one InputError saying how to give times.  Times are
``datetime`` in UTC; differences are seconds of UTC (leap seconds ignored: one second in a sequence that
spans one).
"""

from __future__ import annotations

import csv
import re
import struct
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

from dualsight.errors import InputError

__all__ = ["FrameTime", "SOURCES", "parse_utc", "read_times_csv", "fits_date_obs", "exif_datetime",
           "filename_time", "frame_times", "time_order", "seconds_since"]

SOURCES = ("times_file", "fits", "exif", "file_name")
"""Where a :class:`FrameTime` came from."""

MAX_TIMES_BYTES = 16 * 2**20
"""Largest ``--times`` CSV read (16 MiB: ~300k lines)."""
_EXIF_SCAN_BYTES = 1 << 20
"""Bytes of an image read for its EXIF block (the TIFF IFDs / JPEG APP1 sit near the start)."""


@dataclass(frozen=True)
class FrameTime:
    """One image's time: ``utc`` (timezone-aware UTC datetime) and ``source`` (one of :data:`SOURCES`)."""

    utc: datetime
    source: str

    @property
    def iso(self) -> str:
        """ISO 8601 UTC with microseconds and ``Z`` (e.g. ``2019-07-29T20:47:26.000000Z``)."""
        return self.utc.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def parse_utc(text: str) -> datetime:
    """A timezone-aware UTC datetime of an ISO 8601 time (``Z`` or an offset allowed; none = UTC).
    ValueError for anything else."""
    s = str(text).strip()
    if not s or len(s) > 64:
        raise ValueError(f"not an ISO 8601 time: {text!r}")
    t = datetime.fromisoformat(s.replace("Z", "+00:00").replace("z", "+00:00"))
    return t.replace(tzinfo=timezone.utc) if t.tzinfo is None else t.astimezone(timezone.utc)


def read_times_csv(path: str | Path) -> dict[str, datetime]:
    """{file name: UTC datetime} of a ``--times`` CSV (header ``image,utc``; blank lines and lines starting with
    ``#`` skipped).  InputError naming the file, the line and the field for a missing header, a short line, an
    empty image, a malformed time or an image listed twice."""
    path = Path(path)
    src = str(path)
    try:
        if not path.is_file():
            raise InputError("is not a file (a CSV with the header image,utc)", source=src)
        if path.stat().st_size > MAX_TIMES_BYTES:
            raise InputError(f"is larger than {MAX_TIMES_BYTES // 2**20} MiB", source=src)
        text = path.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise InputError(f"cannot be read ({e.strerror or e})", source=src) from None
    except UnicodeDecodeError:
        raise InputError("is not UTF-8 text (a CSV with the header image,utc)", source=src) from None
    lines = [(n, ln) for n, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError("is empty; expected the header image,utc and one line per image", source=src)
    rows = list(csv.reader([ln for _, ln in lines]))
    head = [h.strip().lower() for h in rows[0]]
    if head[:2] != ["image", "utc"]:
        raise InputError(f"line {lines[0][0]}: the header must be image,utc, got {lines[0][1].strip()!r}", source=src)
    out: dict[str, datetime] = {}
    for (n, _), row in zip(lines[1:], rows[1:]):
        if len(row) < 2:
            raise InputError(f"line {n}: needs two fields image,utc, got {len(row)}", source=src)
        name = Path(row[0].strip()).name
        if not name:
            raise InputError(f"line {n}: field image is empty", source=src)
        try:
            t = parse_utc(row[1])
        except ValueError:
            raise InputError(f"line {n}: field utc is not an ISO 8601 time (e.g. 2019-07-29T20:47:26.25Z): "
                             f"{row[1].strip()!r}", source=src) from None
        if name in out:
            raise InputError(f"line {n}: field image {name!r} is listed twice", source=src)
        out[name] = t
    return out


def fits_date_obs(path: str | Path) -> datetime | None:
    """``DATE-OBS`` of a FITS file's primary header (UTC), or None (no such card, not FITS, unreadable)."""
    p = Path(path)
    if p.suffix.lower() not in (".fits", ".fit", ".fts"):
        return None
    from astropy.io import fits                                        # heavy: only for FITS images

    try:
        value = fits.getval(p, "DATE-OBS", ext=0)
    except (OSError, KeyError, ValueError, IndexError):
        return None
    try:
        return parse_utc(str(value))
    except ValueError:
        return None


_EXIF_DATETIME_ORIGINAL, _EXIF_SUBSEC_ORIGINAL, _EXIF_OFFSET_ORIGINAL = 0x9003, 0x9291, 0x9011
_EXIF_IFD_POINTER = 0x8769


def _tiff_ascii_tags(buf: bytes, base: int) -> dict[int, str]:
    """ASCII tags (type 2) of IFD0 and of the Exif IFD of a TIFF structure starting at ``buf[base:]``
    (byte order "II" or "MM"); {} when malformed.  Offsets are relative to ``base``."""
    if buf[base:base + 2] not in (b"II", b"MM"):
        return {}
    e = "<" if buf[base:base + 2] == b"II" else ">"
    out: dict[int, str] = {}

    def ifd(off: int, depth: int):
        p = base + off
        if depth > 2 or off <= 0 or p + 2 > len(buf):
            return
        (n,) = struct.unpack_from(e + "H", buf, p)
        for i in range(min(n, 512)):
            q = p + 2 + 12 * i
            if q + 12 > len(buf):
                return
            tag, typ, count = struct.unpack_from(e + "HHI", buf, q)
            if tag == _EXIF_IFD_POINTER and typ in (4, 13):
                ifd(struct.unpack_from(e + "I", buf, q + 8)[0], depth + 1)
            elif typ == 2 and 0 < count <= 64:
                s = q + 8 if count <= 4 else base + struct.unpack_from(e + "I", buf, q + 8)[0]
                raw = buf[s:s + count]
                if len(raw) == count:
                    out.setdefault(tag, raw.split(b"\0", 1)[0].decode("ascii", "replace").strip())

    ifd(struct.unpack_from(e + "I", buf, base + 4)[0] if base + 8 <= len(buf) else 0, 0)
    return out


def _exif_block(buf: bytes) -> int | None:
    """Offset of the TIFF structure holding a file's EXIF: 0 for a TIFF, the APP1 ``Exif`` payload of a JPEG."""
    if buf[:4] in (b"II*\0", b"MM\0*"):
        return 0
    if buf[:2] != b"\xff\xd8":
        return None
    p = 2
    while p + 4 <= len(buf) and buf[p] == 0xFF:
        marker, (size,) = buf[p + 1], struct.unpack_from(">H", buf, p + 2)
        if marker == 0xE1 and buf[p + 4:p + 10] == b"Exif\0\0":
            return p + 10
        if marker in (0xDA, 0xD9):                     # start of scan / end: no EXIF before the image data
            return None
        p += 2 + size
    return None


def exif_datetime(path: str | Path) -> datetime | None:
    """EXIF ``DateTimeOriginal`` (+ ``SubSecTimeOriginal``, ``OffsetTimeOriginal``) of a TIFF or JPEG as UTC, or
    None (no such tag, another format, malformed)."""
    try:
        with open(path, "rb") as fh:
            buf = fh.read(_EXIF_SCAN_BYTES)
    except OSError:
        return None
    try:
        base = _exif_block(buf)
        tags = _tiff_ascii_tags(buf, base) if base is not None else {}
    except struct.error:
        return None
    text = tags.get(_EXIF_DATETIME_ORIGINAL)
    if not text:
        return None
    try:
        t = datetime.strptime(text, "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    sub = tags.get(_EXIF_SUBSEC_ORIGINAL, "")
    if sub.isdigit():
        t += timedelta(seconds=int(sub) / 10 ** len(sub))
    off = re.fullmatch(r"([+-])(\d{2}):(\d{2})", tags.get(_EXIF_OFFSET_ORIGINAL, ""))
    if off:
        sign = 1 if off[1] == "+" else -1
        t -= sign * timedelta(hours=int(off[2]), minutes=int(off[3]))
    return t.replace(tzinfo=timezone.utc)


_NAME_TIME = re.compile(r"(?<!\d)(?P<Y>\d{4})-?(?P<M>\d{2})-?(?P<D>\d{2})[T_](?P<h>\d{2}):?(?P<m>\d{2}):?(?P<s>\d{2})"
                        r"(?:[.,](?P<f>\d{1,6}))?(?!\d)")


def filename_time(name: str | Path) -> datetime | None:
    """The UTC time in a file name (module docstring, source 4), or None."""
    m = _NAME_TIME.search(Path(name).name)
    if m is None:
        return None
    try:
        t = datetime(int(m["Y"]), int(m["M"]), int(m["D"]), int(m["h"]), int(m["m"]), int(m["s"]),
                     tzinfo=timezone.utc)
    except ValueError:
        return None
    return t + timedelta(seconds=int(m["f"]) / 10 ** len(m["f"])) if m["f"] else t


def frame_times(paths, times_file: str | Path | None = None) -> list[FrameTime]:
    """The time of every image (module docstring: the first source that answers), in input order.

    InputError (source ``--times`` or ``--track``) naming the first image without a time and how to give one.
    """
    table = read_times_csv(times_file) if times_file is not None else None
    out = []
    for p in paths:
        p = Path(p)
        if table is not None and p.name in table:
            out.append(FrameTime(table[p.name], "times_file"))
            continue
        for source, get in (("fits", fits_date_obs), ("exif", exif_datetime), ("file_name", filename_time)):
            t = get(p)
            if t is not None:
                out.append(FrameTime(t, source))
                break
        else:
            listed = f"not listed in {times_file}, " if table is not None else ""
            raise InputError(f"{p.name}: no time ({listed}no FITS DATE-OBS, no EXIF DateTimeOriginal, no "
                             "YYYY-MM-DDTHHMMSS in the file name); give --times FILE, a CSV with the header "
                             "image,utc and one line per image", source="--times" if table is not None else "--track")
    return out


def time_order(times: list[FrameTime]) -> list[int]:
    """Indices that sort ``times`` (stable: equal times keep their input order)."""
    return sorted(range(len(times)), key=lambda i: times[i].utc)


def seconds_since(times: list[FrameTime], t0: datetime | None = None) -> list[float]:
    """Seconds of each time after ``t0`` (default the first), as floats (microsecond resolution)."""
    if not times:
        return []
    t0 = times[0].utc if t0 is None else t0
    return [(t.utc - t0) / timedelta(microseconds=1) * 1e-6 for t in times]
