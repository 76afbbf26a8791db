"""The non-cooperative target: a rigid sphere with air drag, falling or evading (an effect,
see docs/effects.md).

Forces on the target body (world frame, at its centre of mass):

* **air drag** ``F = −½ ρ C_d π r² |v| v`` (quadratic drag of a sphere, still air);
* **propulsion** (``behaviour: maneuvering``): ``F = m (a_cmd − g)``: the propulsion
  cancels gravity and adds the commanded acceleration ``a_cmd``, held over each
  environment step; with entanglement (:mod:`mysim_jax.effects.entanglement`) only the
  share ``1 − e`` of it is left.

Evasive behaviour (computed once per environment step; the team does not know it):

    a_cmd = flee · ĥ(p − c) + jink + altitude term + speed limit term, |a_cmd| <= max_acceleration

with ``c`` the centroid of the quadrotors, ``ĥ`` the horizontal unit vector away from
it, ``jink`` a horizontal acceleration of fixed size in a random direction redrawn at
random intervals (``jink_interval``), the altitude term a critically damped pull
(``altitude_gain``) back into the preferred altitude band, and the speed limit term
removing any push along the velocity once the speed reaches ``max_speed`` and braking
(time constant 0.25 s) above it. With an arena (``propulsion.arena``), braking at its
walls overrides the rest where the target would otherwise leave it (:func:`arena_braking`).

Randomness. The target's memory carries a PRNG key (``jax.random.PRNGKey`` raw form,
``(2,) uint32``); the spawn (:func:`spawn_target`) and every jink draw split it, so a run
is reproducible from its seed and batched environments draw independently when their
keys differ.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.core import rng, vecmath
from mysim_jax.core.effect import Effect
from mysim_jax.dynamics.forces import Loads
from mysim_jax.effects.entanglement import propulsion_share

SPEED_LIMIT_TIME_CONSTANT = 0.25   # s, braking back to max_speed
SPAWN_TRIES = 8                    # spawn positions drawn when the spawn keeps a clearance


@dataclass(frozen=True)
class TargetScene:
    """Static part: which body is the target, how it behaves."""

    body: int
    behaviour: str                    # "falling" | "maneuvering"
    has_drag: bool
    team_bodies: tuple[int, ...]      # quadrotor bodies (the centroid it flees)
    has_arena: bool = False           # a maneuvering target kept inside propulsion.arena
    has_clearance: bool = False       # the spawn keeps spawn.clearance from the team's centroid


@struct.dataclass
class TargetParams:
    """Traced target constants (vmap them to randomise per environment)."""

    drag_constant: jnp.ndarray        # () kg/m, ½ ρ C_d π r²
    spawn_pos_low: jnp.ndarray        # (3,) m
    spawn_pos_high: jnp.ndarray       # (3,) m
    spawn_vel_low: jnp.ndarray        # (3,) m/s
    spawn_vel_high: jnp.ndarray       # (3,) m/s
    max_acceleration: jnp.ndarray     # () m/s^2
    max_speed: jnp.ndarray            # () m/s
    flee_acceleration: jnp.ndarray    # () m/s^2
    jink_acceleration: jnp.ndarray    # () m/s^2
    jink_interval_low: jnp.ndarray    # () s
    jink_interval_high: jnp.ndarray   # () s
    altitude_low: jnp.ndarray         # () m
    altitude_high: jnp.ndarray        # () m
    altitude_gain: jnp.ndarray        # () 1/s^2
    arena_low: jnp.ndarray            # (3,) m, the box the target's centre stays in (if has_arena)
    arena_high: jnp.ndarray           # (3,) m
    wall_margin: jnp.ndarray          # () m, over which the braking at a wall blends in
    spawn_clearance: jnp.ndarray      # () m, horizontal distance of the spawn from the team's centroid


@struct.dataclass
class TargetMemory:
    """Target memory in the State."""

    key: jnp.ndarray                  # (2,) uint32 PRNG key
    jink: jnp.ndarray                 # (3,) m/s^2, current jink (horizontal)
    next_jink: jnp.ndarray            # () s, when the jink is redrawn


def evasive_command(static: TargetScene, tp: TargetParams, memory: TargetMemory, phys, t):
    """``(a_cmd (3,), memory)``: the evasive behaviour's commanded acceleration (module docstring)."""
    keys = jax.random.split(memory.key, 3)
    key = keys[0]
    redraw = t >= memory.next_jink
    angle, interval = rng.uniform_each(keys[1:], [(), ()], t.dtype,
                                       (0.0, tp.jink_interval_low), (2.0 * jnp.pi, tp.jink_interval_high))
    new_jink = tp.jink_acceleration * jnp.stack([jnp.cos(angle), jnp.sin(angle), jnp.zeros_like(angle)])
    jink = jnp.where(redraw, new_jink, memory.jink)
    next_jink = jnp.where(redraw, t + interval, memory.next_jink)

    p = phys.body_pos[static.body]
    v = phys.body_vel[static.body]
    centroid = jnp.mean(phys.body_pos[np.asarray(static.team_bodies, dtype=np.int32)], axis=0)
    away = (p - centroid).at[2].set(0.0)
    _, away = vecmath.safe_unit(away)
    z_ref = jnp.clip(p[2], tp.altitude_low, tp.altitude_high)
    a_alt = tp.altitude_gain * (z_ref - p[2]) - 2.0 * jnp.sqrt(tp.altitude_gain) * v[2]
    cmd = tp.flee_acceleration * away + jink + jnp.zeros_like(p).at[2].set(a_alt)
    speed, v_hat = vecmath.safe_unit(v)
    along = vecmath.dot(cmd, v_hat)
    at_limit = speed >= tp.max_speed
    cmd = cmd - jnp.where(at_limit & (along > 0.0), along, 0.0) * v_hat
    cmd = cmd - jnp.maximum(speed - tp.max_speed, 0.0) / SPEED_LIMIT_TIME_CONSTANT * v_hat
    size = vecmath.safe_norm(cmd)
    cmd = cmd * jnp.minimum(1.0, tp.max_acceleration / jnp.maximum(size, 1e-12))
    if static.has_arena:
        cmd = arena_braking(tp, p, v, cmd)
    return cmd, memory.replace(key=key, jink=jink, next_jink=next_jink)


