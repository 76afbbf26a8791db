"""Perception stage: cameras, rendering, IMU, visual-inertial odometry. Runs after simulation, outside jit."""
