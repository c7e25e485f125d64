"""Sprung-mass layers of the bank (controller/runtime/mass_layers.py, docs/design.md §11):
the design holds the tire models once per mass layer, each exactly the design for that
mass; the bank runs the layer nearest the sprung-mass estimate, and on a plant of another
mass it then controls like the bank designed for that plant.

The tests build their banks on the configured rig with a one-layer bank
(:func:`controller.config.one_layer`), so each bank is exactly the one a test describes
(layers over sprung mass only; "the bank designed for" a plant is that plant's one
layer), whatever layers the built-in defaults have."""

from __future__ import annotations

import numpy as np
import pytest

from controller.config import ConfigError, RigConfig, default_config, one_layer
from controller.design import design_bank
from controller.runtime.bank import BankRuntime
from controller.runtime.kernels import Blending
from controller.runtime.mass_layers import layer_table
from hil.sim.closed_loop import BankController, cached_design, run_closed_loop
from hil.sim.plant import RigPlant
from hil.sim.roads import make_road
from hil.sim.sensors import SensorReading

CFG = one_layer(default_config())
V = CFG.vehicle
SCALES = [0.7, 1.0, 1.3]
LAYERED = CFG.replace(design={"sprung_mass_scales": SCALES})
DT = CFG.sample_time_s


def test_each_layer_is_the_design_for_its_mass() -> None:
    d = cached_design(LAYERED)
    n_tire = len(CFG.design.linearisation_deflections_m)
    assert d.n_models == 3 * n_tire + 1 and bool(d.airborne[-1])
    params = [[V.sprung_mass_kg * s, V.suspension_stiffness_n_per_m,
               V.suspension_damping_ns_per_m] for s in SCALES]
    layers, layer, n = layer_table(d.equilibrium, d.airborne, np.array(params), V.gravity_mps2)
    np.testing.assert_allclose(layers[:, 0], [350.0, 500.0, 650.0])
    assert n == n_tire and layer.tolist() == [0] * n + [1] * n + [2] * n + [-1]
    for i, scale in enumerate(SCALES):
        ref = design_bank(CFG.replace(vehicle={"sprung_mass_kg": V.sprung_mass_kg * scale}))
        rows = slice(i * n, (i + 1) * n)
        np.testing.assert_allclose(d.lq_gain[:, rows], ref.lq_gain[:, :n], rtol=1e-9)
        np.testing.assert_allclose(d.kalman_gain[rows], ref.kalman_gain[:n], rtol=1e-9)
        assert all(str(name).endswith(f"_M{scale:g}") for name in d.model_names[rows])


def test_after_a_reset_the_bank_runs_the_configured_mass_layer() -> None:
    d = cached_design(LAYERED)
    for blending in Blending:
        rt = BankRuntime(d, blending=blending, cfg=LAYERED)
        assert rt.mass_layer == 1
        running = np.flatnonzero(rt.active)
        assert running.size > 0 and all(3 <= j < 6 or d.airborne[j] for j in running)


def _run(emulator: dict[str, float], mode: str, duration_s: float,
         ctrl_cfg: RigConfig = LAYERED, seed: int = 1
         ) -> tuple[BankController, dict[str, float], dict[str, float]]:
    """(controller, metrics, passive metrics) on the thesis course; the plant is
    ``ctrl_cfg``'s rig with ``emulator`` on top."""
    road = make_road("rough-course", 11.176, duration_s, DT, seed)
    ctrl = BankController(cached_design(ctrl_cfg), ctrl_cfg, mode, 1, road)
    plant_cfg = ctrl_cfg.replace(emulator=emulator) if emulator else ctrl_cfg
    res = run_closed_loop(plant_cfg, road, ctrl, seed=seed)
    passive = run_closed_loop(plant_cfg, road, None, seed=seed)
    return ctrl, res.metrics, passive.metrics


@pytest.mark.parametrize("mode", ["fuzzy", "lqg", "bayes", "moving"])
def test_on_a_light_plant_the_bank_moves_to_the_light_layer(mode: str) -> None:
    ctrl, m, _ = _run({"sprung_mass_scale": 0.7}, mode, 6.0)
    rt = ctrl.rt
    assert rt.mass_layer == 0 and rt.counters()["layer_changes"] == 1
    running = np.flatnonzero(rt.active)
    assert all(j < 3 or rt.design.airborne[j] for j in running), running
    assert m["n_faults"] == 0
    # the monitor saw no transient: fuzzy, Bayes and the single LQG warmed the new layer's
    # filters up; the moving bank starts them at the change from the running filters'
    # deviation and biases, which every model reads in its own frame (docs/design.md §11)
    assert rt.counters()["degradations"] == 0


