"""Spring-rate and damping layers of the bank (docs/design.md §11): the layers cross the
sprung-mass scales with ``design.spring_rate_scales`` and ``damping_scales``; each layer is
exactly the design for its [M, K, C], and the bank runs the layer nearest the estimator's
[M, K, C], so on a rig with another spring and damper it controls like the bank designed
for that rig.

CFG is the configured rig with a one-layer bank (:func:`controller.config.one_layer`):
"the bank designed for" a rig, and the one-layer bank, are that rig's one layer,
whatever layers the built-in defaults have.  Its road preview trusts every layer alike
(``preview_trigger_inner_m`` = 0: one trigger, the force on every layer), so a layered
bank and the bank designed for the rig differ only by their layers; the preview's
caution on the grid's edge is tests/test_road_preview.py's."""

from __future__ import annotations

import numpy as np
import pytest

from controller.config import ConfigError, default_config, layer_scales, one_layer
from controller.design import design_bank
from controller.runtime.bank import BankRuntime
from controller.runtime.mass_layers import layer_table
from hil.sim.closed_loop import BankController, cached_design, run_closed_loop
from hil.sim.roads import make_road

CFG = one_layer(default_config()).replace(design={"preview_trigger_inner_m": 0.0})
V = CFG.vehicle
DT = CFG.sample_time_s
SETTLE_S = 8.0
GRID = CFG.replace(design={"sprung_mass_scales": [0.7, 1.0],
                           "spring_rate_scales": [0.7, 1.0, 1.4],
                           "damping_scales": [0.6, 1.0]})


def test_layers_are_mass_major_and_each_the_design_for_its_plant() -> None:
    d = cached_design(GRID)
    n = len(CFG.design.linearisation_deflections_m)
    scales = layer_scales(GRID)
    assert len(scales) == 12 and scales[:3] == [(0.7, 0.7, 0.6), (0.7, 0.7, 1.0),
                                                (0.7, 1.0, 0.6)]
    assert d.n_models == 12 * n + 1 and bool(d.airborne[-1])
    for i in (1, 5, 10):
        m, k, c = scales[i]
        ref = design_bank(CFG.replace(vehicle={
            "sprung_mass_kg": V.sprung_mass_kg * m,
            "suspension_stiffness_n_per_m": V.suspension_stiffness_n_per_m * k,
            "suspension_damping_ns_per_m": V.suspension_damping_ns_per_m * c}))
        rows = slice(i * n, (i + 1) * n)
        np.testing.assert_allclose(d.lq_gain[:, rows], ref.lq_gain[:, :n], rtol=1e-9)
        np.testing.assert_allclose(d.kalman_gain[rows], ref.kalman_gain[:n], rtol=1e-9)
        assert all(str(name).endswith(f"_M{m:g}_K{k:g}_C{c:g}")
                   for name in d.model_names[rows])
    rt = BankRuntime(d, cfg=GRID)
    np.testing.assert_allclose(rt.layer_params[rt.mass_layer],
                               [V.sprung_mass_kg, V.suspension_stiffness_n_per_m,
                                V.suspension_damping_ns_per_m])
    assert rt.layer_masses_kg.shape == (12,)


def test_layer_table_refuses_a_design_that_is_not_its_layers() -> None:
    d = cached_design(GRID)
    good = np.array(layer_scales(GRID)) * [V.sprung_mass_kg, V.suspension_stiffness_n_per_m,
                                           V.suspension_damping_ns_per_m]
    layer_table(d.equilibrium, d.airborne, good, V.gravity_mps2)
    swapped = good.copy()
    swapped[:, 1] = swapped[::-1, 1]            # spring rates of other layers
    with pytest.raises(ValueError, match="not those of its configured layers"):
        layer_table(d.equilibrium, d.airborne, swapped, V.gravity_mps2)
    with pytest.raises(ValueError, match="not 5 layers"):
        layer_table(d.equilibrium, d.airborne, good[:5], V.gravity_mps2)


def test_bad_scales_name_the_key() -> None:
    for key in ("spring_rate_scales", "damping_scales"):
        for scales in ([], [1.0, 0.7], [1.0, 1.0], [0.1]):
            with pytest.raises(ConfigError, match=rf"design\.{key}"):
                CFG.replace(design={key: scales})


