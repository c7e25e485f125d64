"""Generate :mod:`rig.wire.dbc_constants` and :mod:`rig.wire.dbc_codec` from ``rig/wire/rig.dbc``.

    python -m rig.wire.generate            # rewrite both modules in rig/wire
    python -m rig.wire.generate --check    # exit 1 if a checked-in module is stale
    python -m rig.wire.generate --dbc other.dbc --out-dir DIR   # e.g. to try a DBC change

The DBC owns every number of the protocol: frame IDs and lengths, each signal's bit
position, width, signedness, scale, range and unit, the ``VAL_`` tables, and as
attributes each frame's cycle time and send type (``GenMsgCycleTime`` [ms],
``GenMsgSendType``), the E2E protection (network: ``E2EProfile``, the CRC-8
polynomial, init and final XOR, the counter's maximum; per frame: its CRC and counter
signals) and, per signal, what the encoder does with a value outside the range
(``CodecOutOfRange``: ``Clamp``, the default, or ``Wrap`` for a tick count).  This
generator reads it with cantools (the reference DBC parser; a development dependency,
not needed at run time) and writes

- :mod:`rig.wire.dbc_constants`: the numbers as plain constants, the enumerations as
  ``IntEnum`` classes and each frame's ``struct`` layout;
- :mod:`rig.wire.dbc_codec`: the codec itself, per frame a frame class (one attribute
  per signal) and a codec class whose ``encode`` / ``decode`` have the DBC's numbers
  written in as literals (clamping, range mask, E2E CRC; behaviour described in
  :mod:`rig.wire.protocol`).  Layouts the generated code cannot express (offsets,
  big-endian signals, signals neither byte-aligned nor inside one byte, a range that
  does not fit the bits) are refused with the signal named.

``tests/test_wire_generated.py`` regenerates both into a temporary directory and requires
no difference, and proves with a changed DBC that the codec's numbers come from it.

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
CODEC_PATH = Path(__file__).with_name("dbc_codec.py")

#: DBC unit -> attribute suffix (SI)
UNIT_SUFFIX = {"": "", "m": "_m", "N": "_n", "m/s": "_mps", "m/s^2": "_mps2", "Pa": "_pa",
               "s": "_s"}
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


#: signal attribute naming the bits of a bit-flag signal, from bit 0 up, comma-separated
#: (an empty name leaves that bit unnamed): generated as an ``IntFlag`` named like the signal
BIT_FLAGS_ATTRIBUTE = "BitFlags"


def _bit_flags(sig: Any) -> list[str]:
    """The bit names of a signal's ``BitFlags`` attribute ([] if it has none); refuses
    more names than the signal has bits and names that are not Python identifiers."""
    attr = sig.dbc.attributes.get(BIT_FLAGS_ATTRIBUTE) if sig.dbc is not None else None
    if attr is None or not str(attr.value).strip():
        return []
    names = [n.strip() for n in str(attr.value).split(",")]
    if len(names) > sig.length:
        raise ValueError(f"{sig.name}: {BIT_FLAGS_ATTRIBUTE} names {len(names)} bits, "
                         f"the signal has {sig.length}")
    bad = [n for n in names if n and not n.isidentifier()]
    if bad:
        raise ValueError(f"{sig.name}: {BIT_FLAGS_ATTRIBUTE} bit names {bad} are not "
                         "identifiers")
    return names


def generate(dbc_path: Path = DBC_PATH) -> str:
    """The source of :mod:`rig.wire.dbc_constants` for ``dbc_path``."""
    import cantools

    db: Any = cantools.database.load_file(str(dbc_path), strict=True)
    out = [f'"""Generated from {dbc_path.name} by ``python -m rig.wire.generate``: do not '
           'edit.\n\nEvery number of the CAN protocol, as the DBC defines it (see the '
           'generator\'s\ndocstring for the naming).\n"""',
           "", "from __future__ import annotations", "", "from enum import IntEnum, IntFlag",
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
    for msg in sorted(db.messages, key=lambda m: m.frame_id):
        for sig in msg.signals:
            bits = _bit_flags(sig)
            if not bits:
                continue
            out.append(f"class {sig.name}(IntFlag):")
            out.append(f'    """DBC ``{BIT_FLAGS_ATTRIBUTE}`` of {msg.name}.{sig.name} (its '
                       'comment says what a set bit means)."""')
            out.append("")
            out += [f"    {label} = {1 << bit}" for bit, label in enumerate(bits) if label]
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


# ----------------------------------------------------------------- the codec module

