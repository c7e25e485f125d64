"""Tables (markdown + CSV), thesis-claim checks and figures of the study."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hil.study.matrix import ENVELOPE_LABELS, ENVELOPE_PAIRS, selection_of
from hil.study.tradeoff import TradeoffGrid

__all__ = ["LABEL_ORDER", "claims", "mean_of", "rows_where", "tables_markdown", "write_csv",
           "write_figures"]

Row = dict[str, Any]
LABEL_ORDER = ("passive", "skyhook", "lqg-1", "fuzzy-1", "bayes-1", "moving-1", "fullstate-1",
               "lqg-2", "fuzzy-2", "bayes-2", "moving-2", "fullstate-2",
               "lqg-0", "fuzzy-0", "bayes-0", "moving-0")    # -0: the travel schedule (§12)


def rows_where(rows: Iterable[Row], **kw: Any) -> list[Row]:
    return [r for r in rows if all(r.get(k) == v for k, v in kw.items())]


def mean_of(rows: Sequence[Row], key: str) -> float:
    x = np.array([float(r[key]) for r in rows], dtype=float)
    return float(np.mean(x)) if x.size else math.nan


def _f(x: Any, digits: int = 3) -> str:
    if x is None or not math.isfinite(float(x)):
        return "–"
    return f"{float(x):.{digits}g}"


def write_csv(rows: Sequence[Row], path: Path) -> None:
    keys: list[str] = []
    for r in rows:
        for k in r:
            if k != "traces" and k not in keys:
                keys.append(k)
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in keys})


def _table(header: Sequence[str], body: Iterable[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(row) + " |" for row in body]
    return [*out, ""]


def thesis_rows(rows: Sequence[Row]) -> list[Row]:
    return [r for r in rows if r["group"] == "main" and r["road"] == "rough-course"]


def claim_values(rows: Sequence[Row]) -> dict[str, float]:
    """The numbers behind :func:`claims` (ratios to passive on the thesis case)."""
    t = thesis_rows(rows)

    def vals(label: str, key: str) -> list[float]:
        return [float(r[key]) for r in rows_where(t, label=label)] or [math.nan]

    return {
        "ws1_absorbed_power_mean": float(np.mean(vals("fuzzy-1", "absorbed_power_ratio"))),
        "ws1_absorbed_power_worst": max(vals("fuzzy-1", "absorbed_power_ratio")),
        "ws1_rattlespace_rms_worst": max(vals("fuzzy-1", "rattlespace_rms_m_ratio")),
        "ws2_absorbed_power_mean": float(np.mean(vals("fuzzy-2", "absorbed_power_ratio"))),
        "ws2_rattlespace_peak_worst": max(vals("fuzzy-2", "rattlespace_peak_m_ratio")),
        "ws2_rattlespace_rms_worst": max(vals("fuzzy-2", "rattlespace_rms_m_ratio")),
    }


def claims(rows: Sequence[Row]) -> list[tuple[str, str, bool]]:
    """(claim, measured, holds) on the thesis case (means over the road seeds) for the
    fuzzy-blended bank, the thesis's controller."""
    t = thesis_rows(rows)

    def m(label: str, key: str) -> float:
        return mean_of(rows_where(t, label=label), key)

    def worst(label: str, key: str) -> float:
        sel = rows_where(t, label=label)
        return max(float(r[key]) for r in sel) if sel else math.nan

    def at_most(claim: str, label: str, key: str, bound: float) -> tuple[str, str, bool]:
        """A claim that the worst seed of ``label`` keeps ``key`` at or below ``bound``."""
        return (claim, f"mean {_f(m(label, key))}, worst seed {_f(worst(label, key))}",
                worst(label, key) <= bound)

    ap1, ap2 = m("fuzzy-1", "absorbed_power_ratio"), m("fuzzy-2", "absorbed_power_ratio")
    return [
        at_most("weight set 1 at least halves absorbed power (ratio <= 0.5, every seed)",
                "fuzzy-1", "absorbed_power_ratio", 0.5),
        at_most("weight set 1: rattlespace RMS no larger than passive (ratio <= 1)",
                "fuzzy-1", "rattlespace_rms_m_ratio", 1.0),
        ("weight set 2 reduces absorbed power further than set 1",
         f"set 2 {_f(ap2)} vs set 1 {_f(ap1)}", ap2 < ap1),
        at_most("weight set 2: peak travel no larger than passive (ratio <= 1)",
                "fuzzy-2", "rattlespace_peak_m_ratio", 1.0),
        at_most("weight set 2: rattlespace RMS no larger than passive (ratio <= 1)",
                "fuzzy-2", "rattlespace_rms_m_ratio", 1.0),
    ]


def _headline(rows: Sequence[Row]) -> list[str]:
    t = thesis_rows(rows)
    body = []
    for lab in LABEL_ORDER:
        sel = rows_where(t, label=lab)
        if not sel:
            continue
        ap = [float(r["absorbed_power_ratio"]) for r in sel]
        body.append([
            lab, f"{_f(np.mean(ap))} ({_f(min(ap), 2)}–{_f(max(ap), 2)})",
            _f(mean_of(sel, "wk_rms_mps2_ratio")), _f(mean_of(sel, "rattlespace_rms_m_ratio")),
            _f(mean_of(sel, "rattlespace_peak_m_ratio")),
            _f(mean_of(sel, "tire_load_rms_ratio_ratio")),
            _f(100 * mean_of(sel, "time_off_ground_fraction"), 2),
            _f(mean_of(sel, "bump_stop_time_s"), 2), _stop_degradations(sel),
            _f(mean_of(sel, "force_rms_n"), 4), _f(mean_of(sel, "hydraulic_power_mean_w"), 3),
            str(int(sum(float(r["unstable"]) + float(r["n_faults"]) for r in sel)))])
    return _table(["controller-weights", "absorbed power (seed range)", "Wk RMS",
                   "rattlespace RMS", "rattlespace peak", "dyn. tire load RMS",
                   "off ground [%]", "stop contact [s]", "stop degradations",
                   "force RMS [N]", "hydr. power [W]", "unstable+faults"], body)


