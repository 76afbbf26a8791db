"""Policies of the capture environment by name, for the command-line scripts.

A policy spec is one of

* ``scripted`` — the scripted intercept team (:func:`~mysim_jax.tasks.evaluate.scripted_policy`);
* ``random`` — uniform actions in ``[-1, 1]`` (:func:`~mysim_jax.tasks.evaluate.random_policy`);
* the path of a Python file defining ``make_policy(env, params)``, which returns
  ``policy(key, obs, state, params) -> actions (n_agents, 3)`` for **one** environment
  (``obs`` ``(n_agents, obs_size)``, ``state`` an :class:`~mysim_jax.tasks.capture.EnvState`;
  the evaluator vmaps and jits it). For example::

      import jax.numpy as jnp

      def make_policy(env, params):
          def policy(key, obs, state, params):
              return jnp.zeros(env.action_shape, obs.dtype)   # hold the box's centre
          return policy

Trained checkpoints (MAPPO) are not loadable yet; their loader will be one more kind of
spec here (a checkpoint folder), so the scripts that take ``--policy`` need no change.

:func:`policy_maker` resolves a spec to a ``make_policy(env, params)`` function (it
imports a policy file, so call it after choosing JAX's precision); :func:`check_policy`
traces the policy once (no compilation) to check that it returns what
``CaptureEnv.step`` accepts. Both raise
:class:`PolicyError` with a one-line message.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BUILTIN = ("scripted", "random")


class PolicyError(ValueError):
    """The policy spec cannot be used. The message names it and says why."""


def _usage() -> str:
    return ("give 'scripted', 'random', or a Python file defining make_policy(env, params) -> "
            "policy(key, obs, state, params)")


def check_policy_spec(spec: str, flag: str = "--policy") -> None:
    """Cheap checks of a spec that import nothing: a built-in name or an existing ``.py`` file."""
    if spec in BUILTIN:
        return
    path = Path(spec)
    if not path.exists():
        raise PolicyError(f"{flag} {spec}: not a built-in policy and no such file ({_usage()})")
    if path.is_dir():
        raise PolicyError(f"{flag} {spec}: is a folder; trained checkpoints are not supported yet ({_usage()})")
    if path.suffix != ".py":
        raise PolicyError(f"{flag} {spec}: not a Python file (.py); {_usage()}")


def policy_maker(spec: str, flag: str = "--policy"):
    """``make_policy(env, params) -> policy`` for a spec (module docstring)."""
    check_policy_spec(spec, flag)
    if spec in BUILTIN:
        from mysim_jax.tasks.evaluate import random_policy, scripted_policy

        factory = scripted_policy if spec == "scripted" else random_policy
        return lambda env, params: factory(env)
    path = Path(spec)
    name = f"_mysim_policy_{path.stem}"
    module_spec = importlib.util.spec_from_file_location(name, path)
    if module_spec is None or module_spec.loader is None:
        raise PolicyError(f"{flag} {spec}: cannot be imported as a Python module")
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module
    try:
        module_spec.loader.exec_module(module)
    except Exception as exc:    # the file is the user's: any error in it is an input error
        sys.modules.pop(name, None)
        raise PolicyError(f"{flag} {spec}: importing it failed: {type(exc).__name__}: {exc}") from None
    make = getattr(module, "make_policy", None)
    if not callable(make):
        raise PolicyError(f"{flag} {spec}: defines no function make_policy(env, params) ({_usage()})")
    return make


def check_policy(env, params, policy, spec: str = "policy", flag: str = "--policy") -> None:
    """Trace ``policy`` on the shapes of a reset (``jax.eval_shape``: nothing is compiled
    or run) and check that it returns a float array of shape ``env.action_shape``."""
    import jax
    import jax.numpy as jnp

    if not callable(policy):
        raise PolicyError(f"{flag} {spec}: make_policy returned {type(policy).__name__}, not a function")
    key = jax.random.PRNGKey(0)
    try:
        obs, state = jax.eval_shape(env.reset, key, params)
        out = jax.eval_shape(policy, key, obs, state, params)
    except Exception as exc:    # the policy is the user's: report what it raised
        raise PolicyError(f"{flag} {spec}: calling policy(key, obs, state, params) failed: "
                          f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from None
    shape, dtype = getattr(out, "shape", None), getattr(out, "dtype", None)
    real = dtype is not None and (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer))
    if shape != env.action_shape or not real:
        got = f"shape {shape} dtype {dtype}" if shape is not None else type(out).__name__
        raise PolicyError(f"{flag} {spec}: the policy returns {got}; expected a real (float) array of shape "
                          f"{env.action_shape} (one action in [-1, 1] per UAV, one environment)")
