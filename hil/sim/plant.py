"""Nonlinear quarter car with a servo-hydraulic actuator: the emulated rig's physics.

State vector (``RigPlant.state``), SI, conventions of ``controller/plant.py``:

    0 x1 = w - zs     1 x2 = w - zu (tire deflection)    2 x3 = zs'    3 x4 = zu'
    4 x_v  normalised spool position [-1, 1]              5 P  load pressure [Pa]
    6 w    road height [m] (integrated road velocity, for absolute positions)

Forces (positions from the unloaded springs, gravity acts):

    r       = x1 - x2                           rattlespace, compression positive
    F_bs    = k_bs (r - r0 - travel)   if r - r0 >  travel   (compression bump stop)
              k_bs (r - r0 + travel)   if r - r0 < -travel   (extension rebound stop)
    F_s     = K (r - s) + C (x4 - x3) + F_bs + A P   (pushes body up, wheel down)
    f_tire  = max(0, k' (1000 x2)^e + Ct(x2) x2')  for x2 > 0, else 0  (pushes, never pulls)
    M x3'   =  F_s - M g
    m x4'   = -F_s + f_tire - m g

A ballast change (``[emulator] ballast_step_time_s`` > 0, ``ballast_step_scale``) multiplies
M by the scale once the plant's run time reaches the step time: the ballast joins the body
at rest (momentum kept, x3 scaled by M_before / M_after), the body sags to its new static
equilibrium (M_after g / K + s) and the LVDT zero stays where it was set; :meth:`reset`
takes the ballast off again.

r0 = M_nom g / K_nom is the static rattlespace of the nominal rig (the bump-stop geometry
does not move when Monte Carlo perturbs M or K).  s is the spring-preload shift: 0 unless
``PlantParams.ride_height_offset_m`` is given, in which case a technician has set the
preload so that the static rattlespace is r0 + that offset (s = r0 + offset - M g / K),
as on a real rig; without it a perturbed plant sits at M g / K, off the stops' centre.
The hydraulics are those of ``hil.sim.hydraulics``.  One call of the numba kernel
:func:`advance_kernel` advances one controller tick with ``n_substeps`` classical RK4
steps (the hydraulic mode near 150 Hz and the valve's sqrt law are stiff relative to the
1 ms tick); the road velocity is held over the tick (the road module makes it the exact
mean velocity of the tick, so the integrated road height matches the profile at every
tick).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from controller.arrays import FloatArray
from controller.config import RigConfig
from controller.runtime.layout import SlotValue
from hil.sim.hydraulics import hydraulic_power_w, load_pressure_rate

__all__ = ["N_STATES", "PlantParams", "RigPlant", "advance_kernel", "derivatives",
           "emulated_params"]


N_STATES = 7
# parameter vector layout (float64 array handed to the kernels)
P_M, P_m, P_K, P_C, P_G, P_KT, P_KE, P_C2, P_C3, P_CSAT = range(10)
P_TRAVEL, P_KBS, P_R0, P_A, P_PS, P_ALPHA, P_BETA, P_GAMMA, P_TAUV, P_TAUB = range(10, 20)
P_STROKE, P_PRELIEF, P_PRELOAD = 20, 21, 22
N_PARAMS = 23
# diagnostics vector layout (written by advance_kernel)
D_TIRE_FORCE, D_ACCEL, D_POWER, D_OFF_GROUND_S, D_BUMP_S, D_NONFINITE = range(6)
N_DIAG = 6


@dataclass(frozen=True)
class PlantParams:
    """Overrides of the nominal plant (Monte Carlo, model mismatch).  None = nominal."""

    sprung_mass_kg: float | None = None
    unsprung_mass_kg: float | None = None
    suspension_stiffness_n_per_m: float | None = None
    suspension_damping_ns_per_m: float | None = None
    tire_stiffness_scale: float = 1.0
    tire_damping_scale: float = 1.0
    #: static rattlespace minus the bump stops' centre [m] (compression positive) after a
    #: technician set the ride height by spring preload; None = no preload adjustment
    ride_height_offset_m: float | None = None


def emulated_params(cfg: RigConfig) -> PlantParams | None:
    """The true plant of the emulated rig from ``cfg.emulator`` (None: the configured
    rig itself, so that runs on the nominal plant stay bit-identical)."""
    e = cfg.emulator
    if e.is_nominal:
        return None
    v = cfg.vehicle
    return PlantParams(sprung_mass_kg=v.sprung_mass_kg * e.sprung_mass_scale,
                       unsprung_mass_kg=v.unsprung_mass_kg * e.unsprung_mass_scale,
                       suspension_stiffness_n_per_m=(v.suspension_stiffness_n_per_m
                                                     * e.spring_rate_scale),
                       suspension_damping_ns_per_m=(v.suspension_damping_ns_per_m
                                                    * e.damping_scale),
                       tire_stiffness_scale=e.tire_stiffness_scale,
                       ride_height_offset_m=e.ride_height_offset_m)


@njit(cache=True)
def _forces(x1: float, x2: float, x3: float, x4: float, pr: float, wdot: float,
            p: FloatArray) -> tuple[float, float, float]:
    """(suspension force on the body F_s, tire force, bump-stop force) [N]."""
    r = x1 - x2
    dev = r - p[P_R0]
    fbs = 0.0
    if dev > p[P_TRAVEL]:
        fbs = p[P_KBS] * (dev - p[P_TRAVEL])
    elif dev < -p[P_TRAVEL]:
        fbs = p[P_KBS] * (dev + p[P_TRAVEL])
    fs = p[P_K] * (r - p[P_PRELOAD]) + p[P_C] * (x4 - x3) + fbs + p[P_A] * pr
    ft = 0.0
    if x2 > 0.0:
        mm = 1000.0 * x2
        fk = p[P_KT] * mm ** p[P_KE]
        mmc = mm if mm < p[P_CSAT] else p[P_CSAT]
        ct = 1000.0 * (p[P_C2] * mmc * mmc + p[P_C3] * mmc * mmc * mmc)
        ft = fk + ct * (wdot - x4)
        if ft < 0.0:
            ft = 0.0
    return fs, ft, fbs


@njit(cache=True)
def derivatives(y: FloatArray, p: FloatArray, spool_cmd: float, bypass_open: bool,
                wdot: float, dy: FloatArray) -> None:
    """dy = f(y) for the 7 states (see module docstring)."""
    x1, x2, x3, x4, xv, pr = y[0], y[1], y[2], y[3], y[4], y[5]
    fs, ft, _ = _forces(x1, x2, x3, x4, pr, wdot, p)
    dy[0] = wdot - x3
    dy[1] = wdot - x4
    dy[2] = fs / p[P_M] - p[P_G]
    dy[3] = (-fs + ft) / p[P_m] - p[P_G]
    dy[4] = (spool_cmd - xv) / p[P_TAUV]
    dy[5] = load_pressure_rate(pr, p[P_STROKE] * xv, x3 - x4, p[P_A], p[P_PS], p[P_ALPHA],
                               p[P_BETA], p[P_GAMMA], bypass_open, p[P_TAUB])
    dy[6] = wdot


@njit(cache=True)
def advance_kernel(y: FloatArray, p: FloatArray, dt: float, n_sub: int, spool_cmd: float,
                   bypass_open: bool, wdot: float, diag: FloatArray) -> None:
    """Advance ``y`` in place by ``dt`` with ``n_sub`` RK4 steps; fill ``diag``.

    diag: tire force [N] and sprung acceleration zs'' [m/s^2] at the end of the tick,
    mean hydraulic power over the tick [W], time off the ground [s], time on a bump
    stop [s], 1.0 if the state became non-finite (the state is then left as it is).
    """
    if spool_cmd > 1.0:
        spool_cmd = 1.0
    elif spool_cmd < -1.0:
        spool_cmd = -1.0
    h = dt / n_sub
    n = y.shape[0]
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    yt = np.empty(n)
    power = 0.0
    off = 0.0
    bump = 0.0
    ps = p[P_PS]
    for _ in range(n_sub):
        derivatives(y, p, spool_cmd, bypass_open, wdot, k1)
        for i in range(n):
            yt[i] = y[i] + 0.5 * h * k1[i]
        derivatives(yt, p, spool_cmd, bypass_open, wdot, k2)
        for i in range(n):
            yt[i] = y[i] + 0.5 * h * k2[i]
        derivatives(yt, p, spool_cmd, bypass_open, wdot, k3)
        for i in range(n):
            yt[i] = y[i] + h * k3[i]
        derivatives(yt, p, spool_cmd, bypass_open, wdot, k4)
        for i in range(n):
            y[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        # relief valves (set at the nominal supply): |P| <= Ps
        if y[5] > p[P_PRELIEF]:
            y[5] = p[P_PRELIEF]
        elif y[5] < -p[P_PRELIEF]:
            y[5] = -p[P_PRELIEF]
        power += hydraulic_power_w(y[5], p[P_STROKE] * y[4], ps, p[P_GAMMA], p[P_ALPHA],
                                   p[P_A], bypass_open)
        if y[1] <= 0.0:
            off += h
        dev = y[0] - y[1] - p[P_R0]
        if dev > p[P_TRAVEL] or dev < -p[P_TRAVEL]:
            bump += h
    fs, ft, _ = _forces(y[0], y[1], y[2], y[3], y[5], wdot, p)
    diag[D_TIRE_FORCE] = ft
    diag[D_ACCEL] = fs / p[P_M] - p[P_G]
    diag[D_POWER] = power / n_sub
    diag[D_OFF_GROUND_S] = off
    diag[D_BUMP_S] = bump
    finite = True
    for i in range(n):
        if not math.isfinite(y[i]):
            finite = False
    diag[D_NONFINITE] = 0.0 if finite else 1.0


def _param_vector(cfg: RigConfig, params: PlantParams) -> FloatArray:
    v, t, a = cfg.vehicle, cfg.tire, cfg.actuator
    p = np.zeros(N_PARAMS)
    p[P_M] = params.sprung_mass_kg if params.sprung_mass_kg is not None else v.sprung_mass_kg
    p[P_m] = (params.unsprung_mass_kg if params.unsprung_mass_kg is not None
              else v.unsprung_mass_kg)
    p[P_K] = (params.suspension_stiffness_n_per_m
              if params.suspension_stiffness_n_per_m is not None
              else v.suspension_stiffness_n_per_m)
    p[P_C] = (params.suspension_damping_ns_per_m
              if params.suspension_damping_ns_per_m is not None
              else v.suspension_damping_ns_per_m)
    p[P_G] = v.gravity_mps2
    p[P_KT] = t.stiffness_coefficient * params.tire_stiffness_scale
    p[P_KE] = t.stiffness_exponent
    p[P_C2] = t.damping_c2 * params.tire_damping_scale
    p[P_C3] = t.damping_c3 * params.tire_damping_scale
    p[P_CSAT] = t.damping_saturation_mm
    p[P_TRAVEL] = v.rattlespace_travel_m
    p[P_KBS] = v.bump_stop_stiffness_n_per_m
    p[P_R0] = v.sprung_mass_kg * v.gravity_mps2 / v.suspension_stiffness_n_per_m
    p[P_A] = a.piston_area_m2
    p[P_PS] = a.supply_pressure_pa
    p[P_ALPHA] = a.alpha_n_per_m5
    p[P_BETA] = a.leakage_beta_per_s
    p[P_GAMMA] = a.valve_gamma
    p[P_TAUV] = a.spool_time_constant_s
    p[P_TAUB] = a.bypass_time_constant_s
    p[P_STROKE] = a.spool_stroke_m
    p[P_PRELIEF] = a.supply_pressure_pa
    if params.ride_height_offset_m is not None:
        p[P_PRELOAD] = p[P_R0] + params.ride_height_offset_m - p[P_M] * p[P_G] / p[P_K]
    return p


class RigPlant:
    """The emulated rig's quarter car + actuator.  Never raises on bad numbers: a
    non-finite state sets :attr:`nonfinite` (and stays so until :meth:`reset`).

    ``params`` overrides M, m, K, C and scales the tire stiffness and damping laws;
    None = the emulated rig of ``cfg.emulator`` (:func:`emulated_params`).  Where the
    LVDT reads 0 is ``cfg.emulator.lvdt_zero``: ``"actual"`` (this plant's own static
    rattlespace, as a rig zeroed at rest reads) or ``"nominal"`` (M g / K of the
    configured rig); they differ only when the plant's M, K or preload differ.
    """

    def __init__(self, cfg: RigConfig, params: PlantParams | None = None,
                 substeps: int = 20) -> None:
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        self.cfg = cfg
        if params is None:
            params = emulated_params(cfg)
        self.params = params or PlantParams()
        self.p = _param_vector(cfg, self.params)
        for name, value in zip(("M", "m", "K", "tire_stiffness_scale"),
                               (self.p[P_M], self.p[P_m], self.p[P_K], self.p[P_KT]),
                               strict=True):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"plant parameter {name} must be positive, got {value}")
        self.substeps = int(substeps)
        em = cfg.emulator
        #: sprung mass before any ballast change [kg]; the change (time [s], scale) or None
        self._mass_before_kg = float(self.p[P_M])
        self.ballast_step: tuple[float, float] | None = (
            (em.ballast_step_time_s, em.ballast_step_scale) if em.has_ballast_step else None)
        self._ballast_on = False
        self.state = np.zeros(N_STATES)
        self.diag = np.zeros(N_DIAG)
        self.bypass_open = True
        self.supply_lost = False
        self.time_s = 0.0
        self.nonfinite = False
        self.reset()
        eq = self.equilibrium()
        # the LVDT zero; where M, K and the preload are the configured ones, both choices
        # are the configured M g / K (taken as configured, to the last bit)
        moved = params is not None and (params.sprung_mass_kg is not None
                                        or params.suspension_stiffness_n_per_m is not None
                                        or params.ride_height_offset_m is not None)
        self.static_rattlespace_m = (float(eq[0] - eq[1])
                                     if cfg.emulator.lvdt_zero == "actual" and moved
                                     else float(self.p[P_R0]))

    # ------------------------------------------------------------------ state
    def equilibrium(self) -> FloatArray:
        """Passive static equilibrium [x1, x2, x3, x4] of this (possibly perturbed) plant."""
        p = self.p
        load = (p[P_M] + p[P_m]) * p[P_G]
        x2 = (load / p[P_KT]) ** (1.0 / p[P_KE]) / 1000.0
        r = p[P_M] * p[P_G] / p[P_K] + p[P_PRELOAD]
        return np.array([x2 + r, x2, 0.0, 0.0])

    def reset(self, state: FloatArray | None = None) -> None:
        """Static equilibrium (or ``state`` [x1..x4]), spool centred, P = 0, bypass open."""
        self.p[P_M] = self._mass_before_kg
        self._ballast_on = False
        self.state[:] = 0.0
        self.state[:4] = self.equilibrium() if state is None else np.asarray(state)[:4]
        self.bypass_open = True
        self.set_supply_lost(False)
        self.time_s = 0.0
        self.nonfinite = False
        self.diag[:] = 0.0
        fs, ft = self._forces_now(0.0)
        self.diag[D_TIRE_FORCE] = ft
        self.diag[D_ACCEL] = fs / self.p[P_M] - self.p[P_G]

    def set_supply_lost(self, lost: bool) -> None:
        """Failure mode: hydraulic supply pressure lost (Ps -> 0) or restored."""
        self.supply_lost = bool(lost)
        self.p[P_PS] = 0.0 if lost else self.cfg.actuator.supply_pressure_pa

    def _forces_now(self, wdot: float) -> tuple[float, float]:
        y = self.state
        fs, ft, _ = _forces(y[0], y[1], y[2], y[3], y[5], wdot, self.p)
        return fs, ft

    # ------------------------------------------------------------------ stepping
    def advance(self, dt_s: float, spool_cmd: float, bypass_open: bool,
                road_height_m: float, road_velocity_mps: float) -> None:
        """Advance one tick of ``dt_s`` with the spool command held (clipped to [-1, 1]).

        ``road_velocity_mps`` is held over the tick; ``road_height_m`` (the height at the
        start of the tick) re-anchors the integrated road height, so a road whose velocity
        is its per-tick mean slope leaves no drift.  Non-finite inputs are replaced by 0
        and the spool by the safe command.
        """
        if not math.isfinite(spool_cmd):
            spool_cmd, bypass_open = 0.0, True
        if not math.isfinite(road_velocity_mps):
            road_velocity_mps = 0.0
        if math.isfinite(road_height_m):
            # keep x1, x2 consistent with the given absolute road height
            shift = road_height_m - self.state[6]
            self.state[0] += shift
            self.state[1] += shift
            self.state[6] = road_height_m
        self.bypass_open = bool(bypass_open)
        advance_kernel(self.state, self.p, float(dt_s), self.substeps, float(spool_cmd),
                       self.bypass_open, float(road_velocity_mps), self.diag)
        self.time_s += dt_s
        if self.diag[D_NONFINITE] != 0.0:
            self.nonfinite = True
        step = self.ballast_step
        if step is not None and not self._ballast_on and self.time_s >= step[0] - 1e-9:
            self.change_sprung_mass(self.p[P_M] * step[1])
            self._ballast_on = True

    @property
    def sprung_mass_kg(self) -> float:
        """The body's mass now (after any ballast change) [kg]."""
        return float(self.p[P_M])

    def change_sprung_mass(self, mass_kg: float) -> None:
        """Ballast on or off: the body's mass becomes ``mass_kg``; the ballast joins (or
        leaves) the body at rest in the lab, so the body's momentum is kept.  The
        acceleration read-out is that of the new mass."""
        if not (math.isfinite(mass_kg) and mass_kg > 0.0):
            raise ValueError(f"sprung mass must be positive, got {mass_kg}")
        self.state[2] *= self.p[P_M] / mass_kg
        self.p[P_M] = mass_kg
        fs, _ = self._forces_now(0.0)
        self.diag[D_ACCEL] = fs / mass_kg - self.p[P_G]

    # ------------------------------------------------------------------ signals
    @property
    def rattlespace_m(self) -> float:
        """x1 - x2, absolute (from the unloaded spring)."""
        return float(self.state[0] - self.state[1])

    @property
    def actuator_force_n(self) -> float:
        return float(self.p[P_A] * self.state[5])

    tire_force_n = SlotValue("diag", D_TIRE_FORCE, float, "tire force [N] (0 off the ground)")
    sprung_accel_mps2 = SlotValue(
        "diag", D_ACCEL, float,
        "zs'' [m/s^2] at the end of the last tick (0 at rest; gravity removed)")

    @property
    def off_ground(self) -> bool:
        return bool(self.state[1] <= 0.0)

    off_ground_time_last_tick_s = SlotValue("diag", D_OFF_GROUND_S, float,
                                            "time off the ground in the last tick [s]")
    bump_stop_time_last_tick_s = SlotValue("diag", D_BUMP_S, float,
                                           "time on a bump stop in the last tick [s]")
    hydraulic_power_w = SlotValue("diag", D_POWER, float,
                                  "mean valve hydraulic power P x Q over the last tick [W]")
    spool = SlotValue("state", 4, float, "spool position, normalised to [-1, 1]")
    load_pressure_pa = SlotValue("state", 5, float, "actuator load pressure [Pa]")

    @property
    def supply_pressure_pa(self) -> float:
        return float(self.p[P_PS])

    def true_signals(self) -> tuple[float, float, float]:
        """(rattlespace about the nominal static position [m], actuator force [N],
        sprung acceleration zs'' [m/s^2]) -- what ideal sensors would read."""
        return (self.rattlespace_m - self.static_rattlespace_m, self.actuator_force_n,
                self.sprung_accel_mps2)

    def energy_j(self) -> float:
        """Mechanical energy: kinetic + suspension spring + bump stops + tire + gravity
        (potential zero at the unloaded springs with w = 0) [J]."""
        y, p = self.state, self.p
        x1, x2, x3, x4, w = y[0], y[1], y[2], y[3], y[6]
        r = x1 - x2
        e = 0.5 * p[P_M] * x3**2 + 0.5 * p[P_m] * x4**2 + 0.5 * p[P_K] * (r - p[P_PRELOAD])**2
        dev = r - p[P_R0]
        excess = max(abs(dev) - p[P_TRAVEL], 0.0)
        e += 0.5 * p[P_KBS] * excess**2
        if x2 > 0.0:
            e += p[P_KT] * 1000.0 ** p[P_KE] * x2 ** (p[P_KE] + 1.0) / (p[P_KE] + 1.0)
        zs, zu = w - x1, w - x2
        e += p[P_G] * (p[P_M] * zs + p[P_m] * zu)
        return float(e)
