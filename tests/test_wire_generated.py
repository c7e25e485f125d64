"""rig/wire/dbc_constants.py and rig/wire/dbc_codec.py are generated from rig/wire/rig.dbc
and checked in: the DBC is the one place a protocol number is written."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import cantools
import pytest

from rig.wire import dbc_constants as constants
from rig.wire.generate import (
    CODEC_PATH,
    DBC_PATH,
    OUT_PATH,
    attr_name,
    generate,
    generate_codec,
    main,
)
from rig.wire.protocol import (
    CODECS,
    FAULT_REPORT,
    SENSOR_DATA,
    Blending,
    DecodeStatus,
    FaultCode,
    LifecycleState,
    SensorStatus,
)
from tests.support.crc import ref_encode, with_crc


def test_regenerating_gives_no_difference(tmp_path: Path) -> None:
    assert OUT_PATH.read_text(encoding="utf-8") == generate()
    assert CODEC_PATH.read_text(encoding="utf-8") == generate_codec()
    assert main(["--out-dir", str(tmp_path)]) == 0
    for path in (OUT_PATH, CODEC_PATH):
        assert (tmp_path / path.name).read_text(encoding="utf-8") == \
            path.read_text(encoding="utf-8"), path.name
    assert main(["--check"]) == 0


def test_check_reports_a_stale_module(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--out-dir", str(tmp_path)]) == 0
    capsys.readouterr()
    stale = tmp_path / CODEC_PATH.name
    stale.write_text(stale.read_text(encoding="utf-8").replace("0.005", "0.006"),
                     encoding="utf-8")
    assert main(["--check", "--out-dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "dbc_codec.py is stale" in err and "dbc_constants.py" not in err


def test_generated_codec_module_is_clean() -> None:
    """The generated codec has the do-not-edit header naming the command and no
    hand-written frame code is left in rig.wire.protocol."""
    text = CODEC_PATH.read_text(encoding="utf-8")
    assert text.startswith('"""Generated from rig.dbc by ``python -m rig.wire.generate``: '
                           "do not edit.")
    protocol = (CODEC_PATH.parent / "protocol.py").read_text(encoding="utf-8")
    assert "def encode" not in protocol and "def decode(self, data" not in protocol
    assert "pack_into" not in protocol


def _changed_dbc(tmp_path: Path, *replacements: tuple[str, str]) -> Path:
    text = DBC_PATH.read_text(encoding="utf-8")
    for old, new in replacements:
        assert old in text, old
        text = text.replace(old, new)
    dbc = tmp_path / "rig.dbc"
    dbc.write_text(text, encoding="utf-8")
    return dbc


def _import_codec(tmp_path: Path, dbc: Path) -> ModuleType:
    """Generate the codec of ``dbc`` into ``tmp_path`` and import it (a module of its own,
    next to the checked-in one)."""
    assert main(["--dbc", str(dbc), "--out-dir", str(tmp_path)]) == 0
    name = f"changed_dbc_codec_{abs(hash(str(tmp_path)))}"
    spec = importlib.util.spec_from_file_location(name, tmp_path / CODEC_PATH.name)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[name]
    return module


def test_a_changed_dbc_changes_the_generated_modules(tmp_path: Path) -> None:
    dbc = _changed_dbc(tmp_path, ("SG_ Rattlespace : 16|16@1- (5e-06,0)",
                                  "SG_ Rattlespace : 16|16@1- (1e-05,0)"))
    text = generate(dbc)
    assert "SENSOR_DATA_RATTLESPACE_SCALE: Final = 1e-05" in text
    assert text != OUT_PATH.read_text(encoding="utf-8")
    codec_text = generate_codec(dbc)
    assert "rattlespace_m / 1e-05" in codec_text and "rattlespace_m / 5e-06" not in codec_text
    assert codec_text != CODEC_PATH.read_text(encoding="utf-8")