def _stop_degradations(sel: Sequence[Row]) -> str:
    """Stop-contact degradations summed over the runs (docs/design.md §9.8); "–" for
    controllers without the monitor (passive, skyhook, full-state LQ)."""
    if not all("stop_degradations" in r for r in sel):
        return "–"
    return str(int(sum(float(r["stop_degradations"]) for r in sel)))


def _ap_rs(sel: Sequence[Row]) -> str:
    if not sel:
        return "–"
    s = f"{_f(mean_of(sel, 'absorbed_power_ratio'), 2)} / " \
        f"{_f(mean_of(sel, 'rattlespace_rms_m_ratio'), 2)}"
    marks = []
    if any(float(r["nonfinite"]) for r in sel):
        marks.append("non-finite")
    elif any(float(r["bump_stop_slam"]) for r in sel):
        marks.append("slam")
    if any(float(r["n_faults"]) for r in sel):
        marks.append("fault")
    return s + (f" ✗{'+'.join(marks)}" if marks else "")


def _roads(rows: Sequence[Row]) -> list[str]:
    main = [r for r in rows if r["group"] == "main"]
    keys: list[tuple[str, float]] = []
    for r in main:
        k = (r["road"], r["speed_mps"])
        if k not in keys:
            keys.append(k)
    labels = [lab for lab in LABEL_ORDER[1:] if rows_where(main, label=lab)]
    body = []
    for road, speed in keys:
        sel = rows_where(main, road=road, speed_mps=speed)
        body.append([f"{road} @ {speed:g} m/s"]
                    + [_ap_rs(rows_where(sel, label=lab)) for lab in labels])
    return _table(["road", *labels], body)


def _mc(rows: Sequence[Row]) -> list[str]:
    body = []
    groups = sorted({r["group"] for r in rows if r["group"].startswith("mc")},
                    key=lambda g: int(g[2:]))
    for g in groups:
        sel_g = [r for r in rows if r["group"] == g]
        for lab in LABEL_ORDER:
            sel = rows_where(sel_g, label=lab)
            if not sel:
                continue
            ap = np.array([float(r["absorbed_power_ratio"]) for r in sel])
            rs = np.array([float(r["rattlespace_rms_m_ratio"]) for r in sel])
            pk = np.array([float(r["rattlespace_peak_m"]) for r in sel])
            body.append([f"{g[2:]} %", lab, str(len(sel)),
                         f"{_f(ap.mean())} ± {_f(ap.std(), 2)}",
                         f"{_f(ap.min(), 2)}–{_f(ap.max(), 2)}",
                         f"{_f(rs.mean())} ± {_f(rs.std(), 2)}", _f(1000 * pk.max()),
                         _f(mean_of(sel, "bump_stop_time_s"), 2), _stop_degradations(sel),
                         _f(100 * mean_of(sel, "no_rule_fired_fraction"), 2)
                         if all("no_rule_fired_fraction" in r for r in sel) else "–",
                         str(int(sum(float(r["unstable"]) for r in sel))),
                         str(int(sum(float(r["n_faults"]) > 0 for r in sel)))])
    return _table(["spread", "controller", "runs", "absorbed power", "min–max",
                   "rattlespace RMS", "max peak [mm]", "stop contact [s]",
                   "stop degradations", "no rule fired [%]", "unstable", "faulted"], body)


def _mismatch(rows: Sequence[Row]) -> list[str]:
    mm = [r for r in rows if r["group"] == "mismatch"]
    tags = sorted({r["param_tag"] for r in mm})
    body = []
    for lab in LABEL_ORDER[1:]:
        if rows_where(mm, label=lab):
            body.append([lab] + [_ap_rs(rows_where(mm, label=lab, param_tag=t))
                                 for t in tags])
    heads = [f"tire {'stiffer' if float(t[2:]) > 1 else 'softer'} x{t[2:]}" for t in tags]
    return _table(["controller", *heads], body)


#: issue 22's bounds of the layered bank against the true-plant design: absorbed power
#: at most 10 % above it, rattlespace RMS at most 5 % above it (ratios of seed means)
ENVELOPE_POWER_BOUND = 1.10
ENVELOPE_RATTLESPACE_BOUND = 1.05
#: issue 22's stop-contact budget on many road seeds: passive's contact time plus this
#: fraction of the run
STOP_CONTACT_RUN_FRACTION = 0.001
#: issue 22's bound on the wide Monte Carlo: mean absorbed power / passive's mean
MC_POWER_BOUND = 0.5


def _plant_scale(r: Row, key: str) -> float:
    """A row's plant scale (rows of a study before the key existed: 1)."""
    v = r.get(key, 1.0)
    return 1.0 if v in ("", None) else float(v)


