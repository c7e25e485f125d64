"""Fast offline closed-loop simulation: controller called directly, no bus, no sleeping.

Per tick k (controller period dt = 1 / sample rate):

    1. the sensors sample the plant            (SensorSuite, seeded)
    2. the controller computes a force reference from the readings
       (a :class:`LoopController`; passive: no controller, bypass open)
    3. the PI force loop turns it into a spool command (PIForceLoop)
    4. the command reaches the valve exactly ``delay_ticks`` ticks later (loop delay;
       ``delay_point="force_ref"`` delays the force reference instead, in front of a PI
       force loop that runs locally at the valve)
    5. the plant advances one tick with the road's height/velocity of tick k

A controller fault (``fault``: StepFlag NONFINITE_* / DIVERGED of the bank) or a sensor
status bit latches the safe state like the service does: bypass open, spool centred, for
the rest of the run.  A degraded bank (StepFlag.DEGRADED) is no fault: it keeps
controlling with its conservative law (zero force reference, controller/monitor.py).
A non-finite plant state ends the run early and marks it unstable.

This module holds the one tick loop, :func:`run_closed_loop`, which takes the controller
as an object::

    ctrl.reset()
    force_ref_n = ctrl.step(reading, plant)     # SensorReading, RigPlant (read only)
    ctrl.fault                                  # True: latch the safe state

:class:`BankController` is the LQG bank (``BankRuntime``) behind that interface;
:func:`simulate` runs a controller of :data:`CONTROLLERS` by name: passive (bypass open),
``zero-force`` (:class:`ZeroForceController`: bypass closed, force reference 0 through the
same force loop -- what the closed actuator itself costs), ``skyhook``
(:class:`hil.sim.skyhook.SkyhookController` with its tuned :data:`hil.sim.skyhook.DEFAULT_GAINS`)
or a bank mode.  The study (``hil.study``) adds other controllers (skyhook gain search,
full-state LQ) through the same loop.
"""

from __future__ import annotations

import functools
import math
import operator
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from controller.arrays import FloatArray
from controller.config import RigConfig, design_config_hash
from controller.memo import memoised
from controller.metrics import compute_metrics
from controller.modes import BANK_MODES, CONTROLLER_MODES
from controller.road_preview import cached_road_preview
from hil.sim.plant import PlantParams, RigPlant
from hil.sim.roads import Road
from hil.sim.sensors import SensorReading, SensorSuite
from hil.sim.skyhook import DEFAULT_GAINS, SkyhookController

if TYPE_CHECKING:
    from controller.artifact import Design

__all__ = ["BANK_CONTROLLERS", "CONTROLLERS", "DELAY_POINTS", "BankController",
           "LoopController", "SimResult", "ZeroForceController", "cached_design",
           "config_from_text",
           "run_closed_loop", "simulate"]


#: the bank modes :func:`simulate` runs (they need a design)
BANK_CONTROLLERS = tuple(BANK_MODES)
CONTROLLERS = CONTROLLER_MODES
#: where the loop delay sits: before the valve (the PI force loop runs on the controller
#: side of the bus, inside the delay) or before a PI force loop local to the valve
DELAY_POINTS = ("spool", "force_ref")
#: penetration into a bump stop beyond which a run counts as slamming (unstable) [m]
SLAM_PENETRATION_M = 0.01
#: inner integration step bound of the plant [s]
MAX_INNER_STEP_S = 5e-5
#: per-tick traces of every run (true plant signals unless ``meas_``)
TRACE_KEYS = ("rattlespace_m", "accel_mps2", "force_n", "force_ref_n", "spool_cmd",
              "spool_computed", "tire_force_n", "tire_deflection_m", "hydraulic_power_w",
              "off_ground_s", "bump_stop_s", "meas_rattlespace_m", "meas_force_n",
              "meas_accel_mps2", "sprung_mass_kg", "sprung_mass_est_kg")