#: the DBC signal attribute that says what the encoder does with an out-of-range value
OUT_OF_RANGE_ATTRIBUTE = "CodecOutOfRange"
_WIDTH = 100  # ruff's line length


def _wrapped(head: str, items: list[str], tail: str, indent: int,
             sep: str = ",") -> list[str]:
    """``head + ", ".join(items) + tail`` (or `` | `` with ``sep="|"``) as lines of at
    most 100 characters, the continuation lines aligned after ``head``."""
    first = " " * indent + head
    one = first + (", " if sep == "," else " | ").join(items) + tail
    if len(one) <= _WIDTH:
        return [one]
    cont = " " * len(first)
    lines, line = [], first
    for i, item in enumerate(items):
        piece = item + ((sep if sep == "," else " |") if i < len(items) - 1 else tail)
        if line not in (first, cont) and len(line) + 1 + len(piece) > _WIDTH:
            lines.append(line)
            line = cont
        line += ("" if line in (first, cont) else " ") + piece
    lines.append(line)
    return lines


def _crc_start(frame_id: int, poly: int, init: int) -> int:
    """CRC-8 state after the two data-ID bytes (low byte first), before the final XOR."""
    s = init
    for byte in (frame_id & 0xFF, (frame_id >> 8) & 0xFF):
        s ^= byte
        for _ in range(8):
            s = ((s << 1) ^ poly) & 0xFF if s & 0x80 else (s << 1) & 0xFF
    return s


def _dbc_line(sig: Any) -> str:
    """The signal as its ``SG_`` line in the DBC reads (for comments)."""
    sign = "-" if sig.is_signed else "+"
    scale = sig.scale if sig.scale != int(sig.scale) else int(sig.scale)
    lo = sig.minimum if sig.minimum != int(sig.minimum) else int(sig.minimum)
    hi = sig.maximum if sig.maximum != int(sig.maximum) else int(sig.maximum)
    return (f'{sig.name} : {sig.start}|{sig.length}@1{sign} ({scale},{sig.offset}) '
            f'[{lo}|{hi}] "{sig.unit or ""}"')


class _Sig:
    """What the codec generator needs to know of one signal (counter and CRC apart)."""

    def __init__(self, msg: Any, sig: Any, bit: int, shared: bool) -> None:
        where = f"{msg.name}.{sig.name}"
        if sig.offset != 0:
            raise ValueError(f"{where}: offsets are not supported (offset {sig.offset})")
        self.sig = sig
        self.attr = attr_name(sig)
        self.bit = bit
        self.physical = is_physical(sig)
        self.shift = sig.start % 8 if shared else None
        self.mask = (1 << sig.length) - 1
        self.raw_lo = (-(1 << (sig.length - 1))) if sig.is_signed else 0
        self.raw_hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else self.mask
        self.dbc_raw_min = round(sig.minimum / sig.scale)
        self.dbc_raw_max = round(sig.maximum / sig.scale)
        if not self.raw_lo <= self.dbc_raw_min <= self.dbc_raw_max <= self.raw_hi:
            raise ValueError(f"{where}: DBC range [{sig.minimum}, {sig.maximum}] does not "
                             f"fit {sig.length} bits")
        self.choices = tuple(sorted(int(v) for v in sig.choices)) if sig.choices else None
        if self.choices and not (sig.minimum <= self.choices[0]
                                 and self.choices[-1] <= sig.maximum):
            raise ValueError(f"{where}: VAL_ values outside the DBC range")
        self.boolean = (sig.length == 1 and not sig.is_signed and not self.physical
                        and self.choices is None)
        attrs = sig.dbc.attributes if sig.dbc is not None else {}
        policy = "Clamp"
        if OUT_OF_RANGE_ATTRIBUTE in attrs:
            a = attrs[OUT_OF_RANGE_ATTRIBUTE]
            value = a.value
            policy = a.definition.choices[value] if isinstance(value, int) else str(value)
        if policy not in ("Clamp", "Wrap"):
            raise ValueError(f"{where}: {OUT_OF_RANGE_ATTRIBUTE} {policy!r} (Clamp or Wrap)")
        self.wrap = policy == "Wrap"
        if self.wrap and (self.physical or sig.is_signed or self.choices is not None
                          or (self.dbc_raw_min, self.dbc_raw_max) != (0, self.mask)):
            raise ValueError(f"{where}: only an unsigned integer over its whole raw range "
                             "can wrap")

    def lit(self, x: float) -> str:
        return _num(x, self.physical)

    def encode_check(self) -> list[str]:
        """Statements clamping the parameter into the DBC range and flagging it."""
        if self.boolean or self.wrap:
            return []
        a, s = self.attr, self.sig
        lo, hi = self.lit(s.minimum), self.lit(s.maximum)
        out = [f"        if not {lo} <= {a} <= {hi}:",
               f"            m |= {1 << self.bit:#x}  # {s.name}"]
        if self.physical:
            out += [f"            if {a} < {lo}:", f"                {a} = {lo}",
                    f"            elif {a} > {hi}:", f"                {a} = {hi}",
                    "            else:  # NaN", f"                {a} = 0.0"]
        else:
            out.append(f"            {a} = {lo} if {a} < {lo} else {hi}")
        if self.choices is not None:
            out += _wrapped(f"        elif {a} not in {{", [str(c) for c in self.choices],
                            "}:", 0)
            out.append(f"            m |= {1 << self.bit:#x}  # {s.name}: no VAL_ value")
        return out

    def encode_expr(self) -> str:
        """The raw value, placed at its shift inside a shared byte."""
        a = self.attr
        if self.boolean:
            return f"({1 << (self.shift or 0):#x} if {a} else 0)"
        if self.wrap:
            raw = f"{a} % {self.mask + 1}"
        elif self.physical:
            raw = f"round({a} / {float(self.sig.scale)!r})"
        else:
            raw = a
        if self.shift:
            return f"({raw} << {self.shift})"
        return f"({raw})" if self.shift is not None and self.wrap else raw

    def raw_expr(self, var: str) -> str:
        """The raw value from the unpacked struct field ``var``."""
        if self.shift is None:
            return var
        if self.shift == 0:
            return f"{var} & {self.mask:#x}"
        if self.shift + self.sig.length == 8:
            return f"{var} >> {self.shift}"
        return f"({var} >> {self.shift}) & {self.mask:#x}"

    def decode_check(self, raw: str) -> list[str]:
        """Statements flagging a raw value outside the DBC range or without a VAL_ value
        (none when every raw value of the field is in range)."""
        if self.choices is not None:
            test = _wrapped(f"        if {raw} not in {{", [str(c) for c in self.choices],
                            "}:", 0)
            return [*test, f"            m |= {1 << self.bit:#x}  # {self.sig.name}"]
        if self.raw_lo < self.dbc_raw_min or self.dbc_raw_max < self.raw_hi:
            return [f"        if not {self.dbc_raw_min} <= {raw} <= {self.dbc_raw_max}:",
                    f"            m |= {1 << self.bit:#x}  # {self.sig.name}"]
        return []


