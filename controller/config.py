"""Rig configuration: one TOML format for the controller, the emulated rig and the service.

Every quantity is SI inside (m, s, N, kg, Pa) unless the key name says otherwise
(``_mm``, ``_hz``...).  The defaults are those of ``../shared/reference/NOTES.md``.

Loading validates every key: an unknown key, a wrong type or a value outside its
allowed range raises :class:`ConfigError` naming the dotted key, the value and the
allowed range.  Nothing is silently clamped.

Usage::

    cfg = load_config("rig.toml")      # or default_config()
    cfg.vehicle.sprung_mass_kg
    config_hash(cfg)                   # stable sha256 of the canonical content
"""

from __future__ import annotations

import dataclasses
import hashlib
import ipaddress
import itertools
import json
import math
import re
import reprlib
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, get_args, get_origin, get_type_hints

from controller.files import NotRegularFileError, open_regular

__all__ = [
    "LAYER_KEYS",
    "MAX_BANK_MODELS",
    "MAX_BANK_TABLE_ENTRIES",
    "MAX_CONFIG_BYTES",
    "MAX_LIST_LEN",
    "ActuatorConfig",
    "BayesConfig",
    "CanConfig",
    "ConfigError",
    "DesignConfig",
    "EmulatorConfig",
    "ExcitationConfig",
    "ForceLoopConfig",
    "FoxgloveConfig",
    "FuzzyConfig",
    "MovingBankConfig",
    "NoiseConfig",
    "RecordingConfig",
    "RigConfig",
    "SafetyConfig",
    "SensorConfig",
    "TelemetryConfig",
    "TireConfig",
    "VehicleConfig",
    "config_from_bytes",
    "config_hash",
    "config_to_dict",
    "config_to_toml",
    "decode_text",
    "default_config",
    "excitation_problems",
    "host_problem",
    "layer_config",
    "layer_grid",
    "layer_params",
    "layer_scales",
    "layer_tire_scales",
    "load_config",
    "one_layer",
    "parse_config",
    "parse_toml",
    "read_text_file",
]

#: largest configuration (or fault schedule) file read: a rig configuration is a few kB;
#: the limit only stops a wrong file (a log, /dev/zero) from being read whole
MAX_CONFIG_BYTES = 8 << 20
#: longest list of any key without its own ``max_len``
MAX_LIST_LEN = 64
#: most linear models in the bank (Kalman filter + LQ gain each; every model of a fuzzy
#: or Bayesian bank runs its filter every tick); the moving bank's ``active_models`` <= this
MAX_BANK_MODELS = 64
#: most (model, noise entry) Kalman designs: ``rig design`` solves one Riccati equation
#: per entry (~0.1 ms each, controller/dare.py) and the artifact stores a filter per
#: entry (the default, 568 models x 20 entries, is 11 360: 1.8 s of design with the
#: LQ gains, `python -m bench design`; a 5.2 MB artifact)
MAX_BANK_TABLE_ENTRIES = 12000

_BANK_WHY = (f"one linear tire model each; at most {MAX_BANK_MODELS} models in the bank, "
             "every model's Kalman filter runs each tick")
_NOISE_WHY = ("the Kalman gain table: one Riccati solve per model, speed and roughness, "
              f"at most {MAX_BANK_TABLE_ENTRIES} in all")

# values in error messages: lists, nesting and strings abbreviated (a 200,000-entry list
# or a 3,000-deep nesting still makes a one-line message)
_short = reprlib.Repr()
_short.maxlist = _short.maxtuple = 8
_short.maxlevel = 3
_short.maxstring = _short.maxother = 200
_short.maxdict = 4


#: most decimal digits of an integer in a configuration (Python's own limit on converting
#: between text and int, ``sys.get_int_max_str_digits``: longer ones cost quadratic time)
MAX_INT_DIGITS = 4300
_LONG_INT = re.compile(rf"(?<![.\w])\d[\d_]{{{MAX_INT_DIGITS - 1},}}(?![.\w])")
_TABLE_HEADER = re.compile(r"^\s*\[\[?\s*([^\]]*?)\s*\]")
_KEY_BEFORE_VALUE = re.compile(r"^\s*([^=\s][^=]*?)\s*=")


class _Described(str):
    """A value that an error message describes instead of quoting."""

    __slots__ = ()

    def __repr__(self) -> str:
        return str(self)


def _shown(value: object) -> str:
    """``value`` abbreviated for an error message (an integer too long to print is
    described by its length)."""
    if isinstance(value, int) and value.bit_length() > 3 * MAX_INT_DIGITS:
        return f"<an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits>"
    try:
        return _short.repr(value)
    except ValueError:              # an integer too long for str() inside a list
        return f"<a {type(value).__name__} holding an integer too long to print>"


def _long_int_key(text: str) -> tuple[str, int]:
    """The key (``section.name``) and 1-based line of the first integer literal of
    ``text`` longer than :data:`MAX_INT_DIGITS` digits (("<file>", 0) if none)."""
    m = _LONG_INT.search(text)
    if m is None:
        return "<file>", 0
    lines = text[:m.start()].split("\n")
    name = section = ""
    for line in reversed(lines):    # the key of the value (an array may span lines)
        if h := _TABLE_HEADER.match(line):
            section = h.group(1)
            break
        if not name and (k := _KEY_BEFORE_VALUE.match(line)):
            name = k.group(1).strip()
    if not name:
        return f"<file> line {len(lines)}", len(lines)
    return (f"{section}.{name}" if section else name), len(lines)


#: largest ``design.compute_delay_ticks``: the runtime keeps this many pending spool
#: commands in its buffers (controller.runtime.kernels)
MAX_COMPUTE_DELAY_TICKS = 4
#: the road preview's stop clamp looks at most this far ahead [ticks] (its ring of
#: predictions in the runtime, controller.runtime.kernels.PVC_RING, holds one more)
MAX_CLAMP_LOOKAHEAD_TICKS = 255


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""

    def __init__(self, key: str, value: object, allowed: str) -> None:
        self.key = key
        self.value = value
        self.allowed = allowed
        shown = _shown(value)
        if isinstance(value, list) and len(value) > _short.maxlist:
            shown += f" ({len(value)} entries)"
        super().__init__(f"config key '{key}' = {shown} is invalid: allowed {allowed}")


def _rng(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
         hi_open: bool = False, choices: tuple[object, ...] | None = None,
         max_len: int = MAX_LIST_LEN, len_why: str = "", doc: str = "") -> dict[str, Any]:
    """Field metadata: numeric range (closed unless *_open) or a set of choices; a list
    holds at most ``max_len`` entries (``len_why``: the reason, for the error)."""
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open,
            "choices": choices, "max_len": max_len, "len_why": len_why, "doc": doc}


def _f(default: Any, **kw: Any) -> Any:
    meta = _rng(**kw)
    if isinstance(default, list | dict):
        frozen_default = json.dumps(default)

        def factory() -> Any:
            return json.loads(frozen_default)

        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


# ---------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class VehicleConfig:
    """Quarter car (thesis Ch. I).  K and C are the equivalent wheel-rate values."""

    sprung_mass_kg: float = _f(500.0, lo=1.0, hi=5000.0, doc="M, body mass")
    unsprung_mass_kg: float = _f(60.0, lo=1.0, hi=1000.0, doc="m, wheel and axle mass")
    suspension_stiffness_n_per_m: float = _f(27.4e3, lo=100.0, hi=1e7, doc="K (27.4 N/mm)")
    suspension_damping_ns_per_m: float = _f(1.65e3, lo=0.0, hi=1e6, doc="C (1.65 Ns/mm)")
    gravity_mps2: float = _f(9.80665, lo=0.0, hi=20.0)
    rattlespace_travel_m: float = _f(0.08, lo=0.005, hi=1.0, lo_open=True,
                                     doc="free travel either side of static before bump stops")
    bump_stop_stiffness_n_per_m: float = _f(1.0e6, lo=0.0, hi=1e9)


@dataclass(frozen=True)
class TireConfig:
    """Tire law f_k = k' x2^e (x2 in mm, N); Ct = c2 x2^2 + c3 x2^3 (Ns/mm, x2 in mm)."""

    stiffness_coefficient: float = _f(85.0, lo=0.0, hi=1e5, lo_open=True, doc="k' in N/mm^e")
    stiffness_exponent: float = _f(1.3, lo=1.0, hi=3.0)
    damping_c2: float = _f(1.5e-3, lo=-1.0, hi=1.0)
    damping_c3: float = _f(-2.66e-5, lo=-1.0, hi=1.0)
    damping_saturation_mm: float = _f(38.0, lo=0.0, hi=1000.0, lo_open=True,
                                      doc="Ct held constant above this deflection")


