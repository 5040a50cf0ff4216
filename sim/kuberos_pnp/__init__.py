"""Simulated pick-and-place robot: pure robotics core (world, perception, planning, trajectories, tasks)."""