def test_the_codec_takes_its_numbers_from_the_dbc(tmp_path: Path) -> None:
    """A DBC with Rattlespace at 10 um per bit and +-0.2 m: the codec generated from it
    encodes, clamps and range-checks by those numbers (byte-identical to cantools on the
    changed DBC), where the checked-in one keeps 5 um and +-0.16384 m."""
    dbc = _changed_dbc(tmp_path, ("SG_ Rattlespace : 16|16@1- (5e-06,0) [-0.16384|0.163835]",
                                  "SG_ Rattlespace : 16|16@1- (1e-05,0) [-0.2|0.2]"))
    changed = _import_codec(tmp_path, dbc)
    db: Any = cantools.database.load_file(str(dbc))
    sid = SENSOR_DATA.frame_id
    for rattlespace in (0.01, -0.123456, 0.2, -0.2, 0.0):
        signals = {"SensorData_Counter": 3, "SensorStatus": 1, "Rattlespace": rattlespace,
                   "LoadCellForce": 120.5, "SprungAccel": -2.5}
        buf = bytearray(8)
        assert changed.SENSOR_DATA.encode_signals(buf, signals) == 0
        assert bytes(buf) == ref_encode(db, sid, signals)
    buf, ours = bytearray(8), bytearray(8)
    changed.SENSOR_DATA.encode(buf, 0, 0, 0.01, 0.0, 0.0)
    SENSOR_DATA.encode(ours, 0, 0, 0.01, 0.0, 0.0)
    assert int.from_bytes(buf[2:4], "little", signed=True) == 1000  # 0.01 m / 10 um
    assert int.from_bytes(ours[2:4], "little", signed=True) == 2000  # 0.01 m / 5 um
    # 0.19 m: in range on the changed DBC, clamped (bit 1) on the real one
    assert changed.SENSOR_DATA.encode(buf, 0, 0, 0.19, 0.0, 0.0) == 0
    assert SENSOR_DATA.encode(ours, 0, 0, 0.19, 0.0, 0.0) == 0b10
    assert changed.SENSOR_DATA.encode(buf, 0, 0, 0.25, 0.0, 0.0) == 0b10
    assert int.from_bytes(buf[2:4], "little", signed=True) == 20000
    # decode: raw 20000 is 0.2 m and in range; raw 30000 (0.3 m) is out of the changed
    # range, while every raw value is in range on the real DBC
    for raw, status, mask in ((20000, DecodeStatus.OK, 0),
                              (30000, DecodeStatus.OUT_OF_RANGE, 0b10)):
        data = with_crc(sid, bytes([0, 0x15]) + raw.to_bytes(2, "little", signed=True)
                         + bytes(4))
        frame = changed.SensorData()
        assert changed.SENSOR_DATA.decode(data, frame) is status
        assert frame.range_mask == mask
        assert math.isclose(frame.rattlespace_m, raw * 1e-5)
        ref = db.get_message_by_frame_id(sid).decode(data, decode_choices=False)
        assert frame.rattlespace_m == ref["Rattlespace"]
        real = SENSOR_DATA.new()
        assert SENSOR_DATA.decode(data, real) is DecodeStatus.OK
        assert real.rattlespace_m == raw * 5e-6


def test_the_out_of_range_policy_comes_from_the_dbc(tmp_path: Path) -> None:
    """FaultTick wraps (DBC attribute CodecOutOfRange = Wrap); without the attribute the
    generated encoder clamps it and flags it like any other signal."""
    dbc = _changed_dbc(tmp_path, ('BA_ "CodecOutOfRange" SG_ 129 FaultTick 1;\n', ""))
    changed = _import_codec(tmp_path, dbc)
    tick = 2**32 + 5
    buf = bytearray(8)
    assert FAULT_REPORT.encode(buf, 0, 2, 11, tick, 0) == 0
    assert int.from_bytes(buf[3:7], "little") == 5
    assert changed.FAULT_REPORT.encode(buf, 0, 2, 11, tick, 0) == 0b100
    assert int.from_bytes(buf[3:7], "little") == 2**32 - 1


