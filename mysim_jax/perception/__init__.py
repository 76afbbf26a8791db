"""Perception stage: cameras, rendering, IMU, visual-inertial odometry, run on a finished
trajectory outside jit (plain NumPy/OpenCV; no JAX). Import the submodules directly, e.g.
``mysim_jax.perception.imu``."""