class LoopController(Protocol):
    """What :func:`run_closed_loop` needs from a controller."""

    name: str

    def reset(self) -> None: ...

    def step(self, reading: SensorReading, plant: RigPlant) -> float: ...

    @property
    def fault(self) -> bool: ...


@dataclass
class SimResult:
    metrics: dict[str, float]
    traces: dict[str, FloatArray]
    controller: str
    weight_set: int
    road: str
    info: dict[str, Any] = field(default_factory=dict)


_DESIGNS: dict[str, Design] = {}


@functools.lru_cache(maxsize=8)
def config_from_text(toml_text: str) -> RigConfig:
    """The configuration of ``config_to_toml`` text, memoised in this process: what a
    batch of runs (``hil.batch``) sends to its workers instead of an artifact."""
    from controller.config import parse_config, parse_toml
    return parse_config(parse_toml(toml_text, "<batch configuration>"))


def cached_design(cfg: RigConfig) -> Design:
    """``design_bank(cfg)``, memoised in this process per hash of the sections the design
    reads (:func:`controller.config.design_config_hash`): configurations that differ only
    in e.g. the emulated plant share one design; across processes by the on-disk design
    cache (:mod:`rig.design_cache`)."""
    from rig.design_cache import design_for
    return memoised(_DESIGNS, design_config_hash(cfg), lambda: design_for(cfg))