def _envelope(rows: Sequence[Row]) -> list[str]:
    """Per plant (sprung-mass scale, then tire stiffness scale): each controller's
    ``a / r`` (mean over road seeds) and, per law of :data:`ENVELOPE_PAIRS`, the layered
    bank's absorbed power and rattlespace RMS over the true-plant design's (ratio of the
    seed means) and whether they are within :data:`ENVELOPE_POWER_BOUND` /
    :data:`ENVELOPE_RATTLESPACE_BOUND` with no fault (``–``: the law was not run)."""
    env = [r for r in rows if r["group"] == "envelope"]
    plants = sorted({(_plant_scale(r, "tire_stiffness_scale") != 1.0,
                      _plant_scale(r, "sprung_mass_scale"),
                      _plant_scale(r, "tire_stiffness_scale")) for r in env})
    body = []
    for tire_case, mass, tire in plants:
        at = [r for r in env if _plant_scale(r, "sprung_mass_scale") == mass
              and _plant_scale(r, "tire_stiffness_scale") == tire]
        cells = [_ap_rs(rows_where(at, label=lab)) for lab in ENVELOPE_LABELS]
        verdicts = []
        for _, layered, true_plant in ENVELOPE_PAIRS:
            lay = rows_where(at, label=layered)
            true = rows_where(at, label=true_plant)
            if not (lay and true):
                verdicts.append("–")
                continue
            rel = [mean_of(lay, k) / mean_of(true, k)
                   for k in ("absorbed_power_ratio", "rattlespace_rms_m_ratio")]
            ok = (rel[0] <= ENVELOPE_POWER_BOUND and rel[1] <= ENVELOPE_RATTLESPACE_BOUND
                  and not any(float(r["n_faults"]) for r in lay))
            verdicts.append(f"{rel[0]:.3f}, {rel[1]:.3f}: {'yes' if ok else '**no**'}")
        plant = f"tire x{tire:g}" if tire_case else f"M x{mass:g}"
        body.append([plant, *cells, *verdicts])
    bounds = (f"within {_f(100 * (ENVELOPE_POWER_BOUND - 1))} % / "
              f"{_f(100 * (ENVELOPE_RATTLESPACE_BOUND - 1))} %, no fault")
    return _table(["plant", *ENVELOPE_LABELS,
                   *(f"{law}: layered ÷ true-plant power, rattlespace; {bounds}"
                     for law, _, _ in ENVELOPE_PAIRS)], body)


def _labels_in_order(sel: Sequence[Row]) -> list[str]:
    """Labels in the order the rows first show them, passive first."""
    out = ["passive"] if rows_where(sel, label="passive") else []
    for r in sel:
        if r["label"] not in out:
            out.append(r["label"])
    return out


def _faulted(r: Row) -> bool:
    return bool(float(r["n_faults"]) or float(r["nonfinite"]))


def _passive_by_plant(sel: Sequence[Row]) -> dict[tuple[Any, ...], Row]:
    """The passive row of each (road seed, plant, duration) of one group."""
    return {(r["road_seed"], r["param_tag"], r["duration_s"]): r
            for r in sel if r["controller"] == "passive"}


def _envelope_mc(rows: Sequence[Row]) -> list[str]:
    """The wide Monte Carlo per Monte Carlo seed and controller: slams against passive's
    on the same plants, faults, mean absorbed power over passive's mean (and the mean of
    the per-plant ratios) and the issue-22 verdict."""
    mc = [r for r in rows if r["group"] == "envelope-mc"]
    body = []
    for seed in sorted({int(r["road_seed"]) for r in mc}):
        sel = [r for r in mc if int(r["road_seed"]) == seed]
        ref = _passive_by_plant(sel)
        p_power = mean_of(list(ref.values()), "absorbed_power")
        for lab in _labels_in_order(sel):
            runs = rows_where(sel, label=lab)
            passive = [ref.get((r["road_seed"], r["param_tag"], r["duration_s"]))
                       for r in runs]
            slams = sum(bool(float(r["bump_stop_slam"])) for r in runs)
            p_slams = sum(bool(p is not None and float(p["bump_stop_slam"])) for p in passive)
            new_slams = sum(bool(float(r["bump_stop_slam"])) and not (
                p is not None and float(p["bump_stop_slam"])) for r, p in zip(
                    runs, passive, strict=True))
            faults = sum(_faulted(r) for r in runs)
            power = mean_of(runs, "absorbed_power") / p_power if p_power else math.nan
            verdict = "–" if lab == "passive" else (
                "yes" if slams <= p_slams and faults == 0 and power <= MC_POWER_BOUND
                else "**no**")
            body.append([str(seed), lab, str(len(runs)), f"{slams} ({p_slams})",
                         str(new_slams), str(faults), _f(mean_of(runs, "absorbed_power")),
                         _f(power), _f(mean_of(runs, "absorbed_power_ratio")),
                         _f(mean_of(runs, "rattlespace_rms_m_ratio")),
                         _f(mean_of(runs, "bump_stop_time_s"), 2), _stop_degradations(runs),
                         verdict])
    return _table(["MC seed", "controller", "plants", "slams (passive's)",
                   "slams where passive does not", "faulted",
                   "mean absorbed power [(m/s²)²]", "÷ passive's mean",
                   "mean of per-plant ratios", "rattlespace RMS", "stop contact [s]",
                   "stop degradations",
                   f"slams <= passive's, 0 faults, power <= {_f(MC_POWER_BOUND)}"], body)


