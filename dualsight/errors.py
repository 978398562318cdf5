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


def read_user_file(path, error=InputError, *, what: str = "file", max_bytes: int | None = None) -> bytes:
    """The bytes of a file the user named, every failure one ``error`` naming the file.

    Refuses folders, devices and pipes (``/dev/zero`` is never read), files larger than ``max_bytes`` and
    empty files; ``what`` names the expected content in the messages ("TOML file", "image file").
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise error(f"is not a regular file (a device, pipe or folder); give a {what}", source=str(path))
            data = fh.read() if max_bytes is None else fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise error("file not found", source=str(path)) from None
    except IsADirectoryError:
        raise error(f"is a folder, expected a {what}", source=str(path)) from None
    except PermissionError:
        raise error("cannot be read (permission denied)", source=str(path)) from None
    except OSError as e:
        raise error(f"cannot be read ({e.strerror or e})", source=str(path)) from None
    if max_bytes is not None and len(data) > max_bytes:
        raise error(f"is larger than {max_bytes // 1024} KiB; a {what} is a few kB", source=str(path))
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
