"""Closed-loop runner with a pluggable controller (the study's composition of ``hil.sim``).

``hil.sim.simulate`` takes a controller *name* and builds a :class:`BankRuntime`; the study
also needs controllers that are not in the bank (skyhook, full-state LQ, which reads the
true plant state) and per-tick traces of the firing weights.  :func:`run_closed_loop`
is the same tick as ``simulate`` (sensors -> controller -> PI force loop -> loop delay ->
plant; a controller fault or a sensor status bit latches the safe state; a non-finite
plant ends the run) with the controller given as an object::

    ctrl.reset()
    force_ref_n = ctrl.step(reading, plant)     # SensorReading, RigPlant (read only)
    ctrl.fault                                  # True: latch the safe state

``tests/test_study.py`` proves that with :class:`BankController` this loop reproduces
``simulate`` bit for bit, so both paths are the same experiment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from controller.artifact import Design
from controller.bank import BankRuntime
from controller.config import RigConfig
from controller.design import design_bank  # noqa: F401  (one code version per study run)
from controller.force_loop import PIForceLoop
from controller.kernels import Blending, StepFlag
from hil.metrics import compute_metrics, filter_signal, human_filter_tf
from hil.plant import PlantParams, RigPlant
from hil.roads import Road
from hil.sensors import SensorReading, SensorSuite
from hil.sim import MAX_INNER_STEP_S, SLAM_PENETRATION_M

# modules are imported here, before the study's worker processes fork, so that every run
# of one study uses the same code even while the tree is being edited
__all__ = ["BankController", "LoopResult", "StudyController", "lq_cost", "run_closed_loop"]

FloatArray = NDArray[np.float64]


class StudyController(Protocol):
    """What :func:`run_closed_loop` needs from a controller."""

    name: str

    def reset(self) -> None: ...

    def step(self, reading: SensorReading, plant: RigPlant) -> float: ...

    @property
    def fault(self) -> bool: ...


class BankController:
    """The LQG bank (``BankRuntime``) behind the study interface (reads sensors only)."""

    def __init__(self, design: Design, cfg: RigConfig, blending: str, weight_set: int,
                 road: Road) -> None:
        modes = {"lqg": Blending.SINGLE, "fuzzy": Blending.FUZZY, "bayes": Blending.BAYES,
                 "moving": Blending.MOVING}
        if blending not in modes:
            raise ValueError(f"bank blending {blending!r}: allowed {sorted(modes)}")
        self.name = blending
        self.rt = BankRuntime(design, blending=modes[blending], weight_set=weight_set, cfg=cfg)
        gd = road.roughness_gd if road.roughness_gd is not None else cfg.noise.nominal_roughness_gd
        self.rt.set_road(road.speed_mps, gd)
        self._mask = int(StepFlag.NONFINITE_INPUT | StepFlag.NONFINITE_STATE
                         | StepFlag.DIVERGED)
        self._no_rule = int(StepFlag.NO_RULE_FIRED)
        self.no_rule_ticks = 0
        self.ticks = 0
        self.rt.reset()

    def reset(self) -> None:
        self.rt.reset()
        self.no_rule_ticks = 0
        self.ticks = 0

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        u = float(self.rt.step(reading.rattlespace_m, reading.accel_mps2, reading.force_n))
        self.ticks += 1
        if int(self.rt.flags) & self._no_rule:
            self.no_rule_ticks += 1
        return u

    @property
    def flags(self) -> int:
        return int(self.rt.flags)

    def diagnostics(self) -> dict[str, float]:
        """Fraction of ticks in which no fuzzy rule fired (fallback force used)."""
        return {"no_rule_fired_fraction": self.no_rule_ticks / self.ticks if self.ticks
                else 0.0}

    @property
    def fault(self) -> bool:
        return bool(int(self.rt.flags) & self._mask)

    @property
    def firing_weight(self) -> FloatArray:
        return np.asarray(self.rt.firing_weight)

    @property
    def q(self) -> FloatArray:
        return np.asarray(self.rt.q)


@dataclass
class LoopResult:
    metrics: dict[str, float]
    traces: dict[str, FloatArray]
    controller: str
    info: dict[str, Any] = field(default_factory=dict)


def lq_cost(metrics: dict[str, float], weights: tuple[float, ...] | list[float]) -> float:
    """The Eq. 2.5 cost rate rho4 <y_f^2> + rho1 <x2^2> + rho2 <r^2> + rho3 <u^2> of a run
    (deviations from static; y_f = F(s)-filtered true sprung acceleration, u = actuator
    force) -- what the LQ gain minimises, unlike any single metric."""
    rho1, rho2, rho3, rho4 = (float(w) for w in weights)
    return (rho4 * metrics["absorbed_power"] + rho1 * metrics["tire_deflection_rms_m"] ** 2
            + rho2 * metrics["rattlespace_rms_m"] ** 2 + rho3 * metrics["force_rms_n"] ** 2)


def run_closed_loop(cfg: RigConfig, road: Road, controller: StudyController | None, *,
                    delay_ticks: int = 0, seed: int | None = None,
                    params: PlantParams | None = None, settle_s: float = 0.0,
                    lvdt_zero: str = "nominal", record_weights: bool = False,
                    latch_on_sensor_status: bool = True,
                    delay_point: str = "spool") -> LoopResult:
    """Closed-loop run over ``road`` (sampled at ``cfg.sample_time_s``); ``controller``
    None = passive (bypass open).  Same tick and metrics as ``hil.sim.simulate`` plus
    ``tire_deflection_rms_m`` and, with ``record_weights``, the traces ``firing_weight``
    and ``q`` (ticks x models) of a bank controller.

    ``delay_ticks`` ticks pass between computing and applying.  ``delay_point`` is where
    that loop delay sits: ``"spool"`` (the valve command is late, as in ``simulate``: the
    PI force loop runs on the controller side of the bus, so the delay is inside the
    force loop too) or ``"force_ref"`` (the force reference is late; the PI force loop
    runs locally at the valve without delay).
    """
    if delay_ticks < 0:
        raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
    if delay_point not in ("spool", "force_ref"):
        raise ValueError(f"delay_point {delay_point!r}: allowed 'spool', 'force_ref'")
    delay_ref = delay_point == "force_ref" and delay_ticks > 0
    dt = cfg.sample_time_s
    if not math.isclose(road.dt_s, dt, rel_tol=1e-9):
        raise ValueError(f"road sampled at {road.dt_s} s but the controller runs at {dt} s")
    n = road.n_ticks
    substeps = max(1, math.ceil(dt / MAX_INNER_STEP_S - 1e-9))
    plant = RigPlant(cfg, params, substeps=substeps, lvdt_zero=lvdt_zero)
    sensors = SensorSuite(cfg.sensors, cfg.noise, seed, dt_s=dt)
    pi: Any = None
    if controller is not None:
        controller.reset()
        pi = PIForceLoop(cfg.force_loop, dt)
    keys = ("rattlespace_m", "accel_mps2", "force_n", "force_ref_n", "spool_cmd",
            "tire_force_n", "hydraulic_power_w", "off_ground_s", "bump_stop_s",
            "tire_deflection_m", "spool_computed")
    tr: dict[str, Any] = {k: np.zeros(n) for k in keys}
    weights_tr: FloatArray | None = None
    q_tr: FloatArray | None = None
    if record_weights and controller is not None and hasattr(controller, "firing_weight"):
        nm = np.asarray(getattr(controller, "firing_weight")).shape[0]  # noqa: B009
        weights_tr, q_tr = np.zeros((n, nm)), np.zeros((n, nm))
    # exactly delay_ticks ticks between computing and applying (hil.sim.simulate's queue
    # holds delay_ticks + 1 entries, i.e. one tick more: reported to its owner)
    queue = [0.0] * delay_ticks
    height, velocity = road.height_m, road.velocity_mps
    faulted = False
    n_faults = 0
    fault_tick = -1
    fault_flags = 0
    sensor_status_ticks = 0
    n_done = n
    for k in range(n):
        r_true, f_true, a_true = plant.true_signals()
        rd = sensors.measure(r_true, f_true, a_true)
        if rd.status:
            sensor_status_ticks += 1
        spool, fref, bypass = 0.0, 0.0, True
        if controller is not None and not faulted:
            fref = controller.step(rd, plant)
            if controller.fault or (latch_on_sensor_status and rd.status):
                faulted = True
                n_faults += 1
                fault_tick = k
                fault_flags = int(getattr(controller, "flags", 0)) | (int(rd.status) << 8)
                fref = 0.0
            else:
                if delay_ref:
                    queue.append(fref)
                    fref = queue.pop(0)
                spool = pi.step(fref, rd.force_n)
                bypass = False
            if weights_tr is not None and q_tr is not None:
                weights_tr[k] = getattr(controller, "firing_weight")  # noqa: B009
                q_tr[k] = getattr(controller, "q")  # noqa: B009
        tr["spool_computed"][k] = spool
        if delay_ticks and not delay_ref:
            queue.append(spool)
            spool = queue.pop(0)
        plant.advance(dt, spool, bypass, height[k], velocity[k])
        tr["rattlespace_m"][k] = r_true
        tr["accel_mps2"][k] = a_true
        tr["force_n"][k] = f_true
        tr["force_ref_n"][k] = fref
        tr["spool_cmd"][k] = spool
        tr["tire_force_n"][k] = plant.diag[0]
        tr["hydraulic_power_w"][k] = plant.diag[2]
        tr["off_ground_s"][k] = plant.diag[3]
        tr["bump_stop_s"][k] = plant.diag[4]
        tr["tire_deflection_m"][k] = plant.state[1]
        if plant.nonfinite:
            n_done = k + 1
            break
    if n_done < n:
        tr = {key: v[:n_done] for key, v in tr.items()}
        if weights_tr is not None and q_tr is not None:
            weights_tr, q_tr = weights_tr[:n_done], q_tr[:n_done]
    tr["time_s"] = np.arange(n_done) * dt
    tr["road_height_m"] = height[:n_done].copy()
    v = cfg.vehicle
    static_load = (plant.p[0] + plant.p[1]) * v.gravity_mps2
    metrics = compute_metrics(dt, tr["accel_mps2"], tr["rattlespace_m"], tr["tire_force_n"],
                              static_load, tr["force_n"], tr["hydraulic_power_w"],
                              tr["off_ground_s"], tr["bump_stop_s"], settle_s=settle_s,
                              human_filter=(cfg.design.human_filter_num,
                                            cfg.design.human_filter_den))
    zero_offset = plant.static_rattlespace_m - float(plant.p[12])
    penetration = (float(np.max(np.abs(tr["rattlespace_m"] + zero_offset)))
                   - v.rattlespace_travel_m) if n_done else 0.0
    slam = penetration > SLAM_PENETRATION_M
    i0 = min(round(settle_s / dt), max(n_done - 1, 0))
    x2_dev = tr["tire_deflection_m"][i0:] - plant.equilibrium()[1]
    metrics.update({
        "duration_s": n_done * dt,
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
    diag = getattr(controller, "diagnostics", None)
    if callable(diag):
        metrics.update(diag())
    if weights_tr is not None and q_tr is not None:
        tr["firing_weight"] = weights_tr
        tr["q"] = q_tr
    num, den = human_filter_tf(cfg.design.human_filter_num, cfg.design.human_filter_den)
    tr["filtered_accel"] = filter_signal(tr["accel_mps2"], num, den, dt)
    info = {"substeps": substeps, "delay_ticks": delay_ticks, "dt_s": dt,
            "speed_mps": road.speed_mps, "seed": sensors.seed}
    name = controller.name if controller is not None else "passive"
    return LoopResult(metrics, tr, name, info)
