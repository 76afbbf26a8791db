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

* a trained policy folder (``policy/`` of a ``scripts/train.py`` run: ``policy.json`` and
  ``policy.msgpack``, :mod:`mysim_jax.mappo.checkpoint`): the MAPPO actor's mean action.
  ``policy.json`` records what its observations and actions meant where it was trained
  (:func:`~mysim_jax.tasks.contract.environment_contract`: setpoint mode, policy rate,
  action scale, observation layout, target); an environment that differs in any of these
  is refused with the differences named, unless ``allow_mismatch`` (a deliberate test).

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

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.mappo.checkpoint import is_policy_folder, load_policy
from mysim_jax.mappo.networks import Actor, deterministic_policy
from mysim_jax.tasks.contract import contract_differences, environment_contract
from mysim_jax.tasks.evaluate import random_policy, scripted_policy

BUILTIN = ("scripted", "random")


class PolicyError(ValueError):
    """The policy spec cannot be used. The message names it and says why."""


def _usage() -> str:
    return ("give 'scripted', 'random', a trained policy folder, or a Python file defining "
            "make_policy(env, params) -> policy(key, obs, state, params)")


def check_policy_spec(spec: str, flag: str = "--policy") -> None:
    """Cheap checks of a spec that import nothing: a built-in name or an existing ``.py`` file."""
    if spec in BUILTIN:
        return
    path = Path(spec)
    if not path.exists():
        raise PolicyError(f"{flag} {spec}: not a built-in policy and no such file ({_usage()})")
    if path.is_dir():
        if is_policy_folder(path):
            return
        raise PolicyError(f"{flag} {spec}: is a folder without policy.json and policy.msgpack (a trained policy "
                          f"is the policy/ folder of a train.py run; {_usage()})")
    if path.suffix != ".py":
        raise PolicyError(f"{flag} {spec}: not a Python file (.py); {_usage()}")


def policy_maker(spec: str, flag: str = "--policy", allow_mismatch: bool = False):
    """``make_policy(env, params) -> policy`` for a spec (module docstring)."""
    check_policy_spec(spec, flag)
    if spec in BUILTIN:
        factory = scripted_policy if spec == "scripted" else random_policy
        return lambda env, params: factory(env)
    path = Path(spec)
    if path.is_dir():
        return _trained_policy_maker(path, flag, allow_mismatch)
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


def check_environment(meta: dict, env, params, where: str) -> None:
    """Refuse ``env`` when it differs from the environment a saved policy records in what
    its observations and actions mean (:mod:`mysim_jax.tasks.contract`). ``where`` names
    the policy in the message."""
    recorded = meta.get("environment")
    if recorded is None:
        raise PolicyError(f"{where}: policy.json does not record the environment it was trained on (saved by an "
                          "older version), so this one cannot be checked against it: pass --allow-mismatch to fly it "
                          "unchecked")
    differences = contract_differences(recorded, environment_contract(env, params))
    if differences:
        raise PolicyError(f"{where}: trained on another environment ({recorded.get('scene')}, level "
                          f"{recorded.get('level')}): {'; '.join(differences)}. Evaluate it on the scene it was "
                          "trained on (scene.yaml of its run folder), or pass --allow-mismatch to fly it here anyway")


def check_trained_on(meta: dict, env, params, where: str, allow_mismatch: bool = False) -> None:
    """Refuse ``env`` for a saved policy (``meta``: its policy.json) whose observation and
    action shapes differ from ``env``'s, or, unless ``allow_mismatch``, whose recorded
    environment means something else (:func:`check_environment`; capture environments).
    ``where`` names the policy in the message."""
    if int(meta["obs_size"]) != env.obs_size or tuple(meta["action_shape"]) != tuple(env.action_shape):
        raise PolicyError(f"{where}: trained on observations of size {meta['obs_size']} and actions "
                          f"{tuple(meta['action_shape'])}; this environment has {env.obs_size} and "
                          f"{tuple(env.action_shape)} (another number of UAVs?)")
    if not allow_mismatch and ("environment" in meta or hasattr(env, "scene")):
        check_environment(meta, env, params, where)