def _running_is_the_layer(rt: BankRuntime) -> None:
    """rt.running (what the tick record carries) is the running layer's tire models then
    the airborne model, with the bank's values for them."""
    n = len(CFG.design.linearisation_deflections_m)
    rows = [rt.mass_layer * n + t for t in range(n)] + [rt.n_models - 1]
    run = rt.running
    assert run.models.tolist() == rows
    for key in ("q", "firing_weight", "probability", "u_model", "active", "x_post"):
        np.testing.assert_array_equal(getattr(run, key), getattr(rt, key)[rows], err_msg=key)
    assert run.q.shape == (n + 1,) and run.x_post.shape == (n + 1, 4)


def test_a_one_layer_bank_records_every_model_without_a_copy() -> None:
    rt = BankRuntime(cached_design(CFG), cfg=CFG)
    assert rt.running.models.tolist() == list(range(rt.n_models))
    for key in ("q", "firing_weight", "probability", "u_model", "active", "x_post"):
        assert np.shares_memory(getattr(rt.running, key), getattr(rt, key)), key


def test_the_loop_records_and_publishes_the_running_layer() -> None:
    """Through the loop: the packed tick record (recording and telemetry) has the running
    layer's four columns and their bank indices, and the telemetry state carries both."""
    from rig.recording.codec import TickDecoder, iter_items
    from rig.telemetry_process.child import snapshot_of
    from tests.support.loop_harness import make_harness

    rt = BankRuntime(cached_design(GRID), cfg=GRID)
    h = make_harness(GRID, rt=rt)
    try:
        for _ in range(20):
            h.step()
        packed = bytes(h.loop._tick_record(0))
        _t, rec = TickDecoder(h.loop._packer.layout).decode(next(iter_items(packed)))
    finally:
        h.close()
    n = len(CFG.design.linearisation_deflections_m)
    home = layer_scales(GRID).index((1.0, 1.0, 1.0))
    assert rec["models"] == [home * n + t for t in range(n)] + [rt.n_models - 1]
    assert len(rec["q"]) == len(rec["firing_weight"]) == n + 1
    assert np.shape(rec["x_post"]) == (n + 1, 4)
    state = snapshot_of(0, rec, h.loop.status())["state"]
    assert state["models"] == rec["models"] and state["q"] == rec["q"]


def test_the_running_layer_follows_a_layer_change() -> None:
    """Stepped on the 0.7 x spring's layer's rig, the bank leaves the configured layer;
    the running models follow it tick for tick (not only at the end of a run)."""
    road = make_road("rough-course", 11.176, 6.0, DT, 2)
    layers_seen = set()

    class Check(BankController):
        def step(self, rd, plant):          # type: ignore[no-untyped-def]
            u = super().step(rd, plant)
            if self.ticks % 97 == 0:
                _running_is_the_layer(self.rt)
                layers_seen.add(self.rt.mass_layer)
            return u

    ctrl = Check(cached_design(GRID), GRID, "fuzzy", 0, road)
    run_closed_loop(CFG.replace(emulator={"spring_rate_scale": 0.7, "damping_scale": 0.6}),
                    road, ctrl, seed=2)
    assert len(layers_seen) >= 2


def _power(ctrl_cfg, plant_emulator: dict[str, float], road, seed: int
           ) -> tuple[float, float, BankController]:
    ctrl = BankController(cached_design(ctrl_cfg), ctrl_cfg, "fuzzy", 0, road)
    plant_cfg = CFG.replace(emulator=plant_emulator) if plant_emulator else CFG
    res = run_closed_loop(plant_cfg, road, ctrl, seed=seed, settle_s=SETTLE_S)
    assert res.metrics["n_faults"] == 0
    return res.metrics["absorbed_power"], res.metrics["rattlespace_rms_m"], ctrl


@pytest.mark.parametrize(("spring", "damping", "layer"), [(0.7, 0.6, (1.0, 0.7, 0.6)),
                                                          (1.4, 1.0, (1.0, 1.4, 1.0))])
