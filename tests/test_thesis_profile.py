"""deploy/thesis.toml: the thesis-literal estimation and blending profile (issue 11)."""

from __future__ import annotations

import numpy as np

from controller.config import config_to_dict, default_config, load_config
from controller.design import design_bank
from controller.runtime.bank import BankRuntime, Blending, StepFlag
from tests.support.profiles import THESIS_PROFILE as PROFILE

EXPECTED = {
    ("design", "weight_set"): 1,                   # one fixed LQ weight set, not the schedule (§12)
    ("design", "bump_stop_filter_input"): False,
    ("design", "filter_rattlespace_bias_drift"): 0.0,
    ("design", "accel_mean_window_s"): 0.0,
    ("design", "airborne_filter_wheel_force_intensity"): 0.0,
    ("fuzzy", "statistic"): "raw",
    ("fuzzy", "no_fire_fallback"): "passive",
    ("safety", "stop_contact_degrade"): False,     # reports, does not degrade (§9.8)
    ("design", "sprung_mass_scales"): [1.0],       # the thesis's bank: one layer (§11)
    ("design", "spring_rate_scales"): [1.0],
    ("design", "damping_scales"): [1.0],
    ("design", "tire_stiffness_scales"): [1.0],
    ("design", "preview_horizon_s"): 0.0,         # no road preview (§12)
    ("design", "govern_comfort_set"): False,      # weight set 2 alone, no governor
}


def test_profile_differs_from_the_defaults_in_exactly_the_thesis_keys() -> None:
    thesis, default = config_to_dict(load_config(PROFILE)), config_to_dict(default_config())
    diff = {(s, k): v for s, sec in thesis.items() for k, v in sec.items()
            if default[s][k] != v}
    assert diff == EXPECTED


def test_profile_design_and_runtime_are_thesis_literal() -> None:
    """No bias states, no stop input, an airborne filter with the true (noise-free)
    relative dynamics, and App. A on the raw q with the 0 N fallback: a sustained
    measurement no model explains fires no rule and the force is 0."""
    cfg = load_config(PROFILE)
    d = design_bank(cfg)
    assert np.all(d.bias_gain == 0.0) and d.bump_stop[0] == 0.0
    air = int(np.flatnonzero(d.airborne)[0])
    F = d.innovation_cov[air]           # L ~ 0, F = R: open loop
    np.testing.assert_allclose(F[:, [0, 1], [0, 1]], np.broadcast_to(
        [cfg.noise.rattlespace_std_m ** 2, cfg.noise.accel_std_mps2 ** 2], (len(F), 2)),
        rtol=1e-3)
    # uncorrelated innovations (round-off: the two variances differ by 1e6)
    assert np.all(np.abs(F[:, 0, 1]) <= 1e-6 * np.sqrt(F[:, 0, 0] * F[:, 1, 1]))
    rt = BankRuntime(d, blending=Blending.FUZZY, cfg=cfg)
    for _ in range(30):
        out = rt.step(0.02, 30.0, 0.0)
    assert StepFlag.NO_RULE_FIRED in rt.flags and out == 0.0
    assert rt.step(0.09, 0.0, 0.0) is not None and rt.bump_stop_force == 0.0
