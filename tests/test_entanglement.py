"""Entanglement of an evading drone in the net's lines (mysim_jax/effects/entanglement.py).

The touch test is checked against a NumPy reference written here: the distance from the
target's centre to the net's knot lattice (straight segments between neighbouring knots,
which is where the line masses lie in the flat start state); the level's growth and the
propulsion's share against their definitions; and a short closed-loop run shows what
entanglement is for: a drone hovering on the net drops into it when its rotors tangle,
and keeps flying when they do not."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.sim import step
from mysim_jax.effects.entanglement import ENTANGLEMENT, rotors_touch_lines
from mysim_jax.tasks.scripted import team_policy
from mysim_jax.effects.target import TARGET, evasive_command

CONFIG = "configs/capture_env_maneuvering.yaml"
TIME, MARGIN = 0.2, 0.02
ENTANGLE = f"target.entanglement={{time: {TIME}, margin: {MARGIN}}}"


def _scene(overrides=()):
    cfg = load_config(CONFIG, [ENTANGLE, *overrides])
    return cfg, *build(cfg)


def _place(scene, state, pos, vel=(0.0, 0.0, 0.0)):
    b = scene.body_names.index("target")
    phys = state.phys.replace(body_pos=state.phys.body_pos.at[b].set(jnp.asarray(pos, state.phys.body_pos.dtype)),
                              body_vel=state.phys.body_vel.at[b].set(jnp.asarray(vel, state.phys.body_pos.dtype)))
    return state.replace(phys=phys)


def _lattice_distance(cfg, scene, state, p):
    """NumPy: distance from ``p`` to the segments between neighbouring knots."""
    net = cfg.net
    pos = np.asarray(state.phys.point_pos, float)
    knot = {(i, j): pos[scene.point_names.index(net.knot_name(i, j))] for i in range(net.knots) for j in range(net.knots)}
    best = np.inf
    for (i, j), a in knot.items():
        for di, dj in ((1, 0), (0, 1)):
            if (i + di, j + dj) in knot:
                b = knot[i + di, j + dj]
                t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
                best = min(best, np.linalg.norm(a + t * (b - a) - p))
    return best


def test_rotors_touch_lines_where_the_reference_says():
    cfg, scene, params, state = _scene()
    r = cfg.target.radius
    rng = np.random.default_rng(0)
    centre = np.asarray(cfg.net.center, float)
    touched = free = 0
    for _ in range(200):
        # over the net's inner part, where the nearest line is the lattice's and not a tether
        # (tethers are lines too, rising from the corner knots)
        radius, angle = 0.75 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        p = centre + np.r_[radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-0.05, 0.3)]
        d = _lattice_distance(cfg, scene, state, p) - r - cfg.contact.groups[3].radius
        if abs(d - MARGIN) < 1e-4:       # too close to the threshold for float32
            continue
        got = bool(rotors_touch_lines(scene, params, _place(scene, state, p).phys))
        assert got == (d <= MARGIN), (p, d)
        touched, free = touched + got, free + (not got)
    assert touched > 20 and free > 20


def test_entanglement_grows_with_contact_never_falls_and_scales_the_propulsion():
    cfg, scene, params, state = _scene()
    r = cfg.target.radius
    on_net = _place(scene, state, np.asarray(cfg.net.center) + [0.05, 0.03, r])
    away = _place(scene, state, np.asarray(cfg.net.center) + [0.0, 0.0, 1.0])
    level = 0.0
    s = on_net
    for k in range(int(TIME / scene.dt) + 5):
        _, memory = ENTANGLEMENT.update(scene, params, s)
        level = min(1.0, level + scene.dt / TIME)
        np.testing.assert_allclose(float(memory.level), level, rtol=1e-5, atol=1e-6)
        s = ENTANGLEMENT.with_memory(s, memory)
    assert float(memory.level) == 1.0
    moved = ENTANGLEMENT.with_memory(away, memory.replace(level=jnp.asarray(0.4)))
    _, after = ENTANGLEMENT.update(scene, params, moved)
    assert float(after.level) == pytest.approx(0.4) and not bool(after.touching)
    # the propulsion keeps the share 1 - e of its force m (a_cmd - g)
    a_cmd, _ = evasive_command(TARGET.static(scene), TARGET.params(params), TARGET.memory(moved), moved.phys,
                               moved.time)
    held, _ = TARGET.update(scene, params, moved)
    g = np.asarray(params.gravity)
    np.testing.assert_allclose(np.asarray(held) - g, 0.6 * (np.asarray(a_cmd) - g), rtol=1e-5, atol=1e-6)


def test_a_drone_hovering_on_the_net_drops_into_it_only_when_entangled():
    """The target dives onto the net's centre at 1 m/s, without fleeing or jinking (it
    only holds its altitude band and speed limit); the team holds its formation while the
    net, released flat, bags down under it (measured: its lowest knot 1.25 m lower after
    0.6 s, with or without the target). The entangled drone loses its lift and goes down
    with the net (1.4 m in 0.6 s, entanglement 1); the one without entanglement keeps its
    lift and stays near where it touched (0.28 m lower)."""
    def run(overrides):
        cfg, scene, params, state = _scene(["team={policy: hold}", "target.propulsion.flee_acceleration=0",
                                            "target.propulsion.jink_acceleration=0", *overrides])
        hold = team_policy(cfg, scene)
        b = scene.body_names.index("target")
        start = np.asarray(cfg.net.center) + [0.05, 0.03, cfg.target.radius + 0.01]
        s = _place(scene, state, start, vel=(0.0, 0.0, -1.0))

        def period(_, x):
            return step(scene, params, x, hold(scene, params, x))
        advance = jax.jit(lambda s: jax.lax.fori_loop(0, 300, period, s))
        end = advance(s)
        level = float(ENTANGLEMENT.memory(end).level) if ENTANGLEMENT.in_scene(scene) else 0.0
        return float(end.phys.body_pos[b, 2] - start[2]), level

    drop, level = run([])
    assert level == 1.0 and drop < -0.8, (drop, level)
    drop_free, _ = run(["target.entanglement=null"])
    assert drop_free > -0.4, drop_free


def test_entanglement_needs_target_line_contact_and_rotors():
    with pytest.raises(ConfigError, match="target.entanglement: the target's rotors tangle in net lines"):
        build(load_config(CONFIG, [ENTANGLE, "contact.pairs=[[target, uavs], [uavs, uavs]]"]))
    with pytest.raises(ConfigError, match="entanglement: a falling target has no rotors"):
        load_config("configs/capture_env_falling.yaml", [ENTANGLE])
    with pytest.raises(ConfigError, match="time"):
        load_config(CONFIG, ["target.entanglement={time: 0}"])


def test_simulate_verdict_needs_the_entanglement_column_to_reach_the_threshold():
    """capture_outcome (scripts/simulate.py's verdict) on a hand-built run: the target
    lies still on the flat net's centre for 1 s; it is caught only if its entanglement
    (the trajectory's ``target_entanglement`` column) is 1 over the last 0.5 s."""
    from mysim_jax.io.trajectory import trajectory_columns
    from mysim_jax.core.types import Trajectory
    from mysim_jax.effects.entanglement import EntanglementMemory
    from mysim_jax.tasks.outcome import capture_outcome
    from mysim_jax.core.types import Accelerations

    cfg, scene, params, state = _scene()
    s = _place(scene, state, np.asarray(cfg.net.center) + [0.05, 0.03, cfg.target.radius])
    times = np.linspace(0.0, 1.0, 26)
    phys = jax.tree.map(lambda a: np.repeat(np.asarray(a)[None], len(times), 0), s.phys)
    acc = Accelerations(point_acc=np.zeros_like(phys.point_pos), body_acc=np.zeros_like(phys.body_pos),
                        body_angacc=np.zeros_like(phys.body_pos))

    def caught(levels):
        memory = EntanglementMemory(level=np.asarray(levels, np.float32), touching=np.ones(len(times), bool))
        traj = Trajectory(time=times, phys=phys, acc=acc, effects={ENTANGLEMENT.name: memory})
        columns = trajectory_columns(scene, traj)
        np.testing.assert_array_equal(columns["target_entanglement"], np.asarray(levels, np.float32))
        return capture_outcome(columns, cfg)

    assert caught(np.where(times >= 0.4, 1.0, 0.5)).caught
    late = caught(np.where(times >= 0.6, 1.0, 0.5))
    assert not late.caught and late.first_held == pytest.approx(0.6)
    assert not caught(np.full(len(times), 0.95)).caught
    # the same run without the column is refused, not judged without entanglement
    traj = Trajectory(time=times, phys=phys, acc=acc)
    with pytest.raises(ValueError, match="target_entanglement"):
        capture_outcome(trajectory_columns(scene, traj), cfg)


def test_simulate_verdict_takes_the_scenes_success_thresholds():
    """capture_outcome reads env.success (min_entanglement here) when the scene has it."""
    from mysim_jax.io.trajectory import trajectory_columns
    from mysim_jax.core.types import Trajectory
    from mysim_jax.effects.entanglement import EntanglementMemory
    from mysim_jax.tasks.outcome import capture_outcome
    from mysim_jax.core.types import Accelerations

    cfg, scene, params, state = _scene(["env.success.min_entanglement=0.5"])
    s = _place(scene, state, np.asarray(cfg.net.center) + [0.05, 0.03, cfg.target.radius])
    times = np.linspace(0.0, 1.0, 26)
    phys = jax.tree.map(lambda a: np.repeat(np.asarray(a)[None], len(times), 0), s.phys)
    acc = Accelerations(point_acc=np.zeros_like(phys.point_pos), body_acc=np.zeros_like(phys.body_pos),
                        body_angacc=np.zeros_like(phys.body_pos))
    memory = EntanglementMemory(level=np.full(len(times), 0.6, np.float32), touching=np.ones(len(times), bool))
    columns = trajectory_columns(scene, Trajectory(time=times, phys=phys, acc=acc, effects={ENTANGLEMENT.name: memory}))
    assert capture_outcome(columns, cfg).caught
    assert not capture_outcome(columns, cfg, min_entanglement=1.0).caught