@dataclass(frozen=True)
class DesignConfig:
    """Offline design of the bank (thesis Ch. II, V)."""

    sample_rate_hz: float = _f(1000.0, lo=50.0, hi=20000.0)
    linearisation_deflections_m: list[float] = _f([0.04, 0.025, 0.01], lo=0.0, hi=0.2,
                                                  lo_open=True, max_len=MAX_BANK_MODELS,
                                                  len_why=_BANK_WHY,
                                                  doc="deflection x2 of each linear tire "
                                                      "model; with tire_damping_scales at "
                                                      "most MAX_BANK_MODELS models")
    include_airborne_model: bool = _f(True)
    tire_damping_scales: list[float] = _f([1.0], lo=0.0, hi=10.0, max_len=16,
                                          len_why="one model per deflection and scale",
                                          doc="grid factor on Ct (1 = nominal only)")
    sprung_mass_scales: list[float] = _f([0.6, 0.7, 0.85, 1.0, 1.15, 1.3, 1.5], lo=0.25,
                                         hi=4.0, max_len=16,
                                         len_why="one layer of tire models per scale",
                                         doc="sprung-mass layers of the bank (x "
                                             "vehicle.sprung_mass_kg): the tire models are "
                                             "designed once per layer, and the bank runs the "
                                             "layer nearest the sprung-mass estimate "
                                             "(docs/design.md §11; [1.0] = the configured "
                                             "mass only)")
    spring_rate_scales: list[float] = _f([0.7, 1.0, 1.4], lo=0.25, hi=4.0, max_len=8,
                                         len_why="one layer of tire models per scale",
                                         doc="spring-rate layers of the bank (x "
                                             "vehicle.suspension_stiffness_n_per_m), crossed "
                                             "with the sprung-mass and damping layers; the "
                                             "bank runs the layer nearest the estimate of "
                                             "[M, K, C] (docs/design.md §11; [1.0] = the "
                                             "configured spring only)")
    damping_scales: list[float] = _f([0.6, 1.0, 1.5], lo=0.25, hi=4.0, max_len=8,
                                     len_why="one layer of tire models per scale",
                                     doc="damping layers of the bank (x vehicle."
                                         "suspension_damping_ns_per_m), crossed with the "
                                         "sprung-mass and spring-rate layers "
                                         "(docs/design.md §11; [1.0] = the configured "
                                         "damper only)")
    tire_stiffness_scales: list[float] = _f([0.7, 1.0, 1.3], lo=0.25, hi=4.0, max_len=8,
                                            len_why="one layer of tire models per scale",
                                            doc="tire layers of the bank (x tire."
                                                "stiffness_coefficient), crossed with the "
                                                "sprung-mass, spring-rate and damping layers; "
                                                "the bank runs the layer nearest the passive "
                                                "wheel hop's tire estimate (docs/design.md "
                                                "§11; [1.0] = the configured tire only)")
    weight_set: int = _f(0, lo=0, hi=15, doc="index into weight_sets (1-based); 0 = the "
                                             "travel schedule between the two sets of "
                                             "schedule_weight_sets (docs/design.md §12)")
    weight_sets: list[list[float]] = _f([[1.0, 1e2, 1e-8, 1.0], [1e1, 1e-1, 1e-8, 1.0]],
                                        lo=0.0, hi=1e12, max_len=15,
                                        len_why="design.weight_set indexes 1..15",
                                        doc="[rho1, rho2, rho3, rho4] per set, Eq. 2.5")
    human_filter_num: list[float] = _f([12.0, 0.0], lo=-1e9, hi=1e9, max_len=2,
                                       doc="F(s) numerator")
    human_filter_den: list[float] = _f([1.0, 30.02, 901.3], lo=-1e9, hi=1e9, max_len=3,
                                       doc="F(s) denominator")
    airborne_filter_com_hz: float = _f(0.2, lo=0.0, hi=100.0, lo_open=True,
                                       doc="airborne Kalman filter only: pseudo natural "
                                           "frequency given to the undetectable centre-of-"
                                           "mass modes (docs/design.md)")
    airborne_filter_com_damping: float = _f(0.7, lo=0.0, hi=10.0, lo_open=True,
                                            doc="airborne filter only: pseudo damping ratio")
    airborne_filter_wheel_force_intensity: float = _f(
        300.0, lo=0.0, hi=1e12,
        doc="airborne Kalman filter only: intensity [N^2 s] of a white force on the wheel "
            "standing for the tire force the model leaves out, so the filter tracks the "
            "relative motion instead of predicting it open loop (0 = none, thesis)")
    filter_velocity_leak_hz: float = _f(0.1, lo=0.0, hi=10.0,
                                        doc="on-ground Kalman filters only: pseudo leak on "
                                            "the mass-weighted velocity (0 = pure white-road "
                                            "model; see docs/design.md, bias sensitivity)")
    filter_rattlespace_bias_drift: float = _f(1e-4, lo=0.0, hi=1.0,
                                              doc="Kalman filters: random-walk intensity "
                                                  "[m/sqrt(s)] of a rattlespace measurement-"
                                                  "bias state (LVDT zero, ride height); 0 = no "
                                                  "bias state (docs/design.md §4, DC gain)")
    filter_accel_bias_drift: float = _f(0.0, lo=0.0, hi=100.0,
                                        doc="Kalman filters: random-walk intensity "
                                            "[m/s^2/sqrt(s)] of an accelerometer-bias state; "
                                            "0 = no bias state (the default: the running "
                                            "mean below removes the bias model-free)")
    accel_mean_window_s: float = _f(30.0, lo=0.0, hi=1e5,
                                    doc="the filters see the accelerometer reading minus "
                                        "its running mean over about this time (a body "
                                        "on the rig has zero mean acceleration, so the mean "
                                        "is the sensor's bias); 0 = raw reading")
    bump_stop_filter_input: bool = _f(True, doc="feed the bump-stop force computed from "
                                                "the LVDT reading to the Kalman filters as a "
                                                "known input (docs/design.md §4)")
    bump_stop_centre_lvdt_m: float = _f(0.0, lo=-0.5, hi=0.5,
                                        doc="LVDT reading half-way between the compression "
                                            "and rebound stops (calibrated on the rig: the "
                                            "mean of the two readings at stop contact); the "
                                            "stops engage +/- vehicle.rattlespace_travel_m "
                                            "about it")
    stop_guard_m: float = _f(0.02, lo=0.0, hi=1.0,
                             doc="end-stop guard: within this distance of a bump stop (LVDT "
                                 "frame, as bump_stop_centre_lvdt_m) the bank's force toward "
                                 "that stop fades linearly to 0 at the stop; a force away "
                                 "from it is untouched (0 = off; docs/design.md §9.6)")
    stop_guard_lead_s: float = _f(0.03, lo=0.0, hi=0.5,
                                  doc="end-stop guard: the LVDT reading is led by this "
                                      "many seconds of the approach rate above "
                                      "stop_guard_lead_deadband_mps, so a force toward a "
                                      "stop the suspension closes on fast fades before the "
                                      "force loop's ~20 ms unloading time runs out; under "
                                      "the travel schedule scaled by the comfort share "
                                      "(0 = the distance law; docs/design.md §9.6)")
    stop_guard_lead_deadband_mps: float = _f(0.5, lo=0.0, hi=10.0,
                                             doc="end-stop guard: approach rate [m/s] below "
                                                 "which the lead does nothing (the wheel "
                                                 "hop's rate)")
    schedule_weight_sets: list[int] = _f([2, 1], lo=1, hi=15, max_len=2,
                                         len_why="[comfort set, travel set]",
                                         doc="travel schedule (weight_set = 0): the weight "
                                             "set of the law where travel allows (comfort) "
                                             "and of the law it blends to before the stops "
                                             "(travel), 1-based into weight_sets "
                                             "(docs/design.md §12)")
    schedule_start_m: float = _f(0.025, lo=0.0, hi=1.0,
                                 doc="travel schedule: rattlespace usage (envelope of the "
                                     "LVDT reading's distance from the stops' centre) where "
                                     "the blend toward the travel law begins")
    schedule_full_m: float = _f(0.055, lo=0.0, hi=1.0, lo_open=True,
                                doc="travel schedule: usage at which the travel law has the "
                                    "whole force (above schedule_start_m)")
    schedule_release_s: float = _f(0.7, lo=0.0, hi=100.0,
                                   doc="travel schedule: time constant with which the usage "
                                       "envelope falls after a peak (it rises at once)")
    preview_horizon_s: float = _f(0.2, lo=0.0, hi=1.0,
                                  doc="road preview (travel schedule only): how far ahead "
                                      "the road velocity the rig will play is used to "
                                      "predict the LVDT reading; a predicted peak beyond "
                                      "preview_trigger_m turns the schedule to the travel "
                                      "law before the excursion [s] (0 = off; the "
                                      "simulator and a rig that sends RoadPreview frames "
                                      "supply it: docs/design.md §12)")
    preview_trigger_m: float = _f(0.055, lo=0.0, hi=1.0, lo_open=True,
                                  doc="road preview: predicted distance of the LVDT reading "
                                      "from the stops' centre that turns the schedule to "
                                      "the travel law")
    preview_trigger_inner_m: float = _f(0.075, lo=0.0, hi=1.0,
                                        doc="road preview: the trigger (as preview_trigger_m) "
                                            "while the bank runs a layer inside its grid in "
                                            "spring rate and damping, with the force of "
                                            "preview_force_decay_s; a layer on that edge, "
                                            "whose plant may lie beyond the models, and the "
                                            "travel governor keep preview_trigger_m and the "
                                            "no-force prediction (0 = preview_trigger_m on "
                                            "every layer; docs/design.md §12)")
    preview_check_s: float = _f(0.01, lo=0.0, hi=1.0, lo_open=True,
                                doc="road preview: spacing of the look-ahead times at which "
                                    "the prediction is checked, up to preview_horizon_s")
    preview_force_decay_s: float = _f(0.2, lo=0.0, hi=10.0,
                                      doc="road preview: the prediction adds the force the "
                                          "load cell measures now, fading with this time "
                                          "constant [s], on the layers that take "
                                          "preview_trigger_inner_m (every layer when that "
                                          "is 0; 0 = the no-force prediction; "
                                          "docs/design.md §12)")
    preview_stop_clamp_m: float = _f(0.08, lo=0.0, hi=1.0,
                                     doc="stop clamp: the force is bounded so that the "
                                         "prediction of the LVDT reading (the running "
                                         "layer's model, the force held) stays within this "
                                         "distance from the stops' centre over "
                                         "preview_clamp_horizon_s, for every law and "
                                         "weight set: a push toward a stop is limited, "
                                         "and where the no-force prediction reaches the "
                                         "stop the force brakes away from it "
                                         "(preview_clamp_brake) [m] (0 = off; "
                                         "docs/design.md §12)")
    preview_clamp_horizon_s: float = _f(0.05, lo=0.0, hi=1.0, lo_open=True,
                                        doc="road preview: how far ahead the stop clamp "
                                            "(preview_stop_clamp_m) looks, at the "
                                            "preview_check_s look-ahead times up to it "
                                            "(at least the first), up to "
                                            "preview_horizon_s and 255 ticks [s]")
    preview_clamp_trust_m: float = _f(0.03, lo=0.0, hi=1.0, lo_open=True,
                                      doc="road preview: the stop clamp acts only while its "
                                          "own predictions come true: the RMS error of the "
                                          "no-force prediction at its last look-ahead time "
                                          "against the reading that came (exponential "
                                          "window of 0.2 s) below this [m]; a bank on a "
                                          "layer far from its plant predicts metres")
    preview_clamp_brake: bool = _f(True,
                                   doc="stop clamp: where its no-force prediction reaches a "
                                       "stop, the force brakes away from it by as much as "
                                       "brings the prediction back within "
                                       "preview_stop_clamp_m, up to the barrier's braking "
                                       "force (stop_barrier_force_fraction; the barrier "
                                       "itself may be off); false: the force toward that "
                                       "stop is clipped to 0 and no more (docs/design.md §12)")
    stop_clamp_road_at_rest: bool = _f(True,
                                       doc="the stop clamp (preview_stop_clamp_m) acts "
                                           "without a live road preview too, predicting "
                                           "with the road at rest: the body's and the "
                                           "wheel's momentum alone (needs "
                                           "preview_horizon_s > 0 for its predictor)")
    preview_schedule_start_m: float = _f(0.05, lo=0.0, hi=1.0,
                                         doc="road preview: schedule_start_m while a road "
                                             "preview is live (schedule_start_m applies "
                                             "without one): high, so the preview makes "
                                             "the calls and the reading is a safety net "
                                             "for an excursion the prediction under-reads")
    preview_schedule_full_m: float = _f(0.08, lo=0.0, hi=1.0, lo_open=True,
                                        doc="road preview: schedule_full_m while a road "
                                            "preview is live (above preview_schedule_start_m)")
    govern_comfort_set: bool = _f(True, doc="travel governor: the schedule's comfort set "
                                            "run alone (weight_set = "
                                            "schedule_weight_sets[0]) calls the travel law "
                                            "ahead of a road-preview-predicted excursion "
                                            "(preview_trigger_m) and blends to it near the "
                                            "stops (governor_start_m / governor_full_m); "
                                            "false: that set alone, as the thesis "
                                            "(docs/design.md §12)")
    governor_start_m: float = _f(0.06, lo=0.0, hi=1.0,
                                 doc="travel governor: rattlespace usage (as "
                                     "schedule_start_m) where the governed comfort set "
                                     "begins to blend toward the travel law")
    governor_full_m: float = _f(0.08, lo=0.0, hi=1.0, lo_open=True,
                                doc="travel governor: usage at which the travel law has the "
                                    "whole force (above governor_start_m)")
    stop_barrier: bool = _f(False, doc="end-stop barrier: a safety filter on the force "
                                       "reference that keeps the rattlespace short of the "
                                       "bump stops given the body's momentum and the "
                                       "actuator's braking force and lag (docs/design.md "
                                       "§9.7); the law is untouched while it is safe")
    stop_barrier_margin_m: float = _f(0.01, lo=0.0, hi=1.0,
                                      doc="end-stop barrier: distance short of each stop "
                                          "(LVDT frame) the barrier keeps the rattlespace")
    stop_barrier_force_fraction: float = _f(0.5, lo=0.0, hi=1.0, lo_open=True,
                                            doc="end-stop barrier: braking force it counts "
                                                "on, as a fraction of the actuator's stall "
                                                "force A Ps (and at most "
                                                "force_loop.force_limit_n)")
    stop_barrier_lag_s: float = _f(0.02, lo=0.0, hi=1.0, lo_open=True,
                                   doc="end-stop barrier: reaction time of the force loop "
                                       "(compute delay + force rise) the braking distance "
                                       "allows for [s]")
    stop_barrier_rate_lowpass_hz: float = _f(1.0, lo=0.0, hi=1000.0, lo_open=True,
                                             doc="end-stop barrier: corner of the first-"
                                                 "order low-pass on the LVDT rate it brakes "
                                                 "(at the body mode: the body's momentum, "
                                                 "not the wheel's) [Hz]")
    stop_barrier_passive_uncertainty: float = _f(0.5, lo=0.0, hi=1.0, hi_open=True,
                                                 doc="end-stop barrier: the plant's spring "
                                                     "and damper are known within this "
                                                     "fraction (K, C in [1 - d, 1 + d] x "
                                                     "nominal): it counts on the least "
                                                     "passive help and the most passive push")
    stop_barrier_rate_per_s: float = _f(5.0, lo=0.0, hi=1e4, lo_open=True,
                                        doc="end-stop barrier: gamma of the barrier "
                                            "condition dh/dt >= -gamma h [1/s]")
    mass_estimator_window_s: float = _f(2.0, lo=0.0, hi=600.0,
                                        doc="sprung-mass estimator: time constant of the "
                                            "exponential forgetting of its least squares on "
                                            "the body equation M a = F + K z + C z' [s] (0 = "
                                            "off: the estimate stays the configured mass; "
                                            "docs/design.md §10)")
    mass_estimator_band_hz: list[float] = _f([0.5, 10.0], lo=0.0, hi=1e4, lo_open=True,
                                             max_len=2, len_why="[low, high]",
                                             doc="sprung-mass estimator: [low, high] corners "
                                                 "of the band-pass (2nd-order high-pass and "
                                                 "2nd-order low-pass) applied alike to both "
                                                 "sides of the body equation [Hz]")
    mass_estimator_min_accel_mps2: float = _f(0.05, lo=0.0, hi=100.0,
                                              doc="sprung-mass estimator: it updates only while "
                                                  "the windowed RMS of the band-passed "
                                                  "acceleration exceeds this; below it the rig "
                                                  "is too quiet to tell the mass, and the "
                                                  "estimate holds")
    actuator_model: str = _f("hydraulic", choices=("hydraulic", "ideal"),
                             doc="plant the LQ gains are designed on: 'hydraulic' = plant + "
                                 "linearised servo-valve/actuator under the PI's proportional "
                                 "path + compute delay; 'ideal' = force source (thesis Ch. II; "
                                 "fragile with the real actuator, docs/design.md section 7)")
    compute_delay_ticks: int = _f(1, lo=0, hi=MAX_COMPUTE_DELAY_TICKS,
                                  doc="ticks from the sensor sample to the valve that the "
                                      "'hydraulic' design assumes (CAN loop: 0 or 1)")

    def governs(self, weight_set: int) -> bool:
        """``weight_set`` runs under the travel governor (docs/design.md §12): it is the
        schedule's comfort set, not also its travel set, the travel set is one of
        ``weight_sets`` (the governor's fallback law), and ``govern_comfort_set``."""
        comfort, travel = self.schedule_weight_sets
        return (self.govern_comfort_set and weight_set == comfort and weight_set != travel
                and travel <= len(self.weight_sets))

    def single_gain_weight_set(self, weight_set: int | None = None) -> int:
        """The weight set (1-based) whose one LQ gain stands for ``weight_set`` (default:
        ``self.weight_set``) where one gain is needed (a linear analysis): the set
        itself, or for 0, the travel schedule, its comfort set."""
        ws = self.weight_set if weight_set is None else weight_set
        return ws or self.schedule_weight_sets[0]