def arena_braking(tp: TargetParams, p, v, cmd):
    """``cmd`` (3,) with the arena's walls enforced: on each axis, with ``d`` the distance
    to the wall the target moves toward and ``s = u² / (2 · ½ max_acceleration)`` its
    stopping distance at speed ``u`` toward it, the weight ``w = clip(1 − (d − s) /
    wall_margin, 0, 1)`` blends that component into full braking (``max_acceleration``
    away from the wall); the result is scaled back to ``max_acceleration``. Braking is
    planned at half the acceleration, so a target braking on two or three axes at once,
    each scaled to at least ``max_acceleration / √3``, still stops inside."""
    toward_high = v > 0.0
    distance = jnp.where(toward_high, tp.arena_high - p, p - tp.arena_low)
    stopping = v * v / tp.max_acceleration          # u² / (2 · ½ a_max)
    w = jnp.clip(1.0 - (distance - stopping) / tp.wall_margin, 0.0, 1.0)
    brake = jnp.where(toward_high, -tp.max_acceleration, tp.max_acceleration)
    cmd = (1.0 - w) * cmd + w * brake
    size = vecmath.safe_norm(cmd)
    return cmd * jnp.minimum(1.0, tp.max_acceleration / jnp.maximum(size, 1e-12))


def _drag_stage(scene, params, phys, nodes, held) -> Loads:
    static = TARGET.static(scene)
    v = phys.body_vel[static.body]
    force = -TARGET.params(params).drag_constant * vecmath.safe_norm(v) * v
    return _on_target(scene, phys, static.body, force)


def _propulsion_stage(scene, params, phys, nodes, held) -> Loads:
    static = TARGET.static(scene)
    force = params.body_mass[static.body] * (held - params.gravity)
    return _on_target(scene, phys, static.body, force)


def _on_target(scene, phys, body, force) -> Loads:
    dtype = phys.body_pos.dtype
    body_force = jnp.zeros((scene.n_bodies, 3), dtype=dtype).at[body].set(force)
    return Loads(node_force=jnp.zeros((scene.n_nodes, 3), dtype=dtype), body_force=body_force,
                 body_torque=jnp.zeros((scene.n_bodies, 3), dtype=dtype))