def test_the_generator_refuses_what_the_codec_cannot_express(tmp_path: Path) -> None:
    dbc = _changed_dbc(tmp_path, ("SG_ LoadCellForce : 32|16@1- (0.5,0)",
                                  "SG_ LoadCellForce : 32|16@1- (0.5,100)"))
    with pytest.raises(ValueError, match=r"SensorData\.LoadCellForce: offsets"):
        generate_codec(dbc)
    dbc = _changed_dbc(tmp_path, ("SG_ SprungAccel : 48|16@1- (0.005,0) [-163.84|163.835]",
                                  "SG_ SprungAccel : 48|16@1- (0.005,0) [-200|200]"))
    with pytest.raises(ValueError, match=r"SensorData\.SprungAccel: DBC range"):
        generate_codec(dbc)


def test_enumerations_are_the_dbc_value_tables() -> None:
    db: Any = cantools.database.load_file(str(DBC_PATH))
    for enum, (msg, sig) in ((LifecycleState, ("ValveCommand", "Lifecycle")),
                             (FaultCode, ("FaultReport", "FaultCode")),
                             (Blending, ("ControllerStatus", "Blending"))):
        choices = db.get_message_by_name(msg).get_signal_by_name(sig).choices
        assert {int(v): str(n) for v, n in choices.items()} == {m.value: m.name for m in enum}
    # every other signal with a VAL_ table uses one of these tables
    for msg_name, sig_name, enum in (("FaultReport", "FaultState", LifecycleState),
                                     ("ControllerStatus", "State", LifecycleState),
                                     ("ControllerStatus", "ActiveFault", FaultCode)):
        choices = db.get_message_by_name(msg_name).get_signal_by_name(sig_name).choices
        assert {int(v) for v in choices} == {int(m) for m in enum}


def test_codecs_take_every_number_from_the_dbc() -> None:
    db: Any = cantools.database.load_file(str(DBC_PATH))
    for frame_id, codec in CODECS.items():
        msg = db.get_message_by_frame_id(frame_id)
        assert msg.name == codec.NAME and msg.length == constants.VALVE_COMMAND_LENGTH
        signals = [s for s in msg.signals if not s.name.endswith(("_CRC", "_Counter"))]
        assert [spec.attr for spec in codec.SIGNALS] == [attr_name(s) for s in signals]
        for spec, sig in zip(codec.SIGNALS, signals, strict=True):
            assert (spec.start_bit, spec.length, spec.signed, spec.scale, spec.minimum,
                    spec.maximum) == (sig.start, sig.length, sig.is_signed, sig.scale,
                                      sig.minimum, sig.maximum)


def test_cycle_times_agree_with_the_configuration() -> None:
    """GenMsgCycleTime of every frame is the rate the service / emulated rig sends it
    at with the default configuration: ValveCommand and SensorData every control tick,
    ControllerStatus (and the latched FaultReport with it) at the heartbeat, RigStatus
    at the emulated rig's status rate."""
    from controller.config import default_config
    from hil.node import DEFAULT_STATUS_RATE_HZ
    from rig.wire import dbc_constants as k

    cfg = default_config()
    db = cantools.database.load_file(str(DBC_PATH))
    cycle = {m.name: m.cycle_time for m in db.messages}
    tick_ms = 1000.0 / cfg.design.sample_rate_hz
    heartbeat_ms = 1000.0 / cfg.safety.heartbeat_hz
    assert cycle["ValveCommand"] == k.VALVE_COMMAND_CYCLE_TIME_MS == tick_ms
    assert cycle["SensorData"] == k.SENSOR_DATA_CYCLE_TIME_MS == tick_ms
    assert cycle["ControllerStatus"] == k.CONTROLLER_STATUS_CYCLE_TIME_MS == heartbeat_ms
    assert cycle["FaultReport"] == k.FAULT_REPORT_CYCLE_TIME_MS == heartbeat_ms
    assert k.FAULT_REPORT_SEND_TYPE == "CyclicIfActive"
    assert cycle["RigStatus"] == k.RIG_STATUS_CYCLE_TIME_MS == 1000.0 / DEFAULT_STATUS_RATE_HZ


