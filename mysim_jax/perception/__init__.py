"""Perception: cameras and the renderer, the IMU, visual-inertial odometry (gtsam), the
target detector (``detect/``: a colour baseline and a learned CNN trained with flax), gimbal
tracking and target localisation. Most of it runs on a finished trajectory, outside jit
(NumPy/OpenCV); gimbal tracking (``track.py``) runs the simulation in closed loop, and the
learned detector uses JAX. Import the submodules directly, e.g. ``mysim_jax.perception.imu``."""
