"""The wire contract shared by the service and the emulated rig: the DBC, the
codec, the E2E protection and the enumerations on the bus."""
