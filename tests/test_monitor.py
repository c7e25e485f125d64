"""The estimator monitor (controller/monitor.py and the bank's ``_monitor``): its levels
against a closed form, its false-alarm rate on a plant the filter matches, and config
validation of its keys."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats

from controller.config import ConfigError, default_config
from controller.design import design_bank
from controller.monitor import monitor_settings
from controller.runtime.bank import BankRuntime, Blending
from tests.support.trajectories import smooth_road_config, trajectory


def chi2_even_sf(x: float, dof: int) -> float:
    """P(chi2(dof) > x) for even dof = 2n: the Poisson sum e^{-x/2} sum_{k<n} (x/2)^k / k!
    (closed form, no scipy), in log space."""
    n = dof // 2
    h = 0.5 * x
    terms = [k * math.log(h) - math.lgamma(k + 1) - h for k in range(n)]
    top = max(terms)
    return math.exp(top) * math.fsum(math.exp(t - top) for t in terms)


@pytest.mark.parametrize(("window_s", "alpha", "c"), [(0.1, 1e-6, 1000.0), (0.02, 1e-3, 1.0),
                                                      (0.5, 1e-9, 30.0)])
def test_levels_are_the_chi_square_quantile_and_median(window_s: float, alpha: float,
                                                       c: float) -> None:
    cfg = default_config().replace(safety={"estimator_window_s": window_s,
                                           "estimator_false_alarm": alpha,
                                           "estimator_nis_inflation": c})
    m = monitor_settings(cfg, cfg.sample_time_s)
    n = round(window_s / cfg.sample_time_s)
    assert m.window_ticks == n and m.false_alarm == alpha
    assert chi2_even_sf(m.degrade_sum / c, 2 * n) == pytest.approx(alpha, rel=1e-6)
    assert chi2_even_sf(m.rearm_sum / c, 2 * n) == pytest.approx(0.5, rel=1e-9)
    assert m.rearm_sum < m.degrade_sum
    assert m.rattlespace_bound_m == cfg.sensors.lvdt_range_m
    assert m.accel_bound_mps2 == cfg.sensors.accel_range_mps2


def test_false_alarm_rate_on_a_matched_plant() -> None:
    """A plant the filter models exactly (the piecewise-linear quarter car of the single
    model, its road and sensor noise, no lift-off): q is chi2(2) (mean 2, variance 4),
    the sums over disjoint windows are chi2(2N) (Kolmogorov-Smirnov), and with the
    inflation 1 the degrade level is crossed in the stated fraction alpha of the ticks."""
    cfg = smooth_road_config().replace(safety={"estimator_nis_inflation": 1.0,
                                               "estimator_false_alarm": 0.01,
                                               "estimator_window_s": 0.05})
    d = design_bank(cfg)
    rt = BankRuntime(d, blending=Blending.LQG, cfg=cfg)
    n = 40_000
    meas = trajectory(cfg, n, seed=21)
    q = np.empty(n)
    s = np.empty(n)
    for k in range(n):
        rt.step(meas["rattlespace"][k], meas["accel"][k], meas["force"][k])
        q[k] = rt.q[rt.single_model]
        s[k] = rt.monitor_statistic * rt.monitor.window_ticks
    w = rt.monitor.window_ticks
    q, s = q[2000:], s[2000:]
    assert q.mean() == pytest.approx(2.0, rel=0.03)
    assert q.var() == pytest.approx(4.0, rel=0.06)
    disjoint = s[::w]
    assert scipy.stats.kstest(disjoint, scipy.stats.chi2(2 * w).cdf).pvalue > 1e-3
    rate = float(np.mean(s > rt.monitor.degrade_sum))
    assert 0.005 < rate < 0.02        # alpha = 0.01; overlapping windows: ~760 independent


@pytest.mark.parametrize(("key", "value"), [
    ("estimator_window_s", 0.0), ("estimator_false_alarm", 0.0),
    ("estimator_nis_inflation", 0.5), ("estimator_rearm_s", -1.0),
    ("estimator_authority_ramp_s", 11.0)])
def test_bad_monitor_settings_name_the_key(key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"safety.{key}"):
        default_config().replace(safety={key: value})
