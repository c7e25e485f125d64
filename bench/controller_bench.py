"""Controller step time: ``BankRuntime.step`` per tick, as the 1 kHz loop calls it.

Each case times many single steps with ``time.perf_counter_ns`` around each call (after
a warm-up, garbage collector disabled during the run) and reports the median, p99 and
p99.9 in microseconds, plus the kernel-only mean (the same steps called from a compiled
loop, i.e. without the Python call and numba argument unboxing; the fastest of
``KERNEL_PASSES`` passes over the inputs, so that a pass that shared the core with other
work does not count).  Inputs are the
measurements of a simulated quarter car (so the moving bank does real work).

Cases: on the bank of one layer (``controller.config.one_layer``: the tire models of the
configured vehicle) fuzzy J=3 (the thesis's three deflections, no airborne model), fuzzy
J=4 (with the airborne model), Bayes J=3, single (plain LQG), and a 9 x 3 grid + airborne
(28 models) run as a moving bank with k = 3; and the default bank (189 layers over sprung
mass, spring rate, damping and tire stiffness, 568 models, the default law; its step
runs one layer and
copies that layer's rows for the tick record, docs/design.md §11; its kernel column is
``bank_step`` alone); and the road preview's per-tick prediction
(``controller.road_preview.predicted_peak_m`` of the default horizon: 20 look-ahead
times up to 200 ms, called alone, not part of the step: docs/design.md §12;
its J column is the bank's layers, one predictor each); and the default law's tick with
a live preview as the loop calls it (``BankRuntime.step_previewed``: that prediction,
the stop clamp's on the previewed road and the step; without a preview ``step`` runs
the stop clamp on the road at rest).  The goal is a median
below 10 us and p99.9 below 50 us for fuzzy J=3, and the 28-model moving bank within
1.3x of fuzzy J=3.  ``python -m bench.controller_bench [--quick]`` prints the table.
"""

from __future__ import annotations

import gc
import math
import sys
import time
from typing import Any

import numba as nb
import numpy as np

from controller.config import RigConfig, default_config, one_layer
from controller.design import design_bank
from controller.road_noise import road_velocity_intensity
from controller.road_preview import predicted_peak_m, road_preview
from controller.runtime.bank import BankRuntime, Blending, bank_steps
from tests.support.reference_bank import quarter_car_measurements

NAME = "controller"
TITLE = "Controller step (BankRuntime.step, one call per tick), microseconds"

GRID_DEFLECTIONS_M = [0.045, 0.04, 0.035, 0.03, 0.025, 0.02, 0.015, 0.01, 0.005]
GRID_DAMPING_SCALES = [0.5, 1.0, 2.0]

#: passes of the compiled loop over the inputs; the kernel column is the fastest
KERNEL_PASSES = 5


