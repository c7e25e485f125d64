"""Offline identification run: what ``rig demo --excite`` records, faster than real time.

The same parts as the service against the emulated rig -- :class:`hil.sim.plant.RigPlant`
(the true plant of ``cfg.emulator`` or ``params``), :class:`hil.sim.sensors.SensorSuite`,
:class:`controller.runtime.force_loop.PIForceLoop` fed by
:func:`controller.excitation.excitation_force` -- in one tick loop without a bus:

* ``cfg.excitation.rest_s`` passive (bypass open, road at rest), then the excitation in
  closed force loop, then ``tail_s`` passive again;
* the readings are quantised as the CAN frame ``SensorData`` carries them (LSB 5 um,
  0.5 N, 0.005 m/s^2) and the spool command as ``ValveCommand`` does;
* the spool command reaches the valve one tick after it was computed (the CAN loop: the
  rig applies a ValveCommand at its next tick).

:func:`simulate_excitation` returns the recorded channels under the names of
``/rig/signals`` plus the excitation mask (the ticks between the recording's
``excitation`` start and end events) -- the input of :func:`controller.identify.identify`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from controller.config import RigConfig
from controller.excitation import excitation_force
from controller.runtime.force_loop import PIForceLoop
from hil.sim.plant import PlantParams, RigPlant
from hil.sim.sensors import SensorSuite

__all__ = ["simulate_excitation"]

#: SensorData LSBs (rig/wire/rig.dbc: Rattlespace, LoadCellForce, SprungAccel) and the
#: ValveCommand SpoolCommand LSB
_LSB = (5e-6, 0.5, 0.005)
_SPOOL_LSB = 1.0 / 32767.0


def simulate_excitation(cfg: RigConfig, seed: int | None = None,
                        params: PlantParams | None = None, tail_s: float = 0.5,
                        delay_ticks: int = 1) -> dict[str, NDArray[np.float64]]:
    """Channels of an identification run (see the module docstring): ``rattlespace_m``,
    ``sprung_accel_mps2``, ``force_meas_n``, ``force_ref_n``, ``spool_cmd``,
    ``valve_enable``, ``excitation`` (1.0 while the excitation plays) and, for checks,
    ``true_tire_force_n``."""
    dt = cfg.sample_time_s
    exc = excitation_force(cfg)
    n_rest = round(cfg.excitation.rest_s / dt)
    n_tail = round(tail_s / dt)
    n = n_rest + exc.shape[0] + n_tail
    plant = RigPlant(cfg, params)
    sensors = SensorSuite(cfg.sensors, cfg.noise, seed, dt_s=dt)
    pi = PIForceLoop.from_config(cfg)
    out = {k: np.zeros(n) for k in ("rattlespace_m", "sprung_accel_mps2", "force_meas_n",
                                    "force_ref_n", "spool_cmd", "valve_enable", "excitation",
                                    "true_tire_force_n")}
    queue = [0.0] * delay_ticks
    bypass_queue = [True] * delay_ticks
    for k in range(n):
        rd = sensors.read(plant)
        r = _LSB[0] * round(rd.rattlespace_m / _LSB[0])
        f = _LSB[1] * round(rd.force_n / _LSB[1])
        a = _LSB[2] * round(rd.accel_mps2 / _LSB[2])
        active = n_rest <= k < n_rest + exc.shape[0]
        spool, fref = 0.0, 0.0
        if active:
            fref = float(exc[k - n_rest])
            spool = _SPOOL_LSB * round(pi.step(fref, f, r) / _SPOOL_LSB)
        queue.append(spool)
        bypass_queue.append(not active)
        plant.advance(dt, queue.pop(0), bypass_queue.pop(0), 0.0, 0.0)
        out["rattlespace_m"][k] = r
        out["sprung_accel_mps2"][k] = a
        out["force_meas_n"][k] = f
        out["force_ref_n"][k] = fref
        out["spool_cmd"][k] = spool
        out["valve_enable"][k] = float(active)
        out["excitation"][k] = float(active)
        out["true_tire_force_n"][k] = plant.tire_force_n
    return out
