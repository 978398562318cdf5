"""Errors that name what went wrong, where, and what is allowed.

Every bad input (a malformed config, an impossible camera, a corrupt image)
is reported as a :class:`InputError` whose message names the file, the field
and the allowed range, so that the CLI can print it as one line and exit
with status 2 without touching the lake.
"""

from __future__ import annotations


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