class BankController:
    """The LQG bank (``BankRuntime``, mode ``blending``) behind :class:`LoopController`
    (reads the sensors only).  ``flags`` are the StepFlag bits of the last tick."""

    def __init__(self, design: Design, cfg: RigConfig, blending: str, weight_set: int,
                 road: Road) -> None:
        from controller.runtime.bank import BankRuntime
        from controller.runtime.kernels import Blending, StepFlag
        modes = {"lqg": Blending.LQG, "fuzzy": Blending.FUZZY, "bayes": Blending.BAYES,
                 "moving": Blending.MOVING}
        if blending not in modes:
            raise ValueError(f"bank blending {blending!r}: allowed {sorted(modes)}")
        self.name = blending
        self.weight_set = weight_set
        self.rt = BankRuntime(design, blending=modes[blending], weight_set=weight_set, cfg=cfg)
        gd = road.roughness_gd if road.roughness_gd is not None else cfg.noise.nominal_roughness_gd
        self.rt.set_road(road.speed_mps, gd)
        # road preview (controller/road_preview.py): the simulator knows the road ahead
        # (a fixed weight set other than the governed comfort set never calls it), unless
        # the emulated rig sends none ([emulator] road_preview_s = 0): then the bank's
        # step runs without it, as the loop's does
        self.preview = cached_road_preview(cfg) if cfg.emulator.road_preview_s > 0 else None
        self.rt.use_preview_schedule(self.preview is not None)   # the preview is always live
        self._road_velocity = road.velocity_mps
        self._mask = int(StepFlag.NONFINITE_INPUT | StepFlag.NONFINITE_STATE
                         | StepFlag.DIVERGED)
        self._no_rule = int(StepFlag.NO_RULE_FIRED)
        self._degraded = int(StepFlag.DEGRADED)
        self._off_centre = int(StepFlag.RIDE_HEIGHT)
        self.reset()

    def reset(self) -> None:
        self.rt.reset()
        self.flags = 0
        self.no_rule_ticks = 0
        self.degraded_ticks = 0
        self.ticks = 0
        self.comfort_share_sum = 0.0
        self.off_centre_ticks = 0
        self.off_centre_first_tick = -1
        self.ride_height_max_m = 0.0
        self.preview_calls = 0

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        pv = self.preview
        rt = self.rt
        if pv is not None:      # the preview's check and the step in one call, as the loop
            u = float(rt.step_previewed(pv, reading.rattlespace_m, reading.accel_mps2,
                                        reading.force_n, self._road_velocity, self.ticks))
            if rt.preview_called:
                self.preview_calls += 1
        else:
            u = float(rt.step(reading.rattlespace_m, reading.accel_mps2, reading.force_n))
        self.flags = flags = self.rt.flag_bits
        self.ticks += 1
        self.comfort_share_sum += self.rt.comfort_share
        if flags & self._no_rule:
            self.no_rule_ticks += 1
        if flags & self._degraded:
            self.degraded_ticks += 1
        if flags & self._off_centre:
            if self.off_centre_ticks == 0:
                self.off_centre_first_tick = self.ticks - 1
            self.off_centre_ticks += 1
        h = abs(self.rt.ride_height_m)
        if h > self.ride_height_max_m:
            self.ride_height_max_m = h
        return u

    @property
    def fault(self) -> bool:
        return bool(self.flags & self._mask)

    @property
    def sprung_mass_est_kg(self) -> float:
        """The bank's sprung-mass estimate [kg] (controller/mass_estimator.py)."""
        return float(self.rt.sprung_mass_est_kg)

    def diagnostics(self) -> dict[str, float]:
        """Fractions of ticks in which no fuzzy rule fired (fallback force used) and in
        which the estimator monitor had the bank degraded (conservative law), the
        number of degradations, the fractions of ticks in which the end-stop guard took
        force away and in which its rate lead took more than the distance law (§9.6) and
        in which the end-stop barrier limited the force (docs/design.md §9.7), and the
        stop-contact monitor's view
        (§9.8): contact time by the LVDT reading [s], contact episodes, stop degradations
        and the fraction of ticks stop-degraded (the plant's own time on the stops is
        ``bump_stop_time_s``), the travel schedule's mean comfort share (§12; 0 when
        the schedule is off), the fraction of ticks in which the road preview called
        the travel law (controller/road_preview.py; 0 when it is off) and in which its
        stop clamp clipped the force toward a stop (§12), and the
        ride-height monitor's (§9.9): the largest |ride
        height| [m], the time off centre [s] and when it first found the body off centre
        [s of the run; -1 never]."""
        n = self.ticks
        c = self.rt.counters()
        dt = self.rt.stop_contact_settings.tick_s
        return {"no_rule_fired_fraction": self.no_rule_ticks / n if n else 0.0,
                "degraded_fraction": self.degraded_ticks / n if n else 0.0,
                "degradations": float(c["degradations"]),
                "stop_barrier_fraction": c["stop_barrier_ticks"] / n if n else 0.0,
                "stop_guard_fraction": c["stop_guard_ticks"] / n if n else 0.0,
                "stop_guard_lead_fraction": c["stop_guard_lead_ticks"] / n if n else 0.0,
                "stop_contact_measured_s": c["stop_contact_ticks"] * dt,
                "stop_contact_episodes": float(c["stop_contact_episodes"]),
                "stop_degradations": float(c["stop_degradations"]),
                "stop_degraded_fraction": c["stop_degraded_ticks"] / n if n else 0.0,
                "schedule_comfort_share": self.comfort_share_sum / n if n else 0.0,
                "preview_call_fraction": self.preview_calls / n if n else 0.0,
                "preview_clamp_fraction": c["preview_clamp_ticks"] / n if n else 0.0,
                "ride_height_max_m": self.ride_height_max_m,
                "ride_height_off_centre_s": self.off_centre_ticks * dt,
                "ride_height_first_off_centre_s": (self.off_centre_first_tick * dt
                                                   if self.off_centre_first_tick >= 0
                                                   else -1.0)}

    @property
    def firing_weight(self) -> FloatArray:
        return np.asarray(self.rt.firing_weight)

    @property
    def q(self) -> FloatArray:
        return np.asarray(self.rt.q)


