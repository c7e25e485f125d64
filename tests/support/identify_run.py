"""An identification run recorded once per test session: the service's loop against the
emulated rig's CAN node (``hil.stepped_run.record_emulated_run``, tick-stepped, road
'flat', the excitation of ``[excitation]`` played from the arm) on the rig of the
must-show figures (M x1.12, K x0.92, C x1.10, tire stiffness x0.90), shortened to an
8 s excitation after 1.5 s of rest."""

from __future__ import annotations

from pathlib import Path

from controller.config import RigConfig, parse_config

#: the emulated rig and the shortened excitation of the test recording
IDENT_CFG: RigConfig = parse_config({
    "emulator": {"sprung_mass_scale": 1.12, "spring_rate_scale": 0.92,
                 "damping_scale": 1.10, "tire_stiffness_scale": 0.90},
    "excitation": {"duration_s": 8.0, "rest_s": 1.5},
    "telemetry": {"enabled": False}})
#: rest, excitation and the passive tail [s]
ARM_S = 1.6
SECONDS = ARM_S + 8.0 + 0.7


def true_values(cfg: RigConfig = IDENT_CFG) -> dict[str, float]:
    """The emulated rig's values under the config keys."""
    v, t, e = cfg.vehicle, cfg.tire, cfg.emulator
    return {"vehicle.sprung_mass_kg": v.sprung_mass_kg * e.sprung_mass_scale,
            "vehicle.unsprung_mass_kg": v.unsprung_mass_kg * e.unsprung_mass_scale,
            "vehicle.suspension_stiffness_n_per_m":
                v.suspension_stiffness_n_per_m * e.spring_rate_scale,
            "vehicle.suspension_damping_ns_per_m":
                v.suspension_damping_ns_per_m * e.damping_scale,
            "tire.stiffness_coefficient": t.stiffness_coefficient * e.tire_stiffness_scale}


def record_identification_run(path: Path, design_bytes: bytes, cfg: RigConfig = IDENT_CFG,
                              seconds: float = SECONDS, **kw: object) -> Path:
    from hil.stepped_run import record_emulated_run

    return record_emulated_run(path, seconds, cfg=cfg, design_bytes=design_bytes,
                               arm_at_s=ARM_S, road="flat", excite=True, **kw)  # type: ignore[arg-type]