def widen_policy(meta: dict, arrays: dict | None, env, params, where: str) -> tuple[dict, dict | None]:
    """A saved policy (``meta``: its policy.json, ``arrays``: its arrays, or None to widen
    the record alone) made to read ``env``'s observations when they are the ones it was
    trained on with features appended (``env.observe_top_thrust``, say): its first layer
    gets zero weights for the new features, so it acts exactly as before, and its
    observation normalisation reads them as they are (mean 0, variance 1). A fine-tuning
    (``algo.init: policy``) then learns what to do with them. ``(meta, arrays)`` unchanged
    when the layouts are equal or the new one does not extend the recorded one (then
    :func:`check_trained_on` names the difference)."""
    recorded = (meta.get("environment") or {}).get("observation_layout")
    if recorded is None or not hasattr(env, "scene"):
        return meta, arrays
    current = [[name, width] for name, width in environment_contract(env, params)["observation_layout"]]
    recorded = [list(entry) for entry in recorded]
    if len(current) <= len(recorded) or current[:len(recorded)] != recorded:
        return meta, arrays
    extra = sum(width for _, width in current[len(recorded):])
    if int(meta["obs_size"]) + extra != env.obs_size:
        raise PolicyError(f"{where}: policy.json records {meta['obs_size']} observation features but an observation "
                          f"layout of {sum(w for _, w in recorded)}: the file is damaged")
    meta = {**meta, "obs_size": env.obs_size, "environment": {**meta["environment"], "observation_layout": current},
            "widened_from_obs_size": int(meta["obs_size"])}
    if arrays is None:
        return meta, None
    first = arrays["actor"]["params"]["Dense_0"]
    kernel = np.asarray(first["kernel"])
    kernel = np.concatenate([kernel, np.zeros((extra, kernel.shape[1]), kernel.dtype)], axis=0)
    actor = {**arrays["actor"], "params": {**arrays["actor"]["params"], "Dense_0": {**first, "kernel": kernel}}}
    mean = np.concatenate([np.asarray(arrays["obs_mean"]), np.zeros(extra, np.asarray(arrays["obs_mean"]).dtype)])
    var = np.concatenate([np.asarray(arrays["obs_var"]), np.ones(extra, np.asarray(arrays["obs_var"]).dtype)])
    return meta, {**arrays, "actor": actor, "obs_mean": mean, "obs_var": var}


def _trained_policy_maker(path: Path, flag: str, allow_mismatch: bool = False):
    """``make_policy`` of a saved MAPPO policy; it checks that the environment's
    observation and action shapes are those the policy was trained on and, unless
    ``allow_mismatch``, that they mean the same (:func:`check_environment`)."""
    try:
        meta, arrays = load_policy(path)
    except Exception as exc:    # a damaged file is an input error
        raise PolicyError(f"{flag} {path}: cannot read the saved policy: {type(exc).__name__}: {exc}") from None
    if meta.get("kind") != "mappo":
        raise PolicyError(f"{flag} {path}: policy.json kind {meta.get('kind')!r}, expected 'mappo'")

    def make_policy(env, params):
        check_trained_on(meta, env, params, f"{flag} {path}", allow_mismatch)
        actor = Actor(int(meta["action_shape"][1]), tuple(meta["hidden"]), meta["activation"])
        base = env.scripted_actions if meta.get("residual") else None
        return deterministic_policy(actor, arrays, bool(meta["normalize_obs"]), base)

    return make_policy


def check_policy(env, params, policy, spec: str = "policy", flag: str = "--policy") -> None:
    """Trace ``policy`` on the shapes of a reset (``jax.eval_shape``: nothing is compiled
    or run) and check that it returns a float array of shape ``env.action_shape``."""
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


def make_checked_policy(env, params, spec: str, flag: str = "--policy", allow_mismatch: bool = False):
    """The policy ``spec`` names (:func:`policy_maker`), made for ``env`` and checked on it
    (:func:`check_policy`). Any error in a user's ``make_policy`` is a PolicyError naming
    ``flag`` and ``spec``; a trained policy's environment check (``allow_mismatch``) too."""
    make_policy = policy_maker(spec, flag, allow_mismatch)
    try:
        policy = make_policy(env, params)
    except PolicyError:
        raise
    except Exception as err:   # make_policy is the user's code: any error in it is an input error
        raise PolicyError(f"{flag} {spec}: make_policy(env, params) failed: "
                          f"{type(err).__name__}: {err}") from None
    check_policy(env, params, policy, spec, flag)
    return policy
