"""A deterministic emulated recording: the control loop and the emulated rig's CAN node
(:class:`hil.node.RigNode`) in lockstep on a python-can virtual bus, tick-stepped with
no sleeping, the recorder on (:func:`record_emulated_run`).

The loop is the one ``rig run`` builds (:func:`rig.service.assembly.build_control_loop`)
with a :class:`rig.recording.recorder.RunRecorder` (blocking, so nothing is dropped), on
a stepped clock: each tick's wake-up lateness and compute time are drawn from a seeded
generator, so the recording carries the timing-dependent frames that a replay must
reproduce.  Used by the replay benchmark (``bench/replay_bench.py``) and the tests of
recording, replay, reports and identification.  With ``lockstep_timing`` they are zero,
the timing of a lockstep run (:mod:`rig.rt.lockstep`): the run is then the one ``rig demo
--timing lockstep`` makes with two processes on a socket-pair wire, bit for bit.
"""

from __future__ import annotations

import tempfile
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np

from controller.artifact import load_design, save_design
from controller.config import RigConfig, config_to_toml, default_config
from hil.faults import FaultSchedule
from hil.node import RigNode
from hil.sim.roads import make_road
from rig.bus.core import open_bus, shutdown_all
from rig.design_cache import design_for
from rig.recording.recorder import RunRecorder
from rig.rt.lockstep import START_NS
from rig.rt.pacing import SteppedClock
from rig.service.assembly import LoopSettings, build_control_loop

__all__ = ["record_emulated_run"]


def record_emulated_run(path: str | Path, seconds: float, *, cfg: RigConfig | None = None,
                        design_bytes: bytes | None = None, arm_at_s: float = 0.1,
                        road: str = "rough-course", seed: int = 1,
                        commands: dict[int, tuple[str, Any]] | None = None,
                        late_ticks: dict[int, int] | None = None,
                        faults: FaultSchedule | None = None,
                        shutdown: bool = True, warmup_ticks: int = 20,
                        road_speed_mps: float | None = None,
                        wrap_bus: Callable[[can.BusABC], can.BusABC] | None = None,
                        before_tick: Callable[[int, can.BusABC], None] | None = None,
                        excite: bool = False, road_s: float | None = None,
                        lockstep_timing: bool = False) -> Path:
    """Record ``seconds`` of the loop against :class:`hil.node.RigNode` (virtual bus,
    tick-stepped, no sleeping) into ``path``.  Wake-up lateness and compute time are
    drawn (seeded) so that replay has to reproduce the timing-dependent frames too;
    ``late_ticks`` {tick: lateness_ns} adds overruns, ``commands`` {tick: (name, arg)}
    operator commands (applied before that tick).  ``wrap_bus`` wraps the controller's
    bus (a test double that raises in recv / send); ``before_tick(k, rig_bus)`` runs
    after the rig's tick k, before the loop's (e.g. to inject error frames).
    ``excite``: an identification run (the loop plays ``cfg.excitation`` from the arm;
    pass ``road="flat"``).  ``road_s``: the length of road generated (default the run's,
    at most 120 s; replayed cyclically).  ``lockstep_timing``: zero lateness and compute
    time, as the loop of a lockstep run records (``late_ticks`` still apply).
    Returns ``path``."""
    cfg = cfg or default_config()
    if design_bytes is None:
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "design.npz"
            save_design(design_for(cfg), p)
            design_bytes = p.read_bytes()
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "design.npz"
        p.write_bytes(design_bytes)
        design = load_design(p)
    dt = cfg.sample_time_s
    n = round(seconds / dt)
    speed = cfg.noise.nominal_speed_mps if road_speed_mps is None else road_speed_mps
    rd = make_road(road, speed, min(seconds, 120.0) if road_s is None else road_s, dt, seed)
    channel = f"stepped-run-{uuid.uuid4().hex}"
    ctl_bus = open_bus(cfg.can, role="controller", interface="virtual", channel=channel)
    rig_bus = open_bus(cfg.can, role="rig", interface="virtual", channel=channel)
    node = RigNode(rig_bus, cfg, rd, faults, seed=seed, record_ticks=16)
    settings = LoopSettings(blending=0, weight_set=cfg.design.weight_set,
                            warmup_ticks=warmup_ticks, excite=excite)
    clock = SteppedClock()
    rec = RunRecorder(path, cfg.recording, config_toml=config_to_toml(cfg),
                      design_bytes=design_bytes,
                      metadata={"source": "hil.stepped_run", "seed": seed,
                                **settings.metadata()},
                      clock="stepped", clock_offset_ns=1_700_000_000_000_000_000,
                      blocking=True)
    loop_bus = ctl_bus if wrap_bus is None else wrap_bus(ctl_bus)
    loop = build_control_loop(cfg, design, loop_bus, settings, recorder=rec, clock_ns=clock)
    rng = np.random.default_rng(seed)
    if lockstep_timing:
        lateness, compute = [0] * n, [0] * n
    else:
        lateness = rng.integers(2_000, 90_000, size=n).tolist()
        compute = rng.integers(15_000, 60_000, size=n).tolist()
    for k, v in (late_ticks or {}).items():
        if 0 <= k < n:
            lateness[k] = v
    cmds = dict(commands or {})
    arm_tick = round(arm_at_s / dt)
    cmds.setdefault(arm_tick, ("arm", None))
    period = loop.period_ns
    t = START_NS
    try:
        for k in range(n):
            node.tick()
            if before_tick is not None:
                before_tick(k, rig_bus)
            c = cmds.get(k)
            if c is not None:
                loop.request(c[0], c[1], timeout_s=None)
            clock.now_ns = t + compute[k]
            loop.tick(t, lateness[k])
            t += period
        if shutdown:
            clock.now_ns = t
            loop.shutdown("end of recording")
    finally:
        rec.close()
        shutdown_all([ctl_bus, rig_bus])
    if rec.error or rec.dropped:
        raise RuntimeError(f"recording failed: {rec.error}, dropped {rec.dropped}")
    return Path(path)
