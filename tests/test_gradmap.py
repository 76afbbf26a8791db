"""The gradient map's pieces (mysim_jax/grad): the autodiff gradient of the capture
objective against central finite differences on a short free-flight horizon, the
smoothing estimator's convergence on a quadratic, and bad input refused before anything
compiles."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import CONFIGS, only_array_ops, run_script_main
from mysim_jax.config.scene import load_config
from mysim_jax.grad.engine import GradientEngine
from mysim_jax.grad.gradmap import MapSettings, check_settings
from mysim_jax.grad.objective import ObjectiveWeights
from mysim_jax.grad.rollout import horizon_values
from mysim_jax.grad.smoothing import cosine, smoothed_gradient
from mysim_jax.tasks.capture import make_env

# capture_env_falling.yaml at its cheap level, shrunk: a 3 x 3-knot net, velocity setpoints
# (the scripted team is then the VelocityTeam) at a 10 Hz policy
SMALL = ["level=train", "net.knots=3", "output.plot=[target, uav0]", "env.policy_rate=10.0", "sim.precision=float64",
         *[f"quadrotors.{i}.controller.setpoint_mode=velocity" for i in range(4)],
         *[f"quadrotors.{i}.controller.max_speed=5.0" for i in range(4)]]


@pytest.mark.float64
def test_the_autodiff_gradient_matches_central_differences_on_a_short_free_flight_horizon():
    env, params = make_env(load_config(CONFIGS / "capture_env_falling.yaml", SMALL))
    engine = GradientEngine(env, params, ObjectiveWeights())
    n, n_params = 2, engine.problem.team.size                        # 0.2 s: the target far above the net
    keys = jax.random.split(jax.random.PRNGKey(3), 1)
    s0 = jax.vmap(lambda k: env.reset(k, params)[1])(keys)
    u0, a0 = jnp.zeros((1, n_params)), jnp.zeros((1, n, *env.action_shape))

    def run(closed, u, actions):
        """J and the run (one program: the closed and open loop rollouts of one environment)."""
        rows, flown, states = engine.rollouts(s0, keys, [closed], u, actions, n, keep_states=True)
        return float(jax.vmap(lambda r: horizon_values(r, [n]))(rows)[0, 0]), flown, states

    _, actions, states = run(True, u0, a0)
    window = jax.tree.map(lambda a, b: jnp.concatenate([a[None], jnp.swapaxes(b, 0, 1)]), s0, states)
    g_team = np.asarray(engine.gradient(window, keys, u0, actions, n, closed_loop=True))[0]
    g_act = np.asarray(engine.gradient(window, keys, u0, actions, n, closed_loop=False))[0]
    # central differences: every team parameter, and the actions along one random direction
    h = 1e-5
    fd_team = np.array([(run(True, h * e[None], a0)[0] - run(True, -h * e[None], a0)[0]) / (2 * h)
                        for e in np.eye(n_params)])
    direction = np.asarray(jax.random.normal(jax.random.PRNGKey(4), actions.shape))
    fd_dir = (run(False, u0, actions + h * direction)[0] - run(False, u0, actions - h * direction)[0]) / (2 * h)
    assert np.linalg.norm(g_team) > 1e-3                             # the objective depends on the team
    # measured (float64, h = 1e-5): the largest difference 2e-10, 3e-10 of the largest
    # component, for the team; 6e-10 relative along the action direction. Tolerances ~10x.
    np.testing.assert_allclose(g_team, fd_team, rtol=0.0, atol=3e-9 * np.abs(fd_team).max())
    np.testing.assert_allclose(np.sum(g_act * direction[0]), fd_dir, rtol=6e-9)


def test_the_smoothing_estimate_converges_to_the_gradient_of_a_quadratic():
    a = jnp.diag(jnp.linspace(0.5, 3.0, 6))
    b = jnp.linspace(-1.0, 1.0, 6)
    x = jnp.linspace(0.3, -0.2, 6)

    def f(z):
        return 0.5 * z @ a @ z + b @ z

    true = a @ x + b                                                  # = the smoothed gradient (quadratic)
    errors, cosines = [], []
    for n_pairs in (4, 64, 1024):
        est = jnp.stack([smoothed_gradient(f, x, jax.random.PRNGKey(s), 0.1, n_pairs) for s in range(8)])
        errors.append(float(jnp.mean(jnp.linalg.norm(est - true, axis=1))))
        cosines.append(float(jnp.mean(jax.vmap(lambda e: cosine(e, true))(est))))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.15 * errors[0]                               # ~1/sqrt(N): 1/16 expected
    assert cosines[2] > 0.98 and cosines[0] < cosines[2]


def test_bad_settings_are_refused_with_the_setting_named():
    for settings, match in ((MapSettings(horizons=(-0.1,)), "horizon -0.1"),
                            (MapSettings(horizons=()), "horizons"),
                            (MapSettings(episodes=0), "episodes"),
                            (MapSettings(pairs=0), "pairs"),
                            (MapSettings(sigma_team=0.0), "sigma"),
                            (MapSettings(truncate=(0,)), "truncate"),
                            (MapSettings(segments=("landing",)), "segments")):
        with pytest.raises(ValueError, match=match):
            check_settings(settings)
    with pytest.raises(ValueError, match="longer than the episode"):
        check_settings(MapSettings(horizons=(7.0,)), policy_dt=0.1, t_end=6.0)
    with pytest.raises(ValueError, match="shorter than one policy step"):
        check_settings(MapSettings(horizons=(0.01,)), policy_dt=0.1, t_end=6.0)


@pytest.mark.parametrize("args, message", [
    (["--levels", "train", "coarse"], "coarse"),
    (["--horizons", "-1"], "horizon -1"),
    (["--horizons", "60"], "longer than the episode"),
    (["--cap", "full"], "--cap"),
    (["--cap", "train=0.05"], "horizon cap 0.05 s"),
])
def test_the_script_refuses_bad_input_before_compiling(tmp_path, capsys, args, message):
    out = tmp_path / "map"
    code, _, err, compiled = run_script_main("gradmap", [CONFIGS / "train_capture_falling.yaml", *args,
                                                         "--out", out, "--no-progress"], capsys)
    assert code == 2 and message in err and err.startswith("error:")
    assert only_array_ops(compiled) and not out.exists()


def test_the_optional_end_terms_are_the_target_height_off_the_net_and_under_the_clearance():
    """``vertical`` adds the target's smoothed height off the net's centre and ``ground``
    its depth under ``ground_clearance``, recomputed here in NumPy from the state; with
    both weights zero the end value is the plain one."""
    from mysim_jax.grad.objective import end_value

    env, params = make_env(load_config(CONFIGS / "capture_env_falling.yaml", SMALL[:3]))
    _, state = env.reset(jax.random.PRNGKey(0), params)
    phys = state.sim.phys
    target = np.asarray(phys.body_pos[env.target_body], np.float64)
    for z in (float(target[2]), 0.2):                                # spawned high, then near the ground
        pos = phys.body_pos.at[env.target_body, 2].set(z)
        s = state.replace(sim=state.sim.replace(phys=phys.replace(body_pos=pos)))
        knots = np.asarray(s.sim.phys.point_pos, np.float64)[np.asarray(env.knot_points)]
        vel = np.asarray(s.sim.phys.point_vel, np.float64)[np.asarray(env.knot_points)]
        centre, p = knots.mean(0), np.r_[target[:2], z]
        eps = 0.01
        smooth = lambda x: np.sqrt(np.sum(x * x) + eps * eps) - eps          # noqa: E731
        plain = smooth(p[:2] - centre[:2]) + 0.2 * smooth(np.asarray(s.sim.phys.body_vel[env.target_body]) - vel.mean(0))
        low = eps * np.log1p(np.exp((0.5 - z) / eps))
        w = ObjectiveWeights(vertical=1.0, ground=5.0)
        assert float(end_value(env, ObjectiveWeights(), s, params)) == pytest.approx(plain, rel=1e-5)
        assert float(end_value(env, w, s, params)) == pytest.approx(plain + smooth(p[2:] - centre[2:]) + 5.0 * low,
                                                                     rel=1e-5)
    assert low == pytest.approx(0.3, abs=1e-6)                            # 0.2 m against a 0.5 m clearance
    with pytest.raises(ValueError, match="ground"):
        ObjectiveWeights(ground=-1.0)