def _crc_lines(var: str, start: int, xorout: int, target: str) -> list[str]:
    """Inline E2E CRC over bytes 1..7 of ``var``, two bytes per table lookup."""
    return [f"        w1, w2, w3, b7 = _CRC_WORDS({var})",
            f"        s = _T2[{start << 8:#06x} ^ w1]",
            "        s = _T2[(s << 8) ^ w2]",
            "        s = _T2[(s << 8) ^ w3]",
            f"        {target}_T1[s ^ b7] ^ {xorout:#04x}"]


def _codec_frame(msg: Any, poly: int, init: int, xorout: int) -> list[str]:
    """Frame class, codec class for one message."""
    name, prefix = msg.name, snake(msg.name).upper()
    attrs = {k: a.value for k, a in msg.dbc.attributes.items()}
    crc_name = attrs.get("E2ECrcSignal") or f"{name}_CRC"
    counter_name = attrs.get("E2ECounterSignal") or f"{name}_Counter"
    crc_sig = msg.get_signal_by_name(crc_name)
    counter_sig = msg.get_signal_by_name(counter_name)
    if msg.length != 8 or (crc_sig.start, crc_sig.length) != (0, 8) \
            or (counter_sig.start, counter_sig.length) != (8, 4):
        raise ValueError(f"{name}: the E2E scheme needs 8 bytes, the CRC in byte 0 and the "
                         "counter in the low nibble of byte 1")
    _fmt, groups = layout(msg)
    plain = sorted((s for s in msg.signals if s not in (crc_sig, counter_sig)),
                   key=lambda s: s.start)
    bit_of = {s.name: i for i, s in enumerate(plain)}
    sigs: dict[str, _Sig] = {}
    fields: list[tuple[str, list[Any]]] = []  # (decode variable, signals in the field)
    for group in groups:
        shared = len(group) > 1 or group[0].length < 8
        if group == [crc_sig]:
            var = "crc"
        elif shared:
            var = f"b{group[0].start // 8}"
        else:
            var = f"r_{snake(group[0].name)}"
        for s in group:
            if s not in (crc_sig, counter_sig):
                sigs[s.name] = _Sig(msg, s, bit_of[s.name], shared)
        fields.append((var, group))
    ordered = [sigs[s.name] for s in plain]
    senders = ", ".join(msg.senders)
    receivers = ", ".join(sorted({r for s in msg.signals for r in s.receivers}))
    cycle = f"every {msg.cycle_time} ms" if msg.cycle_time else "on event"
    send = msg.send_type or "Cyclic"
    out: list[str] = []
    # frame class
    out.append(f"class {name}(Frame):")
    out.append(f'    """{name} as decoded: ``counter``, ``range_mask`` and one attribute per '
               'signal\n    (SI units)."""')
    out.append("")
    out += _wrapped("__slots__ = (", [repr(s.attr) for s in sorted(ordered,
                                                                     key=lambda s: s.attr)],
                    ")", 4)
    out += _wrapped("FIELDS = (", [repr(s.attr) for s in ordered], ")", 4)
    for s in ordered:
        out.append(f"    #: {_dbc_line(s.sig)}")
        out.append(f"    {s.attr}: {'float' if s.physical else 'int'}")
    out += ["", ""]
    # codec class
    params = [f"{s.attr}: {'float' if s.physical else 'int'}" for s in ordered]
    out.append(f"class {name}Codec(Codec):")
    out.append(f'    """{name} {msg.frame_id:#05x}, {senders} -> {receivers}, {send} '
               f'{cycle}."""')
    out.append("")
    out.append(f"    FRAME_ID = {msg.frame_id:#05x}")
    out.append(f"    NAME = {name!r}")
    out.append(f"    FRAME_TYPE = {name}")
    out.append(f"    COUNTER_SIGNAL = {counter_name!r}")
    out.append("    SIGNALS = (")
    for s in ordered:
        g = s.sig
        items = [repr(s.attr), repr(g.name), str(g.start), str(g.length), str(g.is_signed),
                 s.lit(g.scale), s.lit(g.minimum), s.lit(g.maximum)]
        if s.choices is not None:
            items.append("(" + ", ".join(str(c) for c in s.choices) + ")")
        out += _wrapped("SignalSpec(", items, "),", 8)
    out.append("    )")
    out.append("")
    out += _wrapped("def encode(", ["self", "buf: bytearray | memoryview", "counter: int",
                                    *params], ") -> int:", 4)
    out.append('        """Counter (modulo 16), signals and CRC into ``buf``; the mask of '
               'clamped\n        or undefined values (bit i = ``FIELDS[i]``)."""')
    out.append("        m = 0")
    for s in ordered:
        out += s.encode_check()
    pack_args = ["buf", "0"]
    for var, group in fields:
        if group == [crc_sig]:
            pack_args.append("0")
            continue
        parts = [f"(counter & {(1 << g.length) - 1:#x})" if g is counter_sig
                 else sigs[g.name].encode_expr() for g in group]
        if len(parts) == 1:
            pack_args.append(parts[0])
            continue
        out += _wrapped(f"{var} = (", parts, ")", 8, sep="|")
        pack_args.append(var)
    out += _wrapped(f"_{prefix}_PACK(", pack_args, ")", 8)
    out += _crc_lines("buf", _crc_start(msg.frame_id, poly, init), xorout, "buf[0] = ")
    out.append("        return m")
    out.append("")
    out.append(f"    def decode(self, data: bytes | bytearray | memoryview, out: {name}"
               ") -> DecodeStatus:")
    out.append('        """Check length and CRC, then fill ``out``; never raises."""')
    out.append(f"        if len(data) != {msg.length}:")
    out.append("            return _BAD_LENGTH")
    out += _wrapped("", [v for v, _ in fields], f" = _{prefix}_UNPACK(data)", 8)
    out += _crc_lines("data", _crc_start(msg.frame_id, poly, init), xorout, "if crc != ")
    out[-1] += ":"
    out.append("            return _BAD_CRC")
    checks: list[str] = []
    values: dict[str, str] = {}
    for var, group in fields:
        for g in group:
            if g is crc_sig:
                continue
            if g is counter_sig:
                values["counter"] = f"{var} & {(1 << g.length) - 1:#x}"
                continue
            s = sigs[g.name]
            raw = s.raw_expr(var)
            check = s.decode_check("RAW")
            if check and raw != var:  # a shared byte: take the value out once
                checks.append(f"        {s.attr} = {raw}")
                raw = s.attr
            checks += [c.replace("RAW", raw) for c in check]
            values[s.attr] = f"{raw} * {float(g.scale)!r}" if s.physical else raw
    if checks:
        out.append("        m = 0")
        out += checks
    out.append(f"        out.counter = {values['counter']}")
    for s in ordered:
        out.append(f"        out.{s.attr} = {values[s.attr]}")
    if checks:
        out.append("        out.range_mask = m")
        out.append("        return _OUT_OF_RANGE if m else _OK")
    else:
        out.append("        out.range_mask = 0  # every raw value of this frame is in range")
        out.append("        return _OK")
    out += ["", ""]
    return out


