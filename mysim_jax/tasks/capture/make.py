"""The capture environment of a scene file: :func:`make_env` builds the scene and reads
the ``env:`` block into a :class:`~mysim_jax.tasks.capture.env.CaptureEnv` (static) and
its :class:`~mysim_jax.tasks.capture.types.EnvParams` (traced)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mysim_jax.build import build
from mysim_jax.config.capture import TeamConfig
from mysim_jax.config.env import REWARD_TERMS, NoiseConfig
from mysim_jax.tasks.capture.env import CaptureEnv
from mysim_jax.tasks.capture.perception_errors import (perception_levels, perception_scale, target_delay,
                                                       target_dropout)
from mysim_jax.tasks.capture.randomisation import episode_ranges
from mysim_jax.tasks.capture.types import EnvParams
from mysim_jax.tasks.outcome import border_knots
from mysim_jax.tasks.scripted import team_policy


def line_contact_radius(scene, params, target_body: int, line_springs, default: float) -> float:
    """Radius [m] of the net's lines as the target touches them, read from the built
    contact scene: the largest capsule radius among the sphere–capsule pairs of the
    target's sphere and the capsules on ``line_springs`` (spring names), or ``default``
    (half the line's diameter) when the scene pairs none. The environment's ``touching``
    check measures the gap from there, so a level that thickens the lines for contact
    counts a touch where its contact acts."""
    cs = scene.contact
    if cs is None or not cs.n_capsule_pairs or target_body not in cs.sphere_body:
        return default
    sphere = len(cs.sphere_point) + cs.sphere_body.index(target_body)
    lines = set(line_springs)
    radius = np.asarray(params.contact.capsule_radius, float)
    radii = [radius[c] for a, c in zip(cs.capsule_pair_sphere, cs.capsule_pair_capsule)
             if a == sphere and cs.capsule_names[c] in lines]
    return float(max(radii)) if radii else default


def make_env(config, discount: float | None = None) -> tuple[CaptureEnv, EnvParams]:
    """The environment of a capture SceneConfig with an ``env:`` block (ValueError
    naming what is missing otherwise). ``discount``: γ of the potential-based shaping
    (``EnvParams.discount``; a trainer passes its own, ``algo.gamma``, so that the shaping
    leaves the optimal policy unchanged), in (0, 1]; None: the file's ``env.discount``."""
    if config.env is None:
        raise ValueError(f"scene '{config.name}': no env: block (add `env: {{}}` for the defaults)")
    if discount is not None and not 0.0 < discount <= 1.0:
        raise ValueError(f"discount: {discount!r}, expected a value in (0, 1] (γ of the reward shaping)")
    env_cfg, net = config.env, config.net
    scene, params, state = build(config)
    team = team_policy(config.model_copy(update={"team": config.team or _default_team()}), scene)
    quads = [q.body for q in config.quadrotors]
    bodies = {b.name: b for b in config.bodies}
    start = np.asarray([bodies[q].pos for q in quads], float)
    slots = start - start.mean(axis=0)
    slots[:, 2] = 0.0
    knots = [net.knot_name(i, j) for i in range(net.knots) for j in range(net.knots)]
    line_names = [n for n in scene.spring_names if n.startswith((f"{net.name}_h", f"{net.name}_v"))]
    line_index = [scene.spring_names.index(n) for n in line_names]
    n_points = scene.n_points
    a = [scene.spring_node_a[i] for i in line_index]
    b = [scene.spring_node_b[i] for i in line_index]
    if max(a + b) >= n_points:
        raise ValueError("net lines must join point masses")
    tethers = [scene.marker_names.index(f"{u}.{net.name}_tether") for u in net.tethers.uavs] if net.tethers else []
    if not tethers:
        raise ValueError("env: the net has no tethers (net.tethers), so nothing carries it")
    control_steps = int(round(1.0 / env_cfg.policy_rate / config.sim.dt))
    max_steps = int(round(config.sim.t_end / (control_steps * config.sim.dt)))
    env = CaptureEnv(
        scene=scene, n_agents=len(quads), agents=tuple(quads),
        quad_bodies=tuple(scene.body_names.index(q) for q in quads),
        target_body=scene.body_names.index(config.target.name), target_radius=float(config.target.radius),
        line_radius=line_contact_radius(scene, params, scene.body_names.index(config.target.name), line_names,
                                        0.5 * float(net.line.diameter)),
        knot_points=tuple(scene.point_names.index(k) for k in knots),
        border_points=tuple(scene.point_names.index(k) for k in border_knots(net)),
        tether_markers=tuple(tethers), line_nodes_a=tuple(a), line_nodes_b=tuple(b),
        slots=tuple(map(tuple, slots.tolist())), control_steps=control_steps, max_steps=max_steps,
        policy_dt=control_steps * config.sim.dt, success=env_cfg.success, failure=env_cfg.failure,
        scales=env_cfg.reward_scales, randomized_wind=env_cfg.randomize.wind_force is not None, scripted=team,
        thrust_loss=env_cfg.randomize.thrust_loss is not None,
        observe_top_thrust=env_cfg.observe_top_thrust,
        fault_failsafe=env_cfg.fault_failsafe,
        falling=config.target.behaviour == "falling",
        target_drag_per_mass=float(config.target.drag_constant / config.target.mass),
        gravity=tuple(float(g) for g in config.gravity),
        perception=env_cfg.perception is not None, scene_name=config.name, level=config.level,
        observation_noise=any(getattr(env_cfg.noise, f).high > 0.0 for f in NoiseConfig.model_fields))
    weights = env_cfg.weights()
    env_params = EnvParams(sim=params, start=state,
                           weights=jnp.asarray([weights[k] for k in REWARD_TERMS], scene.dtype),
                           discount=jnp.asarray(env_cfg.discount if discount is None else discount, scene.dtype),
                           ranges=episode_ranges(config, scene.dtype, len(quads)),
                           perception=perception_levels(env_cfg.perception, control_steps * config.sim.dt,
                                                        scene.dtype),
                           target_delay=jnp.asarray(target_delay(env_cfg.perception, control_steps * config.sim.dt),
                                                    scene.dtype),
                           target_dropout=jnp.asarray(target_dropout(env_cfg.perception,
                                                                      control_steps * config.sim.dt), scene.dtype),
                           perception_scale=jnp.asarray(perception_scale(env_cfg.perception), scene.dtype))
    return env, env_params


def _default_team():
    return TeamConfig(policy="scripted")
