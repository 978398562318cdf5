"""Errors that name what went wrong, where, and what is allowed.

Every bad input (a malformed config, an impossible camera, a corrupt image)
is reported as a :class:`InputError` whose message names the file, the field
and the allowed range, so that the CLI can print it as one line and exit
with status 2 without touching the lake.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


class InputError(ValueError):
    """A user input is invalid.

    Parameters
    ----------
    message : what is wrong and what is allowed.
    source : the file (or "preset X", "--flag") the value came from.
    field : the dotted key inside that source, e.g. ``camera.focal_length_mm``.
    """

    def __init__(self, message: str, *, source: str | None = None, field: str | None = None):
        self.source = source
        self.field = field
        self.detail = message
        where = []
        if source:
            where.append(str(source))
        if field:
            where.append(f"[{field}]")
        prefix = (" ".join(where) + ": ") if where else ""
        super().__init__(prefix + message)


class ConfigError(InputError):
    """A configuration file or preset is invalid."""


class ImageError(InputError):
    """An image file is missing, truncated or in an unsupported format."""


def _a(what: str) -> str:
    return ("an " if what[:1].lower() in "aeiou" else "a ") + what


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` is, in words ("a regular file", "a named pipe (FIFO)", "a folder", ...)."""
    for test, name in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"),
                       (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


def check_regular(path, error=InputError, *, what: str = "file", st: os.stat_result | None = None) -> os.stat_result:
    """``os.stat(path)`` (or ``st``, an ``fstat`` already made) when it is a regular file; otherwise one ``error``
    naming the file, what it is and what is allowed.  Nothing is opened: a named pipe never blocks here."""
    if st is None:
        try:
            st = os.stat(path)
        except FileNotFoundError:
            raise error("file not found", source=str(path)) from None
        except PermissionError:
            raise error("cannot be read (permission denied)", source=str(path)) from None
        except OSError as e:
            raise error(f"cannot be read ({e.strerror or e})", source=str(path)) from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"is {file_kind(st.st_mode)}, not a regular file; give {_a(what)}", source=str(path))
    return st


def open_user_file(path, error=InputError, *, what: str = "file"):
    """A binary file object of a regular file the user named, every failure one ``error`` naming the file.

    The file type is checked with ``os.stat`` before opening (a named pipe would block ``open``), the file is
    opened non-blocking (a pipe swapped in meanwhile cannot block either) and checked again with ``fstat``."""
    check_regular(path, error, what=what)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
                     | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise error("file not found", source=str(path)) from None
    except IsADirectoryError:
        raise error(f"is a folder, expected {_a(what)}", source=str(path)) from None
    except PermissionError:
        raise error("cannot be read (permission denied)", source=str(path)) from None
    except OSError as e:
        raise error(f"cannot be read ({e.strerror or e})", source=str(path)) from None
    try:
        check_regular(path, error, what=what, st=os.fstat(fd))      # against a race since the stat above
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb")


def read_user_file(path, error=InputError, *, what: str = "file", max_bytes: int | None = None) -> bytes:
    """The bytes of a file the user named, every failure one ``error`` naming the file.

    Refuses folders, devices, sockets and named pipes before opening them (:func:`open_user_file`: ``/dev/zero``
    is never read, a FIFO never blocks), files larger than ``max_bytes`` and empty files; ``what`` names the
    expected content in the messages ("TOML file", "image file").
    """
    path = Path(path)
    with open_user_file(path, error, what=what) as fh:
        try:
            data = fh.read() if max_bytes is None else fh.read(max_bytes + 1)
        except OSError as e:
            raise error(f"cannot be read ({e.strerror or e})", source=str(path)) from None
    if max_bytes is not None and len(data) > max_bytes:
        raise error(f"is larger than {max_bytes // 1024} KiB; {_a(what)} is a few kB", source=str(path))
    if not data:
        raise error("file is empty (0 bytes)", source=str(path))
    return data


def output_path(path, *, folder: bool = False):
    """``path`` as a Path when its parent folder exists (and, with ``folder``, create ``path`` itself as the
    one folder the user named); otherwise an InputError: dualsight creates no folder the user did not name."""

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("folder does not exist (dualsight creates no folder you did not name)",
                         source=str(path.parent))
    if folder:
        if path.exists() and not path.is_dir():
            raise InputError("exists and is not a folder", source=str(path))
        path.mkdir(exist_ok=True)
    return path
