"""Issue 11 estimator fixes, each against an independent reference: the compensator's DC
gain with and without the rattlespace-bias state (a linear solve on the design matrices),
the closed-loop stability of soft plants (eigenvalues of the assembled linear loop), and
the airborne model's part in Bayes blending (the piecewise-linear quarter car of
tests/support/reference_bank.py, whose contact flag is the truth)."""

from __future__ import annotations

import numpy as np
import pytest

from controller.artifact import Design
from controller.config import RigConfig, default_config, load_config
from controller.design import design_bank
from controller.human_filter import discretize_zoh
from controller.plant import linear_model, static_tire_deflection_m, tire_damping_ns_per_m
from controller.road_noise import nearest_noise_entry
from controller.runtime.bank import BankRuntime, Blending, default_single_model
from tests.support.profiles import THESIS_PROFILE as PROFILE
from tests.support.trajectories import trajectory

CFG = default_config()
THESIS = load_config(PROFILE)
K_NOM = CFG.vehicle.suspension_stiffness_n_per_m


@pytest.fixture(scope="module")
def designs(default_design: Design) -> dict[str, tuple[RigConfig, Design]]:
    return {"default": (CFG, default_design), "thesis": (THESIS, design_bank(THESIS))}


def _parts(cfg: RigConfig, d: Design, ws: int) -> dict[str, np.ndarray]:
    j = default_single_model(d, cfg)
    s = nearest_noise_entry(d.noise_speeds_mps, d.noise_roughness_gd,
                            cfg.noise.nominal_speed_mps, cfg.noise.nominal_roughness_gd)
    return {"A": d.filter_A[j, s], "By": d.filter_By[j, s], "Bu": d.filter_Bu[j, s],
            "L": d.kalman_gain[j, s], "Lb": d.bias_gain[j, s], "C": d.C_meas[j],
            "D": d.D_meas[j], "Kx": d.lq_gain[ws - 1, j, :4],
            "kf": d.actuator_gain[ws - 1, j, 1]}


def dc_gain(cfg: RigConfig, d: Design, ws: int = 1) -> float:
    """Steady force per metre of constant LVDT reading (acceleration 0, measured force =
    reference as the PI's integrator makes it): the fixed point of the single-model
    compensator, x = A x + By (y - b e0) + Bu u, Lb r = 0 (a bias state holds still only
    when its innovation is zero), u = -Kx x+ - kf u."""
    p = _parts(cfg, d, ws)
    A, By, Bu, L, C, D, Kx = p["A"], p["By"], p["Bu"], p["L"], p["C"], p["D"], p["Kx"]
    has_bias = bool(np.any(p["Lb"][0] != 0.0))
    # unknowns z = [x (4), b_r, u]; reading y = [1, 0] (per metre)
    M, rhs = np.zeros((6, 6)), np.zeros(6)
    M[:4, :4] = np.eye(4) - A
    M[:4, 4] = By[:, 0]
    M[:4, 5] = -Bu
    rhs[:4] = By[:, 0]
    # r = y - b e0 - C x - D u
    if has_bias:
        lb = p["Lb"][0]
        M[4, :4] = -lb @ C
        M[4, 4] = -lb[0]
        M[4, 5] = -lb @ D
        rhs[4] = -lb[0]
    else:
        M[4, 4] = 1.0                       # no bias state: b_r = 0
    # u (1 + kf) + Kx (x + L r) = 0
    M[5, :4] = Kx @ (np.eye(4) - L @ C)
    M[5, 4] = -Kx @ L[:, 0]
    M[5, 5] = 1.0 + p["kf"] - Kx @ L @ D
    rhs[5] = -Kx @ L[:, 0]
    return float(np.linalg.solve(M, rhs)[5])


