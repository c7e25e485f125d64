"""The rig service: CAN I/O, the fixed-rate loop, safety lifecycle, telemetry, recording."""

__version__ = "0.1.0"
