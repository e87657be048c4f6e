"""Simulation bridge: terrains, renderers, trajectories and IMU, the simulated autopilot, replay."""
