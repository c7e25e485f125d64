"""Rewrite a recording with valid MCAP framing and CRCs but changed contents (hostile
input that passes the format's own checks)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

Change = Callable[[bytes], bytes]


def chunk_spans(recording: Path) -> list[tuple[int, int]]:
    """(first byte, end) of each chunk of ``recording``, in file order.  Tests cut, corrupt
    and fill files relative to these, not to the file's size: the design attachment before
    the chunks is most of a short recording (0.1 MB for a one-layer bank, 1.8 MB for the
    built-in layered one)."""
    from mcap.reader import make_reader

    with recording.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted((c.chunk_start_offset, c.chunk_start_offset + c.chunk_length)
                  for c in summary.chunk_indexes)


def rewrite(src: Path, dst: Path, topic: str, change: Change, *, every: bool = False,
            attachments: dict[str, bytes] | None = None) -> Path:
    """Copy the recording ``src`` to ``dst`` with the first (``every``: each) payload on
    ``topic`` changed and the attachments named in ``attachments`` replaced."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with src.open("rb") as f, dst.open("wb") as g:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        w = Writer(g)
        w.start(profile="", library="test")
        for sc in summary.schemas.values():
            w.register_schema(sc.name, sc.encoding, sc.data)
        chans = {c.id: w.register_channel(c.topic, c.message_encoding, c.schema_id)
                 for c in summary.channels.values()}
        for m in reader.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        for a in reader.iter_attachments():
            data = (attachments or {}).get(a.name, a.data)
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, data)
        done = False
        for _, ch, msg in reader.iter_messages(log_time_order=False):
            data = msg.data
            if ch.topic == topic and (every or not done):
                data, done = change(data), True
            w.add_message(chans[ch.id], msg.log_time, data, msg.publish_time, msg.sequence)
        w.finish()
    return dst
