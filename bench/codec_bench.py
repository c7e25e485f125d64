"""Per-frame encode / decode time of the generated codec (rig.wire.protocol) vs cantools.

``run() -> list[dict]``: one row per frame type and direction with the median time per
frame over several batches.  Ours includes the E2E CRC (compute on encode, check on
decode) and the range checks; cantools' encode is timed without computing the CRC (it
has none), so the ratio understates our advantage.  ``python -m bench.codec_bench``
prints the table.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import cantools

from bench.timing import median_call_ns
from rig.wire.protocol import CODECS

ROOT = Path(__file__).resolve().parents[1]

NAME = "codec"
TITLE = "CAN codec: rig.wire.protocol vs cantools, median per frame"
SAMPLE = {
    "ValveCommand": {"ValveCommand_Counter": 5, "Enable": 1, "Lifecycle": 1,
                     "SpoolCommand": 0.4321, "ForceReference": -1234.5,
                     "SensorCounterEcho": 4},
    "FaultReport": {"FaultReport_Counter": 5, "FaultState": 2, "FaultCode": 11,
                    "FaultTick": 123456, "FaultDetail": 3},
    "SensorData": {"SensorData_Counter": 5, "SensorStatus": 0, "Rattlespace": 0.0123,
                   "LoadCellForce": 2345.5, "SprungAccel": -1.234},
    "RoadPreview": {"RoadPreview_Counter": 5, "PreviewStatus": 0, "RoadVelocity": -0.321,
                    "PreviewLead": 250, "PreviewSensorCounter": 5},
    "RigStatus": {"RigStatus_Counter": 5, "BypassOpen": 0, "WatchdogTripped": 0,
                  "SupplyOk": 1, "SupplyPressure": 10342000, "SpoolPosition": 0.25,
                  "LoadPressure": 1234000},
    "ControllerStatus": {"ControllerStatus_Counter": 5, "State": 1, "ActiveFault": 0,
                         "OverrunCount": 3, "Blending": 0, "WeightSet": 1,
                         "JitterP99": 0.000123},
}


def run(quick: bool = False) -> list[dict[str, Any]]:
    db: Any = cantools.database.load_file(str(ROOT / "rig" / "wire" / "rig.dbc"))
    n, batches = (300, 3) if quick else (3000, 7)
    rows: list[dict[str, Any]] = []
    for codec in CODECS.values():
        msg = db.get_message_by_frame_id(codec.frame_id)
        signals = dict(SAMPLE[codec.name])
        buf = bytearray(8)
        frame = codec.new()
        codec.encode_signals(buf, signals)
        codec.decode(buf, frame)
        args = [getattr(frame, f) for f in codec.FRAME_TYPE.FIELDS]
        counter = frame.counter
        encode = codec.encode
        decode = codec.decode
        data = bytes(buf)
        ref_signals = {**signals, msg.signals[0].name: data[0]}

        def ours_enc(e: Any = encode, b: bytearray = buf, c: int = counter,
                     a: list[Any] = args) -> None:
            e(b, c, *a)

        def ours_dec(d: Any = decode, x: bytes = data, f: Any = frame) -> None:
            d(x, f)

        def ref_enc(m: Any = msg, s: dict[str, Any] = ref_signals) -> None:
            m.encode(s)

        def ref_dec(m: Any = msg, x: bytes = data) -> None:
            m.decode(x, decode_choices=False)

        for op, ours, ref in (("encode", ours_enc, ref_enc), ("decode", ours_dec, ref_dec)):
            t_ours = median_call_ns(ours, n, batches)
            t_ref = median_call_ns(ref, max(n // 10, 30), batches)
            rows.append({"frame": codec.name, "op": op, "ours_us": t_ours / 1e3,
                         "cantools_us": t_ref / 1e3, "speedup": t_ref / t_ours})
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    lines = [TITLE, f"{'frame':<18}{'op':<8}{'ours [us]':>11}{'cantools [us]':>15}"
                    f"{'speedup':>9}"]
    for r in rows:
        lines.append(f"{r['frame']:<18}{r['op']:<8}{r['ours_us']:>11.2f}"
                     f"{r['cantools_us']:>15.2f}{r['speedup']:>8.1f}x")
    return "\n".join(lines)


if __name__ == "__main__":
    print(format_table(run(quick="--quick" in sys.argv)))
