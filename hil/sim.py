"""Fast offline closed-loop simulation: controller called directly, no bus, no sleeping.

Per tick k (controller period dt = 1 / sample rate):

    1. the sensors sample the plant            (SensorSuite, seeded)
    2. the controller computes a force reference from the readings
       (BankRuntime.step; passive: no controller, bypass open)
    3. the PI force loop turns it into a spool command (PIForceLoop)
    4. the command reaches the valve ``delay_ticks`` ticks later (loop delay)
    5. the plant advances one tick with the road's height/velocity of tick k

A controller fault (StepFlag NONFINITE_* / DIVERGED, a sensor status bit) latches the
safe state like the service does: bypass open, spool centred, for the rest of the run.
A non-finite plant state ends the run early and marks it unstable.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from controller.config import RigConfig, config_hash
from hil.metrics import compute_metrics
from hil.plant import PlantParams, RigPlant
from hil.roads import Road
from hil.sensors import SensorSuite

if TYPE_CHECKING:
    from controller.artifact import Design

__all__ = ["CONTROLLERS", "SimResult", "cached_design", "simulate"]

FloatArray = NDArray[np.float64]

CONTROLLERS = ("passive", "lqg", "fuzzy", "bayes", "moving")
#: penetration into a bump stop beyond which a run counts as slamming (unstable) [m]
SLAM_PENETRATION_M = 0.01
#: inner integration step bound of the plant [s]
MAX_INNER_STEP_S = 5e-5


@dataclass
class SimResult:
    metrics: dict[str, float]
    traces: dict[str, FloatArray]
    controller: str
    weight_set: int
    road: str
    info: dict[str, Any] = field(default_factory=dict)


_DESIGNS: dict[str, Design] = {}


def cached_design(cfg: RigConfig) -> Design:
    """``design_bank(cfg)``, memoised per configuration hash in this process."""
    from controller.design import design_bank
    key = config_hash(cfg)
    if key not in _DESIGNS:
        if len(_DESIGNS) >= 8:
            _DESIGNS.pop(next(iter(_DESIGNS)))
        _DESIGNS[key] = design_bank(cfg)
    return _DESIGNS[key]


def _make_runtime(controller: str, design: Design, cfg: RigConfig, weight_set: int,
                  road: Road) -> Any:
    from controller.bank import BankRuntime
    from controller.kernels import Blending
    blending = {"lqg": Blending.SINGLE, "fuzzy": Blending.FUZZY, "bayes": Blending.BAYES,
                "moving": Blending.MOVING}[controller]
    rt = BankRuntime(design, blending=blending, weight_set=weight_set, cfg=cfg)
    gd = road.roughness_gd if road.roughness_gd is not None else cfg.noise.nominal_roughness_gd
    rt.set_road(road.speed_mps, gd)
    rt.reset()
    return rt


def simulate(cfg: RigConfig, road: Road, controller: str = "fuzzy", weight_set: int = 1, *,
             delay_ticks: int = 0, seed: int | None = None, params: PlantParams | None = None,
             design: Design | None = None, settle_s: float = 0.0,
             latch_on_sensor_status: bool = True, lvdt_zero: str = "nominal") -> SimResult:
    """Closed-loop run of ``controller`` over ``road`` (sampled at the controller rate).

    ``params`` perturbs the plant (the controller keeps its nominal design); ``design``
    defaults to ``design_bank(cfg)`` (memoised); ``lvdt_zero`` see :class:`RigPlant`.
    Raises ValueError on bad arguments.
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller {controller!r}: use one of "
                         f"{', '.join(CONTROLLERS)}")
    if weight_set < 1 or weight_set > len(cfg.design.weight_sets):
        raise ValueError(f"weight set {weight_set} not in 1..{len(cfg.design.weight_sets)}")
    if delay_ticks < 0:
        raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
    dt = cfg.sample_time_s
    if not math.isclose(road.dt_s, dt, rel_tol=1e-9):
        raise ValueError(f"road sampled at {road.dt_s} s but the controller runs at {dt} s")
    n = road.n_ticks
    substeps = max(1, math.ceil(dt / MAX_INNER_STEP_S - 1e-9))
    plant = RigPlant(cfg, params, substeps=substeps, lvdt_zero=lvdt_zero)
    sensors = SensorSuite(cfg.sensors, cfg.noise, seed, dt_s=dt)
    active = controller != "passive"
    rt: Any = None
    pi: Any = None
    if active:
        from controller.force_loop import PIForceLoop
        from controller.kernels import StepFlag
        fault_mask = int(StepFlag.NONFINITE_INPUT | StepFlag.NONFINITE_STATE
                         | StepFlag.DIVERGED)
        design = design if design is not None else cached_design(cfg)
        rt = _make_runtime(controller, design, cfg, weight_set, road)
        pi = PIForceLoop(cfg.force_loop, dt)

    tr: dict[str, FloatArray] = {k: np.zeros(n) for k in (
        "rattlespace_m", "accel_mps2", "force_n", "force_ref_n", "spool_cmd", "tire_force_n",
        "hydraulic_power_w", "off_ground_s", "spool_computed", "bump_stop_s", "meas_rattlespace_m",
        "meas_force_n", "meas_accel_mps2")}
    # the valve applies the command computed delay_ticks ticks earlier (exactly)
    queue = [0.0] * delay_ticks
    height, velocity = road.height_m, road.velocity_mps
    faulted = False
    n_faults = 0
    fault_tick = -1
    sensor_status_ticks = 0
    n_done = n
    adv = plant.advance
    meas = sensors.measure
    t0 = time.perf_counter()
    for k in range(n):
        r_true, f_true, a_true = plant.true_signals()
        rd = meas(r_true, f_true, a_true)
        if rd.status:
            sensor_status_ticks += 1
        spool = 0.0
        fref = 0.0
        bypass = True
        if active and not faulted:
            fref = rt.step(rd.rattlespace_m, rd.accel_mps2, rd.force_n)
            if (int(rt.flags) & fault_mask) or (latch_on_sensor_status and rd.status):
                faulted = True
                n_faults += 1
                fault_tick = k
                fref = 0.0
            else:
                spool = pi.step(fref, rd.force_n)
                bypass = False
        tr["spool_computed"][k] = spool
        if delay_ticks:
            queue.append(spool)
            spool = queue.pop(0)
        adv(dt, spool, bypass, height[k], velocity[k])
        tr["rattlespace_m"][k] = r_true
        tr["accel_mps2"][k] = a_true
        tr["force_n"][k] = f_true
        tr["force_ref_n"][k] = fref
        tr["spool_cmd"][k] = spool
        tr["tire_force_n"][k] = plant.diag[0]
        tr["hydraulic_power_w"][k] = plant.diag[2]
        tr["off_ground_s"][k] = plant.diag[3]
        tr["bump_stop_s"][k] = plant.diag[4]
        tr["meas_rattlespace_m"][k] = rd.rattlespace_m
        tr["meas_force_n"][k] = rd.force_n
        tr["meas_accel_mps2"][k] = rd.accel_mps2
        if plant.nonfinite:
            n_done = k + 1
            break
    wall = time.perf_counter() - t0
    if n_done < n:
        tr = {key: v[:n_done] for key, v in tr.items()}
    tr["time_s"] = np.arange(n_done, dtype=np.float64) * dt
    tr["road_height_m"] = height[:n_done].copy()
    v = cfg.vehicle
    static_load = (plant.p[0] + plant.p[1]) * v.gravity_mps2
    metrics = compute_metrics(dt, tr["accel_mps2"], tr["rattlespace_m"], tr["tire_force_n"],
                              static_load, tr["force_n"], tr["hydraulic_power_w"],
                              tr["off_ground_s"], tr["bump_stop_s"], settle_s=settle_s,
                              human_filter=(cfg.design.human_filter_num,
                                            cfg.design.human_filter_den))
    zero_offset = plant.static_rattlespace_m - float(plant.p[12])   # LVDT zero - r0
    penetration = (float(np.max(np.abs(tr["rattlespace_m"] + zero_offset)))
                   - v.rattlespace_travel_m) if n_done else 0.0
    slam = penetration > SLAM_PENETRATION_M
    metrics.update({
        "duration_s": n_done * dt,
        "realtime_factor": (n_done * dt / wall) if wall > 0 else math.inf,
        "n_faults": float(n_faults),
        "fault_time_s": fault_tick * dt if fault_tick >= 0 else -1.0,
        "sensor_status_ticks": float(sensor_status_ticks),
        "bump_stop_slam": float(slam),
        "nonfinite": float(plant.nonfinite),
        "unstable": float(plant.nonfinite or slam),
    })
    info = {"substeps": substeps, "delay_ticks": delay_ticks, "dt_s": dt,
            "speed_mps": road.speed_mps, "seed": sensors.seed}
    return SimResult(metrics, tr, controller, weight_set, road.name, info)
