"""The training algorithm as pure functions of a key: what ``scripts/train.py`` trains,
without the files.

    train = make_train(config.algo, env, env_params, curriculum=config.env.curriculum)
    state, metrics = jax.jit(train)(key)                        # one seed
    states, metrics = jax.jit(jax.vmap(train))(keys)            # one seed per key, one program

A run is :func:`start` (networks and environments from the key, then the warm start of
``algo.init``: behaviour cloning of the scripted team, or a saved policy), then every PPO
iteration (:meth:`~mysim_jax.mappo.trainer.Trainer.iterations`, the curriculum inside
them). ``scripts/train.py`` (:func:`mysim_jax.mappo.run.train_run`) runs the same
functions with the same keys, and adds host steps between chunks of iterations that do
not change what is trained: model selection (it flies the current policy on fixed
episodes and keeps the best, :meth:`~mysim_jax.mappo.trainer.Trainer.keep_if_best`),
checkpoints, the metrics files and the final evaluation. Its policy is the selected one;
``make_train``'s state holds the last (``Trainer.policy_arrays``).
"""

from __future__ import annotations

from typing import Callable

import jax

from mysim_jax.mappo import bc
from mysim_jax.mappo.curriculum import Curriculum
from mysim_jax.mappo.shac import make_trainer
from mysim_jax.mappo.trainer import Trainer, TrainerState
from mysim_jax.tasks.capture import scaled_target_ranges


def run_keys(key) -> tuple:
    """``(k_init, k_warm)``: the keys of a run's networks and environments, and of its warm start."""
    k_init, k_warm = jax.random.split(key)
    return k_init, k_warm


def curriculum_of(config) -> Curriculum | None:
    """The :class:`~mysim_jax.mappo.curriculum.Curriculum` of an ``env.curriculum`` block
    (None without one), over the evading target's ranges
    (:func:`~mysim_jax.tasks.capture.scaled_target_ranges`)."""
    if config is None:
        return None
    if isinstance(config, Curriculum):
        return config
    return Curriculum(config, scaled_target_ranges)


def warm_start(trainer: Trainer, ts: TrainerState, key, init_policy: tuple | None = None):
    """``(state, stats)``: a fresh state ``ts`` after ``algo.init``'s warm start. ``bc``:
    the actor cloned from the scripted team (:func:`mysim_jax.mappo.bc.clone`; ``stats``
    its fit, :func:`mysim_jax.mappo.bc.report` makes it a dict); ``policy``: the actor of
    ``init_policy`` (``(meta, arrays)`` of :func:`mysim_jax.mappo.checkpoint.load_policy`,
    ``stats`` empty); ``none``: ``ts`` itself. Pure: jittable and vmappable over keys."""
    init = trainer.config.init
    if init == "bc":
        return bc.clone(trainer, ts, key)
    if init == "policy":
        if init_policy is None:
            raise ValueError("algo.init: policy needs the starting policy: init_policy=(meta, arrays) of load_policy")
        meta, arrays = init_policy
        return bc.from_policy(trainer, ts, meta, arrays, "the starting policy"), {}
    return ts, {}


def start(trainer: Trainer, key, init_policy: tuple | None = None):
    """``(state, stats)``: a run's start from ``key`` (:func:`run_keys`): networks,
    optimiser and ``num_envs`` reset environments (the curriculum's first stage), then the
    warm start (:func:`warm_start`). Pure."""
    k_init, k_warm = run_keys(key)
    return warm_start(trainer, trainer._init_state(k_init), k_warm, init_policy)


def make_train(config, env, env_params, curriculum=None, init_policy: tuple | None = None) -> Callable:
    """``train(key) -> (state, metrics)``: the whole run of ``config`` (an
    :class:`~mysim_jax.mappo.config.AlgoConfig`) from ``key``: :func:`start`, then
    ``config.num_iterations`` iterations as one ``lax.scan``, with ``curriculum`` (an
    ``env.curriculum`` block, or a :class:`~mysim_jax.mappo.curriculum.Curriculum`) when
    given. ``metrics`` holds each iteration's metrics stacked, ``(num_iterations,)`` per
    key. ``train`` is a pure function of ``key``: ``jax.jit(train)`` compiles the whole
    run, and ``jax.vmap(train)(keys)`` trains one seed per key in one program
    (``(n_seeds, ...)`` leaves). One device; model selection, checkpoints and evaluation
    are ``scripts/train.py``'s host steps (module docstring). ``train.trainer`` is the
    :class:`~mysim_jax.mappo.trainer.Trainer`."""
    trainer = make_trainer(config, env, env_params, curriculum=curriculum_of(curriculum))
    if config.init == "policy" and init_policy is None:
        raise ValueError("algo.init: policy needs the starting policy: make_train(..., init_policy=(meta, arrays)) "
                         "with mysim_jax.mappo.checkpoint.load_policy(folder)")

    def train(key):
        state, _ = start(trainer, key, init_policy)
        return trainer.iterations(state, config.num_iterations)

    train.trainer = trainer
    return train
