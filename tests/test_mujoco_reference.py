"""Independent-engine check: the rope net in mysim_jax against MuJoCo (C engine).

The scene is exported with :func:`mysim_jax.io.mjcf.scene_to_mjcf` (point masses on slide
joints, ropes as spatial tendons with stiffness / damping / springlength) and stepped by
MuJoCo's Euler integrator, which is semi-implicit like ours. With the same step (1e-4 s)
in float64 the two engines take the same discrete steps, so they must agree to round-off,
not merely to a discretisation tolerance: a wrong sign, a missing damping term or an
explicit-vs-semi-implicit mix-up shows up as errors of 1e-6 m or more within 0.1 s.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from mysim_jax.build import build  # noqa: E402
from mysim_jax.config.scene import load_config  # noqa: E402
from mysim_jax.io.mjcf import mujoco_point_positions, mujoco_point_velocities, scene_to_mjcf  # noqa: E402
from mysim_jax.sim import accelerations, rollout  # noqa: E402

ROPE_NET = Path(__file__).resolve().parents[1] / "configs" / "rope_net.yaml"
SEMI_IMPLICIT_F64 = ["sim.integrator=semi_implicit_euler", "sim.precision=float64",
                     "sim.dt=1e-4", "sim.substeps=1"]
# Same discrete map in both engines, float64: differences are round-off accumulated over
# 5000 steps (observed ~1e-15 m). 1e-10 m leaves ample margin and is still 5 orders of
# magnitude below what any modelling difference produces.
POSITION_TOLERANCE_M = 1e-10
VELOCITY_TOLERANCE_M_S = 1e-8


def _mujoco(scene, params, state):
    model = mujoco.MjModel.from_xml_string(scene_to_mjcf(scene, params, state, scene.substep))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    return model, data


@pytest.mark.float64
def test_exported_model_matches_scene_structure():
    scene, params, state = build(load_config(ROPE_NET, SEMI_IMPLICIT_F64))
    model, data = _mujoco(scene, params, state)
    assert model.nbody - 1 == scene.n_points and model.nv == 3 * scene.n_points
    assert model.ntendon == scene.n_springs
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    np.testing.assert_allclose(model.opt.gravity, params.gravity, rtol=0, atol=0)
    np.testing.assert_allclose(np.asarray(model.body_mass[1:]), params.point_mass, rtol=1e-15)
    np.testing.assert_allclose(mujoco_point_positions(model, data), state.phys.point_pos, atol=1e-15)
    mujoco.mj_forward(model, data)
    # every rope starts exactly at its rest length
    np.testing.assert_allclose(data.ten_length, params.spring_rest_length, atol=1e-14)


@pytest.mark.float64
def test_accelerations_match_mujoco_at_a_perturbed_state():
    """Stage check: spring + damper + gravity forces at a random non-equilibrium state."""
    scene, params, state = build(load_config(ROPE_NET, SEMI_IMPLICIT_F64))
    rng = np.random.default_rng(0)
    pos = np.asarray(state.phys.point_pos) + 0.01 * rng.standard_normal((scene.n_points, 3))
    vel = 0.5 * rng.standard_normal((scene.n_points, 3))
    phys = state.phys.replace(point_pos=jnp.asarray(pos), point_vel=jnp.asarray(vel))
    ours = np.asarray(accelerations(scene, params, phys).point_acc)

    model, data = _mujoco(scene, params, state)
    data.qpos[:] = (pos - model.body_pos[1:]).reshape(-1)
    data.qvel[:] = vel.reshape(-1)
    mujoco.mj_forward(model, data)
    theirs = np.asarray(data.qacc).reshape(-1, 3)
    # accelerations here are up to ~1e5 m/s^2 (stiff segments stretched by 1 cm)
    scale = np.abs(theirs).max()
    assert scale > 1e3
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12 * scale)


@pytest.mark.float64
def test_rope_net_trajectory_matches_mujoco_euler():
    scene, params, state = build(load_config(ROPE_NET, SEMI_IMPLICIT_F64))
    every, n_out = 1000, 5                        # outputs at 0.1, 0.2, ..., 0.5 s
    _, traj = jax.jit(lambda p, s: rollout(scene, p, s, every * n_out, every))(params, state)
    ours_pos = np.asarray(traj.phys.point_pos)    # (n_out, n_points, 3)
    ours_vel = np.asarray(traj.phys.point_vel)

    model, data = _mujoco(scene, params, state)
    payload = scene.point_names.index("payload")
    for k in range(n_out):
        mujoco.mj_step(model, data, nstep=every)
        t = (k + 1) * every * scene.dt
        assert data.time == pytest.approx(t, abs=1e-9)
        pos = mujoco_point_positions(model, data)
        vel = mujoco_point_velocities(model, data)
        err = np.abs(pos - ours_pos[k]).max()
        assert err < POSITION_TOLERANCE_M, f"t = {t:.1f} s: max position difference {err:.3e} m"
        assert np.abs(vel - ours_vel[k]).max() < VELOCITY_TOLERANCE_M_S
        assert abs(pos[payload, 2] - ours_pos[k, payload, 2]) < POSITION_TOLERANCE_M
    # not a trivially static comparison: the payload has dropped by centimetres
    assert ours_pos[:, payload, 2].min() < -0.02


def test_exporter_rejects_tension_only_rope():
    overrides = ["sim.integrator=semi_implicit_euler", "sim.precision=float32", "ropes.2.model=tension_only"]
    scene, params, state = build(load_config(ROPE_NET, overrides))
    with pytest.raises(ValueError, match=r"tension-only spring.*r2\[0\].*linear"):
        scene_to_mjcf(scene, params, state, scene.substep)


def test_exporter_rejects_rigid_bodies_and_batched_state():
    overrides = ["sim.integrator=semi_implicit_euler", "sim.precision=float32",
                 "bodies=[{name: box, mass: 1.0, inertia: [0.1, 0.1, 0.1], pos: [0, 0, -1]}]"]
    scene, params, state = build(load_config(ROPE_NET, overrides))
    with pytest.raises(ValueError, match="rigid bodies.*box"):
        scene_to_mjcf(scene, params, state, scene.substep)

    scene, params, state = build(load_config(ROPE_NET, overrides[:2]))
    batched = jax.tree.map(lambda x: jnp.broadcast_to(x, (2,) + x.shape), state)
    with pytest.raises(ValueError, match="one environment"):
        scene_to_mjcf(scene, params, batched, scene.substep)
