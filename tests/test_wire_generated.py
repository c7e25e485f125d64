"""rig/wire/dbc_constants.py is generated from rig/wire/rig.dbc and checked in: the DBC
is the one place a protocol number is written."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cantools

from rig.wire import dbc_constants as constants
from rig.wire.generate import DBC_PATH, OUT_PATH, attr_name, generate, main
from rig.wire.protocol import CODECS, Blending, FaultCode, LifecycleState


def test_regenerating_gives_no_difference() -> None:
    assert OUT_PATH.read_text(encoding="utf-8") == generate()
    assert main(["--check"]) == 0


def test_a_changed_dbc_changes_the_generated_module(tmp_path: Path) -> None:
    dbc = tmp_path / "rig.dbc"
    dbc.write_text(DBC_PATH.read_text(encoding="utf-8").replace(
        "SG_ Rattlespace : 16|16@1- (5e-06,0)", "SG_ Rattlespace : 16|16@1- (1e-05,0)"),
        encoding="utf-8")
    text = generate(dbc)
    assert "SENSOR_DATA_RATTLESPACE_SCALE: Final = 1e-05" in text
    assert text != OUT_PATH.read_text(encoding="utf-8")


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