@dataclass(frozen=True)
class NoiseConfig:
    """Noise levels seen by the Kalman filters (and, by default, by the emulated sensors).

    The road process noise is white road velocity.  For an ISO 8608 road its two-sided
    intensity is 2 pi^2 n0^2 Gd(n0) V  [m^2/s]; the bank tabulates filter gains over
    ``speeds_mps`` x ``road_roughness_gd`` (Gd(n0) in m^3).
    """

    rattlespace_std_m: float = _f(5e-5, lo=0.0, hi=0.1, lo_open=True)
    accel_std_mps2: float = _f(0.05, lo=0.0, hi=100.0, lo_open=True)
    force_std_n: float = _f(5.0, lo=0.0, hi=1e4)
    speeds_mps: list[float] = _f([5.0, 11.176, 20.0, 30.0], lo=0.1, hi=100.0, max_len=64,
                                 len_why=_NOISE_WHY)
    road_roughness_gd: list[float] = _f([16e-6, 64e-6, 256e-6, 1024e-6, 4096e-6],
                                        lo=1e-9, hi=1.0, max_len=64, len_why=_NOISE_WHY,
                                        doc="Gd(n0), m^3")
    nominal_speed_mps: float = _f(11.176, lo=0.1, hi=100.0, doc="25 mph")
    nominal_roughness_gd: float = _f(1024e-6, lo=1e-9, hi=1.0)


@dataclass(frozen=True)
class FuzzyConfig:
    """Appendix A: four trapezoid input terms on q, rule outputs on (0, 1)."""

    universe: list[float] = _f([0.0, 10.0], lo=0.0, hi=1e6)
    sml: list[float] = _f([0.0, 0.0, 1.0, 3.0], lo=0.0, hi=1e6, doc="trapezoid a<=b<=c<=d")
    med: list[float] = _f([1.0, 3.0, 4.0, 6.0], lo=0.0, hi=1e6)
    lrg: list[float] = _f([4.0, 6.0, 7.0, 9.0], lo=0.0, hi=1e6)
    v_lrg: list[float] = _f([7.0, 9.0, 10.0, 10.0], lo=0.0, hi=1e6)
    out_high: float = _f(1.0, lo=0.0, hi=1.0, doc="HIGH singleton")
    out_med: list[float] = _f([0.25, 0.5, 0.75], lo=0.0, hi=1.0, doc="triangle a, peak, c")
    out_low: list[float] = _f([0.0, 0.25, 0.5], lo=0.0, hi=1.0, doc="triangle a, peak, c")
    out_zero: float = _f(0.0, lo=0.0, hi=1.0, doc="ZERO singleton")
    singleton_area: float = _f(0.25, lo=0.0, hi=1.0, lo_open=True,
                               doc="area a fully fired singleton carries in centre of area")
    no_fire_fallback: str = _f("best_model", choices=("passive", "best_model"),
                               doc="no rule fired: the best model alone (min statistic) "
                                   "or 0 N ('passive', thesis App. A)")
    statistic: str = _f("relative", choices=("relative", "raw"),
                        doc="fuzzy input: 'relative' = each model's windowed q relative to "
                            "the bank's smallest, scaled to a matched filter's mean (the "
                            "best model always fires); 'raw' = the per-tick q (thesis App. A)")
    window_s: float = _f(0.02, lo=0.0, hi=10.0,
                         doc="time constant of the exponential window of the 'relative' "
                             "statistic (0 = per tick)")


