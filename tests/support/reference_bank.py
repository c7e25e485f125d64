"""A plain-numpy second implementation of the bank step, for tests (slow, allocates).

Written straight from the thesis equations rather than from the fused kernel:

    F_j = innovation_cov (3.3), inverted here with ``np.linalg.inv``
    r_j = y - C_j x⁻_j - D_j u - y_offset                      (3.9)
    q_j = r_j' F_j^-1 r_j                                      (4.8)
    x⁺_j = x⁻_j + L_j r_j                                      (3.5)
    x⁻_j(next) = Φ_j x⁺_j + Γu_j u + Γg_j g                    (3.7)
    u_j = -K_j [x⁺_j - x̄_j; x_f; x̂_v; u; w; s_pending]         (LQ, App. A per model)
    x̂_v, w, s_pending: the spool model of controller/actuator.py on the blended output,
        w the force loop's rate filter (``FlowFeedforward.step``, plain Python)
    p_j: densities of Eq. 4.6 into Eq. 4.2 (:func:`bayes_update_numpy` here)
    f_j: ``np.interp`` on the App. A firing-weight table

and the moving-bank rules of :mod:`controller.runtime.moving_bank` re-implemented with Python
lists, a decaying numpy histogram and the two tire-load CUSUMs written as Page's
recursion g = max(0, g + increment).  Semantics (flags, fallbacks, bumpless starts)
follow docs/architecture.md "Runtime step" and :mod:`controller.runtime.bank`.
"""

from __future__ import annotations

import math

import numpy as np

from controller.actuator import FlowFeedforward
from controller.arrays import FloatArray
from controller.artifact import Design
from controller.config import RigConfig
from controller.monitor import monitor_settings
from controller.road_noise import nearest_noise_entry
from controller.runtime import moving_bank
from controller.runtime.kernels import MEAS_DIM, Q_MAX, QS_INIT, Blending, StepFlag
from controller.stop_contact import contact_time_update, stop_contact_settings
from controller.stop_guard import stop_guard_scale

__all__ = ["ReferenceBank", "bayes_update_numpy"]


def bayes_update_numpy(p_prev: FloatArray, q: FloatArray,
                       logdet_f: FloatArray, meas_dim: int,
                       floor: float) -> FloatArray:
    """The Bayesian probability update written directly from Eq. 4.2/4.6 (the reference
    of :func:`controller.runtime.bayes.bayes_update`).

    Uses the densities themselves where they do not underflow, so it is an independent
    check of the log-space kernel.
    """
    dens = np.exp(-0.5 * q) / ((2.0 * np.pi) ** (meas_dim / 2.0) * np.sqrt(np.exp(logdet_f)))
    num = dens * p_prev
    total = float(np.sum(num))
    if not total > 1e-200:             # densities underflow: use logs (p_prev floor-free)
        logs = np.log(np.maximum(p_prev, 1e-300)) - 0.5 * q - 0.5 * logdet_f
        logs -= np.max(logs)
        num = np.exp(logs)
        total = float(np.sum(num))
    p = num / total
    p = np.maximum(p, floor)
    return np.asarray(p / np.sum(p), dtype=np.float64)


def kernel_cfg(design: Design, cfg: RigConfig | None = None) -> RigConfig:
    """The configuration for the numba bank run beside :class:`ReferenceBank` (``cfg``, or
    the design's): the stop clamp with the road at rest off
    (``design.stop_clamp_road_at_rest``), which the reference does not have; the clamp
    is checked against python-control and on the nonlinear rig in
    tests/test_preview_clamp.py."""
    from controller.runtime.bank import config_of

    base = cfg if cfg is not None else config_of(design)
    return base.replace(design={"stop_clamp_road_at_rest": False})


