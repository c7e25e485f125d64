"""One run of the study matrix: :class:`Case` (picklable spec) -> result row.

A case names the controller, weight set (or custom weights), road, speed, duration,
seeds, loop delay, sample rate and plant perturbation.  :func:`run_case` builds
everything inside the worker process (the design is memoised per configuration by
``hil.sim.closed_loop.cached_design``) and returns a flat row of metrics, optionally with decimated
traces for the figures.

Roads of one (name, speed, duration, seed) are generated once on a fine
:data:`ROAD_BASE_RATE_HZ` grid and decimated to the controller rate, so a sample-rate
sweep drives every rate with the same profile.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

import controller.design

# the controller modules are imported here, before the study's worker processes fork, so
# that every run of one study uses the same code even while the tree is being edited
import controller.runtime.bank
import controller.runtime.force_loop  # noqa: F401
from controller.config import LAYER_KEYS, RigConfig, default_config, one_layer
from controller.metrics import filter_signal, human_filter_tf
from controller.modes import BANK_MODES
from hil.sim.closed_loop import (
    BankController,
    LoopController,
    cached_design,
    config_from_text,
    run_closed_loop,
)
from hil.sim.fullstate import FullStateLQ
from hil.sim.plant import PlantParams
from hil.sim.roads import Road, make_road
from hil.sim.skyhook import DEFAULT_GAINS, SkyhookController, SkyhookGains

__all__ = ["CONTROLLERS", "DESIGN_MASSES", "LAYERED_DESIGN", "LAYERED_SPRUNG_MASS_SCALES",
           "ROAD_BASE_RATE_HZ", "TRACE_DECIMATION", "Case", "case_config", "lq_cost",
           "make_controller", "run_case", "run_case_task", "study_road"]

#: the study's controllers: the reference laws worth comparing, the bank modes of
#: controller.modes, and the full-state LQ (the simulator's true-state reference)
CONTROLLERS = ("passive", "skyhook", *BANK_MODES, "fullstate")
ROAD_BASE_RATE_HZ = 4000.0
TRACE_DECIMATION = 10
#: what the bank of a case is designed for (the plant is ``Case.sprung_mass_scale`` and
#: ``Case.tire_stiffness_scale``): ``configured`` the configuration as it is; ``layered``
#: the configuration with the built-in layers :data:`LAYERED_DESIGN`; ``one-layer`` the
#: configuration with a bank of one layer (``controller.config.one_layer``: the tire
#: models of the configured vehicle only, the thesis's bank); ``true-plant`` that one
#: layer designed with ``vehicle.sprung_mass_kg`` and ``tire.stiffness_coefficient`` those
#: of the plant
DESIGN_MASSES = ("configured", "layered", "one-layer", "true-plant")
#: the built-in ``[design]`` layer keys (``controller.config.LAYER_KEYS``): the bank's
#: layers over sprung mass, spring rate and damping (docs/design.md §11)
LAYERED_DESIGN: dict[str, tuple[float, ...]] = {
    key: tuple(getattr(default_config().design, key)) for key in LAYER_KEYS}
#: the built-in ``[design] sprung_mass_scales``: the masses of the envelope's ballast sweep
LAYERED_SPRUNG_MASS_SCALES = LAYERED_DESIGN["sprung_mass_scales"]


@dataclass(frozen=True)
class Case:
    group: str
    controller: str
    weight_set: int | None = 1             # None: the configuration's design.weight_set
    road: str = "rough-course"
    speed_mps: float = 11.176
    duration_s: float = 10.0
    road_seed: int = 1
    sensor_seed: int = 7
    delay_ms: float = 0.0
    delay_point: str = "spool"             # hil.sim.closed_loop.DELAY_POINTS
    rate_hz: float | None = None           # None: the configuration's rate
    params: PlantParams | None = None
    param_tag: str = "nominal"
    weights: tuple[float, float, float, float] | None = None   # custom [rho1..rho4]
    skyhook: SkyhookGains | None = None
    settle_s: float = 0.0
    trace: bool = False
    sprung_mass_scale: float = 1.0         # the plant: [emulator] sprung_mass_scale
    tire_stiffness_scale: float = 1.0      # the plant: [emulator] tire_stiffness_scale
    design_mass: str = "configured"        # DESIGN_MASSES
    sim_road: bool = False                 # the road as `rig sim` makes it (make_road at
                                           # the controller rate), not study_road's
    observe_s: float = 0.0                 # observed before arming (run_closed_loop); the
                                           # road is observe_s + duration_s long

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLERS:
            raise ValueError(f"controller {self.controller!r}: allowed {CONTROLLERS}")
        if self.delay_point not in ("spool", "force_ref"):
            raise ValueError(f"delay_point {self.delay_point!r}: allowed spool, force_ref")
        if self.design_mass not in DESIGN_MASSES:
            raise ValueError(f"design_mass {self.design_mass!r}: allowed {DESIGN_MASSES}")
        if not (self.sprung_mass_scale > 0 and self.tire_stiffness_scale > 0):
            raise ValueError(f"bad case {self}: sprung_mass_scale and tire_stiffness_scale "
                             "> 0 needed")
        if self.delay_ms < 0 or self.duration_s <= 0 or self.observe_s < 0:
            raise ValueError(f"bad case {self}: delay_ms >= 0, duration_s > 0 and "
                             "observe_s >= 0 needed")

    def ref_key(self) -> tuple[Any, ...]:
        """Cases with equal keys share one passive reference run."""
        return (self.road, self.speed_mps, self.duration_s, self.road_seed, self.rate_hz,
                self.param_tag, self.settle_s, self.sprung_mass_scale,
                self.tire_stiffness_scale, self.sim_road, self.observe_s)

    def passive(self) -> Case:
        return replace(self, controller="passive", weight_set=1, delay_ms=0.0,
                       delay_point="spool", weights=None, skyhook=None,
                       design_mass="configured")

    def describe(self) -> str:
        """What the case runs, for a failure report (plant, road, seeds)."""
        return (f"{self.group} {self.label}, road {self.road} at {self.speed_mps:g} m/s for "
                f"{self.duration_s:g} s, road seed {self.road_seed}, sensor seed "
                f"{self.sensor_seed}, plant {self.param_tag}"
                + (f", delay {self.delay_ms:g} ms" if self.delay_ms else "")
                + (f", rate {self.rate_hz:g} Hz" if self.rate_hz else "")
                + (f", sprung mass x {self.sprung_mass_scale:g}"
                   if self.sprung_mass_scale != 1.0 else "")
                + (f", tire stiffness x {self.tire_stiffness_scale:g}"
                   if self.tire_stiffness_scale != 1.0 else "")
                + (f", design {self.design_mass}" if self.design_mass != "configured"
                   else "")
                + (f", observed {self.observe_s:g} s before arming" if self.observe_s
                   else ""))

    @property
    def label(self) -> str:
        if self.controller in ("passive", "skyhook"):
            lab = self.controller
        elif self.weights is not None:
            lab = f"{self.controller}-rho"
        elif self.weight_set is None:
            lab = f"{self.controller}-default"
        else:
            lab = f"{self.controller}-{self.weight_set}"
        if self.design_mass != "configured":
            lab += f" ({self.design_mass})"
        return lab + (" (local PI)" if self.delay_point == "force_ref" else "")


def case_config(cfg: RigConfig, case: Case) -> RigConfig:
    """``cfg`` with the case's sample rate, custom weight set, plant sprung mass and tire
    stiffness (``[emulator] sprung_mass_scale`` and ``tire_stiffness_scale``, the LVDT
    zeroed at the plant's own rest) and design mass (:data:`DESIGN_MASSES`) applied.  A
    ``true-plant`` case designs one layer with ``vehicle.sprung_mass_kg`` and
    ``tire.stiffness_coefficient`` = the scales x the emulated rig's and emulates that
    vehicle as configured (the same plant)."""
    sections: dict[str, dict[str, Any]] = {}
    design: dict[str, Any] = {}
    if case.rate_hz is not None and not math.isclose(case.rate_hz, cfg.design.sample_rate_hz):
        design["sample_rate_hz"] = float(case.rate_hz)
    if case.weights is not None:
        design["weight_sets"] = [[float(w) for w in case.weights]]
        design["weight_set"] = 1
    if case.design_mass == "layered":
        design.update({key: list(scales) for key, scales in LAYERED_DESIGN.items()})
    if design:
        sections["design"] = design
    em = cfg.emulator
    if case.design_mass == "true-plant":
        mass_kg = cfg.vehicle.sprung_mass_kg * em.sprung_mass_scale
        sections["vehicle"] = {"sprung_mass_kg": mass_kg * case.sprung_mass_scale}
        emulator: dict[str, Any] = {"sprung_mass_scale": 1.0}
        if case.tire_stiffness_scale != 1.0 or em.tire_stiffness_scale != 1.0:
            kt = cfg.tire.stiffness_coefficient * em.tire_stiffness_scale
            sections["tire"] = {"stiffness_coefficient": kt * case.tire_stiffness_scale}
            emulator["tire_stiffness_scale"] = 1.0
        sections["emulator"] = emulator
    else:
        emulator = {}
        if case.sprung_mass_scale != 1.0:
            emulator["sprung_mass_scale"] = em.sprung_mass_scale * case.sprung_mass_scale
        if case.tire_stiffness_scale != 1.0:
            emulator["tire_stiffness_scale"] = (em.tire_stiffness_scale
                                                * case.tire_stiffness_scale)
        if emulator:
            sections["emulator"] = emulator
    out = cfg.replace(**sections) if sections else cfg
    return one_layer(out) if case.design_mass in ("one-layer", "true-plant") else out


def study_road(name: str, speed_mps: float, duration_s: float, dt_s: float,
               seed: int) -> Road:
    """``make_road`` on the :data:`ROAD_BASE_RATE_HZ` grid, decimated to ``dt_s`` when
    that is an integer multiple of the base step (else generated at ``dt_s``)."""
    base = 1.0 / ROAD_BASE_RATE_HZ
    m = round(dt_s / base)
    if m < 1 or not math.isclose(m * base, dt_s, rel_tol=1e-9):
        return make_road(name, speed_mps, duration_s, dt_s, seed)
    fine = make_road(name, speed_mps, duration_s, base, seed)
    n = round(duration_s / dt_s)
    edges = np.append(fine.height_m, fine.height_m[-1] + fine.velocity_mps[-1] * base)
    h = edges[::m][:n + 1]
    if h.shape[0] < n + 1:
        raise ValueError("road decimation lost samples")
    return Road(fine.name, speed_mps, dt_s, np.ascontiguousarray(h[:-1]),
                np.ascontiguousarray(np.diff(h) / dt_s), fine.roughness_gd,
                fine.description, dict(fine.extra))


def make_controller(case: Case, cfg: RigConfig, road: Road) -> LoopController | None:
    """The case's controller for ``cfg`` (already :func:`case_config`-ed)."""
    c = case.controller
    if c == "passive":
        return None
    if c == "skyhook":
        return SkyhookController(cfg, case.skyhook or DEFAULT_GAINS)
    design = cached_design(cfg)
    ws = (1 if case.weights is not None else
          cfg.design.weight_set if case.weight_set is None else case.weight_set)
    if c == "fullstate":
        return FullStateLQ(design, cfg, ws)
    return BankController(design, cfg, c, ws, road)


def lq_cost(metrics: dict[str, float], weights: tuple[float, ...] | list[float]) -> float:
    """The Eq. 2.5 cost rate rho4 <y_f^2> + rho1 <x2^2> + rho2 <r^2> + rho3 <u^2> of a run
    (deviations from static; y_f = F(s)-filtered true sprung acceleration, u = actuator
    force) -- what the LQ gain minimises, unlike any single metric."""
    rho1, rho2, rho3, rho4 = (float(w) for w in weights)
    return (rho4 * metrics["absorbed_power"] + rho1 * metrics["tire_deflection_rms_m"] ** 2
            + rho2 * metrics["rattlespace_rms_m"] ** 2 + rho3 * metrics["force_rms_n"] ** 2)


def _row_fields(case: Case) -> dict[str, Any]:
    row: dict[str, Any] = {k: v for k, v in asdict(case).items()
                           if k not in ("params", "skyhook", "weights", "trace")}
    row["label"] = case.label
    sk = case.skyhook or (DEFAULT_GAINS if case.controller == "skyhook" else None)
    row["c_sky_ns_per_m"] = sk.c_sky_ns_per_m if sk else math.nan
    row["c_ground_ns_per_m"] = sk.c_ground_ns_per_m if sk else math.nan
    row["damper_cancel"] = sk.damper_cancel if sk else math.nan
    w = case.weights
    row["rho1"], row["rho2"] = (w[0], w[1]) if w else (math.nan, math.nan)
    return row


def run_case(case: Case, cfg: RigConfig) -> dict[str, Any]:
    """Run one case; the row holds the case fields, every metric, the Eq. 2.5 cost for
    both thesis weight sets (``lq_cost_w1``/``_w2``) and, if ``case.trace``, a
    ``traces`` dict (decimated by :data:`TRACE_DECIMATION`)."""
    ccfg = case_config(cfg, case)
    dt = ccfg.sample_time_s
    length_s = case.observe_s + case.duration_s
    road = (make_road(case.road, case.speed_mps, length_s, dt, case.road_seed)
            if case.sim_road else
            study_road(case.road, case.speed_mps, length_s, dt, case.road_seed))
    ctrl = make_controller(case, ccfg, road)
    delay_ticks = round(case.delay_ms * 1e-3 / dt)
    res = run_closed_loop(ccfg, road, ctrl, delay_ticks=delay_ticks, seed=case.sensor_seed,
                          params=case.params, settle_s=case.settle_s,
                          record_weights=case.trace,
                          delay_point=case.delay_point, observe_s=case.observe_s)
    row = _row_fields(case)
    row.update({k: float(v) for k, v in res.metrics.items()
                if k != "realtime_factor"})       # wall-clock: would make rows unrepeatable
    row["delay_ticks"] = float(delay_ticks)
    for i, w in enumerate(cfg.design.weight_sets[:2], start=1):
        row[f"lq_cost_w{i}"] = lq_cost(res.metrics, w)
    if case.trace:
        d = TRACE_DECIMATION
        full = dict(res.traces)
        num, den = human_filter_tf(ccfg.design.human_filter_num, ccfg.design.human_filter_den)
        full["filtered_accel"] = filter_signal(full["accel_mps2"], num, den, dt)
        full["int_accel_sq"] = np.cumsum(np.square(full["accel_mps2"])) * dt
        full["int_filtered_accel_sq"] = np.cumsum(np.square(full["filtered_accel"])) * dt
        row["traces"] = {k: np.asarray(v[::d]).copy() for k, v in full.items()}
        row["traces"]["dt_s"] = np.array(dt * d)
    return row


def run_case_task(config_toml: str, case: Case) -> dict[str, Any]:
    """:func:`run_case` as a batch task (``hil.batch``): the configuration arrives as
    TOML text, the worker designs the bank itself."""
    return run_case(case, config_from_text(config_toml))
