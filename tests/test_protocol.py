"""The codec generated from the DBC (rig.wire.dbc_codec, used through rig.wire.protocol)
against cantools (the reference) loading rig/wire/rig.dbc."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig.wire.protocol import (
    CODECS,
    SENSOR_DATA,
    VALVE_COMMAND,
    DecodeStatus,
    FaultCode,
    LifecycleState,
    SensorData,
    ValveCommand,
)
from tests.support.bench_module import load_bench_module
from tests.support.crc import crc8_bitwise, with_crc
from tests.support.crc import ref_encode as cantools_encode
from tests.support.frames import FrameDecoder

DBC: Any = cantools.database.load_file(str(Path(__file__).parents[1] / "rig" / "wire" / "rig.dbc"))
CODEC_LIST = list(CODECS.values())
IDS = [c.frame_id for c in CODEC_LIST]


def ref_encode(frame_id: int, signals: dict[str, Any]) -> bytes:
    """cantools encode (rig.dbc) with the E2E CRC computed by the bitwise reference."""
    return cantools_encode(DBC, frame_id, signals)


# ----------------------------------------------------------------- the DBC itself


@pytest.mark.parametrize("codec", CODEC_LIST, ids=lambda c: c.name)
def test_layout_matches_dbc(codec: Any) -> None:
    msg = DBC.get_message_by_frame_id(codec.frame_id)
    assert msg.name == codec.name and msg.length == 8 and not msg.is_extended_frame
    crc, counter, *rest = msg.signals
    assert (crc.start, crc.length, crc.name) == (0, 8, f"{codec.name}_CRC")
    assert (counter.start, counter.length, counter.name) == (8, 4, codec.COUNTER_SIGNAL)
    assert [s.name for s in rest] == [spec.dbc_name for spec in codec.SIGNALS]
    for sig, spec in zip(rest, codec.SIGNALS, strict=True):
        assert sig.byte_order == "little_endian"
        assert (sig.start, sig.length, sig.is_signed) == (spec.start_bit, spec.length,
                                                          spec.signed)
        assert sig.scale == spec.scale and sig.offset == 0
        assert (sig.minimum, sig.maximum) == (spec.minimum, spec.maximum)
        choices = tuple(sorted(sig.choices)) if sig.choices else None
        assert choices == spec.choices
    assert tuple(codec.FRAME_TYPE.FIELDS) == tuple(s.attr for s in codec.SIGNALS)


def test_enums_match_val_tables() -> None:
    fault = DBC.get_message_by_name("FaultReport").get_signal_by_name("FaultCode")
    assert {k: str(v) for k, v in fault.choices.items()} == {int(f): f.name for f in FaultCode}
    for frame, sig in (("ValveCommand", "Lifecycle"), ("FaultReport", "FaultState"),
                       ("ControllerStatus", "State")):
        s = DBC.get_message_by_name(frame).get_signal_by_name(sig)
        assert {k: str(v) for k, v in s.choices.items()} == \
            {int(x): x.name for x in LifecycleState}
    active = DBC.get_message_by_name("ControllerStatus").get_signal_by_name("ActiveFault")
    assert {k: str(v) for k, v in active.choices.items()} == {int(f): f.name for f in FaultCode}
    assert str(fault.choices[15]) == str(active.choices[15]) == "SENSOR_FROZEN"
    assert FaultCode.SENSOR_FROZEN == 15


# ----------------------------------------------------------------- encode


def _in_range_value(spec: Any) -> st.SearchStrategy[Any]:
    if spec.scale == 1 and float(spec.minimum).is_integer():
        return st.integers(int(spec.minimum), int(spec.maximum))
    return st.floats(spec.minimum, spec.maximum, allow_nan=False)


def _signals_strategy(codec: Any) -> st.SearchStrategy[dict[str, Any]]:
    return st.fixed_dictionaries(
        {codec.COUNTER_SIGNAL: st.integers(0, 15),
         **{spec.dbc_name: _in_range_value(spec) for spec in codec.SIGNALS}})


@pytest.mark.parametrize("codec", CODEC_LIST, ids=lambda c: c.name)
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_encode_byte_identical_to_cantools(codec: Any, data: st.DataObject) -> None:
    signals = data.draw(_signals_strategy(codec))
    buf = bytearray(8)
    mask = codec.encode_signals(buf, signals)
    assert bytes(buf) == ref_encode(codec.frame_id, signals)
    expected_mask = 0
    for i, spec in enumerate(codec.SIGNALS):
        if spec.choices is not None and signals[spec.dbc_name] not in spec.choices:
            expected_mask |= 1 << i
    assert mask == expected_mask


@pytest.mark.parametrize("codec", CODEC_LIST, ids=lambda c: c.name)
def test_encode_range_edges(codec: Any) -> None:
    for pick in (0, 1):
        signals = {spec.dbc_name: (spec.minimum, spec.maximum)[pick] for spec in codec.SIGNALS}
        signals[codec.COUNTER_SIGNAL] = 15 * pick
        buf = bytearray(8)
        codec.encode_signals(buf, signals)
        assert bytes(buf) == ref_encode(codec.frame_id, signals)


_ANY_FLOAT = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                       st.floats(-1e9, 1e9), st.integers(-10**6, 10**6))


@pytest.mark.parametrize("codec", CODEC_LIST, ids=lambda c: c.name)
@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_encode_clamps_out_of_range_and_flags(codec: Any, data: st.DataObject) -> None:
    signals: dict[str, Any] = {codec.COUNTER_SIGNAL: data.draw(st.integers(-100, 100))}
    clamped: dict[str, Any] = {codec.COUNTER_SIGNAL: signals[codec.COUNTER_SIGNAL] % 16}
    expected_mask = 0
    v: Any
    for i, spec in enumerate(codec.SIGNALS):
        is_int = spec.scale == 1
        if spec.dbc_name == "FaultTick":  # a tick counter: wraps like the rolling counter
            v = data.draw(st.integers(-2**40, 2**40))
            signals[spec.dbc_name] = v
            clamped[spec.dbc_name] = v % 2**32
            continue
        if spec.length == 1:  # booleans: any truthy value is 1
            v = data.draw(st.integers(-3, 3))
            signals[spec.dbc_name] = v
            clamped[spec.dbc_name] = int(bool(v))
            continue
        v = data.draw(st.integers(-1000, 10**6) if is_int else _ANY_FLOAT)
        signals[spec.dbc_name] = v
        c: float = 0.0 if isinstance(v, float) and math.isnan(v) else \
            min(max(v, spec.minimum), spec.maximum)
        undefined = spec.choices is not None and v not in spec.choices
        if c != v or (isinstance(v, float) and math.isnan(v)) or undefined:
            expected_mask |= 1 << i
        clamped[spec.dbc_name] = int(c) if is_int else c
    buf = bytearray(8)
    mask = codec.encode_signals(buf, signals)
    assert mask == expected_mask
    assert bytes(buf) == ref_encode(codec.frame_id, clamped)


# ----------------------------------------------------------------- decode


@pytest.mark.parametrize("codec", CODEC_LIST, ids=lambda c: c.name)
@settings(max_examples=200, deadline=None)
@given(payload=st.lists(st.one_of(st.sampled_from([0x00, 0x7F, 0x80, 0xFF]),
                                  st.integers(0, 255)), min_size=8, max_size=8).map(bytes))
def test_decode_identical_to_cantools(codec: Any, payload: bytes) -> None:
    data = with_crc(codec.frame_id, payload)
    ref = DBC.get_message_by_frame_id(codec.frame_id).decode(data, decode_choices=False)
    frame = codec.new()
    status = codec.decode(data, frame)
    got = codec.to_signals(frame)
    for name, value in got.items():
        assert value == ref[name], name
        assert type(value) is int or isinstance(value, float)
    assert set(ref) - set(got) == {f"{codec.name}_CRC"}
    expected_mask = 0
    for i, spec in enumerate(codec.SIGNALS):
        v = ref[spec.dbc_name]
        half_lsb = spec.scale / 2
        if not spec.minimum - half_lsb <= v <= spec.maximum + half_lsb or (
                spec.choices is not None and v not in spec.choices):
            expected_mask |= 1 << i
    assert frame.range_mask == expected_mask
    assert status is (DecodeStatus.OUT_OF_RANGE if expected_mask else DecodeStatus.OK)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**29 - 1), st.binary(max_size=64), st.booleans())
def test_decoder_fuzz_never_raises(frame_id: int, data: bytes, extended: bool) -> None:
    dec = FrameDecoder()
    status = dec.decode(frame_id, data, extended)
    assert isinstance(status, DecodeStatus)
    if extended or frame_id not in CODECS:
        assert status is DecodeStatus.UNKNOWN_ID
    elif len(data) != 8:
        assert status is DecodeStatus.BAD_LENGTH
    else:
        valid = data[0] == crc8_bitwise(bytes([frame_id & 0xFF, frame_id >> 8]) + data[1:])
        assert (status is DecodeStatus.BAD_CRC) == (not valid)
    for view in (bytearray(data), memoryview(data)):
        assert dec.decode(frame_id, view, extended) is status


@pytest.mark.parametrize("codec", CODEC_LIST, ids=lambda c: c.name)
@settings(max_examples=60, deadline=None)
@given(payload=st.binary(min_size=8, max_size=8), pos=st.integers(0, 7),
       flip=st.integers(1, 255))
def test_single_byte_flip_is_bad_crc_and_output_untouched(codec: Any, payload: bytes,
                                                          pos: int, flip: int) -> None:
    data = bytearray(with_crc(codec.frame_id, payload))
    frame = codec.new()
    assert codec.decode(data, frame) in (DecodeStatus.OK, DecodeStatus.OUT_OF_RANGE)
    before = repr(frame)
    data[pos] ^= flip
    assert codec.decode(data, frame) is DecodeStatus.BAD_CRC
    assert repr(frame) == before


def test_frame_of_one_id_is_rejected_under_another() -> None:
    buf = bytearray(8)
    SENSOR_DATA.encode(buf, 5, 0, 0.01, 100.0, 1.0)
    assert VALVE_COMMAND.decode(buf, ValveCommand()) is DecodeStatus.BAD_CRC
    assert SENSOR_DATA.decode(buf, SensorData()) is DecodeStatus.OK


@given(st.floats(-1, 1), st.floats(-16384, 16383.5), st.integers(0, 15), st.booleans())
def test_round_trip_within_half_lsb(spool: float, force: float, echo: int, en: bool) -> None:
    buf = bytearray(8)
    assert VALVE_COMMAND.encode(buf, 9, en, LifecycleState.ACTIVE, spool, force, echo) == 0
    out = ValveCommand()
    assert VALVE_COMMAND.decode(buf, out) is DecodeStatus.OK
    assert abs(out.spool_command - spool) <= 3.06e-5 / 2 * 1.0001
    assert abs(out.force_reference_n - force) <= 0.25
    assert (out.counter, out.enable, out.lifecycle, out.sensor_counter_echo) == \
        (9, int(en), 1, echo)


def test_full_scale_spool_is_in_range() -> None:
    """1/32767 is written with 15 digits in the DBC, so 32767 * scale is a hair above 1;
    the range check works on raw values and must accept full scale, reject -32768."""
    buf = bytearray(8)
    out = ValveCommand()
    for spool in (1.0, -1.0):
        VALVE_COMMAND.encode(buf, 0, 1, 1, spool, 0.0, 0)
        assert VALVE_COMMAND.decode(buf, out) is DecodeStatus.OK
    buf[2:4] = (-32768).to_bytes(2, "little", signed=True)
    buf[0] = crc8_bitwise(bytes([0x80, 0x00]) + bytes(buf[1:]))
    assert VALVE_COMMAND.decode(buf, out) is DecodeStatus.OUT_OF_RANGE
    assert out.range_mask == 4


def test_codec_bench_runs_quick() -> None:
    mod = load_bench_module("codec_bench")
    rows = mod.run(quick=True)
    assert len(rows) == 2 * len(CODECS)
    assert all(r["ours_us"] > 0 and r["cantools_us"] > 0 for r in rows)
    assert "speedup" in mod.format_table(rows)


def test_every_fault_code_has_its_own_plain_language_description() -> None:
    texts = [c.description for c in FaultCode]
    assert all(len(x) > 5 and x[0].isupper() and x.endswith(".") for x in texts)
    assert len(set(texts)) == len(texts)
    assert "watchdog" in FaultCode.RIG_WATCHDOG.description
