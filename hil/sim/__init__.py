"""Simulation of the rig: nonlinear quarter car, servo-hydraulics, sensors, roads,
the closed-loop tick loop and Monte Carlo (no CAN)."""
