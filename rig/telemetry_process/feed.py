"""The feed from the loop process to the telemetry process: the recording's item stream.

The pipe carries the items of :mod:`rig.recording.codec` (``u32 size, u8 kind`` then the
payload): ``ITEM_LAYOUT`` once per process (and again when the layout changes), the
packed ``ITEM_TICK`` records exactly as the recording writer gets them, ``ITEM_EVENT``
and ``ITEM_END``.  Two kinds are the telemetry process's own:

==================  ==========================================================
``ITEM_STATUS``     pickle of the service's status dict (every
                    :data:`STATUS_PERIOD_S`, built off the loop thread)
``ITEM_REPLY``      pickle of ``(command id, accepted, message)``: the loop's
                    answer to an operator command
==================  ==========================================================

Pickle goes one way only, from the loop process (trusted) to the telemetry process.
What the telemetry process sends back (commands, its own state) is JSON lines on its
stdout, parsed and validated again by the loop process (:mod:`rig.telemetry_process.link`):
the process that faces the network is not trusted.

The stream starts with :data:`FEED_MAGIC`, ``u32`` length and a JSON header
(:func:`encode_feed_header`).
"""

from __future__ import annotations

import json
import pickle
import struct
from collections.abc import Mapping
from typing import Any, Final

from rig.recording.codec import ITEM_HEAD

__all__ = ["FEED_MAGIC", "ITEM_REPLY", "ITEM_STATUS", "MAX_LINE_BYTES", "STATUS_PERIOD_S",
           "decode_reply", "decode_status", "encode_feed_header", "encode_reply",
           "encode_status"]

FEED_MAGIC: Final = b"RIGTEL01"
ITEM_STATUS: Final = 16
ITEM_REPLY: Final = 17
#: the loop process publishes its status this often [s]; status queries are answered
#: from the last one (at most this old, plus the pipe)
STATUS_PERIOD_S: Final = 0.2
#: longest line the loop process accepts from the telemetry process (longer: dropped)
MAX_LINE_BYTES: Final = 16384

_U32: Final = struct.Struct("<I")


def encode_feed_header(header: Mapping[str, Any]) -> bytes:
    blob = json.dumps(header, sort_keys=True).encode()
    return FEED_MAGIC + _U32.pack(len(blob)) + blob


def _item(kind: int, payload: bytes) -> bytes:
    return ITEM_HEAD.pack(ITEM_HEAD.size + len(payload), kind) + payload


def encode_status(status: Mapping[str, Any]) -> bytes:
    return _item(ITEM_STATUS, pickle.dumps(dict(status), protocol=pickle.HIGHEST_PROTOCOL))


def encode_reply(command_id: int, accepted: bool, message: str) -> bytes:
    return _item(ITEM_REPLY, pickle.dumps((int(command_id), bool(accepted), str(message)),
                                          protocol=pickle.HIGHEST_PROTOCOL))


def decode_status(item: bytes | memoryview) -> dict[str, Any]:
    value = pickle.loads(item[ITEM_HEAD.size:])
    if not isinstance(value, dict):
        raise ValueError("status item is not a dict")
    return value


def decode_reply(item: bytes | memoryview) -> tuple[int, bool, str]:
    cid, accepted, message = pickle.loads(item[ITEM_HEAD.size:])
    return int(cid), bool(accepted), str(message)