class ReferenceBank:
    """Same constructor and ``step`` contract as :class:`controller.runtime.bank.BankRuntime`."""

    def __init__(self, design: Design, blending: Blending | int = Blending.FUZZY,
                 weight_set: int = 1, single_model: int | None = None, *,
                 cfg: RigConfig | None = None) -> None:
        from controller.runtime.bank import config_of, default_single_model

        d = design
        self.d = d
        self.cfg = cfg if cfg is not None else config_of(d)
        c = self.cfg
        self.J = d.n_models
        dt = d.dt_s
        self.g = -float(d.y_offset[1])
        self.fallback = c.fuzzy.no_fire_fallback
        self.floor = c.bayes.probability_floor
        self.single = default_single_model(d, c) if single_model is None else int(single_model)
        self.xinit = d.equilibrium[self.single].copy()
        self.xbar = np.where(np.isfinite(d.equilibrium), d.equilibrium, self.xinit[None, :])
        self.ground = [j for j in range(self.J) if not d.airborne[j]]
        airs = [j for j in range(self.J) if d.airborne[j]]
        self.air = airs[0] if airs else -1
        mb = c.moving_bank
        self.k = min(mb.active_models, len(self.ground))
        tau = mb.smoothing_time_s
        self.alpha = 1.0 - math.exp(-dt / tau) if tau > 0.0 else 1.0
        fw = c.fuzzy.window_s
        self.beta = 1.0 - math.exp(-dt / fw) if fw > 0.0 else 1.0
        self.relative = c.fuzzy.statistic == "relative"
        aw = c.design.accel_mean_window_s
        self.amean_weight = 1.0 - math.exp(-dt / aw) if aw > 0.0 else 0.0
        self.mon = monitor_settings(c, dt, MEAS_DIM)
        self.stop_k, self.stop_lo, self.stop_hi = (float(v) for v in d.bump_stop)
        self.guard_width = c.design.stop_guard_m
        self.guard_lead_s = c.design.stop_guard_lead_s
        self.guard_deadband_mps = c.design.stop_guard_lead_deadband_mps
        self.sc = stop_contact_settings(c, dt)
        self.t_floor = moving_bank.chi2_threshold_floor(mb.threshold_quantile, MEAS_DIM)
        self.load_off = mb.liftoff_load_fraction               # lift-off reference
        self.load_on = mb.liftoff_load_fraction / mb.hysteresis_ratio   # touch-down reference
        self.cusum_h = mb.liftoff_load_fraction * max(1, round(mb.liftoff_detection_time_s / dt))
        self.load_step = max(1, round(mb.load_estimate_window_s / dt))      # Δ [ticks]
        veh = c.vehicle
        self.mass_sprung, self.mass_unsprung = veh.sprung_mass_kg, veh.unsprung_mass_kg
        self.gravity = veh.gravity_mps2
        self.quant = mb.threshold_quantile
        n_window = max(2.0, mb.history_window_s / dt)
        self.lam = 1.0 - 1.0 / n_window
        self.min_learn = max(1, int(n_window // 4))
        self.dwell = max(1, round(mb.dwell_time_s / dt))
        self.probe_ticks = max(1, round(c.moving_bank.probe_period_s / dt))
        self.nprobe = max(0, min(len(self.ground) - self.k, moving_bank.MAX_PROBE_CANDIDATES))
        self.width = (moving_bank.HIST_HI_LOG10 - moving_bank.HIST_LO_LOG10) / moving_bank.HIST_BINS
        self.order = self._neighbours()
        self.s = nearest_noise_entry(d.noise_speeds_mps, d.noise_roughness_gd,
                                     c.noise.nominal_speed_mps, c.noise.nominal_roughness_gd)
        self.w = int(weight_set)
        self.blending = Blending(int(blending))
        c_ff, a_ff, stall, floor = (float(v) for v in d.servo_model[5:9])
        self.ff = FlowFeedforward(c_ff, a_ff, float(dt), stall, floor)
        self.reset()

    def _neighbours(self) -> dict[int, list[int]]:
        gi = self.d.grid_index
        out: dict[int, list[int]] = {}
        for c in self.ground:
            dist = {j: (int((gi[j, 0] - gi[c, 0]) ** 2 + (gi[j, 1] - gi[c, 1]) ** 2),
                        int(abs(gi[j, 1] - gi[c, 1])), j) for j in self.ground}
            out[c] = sorted(self.ground, key=dist.__getitem__)
        return out

    # ------------------------------------------------------------------ state handling
    def reset(self) -> None:
        J = self.J
        self.x_prior = self.xbar.copy()
        self.x_post = self.xbar.copy()
        self.q = np.zeros(J)
        self.wt = np.zeros(J)
        self.f = np.zeros(J)
        self.p = np.zeros(J)
        self.u = np.zeros(J)
        self.qs = np.full(J, QS_INIT)
        self.qw = np.full(J, QS_INIT)
        self.bias = np.zeros((J, 2))          # [rattlespace, acceleration] bias per model
        self.bias_blend = np.zeros(2)
        self.accel_mean = 0.0
        self.window: list[float] = []         # the monitor's last N values of min q
        self.monitor_ticks = 0
        self.degraded = False
        self.rearm_count = 0
        self.unusable_count = 0
        self.authority = 1.0
        self.n_degradations = 0
        self.stop_force = 0.0
        self.guard = 1.0
        self.contact_s = 0.0                  # stop-contact time in the window [s]
        self.contact_ticks: list[int] = []    # ticks with contact since reset
        self.stop_degraded = False
        self.stop_rearm_count = 0
        self.stop_authority = 1.0
        self.n_stop_degradations = 0
        self.tick = 0
        self.active = np.zeros(J, dtype=bool)
        self.xf = np.zeros(2)
        self.xv = 0.0
        self.rate_state = math.nan
        self.pending: list[float] = [0.0] * self.d.compute_delay_ticks
        self.xhat = self.xinit.copy()
        self.xhatm = self.xinit.copy()
        self.xdev = np.zeros(4)
        self.xdevm = np.zeros(4)
        self.thresh = self.t_floor
        self.hist = np.zeros(moving_bank.HIST_BINS)
        self.nlearn = 0
        self.load = 1.0
        self.g_off = self.g_on = 0.0
        self.n_lift_load = 0
        self.samples: list[tuple[float, float]] = []      # (rattlespace, accel), newest last
        self.mode_air = False
        self.sentinel = -1
        self.centre = self.single
        self.since_switch = self.since_recentre = 0
        self.probe_ptr = self.probe_cnt = 0
        self.flags = StepFlag(0)
        self.n_updates = 0
        self.set_blending(self.blending)
        self.x_prior = self.xbar.copy()
        self.x_post = self.xbar.copy()
        n = int(self.active.sum())
        self.p = np.where(self.active, 1.0 / n, 0.0)
        self.qs = np.full(J, QS_INIT)
        self.qw = np.full(J, QS_INIT)
        self.bias = np.zeros((J, 2))

    def _activate(self, j: int, qs0: float, p0: float) -> None:
        self.active[j] = True
        self.x_prior[j] = self.xbar[j] + self.xdevm
        self.x_post[j] = self.xbar[j] + self.xdev
        self.bias[j] = self.bias_blend
        self.qs[j] = qs0
        self.qw[j] = qs0
        self.p[j] = p0
        self.q[j] = self.wt[j] = self.u[j] = self.f[j] = 0.0

    def _deactivate(self, j: int) -> None:
        self.active[j] = False
        self.q[j] = self.wt[j] = self.p[j] = self.u[j] = self.f[j] = 0.0

    def set_blending(self, blending: Blending | int) -> None:
        b = Blending(int(blending))
        self.blending = b
        self.mode_air = False
        self.sentinel = -1
        if b == Blending.LQG:
            for j in range(self.J):
                if self.active[j] and j != self.single:
                    self._deactivate(j)
            if not self.active[self.single]:
                self._activate(self.single, QS_INIT, 1.0)
        elif b == Blending.MOVING:
            running = [j for j in self.ground if self.active[j]]
            centre = min(running, key=lambda j: self.qs[j]) if running else self.single
            self.since_switch = 0
            self.g_off = self.g_on = 0.0
            self.load = 1.0
            self.samples = []
            self._move_to(centre)
        else:
            for j in range(self.J):
                if not self.active[j]:
                    self._activate(j, QS_INIT, 1.0 / self.J)
        tot = self.p[self.active].sum()
        self.p[self.active] = self.p[self.active] / tot if tot > 0 else 1.0

    def set_road(self, speed_mps: float, roughness_gd: float) -> None:
        self.s = nearest_noise_entry(self.d.noise_speeds_mps, self.d.noise_roughness_gd,
                                     speed_mps, roughness_gd)

    def set_weight_set(self, w: int) -> None:
        self.w = int(w)

    # ------------------------------------------------------------------ the tick
    def step(self, rattlespace_m: float, accel_mps2: float, force_meas_n: float) -> float:
        d, s = self.d, self.s
        if not all(math.isfinite(v) for v in (rattlespace_m, accel_mps2, force_meas_n)):
            self.flags = StepFlag.NONFINITE_INPUT
            return 0.0
        flags = StepFlag(0)
        # bump-stop force from the LVDT reading, a known input like the load-cell force
        stop = 0.0
        if rattlespace_m > self.stop_hi:
            stop = self.stop_k * (rattlespace_m - self.stop_hi)
        elif rattlespace_m < self.stop_lo:
            stop = self.stop_k * (rattlespace_m - self.stop_lo)
        self.stop_force = stop
        accel = accel_mps2
        if self.amean_weight > 0.0:           # minus the running mean (the sensor's bias)
            self.accel_mean += self.amean_weight * (accel_mps2 - self.accel_mean)
            accel = accel_mps2 - self.accel_mean
        y_meas = np.array([rattlespace_m + d.static_rattlespace_m, accel])
        u_in = force_meas_n + stop
        e_min = math.inf
        moving = self.blending == Blending.MOVING
        sentinel = self.sentinel if (moving and self.mode_air) else -1
        contrib = np.zeros(self.J, dtype=bool)
        bad = np.zeros(self.J, dtype=bool)
        K = d.lq_gain[self.w - 1]
        if math.isnan(self.rate_state):
            self.rate_state = self.ff.initial_state(rattlespace_m)
        self.n_updates = int(self.active.sum())
        with np.errstate(all="ignore"):
            for j in np.flatnonzero(self.active):
                Finv = np.linalg.inv(d.innovation_cov[j, s])
                # the measurement-bias states enter the measurement equation additively
                y = y_meas - self.bias[j]
                r = y - d.C_meas[j] @ self.x_prior[j] - d.D_meas[j] * u_in - d.y_offset
                q = float(r @ Finv @ r)
                xp = self.x_prior[j] + d.kalman_gain[j, s] @ r
                xn = d.Phi[j] @ xp + d.Gamma_u[j] * u_in + d.Gamma_g[j] * self.g
                bn = self.bias[j] + d.bias_gain[j, s] @ r      # random walk: prior = posterior
                uj = 0.0 if d.airborne[j] else float(
                    -K[j] @ np.concatenate([xp - self.xbar[j], self.xf])
                    - d.actuator_gain[self.w - 1, j]
                    @ np.array([self.xv, force_meas_n, self.rate_state, *self.pending]))
                if math.isnan(q) or not (np.all(np.isfinite(xp)) and np.all(np.isfinite(xn))
                                         and np.all(np.isfinite(bn)) and math.isfinite(uj)):
                    bad[j] = True
                    self.q[j] = Q_MAX
                    self.u[j] = 0.0
                    flags |= StepFlag.NONFINITE_STATE
                    continue
                qc = min(q, Q_MAX)
                self.x_post[j], self.x_prior[j], self.bias[j] = xp, xn, bn
                self.q[j], self.u[j] = qc, uj
                self.qs[j] += self.alpha * (qc - self.qs[j])
                self.qw[j] += self.beta * (qc - self.qw[j])
                contrib[j] = j != sentinel
                if contrib[j]:
                    e_min = min(e_min, max(abs(r[0]) / self.mon.rattlespace_bound_m,
                                           abs(r[1]) / self.mon.accel_bound_mps2))
        # probabilities (Eq. 4.2 / 4.6), kept in every mode
        if contrib.any():
            self.p[contrib] = bayes_update_numpy(self.p[contrib], self.q[contrib],
                                                 d.innovation_logdet[contrib, s], MEAS_DIM,
                                                 self.floor)
        self.p[~contrib] = 0.0
        stat = self.qw if self.relative else self.q
        s_min = float(np.min(stat[contrib])) if contrib.any() else math.inf
        if self.relative:      # relative to the best, scaled to a matched filter's mean m
            with np.errstate(all="ignore"):
                x = MEAS_DIM * stat / s_min if s_min > 0.0 else np.where(stat > 0.0, Q_MAX, 0.0)
        else:
            x = self.q
        f = np.interp(x, d.fuzzy_q_grid, d.fuzzy_weight_curve)
        f = np.where(np.isfinite(f), np.clip(f, 0.0, 1.0), 0.0)
        self.f = np.where(contrib, f, 0.0)
        if self.blending == Blending.BAYES:
            w = self.p.copy()
        elif self.blending == Blending.LQG:
            w = contrib.astype(float)
        else:
            w = self.f.copy()
        w[~contrib] = 0.0
        best = int(np.argmin(np.where(contrib, stat, np.inf))) if contrib.any() else -1
        if w.sum() > 0.0:
            w = w / w.sum()
        elif best >= 0:
            flags |= StepFlag.NO_RULE_FIRED
            if self.fallback == "best_model":
                w[best] = 1.0
        self.wt = w
        out = float(w @ self.u)
        we = w.copy()
        if we.sum() == 0.0 and best >= 0:
            we[best] = 1.0            # the estimate of the best model, even when passive
        if we.sum() > 0.0:
            self.xhat, self.xhatm = we @ self.x_post, we @ self.x_prior
            self.xdev = we @ (self.x_post - self.xbar)
            self.xdevm = we @ (self.x_prior - self.xbar)
            self.bias_blend = we @ self.bias
        for j in np.flatnonzero(bad):
            x = self.xbar[j] + self.xdevm if we.sum() > 0.0 else self.xbar[j].copy()
            self.x_prior[j] = x
            self.x_post[j] = x
            self.bias[j] = self.bias_blend if we.sum() > 0.0 else np.zeros(2)
        qmin = float(np.min(self.q[contrib])) if contrib.any() else math.inf
        flags |= self._monitor(qmin, e_min)
        with np.errstate(all="ignore"):
            xf = d.human_filter_Ad @ self.xf + d.human_filter_Bd * accel_mps2
        if np.all(np.isfinite(xf)):
            self.xf = xf
        else:
            self.xf = np.zeros(2)
            flags |= StepFlag.NONFINITE_STATE
        flags |= self._stop_contact(rattlespace_m)
        out *= self.authority * self.stop_authority
        self.guard = stop_guard_scale(out, rattlespace_m, self.stop_lo, self.stop_hi,
                                      self.guard_width,
                                      self.ff.rate_mps(self.rate_state, rattlespace_m),
                                      self.guard_lead_s, self.guard_deadband_mps)
        out *= self.guard
        if not math.isfinite(out):
            out = 0.0
            flags |= StepFlag.NONFINITE_STATE
        self._servo(out, force_meas_n, rattlespace_m)
        if moving:
            self._tire_load_update(rattlespace_m, accel_mps2)
            self._supervise()
        self.flags = flags
        self.tick += 1
        return out

    def _stop_contact(self, rattlespace_m: float) -> StepFlag:
        """controller/stop_contact.py: contact beyond a stop less the band, the window's
        contact time, episodes by the gap since the last contact tick, degrade / re-arm
        and the authority ramp toward the travel-conservative law."""
        sc, flags = self.sc, StepFlag(0)
        contact = (rattlespace_m > self.stop_hi - sc.band_m
                   or rattlespace_m < self.stop_lo + sc.band_m)
        self.contact_s = contact_time_update(self.contact_s, contact, sc)
        if contact:
            self.contact_ticks.append(self.tick)
        if self.contact_ticks and self.tick - self.contact_ticks[-1] < sc.episode_gap_ticks:
            flags |= StepFlag.STOP_CONTACT
        if not self.stop_degraded:
            if sc.degrade and self.contact_s > sc.budget_s:
                self.stop_degraded = True
                self.stop_rearm_count = 0
                self.n_stop_degradations += 1
        elif self.contact_s < sc.rearm_level_s:
            self.stop_rearm_count += 1
            if self.stop_rearm_count >= sc.rearm_ticks:
                self.stop_degraded = False
        else:
            self.stop_rearm_count = 0
        step = self.mon.authority_step
        if self.stop_degraded:
            flags |= StepFlag.STOP_DEGRADED
            self.stop_authority = max(sc.authority, self.stop_authority - step)
        else:
            self.stop_authority = min(1.0, self.stop_authority + step)
        return flags

    def _monitor(self, q_min: float, e_min: float) -> StepFlag:
        """controller/monitor.py written with a Python list as the window: the sum of the
        last N values of min q against the degrade / re-arm levels; every model's
        innovation beyond a sensor range for N ticks = DIVERGED; authority ramps."""
        m = self.mon
        flags = StepFlag(0)
        self.monitor_ticks += 1
        if self.monitor_ticks <= m.window_ticks:      # settling after a reset
            return self._authority_step(flags)
        self.window.append(min(q_min, Q_MAX))
        if len(self.window) > m.window_ticks:
            self.window.pop(0)
        if len(self.window) == m.window_ticks:
            total = math.fsum(self.window)
            if not self.degraded:
                if total > m.degrade_sum:
                    self.degraded = True
                    self.rearm_count = 0
                    self.n_degradations += 1
            elif total < m.rearm_sum:
                self.rearm_count += 1
                if self.rearm_count >= m.rearm_ticks:
                    self.degraded = False
            else:
                self.rearm_count = 0
        self.unusable_count = self.unusable_count + 1 if e_min > 1.0 else 0
        if self.unusable_count >= m.window_ticks:
            flags |= StepFlag.DIVERGED
        return self._authority_step(flags)

    def _authority_step(self, flags: StepFlag) -> StepFlag:
        m = self.mon
        if self.degraded:
            flags |= StepFlag.DEGRADED
            self.authority = max(0.0, self.authority - m.authority_step)
        else:
            self.authority = min(1.0, self.authority + m.authority_step)
        return flags

    def _servo(self, force_ref_n: float, force_meas_n: float, rattlespace_m: float) -> None:
        """Spool model (controller/actuator.py): the PI's proportional command plus the
        flow feedforward, delayed by D ticks, through the first-order spool."""
        decay, kp, flim, olim = (float(v) for v in self.d.servo_model[:4])
        s_ff, self.rate_state = self.ff.step(self.rate_state, rattlespace_m, force_meas_n)
        s = float(np.clip(kp * (float(np.clip(force_ref_n, -flim, flim)) - force_meas_n)
                          + s_ff, -olim, olim))
        self.pending.insert(0, s)
        applied = self.pending.pop()
        self.xv = decay * self.xv + (1.0 - decay) * applied

    # ------------------------------------------------------------------ moving bank
    def _normalise_p(self) -> None:
        tot = float(self.p[self.active].sum())
        n = int(self.active.sum())
        self.p[self.active] = self.p[self.active] / tot if tot > 0.0 else 1.0 / n

    def _move_to(self, centre: int) -> None:
        keep = self.order[centre][: self.k]
        qs0 = self.qs[centre]
        for j in range(self.J):
            if self.active[j] and j not in keep:
                self._deactivate(j)
        for j in keep:
            if not self.active[j]:
                self._activate(j, qs0, 1.0 / self.k)
        self._normalise_p()
        self.centre = centre
        self.since_recentre = 0
        self.probe_ptr = self.probe_cnt = 0

    def _quantile(self) -> float:
        tot = self.hist.sum()
        target = self.quant * tot
        cum = np.cumsum(self.hist)
        before = cum - self.hist
        ok = np.flatnonzero((self.hist > 0) & (cum >= target))
        if ok.size == 0:
            return float(10.0 ** moving_bank.HIST_HI_LOG10)
        b = int(ok[0])
        frac = (target - before[b]) / self.hist[b]
        return float(10.0 ** (moving_bank.HIST_LO_LOG10 + (b + frac) * self.width))

    def _tire_load_update(self, rattlespace_m: float, accel_mps2: float) -> None:
        """Tire force of tick k - Δ from the two masses' momentum balance,
        f_t = (M + m)(a + g) + m r'' (r'' central second difference over Δ ticks), over
        the static load (M + m) g; 1.0 while fewer than 2Δ + 1 samples are in."""
        d = self.load_step
        self.samples.append((float(rattlespace_m), float(accel_mps2)))
        if len(self.samples) > 2 * d + 1:
            self.samples.pop(0)
        if len(self.samples) < 2 * d + 1 or self.gravity <= 0.0:
            self.load = 1.0
            return
        m, mt, g, dt = self.mass_unsprung, self.mass_sprung + self.mass_unsprung, \
            self.gravity, self.d.dt_s
        r_new, (r_mid, a_mid), r_old = self.samples[-1][0], self.samples[d], self.samples[0][0]
        r_dd = (r_new - 2.0 * r_mid + r_old) / (d * dt) ** 2
        self.load = (mt * (a_mid + g) + m * r_dd) / (mt * g)

    def _supervise(self) -> None:
        self.since_switch += 1
        self.since_recentre += 1
        if not self.mode_air:
            running = [j for j in range(self.J) if self.active[j] and not self.d.airborne[j]]
            best = min(running, key=lambda j: self.qs[j])
            sig = float(self.qs[best])
            g = self.g_off + (self.load_off - self.load)
            self.g_off = g if g > 0.0 else 0.0
            settled = self.since_switch >= self.dwell
            if settled:
                lo = moving_bank.HIST_LO_LOG10
                b = int((math.log10(sig) - lo) / self.width) if sig > 0 else 0
                self.hist *= self.lam
                self.hist[min(max(b, 0), moving_bank.HIST_BINS - 1)] += 1.0
                self.nlearn += 1
                if (self.nlearn >= self.min_learn
                        and self.nlearn % moving_bank.HIST_RECOMPUTE_TICKS == 0):
                    self.thresh = max(self._quantile(), self.t_floor)
            by_load = self.g_off >= self.cusum_h
            by_residual = sig > self.thresh and self.g_off >= 0.5 * self.cusum_h
            if self.air >= 0 and settled and (by_load or by_residual):
                for j in range(self.J):
                    if self.active[j] and j != self.centre:
                        self._deactivate(j)
                self._activate(self.air, self.qs[self.centre], 1.0)
                self.p[self.centre] = 0.0
                self.wt[self.centre] = 0.0
                self.sentinel = self.centre
                self.mode_air = True
                self.since_switch = 0
                self.n_lift_load += int(by_load)
                self.g_on = 0.0
                return
            if best != self.centre and self.since_recentre >= self.dwell \
                    and self.qs[best] < moving_bank.RECENTRE_RATIO * self.qs[self.centre]:
                self._move_to(best)
                return
            if self.nprobe > 0 and self.k >= 2:
                self.probe_cnt += 1
                if self.probe_cnt >= self.probe_ticks:
                    self.probe_cnt = 0
                    for _ in range(self.nprobe):
                        cand = self.order[self.centre][self.k + self.probe_ptr % self.nprobe]
                        self.probe_ptr += 1
                        if not self.active[cand]:
                            others = [j for j in range(self.J)
                                      if self.active[j] and j != self.centre]
                            if others:
                                worst = max(others, key=lambda j: self.qs[j])
                                self._deactivate(worst)
                                self._activate(cand, self.qs[self.centre], 1.0 / self.k)
                                self._normalise_p()
                            break
        else:
            g = self.g_on + (self.load - self.load_on)
            self.g_on = g if g > 0.0 else 0.0
            if self.since_switch >= self.dwell and self.g_on >= self.cusum_h:
                self._deactivate(self.air)
                self.mode_air = False
                centre = self.sentinel
                self.sentinel = -1
                self.since_switch = 0
                self.g_off = 0.0
                self.xdev = self.x_post[centre] - self.xbar[centre]
                self.xdevm = self.x_prior[centre] - self.xbar[centre]
                self.bias_blend = self.bias[centre].copy()
                self.p[centre] = 1.0 / self.k       # rejoins the set like a newcomer
                self._move_to(centre)


# ============================================================================ test plant


def quarter_car_measurements(cfg: RigConfig, dt_s: float, road_velocity_mps: FloatArray,
                             force_n: FloatArray, rng: np.random.Generator, *,
                             deflection_m: float | None = None, damping_scale: float = 1.0,
                             noise: bool = True) -> dict[str, FloatArray]:
    """Measurements of a piecewise-linear quarter car (for tests of the bank).

    The tire is the secant spring/damper of the model linearised at ``deflection_m``
    (default: the static deflection) while it pushes (x2 > 0 and Kt x2 + Ct x2' > 0) and
    absent otherwise (lift-off); each tick uses the exact ZOH step of the current regime.
    Returns ``rattlespace`` (about static, like the LVDT), ``accel`` (zs''), ``force``,
    ``contact`` (bool) and the true states ``x`` (n, 4).
    """
    from controller.human_filter import discretize_zoh
    from controller.plant import (
        GRAVITY_INPUT,
        linear_model,
        static_tire_deflection_m,
        tire_damping_ns_per_m,
        tire_secant_stiffness_n_per_m,
    )

    v = cfg.vehicle
    x2j = static_tire_deflection_m(cfg) if deflection_m is None else deflection_m
    kt = tire_secant_stiffness_n_per_m(x2j, cfg.tire)
    ct = tire_damping_ns_per_m(x2j, cfg.tire) * damping_scale
    on = linear_model(v, kt, ct)
    off = linear_model(v, 0.0, 0.0)
    g = v.gravity_mps2
    steps = []
    for mdl in (on, off):
        Phi, Gam = discretize_zoh(mdl.A, np.column_stack([mdl.B2, mdl.B1, GRAVITY_INPUT]), dt_s)
        steps.append((Phi, Gam))
    assert on.equilibrium is not None
    x = on.equilibrium.copy()
    n = int(road_velocity_mps.shape[0])
    out = {"rattlespace": np.zeros(n), "accel": np.zeros(n), "force": np.asarray(force_n),
           "contact": np.zeros(n, dtype=bool), "x": np.zeros((n, 4))}
    static_rattle = v.sprung_mass_kg * g / v.suspension_stiffness_n_per_m
    for k in range(n):
        wdot = float(road_velocity_mps[k])
        u = float(force_n[k])
        contact = x[1] > 0.0 and kt * x[1] + ct * (wdot - x[3]) > 0.0
        mdl = on if contact else off
        out["contact"][k] = contact
        out["x"][k] = x
        acc = float(mdl.C_meas[1] @ x + mdl.D_meas[1] * u - g)
        out["rattlespace"][k] = x[0] - x[1] - static_rattle
        out["accel"][k] = acc
        Phi, Gam = steps[0] if contact else steps[1]
        x = Phi @ x + Gam @ np.array([u, wdot, g])
    if noise:
        out["rattlespace"] = out["rattlespace"] + rng.normal(0.0, cfg.noise.rattlespace_std_m, n)
        out["accel"] = out["accel"] + rng.normal(0.0, cfg.noise.accel_std_mps2, n)
    return out