def test_bias_state_removes_the_negative_spring(designs: dict[str, tuple[RigConfig, Design]]
                                               ) -> None:
    """Without a bias state (thesis profile, velocity leak 0.1 Hz) the LQG compensator
    holds a steady LVDT offset with a negative stiffness (-0.92 K with the gains of this
    tree): statically it cancels most of the suspension spring, so a plant softer than
    that has a negative net stiffness.  With the rattlespace-bias state the steady gain
    is 0 whatever the LQ gains: the static load is the spring's."""
    for ws in (1, 2):
        g_thesis = dc_gain(*designs["thesis"], ws)
        g_default = dc_gain(*designs["default"], ws)
        assert g_thesis < -0.1 * K_NOM, (ws, g_thesis / K_NOM)
        assert abs(g_default) < 1e-6 * K_NOM, (ws, g_default / K_NOM)


def closed_loop_radius(cfg: RigConfig, d: Design, k_scale: float, ws: int = 1) -> float:
    """Spectral radius (modes below 2 Hz) of the linear quarter car (tangent tire at the
    static deflection, K scaled, force = the reference of the previous tick) in closed
    loop with the single-model compensator (filter with its bias states, LQ state gain
    and measured-force gain; the human filter and spool model act at higher frequency)."""
    p = _parts(cfg, d, ws)
    v, t = cfg.vehicle, cfg.tire
    x2s = static_tire_deflection_m(cfg)
    kt = t.stiffness_exponent * t.stiffness_coefficient * 1000.0 * (1000.0 * x2s) ** (
        t.stiffness_exponent - 1.0)
    soft = type(v)(**{**v.__dict__, "suspension_stiffness_n_per_m": K_NOM * k_scale})
    lm = linear_model(soft, kt, tire_damping_ns_per_m(x2s, t))
    Phi, Gam = discretize_zoh(lm.A, lm.B2.reshape(4, 1), d.dt_s)
    # state [plant x (4), u_prev, filter x- (4), biases (2)]
    Y = np.zeros((2, 11))
    Y[:, :4], Y[:, 4] = lm.C_meas, lm.D_meas
    Um = np.zeros(11)
    Um[4] = 1.0
    Xm = np.zeros((4, 11))
    Xm[:, 5:9] = np.eye(4)
    B = np.zeros((2, 11))
    B[:, 9:] = np.eye(2)
    R = Y - B - p["C"] @ Xm - np.outer(p["D"], Um)
    T = np.zeros((11, 11))
    T[:4, :4], T[:4, 4] = Phi, Gam[:, 0]
    T[4] = -p["Kx"] @ (Xm + p["L"] @ R) - p["kf"] * Um
    T[5:9] = p["A"] @ Xm + p["By"] @ (Y - B) + np.outer(p["Bu"], Um)
    T[9:] = B + p["Lb"] @ R
    kept = [i for i in range(11) if i < 9 or np.any(p["Lb"][i - 9] != 0.0)]
    ev = np.linalg.eigvals(T[np.ix_(kept, kept)])     # a bias state not modelled: no state
    ev = ev[np.abs(np.angle(ev)) < 2.0 * np.pi * 2.0 * d.dt_s]
    return float(np.max(np.abs(ev)))


def test_soft_plants_keep_a_stable_slow_mode(designs: dict[str, tuple[RigConfig, Design]]
                                            ) -> None:
    """The slow real pole the negative spring creates: without the bias state a plant
    whose K is below the compensator's negative DC stiffness -G (0.92 K_nom here) has a
    real closed-loop pole above 1; with the bias state the same plants, and one at half
    the nominal stiffness, are stable (and both are at K_nom)."""
    k_crit = -dc_gain(*designs["thesis"], 1) / K_NOM
    for k in (0.95 * k_crit, 0.8 * k_crit):
        assert closed_loop_radius(*designs["thesis"], k) > 1.0 + 1e-6, k
        assert closed_loop_radius(*designs["default"], k) < 1.0, k
    assert closed_loop_radius(*designs["default"], 0.5) < 1.0
    assert closed_loop_radius(*designs["thesis"], 1.0) < 1.0 + 1e-9
    assert closed_loop_radius(*designs["default"], 1.0) < 1.0