def _envelope_seeds(rows: Sequence[Row]) -> list[str]:
    """Many road seeds per controller: absorbed power and rattlespace RMS over passive
    (mean and range over seeds), stop-contact time against passive's + the run's
    :data:`STOP_CONTACT_RUN_FRACTION`, slams where passive does not slam, faults and
    the issue-22 verdict."""
    sel = [r for r in rows if r["group"] == "envelope-seeds"]
    ref = _passive_by_plant(sel)
    body = []
    for lab in _labels_in_order(sel):
        runs = rows_where(sel, label=lab)
        passive = [ref.get((r["road_seed"], r["param_tag"], r["duration_s"])) for r in runs]
        excess = [float(r["bump_stop_time_s"]) - float(p["bump_stop_time_s"])
                  - STOP_CONTACT_RUN_FRACTION * float(r["duration_s"])
                  if p is not None else math.nan for r, p in zip(runs, passive, strict=True)]
        over = sum(not e <= 0.0 for e in excess)
        new_slams = sum(bool(float(r["bump_stop_slam"])) and not (
            p is not None and float(p["bump_stop_slam"])) for r, p in zip(
                runs, passive, strict=True))
        faults = sum(_faulted(r) for r in runs)
        ap = [float(r["absorbed_power_ratio"]) for r in runs]
        contact = [float(r["bump_stop_time_s"]) for r in runs]
        verdict = "–" if lab == "passive" else (
            "yes" if over == 0 and new_slams == 0 and faults == 0 else "**no**")
        body.append([lab, str(len(runs)),
                     f"{_f(np.mean(ap))} ({_f(min(ap), 2)}–{_f(max(ap), 2)})",
                     _f(mean_of(runs, "rattlespace_rms_m_ratio")),
                     _f(mean_of(runs, "rattlespace_peak_m_ratio")),
                     f"{_f(np.mean(contact), 2)} / {_f(max(contact), 2)}",
                     "–" if lab == "passive" else f"{over} ({_f(max(excess), 2)})",
                     "–" if lab == "passive" else str(new_slams),
                     str(sum(bool(float(r["bump_stop_slam"])) for r in runs)), str(faults),
                     _stop_degradations(runs), verdict])
    return _table(["controller-weights", "seeds", "absorbed power (seed range)",
                   "rattlespace RMS", "rattlespace peak",
                   "stop contact mean / max [s]",
                   f"seeds over passive + {_f(100 * STOP_CONTACT_RUN_FRACTION)} % "
                   "(largest excess [s])", "slams where passive does not", "slams",
                   "faulted", "stop degradations", "holds"], body)


def _sweep(rows: Sequence[Row], group: str, key: str, unit: str) -> list[str]:
    sel = [r for r in rows if r["group"] == group and r["controller"] != "passive"]
    labels: list[str] = []
    for r in sel:
        if r["label"] not in labels:
            labels.append(r["label"])
    values = sorted({float(r[key]) for r in sel})
    body = [[f"{v:g} {unit}"] + [_ap_rs([r for r in rows_where(sel, label=lab)
                                         if float(r[key]) == v]) for lab in labels]
            for v in values]
    return _table([key, *labels], body)


def _rho(rows: Sequence[Row], grid: TradeoffGrid | None) -> list[str]:
    sel = [r for r in rows if r["group"] == "rho" and r["controller"] != "passive"]
    body = []
    for r in sorted(sel, key=lambda r: (r["rho1"], r["rho2"])):
        lin_ap = lin_rs = rig_ap = rig_rs = math.nan
        if grid is not None and grid.lqg:
            i = int(np.argmin(np.abs(np.log10(grid.rho1) - math.log10(r["rho1"]))))
            j = int(np.argmin(np.abs(np.log10(grid.rho2) - math.log10(r["rho2"]))))
            if math.isclose(grid.rho1[i], r["rho1"]) and math.isclose(grid.rho2[j], r["rho2"]):
                lin_ap = grid.lqg["absorbed_power"][i, j]
                lin_rs = grid.lqg["rattlespace_rms"][i, j]
                hit = [k for k, v in enumerate(grid.rig_rho1) if math.isclose(v, r["rho1"])]
                if hit and grid.rig_lqg:
                    rig_ap = grid.rig_lqg["absorbed_power"][hit[0], j]
                    rig_rs = grid.rig_lqg["rattlespace_rms"][hit[0], j]
        body.append([_f(r["rho1"]), _f(r["rho2"]), _f(lin_ap), _f(lin_rs), _f(rig_ap),
                     _f(rig_rs),
                     _f(r["absorbed_power_ratio"]), _f(r["rattlespace_rms_m_ratio"]),
                     _f(100 * float(r["time_off_ground_fraction"]), 2)])
    return _table(["rho1", "rho2", "linear LQG, ideal actuator: absorbed power",
                   "rattlespace", "linear LQG, rig loop: absorbed power", "rattlespace",
                   "nonlinear absorbed power", "nonlinear rattlespace",
                   "off ground [%]"], body)


def _tuning(rows: Sequence[Row], chosen: Any) -> list[str]:
    sel = [r for r in rows if r["group"] == "tune" and r["controller"] == "skyhook"]
    sel = sorted(sel, key=lambda r: float(r["absorbed_power_ratio"]))
    body = []
    for r in sel:
        mark = " ◀" if (r["c_sky_ns_per_m"], r["c_ground_ns_per_m"], r["damper_cancel"]) == (
            chosen.c_sky_ns_per_m, chosen.c_ground_ns_per_m, chosen.damper_cancel) else ""
        body.append([_f(r["c_sky_ns_per_m"], 4), _f(r["c_ground_ns_per_m"], 4),
                     _f(r["damper_cancel"]), _f(r["absorbed_power_ratio"]) + mark,
                     _f(r["rattlespace_rms_m_ratio"]), _f(r["tire_load_rms_ratio_ratio"])])
    return _table(["c_sky [Ns/m]", "c_ground [Ns/m]", "damper cancel", "absorbed power",
                   "rattlespace RMS", "dyn. tire load RMS"], body)


