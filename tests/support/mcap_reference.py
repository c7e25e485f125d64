"""An independent reader of recordings, for tests: the ``mcap`` library's own indexed
reader (``mcap.reader.make_reader``, summary and chunk indexes) and plain ``json``,
following only docs/recording.md -- none of the project's reading code
(``rig.recording.scan``, ``rig.recording.run_data``).

The production reader (:func:`rig.recording.run_data.read_run`, built on the scanner
replay and the report use) is checked against it: every CAN frame, tick record and
event equal, in the same order.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from jsonschema import Draft202012Validator
from mcap.reader import make_reader

#: the documented channels (docs/recording.md)
FRAME_TOPICS = {"/can/rx": True, "/can/tx": False}        # topic -> received
RECORD_TOPICS = ("/rig/signals", "/controller/internals", "/rig/timing")
EVENT_TOPIC = "/rig/events"
PARTS_KEY = "record_parts"

#: ("frame", t_ns, tick, id, data, is_rx, error_frame, extended_id) |
#: ("record", t_ns, tick, record without t_ns) | ("event", t_ns, tick, kind, detail)
Item = tuple[Any, ...]


def reference_items(paths: Sequence[Path], *, validate: bool = True) -> list[Item]:
    """The items of a complete run written to ``paths`` (its segments, in order), in
    recording order.  Each message is checked against the JSON schema of its channel
    (``validate``); the messages of a tick record (same sequence) are merged."""
    items: list[Item] = []
    merging: tuple[int, dict[str, Any], list[int]] | None = None  # seq, record, parts
    for path in paths:
        with open(path, "rb") as f:
            reader = make_reader(f)
            validators: dict[int, Draft202012Validator] = {}
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                msg = json.loads(message.data)
                if validate:
                    assert schema is not None and schema.encoding == "jsonschema"
                    v = validators.get(schema.id)
                    if v is None:
                        v = validators[schema.id] = Draft202012Validator(
                            json.loads(schema.data))
                    v.validate(msg)
                topic = channel.topic
                if topic in RECORD_TOPICS:
                    if merging is not None and merging[0] == message.sequence:
                        bad = merging[1].get("nonfinite", []) + msg.get("nonfinite", [])
                        merging[1].update(msg)
                        if bad:
                            merging[1]["nonfinite"] = bad
                        merging[2][1] += 1
                        continue
                    parts = [msg.pop(PARTS_KEY, 1), 1]
                    merging = (message.sequence, msg, parts)
                    items.append(("record", msg["t_ns"], msg["tick"], msg))
                    continue
                merging = None
                if topic in FRAME_TOPICS:
                    items.append(("frame", msg["t_ns"], msg["tick"], msg["id"],
                                  bytes.fromhex(msg["data"]), FRAME_TOPICS[topic],
                                  msg.get("error_frame", False),
                                  msg.get("extended_id", False)))
                    assert msg["dlc"] == len(items[-1][4])
                elif topic == EVENT_TOPIC:
                    items.append(("event", msg["t_ns"], msg["tick"], msg["kind"],
                                  json.loads(msg["detail_json"])))
    out: list[Item] = []
    for item in items:
        if item[0] == "record":
            record = dict(item[3])
            del record["t_ns"]
            for key in record.get("nonfinite", ()):   # the documented number -> None
                v = record[key]
                record[key] = ([None if x == -1e308 else x for x in v] if isinstance(v, list)
                               else None if v == -1e308 else v)
            out.append(("record", item[1], item[2], record))
        else:
            out.append(item)
    return out


def items_of_run(run: Any) -> list[Item]:
    """The same tuples from a :class:`rig.recording.run_data.RunData` (its timeline)."""
    out: list[Item] = []
    for r in run.timeline():
        if hasattr(r, "arbitration_id"):
            out.append(("frame", r.t_ns, r.tick, r.arbitration_id, r.data, r.is_rx,
                        r.is_error_frame, r.is_extended_id))
        elif hasattr(r, "kind"):
            out.append(("event", r.t_ns, r.tick, r.kind, r.detail))
        else:
            out.append(("record", r.t_ns, r.tick, r.data))
    return out