class ZeroForceController:
    """Force reference 0 with the valve in closed-loop force control (bypass closed): the
    actuator's own cost, the baseline any active law is added to.  Faults like the
    service on a non-finite sensor reading."""

    name = "zero-force"

    def __init__(self) -> None:
        self._fault = False

    def reset(self) -> None:
        self._fault = False

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        if not (math.isfinite(reading.rattlespace_m) and math.isfinite(reading.accel_mps2)
                and math.isfinite(reading.force_n)):
            self._fault = True
        return 0.0

    @property
    def fault(self) -> bool:
        return self._fault


def simulate(cfg: RigConfig, road: Road, controller: str = "fuzzy", weight_set: int = 1, *,
             delay_ticks: int = 0, seed: int | None = None, params: PlantParams | None = None,
             design: Design | None = None, settle_s: float = 0.0,
             latch_on_sensor_status: bool = True, observe_s: float = 0.0) -> SimResult:
    """Closed-loop run of ``controller`` (one of :data:`CONTROLLERS`) over ``road``
    (sampled at the controller rate): :func:`run_closed_loop` with a :class:`BankController`,
    :class:`ZeroForceController` or :class:`hil.sim.skyhook.SkyhookController`.

    ``params`` perturbs the plant (default: the emulated rig of ``cfg.emulator``; the
    controller keeps its design from the configuration); ``design`` defaults to
    ``design_bank(cfg)`` (memoised, bank modes only); ``observe_s``: the time before
    arming (:func:`run_closed_loop`).  Raises ValueError on bad arguments.
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller {controller!r}: use one of "
                         f"{', '.join(CONTROLLERS)}")
    if weight_set < 0 or weight_set > len(cfg.design.weight_sets):
        raise ValueError(f"weight set {weight_set} not in 0..{len(cfg.design.weight_sets)} "
                         f"(0 = travel schedule)")
    ctrl: LoopController | None = None
    if controller == "zero-force":
        ctrl = ZeroForceController()
    elif controller == "skyhook":
        ctrl = SkyhookController(cfg, DEFAULT_GAINS)
    elif controller != "passive":
        design = design if design is not None else cached_design(cfg)
        ctrl = BankController(design, cfg, controller, weight_set, road)
    res = run_closed_loop(cfg, road, ctrl, delay_ticks=delay_ticks, seed=seed, params=params,
                          settle_s=settle_s, latch_on_sensor_status=latch_on_sensor_status,
                          observe_s=observe_s)
    res.weight_set = weight_set
    return res


def run_closed_loop(cfg: RigConfig, road: Road, controller: LoopController | None, *,
                    delay_ticks: int = 0, delay_point: str = "spool", seed: int | None = None,
                    params: PlantParams | None = None, settle_s: float = 0.0,
                    latch_on_sensor_status: bool = True,
                    record_weights: bool = False, observe_s: float = 0.0) -> SimResult:
    """Closed-loop run of ``controller`` (None = passive, bypass open) over ``road``
    (sampled at ``cfg.sample_time_s``); ``controller.reset()`` is called first.

    ``observe_s`` [s] is the time before arming, as the service runs: the controller
    steps from the first sensor reading (estimator, mass estimate, layer choice, monitors;
    a fault latches) while the valve is in its safe state (bypass open, no force loop),
    and is armed from then on.  The metrics, the slam check and ``tire_deflection_rms_m``
    cover the armed time only (after ``settle_s`` more), so a passive run with the same
    ``observe_s`` is the reference for the same window; the road must cover both.

    ``delay_ticks`` ticks pass between computing and applying; ``delay_point`` (one of
    :data:`DELAY_POINTS`) is what is late: ``"spool"`` the valve command,
    ``"force_ref"`` the force reference (PI force loop local to the valve, undelayed).
    ``record_weights`` adds the traces ``firing_weight`` and ``q`` (ticks x models) of a
    controller that has them (:class:`BankController`).  The metrics are
    :func:`controller.metrics.compute_metrics` plus run bookkeeping, ``tire_deflection_rms_m``
    (deviation from static, after ``settle_s``) and the controller's ``diagnostics()``.
    Raises ValueError on bad arguments.
    """
    if delay_ticks < 0:
        raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
    if delay_point not in DELAY_POINTS:
        raise ValueError(f"delay_point {delay_point!r}: allowed {', '.join(DELAY_POINTS)}")
    if not (math.isfinite(observe_s) and observe_s >= 0):
        raise ValueError(f"observe_s must be finite and >= 0, got {observe_s}")
    delay_ref = delay_point == "force_ref" and delay_ticks > 0
    delay_spool = delay_ticks > 0 and not delay_ref
    dt = cfg.sample_time_s
    if not math.isclose(road.dt_s, dt, rel_tol=1e-9):
        raise ValueError(f"road sampled at {road.dt_s} s but the controller runs at {dt} s")
    n = road.n_ticks
    n_observe = round(observe_s / dt)
    if n_observe >= n:
        raise ValueError(f"observe_s {observe_s} s leaves no armed tick of the "
                         f"{n * dt:g} s road")
    substeps = max(1, math.ceil(dt / MAX_INNER_STEP_S - 1e-9))
    plant = RigPlant(cfg, params, substeps=substeps)
    sensors = SensorSuite(cfg.sensors, cfg.noise, seed, dt_s=dt)
    pi: Any = None
    ctrl_step: Any = None
    if controller is not None:
        from controller.runtime.force_loop import PIForceLoop
        controller.reset()
        pi = PIForceLoop.from_config(cfg)
        ctrl_step = controller.step
    tr: dict[str, FloatArray] = {k: np.zeros(n) for k in TRACE_KEYS}
    weights_tr: FloatArray | None = None
    q_tr: FloatArray | None = None
    if record_weights and controller is not None and hasattr(controller, "firing_weight"):
        nm = np.asarray(getattr(controller, "firing_weight")).shape[0]  # noqa: B009
        weights_tr, q_tr = np.zeros((n, nm)), np.zeros((n, nm))
    # the valve (or the local PI) gets what was computed exactly delay_ticks ticks earlier
    queue = [0.0] * delay_ticks
    height, velocity = road.height_m, road.velocity_mps
    faulted = False
    n_faults = 0
    fault_tick = -1
    fault_flags = 0
    sensor_status_ticks = 0
    n_done = n
    adv = plant.advance
    meas = sensors.measure
    diag, state = plant.diag, plant.state          # updated in place by the plant
    plant_p = plant.p                              # p[0]: the sprung mass (ballast changes)
    (t_r, t_a, t_f, t_fref, t_spool, t_comp, t_tire, t_x2, t_pow, t_off, t_bump, t_mr, t_mf,
     t_ma, t_mass, t_mest) = (tr[k] for k in TRACE_KEYS)
    # the controller's sprung-mass estimate, where it has one (NaN otherwise)
    mass_est = (operator.attrgetter("sprung_mass_est_kg")
                if controller is not None and hasattr(controller, "sprung_mass_est_kg")
                else None)
    t_mest[:] = math.nan
    t0 = time.perf_counter()
    for k in range(n):
        r_true, f_true, a_true = plant.true_signals()
        rd = meas(r_true, f_true, a_true)
        if rd.status:
            sensor_status_ticks += 1
        spool = 0.0
        fref = 0.0
        bypass = True
        if controller is not None and not faulted:
            fref = ctrl_step(rd, plant)
            if controller.fault or (latch_on_sensor_status and rd.status):
                faulted = True
                n_faults += 1
                fault_tick = k
                fault_flags = int(getattr(controller, "flags", 0)) | (int(rd.status) << 8)
                fref = 0.0
            elif k < n_observe:         # not armed yet: observing, valve safe
                fref = 0.0
            else:
                if delay_ref:
                    queue.append(fref)
                    fref = queue.pop(0)
                spool = pi.step(fref, rd.force_n, rd.rattlespace_m)
                bypass = False
            if mass_est is not None:
                t_mest[k] = mass_est(controller)
            if weights_tr is not None and q_tr is not None:
                weights_tr[k] = getattr(controller, "firing_weight")  # noqa: B009
                q_tr[k] = getattr(controller, "q")  # noqa: B009
        t_comp[k] = spool
        if delay_spool:
            queue.append(spool)
            spool = queue.pop(0)
        t_mass[k] = plant_p[0]
        adv(dt, spool, bypass, height[k], velocity[k])
        t_r[k] = r_true
        t_a[k] = a_true
        t_f[k] = f_true
        t_fref[k] = fref
        t_spool[k] = spool
        t_tire[k] = diag[0]
        t_pow[k] = diag[2]
        t_off[k] = diag[3]
        t_bump[k] = diag[4]
        t_x2[k] = state[1]
        t_mr[k] = rd.rattlespace_m
        t_mf[k] = rd.force_n
        t_ma[k] = rd.accel_mps2
        if plant.nonfinite:
            n_done = k + 1
            break
    wall = time.perf_counter() - t0
    if n_done < n:
        tr = {key: v[:n_done] for key, v in tr.items()}
        if weights_tr is not None and q_tr is not None:
            weights_tr, q_tr = weights_tr[:n_done], q_tr[:n_done]
    tr["time_s"] = np.arange(n_done, dtype=np.float64) * dt
    tr["road_height_m"] = height[:n_done].copy()
    if weights_tr is not None and q_tr is not None:
        tr["firing_weight"] = weights_tr
        tr["q"] = q_tr
    v = cfg.vehicle
    static_load = (plant.p[0] + plant.p[1]) * v.gravity_mps2
    metrics = compute_metrics(dt, tr["accel_mps2"], tr["rattlespace_m"], tr["tire_force_n"],
                              static_load, tr["force_n"], tr["hydraulic_power_w"],
                              tr["off_ground_s"], tr["bump_stop_s"],
                              settle_s=n_observe * dt + settle_s,
                              human_filter=(cfg.design.human_filter_num,
                                            cfg.design.human_filter_den))
    zero_offset = plant.static_rattlespace_m - float(plant.p[12])   # LVDT zero - r0
    armed_r = tr["rattlespace_m"][n_observe:]
    penetration = (float(np.max(np.abs(armed_r + zero_offset)))
                   - v.rattlespace_travel_m) if armed_r.size else 0.0
    slam = penetration > SLAM_PENETRATION_M
    i0 = min(n_observe + round(settle_s / dt), max(n_done - 1, 0))
    x2_dev = tr["tire_deflection_m"][i0:] - plant.equilibrium()[1]
    metrics.update({
        "duration_s": n_done * dt,
        "realtime_factor": (n_done * dt / wall) if wall > 0 else math.inf,
        "n_faults": float(n_faults),
        "fault_time_s": fault_tick * dt if fault_tick >= 0 else -1.0,
        "fault_flags": float(fault_flags),
        "sensor_status_ticks": float(sensor_status_ticks),
        "bump_stop_slam": float(slam),
        "nonfinite": float(plant.nonfinite),
        "unstable": float(plant.nonfinite or slam),
        "tire_deflection_rms_m": float(np.sqrt(np.mean(np.square(x2_dev))))
        if x2_dev.size else math.nan,
    })
    if mass_est is not None and n_done:     # the controller's estimate at the end / true mass
        metrics["sprung_mass_est_ratio"] = float(tr["sprung_mass_est_kg"][-1]
                                                 / tr["sprung_mass_kg"][-1])
    diagnostics = getattr(controller, "diagnostics", None)
    if callable(diagnostics):
        metrics.update(diagnostics())
    info = {"substeps": substeps, "delay_ticks": delay_ticks, "delay_point": delay_point,
            "dt_s": dt, "observe_s": n_observe * dt, "speed_mps": road.speed_mps,
            "seed": sensors.seed}
    name = controller.name if controller is not None else "passive"
    return SimResult(metrics, tr, name, int(getattr(controller, "weight_set", 0)), road.name,
                     info)
