"""MAPPO for the capture environment: a shared policy, a centralised critic, PPO.

* :mod:`mysim_jax.mappo.config` — training files (``env:``, ``algo:``, ``run:``), checked
  without JAX;
* :mod:`mysim_jax.mappo.trainer` — :class:`~mysim_jax.mappo.trainer.Trainer` and
  :func:`~mysim_jax.mappo.trainer.make_train`;
* :mod:`mysim_jax.mappo.losses` — GAE, the clipped objectives, running normalisers;
* :mod:`mysim_jax.mappo.checkpoint` — orbax checkpoints and the saved policy;
* :mod:`mysim_jax.mappo.run` — a run folder on disk (``scripts/train.py``);
* :mod:`mysim_jax.mappo.toy` — a small built-in task for tests and smoke runs.
"""
