"""Warehouse flight simulator: trajectory, rendering, IMU synthesis, scenarios, `simulate()`."""