def config_line(cfg: Any) -> str:
    """The configuration values the results depend on most, and the config hash."""
    from controller.config import config_hash
    v, fl, a = cfg.vehicle, cfg.force_loop, cfg.actuator
    return (f"Configuration `{config_hash(cfg)[:12]}`: M = {v.sprung_mass_kg:g} kg, "
            f"m = {v.unsprung_mass_kg:g} kg, controller {cfg.design.sample_rate_hz:g} Hz, "
            f"PI force loop kp = {fl.kp_per_n:g} 1/N, ki = {fl.ki_per_ns:g} 1/(N s), "
            f"spool tau = {1000 * a.spool_time_constant_s:g} ms, design actuator model "
            f"{getattr(cfg.design, 'actuator_model', 'ideal')!r} (compute delay "
            f"{getattr(cfg.design, 'compute_delay_ticks', 0)} tick), weight sets "
            f"{cfg.design.weight_sets}.")


def tables_markdown(rows: Sequence[Row], grid: TradeoffGrid | None, chosen_skyhook: Any,
                    describe: str, wall_s: float, jobs: int, cfg: Any = None) -> str:
    out = ["# Control performance study: results", "",
           "Generated by `rig study` (hil/study); every ratio is closed loop / passive on the "
           "same road, seed, rate and plant.  Cells `a / r` = absorbed-power ratio / "
           "rattlespace-RMS ratio; ✗ marks a run that hit a bump stop hard (slam: more "
           "than 10 mm into it), latched a fault, or went non-finite.  Labels are "
           "controller-weight set; weight set 0 is the travel schedule (weight set 2 where "
           "travel allows, weight set 1 before the stops; docs/design.md §12).", "",
           f"Matrix: {describe}.  {len(rows)} runs in {wall_s:.0f} s on {jobs} processes.", "",
           config_line(cfg) if cfg is not None else "", ""]

    ran = {selection_of(r["group"]) for r in rows}      # hil.study.matrix.GROUPS names
    if "main" in ran:
        out += ["## Thesis case: 1.35 in RMS course at 25 mph (mean over road seeds)", ""]
        out += _headline(rows)
        out += ["## Thesis claims (fuzzy-blended bank)", ""]
        out += _table(["claim", "measured", "holds"],
                      [[c, m, "yes" if ok else "**no**"] for c, m, ok in claims(rows)])
        out += ["## Roads", "", *_roads(rows)]
    if "mc" in ran:
        out += ["## Monte Carlo (thesis case; ratios to the passive run of the same plant)",
                ""]
        out += _mc(rows)
    if "mismatch" in ran:
        out += ["## Plant-model mismatch (tire stiffness law scaled, design nominal)", ""]
        out += _mismatch(rows)
    if "delay" in ran:
        out += ["## Loop delay (thesis case)", "", *_sweep(rows, "delay", "delay_ms", "ms")]
    if "rate" in ran:
        out += ["## Controller sample rate (design redone per rate)", ""]
        out += _sweep(rows, "rate", "rate_hz", "Hz")
    if "rho" in ran:
        out += ["## rho2 trade-off: linear analysis vs nonlinear check points (single LQG)",
                ""]
        out += _rho(rows, grid)
    if "envelope" in ran:
        observed = sorted({float(r.get("observe_s") or 0.0) for r in rows
                           if r["group"] == "envelope"})
        obs = ", ".join(f"{o:g}" for o in observed)
        out += ["## Operating envelope: ballast sweep and tire stiffness (thesis course; "
                "plant sprung mass or tire stiffness scaled)", "",
                "Plant `[emulator] sprung_mass_scale` (M x) or `tire_stiffness_scale` "
                "(tire x) = the scale (LVDT zeroed at its own rest); each run as `rig sim "
                f"--road rough-course --speed 11.176 --seed S --observe {obs}` makes it: "
                f"observed {obs} s before arming, as the service runs (the bank chooses its "
                "layer before the valve is armed; the metrics cover the armed time).  "
                "lqg-1 (one-layer): the single nominal LQG; layered: the fuzzy bank with "
                "the built-in layers over sprung mass, spring rate, damping and tire "
                "stiffness; true-plant: "
                "the fuzzy bank of one layer designed with `vehicle.sprung_mass_kg` and "
                "`tire.stiffness_coefficient` = the scale x nominal, on the same plant; -1: "
                "weight set 1, -default: the "
                "configured law.  Mean over road seeds; the layered bank should "
                f"come within {_f(100 * (ENVELOPE_POWER_BOUND - 1))} % of the true-plant "
                f"design's absorbed power at rattlespace within "
                f"{_f(100 * (ENVELOPE_RATTLESPACE_BOUND - 1))} % (issue 22); figure "
                "fig_envelope_mass.png (the ballast sweep).", ""]
        out += _envelope(rows)
    if "envelope-mc" in ran:
        out += ["## Operating envelope: 25 % parameter spread (Monte Carlo, thesis course)",
                "", "Each Monte Carlo seed's plants and runs as `rig montecarlo --runs N "
                "--spread S --duration D --seed K --weights W --controller fuzzy` makes them "
                "(M m K C Kt Ct ~ N(1, S), ride height set by preload, road seed K).  "
                "fuzzy-default: the configuration's weight set and defaults; (one-layer): "
                "the bank of one layer, the tire models of the configured vehicle; "
                "(layered): the built-in layers over [M, K, C] and the tire.  Slams: runs "
                "more than 10 mm into a bump stop (passive's on the same plants in "
                "brackets); faulted: a latched fault or a non-finite state.  Issue 22 "
                "asks for slams at most passive's, no fault and mean absorbed power at most "
                f"{_f(MC_POWER_BOUND)} x passive's.", ""]
        out += _envelope_mc(rows)
    if "envelope-seeds" in ran:
        out += ["## Operating envelope: many road seeds (thesis course)", "",
                "Each run as `rig sim --road rough-course --speed 11.176 --duration D "
                "--seed S --controller C --weights W` makes it; -default: the "
                "configuration's weight set and defaults.  Ratios to passive on the same "
                "road seed, mean (and range) over seeds.  Issue 22 asks, on every seed, for "
                "stop contact at most passive's + "
                f"{_f(100 * STOP_CONTACT_RUN_FRACTION)} % of the run, no slam where "
                "passive does not slam and no fault.", ""]
        out += _envelope_seeds(rows)
    if "tune" in ran:
        out += ["## Skyhook tuning search (rough course, road seed 101)", ""]
        out += _tuning(rows, chosen_skyhook)
    return "\n".join(out)


