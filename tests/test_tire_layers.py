"""Tire layers of the bank (docs/design.md §11): ``design.tire_stiffness_scales`` crosses
the [M, K, C] layers with the tire's stiffness; each layer is exactly the design for its
tire, and the bank runs the layer nearest the tire estimate of the passive wheel hop
(controller/wheel_hop.py), so on a rig with a softer tire it controls like the bank
designed for that tire once it has seen the rig passive.

CFG is the configured rig with a one-layer bank; TIRE adds a 0.7 x tire layer to it."""

from __future__ import annotations

import numpy as np
import pytest

from controller.config import ConfigError, default_config, layer_grid, one_layer
from controller.design import design_bank
from controller.runtime.bank import BankRuntime
from hil.sim.closed_loop import BankController, cached_design, run_closed_loop, simulate
from hil.sim.roads import make_road

CFG = one_layer(default_config())
K_TIRE = CFG.tire.stiffness_coefficient
TIRE = CFG.replace(design={"tire_stiffness_scales": [0.7, 1.0]})
SOFT = CFG.replace(tire={"stiffness_coefficient": 0.7 * K_TIRE})
OBSERVE_S = 12.0
ARMED_S = 6.0


def test_tire_layers_are_each_the_design_for_their_tire() -> None:
    d = cached_design(TIRE)
    n = len(CFG.design.linearisation_deflections_m)
    assert layer_grid(TIRE) == [(1.0, 1.0, 1.0, 0.7), (1.0, 1.0, 1.0, 1.0)]
    assert d.n_models == 2 * n + 1 and bool(d.airborne[-1])
    for layer, ref in ((0, design_bank(SOFT)), (1, cached_design(CFG))):
        rows = slice(layer * n, (layer + 1) * n)
        np.testing.assert_allclose(d.lq_gain[:, rows], ref.lq_gain[:, :n], rtol=1e-9)
        np.testing.assert_allclose(d.kalman_gain[rows], ref.kalman_gain[:n], rtol=1e-9)
        np.testing.assert_allclose(d.equilibrium[rows], ref.equilibrium[:n], rtol=1e-9)
        tire = (0.7, 1.0)[layer]
        assert all(str(name).endswith(f"_M1_T{tire:g}") for name in d.model_names[rows])
    assert BankRuntime(d, cfg=TIRE).mass_layer == 1          # the configured tire


def test_bad_tire_scales_name_the_key() -> None:
    for scales in ([], [1.0, 0.7], [1.0, 1.0], [0.1], [5.0]):
        with pytest.raises(ConfigError, match=r"design\.tire_stiffness_scales"):
            CFG.replace(design={"tire_stiffness_scales": scales})


def _run(observe_s: float, seed: int) -> tuple[BankController, dict[str, float]]:
    """The TIRE bank (default law) on the rig with a 0.7 x tire: the thesis course,
    ``observe_s`` before arming, then ARMED_S armed."""
    plant = TIRE.replace(emulator={"tire_stiffness_scale": 0.7})
    road = make_road("rough-course", 11.176, observe_s + ARMED_S, CFG.sample_time_s, seed)
    ctrl = BankController(cached_design(TIRE), plant, "fuzzy", 0, road)
    res = run_closed_loop(plant, road, ctrl, seed=seed, observe_s=observe_s)
    assert res.metrics["n_faults"] == 0
    return ctrl, res.metrics


def test_bank_runs_the_tire_layer_the_passive_wheel_hop_tells() -> None:
    """Observed passive for 12 s, the bank reads the soft tire (0.7 within 6 %), runs
    its layer, and armed absorbs the power of the bank designed for that tire within 2 %
    (measured 1.000 on seeds 1 and 2 x 30 s; here 6 s)."""
    ctrl, got = _run(OBSERVE_S, seed=1)
    assert ctrl.rt.tire_stiffness_est == pytest.approx(0.7, rel=0.06)
    assert ctrl.rt.mass_layer == 0 and ctrl.rt.counters()["layer_changes"] == 1
    road = make_road("rough-course", 11.176, OBSERVE_S + ARMED_S, CFG.sample_time_s, 1)
    ref = simulate(SOFT, road, "fuzzy", 0, seed=1, observe_s=OBSERVE_S).metrics
    assert got["absorbed_power"] == pytest.approx(ref["absorbed_power"], rel=0.02)
    assert got["rattlespace_rms_m"] == pytest.approx(ref["rattlespace_rms_m"], rel=0.02)


def test_without_a_passive_stretch_the_bank_keeps_the_configured_tire() -> None:
    """Armed at once the rig is never seen passive: no tire estimate, the configured
    tire's layer throughout."""
    ctrl, _ = _run(0.0, seed=2)
    assert np.isnan(ctrl.rt.tire_stiffness_est)
    assert ctrl.rt.mass_layer == 1 and ctrl.rt.counters()["layer_changes"] == 0


def test_the_tire_is_read_against_the_layers_own_rig_not_the_configured_one() -> None:
    """A softer damper raises the passive wheel hop as a stiffer tire does (0.6 x C on
    the configured tire reads as a 1.1-1.2 x tire against the configured rig): each
    layer compares the wheel hop with its own rig's prediction, so the bank ends on the
    0.6 x damper's layer with the configured tire, not on the stiff tire's."""
    cfg = CFG.replace(design={"damping_scales": [0.6, 1.0], "tire_stiffness_scales": [1.0, 1.3]})
    plant = cfg.replace(emulator={"damping_scale": 0.6})
    road = make_road("rough-course", 11.176, OBSERVE_S + ARMED_S, CFG.sample_time_s, 2)
    ctrl = BankController(cached_design(cfg), plant, "fuzzy", 0, road)
    res = run_closed_loop(plant, road, ctrl, seed=2, observe_s=OBSERVE_S)
    assert res.metrics["n_faults"] == 0
    assert ctrl.rt.tire_stiffness_est > 1.1             # against the configured rig
    assert layer_grid(cfg)[ctrl.rt.mass_layer] == (1.0, 1.0, 0.6, 1.0)