def _inputs(cfg: RigConfig, n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    dt = cfg.sample_time_s
    w = road_velocity_intensity(cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    m = quarter_car_measurements(cfg, dt, rng.normal(0.0, math.sqrt(w / dt), n),
                                 rng.normal(0.0, 300.0, n), rng)
    return np.column_stack([m["rattlespace"], m["accel"], m["force"]])


def _stats(times_ns: np.ndarray, kernel_ns: float) -> dict[str, float]:
    """Median, p99, p99.9 and max of the per-call times and the kernel mean, in us."""
    us = times_ns / 1000.0
    return {"median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)),
            "p99.9_us": float(np.percentile(us, 99.9)), "max_us": float(us.max()),
            "kernel_mean_us": kernel_ns / 1000.0}


def _time_case(rt: BankRuntime, data: np.ndarray) -> dict[str, float]:
    rows = [(float(a), float(b), float(c)) for a, b, c in data]
    step = rt.step
    for r, a, f in rows[: min(2000, len(rows))]:        # warm-up
        step(r, a, f)
    rt.reset()
    times = np.empty(len(rows), dtype=np.int64)
    updates = 0
    gc_was = gc.isenabled()
    gc.disable()
    try:
        pc = time.perf_counter_ns
        for i, (r, a, f) in enumerate(rows):
            t0 = pc()
            step(r, a, f)
            times[i] = pc() - t0
            updates += rt.filter_updates
    finally:
        if gc_was:
            gc.enable()
    rt.reset()
    args = (rt._mat, rt._vec, rt._st, rt._active, rt._fv, rt._iv, rt._nbr)
    bank_steps(*args, data[:10])
    kernel_ns = math.inf
    for _ in range(KERNEL_PASSES):       # the fastest pass: the others met other work
        rt.reset()
        t0 = time.perf_counter_ns()
        bank_steps(*args, data)
        kernel_ns = min(kernel_ns, (time.perf_counter_ns() - t0) / len(rows))
    return {**_stats(times, kernel_ns), "filters_per_tick": updates / len(rows)}




@nb.njit(cache=True)
def _preview_calls(rows: np.ndarray, ticks: np.ndarray, impulse: np.ndarray,
                   force_rows: np.ndarray, layer: int, dx: np.ndarray, data: np.ndarray,
                   velocity: np.ndarray) -> float:
    """predicted_peak_m on every tick of ``data`` from a compiled loop (the kernel column)."""
    acc = 0.0
    for k in range(data.shape[0]):
        acc += predicted_peak_m(rows, ticks, impulse, force_rows, layer, dx, data[k, 2],
                                data[k, 0], 0.0, velocity, k)
    return acc


def _time_preview(cfg: RigConfig, data: np.ndarray) -> dict[str, Any]:
    """The road preview's prediction per tick: one call of predicted_peak_m on the
    default bank's nominal layer, the road velocity the inputs were made with."""
    pv = road_preview(cfg)
    assert pv is not None
    layer = pv.rows.shape[0] // 2
    rng = np.random.default_rng(2)
    velocity = rng.normal(0.0, 0.3, data.shape[0] + pv.horizon_ticks)
    dx = np.array([0.01, 0.002, 0.1, -0.3])
    args = (pv.rows, pv.ticks, pv.impulse, pv.force_rows, layer, dx)
    rows = [(float(r), float(f)) for r, f in data[:, [0, 2]]]
    for k, (r, f) in enumerate(rows[: min(2000, len(rows))]):        # warm-up
        predicted_peak_m(*args, f, r, 0.0, velocity, k)
    times = np.empty(len(rows), dtype=np.int64)
    gc_was = gc.isenabled()
    gc.disable()
    try:
        pc = time.perf_counter_ns
        for k, (r, f) in enumerate(rows):
            t0 = pc()
            predicted_peak_m(*args, f, r, 0.0, velocity, k)
            times[k] = pc() - t0
    finally:
        if gc_was:
            gc.enable()
    _preview_calls(*args, data[:10], velocity)
    kernel_ns = math.inf
    for _ in range(KERNEL_PASSES):
        t0 = time.perf_counter_ns()
        _preview_calls(*args, data, velocity)
        kernel_ns = min(kernel_ns, (time.perf_counter_ns() - t0) / len(rows))
    horizon_ms = round(pv.horizon_ticks * cfg.sample_time_s * 1e3)
    return {"case": f"road preview ({horizon_ms} ms, {pv.ticks.size} checks)",
            "J": pv.rows.shape[0],
            **_stats(times, kernel_ns), "filters_per_tick": 0.0}


def _time_previewed(design: Any, cfg: RigConfig, data: np.ndarray) -> dict[str, Any]:
    """The default law's tick with a live road preview, as the loop calls it:
    ``BankRuntime.step_previewed`` (the preview's prediction, its stop clamp and the step
    in one call) on a road velocity ring; no kernel column."""
    pv = road_preview(cfg)
    assert pv is not None
    rt = BankRuntime(design, blending=Blending.FUZZY, weight_set=0)
    rng = np.random.default_rng(2)
    ring = np.ascontiguousarray(rng.normal(0.0, 0.3, data.shape[0] + pv.horizon_ticks))
    rows = [(float(a), float(b), float(c)) for a, b, c in data]
    step = rt.step_previewed
    for k, (r, a, f) in enumerate(rows[: min(2000, len(rows))]):       # warm-up
        step(pv, r, a, f, ring, k)
    rt.reset()
    times = np.empty(len(rows), dtype=np.int64)
    gc_was = gc.isenabled()
    gc.disable()
    try:
        pc = time.perf_counter_ns
        for k, (r, a, f) in enumerate(rows):
            t0 = pc()
            step(pv, r, a, f, ring, k)
            times[k] = pc() - t0
    finally:
        if gc_was:
            gc.enable()
    return {"case": "default bank, previewed tick", "J": design.n_models,
            **_stats(times, math.nan), "filters_per_tick": math.nan}


def run(quick: bool = False) -> list[dict[str, Any]]:
    n = 20_000 if quick else 200_000
    layered = default_config()
    base = one_layer(layered)
    cfg3 = base.replace(design={"include_airborne_model": False})
    cfg27 = base.replace(design={"linearisation_deflections_m": GRID_DEFLECTIONS_M,
                                 "tire_damping_scales": GRID_DAMPING_SCALES},
                         moving_bank={"active_models": 3})
    d3, d4, d27 = design_bank(cfg3), design_bank(base), design_bank(cfg27)
    d_default = design_bank(layered)
    data = _inputs(base, n)
    # weight set 1: one LQ gain per model; 0: the travel schedule, the default law
    # (two gains per model, docs/design.md §12)
    cases = [
        ("fuzzy J=3", d3, Blending.FUZZY, 1),
        ("fuzzy J=4 (+airborne), set 1", d4, Blending.FUZZY, 1),
        ("fuzzy J=4, schedule (one layer)", d4, Blending.FUZZY, 0),
        ("bayes J=3", d3, Blending.BAYES, 1),
        ("single (plain LQG)", d4, Blending.LQG, 1),
        ("moving 9x3+air=28, k=3", d27, Blending.MOVING, 1),
        ("fuzzy, schedule, default bank", d_default, Blending.FUZZY, 0),
    ]
    rows: list[dict[str, Any]] = []
    for name, d, mode, ws in cases:
        rt = BankRuntime(d, blending=mode, weight_set=ws)
        row: dict[str, Any] = {"case": name, "J": d.n_models}
        row.update(_time_case(rt, data))
        rows.append(row)
    rows.append(_time_preview(layered, data))
    rows.append(_time_previewed(d_default, layered, data))
    return rows


def notes(rows: list[dict[str, Any]]) -> list[str]:
    by = {r["case"]: r for r in rows}
    ref, mov = by.get("fuzzy J=3"), by.get("moving 9x3+air=28, k=3")
    out = []
    if ref and mov:
        out.append(f"ratio moving 28 (k=3) / fuzzy J=3: median "
                   f"{mov['median_us'] / ref['median_us']:.2f}x, kernel "
                   f"{mov['kernel_mean_us'] / ref['kernel_mean_us']:.2f}x (goal <= 1.3x)")
        ok = ref["median_us"] < 10.0 and ref["p99.9_us"] < 50.0
        out.append(f"fuzzy J=3 goal (median < 10 us, p99.9 < 50 us): "
                   f"{'met' if ok else 'NOT met'}")
    one, default = (by.get("fuzzy J=4, schedule (one layer)"),
                    by.get("fuzzy, schedule, default bank"))
    if one and default:
        out.append(f"default bank ({default['J']} models) / one layer: median "
                   f"{default['median_us'] / one['median_us']:.2f}x "
                   f"({default['median_us']:.2f} us; issue 22's goal for the default bank: "
                   "<= 5 us)")
    previewed = by.get("default bank, previewed tick")
    if previewed:
        out.append(f"default bank, tick with a live road preview (step_previewed: the "
                   f"prediction, the stop clamp and the step): {previewed['median_us']:.2f} "
                   "us median (goal for the default bank <= 5 us)")
    return out


def format_table(rows: list[dict[str, Any]]) -> str:
    head = f"{'case':<32}{'J':>4}{'median':>9}{'p99':>9}{'p99.9':>9}{'max':>9}" \
           f"{'kernel':>9}{'filt/tick':>10}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['case']:<32}{r['J']:>4}{r['median_us']:>9.2f}{r['p99_us']:>9.2f}"
                     f"{r['p99.9_us']:>9.2f}{r['max_us']:>9.1f}{r['kernel_mean_us']:>9.3f}"
                     f"{r['filters_per_tick']:>10.2f}")
    return "\n".join(lines + notes(rows))


if __name__ == "__main__":
    rows_ = run(quick="--quick" in sys.argv[1:])
    print(TITLE)
    print(format_table(rows_))