# ------------------------------------------------------------------------------- figures


def _plt() -> Any:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    _plt().close(fig)
    return path


def _trace(rows: Sequence[Row], **kw: Any) -> dict[str, Any] | None:
    for r in rows_where(rows, **kw):
        if "traces" in r:
            tr: dict[str, Any] = r["traces"]
            return tr
    return None


def _fig_thesis(rows: Sequence[Row], out: Path, ws: int, name: str) -> Path | None:
    t = [r for r in thesis_rows(rows) if "traces" in r]
    p, c = _trace(t, label="passive"), _trace(t, label=f"fuzzy-{ws}")
    if p is None or c is None:
        return None
    plt = _plt()
    fig, ax = plt.subplots(2, 1, figsize=(8, 5.5))
    tp = np.arange(p["accel_mps2"].shape[0]) * float(p["dt_s"])
    tc = np.arange(c["accel_mps2"].shape[0]) * float(c["dt_s"])
    ax[0].plot(tp, p["int_accel_sq"], label="open loop (passive)")
    ax[0].plot(tc, c["int_accel_sq"], label=f"closed loop (fuzzy bank, weight set {ws})")
    ax[0].set_ylabel("∫ acc² dt [m²/s³]")
    ax[0].set_xlabel("time [s]")
    ax[0].legend(fontsize=8)
    ax[0].grid(alpha=0.3)
    ax[1].plot(tp, 1000 * p["rattlespace_m"], lw=0.6, label="open loop")
    ax[1].plot(tc, 1000 * c["rattlespace_m"], lw=0.6, label="closed loop")
    ax[1].set_ylabel("working space about static [mm]")
    ax[1].set_xlabel("time [s] (first 20 s)")
    ax[1].set_xlim(0, min(tp[-1], 20.0))
    ax[1].grid(alpha=0.3)
    ax[0].set_title(f"Fig. {name}: 1.35 in RMS course, 25 mph, weight set {ws}", fontsize=9)
    return _save(fig, out / f"fig{name.replace('.', '_')}_ws{ws}.png")


def _fig_actuation(rows: Sequence[Row], out: Path) -> Path | None:
    t = [r for r in thesis_rows(rows) if "traces" in r]
    plt = _plt()
    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    found = False
    for i, ws in enumerate((1, 2)):
        c = _trace(t, label=f"fuzzy-{ws}")
        if c is None:
            continue
        found = True
        tc = np.arange(c["force_n"].shape[0]) * float(c["dt_s"])
        ax[i].plot(tc, c["force_n"] / 1000, lw=0.5)
        ax[i].set_ylabel("force [kN]")
        ax[i].set_title(f"Fig. {'5.2' if ws == 1 else '5.4'}: control actuation, weight set "
                        f"{ws}", fontsize=9)
        ax[i].grid(alpha=0.3)
        ax[i].set_xlim(0, min(tc[-1], 20.0))
    ax[1].set_xlabel("time [s]")
    if not found:
        plt.close(fig)
        return None
    return _save(fig, out / "fig5_2_5_4_actuation.png")


def _fig_firing(rows: Sequence[Row], out: Path, q_grid: np.ndarray, curve: np.ndarray,
                model_names: Sequence[str]) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(q_grid, curve)
    ax[0].set_xlabel("likelihood quotient q")
    ax[0].set_ylabel("firing weight (centre of area)")
    ax[0].set_title("Fig. A.4: firing weight vs q", fontsize=9)
    ax[0].grid(alpha=0.3)
    c = _trace(thesis_rows(rows), label="fuzzy-1")
    if c is not None and "firing_weight" in c:
        w = c["firing_weight"]
        tc = np.arange(w.shape[0]) * float(c["dt_s"])
        sel = tc <= 5.0
        # the models that ran (a layered bank runs one layer's; the others weigh 0)
        for j in np.flatnonzero(np.any(w[sel] != 0.0, axis=0)):
            ax[1].plot(tc[sel], w[sel, j], lw=0.7, label=str(model_names[int(j)]))
        ax[1].legend(fontsize=7)
    ax[1].set_xlabel("time [s]")
    ax[1].set_ylabel("normalised firing weight")
    ax[1].set_title("firing weight per model, thesis case, weight set 1", fontsize=9)
    ax[1].grid(alpha=0.3)
    return _save(fig, out / "figA_4_firing_weight.png")