@pytest.mark.parametrize("seed", [7, 8])
def test_airborne_model_takes_part_in_bayes_blending(
        designs: dict[str, tuple[RigConfig, Design]], seed: int) -> None:
    """The piecewise-linear quarter car loses contact for 20-30 ms when the road drops:
    with the wheel-force noise of the default design the airborne filter tracks the
    relative motion (q ~ 1 in the air, ~1e2 on the ground) and takes most of the MMAE
    probability while the wheel is off the ground, little while it is on it.  The
    thesis-literal airborne filter (an open-loop predictor, q ~ 1e7) never takes part."""
    weights = {}
    for name in ("default", "thesis"):
        cfg, d = designs[name]
        air = int(np.flatnonzero(d.airborne)[0])
        meas = trajectory(cfg, 2500, seed=seed, drop_at=1500)
        rt = BankRuntime(d, blending=Blending.BAYES, cfg=cfg)
        w, q = np.empty(2500), np.empty(2500)
        for k in range(2500):
            rt.step(meas["rattlespace"][k], meas["accel"][k], meas["force"][k])
            w[k], q[k] = rt.firing_weight[air], rt.q[air]
        contact = meas["contact"]
        assert 20 <= int(np.sum(~contact)) <= 40
        weights[name] = (w[contact].mean(), w[~contact].mean(), np.median(q[contact]),
                         np.median(q[~contact]))
    ground, flight, q_ground, q_flight = weights["default"]
    assert flight > 0.3 and ground < 0.01
    assert q_flight < 3.0 < 30.0 < q_ground
    assert max(weights["thesis"][:2]) < 1e-3 and weights["thesis"][3] > 1e5


def test_bias_augmented_gains_match_python_control_dlqe() -> None:
    """The steady-state filter with random-walk measurement biases: python-control's
    dlqe on the augmented model built here gives the same predictor gain Phi_a L_a."""
    import control

    from controller.design import design_models, measurement_noise_cov
    from controller.kalman import steady_state_kalman
    from controller.road_noise import road_velocity_intensity

    dt = CFG.sample_time_s
    w = road_velocity_intensity(CFG.noise.nominal_speed_mps, CFG.noise.nominal_roughness_gd)
    R = measurement_noise_cov(CFG)
    qb = np.array([3e-5 ** 2, 1e-3 ** 2]) * dt
    for md in design_models(CFG)[:3]:
        Qd = md.dfm.Qd_unit * w
        kf = steady_state_kalman(md.dfm.Phi, md.fm.C, Qd, R, qb)
        Phi_a = np.eye(6)
        Phi_a[:4, :4] = md.dfm.Phi
        C_a = np.hstack([md.fm.C, np.eye(2)])
        Q_a = np.zeros((6, 6))
        Q_a[:4, :4], Q_a[4, 4], Q_a[5, 5] = Qd, qb[0], qb[1]
        L_pred, _, _ = control.dlqe(Phi_a, np.eye(6), C_a, Q_a, R)
        L_meas = np.vstack([kf.L, kf.L_bias])
        np.testing.assert_allclose(Phi_a @ L_meas, L_pred, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize(("section", "key", "value"), [
    ("design", "filter_rattlespace_bias_drift", -1e-4),
    ("design", "filter_accel_bias_drift", 1e3),
    ("design", "accel_mean_window_s", -1.0),
    ("design", "bump_stop_centre_lvdt_m", 0.6),
    ("design", "bump_stop_filter_input", 1),
    ("design", "airborne_filter_wheel_force_intensity", -1.0),
    ("fuzzy", "statistic", "windowed"),
    ("fuzzy", "window_s", 11.0)])
def test_bad_estimator_settings_name_the_key(section: str, key: str, value: object) -> None:
    from controller.config import ConfigError
    with pytest.raises(ConfigError, match=f"{section}.{key}"):
        CFG.replace(**{section: {key: value}})
