"""FaultSchedule parsing and every fault kind visibly happening on the bus at its
scripted ticks (node tick-stepped on python-can's virtual bus, no sleeping)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from controller.config import ConfigError
from hil.faults import FaultKind, FaultSchedule, FaultWindow
from rig.wire.protocol import CounterMonitor, CounterStatus, DecodeStatus
from tests.support.node_harness import CFG, Harness, harness

# window 100..150 ticks at 1 kHz
T0, T1 = 0.100, 0.150
K0, K1 = 100, 150


def one(kind: str, **params: object) -> FaultSchedule:
    return FaultSchedule.from_list([(T0, T1, kind, params)], seed=11)


def in_window(tick: int) -> bool:
    return K0 <= tick < K1


# ----------------------------------------------------------------- schedule


def test_defaults_and_tick_binding() -> None:
    s = FaultSchedule.from_list([(0.5, 0.6, "delay", {}), (0.1, 0.2, "drop",
                                                          {"probability": 0.25})])
    assert [w.kind for w in s.windows] == [FaultKind.DROP, FaultKind.DELAY]  # sorted
    assert s.windows[1].params == {"ticks": 5, "frames": "sensor"}
    s.bind(1e-3)
    assert s.active(99) == [] and s.active(100) == [s.windows[0]]
    assert s.active(199) == [s.windows[0]] and s.active(200) == []
    assert s.end_s == 0.6


def test_load_toml_and_json(tmp_path: Path) -> None:
    toml = tmp_path / "f.toml"
    toml.write_text('seed = 4\n[[faults]]\nkind = "corrupt_crc"\nstart_s = 1\nend_s = 2\n'
                    'xor = 3\nframes = "all"\n')
    s = FaultSchedule.load(toml)
    assert s.seed == 4 and s.windows[0] == FaultWindow(1.0, 2.0, FaultKind.CORRUPT_CRC,
                                                       {"xor": 3, "frames": "all"})
    js = tmp_path / "f.json"
    js.write_text(json.dumps([[1, 2, "corrupt_crc", {"xor": 3, "frames": "all"}]]))
    assert FaultSchedule.load(js).windows == s.windows
    js.write_text(json.dumps({"seed": 4, "faults": [
        {"kind": "corrupt_crc", "start_s": 1, "end_s": 2, "xor": 3, "frames": "all"}]}))
    assert FaultSchedule.load(js).windows == s.windows


@pytest.mark.parametrize(("entry", "key"), [
    ((0.1, 0.2, "meteor", {}), "faults[0].kind"),
    ((0.2, 0.1, "drop", {}), "faults[0].end_s"),
    ((-1.0, 0.1, "drop", {}), "faults[0].start_s"),
    ((0.1, 0.2, "drop", {"probability": 1.5}), "faults[0].probability"),
    ((0.1, 0.2, "drop", {"ticks": 3}), "faults[0].ticks"),
    ((0.1, 0.2, "delay", {"ticks": 0}), "faults[0].ticks"),
    ((0.1, 0.2, "corrupt_crc", {"xor": 0}), "faults[0].xor"),
    ((0.1, 0.2, "stuck_counter", {"frames": "valve"}), "faults[0].frames"),
    ((0.1, 0.2, "out_of_range", {"value": float("nan")}), "faults[0].value"),
    ((0.1, 0.2), "faults[0]"),
])
def test_invalid_entries_name_the_key(entry: tuple[object, ...], key: str) -> None:
    with pytest.raises(ConfigError) as exc:
        FaultSchedule.from_list([entry])
    assert exc.value.key == key


def test_bad_file_is_a_config_error(tmp_path: Path) -> None:
    p = tmp_path / "f.toml"
    p.write_text("[[faults]\n")
    with pytest.raises(ConfigError):
        FaultSchedule.load(p)
    p.write_text('bogus = 1\n')
    with pytest.raises(ConfigError) as exc:
        FaultSchedule.load(p)
    assert exc.value.key == "bogus"


# ----------------------------------------------------------------- on the bus


def _run(faults: FaultSchedule, n: int = 200, road: str = "iso-C",
         commands: bool = False) -> Harness:
    with harness(faults, road=road) as h:
        h.step(n, command=(lambda k: {"enable": 1, "spool": 0.1}) if commands else None)
        return h


def test_drop_all_sensor_frames_in_window() -> None:
    h = _run(one("drop"))
    ticks = [r.tick for r in h.sensor_frames()]
    assert ticks == [k for k in range(200) if not in_window(k)]
    # the sender kept counting: the receiver sees a jump of exactly the window length
    mon = CounterMonitor()
    statuses = [mon.check(r.sensor.counter) for r in h.sensor_frames() if r.sensor]
    jumps = [i for i, s in enumerate(statuses) if s is CounterStatus.JUMPED]
    assert jumps == [K0] and mon.lost_total == (K1 - K0) % 16  # 50 lost alias to 2
    assert all(r.sensor.counter == r.tick % 16 for r in h.sensor_frames() if r.sensor)
    assert len(h.status_frames()) == 20  # RigStatus untouched


def test_random_drop_is_deterministic_for_a_seed() -> None:
    patterns = []
    for seed in (5, 5, 6):
        s = FaultSchedule.from_list([(0.0, 1.0, "drop", {"probability": 0.3})], seed=seed)
        h = _run(s, n=1000, road="bump")
        patterns.append(tuple(r.tick for r in h.sensor_frames()))
    assert patterns[0] == patterns[1] != patterns[2]
    kept = len(patterns[0]) / 1000
    assert abs(kept - 0.7) < 4.5 * np.sqrt(0.3 * 0.7 / 1000)


def test_delay_holds_frames_n_ticks() -> None:
    h = _run(one("delay", ticks=7))
    frames = h.sensor_frames()
    got = sorted((r.tick, r.sensor.counter) for r in frames if r.sensor)
    expected = sorted((k + 7 if in_window(k) else k, k % 16) for k in range(200))
    assert got == expected
    assert not [r for r in frames if K0 <= r.tick < K0 + 7]  # nothing for the first 7
    assert len(frames) == 200  # every frame eventually arrives
    assert len([r for r in frames if r.tick == K1 + 3]) == 2  # late and fresh together


def test_corrupt_crc_in_window_only() -> None:
    h = _run(one("corrupt_crc", frames="all"))
    for r in h.rx:
        expected = DecodeStatus.BAD_CRC if in_window(r.tick) else DecodeStatus.OK
        assert r.status is expected, r.tick
    # SensorData and RoadPreview every tick, RigStatus every 10th
    assert sum(r.status is DecodeStatus.BAD_CRC for r in h.rx) == 50 + 50 + 5


def test_stuck_counter() -> None:
    h = _run(one("stuck_counter"))
    counters = {r.tick: r.sensor.counter for r in h.sensor_frames() if r.sensor}
    for k in range(K0, K1):
        assert counters[k] == (K0 - 1) % 16
    assert counters[K1] == K0 % 16  # resumes counting from the stuck value
    assert all(r.status is DecodeStatus.OK for r in h.sensor_frames())


def test_stuck_counter_on_rig_status_only() -> None:
    h = _run(one("stuck_counter", frames="status"))
    rig = {r.tick: r.rig.counter for r in h.status_frames() if r.rig}
    assert [rig[k] for k in range(K0, K1, 10)] == [(K0 // 10 - 1) % 16] * 5
    counters = [r.sensor.counter for r in h.sensor_frames() if r.sensor]
    assert counters == [k % 16 for k in range(200)]


def test_frozen_sensor_repeats_last_values() -> None:
    h = _run(one("frozen_sensor"), road="iso-D")
    vals = {r.tick: (r.sensor.rattlespace_m, r.sensor.load_cell_force_n,
                     r.sensor.sprung_accel_mps2) for r in h.sensor_frames() if r.sensor}
    assert all(vals[k] == vals[K0 - 1] for k in range(K0, K1))
    assert len({vals[k] for k in range(K1, 200)}) > 10  # live again
    assert len({vals[k] for k in range(0, K0)}) > 10
    counters = [vals and r.sensor.counter for r in h.sensor_frames() if r.sensor]
    assert counters == [k % 16 for k in range(200)]  # only the values freeze


@pytest.mark.parametrize(("signal", "attr", "limit"), [
    ("rattlespace", "rattlespace_m", 0.163835),
    ("force", "load_cell_force_n", 16383.5),
    ("accel", "sprung_accel_mps2", 163.835),
])
def test_out_of_range_values(signal: str, attr: str, limit: float) -> None:
    h = _run(one("out_of_range", signal=signal))
    sensor_range = {"rattlespace": CFG.sensors.lvdt_range_m,
                    "force": CFG.sensors.load_cell_range_n,
                    "accel": CFG.sensors.accel_range_mps2}[signal]
    for r in h.sensor_frames():
        assert r.sensor is not None and r.status is DecodeStatus.OK
        v = getattr(r.sensor, attr)
        if in_window(r.tick):
            assert v == limit and v > sensor_range  # saturated at the DBC limit
        else:
            assert abs(v) <= sensor_range


def test_sensor_status_bits() -> None:
    h = _run(one("sensor_status", bits=5))
    for r in h.sensor_frames():
        assert r.sensor is not None
        assert r.sensor.sensor_status == (5 if in_window(r.tick) else 0)


def test_silence_stops_all_transmission() -> None:
    h = _run(one("silence"))
    assert not [r for r in h.rx if in_window(r.tick)]
    assert {r.tick for r in h.sensor_frames()} == {k for k in range(200) if not in_window(k)}
    assert h.node.stats.frames_sent == 150 + 150 + 15     # SensorData, RoadPreview, RigStatus


def test_supply_loss() -> None:
    h = _run(one("supply_loss"), commands=True, n=300)
    for r in h.status_frames():
        assert r.rig is not None
        assert r.rig.supply_ok == (0 if in_window(r.tick) else 1)
        assert (r.rig.supply_pressure_pa == 0.0) == in_window(r.tick)
    force = {r.tick: r.sensor.load_cell_force_n for r in h.sensor_frames() if r.sensor}
    assert abs(force[K0 - 1]) > 1000.0  # the command was producing force
    assert abs(force[K1 - 1]) < 0.2 * abs(force[K0 - 1])  # gone without supply
    assert abs(force[299]) > 1000.0  # back after the window
    rec = h.node.record.arrays()
    assert rec["supply_lost"][K0:K1].all() and not rec["supply_lost"][:K0].any()


def test_every_kind_is_covered() -> None:
    tested = {"drop", "delay", "corrupt_crc", "stuck_counter", "frozen_sensor",
              "out_of_range", "sensor_status", "silence", "supply_loss"}
    assert tested == {k.value for k in FaultKind}