def test_e2e_attributes_are_what_the_codec_uses() -> None:
    """The DBC declares the E2E protection the codec computes: CRC-8 parameters (the
    codec's CRC gives the SAE J1850 check value with them) and each frame's CRC and
    counter signals at bytes 0 and 1."""
    from rig.wire import e2e

    db = cantools.database.load_file(str(DBC_PATH))
    net = {name: a.value for name, a in db.dbc.attributes.items()}
    assert (net["E2ECrcPolynomial"], net["E2ECrcInit"], net["E2ECrcXorOut"]) == (
        e2e.CRC8_POLY, e2e.CRC8_INIT, e2e.CRC8_XOROUT) == (0x1D, 0xFF, 0xFF)
    assert net["E2ECounterMax"] + 1 == e2e.COUNTER_MODULO == 16
    assert e2e.crc8_sae_j1850(b"123456789") == e2e.CRC8_CHECK_VALUE
    for msg in db.messages:
        attrs = {name: a.value for name, a in msg.dbc.attributes.items()}
        crc = msg.get_signal_by_name(attrs["E2ECrcSignal"])
        counter = msg.get_signal_by_name(attrs["E2ECounterSignal"])
        assert (crc.start, crc.length) == (0, 8), msg.name
        assert (counter.start, counter.length) == (8, 4), msg.name


def test_bit_flags_are_the_dbc_attribute(tmp_path: Path) -> None:
    """SensorStatus is generated from SensorData.SensorStatus's BitFlags attribute: renamed,
    unnamed or added bits in the DBC change the IntFlag; too many or bad names are refused."""
    db: Any = cantools.database.load_file(str(DBC_PATH))
    sig = db.get_message_by_name("SensorData").get_signal_by_name("SensorStatus")
    names = str(sig.dbc.attributes["BitFlags"].value).split(",")
    assert {m.name: m.value for m in SensorStatus} == {n: 1 << i for i, n in enumerate(names)}
    line = 'BA_ "BitFlags" SG_ 256 SensorStatus "LVDT_FAULT,LOAD_CELL_FAULT,ACCEL_FAULT";'

    def generated_flags(value: str) -> str:
        text = generate(_changed_dbc(tmp_path, (line, line.replace(
            "LVDT_FAULT,LOAD_CELL_FAULT,ACCEL_FAULT", value))))
        return text[text.index("class SensorStatus(IntFlag):"):text.index("# E2E protection")]

    flags = generated_flags("LVDT_FAULT,,ACCEL_FAULT,TEMP_FAULT")
    assert "    LVDT_FAULT = 1\n    ACCEL_FAULT = 4\n    TEMP_FAULT = 8\n" in flags
    assert "LOAD_CELL" not in flags
    with pytest.raises(ValueError, match="SensorStatus: BitFlags names 5 bits, the signal has 4"):
        generated_flags("A,B,C,D,E")
    with pytest.raises(ValueError, match=r"SensorStatus: BitFlags bit names \['B-C'\] are not"):
        generated_flags("A,B-C")


def test_blending_wire_map_is_complete_and_one_to_one() -> None:
    """The controller owns the mode names (``controller.modes.Blending``), the DBC the
    wire numbers (``rig.wire.protocol.Blending``); ``rig.wire_modes`` maps every one of
    each onto exactly one of the other, and the ControllerStatus codec carries them."""
    from controller.modes import BANK_MODES
    from controller.modes import Blending as ModeBlending
    from rig.wire.protocol import Blending as WireBlending
    from rig.wire_modes import TO_WIRE, from_wire, to_wire

    assert set(TO_WIRE) == set(ModeBlending)
    assert set(TO_WIRE.values()) == set(WireBlending)
    assert len(set(TO_WIRE.values())) == len(TO_WIRE)
    assert set(BANK_MODES.values()) == set(ModeBlending)
    for mode in ModeBlending:
        assert from_wire(to_wire(mode)) is mode
        assert to_wire(int(mode)) == to_wire(mode) == int(TO_WIRE[mode])   # the code too
        assert TO_WIRE[mode].name == mode.name   # same meaning, spelled alike
    with pytest.raises(ValueError):
        to_wire(max(ModeBlending) + 1)
    dbc: Any = cantools.database.load_file(str(DBC_PATH))
    choices = dbc.get_message_by_name("ControllerStatus").get_signal_by_name("Blending").choices
    assert {int(v) for v in choices} == {int(w) for w in WireBlending}
    with pytest.raises(ValueError):
        from_wire(max(WireBlending) + 1)