@dataclass(frozen=True)
class BayesConfig:
    """Bayesian MMAE blending (``--controller bayes``)."""

    probability_floor: float = _f(1e-4, lo=0.0, hi=0.5, lo_open=True,
                                  doc="lowest model probability, so a model can come back "
                                      "(must be below 1/J for a bank of J models)")


@dataclass(frozen=True)
class MovingBankConfig:
    """Ch. VI: on-ground / airborne sets, switched on tire-load CUSUMs and residual thresholds.

    Lift-off and touch-down are decided by two CUSUM tests on a model-free tire-load
    estimate, plus the learnt residual threshold (controller/runtime/moving_bank.py)."""

    active_models: int = _f(3, lo=1, hi=MAX_BANK_MODELS, doc="k, size of the moving subset")
    threshold_quantile: float = _f(0.999, lo=0.5, hi=1.0, hi_open=True,
                                   doc="quantile of learnt q history used as threshold")
    history_window_s: float = _f(2.0, lo=0.01, hi=600.0)
    smoothing_time_s: float = _f(0.005, lo=0.0, hi=1.0)
    hysteresis_ratio: float = _f(0.5, lo=0.0, hi=1.0, lo_open=True, hi_open=True,
                                 doc="Schmitt gap of the tire-contact test: touch-down "
                                     "reference load = liftoff_load_fraction / ratio")
    dwell_time_s: float = _f(0.01, lo=0.0, hi=10.0, doc="minimum time between switches")
    liftoff_load_fraction: float = _f(0.2, lo=0.0, hi=1.0, lo_open=True, hi_open=True,
                                      doc="lift-off CUSUM reference: estimated tire load "
                                          "as a fraction of the static load (M + m) g")
    liftoff_detection_time_s: float = _f(0.008, lo=0.0, hi=1.0, lo_open=True,
                                         doc="time at zero estimated tire load until the "
                                             "lift-off CUSUM fires (sets its threshold)")
    load_estimate_window_s: float = _f(0.005, lo=0.0, hi=0.1, lo_open=True,
                                       doc="difference step of the model-free tire-load "
                                           "estimate (LVDT second difference): longer = "
                                           "less noise, more lag")
    probe_period_s: float = _f(0.05, lo=0.0, hi=10.0, lo_open=True,
                               doc="how often the probe slot tries the next neighbour model")


@dataclass(frozen=True)
class ForceLoopConfig:
    """PI force inner loop for the servo valve (output: normalised spool command)."""

    kp_per_n: float = _f(1.0e-4, lo=0.0, hi=1.0,
                         doc="force-loop crossover ~31 Hz; phase margin there ~89/78/67 deg at "
                             "0/1/2 ticks of loop delay with the flow feedforward, 72/61/50 "
                             "without (controller/margins.py, docs/design.md 7)")
    ki_per_ns: float = _f(0.002, lo=0.0, hi=1e3,
                          doc="integral corner ki/kp = 20 rad/s, a decade below crossover")
    output_limit: float = _f(1.0, lo=0.0, hi=1.0, lo_open=True)
    force_limit_n: float = _f(8000.0, lo=0.0, hi=1e6, lo_open=True,
                              doc="force reference saturation")
    flow_feedforward_gain: float = _f(1.0, lo=0.0, hi=1.25,
                                      doc="valve flow feedforward: fraction of the piston "
                                          "flow A x_p' (x_p' from the differentiated LVDT) "
                                          "the spool command supplies (Alleyne & Hedrick's "
                                          "compensation; 1 = full, 0 = off, above 1 "
                                          "the oil column acts as a negative spring; "
                                          "controller/actuator.py, docs/design.md 7)")
    rattle_rate_lowpass_hz: float = _f(150.0, lo=1.0, hi=1e5,
                                       doc="corner of the first-order low-pass on the "
                                           "differentiated LVDT reading that feeds the "
                                           "flow feedforward")
    min_pressure_drop_fraction: float = _f(0.1, lo=0.0, hi=1.0, lo_open=True,
                                           doc="floor of the valve pressure drop "
                                               "(Ps - sgn(x_v) P) / Ps in the feedforward's "
                                               "sqrt law (bounds the spool near stall)")


@dataclass(frozen=True)
class ActuatorConfig:
    """Servo-hydraulic actuator (Alleyne & Hedrick form), sized for the 500 kg body."""

    piston_area_m2: float = _f(1.0e-3, lo=1e-6, hi=1.0)
    supply_pressure_pa: float = _f(10.3425e6, lo=1e5, hi=1e8)
    alpha_n_per_m5: float = _f(4.515e11, lo=1e6, hi=1e16,
                               doc="4 beta_e / Vt; A&H's 4.515e13 softened 100x by "
                                   "chamber accumulators so a 1 kHz PI force loop can track "
                                   "(docs/hil.md)")
    leakage_beta_per_s: float = _f(1.0, lo=0.0, hi=1e4)
    valve_gamma: float = _f(4.6e9, lo=0.0, hi=1e13, lo_open=True,
                            doc="flow gain; 1.545e9 x area ratio to A&H piston")
    spool_time_constant_s: float = _f(0.001, lo=1e-5, hi=1.0,
                                      doc="~160 Hz high-response servo valve; at 3 ms the "
                                          "rho3 = 1e-8 LQG oscillates against the force "
                                          "loop (docs/hil.md)")
    bypass_time_constant_s: float = _f(0.002, lo=1e-5, hi=1.0,
                                       doc="load-pressure decay when the bypass is open")
    spool_stroke_m: float = _f(1.0e-4, lo=1e-9, hi=0.1,
                               doc="spool opening at normalised command 1 (x_s = stroke x_v);"
                                   " 3.3 m/s no-load velocity with the defaults")


@dataclass(frozen=True)
class SensorConfig:
    """The rig's sensors as the emulator models them (and the ranges the service checks)."""

    lvdt_range_m: float = _f(0.1, lo=0.001, hi=1.0, doc="+/- range about static")
    lvdt_resolution_m: float = _f(5e-6, lo=0.0, hi=1e-2)
    load_cell_range_n: float = _f(15000.0, lo=1.0, hi=1e6)
    load_cell_offset_n: float = _f(0.0, lo=-1e4, hi=1e4)
    accel_range_mps2: float = _f(150.0, lo=1.0, hi=1e4)
    accel_bias_mps2: float = _f(0.0, lo=-100.0, hi=100.0)
    accel_bandwidth_hz: float = _f(300.0, lo=1.0, hi=1e5)
    seed: int = _f(12345, lo=0, hi=2**63 - 1)


@dataclass(frozen=True)
class EmulatorConfig:
    """The emulated rig's true plant where it differs from the configuration the
    controller is designed from (``rig demo``, ``rig hil``, ``rig sim``, ``rig montecarlo``;
    the Monte Carlo draws on top of it).  All scales 1 and no offset: the configured rig."""

    sprung_mass_scale: float = _f(1.0, lo=0.25, hi=4.0, doc="true M / vehicle.sprung_mass_kg")
    unsprung_mass_scale: float = _f(1.0, lo=0.25, hi=4.0,
                                    doc="true m / vehicle.unsprung_mass_kg")
    spring_rate_scale: float = _f(1.0, lo=0.25, hi=4.0,
                                  doc="true K / vehicle.suspension_stiffness_n_per_m")
    damping_scale: float = _f(1.0, lo=0.25, hi=4.0,
                              doc="true C / vehicle.suspension_damping_ns_per_m")
    tire_stiffness_scale: float = _f(1.0, lo=0.25, hi=4.0,
                                     doc="scale of the tire stiffness law (coefficient)")
    ride_height_offset_m: float = _f(0.0, lo=-0.05, hi=0.05,
                                     doc="static rattlespace about the bump stops' centre "
                                         "[m] once the ride height is set by spring preload "
                                         "(used when the true plant differs)")
    lvdt_zero: str = _f("actual", choices=("actual", "nominal"),
                        doc="where the LVDT reads 0: 'actual' = the true plant's static "
                            "position (zeroed at rest, as on a rig), 'nominal' = M g / K of "
                            "the configured rig (a mis-zeroed sensor when they differ)")

    road_preview_s: float = _f(0.25, lo=0.0, hi=10.0,
                               doc="how far ahead of each SensorData frame the emulated "
                                   "rig sends the road velocity it will play (RoadPreview "
                                   "frames, docs/design.md §12) [s]; 0 = no RoadPreview "
                                   "frames (a rig that does not know its road)")
    ballast_step_time_s: float = _f(0.0, lo=0.0, hi=1e7,
                                    doc="run time at which ballast is put on (or taken "
                                        "off) the sprung mass [s]; 0 = no ballast change "
                                        "(docs/hil.md)")
    ballast_step_scale: float = _f(1.0, lo=0.25, hi=4.0,
                                   doc="sprung mass after the ballast change / before it "
                                       "(1.3: +30 % ballast; 1 = no change)")

    @property
    def has_ballast_step(self) -> bool:
        """True when the emulated rig's sprung mass changes during a run."""
        return self.ballast_step_time_s > 0.0 and self.ballast_step_scale != 1.0

    @property
    def is_nominal(self) -> bool:
        """True when the emulated plant is the configured one (before any ballast change:
        see :attr:`has_ballast_step`)."""
        return (self.sprung_mass_scale == self.unsprung_mass_scale == self.spring_rate_scale
                == self.damping_scale == self.tire_stiffness_scale == 1.0
                and self.ride_height_offset_m == 0.0)


