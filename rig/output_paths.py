"""Where ``rig`` may write its outputs: one set of rules for the command line's argument
checks (:mod:`rig.argtypes`, at parse time) and the recorder (:class:`rig.recording.recorder.
RunRecorder`, at start).

- A recording is never overwritten: a new run needs a new ``.mcap`` name, and none of
  its rotation segments (``<stem>.001.mcap`` ...) may exist either.  A directory target
  gets ``run-<UTC>.mcap`` (``run-<UTC>-2.mcap`` ... if a run started in the same second).
- A single output file (a design artifact, saved traces) is replaced only with
  ``--force``.
- An output directory may exist (the command rewrites its own files in it) but must not
  be a file.  Its files are written into a hidden staging directory next to it and moved
  in only when all of them are done (:func:`staged_dir`): a command that fails half-way
  leaves no partial output.
- Directories that do not exist yet are created, so the nearest existing ancestor must be
  a directory in which this process can create entries (tried, not guessed from mode
  bits: root passes ``os.access`` on a read-only or pseudo file system).

Each ``*_problem`` function returns None when the path is usable, else one phrase saying
what is wrong and what would do (to follow ``"<path>: "``).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

__all__ = [
    "OUTPUT_FAILED",
    "RECORDING_SUFFIX",
    "new_file_problem",
    "new_recording_problem",
    "output_dir_problem",
    "recording_file",
    "recording_target_problem",
    "staged_dir",
    "staged_file",
]

RECORDING_SUFFIX = ".mcap"
#: exit status of a command whose output (a recording it was asked for) could not be
#: written whole: a write failed, e.g. a full disk (``rig replay --out``, ``rig run
#: --record`` / ``--excite``, ``rig demo --record``)
OUTPUT_FAILED = 3


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _creatable_below(path: Path) -> str | None:
    """None if ``path`` (and missing directories above it) can be created."""
    anc = _nearest_existing(path.parent)
    if not anc.is_dir():
        return f"cannot be created: {anc} is not a directory"
    try:
        with tempfile.TemporaryFile(dir=anc):
            pass
    except OSError as exc:
        return f"cannot be created: no new files in {anc} ({exc.strerror or exc})"
    return None


def recording_file(target: str | Path, now: datetime | None = None) -> Path:
    """The first segment's path of a recording into ``target``: ``target`` itself when it
    ends in ``.mcap``, else a new ``run-<UTC>.mcap`` in the directory ``target``."""
    target = Path(target)
    if target.suffix == RECORDING_SUFFIX:
        return target
    stamp = (now or datetime.now(UTC)).strftime("%Y%m%dT%H%M%SZ")
    path = target / f"run-{stamp}{RECORDING_SUFFIX}"
    n = 1
    while path.exists() or _segment(path, 1).exists():
        n += 1
        path = target / f"run-{stamp}-{n}{RECORDING_SUFFIX}"
    return path


def _segment(base: Path, index: int) -> Path:
    from rig.recording.writer import segment_path

    return segment_path(base, index)


def new_recording_problem(path: str | Path) -> str | None:
    """Why a new recording cannot start at the ``.mcap`` path ``path``, or None."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        return (f"exists: a recording is never overwritten; give a new {RECORDING_SUFFIX} "
                "name or a directory")
    seg = _segment(path, 1)
    if seg.exists():
        return (f"its rotation segment {seg.name} exists (an earlier run): give a new "
                f"{RECORDING_SUFFIX} name or a directory")
    return _creatable_below(path)


def recording_target_problem(target: str | Path) -> str | None:
    """Why ``--record`` / ``--out`` ``target`` (a new ``.mcap`` path or a directory) cannot
    take a new recording, or None."""
    target = Path(target)
    if target.suffix == RECORDING_SUFFIX:
        return new_recording_problem(target)
    if target.exists() and not target.is_dir():
        return (f"exists and is not a directory: give a directory or a new "
                f"{RECORDING_SUFFIX} path")
    return _creatable_below(target / "x")


def new_file_problem(path: str | Path, force: bool) -> str | None:
    """Why the single output file ``path`` cannot be written, or None (``force``: an
    existing file may be replaced)."""
    path = Path(path)
    if path.is_dir():
        return "is a directory: give a file name"
    if path.exists() and not force:
        return "exists: add --force to replace it"
    if not path.parent.absolute().is_dir():
        return f"directory {path.parent} does not exist"
    if path.exists():
        return None if os.access(path, os.W_OK) else "is not writable"
    return _creatable_below(path)


def output_dir_problem(path: str | Path) -> str | None:
    """Why ``path`` cannot be (created as) an output directory, or None."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        return "exists and is not a directory: give a directory"
    return _creatable_below(path / "x")


@contextlib.contextmanager
def staged_dir(out: str | Path) -> Iterator[Path]:
    """A new empty directory to write the files of the output directory ``out`` into.
    When the ``with`` block ends normally they are moved into ``out`` (``out`` itself
    is renamed into place when it does not exist yet; else each file replaces its
    namesake, the others in ``out`` are kept); when it raises, the staging directory is
    removed and ``out`` is left as it was."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        yield stage
        if not (out.exists() or out.is_symlink()):
            os.rename(stage, out)          # atomic
        else:                              # keep the directory (or symlink) the user has
            for item in sorted(stage.iterdir(), key=_html_last):
                os.replace(item, out / item.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


@contextlib.contextmanager
def staged_file(out: str | Path) -> Iterator[Path]:
    """A new hidden path next to the output file ``out`` to write it to; renamed over
    ``out`` when the ``with`` block ends normally, removed when it raises (no partial
    output, an earlier ``out`` left as it was)."""
    out = Path(out)
    fd, name = tempfile.mkstemp(prefix=f".{out.stem}.partial-", suffix=out.suffix,
                                dir=out.parent)
    os.close(fd)
    stage = Path(name)
    try:
        yield stage
        os.replace(stage, out)             # atomic
    finally:
        stage.unlink(missing_ok=True)


def _html_last(item: Path) -> tuple[bool, str]:
    """The page after its images: a reader never finds a page whose images are missing."""
    return item.suffix == ".html", item.name
