"""The capture scene: net expansion, target, line drag, bad input, and the scripted catch.

References here are independent of the package's builder: mass lumping is summed from
the documented rule, the falling net's speed is the closed-form quadratic-drag fall
``v(t) = v_t tanh(g t / v_t)``.
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
import yaml

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict, load_config
from mysim_jax.driver import simulate
from conftest import CONFIGS

FALLING = CONFIGS / "capture_falling.yaml"
MANEUVERING = CONFIGS / "capture_maneuvering.yaml"


def raw(path=FALLING) -> dict:
    return yaml.safe_load(path.read_text())


def _small_net(knots=3, **net) -> dict:
    """Two hovering quadrotors (no controller needed) and a G x G net, no contact."""
    return {
        "name": "small_net",
        "sim": {"t_end": 0.1, "dt": 1e-3, "output_dt": 0.01, "substeps": "auto"},
        "bodies": [{"name": "u0", "mass": 0.28, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": [-0.6, -0.6, 2.7]},
                   {"name": "u1", "mass": 0.28, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": [0.6, -0.6, 2.7]}],
        "quadrotors": [{"body": "u0", "controller": None}, {"body": "u1", "controller": None}],
        "net": {"knots": knots, "size": 1.0, "center": [0.0, 0.0, 2.0],
                "tethers": {"uavs": ["u0", "u1"], "length": 1.0}, **net},
    }


# --- net expansion ------------------------------------------------------------------------


def test_net_expands_to_knots_ropes_and_tether_markers():
    cfg = config_from_dict(_small_net(knots=4, masses_per_edge=2, knot_mass=0.01))
    scene, params, _ = build(cfg)
    net = cfg.net
    g = 4
    knots = [f"net_k{i}_{j}" for i in range(g) for j in range(g)]
    assert all(k in scene.point_names for k in knots)
    n_edges = 2 * g * (g - 1)
    # every edge and tether is a rope of N masses and N + 1 segments
    assert len(scene.rope_names) == n_edges + 2
    assert scene.n_springs == n_edges * 3 + 2 * (net.tethers.n_masses + 1)
    assert "u0.net_tether" in scene.marker_names and "u1.net_tether" in scene.marker_names
    # mass lumping keeps every line's whole mass, plus the knots' own mass
    mu, a = net.line.mass_per_length, net.size / (g - 1)
    n_t = net.tethers.n_masses
    # a tether's interior masses and its knot-end half; the UAV-end half belongs to the UAV
    tether_mass = 2 * net.tethers.line.mass_per_length * net.tethers.length * (n_t + 0.5) / (n_t + 1)
    expected = n_edges * mu * a + g * g * 0.01 + tether_mass
    assert float(np.sum(params.point_mass)) == pytest.approx(expected, rel=1e-6)
    # default tethers go to the corners, in order
    assert cfg.net.tether_knots() == [(0, 0), (0, 3)]


def test_net_starts_slack_and_flat():
    cfg = config_from_dict(_small_net(knots=5))
    scene, params, state = build(cfg)
    pos = np.asarray(state.phys.point_pos)
    k = [scene.point_names.index(f"net_k{i}_{j}") for i in range(5) for j in range(5)]
    assert np.allclose(pos[k, 2], 2.0)
    spacing = np.diff(np.sort(np.unique(np.round(pos[k, 0], 9))))
    assert np.allclose(spacing, 0.25 * cfg.net.spread)


# --- bad input ----------------------------------------------------------------------------


@pytest.mark.parametrize("edit, field", [
    (lambda r: r["net"].update(knots=1), "net.knots"),
    (lambda r: r["net"]["tethers"].update(uavs=["u0", "u9"]), "net.tethers.uavs.1"),
    (lambda r: r["net"]["tethers"].update(uavs=["u0", "u0"]), "net.tethers.uavs.1"),
    (lambda r: r["net"]["tethers"].update(knots=[[0, 0], [5, 0]]), "net.tethers.knots.1"),
    (lambda r: r["net"]["tethers"].update(knots=[[0, 0]]), "net.tethers.knots"),
    (lambda r: r["net"]["tethers"].update(length=0.5), "would start stretched"),
    (lambda r: r["bodies"][1].update(pos=[3.0, 3.0, 2.7]), "net.tethers.uavs.1"),
])
def test_bad_net_is_named(edit, field):
    r = _small_net()
    edit(r)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.") if "." in field else field):
        config_from_dict(r)


def test_tether_to_a_body_that_is_not_a_quadrotor():
    r = _small_net()
    r["bodies"].append({"name": "crate", "mass": 1.0, "inertia": [0.1, 0.1, 0.1], "pos": [0.6, 0.6, 2.7]})
    r["net"]["tethers"]["uavs"] = ["u0", "crate"]
    with pytest.raises(ConfigError, match=r"net\.tethers\.uavs\.1: 'crate' is not a quadrotor body"):
        config_from_dict(r)



def test_a_quadrotor_on_a_missing_body_is_named_with_a_spawn_clearance():
    """The clearance check reads the quadrotors' bodies: one that names no body is the
    quadrotor check's error, not a crash of the clearance check (a fuzzed --set found it)."""
    with pytest.raises(ConfigError, match=r"quadrotors\.1\.body: 'nan' is not a body"):
        load_config(CONFIGS / "capture_env_maneuvering.yaml", ["quadrotors.1.body=nan"])