@dataclass(frozen=True)
class ExcitationConfig:
    """Identification run (``rig run --excite``, ``rig demo --excite``; docs/identify.md):
    with the road (shaker) at rest, the force reference is a logarithmic chirp plus a
    PRBS (``controller/excitation.py``), played once from the arm; the rig rests passive
    for ``rest_s`` first (sensor offsets and noise are measured there)."""

    duration_s: float = _f(20.0, lo=2.0, hi=3600.0, doc="length of the excitation")
    rest_s: float = _f(2.0, lo=0.5, hi=600.0,
                       doc="passive rest before arming (offsets, noise levels)")
    chirp_start_hz: float = _f(0.5, lo=0.01, hi=200.0, doc="log chirp start frequency")
    chirp_stop_hz: float = _f(25.0, lo=0.1, hi=500.0, doc="log chirp stop frequency")
    chirp_amplitude_n: float = _f(800.0, lo=0.0, hi=1e5,
                                  doc="chirp force amplitude above chirp_corner_hz")
    chirp_corner_hz: float = _f(3.0, lo=0.0, hi=500.0,
                                doc="below this the chirp amplitude falls in proportion "
                                    "to frequency (keeps the body mode's travel small)")
    prbs_amplitude_n: float = _f(150.0, lo=0.0, hi=1e5,
                                 doc="PRBS force amplitude (+/-), added to the chirp")
    prbs_clock_hz: float = _f(50.0, lo=1.0, hi=1000.0,
                              doc="PRBS bit rate (flat spectrum to ~0.45 x this)")
    taper_s: float = _f(0.5, lo=0.0, hi=60.0, doc="cosine fade in / out")
    travel_limit_m: float = _f(0.05, lo=0.001, hi=1.0,
                               doc="LVDT reading beyond +/- this stops the excitation "
                                   "(valve safe, run marked aborted)")
    seed: int = _f(1, lo=0, hi=2**63 - 1, doc="PRBS seed")


@dataclass(frozen=True)
class SafetyConfig:
    arm_warmup_s: float = _f(0.05, lo=0.0, hi=60.0,
                             doc="good sensor ticks the estimator needs before arming")
    stale_ticks: int = _f(2, lo=1, hi=1000, doc="sensor frame missing for more ticks = fault")
    overrun_streak: int = _f(5, lo=1, hi=100000)
    overrun_threshold_s: float = _f(0.0005, lo=0.0, hi=1.0, lo_open=True,
                                    doc="a tick later than this counts as overrun")
    estimator_window_s: float = _f(0.1, lo=0.0, hi=10.0, lo_open=True,
                                   doc="window of the estimator monitor: the sum of the "
                                       "bank's smallest q over it is tested against its "
                                       "chi-square distribution (docs/design.md §9)")
    estimator_false_alarm: float = _f(1e-6, lo=1e-15, hi=0.5,
                                      doc="per-tick probability that a consistent bank (q "
                                          "of the matched model inflated by at most "
                                          "estimator_nis_inflation) trips the monitor")
    estimator_nis_inflation: float = _f(1000.0, lo=1.0, hi=1e9,
                                        doc="innovation-covariance inflation tolerated as "
                                            "ordinary model mismatch before degrading (1000: "
                                            "innovation std ~2 mm of rattlespace, ~3 m/s^2 of "
                                            "acceleration with the default noise)")
    estimator_rearm_s: float = _f(0.5, lo=0.0, hi=600.0,
                                  doc="degraded: the window statistic must stay below its "
                                      "median under the tolerated mismatch this long to "
                                      "re-arm")
    estimator_authority_ramp_s: float = _f(0.05, lo=0.0, hi=10.0,
                                           doc="force authority ramps 1 -> 0 (degrade) and "
                                               "0 -> 1 (re-arm) over this time")
    stop_contact_band_m: float = _f(0.0, lo=0.0, hi=0.1,
                                    doc="stop-contact monitor: an LVDT reading within this of "
                                        "a bump stop (design.bump_stop_centre_lvdt_m +/- "
                                        "vehicle.rattlespace_travel_m) counts as contact "
                                        "(0 = on the stop; docs/design.md §9.8)")
    stop_contact_window_s: float = _f(2.0, lo=0.0, hi=600.0, lo_open=True,
                                      doc="time constant of the exponential window of the "
                                          "stop-contact time (contact seconds, older ones "
                                          "fading with this time constant)")
    stop_contact_budget_s: float = _f(0.03, lo=0.0, hi=600.0, lo_open=True,
                                      doc="stop-contact time in the window above which the "
                                          "bank degrades to its travel-conservative law")
    stop_contact_rearm_level_s: float = _f(0.01, lo=0.0, hi=600.0,
                                           doc="stop-degraded: the window's contact time must "
                                               "stay below this for stop_contact_rearm_s to "
                                               "re-arm (< stop_contact_budget_s)")
    stop_contact_rearm_s: float = _f(1.0, lo=0.0, hi=600.0,
                                     doc="stop-degraded: time below the re-arm level needed "
                                         "to re-arm")
    stop_contact_degrade: bool = _f(True, doc="above the budget the bank degrades (false: "
                                              "the monitor only reports)")
    stop_contact_authority: float = _f(0.0, lo=0.0, hi=1.0,
                                       doc="force authority of the travel-conservative law "
                                           "(0 = zero force reference: the passive "
                                           "suspension); ramps over "
                                           "estimator_authority_ramp_s")
    ride_height_window_s: float = _f(2.0, lo=0.0, hi=600.0, lo_open=True,
                                     doc="ride-height monitor: time constant of the mean "
                                         "LVDT reading about the stops' centre "
                                         "(docs/design.md §9.9)")
    ride_height_warn_m: float = _f(0.02, lo=0.0, hi=1.0,
                                   doc="ride-height monitor: a mean position farther than "
                                       "this from the stops' centre is reported (an event, "
                                       "the status; e.g. ballast put on without re-setting "
                                       "the preload), not a fault; 0 = off")
    force_range_n: float = _f(15000.0, lo=1.0, hi=1e6)
    heartbeat_hz: float = _f(10.0, lo=0.1, hi=1000.0)
    frozen_ticks: int = _f(50, lo=2, hi=100000,
                           doc="a sensor value bit-identical for more SensorData frames = "
                           "SENSOR_FROZEN (real sensor noise is ~10 LSB std)")
    rig_status_stale_ticks: int = _f(50, lo=1, hi=100000,
                                     doc="no RigStatus for more ticks (5 periods of 100 Hz) "
                                     "= arm/reset refused")
    host_check_s: float = _f(1.0, lo=0.0, hi=60.0,
                             doc="rig run: measure the loop thread's wake-up latency this "
                                 "long before the first tick and report it (0 = no check; "
                                 "`rig check-host`, docs/deploy.md)")
    host_check_required: bool = _f(False, doc="a host check that fails the timing budgets "
                                              "(stale_ticks x period, overrun_threshold_s) "
                                              "refuses every arm")


@dataclass(frozen=True)
class CanConfig:
    interface: str = _f("virtual", choices=("socketcan", "virtual"))
    channel: str = _f("vcan0")
    bitrate: int = _f(1_000_000, lo=10_000, hi=8_000_000)
    fd: bool = _f(False)
    receive_buffer_bytes: int = _f(1 << 21, lo=0, hi=1 << 30,
                                   doc="SocketCAN SO_RCVBUF request (0 = kernel default); "
                                       "2 MiB keeps about a second of the rig's frames "
                                       "(SensorData and RoadPreview every tick)")


@dataclass(frozen=True)
class TelemetryConfig:
    enabled: bool = _f(True)
    endpoints: list[str] = _f(["tcp/127.0.0.1:7447"],
                              doc="Zenoh locators: tcp|udp|tls|quic|ws/<host>:<port>, "
                              "unixsock-stream/<absolute path>")
    mode: str = _f("peer", choices=("peer", "client", "router"))
    listen: bool = _f(True, doc="listen on endpoints (else connect to them)")
    multicast_scouting: bool = _f(False)
    key_prefix: str = _f("rig", doc="Zenoh key expression of '/'-separated chunks, "
                         "no wildcards (* $) and no # ? or spaces")
    rate_hz: float = _f(50.0, lo=0.1, hi=1000.0)
    queue_size: int = _f(256, lo=1, hi=1_000_000)
    commands_enabled: bool = _f(False)
    status_queries_per_s: float = _f(20.0, lo=0.1, hi=10_000.0,
                                     doc="status queries answered per second, all peers "
                                         "together; the rest get an error reply")
    status_burst: int = _f(20, lo=1, hi=100_000, doc="status queries answered at once")
    commands_per_s: float = _f(10.0, lo=0.1, hi=1000.0,
                               doc="operator commands taken per second, all peers "
                                   "together; the rest are refused unread")
    command_burst: int = _f(20, lo=1, hi=10_000, doc="operator commands taken at once")
    status_queries_per_peer_s: float = _f(
        10.0, lo=0.1, hi=10_000.0,
        doc="status queries answered per second to one peer (its Zenoh id when the query "
            "names one, else the key expression it used), within status_queries_per_s")
    status_peer_burst: int = _f(10, lo=1, hi=100_000,
                                doc="status queries answered to one peer at once")
    commands_per_peer_s: float = _f(5.0, lo=0.1, hi=1000.0,
                                    doc="operator commands taken per second from one peer, "
                                        "within commands_per_s")
    command_peer_burst: int = _f(10, lo=1, hi=10_000,
                                 doc="operator commands taken from one peer at once")
    zenoh_config_file: str = _f("", doc="json5 file merged first (TLS, access_control); "
                                "mode/endpoints/scouting above override it")


