"""What a policy's observations and actions mean in a capture environment, and how two
environments differ in it.

A policy trained on one environment reads its observations and writes its actions in that
environment's terms: which setpoints the actions are (position or velocity), what an
action of 1 is (the flyable box's edge, or ``max_speed``), how often it acts, which feature
sits where in the observation, and what the catch-point features predict (a falling
target's fall, or an evading target's position). :func:`environment_contract` writes this
down for an environment (a trained policy's ``policy.json`` keeps it under
``environment``); :func:`contract_differences` lists, in words, where another environment
differs, so a policy flown on an environment it was not trained for is refused unless the
user says it is deliberate (``scripts/evaluate.py --allow-mismatch``).

The fidelity level, the scene's name, the per-episode ranges, the perception errors and
the physics are recorded too but are not a mismatch: evaluating a policy trained on the
level ``train`` on ``full``, on perceived states or under shifted ranges is what the
evaluations are for.
"""

from __future__ import annotations

import numpy as np

# the keys whose difference changes what the policy's inputs or outputs mean
MEANING_KEYS = ("target", "setpoint_mode", "policy_rate_hz", "action_scale", "observation_layout")


def observation_layout(env) -> list[tuple[str, int]]:
    """The observation's features in order, ``(name, width)``, for one agent (world frame,
    positions in m and velocities in m/s unless the name gives a scale); the widths sum to
    ``env.obs_size``."""
    n = env.n_agents
    return [("own_position", 3), ("own_velocity", 3), ("own_attitude_wxyz", 4), ("own_body_rate", 3),
            ("target_position_relative", 3), ("target_velocity_relative", 3),
            ("net_centre_position_relative", 3), ("net_centre_velocity_relative", 3),
            (f"teammates_position_velocity_relative_x{n - 1}", 6 * (n - 1)),
            ("catch_point_from_own_slot_per_2m", 3), ("time_to_catch_per_1s", 1),
            (f"agent_one_hot_x{n}", n), ("episode_fraction_left", 1)] + (
        [(f"top_thrust_fraction_own_then_teammates_x{n}", n)] if getattr(env, "observe_top_thrust", False) else [])


def _rounded(values) -> list:
    return np.round(np.asarray(values, dtype=float), 6).tolist()


def environment_contract(env, params) -> dict:
    """What observations and actions mean in ``env`` (a CaptureEnv) with ``params`` (its
    EnvParams), as plain JSON values."""
    cp = params.sim.controller
    mode = env.scene.quadrotor.setpoint_mode
    if mode == "velocity":
        scale = {"max_speed_m_s": _rounded(cp.max_speed)}
    else:
        scale = {"box_low_m": _rounded(cp.box_low), "box_high_m": _rounded(cp.box_high)}
    return {
        "scene": env.scene_name,
        "level": env.level,
        "target": "falling" if env.falling else "maneuvering",
        "agents": list(env.agents),
        "setpoint_mode": mode,
        "policy_rate_hz": round(1.0 / env.policy_dt, 6),
        "action_scale": scale,
        "observation_layout": [[name, width] for name, width in observation_layout(env)],
        "perception": bool(env.perception),
    }


def _words(key: str, value) -> str:
    if key == "policy_rate_hz":
        return f"{value:g} Hz"
    if key == "setpoint_mode":
        return f"{value} setpoints"
    if key == "target":
        return f"a {value} target"
    if key == "action_scale":
        # one value when every UAV has the same
        return ", ".join(f"{k} {v[0] if all(x == v[0] for x in v) else v}" for k, v in value.items())
    if key == "observation_layout":
        return f"{sum(w for _, w in value)} features ({', '.join(f'{n}:{w}' for n, w in value)})"
    return str(value)


def contract_differences(recorded: dict, current: dict) -> list[str]:
    """One phrase per meaning key (:data:`MEANING_KEYS`) where ``current`` differs from
    ``recorded``, e.g. ``"policy rate: trained at 10 Hz, this environment 25 Hz"``."""
    out = []
    for key in MEANING_KEYS:
        if key in recorded and recorded[key] != current.get(key):
            what = key.replace("_hz", "").replace("_", " ")
            out.append(f"{what}: trained with {_words(key, recorded[key])}, this environment has "
                       f"{_words(key, current.get(key))}")
    return out
