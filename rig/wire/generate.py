"""Generate :mod:`rig.wire.dbc_constants` from ``rig/wire/rig.dbc``.

    python -m rig.wire.generate            # rewrite rig/wire/dbc_constants.py
    python -m rig.wire.generate --check    # exit 1 if the checked-in module is stale

The DBC owns every number of the protocol: frame IDs and lengths, each signal's bit
position, width, signedness, scale, range and unit, the ``VAL_`` tables, and as
attributes each frame's cycle time and send type (``GenMsgCycleTime`` [ms],
``GenMsgSendType``) and the E2E protection (network: ``E2EProfile``, the CRC-8
polynomial, init and final XOR, the counter's maximum; per frame: its CRC and counter
signals).  This
generator reads it with cantools (the reference DBC parser; a development dependency,
not needed at run time) and writes them as plain constants, the enumerations as
``IntEnum`` classes and each frame's ``struct`` layout, so that the hand-optimised codec
in :mod:`rig.wire.protocol` writes no DBC number of its own.  ``tests/test_wire_generated.py``
regenerates into a temporary file and requires no difference.

Names: a signal's constants are ``<FRAME>_<SIGNAL>_<WHAT>`` in upper snake case, e.g.
``SENSOR_DATA_RATTLESPACE_SCALE``; ``SHIFT`` and ``MASK`` place a signal narrower than a
byte inside its byte of the ``struct`` layout.  The attribute names of the decoded frame
objects are the signal names in snake case with the unit appended (``Rattlespace`` [m]
-> ``rattlespace_m``), see :func:`attr_name`.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

DBC_PATH = Path(__file__).with_name("rig.dbc")
OUT_PATH = Path(__file__).with_name("dbc_constants.py")

#: DBC unit -> attribute suffix (SI)
UNIT_SUFFIX = {"": "", "m": "_m", "N": "_n", "m/s^2": "_mps2", "Pa": "_pa", "s": "_s"}
#: VAL_ tables that several signals share, by the enumeration they define
ENUMS = {"LifecycleState": ("ValveCommand", "Lifecycle"),
         "FaultCode": ("FaultReport", "FaultCode"),
         "Blending": ("ControllerStatus", "Blending")}
_STRUCT_CODE = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h",
                (32, False): "I", (32, True): "i"}


def snake(name: str) -> str:
    """``SprungAccel`` -> ``sprung_accel``; ``JitterP99`` -> ``jitter_p99``."""
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", name).lower()


def attr_name(signal: Any) -> str:
    """The frame object's attribute of a DBC signal: snake case + the unit suffix."""
    return snake(signal.name) + UNIT_SUFFIX[signal.unit or ""]


def _num(x: float, physical: bool) -> str:
    """A number as Python source: a float for a physical signal (scaled or with a unit),
    an int for a plain integer one."""
    return repr(float(x)) if physical else repr(int(x))


def is_physical(signal: Any) -> bool:
    """Decoded as a float (a scaled quantity or one with a unit), else as an int."""
    return bool(signal.scale != 1 or signal.offset != 0 or signal.unit)