@pytest.mark.parametrize("edit, message", [
    (lambda t: t["spawn"]["position"].update(low=[0.0, 0.0, 7.0], high=[1.0, 1.0, 6.0]),
     r"target\.spawn\.position.*empty range: low > high on axis z"),
    (lambda t: t["spawn"]["velocity"].update(low=[1.0, 0.0, 0.0], high=[0.0, 0.0, 0.0]),
     r"target\.spawn\.velocity.*empty range: low > high on axis x"),
    (lambda t: t["spawn"]["position"].update(low=[0.0, 0.0, 0.05]),
     r"target.*spawn\.position\.low: z = 0\.05 m puts the target below the ground"),
    (lambda t: t["spawn"]["position"].update(low=[0.0, 0.0, -1.0]), r"below the ground"),
    (lambda t: t.update(propulsion={"max_speed": 2.0}), r"target.*a falling target has no propulsion"),
    (lambda t: t.update(mass=-0.1), r"target\.mass"),
])
def test_bad_target_is_named(edit, message):
    r = raw()
    edit(r["target"])
    with pytest.raises(ConfigError, match=message):
        config_from_dict(r)


def test_target_contact_radius_must_match_the_target():
    r = raw()
    r["target"]["radius"] = 0.1
    with pytest.raises(ConfigError, match=r"contact\.groups\.0\.radius: 0\.15 m, but target 'target' has radius 0\.1 m"):
        config_from_dict(r)


def test_team_outside_the_flyable_box_is_named():
    r = raw()
    r["team"]["altitude"] = 50.0
    with pytest.raises(ConfigError, match=r"team\.altitude: 50 m is outside quadrotors\.0's flyable box"):
        config_from_dict(r)


