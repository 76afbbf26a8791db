"""The evading target's arena (``target.propulsion.arena``): the target's centre stays in
the box whatever its flight, and bad arenas are refused before anything compiles.

The flight is the target's own model integrated here, not through the scene: its
propulsion cancels gravity and adds the commanded acceleration
(:func:`mysim_jax.effects.target.evasive_command`, held over each ``sim.dt``), quadratic
drag slows it, the quadrotors stay where they start (the target flees their centroid,
so it runs for the walls)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.effects.target import TARGET, evasive_command, spawn_target

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "capture_env_maneuvering.yaml"
LOW, HIGH = np.array([-4.0, -4.0, 1.5]), np.array([4.0, 4.0, 5.0])
ARENA = f"target.propulsion.arena={{low: {LOW.tolist()}, high: {HIGH.tolist()}}}"


def _flights(overrides, n_targets=256, seconds=12.0):
    """Centre positions ``(n_targets, steps, 3)`` of targets spawned from distinct keys."""
    config = load_config(CONFIG, overrides)
    scene, params, state = build(config)
    static = TARGET.static(scene)
    tp = TARGET.params(params)
    b = static.body
    mass = params.body_mass[b]
    dt = scene.dt

    def flight(key):
        s = spawn_target(scene, params, state, key)

        def step(carry, _):
            phys, memory, t = carry
            cmd, memory = evasive_command(static, tp, memory, phys, t)
            v = phys.body_vel[b]
            acc = cmd - tp.drag_constant / mass * jnp.linalg.norm(v) * v
            v = v + dt * acc
            phys = phys.replace(body_vel=phys.body_vel.at[b].set(v),
                                body_pos=phys.body_pos.at[b].add(dt * v))
            return (phys, memory, t + dt), phys.body_pos[b]

        steps = int(round(seconds / dt))
        return jax.lax.scan(step, (s.phys, TARGET.memory(s), s.time), None, length=steps)[1]

    keys = jax.random.split(jax.random.PRNGKey(3), n_targets)
    return np.asarray(jax.jit(jax.vmap(flight))(keys))


def test_the_target_stays_in_its_arena_and_leaves_without_one():
    # the fastest, most evasive target the randomisation ranges allow
    fast = ["target.propulsion.max_speed=3.5", "target.propulsion.flee_acceleration=3.0",
            "target.propulsion.jink_acceleration=4.0"]
    inside = _flights(fast + [ARENA])
    overshoot = np.maximum(np.maximum(LOW - inside, inside - HIGH), 0.0).max()
    assert overshoot == 0.0, f"a target left the arena by {overshoot:.3g} m"
    # it does use the arena: most targets come within 1 m of a wall
    near_wall = np.minimum(inside - LOW, HIGH - inside)[..., :2].min(axis=(1, 2))
    assert np.mean(near_wall < 1.0) > 0.5
    free = _flights(fast + ["target.propulsion.arena=null"])
    assert np.mean(np.any((free[..., :2] < LOW[:2]) | (free[..., :2] > HIGH[:2]), axis=(1, 2))) > 0.5


@pytest.mark.parametrize("sets, message", [
    (["target.spawn.position={low: [-0.5, -0.5, 2.5], high: [0.5, 0.5, 4.0]}", "target.spawn.clearance=0",
      ARENA.replace("low: [-4.0, -4.0, 1.5]", "low: [-1.0, -4.0, 1.5]").replace("high: [4.0, 4.0", "high: [1.0, 4.0")],
     "target.propulsion.arena: 2 m and 8 m wide, no wider than the net (net.size = 2 m) on axis x: widen"),
    ([ARENA.replace("low: [-4.0, -4.0, 1.5]", "low: [-2.0, -4.0, 1.5]")],
     "spawn.position: the box (low [-2.5, -2.5, 2.5], high [2.5, 2.5, 4.0]) reaches outside propulsion.arena"),
    ([ARENA.replace("high: [4.0, 4.0, 5.0]", "high: [4.0, 4.0, 1.0]")], "propulsion.arena: empty range"),
    ([ARENA, "target.propulsion.altitude=[2.0, 6.0]"], "altitude: the band [2.0, 6.0] m is not inside the arena"),
    ([ARENA, "target.propulsion.wall_margin=-1"], "wall_margin"),
    ([ARENA, "target.propulsion.max_speed=-2"], "max_speed"),
])
def test_bad_arenas_are_one_line_errors(sets, message):
    with pytest.raises(ConfigError) as err:
        load_config(CONFIG, sets)
    text = str(err.value)
    problems = text.splitlines()[1:]          # the file's name, then one line per problem
    assert len(problems) == 1 and message in problems[0], text


def test_the_spawn_keeps_its_clearance_and_stays_uniform_over_what_is_left():
    """spawn.clearance: every one of 4096 spawns at least 1.5 m (horizontally) from the
    quadrotors' centroid and inside the box; the spawns' distances from the centroid
    distributed as uniform draws over the box with the disk cut out (a NumPy rejection
    sampler: mean and quartiles to within 4 standard errors); a first draw that is already
    clear is the spawn, the same as without a clearance."""
    def spawns(overrides, n=4096):
        config = load_config(CONFIG, overrides)
        scene, params, state = build(config)
        b = TARGET.static(scene).body
        keys = jax.random.split(jax.random.PRNGKey(11), n)
        return np.asarray(jax.jit(jax.vmap(lambda k: spawn_target(scene, params, state, k).phys.body_pos[b]))(keys))

    config = load_config(CONFIG)
    centre = np.mean([b.pos for b in config.bodies if b.name.startswith("uav")], axis=0)
    low, high = np.asarray(config.target.spawn.position.low), np.asarray(config.target.spawn.position.high)
    pos = spawns(["target.spawn.clearance=1.5"])
    r = np.linalg.norm(pos[:, :2] - centre[:2], axis=-1)
    assert r.min() >= 1.5 - 1e-5
    assert np.all(pos >= low - 1e-6) and np.all(pos <= high + 1e-6)
    ref = np.random.default_rng(0).uniform(low, high, (400_000, 3))
    ref_r = np.linalg.norm(ref[:, :2] - centre[:2], axis=-1)
    ref_r = ref_r[ref_r >= 1.5]
    se = ref_r.std() / np.sqrt(r.size)
    assert abs(r.mean() - ref_r.mean()) < 4 * se
    for q in (0.25, 0.5, 0.75):
        assert abs(np.mean(r <= np.quantile(ref_r, q)) - q) < 4 * np.sqrt(q * (1 - q) / r.size)
    # the first draw is the draw without a clearance, kept whenever it is already clear
    plain = spawns(["target.spawn.clearance=0"])
    kept = np.linalg.norm(plain[:, :2] - centre[:2], axis=-1) >= 1.5
    assert 0.5 < kept.mean() < 0.9
    np.testing.assert_array_equal(pos[kept], plain[kept])
    assert not np.any(np.all(pos[~kept] == plain[~kept], axis=-1))
    # the clearance is checked against the spawn box before anything compiles
    with pytest.raises(ConfigError, match=r"target.spawn.clearance: 4 m, but no spawn position"):
        load_config(CONFIG, ["target.spawn.clearance=4.0"])