@dataclass(frozen=True)
class FoxgloveConfig:
    """Live Foxglove WebSocket view (rig/foxglove_server.py, docs/foxglove.md)."""

    enabled: bool = _f(False, doc="serve the live view (rig run/demo --foxglove HOST:PORT "
                       "turns it on)")
    host: str = _f("127.0.0.1", doc="IP address the WebSocket server binds (127.0.0.1: this "
                   "computer only, reach it through an SSH tunnel; 0.0.0.0: every interface)")
    port: int = _f(8765, lo=0, hi=65535, doc="TCP port (0: any free port)")
    rate_hz: float = _f(100.0, lo=1.0, hi=1000.0,
                        doc="tick records published per second (every n-th tick; at most "
                            "design.sample_rate_hz)")
    queue_size: int = _f(256, lo=1, hi=100_000,
                         doc="tick records and events waiting for the publisher thread; a "
                             "full queue drops and counts")
    client_backlog: int = _f(1024, lo=16, hi=1_000_000,
                             doc="messages buffered per client; a slow client loses the "
                                 "oldest")


@dataclass(frozen=True)
class RecordingConfig:
    enabled: bool = _f(True)
    directory: str = _f("runs")
    rotate_bytes: int = _f(512 * 1024 * 1024, lo=1024, hi=2**40)
    rotate_seconds: float = _f(3600.0, lo=1.0, hi=1e7)
    chunk_bytes: int = _f(256 * 1024, lo=1024, hi=2**30)
    queue_size: int = _f(65536, lo=16, hi=10_000_000)
    batch_ticks: int = _f(8, lo=1, hi=1000,
                          doc="ticks whose records go to the writer process in one write "
                              "(fewer system calls on the loop thread; a dropped batch loses "
                              "that many ticks)")