def test_validating_a_capture_config_does_not_import_jax():
    import subprocess
    import sys

    code = ("import sys; from mysim_jax.config.scene import load_config; "
            f"load_config(r'{FALLING}'); load_config(r'{MANEUVERING}'); "
            "assert 'jax' not in sys.modules, 'jax imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


# --- target -------------------------------------------------------------------------------


def test_spawn_is_reproducible_from_the_seed_and_inside_the_ranges():
    cfg = load_config(FALLING)
    s1 = build(cfg)[2]
    s2 = build(cfg)[2]
    s3 = build(load_config(FALLING, ["target.seed=7"]))[2]
    body = build(cfg)[0].body_names.index("target")
    p1, p2, p3 = (np.asarray(s.phys.body_pos[body]) for s in (s1, s2, s3))
    assert np.array_equal(p1, p2)
    assert not np.allclose(p1, p3)
    spawn = cfg.target.spawn
    for s in (s1, s3):
        p, v = np.asarray(s.phys.body_pos[body]), np.asarray(s.phys.body_vel[body])
        assert np.all(p >= np.asarray(spawn.position.low) - 1e-6) and np.all(p <= np.asarray(spawn.position.high) + 1e-6)
        assert np.all(v >= np.asarray(spawn.velocity.low) - 1e-6) and np.all(v <= np.asarray(spawn.velocity.high) + 1e-6)


def test_spawn_vmaps_over_keys():
    from mysim_jax.effects.target import TARGET, spawn_target

    scene, params, state = build(load_config(FALLING))
    body = scene.body_names.index("target")
    keys = jax.random.split(jax.random.PRNGKey(3), 64)
    states = jax.vmap(lambda k: spawn_target(scene, params, state, k))(keys)
    p = np.asarray(states.phys.body_pos[:, body])
    assert len(np.unique(p[:, 0])) == 64
    low, high = np.asarray(TARGET.params(params).spawn_pos_low), np.asarray(TARGET.params(params).spawn_pos_high)
    assert np.all(p >= low - 1e-6) and np.all(p <= high + 1e-6)
    # a uniform draw: the mean of 64 draws is within 4 standard errors of the middle
    sem = (high - low) / math.sqrt(12.0 * 64)
    assert np.all(np.abs(p.mean(axis=0) - 0.5 * (low + high)) < 4 * sem)
    # the other bodies do not move
    others = np.asarray([i for i in range(scene.n_bodies) if i != body])
    assert np.array_equal(np.asarray(states.phys.body_pos[:, others]), np.broadcast_to(
        np.asarray(state.phys.body_pos[others]), (64, len(others), 3)))


def _evader_scene(seed=0):
    """One hovering quadrotor (held by its reference) and the maneuvering target, no net."""
    r = raw(MANEUVERING)
    target = r["target"]
    target["seed"] = seed
    return {
        "name": "evader", "sim": {"t_end": 3.0, "dt": 2e-3, "output_dt": 0.02},
        "bodies": [{"name": "u0", "mass": 0.28, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": [0.0, 0.0, 3.0]}],
        "quadrotors": [{"body": "u0", "reference": {"center": [0.0, 0.0, 3.0]}}],
        "target": target,
        "output": {"plot": ["target"]},
    }


def test_maneuvering_target_keeps_its_limits_and_is_reproducible():
    runs = {}
    for seed in (0, 0, 1):
        cfg = config_from_dict(_evader_scene(seed))
        scene, params, state = build(cfg)
        traj = simulate(scene, params, state, cfg.run_settings(), progress=False)
        assert traj.ok
        b = scene.body_names.index("target")
        runs.setdefault(seed, []).append((np.asarray(traj.phys.body_pos[:, b]), np.asarray(traj.phys.body_vel[:, b]),
                                          np.asarray(traj.acc.body_acc[:, b])))
    (p0, v0, a0), (p0b, _, _) = runs[0]
    p1 = runs[1][0][0]
    assert np.array_equal(p0, p0b)                     # same seed, same path
    assert np.max(np.linalg.norm(p0 - p1, axis=1)) > 0.5  # another seed, another path
    prop = config_from_dict(_evader_scene()).target.propulsion
    speed = np.linalg.norm(v0, axis=1)
    # the propulsion stops pushing at max_speed and brakes above it (drag also slows it)
    assert speed.max() < prop.max_speed * 1.05
    assert speed.max() > prop.max_speed * 0.7          # it does run
    # commanded acceleration within max_acceleration: what is left after gravity
    # compensation and drag (drag at most ½ρC_dπr² v² / m) is within the limit
    drag = 0.5 * 1.225 * 0.47 * math.pi * 0.15 ** 2 * speed ** 2 / 0.3
    assert np.all(np.linalg.norm(a0, axis=1) <= prop.max_acceleration + drag + 1e-3)
    # it flees: it ends farther from the quadrotor than it started
    assert np.linalg.norm(p0[-1, :2]) > np.linalg.norm(p0[0, :2]) + 1.0


# --- line drag ------------------------------------------------------------------------------


@pytest.mark.float64
def test_free_falling_net_reaches_the_closed_form_drag_speed():
    """A flat net without tethers falls undeformed (every mass has the same drag area per
    kilogram), so each mass follows ``v(t) = v_t tanh(g t / v_t)`` with
    ``v_t = √(μ g / (½ ρ C_d d))``."""
    r = {"name": "falling_net", "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 0.01, "integrator": "rk4",
                                        "precision": "float64", "substeps": "auto"},
         "net": {"knots": 4, "size": 0.6, "center": [0.0, 0.0, 10.0], "spread": 1.0}}
    cfg = config_from_dict(r)
    scene, params, state = build(cfg)
    traj = simulate(scene, params, state, cfg.run_settings(), progress=False)
    line = cfg.net.line
    v_t = math.sqrt(line.mass_per_length * 9.81 / (0.5 * 1.225 * line.drag_coefficient * line.diameter))
    expected = -v_t * np.tanh(9.81 * traj.time / v_t)
    vz = np.asarray(traj.phys.point_vel[..., 2])
    err = np.max(np.abs(vz - expected[:, None]))
    assert err < 1e-12                                  # measured 8e-15 (rk4 at the auto step: round-off)
    assert vz[-1].mean() < -0.9 * v_t                   # it nearly reached terminal speed


def test_scene_without_net_or_target_traces_no_effect():
    scene, params, state = build(load_config(CONFIGS / "rope_net.yaml", ["sim.precision=float32"]))
    assert scene.effects == () and params.effects == {} and state.effects == {}


# --- the scripted catch ---------------------------------------------------------------------


def test_scripted_team_catches_the_falling_target_on_the_default_seed():
    from mysim_jax.io.trajectory import trajectory_columns
    from mysim_jax.tasks.outcome import capture_outcome
    from mysim_jax.tasks.scripted import team_policy

    cfg = load_config(FALLING, ["sim.t_end=4"])         # the catch is over by 3 s
    scene, params, state = build(cfg)
    traj = simulate(scene, params, state, cfg.run_settings(), progress=False, policy=team_policy(cfg, scene))
    assert traj.ok
    columns = trajectory_columns(scene, traj)
    outcome = capture_outcome(columns, cfg)
    assert outcome.caught, outcome.summary()
    # the UAVs never came near the ground
    uav_z = np.asarray(traj.phys.body_pos[:, [scene.body_names.index(q.body) for q in cfg.quadrotors], 2])
    assert uav_z.min() > 2.0
    # without the team the target is not held: the net does not come to it, and the target
    # falls past it to the ground (radius 0.15 m; it touches down about 1.5 s in)
    hold = load_config(FALLING, ["team.policy=hold", "sim.t_end=1.6"])
    traj_hold = simulate(scene, params, state, hold.run_settings(), progress=False, policy=team_policy(hold, scene))
    columns_hold = trajectory_columns(scene, traj_hold)
    assert not capture_outcome(columns_hold, hold).caught
    assert columns_hold["target_z"].min() < 0.25


# --- the script ---------------------------------------------------------------------------


def test_simulate_script_writes_the_capture_outputs_and_refuses_a_bad_tether(tmp_path, capsys):
    import json
    import subprocess
    import sys

    from conftest import ROOT, only_array_ops, run_script_main

    script = ROOT / "scripts" / "simulate.py"
    out = tmp_path / "capture"
    res = subprocess.run([sys.executable, str(script), str(FALLING), "--out", str(out), "--no-progress",
                          "--set", "sim.t_end=0.2", "--set", "sim.output_dt=0.05"], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert "target not caught" in res.stdout          # 0.2 s: it is still falling
    for name in ("capture_top.png", "capture_side.png", "capture_distances.png", "capture_tensions.png"):
        assert (out / name).stat().st_size > 10_000
    assert (out / "capture.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    metrics = json.loads((out / "metrics.json").read_text())
    capture = metrics["capture"]
    assert capture["caught"] is False and capture["at_end"]["above_ground"] is True
    assert set(capture["thrust_fraction_last_1s"]) == {"uav0", "uav1", "uav2", "uav3"}
    assert 0.3 < capture["thrust_fraction_last_1s"]["uav0"] < 0.6
    # a tether to a UAV that does not exist: exit 2, a message naming the field, nothing
    # compiled or written (the script's main() in this process: conftest.run_script_main)
    bad = tmp_path / "bad"
    code, _, err, compiled = run_script_main("simulate", [FALLING, "--out", bad, "--no-progress",
                                                          "--set", "net.tethers.uavs.3=uav7"], capsys)
    assert code == 2
    assert "net.tethers.uavs.3: 'uav7' is not a quadrotor body" in err
    assert only_array_ops(compiled) and not bad.exists()


def test_capture_sweep_draws_the_spawn_of_each_seed_as_build_does():
    from mysim_jax.tasks.sweep import capture_sweep

    cfg = load_config(FALLING, ["sim.t_end=0.2"])
    result = capture_sweep(cfg, [0, 5])
    assert len(result.outcomes) == 2 and result.caught == 0          # 0.2 s: still falling
    for k, seed in enumerate((0, 5)):
        scene, _, state = build(load_config(FALLING, [f"target.seed={seed}"]))
        b = scene.body_names.index("target")
        np.testing.assert_array_equal(result.spawn[k], np.asarray(state.phys.body_pos[b]))
    assert np.all(result.min_uav_height > 3.0)


@pytest.mark.parametrize("k, n", [(20, 24), (0, 5), (5, 5), (1, 2)])
def test_wilson_interval_solves_its_defining_equation(k, n):
    """The Wilson bounds b are the roots of (p − b)² = z² b (1 − b) / n (closed interval
    at k = 0 and k = n, where one root is 0 or 1)."""
    from mysim_jax.tasks.sweep import wilson_interval

    z, p = 1.96, k / n
    lo, hi = wilson_interval(k, n, z)
    assert 0.0 <= lo <= p <= hi <= 1.0
    for b in (lo, hi):
        assert (p - b) ** 2 == pytest.approx(z * z * b * (1 - b) / n, abs=1e-12)
    with pytest.raises(ValueError):
        wilson_interval(0, 0)


def test_wilson_interval_is_closed_at_zero_and_all_successes():
    """At k = 0 the lower bound is exactly 0 and at k = n the upper bound exactly 1, for
    every n (computed through the square root, one in five of n <= 2000 landed a rounding
    error inside the rate, and a plot's error bar got a negative length)."""
    from mysim_jax.tasks.sweep import wilson_interval

    for n in range(1, 2001):
        assert wilson_interval(0, n)[0] == 0.0 and wilson_interval(n, n)[1] == 1.0, n
