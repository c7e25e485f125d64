"""`rig identify` on runs with missed sensor samples (issue 24): the filter chains restart
after each gap, the fit stays within the identification targets, what was left out is
said, and too little data between gaps is refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from controller.identify import SEGMENT_SETTLE_S, IdentificationRefusedError, RunData, identify
from hil.sim.excitation_run import simulate_excitation
from tests.support.identify_run import IDENT_CFG, true_values

pytestmark = pytest.mark.timeout(300)

#: the targets of tests/test_identify.py::test_recovers_the_emulated_rig_within_tolerance
TOL = {"vehicle.sprung_mass_kg": 0.01, "vehicle.suspension_stiffness_n_per_m": 0.01,
       "vehicle.suspension_damping_ns_per_m": 0.01, "vehicle.unsprung_mass_kg": 0.03,
       "tire.stiffness_coefficient": 0.03}


@pytest.fixture(scope="module")
def channels() -> dict[str, np.ndarray]:
    return simulate_excitation(IDENT_CFG, seed=3)


def _with_gaps(ch: dict[str, np.ndarray], stalls: list[float], held: list[float]) -> RunData:
    """Loop stalls (8 periods skipped: ticks absent, the next one not fresh) and held
    samples (a tick without fresh SensorData) at these times into the excitation [s]."""
    excite = ch["excitation"] > 0
    n = excite.size
    rest = np.zeros(n, dtype=bool)
    rest[:round(IDENT_CFG.excitation.rest_s * 1000)] = True
    first = int(np.flatnonzero(excite)[0])
    keep = np.ones(n, dtype=bool)
    fresh = np.ones(n, dtype=bool)
    for t in stalls:
        i = first + round(t * 1000)
        keep[i:i + 8] = False
        fresh[i + 8] = False
    for t in held:
        fresh[first + round(t * 1000)] = False

    def k(name: str) -> np.ndarray:
        return np.asarray(ch[name], dtype=np.float64)[keep]

    return RunData(IDENT_CFG.sample_time_s, k("rattlespace_m"), k("sprung_accel_mps2"),
                   k("force_meas_n"), k("force_ref_n"), k("spool_cmd"), excite[keep],
                   rest[keep], fresh[keep])


def test_a_stall_in_the_excitation_is_fitted_around(channels: dict[str, np.ndarray]) -> None:
    ident = identify(_with_gaps(channels, stalls=[1.5], held=[]), IDENT_CFG)
    for key, truth in true_values().items():
        est = ident.estimates[key]
        assert abs(est / truth - 1.0) < TOL[key], (key, est, truth)
        lo, hi = ident.ci95[key]
        assert lo <= truth <= hi, (key, lo, truth, hi)
    gaps = ident.fit["gaps"]
    assert gaps["gaps"] == 1 and gaps["missed_sensor_samples"] == 1
    assert gaps["left_out_s"] == pytest.approx(SEGMENT_SETTLE_S, abs=0.01)
    assert 0.0 < gaps["left_out_fraction"] < 0.5


def test_too_little_data_between_gaps_is_refused_in_one_line(
        channels: dict[str, np.ndarray]) -> None:
    # a gap every 0.5 s: the chains never settle
    held = [1.2 + 0.5 * i for i in range(12)]
    with pytest.raises(IdentificationRefusedError) as err:
        identify(_with_gaps(channels, stalls=[], held=held), IDENT_CFG)
    msg = str(err.value)
    assert msg.startswith("too little data between missed sensor samples") and "\n" not in msg
    assert "12 gaps" in msg
