"""The road preview on the CAN loop: RoadPreview frames -> the road ahead
(rig/service/road_preview_stream.py), and the loop against the emulated rig that sends
them (hil/node.py), on a python-can virtual bus stepped tick by tick."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.config import default_config
from rig.service.road_preview_stream import RoadPreviewStream
from rig.wire.protocol import ROAD_PREVIEW_ID, PreviewStatus

H = 150


def _feed(stream: RoadPreviewStream, ticks: range, lead: int, skip: set[int] = frozenset(),
          velocity: Any = None) -> None:
    """The rig's ticks ``ticks``: SensorData (counter k mod 16), then RoadPreview with the
    velocity of tick k + lead (``velocity(t)``, default t / 1000); ``skip``: RoadPreview
    frames lost."""
    v = velocity or (lambda t: t / 1000.0)
    for k in ticks:
        stream.sensor(k & 15)
        if k not in skip:
            stream.frame(True, 0, v(k + lead), lead, k & 15)


def _window(stream: RoadPreviewStream) -> np.ndarray:
    start = stream.window_start()
    assert start >= 0
    return stream.ring[start:start + stream.horizon]


def test_window_is_the_road_after_the_latest_sensor_frame() -> None:
    s = RoadPreviewStream(H)
    assert s.why_not_live() == "no_frame"
    _feed(s, range(0, 100), lead=250)
    assert s.why_not_live() == "filling"       # the run began 250 ticks ahead of tick 0
    _feed(s, range(100, 249), lead=250)
    assert s.why_not_live() == "filling"       # tick 248's window would begin at 249
    _feed(s, range(249, 250), lead=250)
    assert s.why_not_live() == "live"          # tick 249's: 250 .. 399, the first sample on
    _feed(s, range(250, 600), lead=250)
    assert s.why_not_live() == "live"
    # tick 599 is the latest: its window is the road of rig ticks 600 .. 749
    np.testing.assert_array_equal(_window(s), np.arange(600, 600 + H) / 1000.0)


def test_counter_wrap_and_ring_wrap_keep_the_alignment() -> None:
    s = RoadPreviewStream(H, capacity=512)
    _feed(s, range(0, 5000), lead=300)
    np.testing.assert_array_equal(_window(s), np.arange(5000, 5000 + H) / 1000.0)


def test_a_lost_sensor_frame_counts_its_tick() -> None:
    """SensorData of tick 700 lost: the rig's tick still advances by the counter's step,
    and the window follows the rig, not the frames received."""
    s = RoadPreviewStream(H)
    v = lambda t: t / 1000.0        # noqa: E731
    for k in range(0, 800):
        if k != 700:
            s.sensor(k & 15)
        s.frame(True, 0, v(k + 250), 250, k & 15)
    assert s.rig_tick == 799
    np.testing.assert_array_equal(_window(s), np.arange(800, 800 + H) / 1000.0)


def test_a_lost_preview_frame_is_a_hole_until_the_window_passes_it() -> None:
    s = RoadPreviewStream(H)
    _feed(s, range(0, 600), lead=250)
    _feed(s, range(600, 601), lead=250, skip={600})     # the sample of tick 850 is lost
    _feed(s, range(601, 602), lead=250)
    assert s.breaks == 1
    assert s.why_not_live() == "filling"
    _feed(s, range(602, 850), lead=250)
    assert s.why_not_live() == "filling"       # the window still reaches back over 851
    _feed(s, range(850, 851), lead=250)
    assert s.why_not_live() == "live"          # tick 850's window: 851 .. 1000
    np.testing.assert_array_equal(_window(s), np.arange(851, 851 + H) / 1000.0)


def test_frames_that_stop_leave_the_window_short() -> None:
    s = RoadPreviewStream(H)
    _feed(s, range(0, 600), lead=250)
    for k in range(600, 700):
        s.sensor(k & 15)                       # the rig stops sending RoadPreview:
    assert s.why_not_live() == "live"          # what came holds up to tick 849
    for k in range(700, 800):
        s.sensor(k & 15)
    assert s.why_not_live() == "short"
    assert s.window_start() == -1


@pytest.mark.parametrize(("good", "status", "lead", "velocity", "why"), [
    (False, 0, 250, 0.1, "corrupt"),
    (True, int(PreviewStatus.NO_ROAD), 250, 0.1, "no_road"),
    (True, 0, H - 1, 0.1, "lead"),
    (True, 0, 5000, 0.1, "lead"),
    (True, 0, 250, float("nan"), "corrupt"),
])
def test_an_unusable_frame_ends_the_run_and_says_why(good: bool, status: int, lead: int,
                                                     velocity: float, why: str) -> None:
    s = RoadPreviewStream(H)
    _feed(s, range(0, 600), lead=250)
    assert s.why_not_live() == "live"
    s.sensor(600 & 15)
    s.frame(good, status, velocity, lead, 600 & 15)
    assert s.window_start() == -1
    assert s.why_not_live() == why


def test_a_changed_lead_restarts_the_run_and_repeats_are_ignored() -> None:
    s = RoadPreviewStream(H)
    _feed(s, range(0, 600), lead=250)
    s.frame(True, 0, 99.0, 250, 599 & 15)        # a repeat of tick 849's sample
    assert s.why_not_live() == "live" and s.breaks == 0
    np.testing.assert_array_equal(_window(s), np.arange(600, 600 + H) / 1000.0)
    _feed(s, range(600, 601), lead=200)
    assert s.why_not_live() == "filling"
    _feed(s, range(601, 800), lead=200)
    np.testing.assert_array_equal(_window(s), np.arange(800, 800 + H) / 1000.0)


def test_no_frame_before_a_sensor_frame() -> None:
    s = RoadPreviewStream(H)
    s.frame(True, 0, 0.1, 250, 0)
    assert s.why_not_live() == "no_sensor"


@settings(max_examples=60, deadline=None)
@given(lead=st.integers(H, 1000), lost=st.lists(st.integers(0, 2999), max_size=8),
       n=st.integers(1200, 3000))
def test_a_live_window_is_always_the_true_road_ahead(lead: int, lost: list[int],
                                                     n: int) -> None:
    """Whatever frames are lost, a window the stream calls live holds exactly the road
    of the H rig ticks after the latest SensorData's."""
    s = RoadPreviewStream(H)
    skip = set(lost)
    for k in range(n):
        _feed(s, range(k, k + 1), lead, skip)
        start = s.window_start()
        if start >= 0:
            np.testing.assert_array_equal(s.ring[start:start + H],
                                          np.arange(k + 1, k + 1 + H) / 1000.0)
    # the stream keeps one run: the samples after the last lost frame that a received
    # one follows (a lost frame of tick j is a hole at rig tick j + lead), up to the
    # latest received one; the last window (ticks n .. n + H - 1) is live exactly when
    # that run covers it (a lost frame after the latest received one leaves no hole)
    received = [k for k in range(n) if k not in skip]
    holes = [j for j in skip if j < received[-1]]
    run_start = (max(holes) + 1 if holes else 0) + lead
    run_end = received[-1] + lead
    assert (s.window_start() >= 0) is (run_start <= n and run_end >= n + H - 1)