def _fig_mc(rows: Sequence[Row], out: Path) -> list[Path]:
    plt = _plt()
    paths = []
    tr = [r["traces"] for r in rows if r["group"] == "mc5" and r.get("label") == "fuzzy-1"
          and "traces" in r]
    if tr:
        fig, ax = plt.subplots(figsize=(8, 4))
        for t in tr[:8]:
            tt = np.arange(t["rattlespace_m"].shape[0]) * float(t["dt_s"])
            ax.plot(tt, 1000 * t["rattlespace_m"], lw=0.5)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("rattlespace about static [mm]")
        ax.set_title(f"Fig. 4.1: Monte Carlo, fuzzy bank weight set 1, 5 % spread, "
                     f"{min(len(tr), 8)} runs", fontsize=9)
        ax.grid(alpha=0.3)
        paths.append(_save(fig, out / "fig4_1_montecarlo.png"))
    groups = sorted({r["group"] for r in rows if r["group"].startswith("mc")},
                    key=lambda g: int(g[2:]))
    if groups:
        fig, axes = plt.subplots(1, len(groups), figsize=(5 * len(groups), 4), sharey=True,
                                 squeeze=False)
        for ax, g in zip(axes[0], groups, strict=True):
            labs = [lab for lab in LABEL_ORDER[1:] if rows_where(rows, group=g, label=lab)]
            data = [[float(r["absorbed_power_ratio"]) for r in rows_where(rows, group=g,
                                                                            label=lab)]
                    for lab in labs]
            ax.boxplot(data)
            ax.set_xticks(range(1, len(labs) + 1), labs, rotation=45, fontsize=8)
            ax.set_title(f"Monte Carlo {g[2:]} % spread", fontsize=9)
            ax.axhline(1.0, color="k", lw=0.5)
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel("absorbed power / passive")
        paths.append(_save(fig, out / "fig_montecarlo_spread.png"))
    return paths


def _fig_tradeoff(rows: Sequence[Row], grid: TradeoffGrid, out: Path,
                  thesis_sets: Sequence[Sequence[float]]) -> list[Path]:
    plt = _plt()
    paths = []
    fig, ax = plt.subplots(figsize=(7, 5))
    lr1, lr2 = np.log10(grid.rho1), np.log10(grid.rho2)
    z = np.log10(grid.lq["absorbed_power"])
    cs = ax.contourf(lr2, lr1, z, levels=20, cmap="viridis")
    fig.colorbar(cs, ax=ax, label="log10 absorbed power / passive (LQ)")
    cl = ax.contour(lr2, lr1, grid.lq["rattlespace_rms"], levels=[0.8, 1.0, 1.2],
                    colors="w", linewidths=0.8)
    ax.clabel(cl, fmt="rattlespace %.1f", fontsize=7)
    for i, w in enumerate(thesis_sets[:2], start=1):
        ax.plot(math.log10(w[1]), math.log10(w[0]), "r*", ms=10)
        ax.annotate(f"set {i}", (math.log10(w[1]), math.log10(w[0])), color="r",
                    xytext=(5, 5), textcoords="offset points")
    ax.set_xlabel("log10 rho2 (rattlespace weight)")
    ax.set_ylabel("log10 rho1 (tire deflection weight)")
    ax.set_title(f"Fig. 2.2: absorbed power surface (LQ, ideal force actuator), rho3 = "
                 f"{grid.rho3:g}, model {grid.model}", fontsize=9)
    paths.append(_save(fig, out / "fig2_2_absorbed_power_surface.png"))

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for i, r1 in enumerate(grid.rho1):
        if r1 not in (1.0, 10.0):
            continue
        for kind, d, st in (("LQ", grid.lq, "-"), ("LQG", grid.lqg, "--")):
            if not d:
                continue
            ax[0].semilogx(grid.rho2, d["absorbed_power"][i], st, label=f"{kind}, rho1={r1:g}")
            ax[1].plot(d["rattlespace_rms"][i], d["absorbed_power"][i], st,
                       label=f"{kind}, rho1={r1:g}")
    for i, r1 in enumerate(grid.rig_rho1):
        for kind, d, st in (("rig LQ", grid.rig_lq, ":"), ("rig LQG", grid.rig_lqg, "-.")):
            if d:
                ax[0].semilogx(grid.rho2, d["absorbed_power"][i], st,
                               label=f"{kind}, rho1={r1:g}")
                ax[1].plot(d["rattlespace_rms"][i], d["absorbed_power"][i], st,
                           label=f"{kind}, rho1={r1:g}")
    chk = [r for r in rows if r["group"] == "rho" and r["controller"] != "passive"]
    if chk:
        ax[0].semilogx([r["rho2"] for r in chk], [r["absorbed_power_ratio"] for r in chk],
                       "ko", ms=4, label="nonlinear sim (LQG)")
        ax[1].plot([r["rattlespace_rms_m_ratio"] for r in chk],
                   [r["absorbed_power_ratio"] for r in chk], "ko", ms=4,
                   label="nonlinear sim (LQG)")
    ax[0].set_xlabel("rho2")
    ax[0].set_ylabel("absorbed power / passive")
    ax[0].set_yscale("log")
    ax[1].set_xlabel("rattlespace RMS / passive")
    ax[1].set_ylabel("absorbed power / passive")
    ax[1].set_yscale("log")
    ax[1].set_xlim(0.4, 1.8)
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    ax[0].set_title("vs rho2 (rho3 = 1e-8); rig = servo-hydraulic loop", fontsize=8)
    ax[1].set_title("comfort / travel trade-off (lines linear, dots nonlinear)", fontsize=8)
    paths.append(_save(fig, out / "fig_tradeoff_rho2.png"))
    return paths


