"""Quadrotor control: cascaded PID (:mod:`.pid`), setpoints and their limits
(:mod:`.setpoint`), reference trajectories (:mod:`.reference`), the per-step control
stage (:mod:`.actuation`), configuration (:mod:`.config`), scene assembly (:mod:`.build`)
and gradient-based gain tuning (:mod:`.tuning`)."""