def test_bad_construction() -> None:
    with pytest.raises(ValueError, match="horizon"):
        RoadPreviewStream(0)
    with pytest.raises(ValueError, match="power of two"):
        RoadPreviewStream(H, capacity=1000)


# --------------------------------------------------------------- the loop and the rig
def _run(cfg: Any, seconds: float, faults: Any = None, weight_set: int = 0
         ) -> tuple[Any, list[dict[str, Any]], list[float]]:
    """The loop of ``cfg`` (the travel schedule, or ``weight_set``) against the emulated
    rig on the thesis course (road seed 7), stepped in lockstep; armed at 0.1 s.  Returns
    (the loop, its notes, the largest differences between a live window and the road the
    rig plays next)."""
    from hil.node import RigNode
    from hil.sim.roads import make_road
    from rig.bus.core import open_bus, shutdown_all
    from rig.design_cache import design_for
    from rig.rt.pacing import SteppedClock
    from rig.service.assembly import LoopSettings, build_control_loop

    channel = f"preview-{uuid.uuid4().hex}"
    ctl = open_bus(cfg.can, role="controller", interface="virtual", channel=channel)
    rig = open_bus(cfg.can, role="rig", interface="virtual", channel=channel)
    road = make_road("rough-course", 11.176, seconds, cfg.sample_time_s, 7)
    node = RigNode(rig, cfg, road, faults, seed=7, record_ticks=16)
    clock = SteppedClock()
    loop = build_control_loop(cfg, design_for(cfg), ctl,
                              LoopSettings(blending=0, weight_set=weight_set,
                                           warmup_ticks=20),
                              clock_ns=clock)
    notes: list[dict[str, Any]] = []
    loop._record_event = lambda _t, _k, kind, detail: notes.append(detail)
    errors: list[float] = []
    t = 1_000_000_000
    try:
        for k in range(round(seconds / cfg.sample_time_s)):
            node.tick()
            if k == 100:
                loop.request("arm", None, timeout_s=None)
            clock.now_ns = t
            loop.tick(t, 0)
            t += loop.period_ns
            s = loop.preview_stream
            if s is not None and s.window_start() >= 0 and k % 97 == 0:
                ahead = road.velocity_mps[(np.arange(k + 1, k + 1 + s.horizon))
                                          % road.n_ticks]
                errors.append(float(np.max(np.abs(_window(s) - ahead))))
    finally:
        shutdown_all([ctl, rig])
    return loop, notes, errors