class _Target(Effect[TargetScene, TargetParams, TargetMemory]):
    """The target effect (docs/effects.md for the protocol)."""

    name = "target"

    def build(self, config, ctx):
        t = config.target
        if t is None:
            return None
        prop = t.propulsion_or_default()
        arena = prop.arena if prop is not None else None
        static = TargetScene(body=ctx.body_names.index(t.name), behaviour=t.behaviour,
                             has_drag=t.drag_constant > 0.0, team_bodies=tuple(ctx.quadrotor_bodies),
                             has_arena=arena is not None, has_clearance=t.spawn.clearance > 0.0)
        if static.behaviour == "maneuvering" and not static.team_bodies:
            raise ValueError("target.behaviour: a maneuvering target flees quadrotors, and the scene has none")

        def s(x):
            return jnp.asarray(x, dtype=ctx.dtype)

        params = TargetParams(
            drag_constant=s(t.drag_constant),
            spawn_pos_low=s(t.spawn.position.low), spawn_pos_high=s(t.spawn.position.high),
            spawn_vel_low=s(t.spawn.velocity.low), spawn_vel_high=s(t.spawn.velocity.high),
            max_acceleration=s(prop.max_acceleration if prop else 0.0),
            max_speed=s(prop.max_speed if prop else 0.0),
            flee_acceleration=s(prop.flee_acceleration if prop else 0.0),
            jink_acceleration=s(prop.jink_acceleration if prop else 0.0),
            jink_interval_low=s(prop.jink_interval.low if prop else 1.0),
            jink_interval_high=s(prop.jink_interval.high if prop else 1.0),
            altitude_low=s(prop.altitude[0] if prop else 0.0),
            altitude_high=s(prop.altitude[1] if prop else 0.0),
            altitude_gain=s(prop.altitude_gain if prop else 1.0),
            arena_low=s(arena.low if arena else (0.0, 0.0, 0.0)),
            arena_high=s(arena.high if arena else (0.0, 0.0, 0.0)),
            wall_margin=s(prop.wall_margin if prop else 1.0),
            spawn_clearance=s(t.spawn.clearance),
        )
        memory = TargetMemory(key=jax.random.PRNGKey(t.seed), jink=jnp.zeros(3, dtype=ctx.dtype),
                              next_jink=jnp.zeros((), dtype=ctx.dtype))
        return static, params, memory

    def update(self, scene, params, state):
        static = self.static(scene)
        memory = self.memory(state)
        if static.behaviour != "maneuvering":
            return None, memory
        cmd, memory = evasive_command(static, self.params(params), memory, state.phys, state.time)
        share = propulsion_share(scene, state)
        if share is not None:      # entangled rotors: the propulsion force m (a_cmd − g) scaled by the share
            cmd = params.gravity + share * (cmd - params.gravity)
        return cmd, memory

    def init(self, scene, params, state):
        """The seeded spawn: a draw from the key the memory holds (``target.seed``)."""
        return spawn_target(scene, params, state, self.memory(state).key)

    def stages(self, static):
        stages = []
        if static.has_drag:
            stages.append(("target_drag", _drag_stage))
        if static.behaviour == "maneuvering":
            stages.append(("target_propulsion", _propulsion_stage))
        return tuple(stages)


TARGET = _Target()


def _clear_spawn(static: TargetScene, tp: TargetParams, phys, key, first):
    """A spawn position at least ``spawn_clearance`` horizontally from the team's
    centroid: the first of ``first`` and SPAWN_TRIES − 1 more uniform draws that is, else
    the last draw pushed straight out to the clearance (SpawnConfig)."""
    dtype = first.dtype
    more = tp.spawn_pos_low + (tp.spawn_pos_high - tp.spawn_pos_low) * jax.random.uniform(
        jax.random.fold_in(key, 1), (SPAWN_TRIES - 1, 3), dtype)
    draws = jnp.concatenate([first[None], more], axis=0)
    centre = jnp.mean(phys.body_pos[np.asarray(static.team_bodies, dtype=np.int32)], axis=0)
    offset = (draws - centre).at[:, 2].set(0.0)
    clear = vecmath.safe_norm(offset) >= tp.spawn_clearance
    pick = jnp.where(jnp.any(clear), jnp.argmax(clear), SPAWN_TRIES - 1)
    chosen = draws[pick]
    distance, away = vecmath.safe_unit(offset[pick])
    pushed = chosen + jnp.maximum(tp.spawn_clearance - distance, 0.0) * away
    return jnp.where(jnp.any(clear), chosen, pushed)


def spawn_target(scene, params, state, key):
    """The state with the target placed by a fresh draw from its spawn ranges (uniform
    position and velocity, at rest in rotation) and its memory re-keyed. Pure: vmap it
    over keys to spawn a batch. The other bodies and points are not touched."""
    static = TARGET.static(scene)
    tp = TARGET.params(params)
    keys = jax.random.split(key, 3)      # position, velocity, the target's next key
    k_next = keys[2]
    dtype = state.phys.body_pos.dtype
    pos, vel = rng.uniform_each(keys[:2], [(3,), (3,)], dtype,
                                (tp.spawn_pos_low, tp.spawn_vel_low), (tp.spawn_pos_high, tp.spawn_vel_high))
    if static.has_clearance:
        pos = _clear_spawn(static, tp, state.phys, keys[0], pos)
    b = static.body
    phys = state.phys.replace(
        body_pos=state.phys.body_pos.at[b].set(pos),
        body_vel=state.phys.body_vel.at[b].set(vel),
        body_quat=state.phys.body_quat.at[b].set(jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype=dtype)),
        body_angvel=state.phys.body_angvel.at[b].set(0.0),
    )
    memory = TARGET.memory(state).replace(key=k_next, jink=jnp.zeros(3, dtype=dtype), next_jink=state.time)
    return TARGET.with_memory(state.replace(phys=phys), memory)
