"""Opening input files that may be hostile: only regular files are read.

A FIFO named as a configuration, a road profile or a recording would block the reader
until something writes to it (or forever); a character device (``/dev/zero``,
``/dev/urandom``) never ends.  :func:`open_regular` opens without blocking, checks the
open file itself (no race between a check and the open) and refuses anything that is
not a regular file with :class:`NotRegularFileError`, one phrase naming what it is.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

__all__ = ["NotRegularFileError", "file_kind", "open_regular", "regular_file_problem"]

_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISDIR, "a directory"))


class NotRegularFileError(OSError):
    """The path names something other than a regular file (``str()``: ``<path>: is a
    FIFO (named pipe), expected a regular file``; ``what``: the part after the path)."""

    def __init__(self, path: str | Path, what: str) -> None:
        super().__init__(f"{path}: {what}")
        self.what = what


def _what(mode: int) -> str:
    return f"is {file_kind(mode)}, expected a regular file"


def regular_file_problem(path: str | Path) -> str | None:
    """Why ``path`` is not a regular file to read (``is a FIFO ...``), or None; a path
    that does not exist or cannot be examined is left to the open that follows."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return None if stat.S_ISREG(mode) else _what(mode)


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, in words ("a regular file", "a FIFO ...")."""
    return next((name for test, name in _KINDS if test(mode)), "a regular file")


def open_regular(path: str | Path) -> BinaryIO:
    """``path`` opened for binary reading; :class:`NotRegularFileError` if it is not a
    regular file (OSError as ``open`` when it cannot be opened)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise NotRegularFileError(path, _what(mode))
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
