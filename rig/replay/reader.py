"""The reader process of a replay: reads and decodes the recording in a forked process
while the loop replays it (docs/replay.md, "Speed").

Reading (zstd, CRC, column extraction, frames) and ticking the loop each take about
half of the time on one core; with a second core free, overlapping them brings a
1 kHz recording from ~35x to ~50x real time.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Final

from rig.recording.scan import RecordingError, ScanResult, check_is_recording, scan_recording
from rig.replay.recorded import Piece, RunDecoder, malformed_payload

__all__ = ["PIPELINE_MIN_BYTES", "ReaderProcess", "idle_cpu"]

#: recordings at least this large are read by a reader process while the loop replays
PIPELINE_MIN_BYTES: Final = 8 * 1024 * 1024


def _reader_main(path: str, conn: Any, flush_messages: int) -> None:
    """Reader process: scan + decode, sending ("head", scan, first internals) after the
    first chunk, ("piece", Piece) per piece, ("end", scan) or ("error", exception)."""
    try:
        res = ScanResult()
        dec = RunDecoder(flush_messages, emit=lambda piece: conn.send(("piece", piece)))
        head_sent = False

        def after() -> None:
            nonlocal head_sent
            if not head_sent and res.topics:
                check_is_recording(res, Path(path))
                conn.send(("head", res, dec.first))
                head_sent = True
            dec.after_chunk()

        scan_recording(path, dec.handlers(), after_chunk=after, result=res)
        try:
            dec.flush(final=True)
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise malformed_payload(path, exc) from exc
        if not head_sent:
            conn.send(("head", res, dec.first))
        conn.send(("end", res))
    except BaseException as exc:  # handed to the replaying process
        conn.send(("error", exc))
    finally:
        conn.close()


class ReaderProcess:
    """Pieces of a recording from a forked reader process (overlaps reading the MCAP
    with replaying it: each takes about half the time on one core)."""

    def __init__(self, path: Path, flush_messages: int = 16384) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("fork")
        self.path = path
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_reader_main, args=(str(path), child, flush_messages),
                                 name="rig-replay-reader", daemon=True)
        self._proc.start()
        child.close()
        self.scan: ScanResult | None = None
        self.first: dict[str, Any] | None = None
        self.pieces: list[Piece] = []
        self._early: list[Piece] = []
        self._done = False

    def _recv(self) -> tuple[Any, ...]:
        try:
            msg: tuple[Any, ...] = self._conn.recv()
        except EOFError:
            self._proc.join(5.0)
            raise RecordingError(f"{self.path}: reader process ended without a result "
                                 f"(exit code {self._proc.exitcode})") from None
        if msg[0] == "error":
            self._done = True
            raise msg[1]
        return msg

    def head(self) -> tuple[ScanResult, dict[str, Any] | None]:
        while True:
            msg = self._recv()
            if msg[0] == "head":
                return msg[1], msg[2]
            if msg[0] == "piece":
                self._early.append(msg[1])

    def __iter__(self) -> Iterator[Piece]:
        for piece in self._early:
            self.pieces.append(piece)
            yield piece
        self._early = []
        while not self._done:
            msg = self._recv()
            if msg[0] == "piece":
                self.pieces.append(msg[1])
                yield msg[1]
            elif msg[0] == "end":
                self.scan = msg[1]
                self._done = True

    def close(self) -> None:
        self._conn.close()
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.terminate()   # our own child, by its handle
            self._proc.join(2.0)


def idle_cpu() -> bool:
    """A second CPU is free for the reader (1-minute load average below cores - 1);
    on a busy machine the reader would only slow the loop down."""
    try:
        return os.getloadavg()[0] < (os.cpu_count() or 1) - 1
    except OSError:
        return False

