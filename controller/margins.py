"""The loop on the linearised rig, and its margins: linear analysis with python-control.

Discrete python-control blocks on the 1 kHz sample grid, joined by signal name
(:func:`connect`: ``control.append`` and one static feedback, the system
``control.interconnect`` gives, 10 times faster; docs/design.md section 7):

- ``plant`` (:func:`rig_plant_ss`): linear quarter-car model j in deviation coordinates,
  with the true human filter F(s) as a state (exact performance output), and either an
  *ideal* actuator (force = the held command; the load cell at tick k reads the command
  of tick k-1) or the *hydraulic* actuator of ``hil/sim/hydraulics.py`` linearised at zero
  load pressure (:mod:`controller.actuator`, ZOH on the spool command).  Sampled at
  t_k: rattlespace, true acceleration A[2] x + F / M, force, and the performance outputs;
  optional noise inputs (state noise of the road, sensor noise);
- ``accel``: the accelerometer low-pass of ``hil/sim/sensors.py`` (Tustin, pre-warped);
- ``ctrl`` (:func:`runtime_controller_ss`): the runtime bank for model j
  (``controller/runtime/bank.py``): Kalman update and propagation with the measured force,
  human filter on the measured acceleration, the spool model of ``controller/actuator.py``
  on its own output and the measured rattlespace, fref = -K [x+; xf] - K_a [x̂_v; F; w;
  s_pending];
- ``pi``: ``controller/runtime/force_loop.py`` (backward-Euler PI, unsaturated, plus the valve
  flow feedforward of the measured rattlespace, linearised at zero load pressure);
- ``delay``: ``delay_ticks`` ticks between the PI output and the valve, i.e. inside the
  force loop too, as in ``hil/sim/closed_loop.py`` and on the CAN loop (the PI runs in
  the controller).

Timing: with ``delay_ticks = 0`` the sensors sample at t_k and the spool command
computed from them acts over [t_k, t_k+1) (``hil/sim/closed_loop.py``).  The CAN loop
(``hil/node.py`` advances the plant with the latest valve command, then samples and
sends) equals that when the command reaches the rig before its next tick, and is one
tick later otherwise: 0 or 1, set by the phase of the two free-running 1 kHz timers.

Margins: every gain crossover of the loop gain L(e^{jwT}) broken at the force reference
(negative-feedback convention, closed loop 1 + L), its phase margin and the delay margin
PM / w (the extra pure delay at the break point that makes that crossover touch -1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import control
import numpy as np

from controller.actuator import FlowFeedforward, ServoModel, flow_feedforward, servo_model
from controller.arrays import FloatArray
from controller.config import ForceLoopConfig, RigConfig
from controller.design import ModelDesign, measurement_noise_cov
from controller.human_filter import HumanFilter, discretize_zoh, human_filter
from controller.kalman import process_noise_cov, steady_state_kalman
from controller.lq import actuated_lq_gain, actuated_plant, augmented_plant, lq_gain
from controller.road_noise import road_velocity_intensity

__all__ = [
    "Actuator",
    "Crossover",
    "LoopParts",
    "accel_sensor_ss",
    "closed_loop_stable",
    "crossovers",
    "delay_margin_s",
    "delay_ss",
    "force_loop_gain",
    "force_loop_ss",
    "fullstate_controller_ss",
    "loop_kalman_gain",
    "loop_parts",
    "lqg_loop_gain",
    "rig_plant_ss",
    "runtime_controller_ss",
]

Actuator = Literal["ideal", "hydraulic"]

#: plant outputs: sensors, then performance (filtered accel, rattlespace, tire deflection)
PLANT_OUTPUTS = ("r", "a_true", "Fm", "yf", "rattle", "tire")


@dataclass(frozen=True)
class Crossover:
    """One gain crossover |L| = 1: frequency, phase margin, delay margin."""

    freq_hz: float
    phase_margin_deg: float
    delay_margin_s: float


@dataclass(frozen=True)
class LoopParts:
    """What the loop of model j needs: human filter, gains, Kalman gain, spool model."""

    hf: HumanFilter
    K: FloatArray       # (6,)  on [x+ - x̄; xf]
    Ka: FloatArray      # (3 + D,) on [x̂_v; F_meas; w; s_{k-1..k-D}]
    L: FloatArray       # (4, 2)
    servo: ServoModel


def loop_kalman_gain(cfg: RigConfig, md: ModelDesign) -> FloatArray:
    """The (4, 2) Kalman gain of model j's loop: the plant filter (no bias states) at the
    nominal noise entry (road velocity of the nominal speed and roughness)."""
    W = road_velocity_intensity(cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    return steady_state_kalman(md.dfm.Phi, md.fm.C, md.dfm.Qd_unit * W,
                               measurement_noise_cov(cfg)).L


def loop_parts(cfg: RigConfig, md: ModelDesign, weights: list[float], *,
               gains: tuple[FloatArray, FloatArray] | None = None,
               kalman_gain: FloatArray | None = None) -> LoopParts:
    """Gains as ``design_bank(cfg)`` makes them (``design.actuator_model``), Kalman gain at
    the nominal noise entry (:func:`loop_kalman_gain`).  ``gains`` = (K, Ka) and
    ``kalman_gain`` skip recomputing what the caller has already (the design's
    ``lq_gain[w, j]`` and ``actuator_gain[w, j]`` are these gains, bit for bit)."""
    dt = cfg.sample_time_s
    hf = human_filter(cfg.design, dt)
    servo = servo_model(cfg)
    if gains is not None:
        K, Ka = gains
    elif cfg.design.actuator_model == "hydraulic":
        k = actuated_lq_gain(md.model, hf, weights, servo)
        K, Ka = k[:6], k[6:]
    else:
        K, Ka = lq_gain(md.model, hf, weights), np.zeros(3 + servo.delay_ticks)
    L = loop_kalman_gain(cfg, md) if kalman_gain is None else kalman_gain
    return LoopParts(hf, K, Ka, L, servo)


def rig_plant_ss(md: ModelDesign, cfg: RigConfig, actuator: Actuator, *,
                 noise: bool = False) -> tuple[control.StateSpace, FloatArray]:
    """Discrete plant of model j and its process-noise covariance Qw (white road velocity
    at the nominal speed and roughness, Van Loan).  Input ``s`` (spool command, or force
    if ideal); with ``noise``: ``w0..`` added to the state, ``v_r``, ``v_F`` added to the
    rattlespace and force readings.  Outputs :data:`PLANT_OUTPUTS` then ``z0..`` (state).
    States: ideal [x (4), xf (2), F_held], hydraulic [x (4), xf (2), x_v, F]."""
    dt = cfg.sample_time_s
    hf = human_filter(cfg.design, dt)
    model = md.model
    inv_m = float(model.B2[2])
    W = road_velocity_intensity(cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    n = 7 if actuator == "ideal" else 8
    Ad = np.zeros((n, n))
    Bs = np.zeros(n)
    Qw = np.zeros((n, n))
    if actuator == "ideal":
        aug = augmented_plant(model, hf, (0.0, 0.0, 1.0, 0.0))
        Pa, Ga = discretize_zoh(aug.A, aug.B, dt)
        Ad[:6, :6] = Pa
        Bs[:6] = Ga
        Bs[6] = 1.0
        Qw[:6, :6] = process_noise_cov(aug.A, aug.B1, W, dt)
        iF = 6
    elif actuator == "hydraulic":
        A8, B8, B1 = actuated_plant(model, hf, servo_model(cfg))
        Ad, Bs = discretize_zoh(A8, B8, dt)
        Qw = process_noise_cov(A8, B1, W, dt)
        iF = 7
    else:
        raise ValueError(f"actuator {actuator!r}: allowed 'ideal', 'hydraulic'")
    C = np.zeros((6 + n, n))
    C[0, :2] = [1.0, -1.0]
    C[1, :4] = model.A[2]
    C[1, iF] = inv_m
    C[2, iF] = 1.0
    C[3, 4:6] = hf.Cf
    C[4, :2] = [1.0, -1.0]
    C[5, 1] = 1.0
    C[6:] = np.eye(n)
    inputs = ["s"]
    B = Bs.reshape(n, 1)
    D = np.zeros((6 + n, 1))
    if noise:
        inputs += [f"w{i}" for i in range(n)] + ["v_r", "v_F"]
        B = np.hstack([B, np.eye(n), np.zeros((n, 2))])
        D = np.zeros((6 + n, 1 + n + 2))
        D[0, 1 + n] = 1.0
        D[2, 2 + n] = 1.0
    sys = control.ss(Ad, B, C, D, dt, inputs=inputs,
                     outputs=[*PLANT_OUTPUTS, *[f"z{i}" for i in range(n)]], name="plant")
    return sys, Qw


def accel_sensor_ss(cfg: RigConfig, *, noise: bool = False) -> control.StateSpace:
    """The accelerometer low-pass of ``hil/sim/sensors.py`` (``a_true`` [+ ``v_a``] -> ``a``;
    the noise is added after the filter, as there)."""
    dt = cfg.sample_time_s
    wc = 2.0 * math.pi * cfg.sensors.accel_bandwidth_hz
    if wc >= 0.999 * math.pi / dt:
        lp = control.ss([], [], [], [[1.0]], dt)
    else:
        k = math.tan(wc * dt / 2.0)
        b, a = k / (1.0 + k), (k - 1.0) / (1.0 + k)
        lp = control.ss(control.tf([b, b], [1.0, a], dt))
    if noise:
        return control.ss(lp.A, np.hstack([lp.B, np.zeros((lp.nstates, 1))]), lp.C,
                          np.hstack([lp.D, [[1.0]]]), dt, inputs=["a_true", "v_a"],
                          outputs=["a"], name="accel")
    return control.ss(lp.A, lp.B, lp.C, lp.D, dt, inputs=["a_true"], outputs=["a"],
                      name="accel")


def _servo_rows(n: int, n0: int, cu: FloatArray, du: FloatArray, servo: ServoModel,
                A: FloatArray, B: FloatArray) -> None:
    """Rows of the spool model x̂_v (index n0), the feedforward's rate-filter state w
    (n0 + 1) and the pending commands (n0 + 2 ...) given fref = cu z + du [r, a, F]:
    s = kp (fref - F) - c (w + b r), applied = s_{k-D}, w+ = (1 - a) w - a b r."""
    D = servo.delay_ticks
    kp = servo.kp_per_n
    ff = servo.feedforward
    c, a_ff, b = ff.gain_s_per_m, ff.rate_filter_coeff, ff.rate_input_gain_per_s
    iw = n0 + 1
    p0 = n0 + 2
    s_c = kp * cu
    s_c[iw] -= c
    s_d = kp * du.copy()
    s_d[2] -= kp
    s_d[0] -= c * b
    if D == 0:
        ap_c, ap_d = s_c, s_d
    else:
        ap_c = np.zeros(n)
        ap_c[p0 + D - 1] = 1.0
        ap_d = np.zeros(3)
    a = servo.spool_decay
    A[n0] = (1.0 - a) * ap_c
    A[n0, n0] += a
    B[n0] = (1.0 - a) * ap_d
    A[iw, iw] = 1.0 - a_ff
    B[iw, 0] = -a_ff * b
    if D:
        A[p0] = s_c
        B[p0] = s_d
        for i in range(1, D):
            A[p0 + i, p0 + i - 1] = 1.0


def runtime_controller_ss(md: ModelDesign, parts: LoopParts, dt_s: float
                          ) -> control.StateSpace:
    """The runtime bank for model j alone: inputs ``r, a, Fm``, output ``fref_out``.
    States [x⁻ (4), xf (2), x̂_v, w, s_{k-1..k-D}]."""
    Phi, Gam, C, Dm = md.dfm.Phi, md.dfm.Gamma_u, md.fm.C, md.fm.D
    K, Ka, L, hf, servo = parts.K, parts.Ka, parts.L, parts.hf, parts.servo
    Kx, Kf = K[:4], K[4:6]
    nd = servo.delay_ticks
    n = 8 + nd
    ILC = np.eye(4) - L @ C
    cu = np.zeros(n)
    du = np.zeros(3)
    cu[:4] = -Kx @ ILC
    du[:2] = -Kx @ L
    du[2] = Kx @ L @ Dm - Ka[1]
    cu[4:6] = -Kf
    cu[6] = -Ka[0]
    cu[7:] = -Ka[2:]                    # w, then the pending commands
    A = np.zeros((n, n))
    B = np.zeros((n, 3))
    A[:4, :4] = Phi @ ILC
    B[:4, :2] = Phi @ L
    B[:4, 2] = Gam - Phi @ L @ Dm
    A[4:6, 4:6] = hf.Ad
    B[4:6, 1] = hf.Bd
    _servo_rows(n, 6, cu, du, servo, A, B)
    return control.ss(A, B, cu.reshape(1, n), du.reshape(1, 3), dt_s,
                      inputs=["r", "a", "Fm"], outputs=["fref_out"], name="ctrl")


def fullstate_controller_ss(parts: LoopParts, n_plant: int, dt_s: float
                            ) -> control.StateSpace:
    """LQ on the true plant state (hydraulic plant: [x, xf, x_v, F] = ``z0..z7``) with the
    runtime's own rate-filter state w (on the measured rattlespace ``r``) and pending
    spool commands: the estimation-free bound of the LQG loop.  States [w, pending]."""
    if n_plant != 8:
        raise ValueError("the full-state loop needs the hydraulic plant (8 states)")
    servo = parts.servo
    ff = servo.feedforward
    c, a_ff, b = ff.gain_s_per_m, ff.rate_filter_coeff, ff.rate_input_gain_per_s
    nd = servo.delay_ticks
    n = 1 + nd
    k_state = np.concatenate([parts.K, parts.Ka[:2]])     # on z0..z7
    # inputs [z0..z7, r]; fref = -k_state z - K_w w - Kp p
    cu = -parts.Ka[2:].copy()
    dz = np.zeros(9)
    dz[:8] = -k_state
    A = np.zeros((n, n))
    Bz = np.zeros((n, 9))
    A[0, 0] = 1.0 - a_ff
    Bz[0, 8] = -a_ff * b
    if nd:                              # s = kp (fref - F) - c (w + b r)
        kp = servo.kp_per_n
        A[1] = kp * cu
        A[1, 0] -= c
        Bz[1] = kp * dz
        Bz[1, 7] -= kp
        Bz[1, 8] -= c * b
        for i in range(1, nd):
            A[1 + i, i] = 1.0
    return control.ss(A, Bz, cu.reshape(1, n), dz.reshape(1, 9), dt_s,
                      inputs=[*[f"z{i}" for i in range(8)], "r"], outputs=["fref_out"],
                      name="ctrl")


def force_loop_ss(fl: ForceLoopConfig, ff: FlowFeedforward, dt_s: float
                  ) -> control.StateSpace:
    """The force loop of ``controller/runtime/force_loop.py`` (unsaturated, feedforward at zero
    load pressure): ``fref, Fm, r`` -> ``s_pi``.  States [I, w]:
    s = kp e + ki (I + e T) - c (w + b r), I+ = I + e T, w+ = (1 - a) w - a b r."""
    kp, ki = fl.kp_per_n, fl.ki_per_ns
    g = kp + ki * dt_s
    c, a_ff, b = ff.gain_s_per_m, ff.rate_filter_coeff, ff.rate_input_gain_per_s
    A = np.array([[1.0, 0.0], [0.0, 1.0 - a_ff]])
    B = np.array([[dt_s, -dt_s, 0.0], [0.0, 0.0, -a_ff * b]])
    C = np.array([[ki, -c]])
    D = np.array([[g, -g, -c * b]])
    return control.ss(A, B, C, D, dt_s, inputs=["fref", "Fm", "r"], outputs=["s_pi"],
                      name="pi")


def delay_ss(ticks: int, dt_s: float, inp: str, out: str) -> control.StateSpace:
    """z^-ticks from ``inp`` to ``out``."""
    if ticks < 0:
        raise ValueError(f"delay ticks must be >= 0, got {ticks}")
    name = f"delay_{inp}_{out}"
    if ticks == 0:
        return control.ss([], [], [], [[1.0]], dt_s, inputs=[inp], outputs=[out], name=name)
    A = np.eye(ticks, k=-1)
    B = np.zeros((ticks, 1))
    B[0, 0] = 1.0
    C = np.zeros((1, ticks))
    C[0, -1] = 1.0
    return control.ss(A, B, C, [[0.0]], dt_s, inputs=[inp], outputs=[out], name=name)


def connect(blocks: list[control.StateSpace], inputs: list[str], outputs: list[str]
            ) -> control.StateSpace:
    """The blocks joined by signal name, as ``control.interconnect(blocks, inplist=inputs,
    outlist=outputs)`` joins them: a block input takes the block output of the same name,
    an external input in ``inputs`` drives every block input of its name, ``outputs``
    are block outputs; states in block order.  Built with ``control.append`` and one
    static positive feedback u = w + M y (``StateSpace.feedback``: matrix algebra),
    where interconnect linearises the joined system numerically, 15 ms against 1 ms
    for the rig's loops (`rig design` summarises 1134 of them).  Raises ``ValueError``
    for a name that is not an output of exactly one block."""
    in_names = [n for b in blocks for n in b.input_labels]
    out_names = [n for b in blocks for n in b.output_labels]
    out_index: dict[str, int] = {}
    for j, name in enumerate(out_names):
        if name in out_index:
            raise ValueError(f"signal {name!r} is the output of two blocks")
        out_index[name] = j
    joined = control.append(*blocks)
    M = np.zeros((len(in_names), len(out_names)))
    for i, name in enumerate(in_names):
        if name in out_index and name not in inputs:
            M[i, out_index[name]] = 1.0
    closed = joined.feedback(control.ss([], [], [], M, joined.dt), sign=1)
    E = np.zeros((len(in_names), len(inputs)))
    for k, name in enumerate(inputs):
        for i, block_input in enumerate(in_names):
            if block_input == name:
                E[i, k] = 1.0
    S = np.zeros((len(outputs), len(out_names)))
    for k, name in enumerate(outputs):
        if name not in out_index:
            raise ValueError(f"signal {name!r} is no block's output")
        S[k, out_index[name]] = 1.0
    return control.ss(closed.A, closed.B @ E, S @ closed.C, S @ closed.D @ E, joined.dt)


def lqg_loop_gain(cfg: RigConfig, md: ModelDesign, weights: list[float],
                  actuator: Actuator = "hydraulic", delay_ticks: int = 0,
                  outer_delay_ticks: int = 0) -> control.StateSpace:
    """Loop gain at the force reference (negative feedback: the closed loop is
    ``control.feedback(L, 1)``).  ``delay_ticks`` sit between the PI and the valve
    (inside the force loop, as in ``hil/sim/closed_loop.py``; for the ideal actuator between the
    command and the force); ``outer_delay_ticks`` only on the force reference."""
    dt = cfg.sample_time_s
    parts = loop_parts(cfg, md, weights)
    plant, _ = rig_plant_ss(md, cfg, actuator)
    blocks = [plant, accel_sensor_ss(cfg), runtime_controller_ss(md, parts, dt),
              delay_ss(outer_delay_ticks, dt, "u", "fref")]
    if actuator == "ideal":
        blocks.append(delay_ss(delay_ticks, dt, "fref", "s"))
    else:
        blocks += [force_loop_ss(cfg.force_loop, flow_feedforward(cfg), dt),
                   delay_ss(delay_ticks, dt, "s_pi", "s")]
    return -connect(blocks, ["u"], ["fref_out"])


def force_loop_gain(cfg: RigConfig, md: ModelDesign, delay_ticks: int = 0
                    ) -> control.StateSpace:
    """Loop gain of the PI force loop alone (outer loop open), broken at the spool
    command, with the quarter car of model j attached (velocity coupling) and the flow
    feedforward of the measured rattlespace (linearised at zero load pressure)."""
    dt = cfg.sample_time_s
    fl = cfg.force_loop
    # c = -(spool) for a zero force reference: PI(+Fm) - s_ff(r)
    fwd = force_loop_ss(fl, flow_feedforward(cfg), dt)
    pi_fb = control.ss(fwd.A, fwd.B[:, 1:], -fwd.C, -fwd.D[:, 1:], dt, inputs=["Fm", "r"],
                       outputs=["c"], name="pi")
    plant, _ = rig_plant_ss(md, cfg, "hydraulic")
    return connect([plant, pi_fb, delay_ss(delay_ticks, dt, "s_in", "s")], ["s_in"], ["c"])


def crossovers(L: control.StateSpace, n_points: int = 4000) -> list[Crossover]:
    """Every gain crossover of the discrete loop gain L up to Nyquist (log grid, refined
    by bisection), with its phase margin in [0, 360) degrees and delay margin PM / w."""
    dt = float(L.dt)
    w = np.logspace(-1.0, math.log10(math.pi / dt) - 1e-9, n_points)

    def mag_minus_one(wi: float) -> float:
        return abs(complex(L(np.exp(1j * wi * dt)))) - 1.0

    f = np.abs(np.asarray(L(np.exp(1j * w * dt))).reshape(-1)) - 1.0
    out = []
    for i in np.flatnonzero(np.sign(f[:-1]) * np.sign(f[1:]) < 0):
        lo, hi = w[i], w[i + 1]
        flo = f[i]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            fm = mag_minus_one(mid)
            if np.sign(fm) == np.sign(flo):
                lo, flo = mid, fm
            else:
                hi = mid
        wc = 0.5 * (lo + hi)
        pm = (math.pi + float(np.angle(complex(L(np.exp(1j * wc * dt)))))) % (2 * math.pi)
        out.append(Crossover(wc / (2 * math.pi), math.degrees(pm), pm / wc))
    return out


def delay_margin_s(L: control.StateSpace) -> float:
    """Smallest delay margin over the crossovers [s]; inf without a crossover, 0 if the
    closed loop ``feedback(L, 1)`` is already unstable."""
    if not closed_loop_stable(L):
        return 0.0
    return min((c.delay_margin_s for c in crossovers(L)), default=math.inf)


def closed_loop_stable(L: control.StateSpace) -> bool:
    cl = control.feedback(L, 1)
    return bool(np.max(np.abs(np.linalg.eigvals(cl.A))) < 1.0)
