"""The paper's collision scenes against an independent tight-tolerance reference.

Issue #3: with each scene's default settings, the ball's and the payload's z stay within
2e-3 m of a float64 tight-tolerance solution of the same equations over the first 1.5 s
(friction off for that comparison; on the symmetry axis of these scenes the tangential
slip is zero up to round-off: friction on moves the default run by < 5e-6 m).

Reference: tests/contact_reference.py — the rope-net and contact equations re-derived in
NumPy from the config fields (not from mysim_jax), written once more with jax.numpy and
integrated by diffrax's 8th-order Dopri8 at rtol 1e-12 (the library's default is the
5th-order tsit5). Its right-hand side is checked against the NumPy one, and its solution
against SciPy's DOP853 over the first impact.
"""

import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.io.trajectory import read_trajectory_csv
from mysim_jax.driver import simulate

from conftest import CONFIGS, ROOT
from contact_reference import CollisionNetReference

TOLERANCE_M = 2e-3        # issue #3
T_COMPARE = 1.5           # s
FRICTION_OFF = ["contact.friction=null", f"sim.t_end={T_COMPARE}"]
TIMES = np.arange(int(round(T_COMPARE / 1e-3)) + 1) * 1e-3

pytestmark = pytest.mark.float64


def _reference(name):
    with jax.enable_x64(True):
        cfg = load_config(CONFIGS / f"{name}.yaml", FRICTION_OFF)
        ref = CollisionNetReference(cfg)
        return ref, ref.solve_diffrax(TIMES)


@pytest.fixture(scope="module")
def light_reference():
    return _reference("collision_light")


@pytest.fixture(scope="module")
def heavy_reference():
    return _reference("collision_heavy")


def test_reference_rhs_and_solver_are_independent_and_agree(light_reference):
    ref, pos = light_reference
    rng = np.random.default_rng(0)
    acc = jax.jit(ref.jax_accelerations())
    for _ in range(3):                      # jax.numpy form == NumPy form, in contact
        x = ref.x0 + rng.normal(scale=1e-3, size=ref.x0.shape)
        x[1] = x[0] + [0.0, 0.0, 0.0599]
        v = rng.normal(size=x.shape)
        np.testing.assert_allclose(np.asarray(acc(jnp.asarray(x), jnp.asarray(v))), ref.accelerations(x, v),
                                   rtol=1e-10, atol=1e-8)
    # SciPy's DOP853 on the NumPy form agrees through the first impact (at ~0.31 s)
    n = 401
    scipy_pos = ref.solve(TIMES[n - 1], TIMES[:n], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(scipy_pos[:, :2, 2], pos[:n, :2, 2], atol=1e-8)
    assert pos[n - 1, 1, 2] - pos[n - 1, 0, 2] > 0.06 and pos[:n, 1, 2].min() < 0.05   # it hit and bounced


@pytest.mark.parametrize("name", ["collision_light", "collision_heavy"])
def test_default_settings_stay_within_2e_3_of_the_reference(name, request):
    ref, ref_pos = request.getfixturevalue("light_reference" if name.endswith("light") else "heavy_reference")
    config = load_config(CONFIGS / f"{name}.yaml", FRICTION_OFF)
    scene, params, state = build(config)
    assert scene.precision == "float64" and scene.integrator == "tsit5"    # the defaults
    t0 = time.perf_counter()
    traj = simulate(scene, params, state, config.run_settings(), progress=False)
    wall = time.perf_counter() - t0
    np.testing.assert_allclose(traj.time, TIMES, atol=1e-12)
    assert list(scene.point_names) == ref.names
    ball, payload = scene.point_names.index("ball"), scene.point_names.index("payload")
    err_ball = np.abs(traj.phys.point_pos[:, ball, 2] - ref_pos[:, ball, 2])
    err_payload = np.abs(traj.phys.point_pos[:, payload, 2] - ref_pos[:, payload, 2])
    print(f"{name} default (tsit5 rtol {scene.rtol:g}, float64): max |z error| ball {err_ball.max():.2e} m, "
          f"payload {err_payload.max():.2e} m over {T_COMPARE} s ({wall:.1f} s incl. compile)")
    assert err_ball.max() < TOLERANCE_M and err_payload.max() < TOLERANCE_M
    # the comparison is not vacuous: the ball bounces on the payload several times
    # (contacts last ~1e-4 s, so count the near-contact minima of the gap on the 1 ms grid)
    gap = ref_pos[:, ball, 2] - ref_pos[:, payload, 2] - 0.06
    bounces = (gap[1:-1] < gap[:-2]) & (gap[1:-1] <= gap[2:]) & (gap[1:-1] < 2e-3)
    assert np.count_nonzero(bounces) >= 3
    assert ref_pos[:, payload, 2].min() < -0.05


def test_simulate_script_writes_both_bodies_and_the_collision_plots(tmp_path):
    out = tmp_path / "light"
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "simulate.py"), str(CONFIGS / "collision_light.yaml"),
                          "--out", str(out), "--set", "sim.t_end=0.4", "--no-progress"],
                         capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    cols = read_trajectory_csv(out / "trajectory.csv")
    assert {"ball_z", "ball_vz", "ball_az", "payload_z", "payload_vz", "payload_az"} <= set(cols)
    assert cols["ball_z"][0] == pytest.approx(0.5) and cols["ball_z"].min() < 0.05     # it fell onto the net
    for who in ("payload", "ball"):
        for what in ("position", "velocity", "acceleration"):
            assert (out / f"{who}_{what}.png").stat().st_size > 10_000