def test_loop_takes_the_emulated_rigs_preview() -> None:
    """The defaults against the emulated rig (emulator.road_preview_s 0.25 s): the
    preview goes live within the lead of the first frame and stays live, every live window
    is the road the rig plays next (to the frame's 1 mm/s), the schedule runs on the
    preview's thresholds, and the preview calls the travel law in a few per cent of the
    ticks, as in the simulator; no fault."""
    cfg = default_config()
    loop, notes, errors = _run(cfg, 8.0)
    st_ = loop.status()
    assert st_["lifecycle"] == "ACTIVE", st_
    assert st_["road_preview"] == "live" and loop.rt.preview_schedule
    assert errors and max(errors) <= 0.0005 + 1e-12
    n = loop.tick_count
    assert 0.0 < loop.preview_calls / n < 0.2
    assert loop.preview_stream.breaks == 0
    assert [n["road_preview"] for n in notes if "road_preview" in n] == ["live"]


def test_loop_governs_weight_set_2_with_the_rigs_preview() -> None:
    """Weight set 2 on the CAN path runs under the travel governor (docs/design.md §12):
    the rig's preview goes live and calls the travel law in a few per cent of the ticks,
    the bank runs the governor's thresholds; weight set 1 (the travel set) takes no
    preview: the stream is live but unused and nothing is called.  No fault either way."""
    cfg = default_config()
    loop, _notes, errors = _run(cfg, 6.0, weight_set=2)
    st_ = loop.status()
    assert st_["lifecycle"] == "ACTIVE", st_
    assert st_["road_preview"] == "live" and loop.rt.governed
    assert errors and max(errors) <= 0.0005 + 1e-12
    assert 0.0 < loop.preview_calls / loop.tick_count < 0.2
    fixed, _notes, _errors = _run(cfg, 3.0, weight_set=1)
    st1 = fixed.status()
    assert st1["lifecycle"] == "ACTIVE", st1
    assert st1["road_preview"] == "unused" and not fixed.rt.governed
    assert fixed.preview_calls == 0 and fixed.preview_stream.window_start() >= 0


def test_loop_without_the_rigs_preview_runs_the_reading_schedule() -> None:
    """A rig that sends no RoadPreview (emulator.road_preview_s = 0), and one whose
    RoadPreview frames are lost for 1 s: the preview is not live, the schedule runs on
    the reading's thresholds and nothing faults; after the loss it is live again, and
    the loss and the recovery are notes."""
    cfg = default_config()
    loop, _n, _e = _run(cfg.replace(emulator={"road_preview_s": 0.0}), 2.0)
    assert loop.status()["road_preview"] == "no_frame"
    assert loop.preview_calls == 0 and not loop.rt.preview_schedule
    assert loop.status()["lifecycle"] == "ACTIVE"

    from hil.faults import FaultSchedule

    faults = FaultSchedule.from_list([(2.0, 3.0, "drop", {"frames": "preview"})])
    loop, notes, _e = _run(cfg, 3.2, faults)
    assert loop.status()["lifecycle"] == "ACTIVE"
    assert loop.status()["road_preview"] in ("filling", "short")
    assert not loop.rt.preview_schedule
    loop, notes, errors = _run(cfg, 3.6, faults)
    assert loop.status()["lifecycle"] == "ACTIVE"
    assert loop.status()["road_preview"] == "live" and loop.rt.preview_schedule
    assert loop.preview_stream.breaks == 1
    assert errors and max(errors) <= 0.0005 + 1e-12
    seen = [(n["road_preview"], n["why"]) for n in notes if "road_preview" in n]
    assert seen[0] == ("live", "live") and seen[-1] == ("live", "live")
    assert ("lost", "short") in seen


def test_a_run_with_the_rigs_preview_replays_bit_for_bit(tmp_path: Path) -> None:
    """The RoadPreview frames are rx frames like any other: a recorded run of the
    preview profile (lockstep timing, course) replays bit for bit, and the recording
    holds the note of the preview going live."""
    from hil.stepped_run import record_emulated_run
    from rig.recording.run_data import read_run
    from rig.replay.driver import replay_recording

    cfg = default_config()
    path = record_emulated_run(tmp_path / "preview.mcap", 1.5, cfg=cfg, seed=4,
                               lockstep_timing=True)
    res = replay_recording(path)
    assert res.same_controller and res.bit_exact, res.summary()
    run = read_run(path)
    notes = [e.detail for e in run.events if e.kind == "note" and "road_preview" in e.detail]
    assert [n["road_preview"] for n in notes] == ["live"]
    assert sum(1 for f in run.frames if f.is_rx and f.arbitration_id == ROAD_PREVIEW_ID) > 1400