def layout(message: Any) -> tuple[str, list[list[Any]]]:
    """The frame's ``struct`` format (little endian) and, per struct field, the signals
    in it: one whole signal for a byte-aligned 8/16/32-bit one, else the signals that
    share one byte.  Other layouts are refused (the codec would need bit arithmetic)."""
    by_byte: dict[int, list[Any]] = {}
    fields: list[tuple[int, str, list[Any]]] = []
    for sig in message.signals:
        if sig.byte_order != "little_endian":
            raise ValueError(f"{message.name}.{sig.name}: only little-endian signals")
        if sig.start % 8 == 0 and (sig.length, sig.is_signed) in _STRUCT_CODE:
            fields.append((sig.start // 8, _STRUCT_CODE[(sig.length, sig.is_signed)], [sig]))
        elif sig.start // 8 == (sig.start + sig.length - 1) // 8 and not sig.is_signed:
            by_byte.setdefault(sig.start // 8, []).append(sig)
        else:
            raise ValueError(f"{message.name}.{sig.name}: neither byte-aligned nor "
                             "inside one byte")
    fields += [(b, "B", sigs) for b, sigs in by_byte.items()]
    fields.sort(key=lambda f: f[0])
    fmt, pos, groups = "<", 0, []
    for byte, code, sigs in fields:
        if byte < pos:
            raise ValueError(f"{message.name}: signals overlap at byte {byte}")
        fmt += "x" * (byte - pos) + code
        pos = byte + {"B": 1, "b": 1, "H": 2, "h": 2, "I": 4, "i": 4}[code]
        groups.append(sigs)
    fmt += "x" * (message.length - pos)
    return fmt, groups


def generate(dbc_path: Path = DBC_PATH) -> str:
    """The source of :mod:`rig.wire.dbc_constants` for ``dbc_path``."""
    import cantools

    db: Any = cantools.database.load_file(str(dbc_path), strict=True)
    out = [f'"""Generated from {dbc_path.name} by ``python -m rig.wire.generate``: do not '
           'edit.\n\nEvery number of the CAN protocol, as the DBC defines it (see the '
           'generator\'s\ndocstring for the naming).\n"""',
           "", "from __future__ import annotations", "", "from enum import IntEnum",
           "from typing import Final", "", ""]
    for enum_name, (msg_name, sig_name) in ENUMS.items():
        choices = db.get_message_by_name(msg_name).get_signal_by_name(sig_name).choices
        out.append(f"class {enum_name}(IntEnum):")
        out.append(f'    """DBC ``VAL_`` table of {msg_name}.{sig_name}."""')
        out.append("")
        out += [f"    {label!s} = {int(value)}" for value, label in sorted(choices.items())]
        if enum_name == "FaultCode":
            out += ["", "    @property", "    def description(self) -> str:",
                    '        """What the code means, in plain language for the rig engineer '
                    '(event\n        tables, reports): rig.wire.fault_descriptions."""',
                    "        from rig.wire.fault_descriptions import FAULT_DESCRIPTIONS",
                    "", "        return FAULT_DESCRIPTIONS[self.name]"]
        out += ["", ""]
    net = {k: a.value for k, a in db.dbc.attributes.items()}
    out.append("# E2E protection (network attributes): CRC-8 parameters, counter range")
    out.append(f"E2E_PROFILE: Final = {net['E2EProfile']!r}")
    out.append(f"E2E_CRC_POLYNOMIAL: Final = {int(net['E2ECrcPolynomial']):#04x}")
    out.append(f"E2E_CRC_INIT: Final = {int(net['E2ECrcInit']):#04x}")
    out.append(f"E2E_CRC_XOROUT: Final = {int(net['E2ECrcXorOut']):#04x}")
    out.append(f"E2E_COUNTER_MAX: Final = {int(net['E2ECounterMax'])}")
    out.append("")
    frames = []
    for msg in sorted(db.messages, key=lambda m: m.frame_id):
        prefix = snake(msg.name).upper()
        frames.append(prefix)
        fmt, groups = layout(msg)
        out.append(f"# {msg.name}: sent by {', '.join(msg.senders)}")
        out.append(f"{prefix}_ID: Final = {msg.frame_id:#05x}")
        out.append(f"{prefix}_NAME: Final = {msg.name!r}")
        out.append(f"{prefix}_LENGTH: Final = {msg.length}")
        out.append(f"{prefix}_STRUCT: Final = {fmt!r}")
        attrs = {k: a.value for k, a in msg.dbc.attributes.items()}
        out.append(f"{prefix}_CYCLE_TIME_MS: Final = {int(msg.cycle_time or 0)}")
        out.append(f"{prefix}_SEND_TYPE: Final = {msg.send_type!r}")
        out.append(f"{prefix}_E2E_CRC_SIGNAL: Final = {attrs.get('E2ECrcSignal', '')!r}")
        out.append(f"{prefix}_E2E_COUNTER_SIGNAL: Final = "
                   f"{attrs.get('E2ECounterSignal', '')!r}")
        stems = []
        for group in groups:
            for sig in group:
                stem = snake(sig.name.removeprefix(msg.name + '_')).upper()
                name = f"{prefix}_{stem}"
                out.append(f"{name}_START: Final = {sig.start}")
                out.append(f"{name}_LENGTH: Final = {sig.length}")
                if len(group) > 1 or sig.length < 8:
                    out.append(f"{name}_SHIFT: Final = {sig.start % 8}")
                    out.append(f"{name}_MASK: Final = {(1 << sig.length) - 1:#x}")
                if sig.name.endswith(("_CRC", "_Counter")):
                    if sig.name.endswith("_Counter"):
                        out.append(f"{prefix}_COUNTER_SIGNAL: Final = {sig.name!r}")
                    continue
                stems.append((sig.start, stem))
                out.append(f"{name}_DBC: Final = {sig.name!r}")
                out.append(f"{name}_SIGNED: Final = {sig.is_signed}")
                phys = is_physical(sig)
                out.append(f"{name}_SCALE: Final = {_num(sig.scale, phys)}")
                out.append(f"{name}_MIN: Final = {_num(sig.minimum, phys)}")
                out.append(f"{name}_MAX: Final = {_num(sig.maximum, phys)}")
                out.append(f"{name}_RAW_MIN: Final = {round(sig.minimum / sig.scale)}")
                out.append(f"{name}_RAW_MAX: Final = {round(sig.maximum / sig.scale)}")
                out.append(f"{name}_ATTR: Final = {attr_name(sig)!r}")
                if sig.choices:
                    values = ", ".join(str(int(v)) for v in sorted(sig.choices))
                    out.append(f"{name}_VALUES: Final = frozenset({{{values}}})")
        out.append(f"{prefix}_SIGNALS: Final = {tuple(stem for _, stem in sorted(stems))!r}")
        out.append("")
    out.append("#: frame prefixes in frame-ID order")
    out.append(f"FRAMES: Final = {tuple(frames)!r}")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rig.wire.generate",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="compare with the checked-in module instead of writing it")
    args = parser.parse_args(argv)
    text = generate()
    if args.check:
        if OUT_PATH.read_text(encoding="utf-8") != text:
            print(f"{OUT_PATH} is stale: run python -m rig.wire.generate", file=sys.stderr)
            return 1
        return 0
    OUT_PATH.write_text(text, encoding="utf-8")
    print(f"wrote {OUT_PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
