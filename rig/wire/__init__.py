"""The wire contract shared by the service and the emulated rig: the DBC, the codec
generated from it (``python -m rig.wire.generate``), the E2E protection and the
enumerations on the bus."""
