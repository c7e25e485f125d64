"""The study matrix (full and ``--quick``), its parallel execution and the passive ratios.

Groups of cases:

``tune``      skyhook gain search on the rough course (its own road seed)
``main``      every controller (both weight sets) on the thesis case and the road set
``mc5/mc15``  Monte Carlo, M m K C Kt Ct ~ nominal x N(1, 5 % / 15 %), rig LVDT zeroed
              at its own static position (``hil.sim.montecarlo`` convention)
``mismatch``  tire stiffness law 20 % softer / stiffer than designed
``delay``     loop delay 0..25 ms (thesis case, fuzzy bank; LQG and skyhook alongside),
              once before the valve (PI force loop inside the delay, as ``simulate``)
              and once before a local PI force loop ("local PI")
``rate``      controller sample rate 250 Hz .. 2 kHz (design redone at each rate)
``rho``       nonlinear check points of the linear rho2 trade-off (single LQG)
``envelope``  operating envelope (issue 22): ballast sweep, plant sprung mass x 0.6..1.5,
              and the tire stiffness x 0.7 / 1.3 on the thesis course, the single nominal
              LQG (one layer), the fuzzy bank with the built-in layers and the fuzzy
              bank of one layer designed for the true plant (weight set 1); runs as
              ``rig sim`` makes them (its road, sensor seed = road seed, no settle
              skip) so they repeat docs/study.md's "Payload" cells
``envelope-mc``  the 25 % parameter-spread Monte Carlo as ``rig montecarlo --runs 20
              --spread 0.25 --duration 20 --seed S`` makes it (Monte Carlo seeds 1 and 2),
              passive and the fuzzy bank with weight set 1, 2 and the configured one,
              and with the one-layer or the layered bank, whichever is not configured
``envelope-seeds``  many road seeds on the thesis course as ``rig sim --seed S`` makes them
              (1-12 x 60 s), passive and lqg / fuzzy / bayes / moving with weight set 1,
              2 and the configured one; the longest group, not run unless selected
              (``rig study --groups all``, :data:`DEFAULT_GROUPS`)

``rig study --groups`` selects groups by the names of :data:`GROUPS` (``mc`` = mc5 and
mc15).  Every non-passive row is divided by the passive row of the same road, speed, duration,
road seed, rate and plant (:meth:`Case.ref_key`): ``<metric>_ratio``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

from controller.config import RigConfig, config_to_dict, config_to_toml
from hil.batch import BatchExecutor, LocalExecutor
from hil.sim.montecarlo import RIDE_HEIGHT_STD_M, draw_params
from hil.sim.plant import PlantParams
from hil.sim.skyhook import TUNING_GRID, SkyhookGains
from hil.study.cases import LAYERED_SPRUNG_MASS_SCALES, Case, case_config, run_case_task

__all__ = ["DEFAULT_GROUPS", "ENVELOPE_CONTROLLERS", "ENVELOPE_LABELS",
           "ENVELOPE_MC_CONTROLLERS", "ENVELOPE_PAIRS", "ENVELOPE_SEED_CONTROLLERS", "GROUPS",
           "RATIO_METRICS", "StudyPlan", "add_ratios", "bank_labels", "envelope_cases",
           "envelope_mc_cases", "envelope_seed_cases", "main_cases", "plan", "run_cases",
           "selected", "selection_of", "study_cases"]

#: metrics reported as closed loop / passive (passive is never zero for these)
RATIO_METRICS = ("absorbed_power", "wk_rms_mps2", "accel_rms_mps2", "rattlespace_rms_m",
                 "rattlespace_peak_m", "tire_load_rms_ratio", "tire_deflection_rms_m",
                 "lq_cost_w1", "lq_cost_w2")
THESIS_SPEED_MPS = 11.176   # 25 mph
#: (controller, design mass, weight set) of the envelope group: the single nominal LQG
#: (one layer), the layered fuzzy bank and the fuzzy bank designed on the true plant, with
#: weight set 1 and with the configured law (None: ``design.weight_set``, the travel
#: schedule by default)
ENVELOPE_CONTROLLERS: tuple[tuple[str, str, int | None], ...] = (
    ("lqg", "one-layer", 1), ("fuzzy", "layered", 1), ("fuzzy", "true-plant", 1),
    ("fuzzy", "layered", None), ("fuzzy", "true-plant", None))
#: the row label of each :data:`ENVELOPE_CONTROLLERS` entry, in that order
ENVELOPE_LABELS = tuple(Case("envelope", c, weight_set=ws, design_mass=dm).label
                        for c, dm, ws in ENVELOPE_CONTROLLERS)
#: (law, layered label, true-plant label) of each weight set the envelope runs both
#: designs with: the pairs the envelope table compares
ENVELOPE_PAIRS = tuple(
    ("default" if ws is None else f"set {ws}",
     Case("envelope", c, weight_set=ws, design_mass="layered").label,
     Case("envelope", c, weight_set=ws, design_mass="true-plant").label)
    for c, dm, ws in ENVELOPE_CONTROLLERS if dm == "layered")
#: (controller, weight set, design) of the 25 % Monte Carlo: the default controller (``rig
#: montecarlo``'s fuzzy bank) with each weight set and the configured one (None: the
#: configuration's ``design.weight_set`` and defaults as they are when the study runs),
#: and with weight set 1 and the configured one the bank of one layer and the layered
#: bank over [M, K, C] (the built-in layers); :func:`envelope_mc_cases` leaves out a
#: design that is the configured one (the one-layer bank under deploy/thesis.toml, the
#: layered bank under the defaults)
ENVELOPE_MC_CONTROLLERS: tuple[tuple[str, int | None, str], ...] = (
    ("fuzzy", 1, "configured"), ("fuzzy", 2, "configured"), ("fuzzy", None, "configured"),
    ("fuzzy", 1, "one-layer"), ("fuzzy", None, "one-layer"),
    ("fuzzy", 1, "layered"), ("fuzzy", None, "layered"))
#: (controller, weight set) of the many-road-seeds group: every bank mode x set 1, set 2,
#: the configured one
ENVELOPE_SEED_CONTROLLERS: tuple[tuple[str, int | None], ...] = tuple(
    (c, ws) for ws in (1, 2, None) for c in ("lqg", "fuzzy", "bayes", "moving"))
#: the groups ``rig study --groups`` selects (``mc``: the mc5 / mc15 Monte Carlo)
GROUPS = ("tune", "main", "mc", "mismatch", "delay", "rate", "rho", "envelope",
          "envelope-mc", "envelope-seeds")
#: what ``rig study`` runs without ``--groups``: all but the many road seeds (156 runs of
#: 60 s, about half the rest of the study again)
DEFAULT_GROUPS = tuple(g for g in GROUPS if g != "envelope-seeds")


@dataclass(frozen=True)
class StudyPlan:
    quick: bool
    thesis_duration_s: float
    thesis_seeds: tuple[int, ...]
    road_duration_s: float
    event_duration_s: float
    roads: tuple[tuple[str, float], ...]          # (road, speed) besides the thesis case
    mc_runs: int
    mc_spreads: tuple[float, ...]
    mc_duration_s: float
    mismatch_scales: tuple[float, ...]
    delays_ms: tuple[float, ...]
    rates_hz: tuple[float, ...]
    sweep_duration_s: float
    rho2_checks: tuple[float, ...]
    tune_grid: tuple[tuple[float, float, float], ...]
    tune_duration_s: float
    settle_s: float
    envelope_mass_scales: tuple[float, ...]
    envelope_seeds: tuple[int, ...]
    envelope_duration_s: float
    envelope_tire_scales: tuple[float, ...]
    envelope_mc_runs: int
    envelope_mc_spread: float
    envelope_mc_seeds: tuple[int, ...]
    envelope_mc_duration_s: float
    envelope_road_seeds: tuple[int, ...]
    envelope_road_duration_s: float
    envelope_observe_s: float = 0.0

    def describe(self) -> str:
        return (f"thesis case {len(self.thesis_seeds)} x {self.thesis_duration_s:g} s; other "
                f"random roads {self.road_duration_s:g} s; bump/pothole "
                f"{self.event_duration_s:g} s; Monte Carlo {self.mc_runs} runs x "
                f"{self.mc_duration_s:g} s per controller and spread; delay/rate/mismatch "
                f"{self.sweep_duration_s:g} s; skyhook search {len(self.tune_grid)} settings "
                f"x {self.tune_duration_s:g} s; statistics skip the first {self.settle_s:g} s; "
                f"envelope {len(self.envelope_mass_scales)} sprung masses and "
                f"{len(self.envelope_tire_scales)} tire stiffnesses x "
                f"{len(self.envelope_seeds)} seeds x {self.envelope_duration_s:g} s armed "
                f"after {self.envelope_observe_s:g} s observed; "
                f"envelope Monte Carlo {self.envelope_mc_runs} plants x "
                f"{self.envelope_mc_duration_s:g} s at {100 * self.envelope_mc_spread:g} % "
                f"spread, seeds {', '.join(map(str, self.envelope_mc_seeds))}; envelope "
                f"road seeds {len(self.envelope_road_seeds)} x "
                f"{self.envelope_road_duration_s:g} s")


def plan(quick: bool) -> StudyPlan:
    if quick:
        return StudyPlan(True, 3.0, (1,), 2.0, 2.0, (("iso-B", 20.0), ("bump", 10.0)), 2,
                         (0.05,), 2.0, (0.8, 1.2), (0.0, 10.0), (500.0, 1000.0), 2.0,
                         (1e-1, 1e2), TUNING_GRID[:: max(1, len(TUNING_GRID) // 3)], 2.0, 0.5,
                         (0.7, 1.3), (1,), 2.0, envelope_tire_scales=(0.7,),
                         envelope_mc_runs=2, envelope_mc_spread=0.25,
                         envelope_mc_seeds=(1,), envelope_mc_duration_s=2.0,
                         envelope_road_seeds=(1, 2), envelope_road_duration_s=2.0,
                         envelope_observe_s=0.5)
    roads = (("iso-B", 10.0), ("iso-B", 20.0), ("iso-B", 30.0), ("iso-D", 10.0),
             ("iso-D", 20.0), ("iso-D", 30.0), ("iso-F", 5.0), ("iso-F", 10.0),
             ("bump", 5.0), ("bump", 10.0), ("pothole", 5.0), ("pothole", 10.0))
    return StudyPlan(False, 60.0, (1, 2, 3), 30.0, 4.0, roads, 20, (0.05, 0.15), 20.0,
                     (0.8, 1.2), (0.0, 1.0, 2.0, 5.0, 10.0, 15.0, 20.0, 25.0),
                     (250.0, 500.0, 1000.0, 2000.0), 30.0,
                     (1e-2, 1e-1, 1e0, 1e1, 1e2, 3e2, 1e3), TUNING_GRID, 20.0, 1.0,
                     LAYERED_SPRUNG_MASS_SCALES, (1, 2), 30.0,
                     envelope_tire_scales=(0.7, 1.3), envelope_mc_runs=20,
                     envelope_mc_spread=0.25, envelope_mc_seeds=(1, 2),
                     envelope_mc_duration_s=20.0, envelope_road_seeds=tuple(range(1, 13)),
                     envelope_road_duration_s=60.0, envelope_observe_s=10.0)


def bank_labels() -> list[tuple[str, int]]:
    """(controller, weight set) of every active configuration in the main comparison;
    weight set 0 is the travel schedule (docs/design.md §12: the bank's own law, so no
    full-state counterpart)."""
    out: list[tuple[str, int]] = [("skyhook", 1)]
    for ws in (1, 2):
        out += [(c, ws) for c in ("lqg", "fuzzy", "bayes", "moving", "fullstate")]
    out += [(c, 0) for c in ("lqg", "fuzzy", "bayes", "moving")]
    return out


def tune_cases(p: StudyPlan) -> list[Case]:
    base = Case("tune", "passive", road="rough-course", speed_mps=THESIS_SPEED_MPS,
                duration_s=p.tune_duration_s, road_seed=101, settle_s=p.settle_s)
    return [base] + [replace(base, controller="skyhook", skyhook=SkyhookGains(cs, cg, kc))
                     for cs, cg, kc in p.tune_grid]


def main_cases(p: StudyPlan, skyhook: SkyhookGains) -> list[Case]:
    cases: list[Case] = []
    roads: list[tuple[str, float, float, int]] = [
        ("rough-course", THESIS_SPEED_MPS, p.thesis_duration_s, s) for s in p.thesis_seeds]
    roads += [(r, v, p.event_duration_s if r in ("bump", "pothole") else p.road_duration_s, 1)
              for r, v in p.roads]
    for road, speed, dur, seed in roads:
        thesis = road == "rough-course" and seed == p.thesis_seeds[0]
        base = Case("main", "passive", road=road, speed_mps=speed, duration_s=dur,
                    road_seed=seed, settle_s=p.settle_s if dur > 3 * p.settle_s else 0.0,
                    trace=thesis)
        cases.append(base)
        for c, ws in bank_labels():
            cases.append(replace(base, controller=c, weight_set=ws,
                                 skyhook=skyhook if c == "skyhook" else None,
                                 trace=thesis and c in ("fuzzy", "lqg", "fullstate")))
    return cases


def other_cases(p: StudyPlan, cfg: RigConfig, skyhook: SkyhookGains) -> list[Case]:
    cases: list[Case] = []
    thesis = Case("mc", "passive", road="rough-course", speed_mps=THESIS_SPEED_MPS,
                  duration_s=p.mc_duration_s, road_seed=1, settle_s=p.settle_s)
    mc_ctrl = [(c, ws) for c, ws in bank_labels() if ws == 1] + [("fuzzy", 2), ("fuzzy", 0)]
    for spread in p.mc_spreads:
        group = f"mc{round(100 * spread)}"
        for i, prm in enumerate(draw_params(cfg, p.mc_runs, spread, seed=11)):
            base = replace(thesis, group=group, params=prm, param_tag=f"{group}-{i}",
                           sensor_seed=1000 + i)
            cases.append(base)
            for c, ws in mc_ctrl:
                cases.append(replace(base, controller=c, weight_set=ws,
                                     skyhook=skyhook if c == "skyhook" else None,
                                     trace=c == "fuzzy" and ws == 1 and spread == 0.05
                                     and i < 8))
    sweep = replace(thesis, group="mismatch", duration_s=p.sweep_duration_s)
    for scale in p.mismatch_scales:
        base = replace(sweep, params=PlantParams(tire_stiffness_scale=scale),
                       param_tag=f"kt{scale:g}")
        cases.append(base)
        for c, ws in bank_labels():
            cases.append(replace(base, controller=c, weight_set=ws,
                                 skyhook=skyhook if c == "skyhook" else None))
    base = replace(sweep, group="delay")
    cases.append(base)
    for point in ("spool", "force_ref"):
        for d in p.delays_ms:
            for c, ws in (("fuzzy", 1), ("fuzzy", 2), ("lqg", 1), ("skyhook", 1)):
                cases.append(replace(base, controller=c, weight_set=ws, delay_ms=d,
                                     delay_point=point,
                                     skyhook=skyhook if c == "skyhook" else None))
    for rate in p.rates_hz:
        base = replace(sweep, group="rate", rate_hz=rate)
        cases.append(base)
        for c, ws in (("fuzzy", 1), ("fuzzy", 2), ("lqg", 1)):
            cases.append(replace(base, controller=c, weight_set=ws))
    base = replace(sweep, group="rho")
    cases.append(base)
    for rho1 in (1.0, 10.0):
        for rho2 in p.rho2_checks:
            cases.append(replace(base, controller="lqg", weights=(rho1, rho2, 1e-8, 1.0)))
    return cases + envelope_cases(p) + envelope_mc_cases(p, cfg) + envelope_seed_cases(p)


def envelope_cases(p: StudyPlan) -> list[Case]:
    """The ballast sweep and the tire cases: passive and :data:`ENVELOPE_CONTROLLERS` per
    sprung-mass scale (``param_tag`` ``M<scale>``) or tire stiffness scale
    (``Kt<scale>``) and road seed, each observed ``envelope_observe_s`` before arming as
    the service runs (a ballast change with the service stopped: the bank chooses its
    layer before the operator arms; a change during a run is the ballast-step case)."""
    plants = ([(f"M{s:g}", s, 1.0) for s in p.envelope_mass_scales]
              + [(f"Kt{s:g}", 1.0, s) for s in p.envelope_tire_scales])
    cases: list[Case] = []
    for seed in p.envelope_seeds:
        for tag, mass, tire in plants:
            base = Case("envelope", "passive", road="rough-course", speed_mps=THESIS_SPEED_MPS,
                        duration_s=p.envelope_duration_s, road_seed=seed, sensor_seed=seed,
                        sprung_mass_scale=mass, tire_stiffness_scale=tire, param_tag=tag,
                        sim_road=True, observe_s=p.envelope_observe_s)
            cases.append(base)
            cases += [replace(base, controller=c, design_mass=dm, weight_set=ws)
                      for c, dm, ws in ENVELOPE_CONTROLLERS]
    return cases


def envelope_mc_cases(p: StudyPlan, cfg: RigConfig) -> list[Case]:
    """The wide Monte Carlo, run by run as ``rig montecarlo --runs R --spread S
    --duration D --seed K`` makes it (``hil.sim.montecarlo.run_montecarlo``: road seed K
    at the controller rate, plants ``draw_params(cfg, R, S, K)`` with the default ride
    height spread, sensor seed K + 1000 + run, no settle skip): passive and
    :data:`ENVELOPE_MC_CONTROLLERS` per plant (``param_tag`` ``mc<S>s<K>-<run>``), but
    for a design that resolves to the configured one."""
    configured = config_to_dict(cfg)
    laws = [(c, ws, dm) for c, ws, dm in ENVELOPE_MC_CONTROLLERS if dm == "configured"
            or config_to_dict(case_config(cfg, Case("envelope-mc", c, design_mass=dm)))
            != configured]
    cases: list[Case] = []
    spread = p.envelope_mc_spread
    for seed in p.envelope_mc_seeds:
        plants = draw_params(cfg, p.envelope_mc_runs, spread, seed, RIDE_HEIGHT_STD_M)
        for i, prm in enumerate(plants):
            base = Case("envelope-mc", "passive", road="rough-course",
                        speed_mps=THESIS_SPEED_MPS, duration_s=p.envelope_mc_duration_s,
                        road_seed=seed, sensor_seed=seed + 1000 + i, params=prm,
                        param_tag=f"mc{100 * spread:g}s{seed}-{i}", sim_road=True)
            cases.append(base)
            cases += [replace(base, controller=c, weight_set=ws, design_mass=dm)
                      for c, ws, dm in laws]
    return cases


def envelope_seed_cases(p: StudyPlan) -> list[Case]:
    """Many road seeds on the thesis course, each run as ``rig sim --road rough-course
    --speed 11.176 --duration D --seed S`` makes it: passive and
    :data:`ENVELOPE_SEED_CONTROLLERS` per road seed."""
    cases: list[Case] = []
    for seed in p.envelope_road_seeds:
        base = Case("envelope-seeds", "passive", road="rough-course",
                    speed_mps=THESIS_SPEED_MPS, duration_s=p.envelope_road_duration_s,
                    road_seed=seed, sensor_seed=seed, sim_road=True)
        cases.append(base)
        cases += [replace(base, controller=c, weight_set=ws)
                  for c, ws in ENVELOPE_SEED_CONTROLLERS]
    return cases


def selection_of(case_group: str) -> str:
    """The :data:`GROUPS` name that selects a case group (mc5, mc15 -> ``mc``)."""
    return "mc" if case_group.startswith("mc") else case_group


def selected(cases: Sequence[Case], groups: Sequence[str]) -> list[Case]:
    """The cases of the selected :data:`GROUPS` (ValueError naming an unknown one)."""
    unknown = sorted(set(groups) - set(GROUPS))
    if unknown:
        raise ValueError(f"study groups {unknown}: allowed {', '.join(GROUPS)}")
    return [c for c in cases if selection_of(c.group) in groups]


def study_cases(p: StudyPlan, cfg: RigConfig, skyhook: SkyhookGains,
                groups: Sequence[str] = DEFAULT_GROUPS) -> list[Case]:
    """Every case of the matrix but the skyhook search (:func:`tune_cases`) in the
    selected groups."""
    return selected(main_cases(p, skyhook) + other_cases(p, cfg, skyhook), groups)


def run_cases(cases: Sequence[Case], cfg: RigConfig, jobs: int | None = None,
              progress: bool = True, desc: str = "study",
              executor: BatchExecutor | None = None) -> list[dict[str, Any]]:
    """Run every case on ``executor`` (default: a local pool of ``jobs`` processes), rows
    in case order; :class:`hil.batch.BatchError` naming the failed cases if any raised."""
    # longest first balances the pool
    order = sorted(range(len(cases)),
                   key=lambda i: -cases[i].duration_s * (cases[i].rate_hz or 1000.0))
    ex = executor if executor is not None else LocalExecutor(
        max(1, min(jobs or os.cpu_count() or 1, len(cases))))
    try:
        res = ex.run(run_case_task, config_to_toml(cfg), list(cases),
                     [c.describe() for c in cases], desc=desc, progress=progress,
                     order=order)
    finally:
        if executor is None:
            ex.close()
    return res.values()


def add_ratios(rows: list[dict[str, Any]], cases: Sequence[Case]) -> None:
    """Add ``<metric>_ratio`` to every row (passive rows get exactly 1)."""
    ref: dict[tuple[Any, ...], dict[str, Any]] = {}
    for row, case in zip(rows, cases, strict=True):
        if case.controller == "passive":
            ref.setdefault((case.group, *case.ref_key()), row)
    for row, case in zip(rows, cases, strict=True):
        base = ref.get((case.group, *case.ref_key()))
        for m in RATIO_METRICS:
            if base is None:
                row[f"{m}_ratio"] = math.nan
                continue
            num, den = float(row[m]), float(base[m])
            row[f"{m}_ratio"] = num / den if den != 0.0 else math.nan
