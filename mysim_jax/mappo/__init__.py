"""MAPPO for the capture environment: a shared policy, a centralised critic, PPO (or SHAC).

* :mod:`mysim_jax.mappo.config` — training files (``env:``, ``algo:``, ``run:``), checked
  without JAX;
* :mod:`mysim_jax.mappo.trainer` — :class:`~mysim_jax.mappo.trainer.Trainer`: MAPPO's
  state, iteration and scan of iterations;
* :mod:`mysim_jax.mappo.shac` — :class:`~mysim_jax.mappo.shac.ShacTrainer` (``algo.name:
  shac``): the same trainer with the actor's gradient taken through the simulator over a
  short horizon; :func:`~mysim_jax.mappo.shac.make_trainer` picks the trainer of ``algo.name``;
* :mod:`mysim_jax.mappo.networks` — the actor, the critic and the deterministic policy;
* :mod:`mysim_jax.mappo.algorithm` — a whole run as a pure function of a key
  (:func:`~mysim_jax.mappo.algorithm.make_train`: start, warm start, iterations);
* :mod:`mysim_jax.mappo.losses` — GAE, the clipped objectives, running normalisers;
* :mod:`mysim_jax.mappo.checkpoint` — orbax checkpoints and the saved policy;
* :mod:`mysim_jax.mappo.run` — a training run, from the training file to the evaluated
  policy (``scripts/train.py``);
* :mod:`mysim_jax.mappo.run_files` — a run's folder: the checked run, its self-contained
  files and ``metrics.csv`` (no JAX);
* :mod:`mysim_jax.mappo.curriculum` — the curriculum's stage rule and state;
* :mod:`mysim_jax.mappo.bc` — cloning the scripted team, and starting from a saved policy;
* :mod:`mysim_jax.mappo.policies` — saved policies loaded and checked for evaluation;
* :mod:`mysim_jax.mappo.toy` — a small built-in task for tests and smoke runs.
"""
