"""A second process on the bus for the smoke tests: echo and flow-controlled sink.

    python -m tests.socketcan.peer --channel vcan0

- a frame with id ``PING_ID`` is answered at once with ``PONG_ID`` and the same data;
- ``STREAM_ID`` frames carry a 32-bit little-endian sequence number in bytes 0..3; the
  peer checks they arrive in order without gaps and acknowledges every ``WINDOW``-th (and
  the last of a burst flagged by byte 4 = 1) with ``ACK_ID`` carrying that sequence number;
- ``STOP_ID`` ends it; it then prints one line ``stream received=N lost=L reordered=R``.
"""

from __future__ import annotations

import argparse
import struct

import can

PING_ID, PONG_ID, STREAM_ID, ACK_ID, STOP_ID = 0x7E0, 0x7E1, 0x7E2, 0x7E3, 0x7EF
WINDOW = 32


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--channel", default="vcan0")
    args = parser.parse_args()
    received = lost = reordered = 0
    expected = 0
    with can.Bus(interface="socketcan", channel=args.channel,
                 can_filters=[{"can_id": i, "can_mask": 0x7FF}
                              for i in (PING_ID, STREAM_ID, STOP_ID)]) as bus:
        print("peer ready", flush=True)
        while True:
            msg = bus.recv(timeout=30.0)
            if msg is None or msg.arbitration_id == STOP_ID:
                break
            if msg.arbitration_id == PING_ID:
                bus.send(can.Message(arbitration_id=PONG_ID, data=msg.data,
                                     is_extended_id=False))
            elif msg.arbitration_id == STREAM_ID:
                (seq,) = struct.unpack_from("<I", msg.data)
                received += 1
                if seq > expected:
                    lost += seq - expected
                elif seq < expected:
                    reordered += 1
                expected = seq + 1
                if (seq + 1) % WINDOW == 0 or msg.data[4] == 1:
                    bus.send(can.Message(arbitration_id=ACK_ID, data=msg.data[:4],
                                         is_extended_id=False))
    print(f"stream received={received} lost={lost} reordered={reordered}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
