"""The compiled functions called without numba's dispatch (controller/runtime/compiled.py):
the bank's step, its previewed step and the force loop give what the dispatcher gives,
to the bit; an array of another type is never handed to an entry point, and the
previewed step given one is a flagged tick, not a misread."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from controller.config import default_config
from controller.road_preview import RoadPreview, road_preview
from controller.runtime.bank import BankRuntime, bank_step, bank_tick, bank_tick_preview
from controller.runtime.compiled import args_match, direct_call
from controller.runtime.force_loop import PIForceLoop, pi_force_step
from controller.runtime.kernels import StepFlag
from hil.sim.closed_loop import cached_design, simulate
from hil.sim.roads import make_road

CFG = default_config()
N = 1500


def _ride() -> dict[str, np.ndarray]:
    road = make_road("rough-course", 11.176, N / 1000 + 0.5, CFG.sample_time_s, seed=3)
    return simulate(CFG, road, "passive", 1, seed=3).traces


def _ring(ride: dict[str, np.ndarray], pv: RoadPreview) -> np.ndarray:
    return np.ascontiguousarray(np.append(np.diff(ride["road_height_m"]) / CFG.sample_time_s,
                                          np.zeros(pv.horizon_ticks + 1)))


def test_runtime_and_force_loop_take_the_entry_points() -> None:
    rt = BankRuntime(cached_design(CFG), cfg=CFG)
    for call, dispatcher in ((rt._step_call, bank_step), (rt._tick_call, bank_tick)):
        assert call is not dispatcher
        assert call is dispatcher.overloads[dispatcher.signatures[0]].entry_point
    pi = PIForceLoop.from_config(CFG)
    assert pi._call is pi_force_step.overloads[pi_force_step.signatures[0]].entry_point


@pytest.mark.parametrize("weight_set", [0, 1])
def test_entry_points_give_the_dispatchers_results_to_the_bit(weight_set: int) -> None:
    """The same ride through a runtime and a force loop on the entry points and through
    twins made to call the dispatchers: forces, spool commands and every state slot."""
    pv = road_preview(CFG)
    assert pv is not None
    ride = _ride()
    ring = _ring(ride, pv)
    reading, accel = ride["meas_rattlespace_m"], ride["meas_accel_mps2"]
    force = 300.0 * np.sin(2 * np.pi * 0.9 * ride["time_s"])
    direct = BankRuntime(cached_design(CFG), weight_set=weight_set, cfg=CFG)
    plain = BankRuntime(cached_design(CFG), weight_set=weight_set, cfg=CFG)
    plain._step_call, plain._tick_call = bank_step, bank_tick
    pi_direct, pi_plain = PIForceLoop.from_config(CFG), PIForceLoop.from_config(CFG)
    pi_plain._call = pi_force_step
    for k in range(N):
        if k % 2:                           # the previewed step and the plain one in turn
            u_d = direct.step_previewed(pv, reading[k], accel[k], force[k], ring, k)
            plain.check_road_preview(pv, reading[k], force[k], ring, k)
            u_p = plain.step(reading[k], accel[k], force[k])
        else:
            u_d = direct.step(reading[k], accel[k], force[k])
            u_p = plain.step(reading[k], accel[k], force[k])
        assert u_d == u_p, k
        s_d = pi_direct.step(u_d, force[k], reading[k])
        assert s_d == pi_plain.step(u_p, force[k], reading[k]), k
    assert direct._tick_preview_call is not bank_tick_preview
    np.testing.assert_array_equal(direct._fv, plain._fv)
    np.testing.assert_array_equal(direct._st, plain._st)
    np.testing.assert_array_equal(pi_direct._s, pi_plain._s)


def test_previewed_step_on_a_foreign_array_is_a_flagged_tick_then_recovers() -> None:
    """A road-velocity array of another dtype, or not contiguous, goes to the dispatcher,
    which refuses it: force 0 and NONFINITE_INPUT, the state untouched.  The loop's own
    ring afterwards takes the entry point again."""
    pv = road_preview(CFG)
    assert pv is not None
    ride = _ride()
    ring = _ring(ride, pv)
    rt = BankRuntime(cached_design(CFG), cfg=CFG)
    reading, accel = ride["meas_rattlespace_m"], ride["meas_accel_mps2"]
    for k in range(50):
        rt.step_previewed(pv, reading[k], accel[k], 0.0, ring, k)
    wide = np.repeat(ring, 2)
    for foreign in (ring.astype(np.float32), wide[::2], ring.reshape(1, -1)):
        fv = rt._fv.copy()
        assert rt.step_previewed(pv, reading[50], accel[50], 0.0, foreign, 50) == 0.0
        assert rt._tick_preview_call is bank_tick_preview
        assert StepFlag.NONFINITE_INPUT in rt.flags
        np.testing.assert_array_equal(rt._fv, fv)
    rt.step_previewed(pv, reading[50], accel[50], 0.0, ring, 50)
    assert rt._tick_preview_call is not bank_tick_preview
    assert StepFlag.NONFINITE_INPUT not in rt.flags


def test_a_number_in_a_string_is_refused_as_before() -> None:
    """The entry point would read "0.01" as 0.01 (Python's float()); only Python floats
    take it, so a string is refused as the dispatcher refuses it (a flagged tick, the
    state untouched), and NumPy and int numbers give what floats give."""
    pv = road_preview(CFG)
    assert pv is not None
    ring = np.zeros(2 * pv.horizon_ticks)
    rt = BankRuntime(cached_design(CFG), cfg=CFG)
    twin = BankRuntime(cached_design(CFG), cfg=CFG)
    for k in range(30):
        r = 0.002 * np.sin(0.3 * k)
        fv = rt._fv.copy()
        for bad in (("0.01", 0.0, 0.0), (0.01, b"0", 0.0), (0.01, 0.0, "5")):
            assert rt.step(*bad) == 0.0                  # type: ignore[arg-type]
            assert rt.flags == StepFlag.NONFINITE_INPUT
            assert rt.step_previewed(pv, *bad, ring, 0) == 0.0  # type: ignore[arg-type]
            assert rt.flags == StepFlag.NONFINITE_INPUT
            np.testing.assert_array_equal(rt._fv, fv)
        assert rt.step_previewed(pv, 0.01, 0.0, 0.0, ring, "0") == 0.0  # type: ignore[arg-type]
        assert rt.flags == StepFlag.NONFINITE_INPUT
        if k % 2:
            u = rt.step(np.float64(r), 1, np.float32(2.5))   # type: ignore[arg-type]
        else:
            u = rt.step_previewed(pv, np.float64(r), 1, np.float32(2.5), ring,  # type: ignore[arg-type]
                                  np.int64(k))
        assert u == (twin.step(float(r), 1.0, 2.5) if k % 2
                     else twin.step_previewed(pv, float(r), 1.0, 2.5, ring, k))
    pi, pi_twin = PIForceLoop.from_config(CFG), PIForceLoop.from_config(CFG)
    with pytest.raises(TypeError):                       # as the dispatcher always did
        pi.step("1", 0.0, 0.0)                           # type: ignore[arg-type]
    assert pi.step(np.float64(100.0), 3, 0.001) == pi_twin.step(100.0, 3.0, 0.001)


_DTYPES = st.sampled_from([np.float64, np.float32, np.int64, np.int32, np.bool_])


@settings(max_examples=60, deadline=None)
@example(p_dtype=np.float64, s_dtype=np.float64, p_len=1, p_strided=True, s_2d=False,
         s_readonly=False)
@example(p_dtype=np.float64, s_dtype=np.float64, p_len=2, p_strided=True, s_2d=False,
         s_readonly=False)
@given(p_dtype=_DTYPES, s_dtype=_DTYPES, p_len=st.integers(1, 40),
       p_strided=st.booleans(), s_2d=st.booleans(), s_readonly=st.booleans())
def test_only_the_signatures_array_types_get_the_entry_point(
        p_dtype: type, s_dtype: type, p_len: int, p_strided: bool, s_2d: bool,
        s_readonly: bool) -> None:
    """direct_call hands out the entry point exactly when every array is a writeable,
    C-contiguous, one-dimensional float64 array, as pi_force_step's signature says."""
    p = np.zeros(2 * p_len, dtype=p_dtype)[::2] if p_strided else np.zeros(p_len, p_dtype)
    s = np.zeros((1, 12) if s_2d else 12, dtype=s_dtype)
    s.flags.writeable = not s_readonly
    # a strided view of one element is contiguous (NumPy's flags, numba's layout)
    fits = (p_dtype is np.float64 and s_dtype is np.float64
            and (not p_strided or p_len == 1) and not s_2d and not s_readonly)
    args = (p, s, 0.0, 0.0, 0.0)
    assert args_match(pi_force_step, args) is fits
    call = direct_call(pi_force_step, args)
    assert (call is not pi_force_step) is fits
    assert not args_match(pi_force_step, args[:4])        # one argument short