def generate_codec(dbc_path: Path = DBC_PATH) -> str:
    """The source of :mod:`rig.wire.dbc_codec` for ``dbc_path``."""
    import cantools

    db: Any = cantools.database.load_file(str(dbc_path), strict=True)
    net = {k: a.value for k, a in db.dbc.attributes.items()}
    poly, init = int(net["E2ECrcPolynomial"]), int(net["E2ECrcInit"])
    xorout = int(net["E2ECrcXorOut"])
    messages = sorted(db.messages, key=lambda m: m.frame_id)
    out = [f'"""Generated from {dbc_path.name} by ``python -m rig.wire.generate``: do not '
           'edit.\n\nThe CAN codec: per frame of the DBC its frame class and its codec, '
           '``encode`` and\n``decode`` written out with the DBC\'s bit positions, scales, '
           'ranges and ``VAL_``\nvalues as literals (behaviour: :mod:`rig.wire.protocol`; '
           'shared parts:\n:mod:`rig.wire.codec_base`; E2E CRC tables: '
           ':mod:`rig.wire.e2e`).\n"""',
           "", "from __future__ import annotations", "", "import struct",
           "from collections.abc import Mapping", "from typing import Final", "",
           "from rig.wire.codec_base import Codec, DecodeStatus, Frame, SignalSpec",
           "from rig.wire.e2e import CRC8_TABLE, CRC8_TABLE2", "",
           "_OK: Final = DecodeStatus.OK",
           "_BAD_LENGTH: Final = DecodeStatus.BAD_LENGTH",
           "_BAD_CRC: Final = DecodeStatus.BAD_CRC",
           "_OUT_OF_RANGE: Final = DecodeStatus.OUT_OF_RANGE",
           "_T1: Final = CRC8_TABLE",
           "_T2: Final = CRC8_TABLE2",
           "#: bytes 1-2, 3-4 and 5-6 as big-endian words and byte 7: the CRC's table lookups",
           '_CRC_WORDS: Final = struct.Struct(">xHHHB").unpack_from']
    for msg in messages:
        prefix = snake(msg.name).upper()
        fmt, _ = layout(msg)
        out.append(f"_{prefix}_PACK: Final = struct.Struct({fmt!r}).pack_into")
        out.append(f"_{prefix}_UNPACK: Final = struct.Struct({fmt!r}).unpack")
    out += ["", ""]
    for msg in messages:
        out += _codec_frame(msg, poly, init, xorout)
    names = [snake(m.name).upper() for m in messages]
    out += [f"{p}: Final = {m.name}Codec()" for p, m in zip(names, messages, strict=True)]
    out.append("#: frame ID -> codec")
    out += _wrapped("CODECS: Final[Mapping[int, Codec]] = {",
                    [f"{p}.FRAME_ID: {p}" for p in names], "}", 0)
    return "\n".join(out) + "\n"


def outputs(dbc_path: Path = DBC_PATH) -> dict[Path, str]:
    """Every generated module's path and its source for ``dbc_path``."""
    return {OUT_PATH: generate(dbc_path), CODEC_PATH: generate_codec(dbc_path)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rig.wire.generate",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="compare with the checked-in modules instead of writing them")
    parser.add_argument("--dbc", type=Path, default=DBC_PATH,
                        help="the DBC to read (default: rig/wire/rig.dbc)")
    parser.add_argument("--out-dir", type=Path, default=None,
                        help="write the modules into this directory instead of rig/wire")
    args = parser.parse_args(argv)
    texts = outputs(args.dbc)
    if args.out_dir is not None:
        if not args.out_dir.is_dir():
            parser.error(f"--out-dir {args.out_dir}: not a directory")
        texts = {args.out_dir / p.name: text for p, text in texts.items()}
    if args.check:
        stale = [p for p, text in texts.items() if p.read_text(encoding="utf-8") != text]
        for path in stale:
            print(f"{path} is stale: run python -m rig.wire.generate", file=sys.stderr)
        return 1 if stale else 0
    for path, text in texts.items():
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