def test_on_another_spring_and_damper_the_bank_runs_that_layer(
        spring: float, damping: float, layer: tuple[float, float, float]) -> None:
    """A rig whose spring and damper differ from the configuration (the configured mass):
    armed, the bank runs the layer of that spring and damper and
    controls within 10 % of the bank designed for the rig (absorbed power, rattlespace
    within 5 %, over the 10 s after the first 8 s), far better than the bank of the
    configured rig alone.  (Armed, not observed: with the valve safe the load cell reads
    about 0 N, and M a = K z + C z' fixes [M, K, C] only up to a common scale, which the
    estimator's prior on K and C then sets; the actuator's force gives the scale.)"""
    road = make_road("rough-course", 11.176, SETTLE_S + 10.0, DT, 3)
    plant = {"spring_rate_scale": spring, "damping_scale": damping}
    layered, layered_rms, ctrl = _power(GRID, plant, road, 3)
    assert layer_scales(GRID)[ctrl.rt.mass_layer] == layer
    _running_is_the_layer(ctrl.rt)
    true_cfg = CFG.replace(vehicle={
        "suspension_stiffness_n_per_m": V.suspension_stiffness_n_per_m * spring,
        "suspension_damping_ns_per_m": V.suspension_damping_ns_per_m * damping})
    ctrl_true = BankController(cached_design(true_cfg), true_cfg, "fuzzy", 0, road)
    res = run_closed_loop(true_cfg, road, ctrl_true, seed=3, settle_s=SETTLE_S)
    true, true_rms = res.metrics["absorbed_power"], res.metrics["rattlespace_rms_m"]
    nominal, _, _ = _power(CFG, plant, road, 3)
    assert layered == pytest.approx(true, rel=0.10)
    assert layered_rms == pytest.approx(true_rms, rel=0.05)
    assert nominal > 1.2 * true


def test_at_rest_every_model_reads_its_own_static_deflection() -> None:
    """The LVDT reads 0 at rest (zeroed there, or the ride height set by preload), so each
    on-ground model's filter must see its own static suspension deflection M_l g / K_l
    there, not the configured rig's: its measurement at its equilibrium (C x̄ + y_offset,
    from the design) is the reading the loop hands it at rest (M g / K + V_YSTAT).
    Before, a spring layer read 51 mm (K x 1.4) or -77 mm (K x 0.7) off it: its bias state
    took that up, and every filter started from another layer's biases was that far off."""
    from controller.runtime import kernels as kern

    d = cached_design(GRID)
    rt = BankRuntime(d, cfg=GRID)
    mat, vec, fv = rt._mat, rt._vec, rt._fv
    at_rest = fv[kern.F_STATIC] + vec[:, kern.V_YSTAT]
    for j in np.flatnonzero(~d.airborne):
        predicted = mat[j, :, kern.M_CT] @ mat[j, :, kern.M_XBAR] + fv[kern.F_YOFF]
        assert at_rest[j] == pytest.approx(predicted, abs=1e-9), d.model_names[j]
    m, k, _ = np.array(layer_scales(GRID)).T
    np.testing.assert_allclose(
        at_rest[:-1:len(CFG.design.linearisation_deflections_m)],
        m * V.sprung_mass_kg * V.gravity_mps2 / (k * V.suspension_stiffness_n_per_m))


def test_the_moving_bank_on_another_spring_runs_its_layer_without_degrading() -> None:
    """The moving bank starts the new layer's filters at the change and the airborne filter
    at each lift-off from the running filters' biases: on a rig with a 1.4 x spring it
    moves to that layer and flies through the course's lift-offs without a degradation
    (before: the 1.4 x layer's biases held a 51 mm offset the airborne model does not
    have, and each lift-off degraded the bank: 9 times in these 18 s), and controls within
    10 % of the moving bank designed for the rig."""
    road = make_road("rough-course", 11.176, SETTLE_S + 10.0, DT, 1)
    plant = {"spring_rate_scale": 1.4}
    ctrl = BankController(cached_design(GRID), GRID, "moving", 1, road)
    res = run_closed_loop(CFG.replace(emulator=plant), road, ctrl, seed=1, settle_s=SETTLE_S)
    c = ctrl.rt.counters()
    assert layer_scales(GRID)[ctrl.rt.mass_layer] == (1.0, 1.4, 1.0)
    assert c["layer_changes"] >= 1 and c["set_switches"] >= 4     # lift-offs and landings
    assert c["degradations"] == 0 and res.metrics["n_faults"] == 0
    true_cfg = CFG.replace(vehicle={
        "suspension_stiffness_n_per_m": V.suspension_stiffness_n_per_m * 1.4})
    true = run_closed_loop(true_cfg, road, BankController(cached_design(true_cfg), true_cfg,
                                                          "moving", 1, road),
                           seed=1, settle_s=SETTLE_S)
    assert res.metrics["absorbed_power"] == pytest.approx(true.metrics["absorbed_power"],
                                                          rel=0.10)