def _fig_sweeps(rows: Sequence[Row], out: Path) -> Path | None:
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    any_ = False
    for a, group, key, xl in ((ax[0], "delay", "delay_ms", "loop delay [ms]"),
                              (ax[1], "rate", "rate_hz", "sample rate [Hz]")):
        sel = [r for r in rows if r["group"] == group and r["controller"] != "passive"]
        labels = sorted({r["label"] for r in sel})
        for lab in labels:
            s = sorted(rows_where(sel, label=lab), key=lambda r: float(r[key]))
            if not s:
                continue
            any_ = True
            x = [float(r[key]) for r in s]
            y = [float(r["absorbed_power_ratio"]) for r in s]
            line = a.plot(x, y, "o--" if "local" in lab else "o-", label=lab, ms=3)[0]
            bad = [(xi, yi) for xi, yi, r in zip(x, y, s, strict=True)
                   if float(r["unstable"]) or float(r["n_faults"])]
            if bad:
                a.plot(*zip(*bad, strict=True), "x", color=line.get_color(), ms=9)
        a.axhline(1.0, color="k", lw=0.5)
        a.set_xlabel(xl)
        a.set_ylabel("absorbed power / passive")
        a.set_yscale("log")
        a.grid(alpha=0.3)
        if labels:
            a.legend(fontsize=7)
    if not any_:
        plt.close(fig)
        return None
    ax[1].set_xscale("log")
    rates = sorted({float(r["rate_hz"]) for r in rows if r["group"] == "rate"})
    if rates:
        ax[1].set_xticks(rates, [f"{v:g}" for v in rates])
        ax[1].minorticks_off()
    ax[0].set_title("loop delay (x = slam or latched fault)", fontsize=9)
    ax[1].set_title("controller sample rate", fontsize=9)
    return _save(fig, out / "fig_delay_rate.png")


def _fig_envelope(rows: Sequence[Row], out: Path) -> Path | None:
    env = [r for r in rows if r["group"] == "envelope" and r["controller"] != "passive"
           and _plant_scale(r, "tire_stiffness_scale") == 1.0]
    if not env:
        return None
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    scales = sorted({float(r["sprung_mass_scale"]) for r in env})
    for a, key, name in ((ax[0], "absorbed_power_ratio", "absorbed power / passive"),
                         (ax[1], "rattlespace_rms_m_ratio", "rattlespace RMS / passive")):
        for lab in ENVELOPE_LABELS:
            pts = [(s, mean_of([r for r in rows_where(env, label=lab)
                                if float(r["sprung_mass_scale"]) == s], key)) for s in scales]
            pts = [(x, y) for x, y in pts if math.isfinite(y)]
            if not pts:
                continue
            line = a.plot(*zip(*pts, strict=True), "o-", label=lab, ms=3)[0]
            bad = sorted({float(r["sprung_mass_scale"]) for r in rows_where(env, label=lab)
                          if float(r["bump_stop_slam"]) or float(r["n_faults"])
                          or float(r["nonfinite"])})
            if bad:
                a.plot(bad, [y for x, y in pts if x in bad], "x", color=line.get_color(),
                       ms=9)
        a.axvline(1.0, color="k", lw=0.5)
        a.set_xlabel("plant sprung mass / configured")
        a.set_ylabel(name)
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    ax[0].set_title("ballast sweep, thesis course (x = slam or fault)", fontsize=9)
    ax[1].set_title("mean over road seeds", fontsize=9)
    return _save(fig, out / "fig_envelope_mass.png")


def _fig_controllers(rows: Sequence[Row], out: Path) -> Path | None:
    plt = _plt()
    t = thesis_rows(rows)
    labs = [lab for lab in LABEL_ORDER[1:] if rows_where(t, label=lab)]
    if not labs:
        return None
    keys = (("absorbed_power_ratio", "absorbed power"),
            ("rattlespace_rms_m_ratio", "rattlespace RMS"),
            ("tire_load_rms_ratio_ratio", "dyn. tire load RMS"))
    fig, ax = plt.subplots(figsize=(10, 4))
    x = np.arange(len(labs))
    for i, (k, name) in enumerate(keys):
        ax.bar(x + (i - 1) * 0.27, [mean_of(rows_where(t, label=lab), k) for lab in labs],
               0.27, label=name)
    ax.axhline(1.0, color="k", lw=0.6)
    ax.set_xticks(x, labs, rotation=30, fontsize=8)
    ax.set_ylabel("ratio to passive")
    ax.set_title("thesis case (1.35 in RMS, 25 mph): controllers compared", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    return _save(fig, out / "fig_controllers.png")


def write_figures(rows: Sequence[Row], out: Path, grid: TradeoffGrid | None,
                  firing: tuple[np.ndarray, np.ndarray, Sequence[str]] | None,
                  thesis_sets: Sequence[Sequence[float]]) -> list[Path]:
    """The figures of what ran (``firing``: the design's q grid, firing-weight curve and
    model names, None without the main group)."""
    makers: list[Callable[[], Path | list[Path] | None]] = [
        lambda: _fig_thesis(rows, out, 1, "5.1"),
        lambda: _fig_thesis(rows, out, 2, "5.3"),
        lambda: _fig_actuation(rows, out),
        lambda: _fig_firing(rows, out, *firing) if firing is not None else None,
        lambda: _fig_mc(rows, out),
        lambda: _fig_sweeps(rows, out),
        lambda: _fig_controllers(rows, out),
        lambda: _fig_envelope(rows, out),
    ]
    if grid is not None:
        makers.append(lambda: _fig_tradeoff(rows, grid, out, thesis_sets))
    paths: list[Path] = []
    for mk in makers:
        res = mk()
        if isinstance(res, list):
            paths += res
        elif res is not None:
            paths.append(res)
    return paths