def test_light_plant_controlled_like_the_design_for_it() -> None:
    """M = 0.7 x configured: the layered bank absorbs within 10 % of the bank designed for
    350 kg, at rattlespace within 5 %; the bank designed for 500 kg is far off."""
    _, layered, passive = _run({"sprung_mass_scale": 0.7}, "fuzzy", 20.0)
    true_cfg = CFG.replace(vehicle={"sprung_mass_kg": 0.7 * V.sprung_mass_kg})
    _, true, passive_true = _run({}, "fuzzy", 20.0, ctrl_cfg=true_cfg)
    _, nominal, _ = _run({"sprung_mass_scale": 0.7}, "fuzzy", 20.0, ctrl_cfg=CFG)
    assert passive["absorbed_power"] == pytest.approx(passive_true["absorbed_power"],
                                                      rel=1e-6)   # the same plant
    assert layered["absorbed_power"] == pytest.approx(true["absorbed_power"], rel=0.10)
    assert layered["rattlespace_rms_m"] == pytest.approx(true["rattlespace_rms_m"], rel=0.05)
    assert nominal["absorbed_power"] > 1.3 * true["absorbed_power"]


class _LayerTrace(BankController):
    """The bank with the running layer of every tick."""

    def reset(self) -> None:
        super().reset()
        self.layers: list[int] = []

    def step(self, reading: SensorReading, plant: RigPlant) -> float:
        u = super().step(reading, plant)
        self.layers.append(int(self.rt.mass_layer))
        return u


def test_observed_before_arming_the_light_plant_starts_on_its_layer() -> None:
    """As the service runs (the bank steps from the first sensor reading, armed or not),
    5 s of observing choose the light layer before the valve is armed (estimator settling
    plus the 1 s dwell take about 3 s), so the armed run matches the design for the true
    mass from its first tick: 0.6 x, whose start on the configured layer costs most when
    armed at once (docs/design.md §11)."""
    light = CFG.replace(design={"sprung_mass_scales": [0.6, 1.0]})
    road = make_road("rough-course", 11.176, 11.0, DT, 2)
    n_obs = round(5.0 / DT)
    true_cfg = CFG.replace(vehicle={"sprung_mass_kg": 0.6 * V.sprung_mass_kg})
    plant_cfg = light.replace(emulator={"sprung_mass_scale": 0.6})
    power = {}
    for name, ctrl_cfg in (("layered", light), ("true", true_cfg)):
        for observe_s in (0.0, 5.0):
            ctrl = _LayerTrace(cached_design(ctrl_cfg), ctrl_cfg, "fuzzy", 1, road)
            res = run_closed_loop(plant_cfg if name == "layered" else true_cfg, road, ctrl,
                                  seed=2, observe_s=observe_s)
            assert res.metrics["n_faults"] == 0
            power[name, observe_s] = res.metrics["absorbed_power"]
            if name == "layered":
                assert ctrl.layers[0] == 1 and ctrl.layers[-1] == 0
                if observe_s:
                    assert ctrl.layers[n_obs - 1] == 0      # chosen before arming
    assert power["layered", 5.0] == pytest.approx(power["true", 5.0], rel=0.05)
    assert power["layered", 0.0] > 1.15 * power["true", 0.0]


def test_ballast_step_moves_the_bank_to_the_heavy_layer_without_fault() -> None:
    ctrl, m, _ = _run({"ballast_step_time_s": 3.0, "ballast_step_scale": 1.3}, "fuzzy", 8.0)
    assert ctrl.rt.mass_layer == 2 and ctrl.rt.counters()["layer_changes"] == 1
    assert m["n_faults"] == 0


def test_bad_scales_name_the_key() -> None:
    for scales in ([], [1.0, 0.7], [1.0, 1.0], [0.1]):
        with pytest.raises(ConfigError, match=r"design\.sprung_mass_scales"):
            CFG.replace(design={"sprung_mass_scales": scales})
