"""What each fault code means, in plain language for the rig engineer (event tables,
reports; :attr:`rig.wire.protocol.FaultCode.description`).  Keyed by the code's name in
the DBC's ``VAL_`` table; the condition and the detail byte per code: docs/service.md."""

from __future__ import annotations

from typing import Final

FAULT_DESCRIPTIONS: Final[dict[str, str]] = {
    "NONE": "No fault.",
    "SENSOR_STALE":
        "No valid SensorData frame for longer than safety.stale_ticks: the controller "
        "could no longer see the rig.",
    "SENSOR_CRC":
        "A SensorData or RigStatus frame failed its end-to-end check (CRC or length): "
        "it was corrupted on the way.",
    "SENSOR_COUNTER":
        "A frame's rolling counter repeated or jumped: the sender is stuck or frames "
        "were lost.",
    "SENSOR_RANGE":
        "A sensor reading (rattlespace, force or acceleration) left its valid range.",
    "NONFINITE":
        "A sensor value, the estimator state, the force reference or the spool command "
        "was not a finite number.",
    "ESTIMATOR_DIVERGED":
        "The Kalman filter bank's estimate became unusable: every tire model's "
        "innovation stayed beyond a sensor's range for a whole monitor window.",
    "OVERRUN_STREAK":
        "The control loop woke up late on too many consecutive ticks "
        "(safety.overrun_streak): its timing could not be trusted.",
    "BUS_ERROR":
        "The CAN bus reported an error: a send or receive failed, or an error frame "
        "arrived.",
    "BUS_OFF": "The CAN controller went bus-off or the interface disappeared.",
    "EXCEPTION": "The control tick raised an unexpected exception.",
    "RIG_WATCHDOG":
        "The rig's drive watchdog tripped: no valid valve command reached the drive "
        "within its timeout, so the drive opened the bypass on its own.",
    "SUPPLY_LOSS": "The rig reported loss of hydraulic supply pressure.",
    "SENSOR_STATUS":
        "A sensor reported its own fault (SensorStatus: LVDT, load cell or "
        "accelerometer).",
    "SHUTDOWN":
        "The service was stopping: valve to its safe state (not a latched fault).",
    "SENSOR_FROZEN":
        "A sensor value stayed bit-identical for more than safety.frozen_ticks frames "
        "while its counter advanced: the sensor is frozen.",
    "ESTIMATOR_DEGRADED":
        "Not a latched fault: the estimator monitor found that no tire model fits the "
        "measurements (windowed innovation statistic above its chi-square level), so the "
        "bank commands zero force (the actuator follows the body, transparent) until the "
        "statistic recovers and it re-arms by itself.",
}
