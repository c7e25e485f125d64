"""The emulated test rig (hardware in the loop)."""