@dataclass(frozen=True)
class RigConfig:
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    tire: TireConfig = field(default_factory=TireConfig)
    design: DesignConfig = field(default_factory=DesignConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    fuzzy: FuzzyConfig = field(default_factory=FuzzyConfig)
    bayes: BayesConfig = field(default_factory=BayesConfig)
    moving_bank: MovingBankConfig = field(default_factory=MovingBankConfig)
    force_loop: ForceLoopConfig = field(default_factory=ForceLoopConfig)
    actuator: ActuatorConfig = field(default_factory=ActuatorConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    can: CanConfig = field(default_factory=CanConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    foxglove: FoxgloveConfig = field(default_factory=FoxgloveConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    emulator: EmulatorConfig = field(default_factory=EmulatorConfig)
    excitation: ExcitationConfig = field(default_factory=ExcitationConfig)

    @property
    def sample_time_s(self) -> float:
        return 1.0 / self.design.sample_rate_hz

    @property
    def weights(self) -> tuple[float, float, float, float]:
        """The selected [rho1, rho2, rho3, rho4] (weight_set 0, the travel schedule: its
        comfort set)."""
        w = self.design.weight_sets[self.design.single_gain_weight_set() - 1]
        return (w[0], w[1], w[2], w[3])

    def replace(self, **sections: Any) -> RigConfig:
        """Copy with some sections replaced, re-validated.  ``cfg.replace(design={...})``
        merges a dict into that section; a section object replaces it whole."""
        data = config_to_dict(self)
        for name, value in sections.items():
            if name not in data:
                raise ConfigError(name, value, f"one of {sorted(data)}")
            if isinstance(value, Mapping):
                data[name].update(value)
            else:
                data[name] = config_to_dict(value) if dataclasses.is_dataclass(value) else value
        return parse_config(data)


# ---------------------------------------------------------------------------- validation

T = TypeVar("T")


def _describe(meta: Mapping[str, Any]) -> str:
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo, hi = meta.get("lo"), meta.get("hi")
    left = "(" if meta.get("lo_open") else "["
    right = ")" if meta.get("hi_open") else "]"
    lo_s = "-inf" if lo is None else repr(lo)
    hi_s = "inf" if hi is None else repr(hi)
    if lo is None and hi is None:
        return "any value of the right type"
    return f"{left}{lo_s}, {hi_s}{right}"


def _check_scalar(key: str, value: Any, typ: type, meta: Mapping[str, Any]) -> Any:
    allowed = _describe(meta)
    if typ is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, value, "true or false")
        return value
    if typ is str:
        if not isinstance(value, str):
            raise ConfigError(key, value, f"a string, {allowed}")
        if meta.get("choices") and value not in meta["choices"]:
            raise ConfigError(key, value, allowed)
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, value, f"an integer in {allowed}")
    elif typ is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(key, value, f"a number in {allowed}")
        try:
            value = float(value)
        except OverflowError:       # an integer beyond the largest float
            raise ConfigError(key, value, f"a finite number in {allowed}") from None
        if not math.isfinite(value):
            raise ConfigError(key, value, f"a finite number in {allowed}")
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is not None and (value < lo or (meta.get("lo_open") and value == lo)):
        raise ConfigError(key, value, allowed)
    if hi is not None and (value > hi or (meta.get("hi_open") and value == hi)):
        raise ConfigError(key, value, allowed)
    return value


def _check_value(key: str, value: Any, typ: Any, meta: Mapping[str, Any]) -> Any:
    if get_origin(typ) is list:
        (inner,) = get_args(typ)
        if not isinstance(value, list) or not value:
            raise ConfigError(key, value, f"a non-empty list, elements in {_describe(meta)}")
        max_len = meta.get("max_len", MAX_LIST_LEN)
        if len(value) > max_len:
            why = meta.get("len_why")
            raise ConfigError(key, value,
                              f"at most {max_len} entries" + (f" ({why})" if why else ""))
        return [_check_value(f"{key}[{i}]", v, inner, meta) for i, v in enumerate(value)]
    return _check_scalar(key, value, typ, meta)


def _build(cls: type[T], data: Mapping[str, Any], prefix: str) -> T:
    if not isinstance(data, Mapping):
        raise ConfigError(prefix, data, "a table")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for key in data:
        if key not in names:
            raise ConfigError(f"{prefix}.{key}" if prefix else key, data[key],
                              f"a known key: {', '.join(sorted(names))}")
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if f.name not in data:
            continue
        key = f"{prefix}.{f.name}" if prefix else f.name
        typ = hints[f.name]
        if dataclasses.is_dataclass(typ):
            kwargs[f.name] = _build(typ, data[f.name], key)  # type: ignore[arg-type]
        else:
            kwargs[f.name] = _check_value(key, data[f.name], typ, f.metadata)
    return cls(**kwargs)


def _trapezoid_ok(key: str, t: list[float], universe: list[float]) -> None:
    if len(t) != 4 or not (t[0] <= t[1] <= t[2] <= t[3]):
        raise ConfigError(key, t, "4 numbers a <= b <= c <= d")
    if t[0] < universe[0] or t[3] > universe[1]:
        raise ConfigError(key, t, f"within the universe {universe}")


def _cross_checks(cfg: RigConfig) -> None:
    d = cfg.design
    if cfg.design.weight_set > len(d.weight_sets):
        raise ConfigError("design.weight_set", d.weight_set, f"[1, {len(d.weight_sets)}]")
    if d.weight_set == 0:
        for i, ws in enumerate(d.schedule_weight_sets):
            if ws > len(d.weight_sets):
                raise ConfigError(f"design.schedule_weight_sets[{i}]", ws,
                                  f"[1, {len(d.weight_sets)}]")
    if len(d.schedule_weight_sets) != 2:
        raise ConfigError("design.schedule_weight_sets", d.schedule_weight_sets,
                          "2 weight sets [comfort, travel]")
    if d.schedule_full_m <= d.schedule_start_m:
        raise ConfigError("design.schedule_full_m", d.schedule_full_m,
                          f"above design.schedule_start_m ({d.schedule_start_m:g})")
    if d.preview_schedule_full_m <= d.preview_schedule_start_m:
        raise ConfigError("design.preview_schedule_full_m", d.preview_schedule_full_m,
                          f"above design.preview_schedule_start_m "
                          f"({d.preview_schedule_start_m:g})")
    if d.governor_full_m <= d.governor_start_m:
        raise ConfigError("design.governor_full_m", d.governor_full_m,
                          f"above design.governor_start_m ({d.governor_start_m:g})")
    if d.preview_horizon_s > 0.0 and d.schedule_release_s == 0.0:
        raise ConfigError("design.preview_horizon_s", d.preview_horizon_s,
                          "0 while design.schedule_release_s is 0 (the preview holds the "
                          "travel law through the schedule's release)")
    if round(d.preview_clamp_horizon_s * d.sample_rate_hz) > MAX_CLAMP_LOOKAHEAD_TICKS:
        raise ConfigError("design.preview_clamp_horizon_s", d.preview_clamp_horizon_s,
                          f"at most {MAX_CLAMP_LOOKAHEAD_TICKS} ticks "
                          f"({MAX_CLAMP_LOOKAHEAD_TICKS / d.sample_rate_hz:g} s at "
                          "design.sample_rate_hz)")
    if (d.preview_horizon_s > 0.0 and d.preview_stop_clamp_m > 0.0
            and round(d.preview_check_s * d.sample_rate_hz) > MAX_CLAMP_LOOKAHEAD_TICKS):
        # the clamp takes at least the first checked look-ahead tick
        raise ConfigError("design.preview_check_s", d.preview_check_s,
                          f"at most {MAX_CLAMP_LOOKAHEAD_TICKS} ticks "
                          f"({MAX_CLAMP_LOOKAHEAD_TICKS / d.sample_rate_hz:g} s) while "
                          "design.preview_stop_clamp_m is on (the clamp looks at least "
                          "one check ahead)")
    if 0.0 < d.preview_horizon_s < d.preview_clamp_horizon_s:
        raise ConfigError("design.preview_clamp_horizon_s", d.preview_clamp_horizon_s,
                          f"at most design.preview_horizon_s ({d.preview_horizon_s:g})")
    if 0.0 < d.preview_horizon_s < d.preview_check_s:
        raise ConfigError("design.preview_check_s", d.preview_check_s,
                          f"at most design.preview_horizon_s ({d.preview_horizon_s:g})")
    for i, w in enumerate(d.weight_sets):
        if len(w) != 4:
            raise ConfigError(f"design.weight_sets[{i}]", w, "4 numbers [rho1, rho2, rho3, rho4]")
        if w[2] <= 0.0:
            raise ConfigError(f"design.weight_sets[{i}][2]", w[2], "rho3 > 0 (control weight)")
    pts = d.linearisation_deflections_m
    if len(set(pts)) != len(pts):
        raise ConfigError("design.linearisation_deflections_m", pts, "distinct values")
    if len(d.human_filter_den) != 3 or len(d.human_filter_num) > 2:
        raise ConfigError("design.human_filter_den", d.human_filter_den,
                          "a 2nd-order denominator [1, a1, a0] and numerator of order <= 1")
    if not all(c > 0 for c in d.human_filter_den):
        raise ConfigError("design.human_filter_den", d.human_filter_den,
                          "positive coefficients (a stable filter)")
    if d.stop_barrier and d.stop_barrier_margin_m >= cfg.vehicle.rattlespace_travel_m:
        raise ConfigError("design.stop_barrier_margin_m", d.stop_barrier_margin_m,
                          f"< vehicle.rattlespace_travel_m = "
                          f"{cfg.vehicle.rattlespace_travel_m} (the barrier must leave "
                          "travel to move in)")
    sa = cfg.safety
    if sa.stop_contact_rearm_level_s >= sa.stop_contact_budget_s:
        raise ConfigError("safety.stop_contact_rearm_level_s", sa.stop_contact_rearm_level_s,
                          f"< safety.stop_contact_budget_s = {sa.stop_contact_budget_s} "
                          "(the re-arm level lies below the degrade level)")
    if sa.stop_contact_band_m >= cfg.vehicle.rattlespace_travel_m:
        raise ConfigError("safety.stop_contact_band_m", sa.stop_contact_band_m,
                          f"< vehicle.rattlespace_travel_m = "
                          f"{cfg.vehicle.rattlespace_travel_m}")
    band = d.mass_estimator_band_hz
    nyquist = 0.5 * d.sample_rate_hz
    if len(band) != 2 or not 0.0 < band[0] < band[1] < 0.5 * nyquist:
        raise ConfigError("design.mass_estimator_band_hz", band,
                          f"[low, high] with 0 < low < high < {0.5 * nyquist:g} Hz (a quarter "
                          "of the sample rate)")
    fz = cfg.fuzzy
    if len(fz.universe) != 2 or fz.universe[0] >= fz.universe[1]:
        raise ConfigError("fuzzy.universe", fz.universe, "[lo, hi] with lo < hi")
    for name in ("sml", "med", "lrg", "v_lrg"):
        _trapezoid_ok(f"fuzzy.{name}", getattr(fz, name), fz.universe)
    for name in ("out_med", "out_low"):
        t = getattr(fz, name)
        if len(t) != 3 or not (t[0] <= t[1] <= t[2]) or t[0] == t[2]:
            raise ConfigError(f"fuzzy.{name}", t, "3 numbers a <= peak <= c with a < c")
    for key in LAYER_KEYS:
        ls = getattr(d, key)
        if not ls or any(b <= a for a, b in itertools.pairwise(ls)):
            raise ConfigError(f"design.{key}", ls, "at least one scale, strictly increasing")
    n_layers = len(layer_grid(cfg))
    per_layer = len(pts) * len(d.tire_damping_scales) + int(d.include_airborne_model)
    if per_layer > MAX_BANK_MODELS:
        raise ConfigError("design.linearisation_deflections_m", pts,
                          f"at most {MAX_BANK_MODELS} models in a layer of the bank: "
                          f"{len(pts)} deflections x {len(d.tire_damping_scales)} "
                          f"tire_damping_scales"
                          f"{' + airborne' * d.include_airborne_model} "
                          f"= {per_layer} (every model of the running layer filters each "
                          "tick)")
    n_models = (len(pts) * len(d.tire_damping_scales) * n_layers
                + int(d.include_airborne_model))
    n_noise = len(cfg.noise.speeds_mps) * len(cfg.noise.road_roughness_gd)
    if n_models * n_noise > MAX_BANK_TABLE_ENTRIES:
        raise ConfigError("noise.speeds_mps", cfg.noise.speeds_mps,
                          f"a bank table of at most {MAX_BANK_TABLE_ENTRIES} Kalman designs: "
                          f"{n_models} models x {len(cfg.noise.speeds_mps)} speeds x "
                          f"{len(cfg.noise.road_roughness_gd)} road_roughness_gd = "
                          f"{n_models * n_noise} (one Riccati solve and filter each)")
    if cfg.moving_bank.active_models > per_layer:
        # the moving bank walks the running layer (docs/design.md §11)
        raise ConfigError("moving_bank.active_models", cfg.moving_bank.active_models,
                          f"[1, {per_layer}] (the number of models in a layer of the bank)")
    mb = cfg.moving_bank
    if mb.liftoff_load_fraction / mb.hysteresis_ratio >= 1.0:
        raise ConfigError("moving_bank.liftoff_load_fraction", mb.liftoff_load_fraction,
                          f"< hysteresis_ratio = {mb.hysteresis_ratio} (the touch-down "
                          "reference load_fraction / ratio must stay below the static load)")
    if cfg.noise.nominal_speed_mps < min(cfg.noise.speeds_mps) or \
            cfg.noise.nominal_speed_mps > max(cfg.noise.speeds_mps):
        raise ConfigError("noise.nominal_speed_mps", cfg.noise.nominal_speed_mps,
                          f"within noise.speeds_mps [{min(cfg.noise.speeds_mps)}, "
                          f"{max(cfg.noise.speeds_mps)}]")
    if sorted(cfg.noise.speeds_mps) != cfg.noise.speeds_mps:
        raise ConfigError("noise.speeds_mps", cfg.noise.speeds_mps, "increasing values")
    if sorted(cfg.noise.road_roughness_gd) != cfg.noise.road_roughness_gd:
        raise ConfigError("noise.road_roughness_gd", cfg.noise.road_roughness_gd,
                          "increasing values")
    _excitation_checks(cfg)
    _telemetry_checks(cfg.telemetry)
    _foxglove_checks(cfg)


def _excitation_checks(cfg: RigConfig) -> None:
    """The [excitation] section on its own; what it must satisfy against the rest of the
    configuration is checked when an excitation is built (:func:`excitation_problems`),
    so that a configuration made for other runs (a low rate, short travel, a small force
    limit) is not refused for an excitation it never plays."""
    ex = cfg.excitation
    if ex.chirp_stop_hz <= ex.chirp_start_hz:
        raise ConfigError("excitation.chirp_stop_hz", ex.chirp_stop_hz,
                          f"> excitation.chirp_start_hz = {ex.chirp_start_hz}")
    if ex.chirp_amplitude_n + ex.prbs_amplitude_n <= 0.0:
        raise ConfigError("excitation.chirp_amplitude_n", ex.chirp_amplitude_n,
                          "chirp + PRBS amplitude > 0")
    if 2.0 * ex.taper_s >= ex.duration_s:
        raise ConfigError("excitation.taper_s", ex.taper_s,
                          f"< half of excitation.duration_s = {ex.duration_s}")


def excitation_problems(cfg: RigConfig) -> None:
    """Raise :class:`ConfigError` (naming the key) when the [excitation] section does not
    fit the rest of the configuration: below the Nyquist frequency of the controller
    rate, within the force loop's limit, and stopping before the bump stops."""
    ex = cfg.excitation
    nyquist = 0.5 * cfg.design.sample_rate_hz
    if ex.chirp_stop_hz >= nyquist or ex.prbs_clock_hz > cfg.design.sample_rate_hz:
        raise ConfigError("excitation.chirp_stop_hz", ex.chirp_stop_hz,
                          f"< the Nyquist frequency {nyquist} Hz (and prbs_clock_hz <= "
                          "design.sample_rate_hz)")
    peak = ex.chirp_amplitude_n + ex.prbs_amplitude_n
    if peak > cfg.force_loop.force_limit_n:
        raise ConfigError("excitation.chirp_amplitude_n", ex.chirp_amplitude_n,
                          f"chirp + PRBS amplitude <= force_loop.force_limit_n = "
                          f"{cfg.force_loop.force_limit_n} N (got {peak} N)")
    if ex.travel_limit_m > cfg.vehicle.rattlespace_travel_m:
        raise ConfigError("excitation.travel_limit_m", ex.travel_limit_m,
                          f"<= vehicle.rattlespace_travel_m = {cfg.vehicle.rattlespace_travel_m}"
                          " (stop before the bump stops)")


_HOST_NAME = r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_PARAMS = r"[A-Za-z0-9_]+=[^;#?\s]*(?:;[A-Za-z0-9_]+=[^;#?\s]*)*"
_IP_ENDPOINT = re.compile(
    rf"(?P<proto>tcp|udp|tls|quic|ws)/(?P<host>\[[0-9A-Fa-f:.]+\]|{_HOST_NAME}"
    rf"(?:\.{_HOST_NAME})*):(?P<port>[0-9]{{1,5}})(?:\?{_PARAMS})?(?:#{_PARAMS})?")
_UNIX_ENDPOINT = re.compile(rf"unixsock-stream//[^\s?#]+(?:\?{_PARAMS})?(?:#{_PARAMS})?")
_ENDPOINT_FORM = ("<tcp|udp|tls|quic|ws>/<IPv4, [IPv6] or host name>:<port 1-65535>"
                  "[?key=value;...][#key=value;...] or unixsock-stream/<absolute path>")
_KEY_CHUNK = re.compile(r"[^*$#?\s/]+")


def _endpoint_problem(endpoint: str) -> str:
    """'' for a well-formed Zenoh locator (as the service uses them), else what is wrong."""
    if _UNIX_ENDPOINT.fullmatch(endpoint):
        return ""
    m = _IP_ENDPOINT.fullmatch(endpoint)
    if m is None:
        return _ENDPOINT_FORM
    host, port = m["host"], int(m["port"])
    if not 1 <= port <= 65535:
        return f"a port in [1, 65535] ({_ENDPOINT_FORM})"
    try:
        if host.startswith("["):
            ipaddress.IPv6Address(host[1:-1])
        elif host.replace(".", "").isdigit():
            ipaddress.IPv4Address(host)
    except ValueError:
        return f"a valid IP address ({_ENDPOINT_FORM})"
    return ""


def _telemetry_checks(t: TelemetryConfig) -> None:
    for i, endpoint in enumerate(t.endpoints):
        problem = _endpoint_problem(endpoint)
        if problem:
            raise ConfigError(f"telemetry.endpoints[{i}]", endpoint, problem)
    chunks = t.key_prefix.split("/")
    if len(t.key_prefix) > 128 or not all(_KEY_CHUNK.fullmatch(c) for c in chunks) \
            or chunks[0].startswith("@"):
        raise ConfigError("telemetry.key_prefix", t.key_prefix,
                          "a Zenoh key of 1-128 characters: '/'-separated non-empty chunks "
                          "without wildcards (* $), # ? or spaces, not starting with @")
    if t.mode == "client" and t.listen:
        raise ConfigError("telemetry.listen", t.listen,
                          "false in client mode (a Zenoh client connects, it cannot listen)")


def host_problem(host: str) -> str:
    """'' for an IPv4 / IPv6 address a server can bind, else what is allowed."""
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return "an IPv4 or IPv6 address, e.g. 127.0.0.1 or 0.0.0.0"
    return ""


def _foxglove_checks(cfg: RigConfig) -> None:
    fg = cfg.foxglove
    problem = host_problem(fg.host)
    if problem:
        raise ConfigError("foxglove.host", fg.host, problem)
    if fg.rate_hz > cfg.design.sample_rate_hz:
        raise ConfigError("foxglove.rate_hz", fg.rate_hz,
                          f"<= design.sample_rate_hz = {cfg.design.sample_rate_hz}")


def parse_config(data: Mapping[str, Any]) -> RigConfig:
    """Build and validate a :class:`RigConfig` from a (TOML-shaped) mapping.

    Missing keys take their defaults; unknown keys are errors.
    """
    cfg = _build(RigConfig, data, "")
    _cross_checks(cfg)
    return cfg


def read_text_file(path: str | Path, kind: str = "TOML",
                   max_bytes: int = MAX_CONFIG_BYTES) -> str:
    """The UTF-8 text of a configuration-like file; :class:`ConfigError` (key
    ``<file>``) when it cannot be read, is larger than ``max_bytes`` or is not UTF-8."""
    p = Path(path)
    try:
        with open_regular(p) as f:
            raw = f.read(max_bytes + 1)
    except NotRegularFileError as exc:
        raise ConfigError("<file>", str(p), f"a readable {kind} file (it {exc.what})") \
            from None
    except OSError as exc:
        raise ConfigError("<file>", str(p),
                          f"a readable {kind} file ({exc.strerror or exc})") from exc
    if len(raw) > max_bytes:
        raise ConfigError("<file>", str(p), f"a {kind} file of at most {max_bytes} bytes")
    return decode_text(raw, p)


def decode_text(raw: bytes, where: str | Path) -> str:
    """``raw`` as UTF-8; :class:`ConfigError` (key ``<file>``, value ``where``) naming the
    first byte that is not."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError("<file>", str(where),
                          f"UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start} "
                          "is not UTF-8)") from exc


def config_from_bytes(raw: bytes, where: str | Path) -> RigConfig:
    """The configuration in the TOML bytes ``raw`` (e.g. a recording's attachment, named
    by ``where``); :class:`ConfigError` as :func:`load_config`."""
    return parse_config(parse_toml(decode_text(raw, where), where))


def parse_toml(text: str, path: str | Path) -> dict[str, Any]:
    """``tomllib.loads`` with its errors (including nesting too deep for the parser)
    as :class:`ConfigError` naming the file."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("<file>", str(path), f"valid TOML ({exc})") from exc
    except ValueError:              # int(): more digits than sys.get_int_max_str_digits
        key, line = _long_int_key(text)
        raise ConfigError(key, _Described(f"<an integer of more than {MAX_INT_DIGITS} "
                                          f"digits on line {line} of {path}>"),
                          f"an integer of at most {MAX_INT_DIGITS} digits") from None
    except RecursionError:
        raise ConfigError("<file>", str(path),
                          "valid TOML nested at most a few hundred levels deep") from None


def layer_grid(cfg: RigConfig) -> list[tuple[float, float, float, float]]:
    """(sprung mass, spring rate, damping, tire stiffness) scale of each layer of the
    bank, in the bank's order: ``design.sprung_mass_scales`` x ``spring_rate_scales`` x
    ``damping_scales`` x ``tire_stiffness_scales``, mass major, tire minor."""
    d = cfg.design
    return list(itertools.product(d.sprung_mass_scales, d.spring_rate_scales,
                                  d.damping_scales, d.tire_stiffness_scales))


def layer_scales(cfg: RigConfig) -> list[tuple[float, float, float]]:
    """(sprung mass, spring rate, damping) scale of each layer of the bank, in the bank's
    order (:func:`layer_grid`; the tire layers of one [M, K, C] repeat it)."""
    return [(m, k, c) for m, k, c, _t in layer_grid(cfg)]


def layer_tire_scales(cfg: RigConfig) -> list[float]:
    """Tire stiffness scale (x ``tire.stiffness_coefficient``) of each layer of the bank,
    in the bank's order (:func:`layer_grid`)."""
    return [t for _m, _k, _c, t in layer_grid(cfg)]


def layer_config(cfg: RigConfig, mass_scale: float, spring_scale: float = 1.0,
                 damping_scale: float = 1.0, tire_scale: float = 1.0) -> RigConfig:
    """The configuration of one layer of the bank: the vehicle's sprung mass, suspension
    spring rate and damping x the scales, the tire's stiffness coefficient x
    ``tire_scale`` (its damping law as configured).  The design of each layer, the
    runtime's per-layer wheel-hop predictions and the wheel-hop tracker's tire table all
    take their rigs from here."""
    if (mass_scale, spring_scale, damping_scale, tire_scale) == (1.0, 1.0, 1.0, 1.0):
        return cfg
    # the two sections copied with the scaled values, not the whole configuration
    # re-parsed (cfg.replace validates every section: 7 ms a layer, 0.4 s of the default
    # bank's design); the scales are within their keys' validated bounds
    v = cfg.vehicle
    return dataclasses.replace(
        cfg, vehicle=dataclasses.replace(
            v, sprung_mass_kg=v.sprung_mass_kg * mass_scale,
            suspension_stiffness_n_per_m=v.suspension_stiffness_n_per_m * spring_scale,
            suspension_damping_ns_per_m=v.suspension_damping_ns_per_m * damping_scale),
        tire=dataclasses.replace(
            cfg.tire, stiffness_coefficient=cfg.tire.stiffness_coefficient * tire_scale))


#: the ``[design]`` keys of the bank's layers (:func:`layer_grid`)
LAYER_KEYS = ("sprung_mass_scales", "spring_rate_scales", "damping_scales",
              "tire_stiffness_scales")


def one_layer(cfg: RigConfig) -> RigConfig:
    """``cfg`` with a bank of one layer: the tire models designed for the configured
    vehicle only (every :data:`LAYER_KEYS` = [1.0]), as the thesis's bank is."""
    return cfg.replace(design={key: [1.0] for key in LAYER_KEYS})


def layer_params(cfg: RigConfig, vehicle: VehicleConfig | None = None
                 ) -> list[tuple[float, float, float]]:
    """(sprung mass [kg], spring rate [N/m], damping [N s/m]) of each layer of the bank,
    in the bank's order: :func:`layer_scales` of ``cfg`` x those of ``vehicle`` (default
    ``cfg.vehicle``)."""
    v = cfg.vehicle if vehicle is None else vehicle
    return [(m * v.sprung_mass_kg, k * v.suspension_stiffness_n_per_m,
             c * v.suspension_damping_ns_per_m) for m, k, c in layer_scales(cfg)]


def load_config(path: str | Path | None = None) -> RigConfig:
    """Load ``path`` (TOML), or the built-in defaults when ``path`` is None."""
    if path is None:
        return default_config()
    return parse_config(parse_toml(read_text_file(path), path))


def default_config() -> RigConfig:
    cfg = RigConfig()
    _cross_checks(cfg)
    return cfg


def config_to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def config_to_toml(cfg: RigConfig) -> str:
    """The canonical TOML text of ``cfg`` (round-trips through :func:`load_config`)."""
    lines: list[str] = []
    for section, values in config_to_dict(cfg).items():
        lines.append(f"[{section}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in values.items())
        lines.append("")
    return "\n".join(lines)


def config_hash(cfg: RigConfig) -> str:
    """sha256 of the canonical JSON of the configuration (stable across key order)."""
    blob = json.dumps(config_to_dict(cfg), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()


#: the sections a design artifact depends on (controller.design and what it calls read
#: vehicle, tire, design, noise, fuzzy, actuator and force_loop; moving_bank shapes the
#: bank built from the artifact).  sensors/safety/can/telemetry/recording do not.
DESIGN_SECTIONS: tuple[str, ...] = ("vehicle", "tire", "design", "noise", "fuzzy", "bayes",
                                    "moving_bank", "force_loop", "actuator")


def design_config_hash(cfg: RigConfig) -> str:
    """sha256 of the canonical JSON of only the :data:`DESIGN_SECTIONS` (the design
    artifact's check: changing e.g. the telemetry port keeps an artifact valid)."""
    full = config_to_dict(cfg)
    blob = json.dumps({k: full[k] for k in DESIGN_SECTIONS}, sort_keys=True,
                      separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()
