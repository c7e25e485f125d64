"""The telemetry process: every surface a network client can reach (the Zenoh session and
the live Foxglove WebSocket server) in a process of its own, fed by the control loop.

- :mod:`rig.telemetry_process.feed`: the items on the pipe from the loop to the process
  (the recording's packed tick records, events and tick layout of
  :mod:`rig.recording.codec`, plus the status snapshot and command replies);
- :mod:`rig.telemetry_process.link`: the loop process's side (starts and supervises the
  process, writes the feed without ever blocking, takes the commands back);
- :mod:`rig.telemetry_process.child`: the process itself (``python -m
  rig.telemetry_process``), holding :class:`rig.telemetry.TelemetryPublisher` and
  :class:`rig.foxglove_server.FoxgloveView`;
- :mod:`rig.telemetry_process.peers`: per-peer rate limits.

docs/telemetry.md ("The telemetry process") describes the split.
"""
