"""Estimator monitor settings: innovation statistics -> degrade / re-arm / fault levels.

The bank (:func:`controller.runtime.bank._monitor`) keeps the sum over the last N ticks of the
smallest likelihood quotient q = r' F^-1 r among the contributing filters:

    S_k = sum_{i = k-N+1..k} min_j q_j,i

**Consistency (degrade / re-arm).**  For a filter whose model matches the plant, the
innovations are white Gaussian with covariance F, so q ~ chi2(m) per tick (m = 2
measurements) and independent between ticks; the window sum of *that* filter's q is
chi2(m N).  Model mismatch that only inflates the innovation covariance to at most c F
(c = ``safety.estimator_nis_inflation``) keeps q / c below a chi2(m) variable, and
min_j q_j is never above the matched filter's q, so

    P(S_k > c chi2_{1-α}(m N)) <= α          (α = ``safety.estimator_false_alarm``)

for every tick k: the degrade threshold has a per-tick false-alarm probability of at
most α whenever one model of the bank explains the data up to the tolerated inflation.
Windows of neighbouring ticks overlap, so alarms cluster; the expected number of
*episodes* per second is below α x rate (an upper bound, met with equality only if
every alarm were isolated).  Re-arming needs S below c times the *median* of chi2(m N)
for ``safety.estimator_rearm_s``: the statistic is back in the body of its distribution,
not merely below the tail threshold (a hysteresis of several standard deviations).

**Usability (fault).**  The estimate is unusable when *every* contributing filter
predicts a measurement further from the reading than that sensor's whole range
(``sensors.lvdt_range_m`` for the rattlespace, ``sensors.accel_range_mps2`` for the
acceleration) for a whole window.  The loop range-checks every reading, so such a
prediction lies outside anything the rig can do (beyond the bump stops, or an
acceleration the accelerometer cannot even read): that estimate is broken, not
mismatched.  A non-finite estimate is flagged at once (``StepFlag.NONFINITE_STATE``).

While degraded the filters keep running (the statistics can recover) and the force
authority ramps linearly to 0 over ``safety.estimator_authority_ramp_s``; on re-arm it
ramps back.  The force reference of the degraded bank is therefore 0 N: with the PI force
loop closed this is the zero-force law (no jump in the force, the valve stays armed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import scipy.stats

from controller.config import RigConfig

__all__ = ["MonitorSettings", "monitor_settings"]


@dataclass(frozen=True)
class MonitorSettings:
    window_ticks: int           # N
    degrade_sum: float          # degrade when S_k exceeds this
    rearm_sum: float            # re-arm after S_k stays below this for rearm_ticks ticks
    rearm_ticks: int
    authority_step: float       # authority change per tick
    rattlespace_bound_m: float  # usability bounds on the innovations
    accel_bound_mps2: float
    false_alarm: float          # α, per tick, under the tolerated inflation


def monitor_settings(cfg: RigConfig, dt_s: float, meas_dim: int = 2) -> MonitorSettings:
    """The monitor's levels for ``cfg`` at the sample time ``dt_s`` (see module docstring)."""
    sa = cfg.safety
    n = max(1, round(sa.estimator_window_s / dt_s))
    c = sa.estimator_nis_inflation
    dof = meas_dim * n
    degrade = c * float(scipy.stats.chi2.isf(sa.estimator_false_alarm, dof))
    rearm = c * float(scipy.stats.chi2.median(dof))
    ramp = sa.estimator_authority_ramp_s
    step = 1.0 if ramp <= 0.0 else min(1.0, dt_s / ramp)
    return MonitorSettings(window_ticks=n, degrade_sum=degrade, rearm_sum=rearm,
                           rearm_ticks=max(1, math.ceil(sa.estimator_rearm_s / dt_s - 1e-9)),
                           authority_step=step,
                           rattlespace_bound_m=cfg.sensors.lvdt_range_m,
                           accel_bound_mps2=cfg.sensors.accel_range_mps2,
                           false_alarm=sa.estimator_false_alarm)
