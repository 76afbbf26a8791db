"""Perception stage: sensors and estimators run on a finished trajectory, outside jit
(plain NumPy; no JAX). Import the submodules directly, e.g. ``mysim_jax.perception.imu``."""
