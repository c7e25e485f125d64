"""End to end on a real CAN interface: the emulated rig (``rig hil``) and the service
(``rig run --arm``) as separate processes on vcan0, watched by candump and by a Zenoh
subscriber process (see tests/socketcan/harness.py and docs/socketcan.md).

Closed loop: the run matches the in-process offline simulation of the same road, noise
seed and configuration; no frame is lost or duplicated; telemetry reaches the other
process; the MCAP recording is complete.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.metrics import filter_signal, human_filter_tf
from tests.socketcan import capture as cap
from tests.socketcan.harness import (
    RATE_HZ,
    ROAD,
    SEED,
    SPEED_MPS,
    Scenario,
    ScenarioResult,
    e2e_config,
    e2e_marks,
    run_scenario,
)
from tests.socketcan.support import CHANNEL, Children, counter_gaps, record

pytestmark = e2e_marks(600)

SERVICE_S = 20.0   # service loop time (the rig starts after it, then it arms when healthy)
SETTLE_S = 2.0     # after arming, before the comparison window
#: the ride comparison needs a command for this share of the rig's ticks (a loop that
#: keeps up; see test_ride_matches_the_offline_closed_loop)
MIN_COMMANDS_PER_TICK = 0.9995


def _absorbed_power(accel_mps2: np.ndarray, dt_s: float, i0: int, i1: int) -> float:
    num, den = human_filter_tf()
    filtered = filter_signal(accel_mps2, num, den, dt_s)
    return float(np.mean(np.square(filtered[i0:i1])))


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _see_it_armed(sc: Scenario) -> None:
    """The service arms itself on start; a UML stall in its first ticks can trip the rig's
    drive watchdog first (the arm is then refused from FAULT), so the operator resets and
    arms over Zenoh until it is ACTIVE, as on the rig.  A service that never arms fails
    test_processes_ran_and_stopped_cleanly."""
    sc.operator.recover(sc.state, timeout_s=60.0)


@pytest.fixture(scope="module")
def closed_loop(tmp_path_factory: pytest.TempPathFactory) -> ScenarioResult:
    """One armed run of SERVICE_S seconds on vcan0, shared by the closed-loop tests."""
    tmp = tmp_path_factory.mktemp("closed_loop")
    kids = Children(tmp)
    try:
        cfg, cfg_path = e2e_config(tmp, CHANNEL)
        result = run_scenario(kids, tmp, cfg, cfg_path, duration_s=SERVICE_S,
                              during=_see_it_armed)
    finally:
        kids.stop_all()
    # the processes' outputs are in the result (and in tmp); a failing test prints them
    return result


def test_processes_ran_and_stopped_cleanly(closed_loop: ScenarioResult) -> None:
    r = closed_loop
    assert r.service_status == 0, r.service_output
    assert r.rig_status == 0, r.rig_output
    assert "Traceback" not in r.service_output + r.rig_output
    armed = cap.first_armed_time(r.decoded)
    assert armed is not None, f"the service never armed:\n{r.service_output}"
    record("e2e run: service wall time", r.wall_s["service"], "s", f"--duration {SERVICE_S}")


def test_no_frame_lost_or_duplicated(closed_loop: ScenarioResult) -> None:
    r = closed_loop
    assert r.capture_drops == 0, "candump's socket dropped frames: the capture is incomplete"
    n_sd, lost_sd, dup_sd = counter_gaps(r.frames, cap.SENSOR_DATA)
    n_vc, lost_vc, dup_vc = counter_gaps(r.frames, cap.VALVE_COMMAND)
    assert n_sd > 0 and n_vc > 0
    assert (lost_sd, dup_sd) == (0, 0), "SensorData counters in the capture"
    assert (lost_vc, dup_vc) == (0, 0), "ValveCommand counters in the capture"
    assert all(f.crc_ok for f in r.decoded if f.counter >= 0), "a frame with a bad CRC"
    # the rig saw every command (its own counter monitor) and nothing bad
    assert " lost=0 " in r.rig_output and " bad=0 " in r.rig_output, r.rig_output
    # the service received every SensorData frame sent while it ran, once, in order
    from rig.recording.recorder import read_run

    run = read_run(r.recordings[0])
    rx = [(f.tick, bytes(f.data)) for f in run.frames
          if f.is_rx and f.arbitration_id == cap.SENSOR_DATA]
    tx = [bytes(f.data) for f in run.frames if not f.is_rx
          and f.arbitration_id == cap.VALVE_COMMAND]
    on_bus = [f.data for f in r.frames if f.arbitration_id == cap.SENSOR_DATA]
    # what the service's socket received is the bus's sequence, in order, no duplicate;
    # a gap is allowed only right after a stall of the service longer than its socket's
    # receive buffer lasts (~0.5 s of frames; UML guests stall like that now and then)
    period = {t.tick: t.data.get("period_s") or 0.0 for t in run.records}
    pos = on_bus.index(rx[0][1])
    lost = 0
    for tick, data in rx:
        j = on_bus.index(data, pos)
        if j != pos:
            stall = max(period.get(tick, 0.0), period.get(tick - 1, 0.0),
                        period.get(tick - 2, 0.0))
            assert stall > 0.5, f"{j - pos} SensorData frames lost at tick {tick} (no stall)"
            lost += j - pos
        pos = j + 1
    record("SensorData lost at the service's socket (stalls > 0.5 s)", lost, "frames",
           f"of {len(rx)}")
    bus_vc = [f.data for f in r.frames if f.arbitration_id == cap.VALVE_COMMAND]
    assert bus_vc == tx, "ValveCommands on the bus != the ones the service recorded sending"
    record("e2e frames: SensorData / ValveCommand on the bus", n_sd, "frames", f"/ {n_vc}")


def _armed_window(r: ScenarioResult) -> tuple[list[cap.Decoded], int, int, int, int]:
    """(SensorData frames, k_arm, k_end, i_arm, i_off): the first armed stretch in rig
    ticks (a SensorData frame's index is its rig tick: the capture starts before the rig)
    and in ValveCommand indices."""
    sd = cap.of(r.decoded, cap.SENSOR_DATA)
    valves = cap.of(r.decoded, cap.VALVE_COMMAND)
    t_sd = np.array([f.t_s for f in sd])
    i_arm = next(i for i, f in enumerate(valves) if cap.enable(f))
    i_off = next((i for i in range(i_arm, len(valves)) if not cap.enable(valves[i])),
                 len(valves) - 1)
    k_arm = int(np.searchsorted(t_sd, valves[i_arm].t_s))
    k_end = int(np.searchsorted(t_sd, valves[i_off].t_s))
    return sd, k_arm, k_end, i_arm, i_off


def _simulations(r: ScenarioResult) -> dict[str, Any]:
    from hil.sim.closed_loop import simulate
    from hil.sim.roads import make_road
    from rig.commands.hil import MAX_ROAD_S

    cfg = r.cfg
    road = make_road(ROAD, SPEED_MPS, MAX_ROAD_S, cfg.sample_time_s, SEED)
    sims = {"passive": simulate(cfg, road, "passive", seed=SEED)}
    for d in (0, 1):
        sims[f"delay{d}"] = simulate(cfg, road, "fuzzy", cfg.design.weight_set,
                                     delay_ticks=d, seed=SEED)
    return sims


def test_open_loop_rig_over_can_matches_the_offline_plant(closed_loop: ScenarioResult
                                                          ) -> None:
    """Before arming (bypass open) the rig process's SensorData over CAN equal the
    offline simulator's readings of the same road and noise seed, sample by sample."""
    sd, k_arm, _, _, _ = _armed_window(closed_loop)
    sims = _simulations(closed_loop)
    n_pre = min(k_arm, round(3.0 / closed_loop.cfg.sample_time_s))
    assert n_pre > 10, "the service armed before the rig had run 10 ticks"
    hil_rs = np.array([f.signals["Rattlespace"] for f in sd[k_arm - n_pre:k_arm]])
    hil_acc = np.array([f.signals["SprungAccel"] for f in sd[k_arm - n_pre:k_arm]])
    passive = sims["passive"].traces
    # the rig sends tick k's reading after advancing the plant: the simulator's reading
    # at the start of tick k + 1
    ref = slice(k_arm - n_pre + 1, k_arm + 1)
    # (the rig integrates with 20 RK4 substeps per tick, the simulator with 5e-5 s steps:
    # not bit-equal; a tick of misalignment would differ by millimetres)
    diff = np.abs(hil_rs - passive["meas_rattlespace_m"][ref])
    assert float(np.median(diff)) < 1e-4 and float(diff.max()) < 5e-4, diff
    acc_ref = passive["meas_accel_mps2"][ref]
    # the acceleration differs more than the rattlespace between the two integrators
    # (the median difference was 0.03-0.05 m/s^2 over a few hundred ticks in UML runs,
    # depending on how long the rig ran before arming): bound it at twice that
    assert float(np.median(np.abs(hil_acc - acc_ref))) < 0.1
    assert float(np.corrcoef(hil_acc, acc_ref)[0, 1]) > 0.98
    record("open loop: |rattlespace over CAN - offline| max", 1e6 * float(np.max(np.abs(
        hil_rs - passive["meas_rattlespace_m"][ref]))), "um", f"{n_pre} ticks before arming")


def test_service_over_can_is_bit_exact_with_the_in_process_loop(closed_loop: ScenarioResult
                                                                 ) -> None:
    """The frames the service process sent over vcan0 equal, byte for byte, what the
    unmodified ControlLoop computes in-process from the frames it received (rig.replay),
    and they are the frames on the bus."""
    from rig.replay import replay_recording

    res = replay_recording(closed_loop.recordings[0])
    assert res.bit_exact, res.summary()
    record("replay: ValveCommand/FaultReport frames compared", res.tx_frames_compared, "frames",
           "bit-exact with the in-process loop")


def test_ride_matches_the_offline_closed_loop(closed_loop: ScenarioResult) -> None:
    """Absorbed power and rattlespace while armed against the offline closed loop with
    the loop delay the bus shows.  Needs a loop that keeps up (delay 0 on >= 95 % of the
    commands, a command for >= 99.95 % of the rig's ticks and 5 s armed); in a UML guest
    it may not: the figures are printed and the test is skipped with the measured delays
    as the reason.  (Missed ticks come in stalls of a few ticks; offline, 1-2 % of ticks
    missed that way take the default law from 0.008 to 0.011-0.016 (m/s²)² on this road,
    one-layer and layered bank alike: beyond the 25 % this test allows.  In the guest
    0.16 % was already too many: a clean clone's run with 0.998 commands per rig tick,
    delay 0 on every command, measured 0.0122 against the offline 0.0082, so the bound
    was 99.5 % until 2026-11-29 and is 99.95 %, about 10 ticks of 20 s.)  The layers the
    bank ran are printed."""
    r = closed_loop
    dt = r.cfg.sample_time_s
    sd, k_arm, k_end, i_arm, i_off = _armed_window(r)
    delays = cap.command_delay_ticks(r.decoded)
    hist = np.bincount(np.clip(delays, 0, 3), minlength=4) / max(1, delays.size)
    record("loop delay 0/1/2/3+ ticks (fraction of commands)", hist[0], "",
           f"{hist[1]:.3f} / {hist[2]:.3f} / {hist[3]:.3f}")
    i0, i1 = k_arm + round(SETTLE_S / dt), k_end
    # a fresh command for every rig tick?  (the service skips ticks when it stalls)
    per_tick = (i_off - i_arm) / max(1, k_end - k_arm)
    record("ValveCommands per rig tick while armed", per_tick, "")
    record("armed stretch", (k_end - k_arm) * dt, "s", (r.service_output.count("FAULT") and
           "ended by a fault") or "until the end")
    sims = _simulations(r)
    from rig.report.series import load_series

    series = load_series(r.recordings[0])
    layers = np.unique(series.layer_mkc[np.all(np.isfinite(series.layer_mkc), axis=1)],
                       axis=0)
    record("bank layers run [M kg, K N/m, C N s/m]", len(layers), "",
           "; ".join(", ".join(f"{v:.0f}" for v in row) for row in layers))
    est = series.sprung_mass_est_kg
    if np.isfinite(est).any():
        record("sprung-mass estimate min / max", float(np.nanmin(est)), "kg",
               f"/ {float(np.nanmax(est)):.0f} kg")
    if i1 - i0 < round(5.0 / dt) or hist[0] < 0.95 or per_tick < MIN_COMMANDS_PER_TICK:
        pytest.skip(f"loop does not keep up here ({RATE_HZ:g} Hz, delays 0/1/2/3+ = "
                    f"{np.round(hist, 3).tolist()}, {per_tick:.3f} commands per rig tick, "
                    f"armed {(k_end - k_arm) * dt:.2f} s): the offline closed loop is not "
                    "the reference")
    hil_acc = np.array([f.signals["SprungAccel"] for f in sd])
    hil_rs = np.array([f.signals["Rattlespace"] for f in sd])
    figures = {"hil": (_absorbed_power(hil_acc, dt, i0, i1), _rms(hil_rs[i0:i1]))}
    for name, res in sims.items():
        figures[name] = (_absorbed_power(res.traces["meas_accel_mps2"], dt, i0, i1),
                         _rms(res.traces["meas_rattlespace_m"][i0:i1]))
    for name, (power, rs_rms) in figures.items():
        record(f"absorbed power, {name}", power, "(m/s2)^2", f"ticks {i0}..{i1}")
        record(f"rattlespace rms, {name}", 1e3 * rs_rms, "mm")
    valves = cap.of(r.decoded, cap.VALVE_COMMAND)
    spools = np.array([f.signals["SpoolCommand"] for f in valves[i_arm:i_off]])
    assert np.count_nonzero(spools) > 0.9 * spools.size, "armed but no spool commands"
    assert figures["hil"][0] == pytest.approx(figures["delay0"][0], rel=0.25)
    assert figures["hil"][1] == pytest.approx(figures["delay0"][1], rel=0.25)


def test_loop_timing_on_the_bus(closed_loop: ScenarioResult) -> None:
    """Jitter and sensor-to-command latency as seen on the bus (printed; the assertion is
    only that every command echoes a recent SensorData counter)."""
    r = closed_loop
    valves = cap.of(r.decoded, cap.VALVE_COMMAND)
    sd = cap.of(r.decoded, cap.SENSOR_DATA)
    for label, frames in (("ValveCommand", valves), ("SensorData", sd)):
        st = cap.period_stats_s([f.t_s for f in frames])
        record(f"{label} period median", 1e3 * st["median"], "ms", f"at {RATE_HZ:g} Hz")
        record(f"{label} period p01/p99/max", 1e3 * st["p99"], "ms",
               f"p01 {1e3 * st['p01']:.3f} max {1e3 * st['max']:.3f}")
    lat = cap.sensor_to_command_latency_s(r.decoded)
    after_first_sd = [v for v in valves if v.t_s > sd[0].t_s]
    assert lat.size > 0.9 * len(after_first_sd), (lat.size, len(after_first_sd))
    record("sensor-to-command latency median", 1e3 * float(np.median(lat)), "ms")
    record("sensor-to-command latency p99", 1e3 * float(np.percentile(lat, 99)), "ms")
    from rig.recording.recorder import read_run

    run = read_run(r.recordings[0])
    late = np.array([t.data.get("wake_late_s") or 0.0 for t in run.records])
    if late.size:
        record("service wake lateness p50", 1e6 * float(np.median(late)), "us", "from MCAP")
        record("service wake lateness p99", 1e6 * float(np.percentile(late, 99)), "us")
        record("service wake lateness max", 1e6 * float(late.max()), "us")


def test_telemetry_reaches_a_separate_zenoh_process(closed_loop: ScenarioResult) -> None:
    """The loop offers a state sample every rate / telemetry.rate_hz ticks it executes
    (deadlines missed under a UML stall are skipped, not executed): at least half of them
    reach the subscriber process (it connects after the service started)."""
    r = closed_loop
    states = r.samples("state")
    lifecycles = [s.get("lifecycle") for s in r.samples("lifecycle")]
    m = re.search(r"service stopped \(duration\): (\d+) ticks", r.service_output)
    assert m is not None, r.service_output[-2000:]
    every = max(1, round(r.cfg.design.sample_rate_hz / r.cfg.telemetry.rate_hz))
    offered = int(m[1]) // every
    assert len(states) > 0.5 * offered, f"{len(states)} state samples of {offered} offered"
    assert "ACTIVE" in lifecycles, lifecycles
    ticks = [s["tick"] for s in states]
    assert ticks == sorted(ticks), "telemetry out of order"
    assert all(np.isfinite(s["rattlespace_m"]) for s in states)
    timing = r.samples("timing")
    assert timing and all("wake_late_s" in t for t in timing)
    record("telemetry samples received (state)", len(states), "", "20 Hz publisher")


def test_mcap_recording_is_complete(closed_loop: ScenarioResult) -> None:
    from rig.recording.recorder import read_run

    r = closed_loop
    assert len(r.recordings) == 1, r.recordings
    run = read_run(r.recordings[0])
    assert run.complete, run.stopped_at
    ticks = [t.tick for t in run.records]
    assert ticks == list(range(ticks[0], ticks[0] + len(ticks))), "missing tick records"
    # every tick the loop executed is recorded (deadlines it missed by more than a
    # period are skipped and counted, not executed)
    m = re.search(r"service stopped \(duration\): (\d+) ticks", r.service_output)
    assert m is not None, r.service_output[-2000:]
    assert len(ticks) == int(m[1])
    assert "config.toml" in run.attachments
    kinds = {e.kind for e in run.events}
    assert "lifecycle" in kinds, kinds
    assert all(t.data.get("dropped_recording", 0) == 0 for t in run.records[-5:])
    record("MCAP tick records", len(ticks), "", Path(r.recordings[0]).name)
