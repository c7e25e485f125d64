"""Process plumbing shared by the service and the emulated rig: real-time set-up,
stop signals, systemd notification."""
