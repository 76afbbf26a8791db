"""The benchmark's hand-written batch-last rope kernel computes the library's physics.

The kernel (``mysim_jax/bench/rope_kernel.py``) is separate code: it shares only the
built Scene's topology and the Params' constants with the library's force pipeline. If it
drifted from the library, the benchmark's library/kernel ratio would compare different
work.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.bench.rope_kernel import from_node_columns, rope_net_kernel, to_node_columns
from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.sim import rollout


@pytest.mark.float64
@pytest.mark.parametrize("config", ["configs/rope_net.yaml", "configs/rope_net_slack.yaml"])
def test_kernel_equals_library_steps(config):
    scene, params, state = build(load_config(config, ["sim.integrator=semi_implicit_euler", "sim.dt=1e-4",
                                                      "sim.substeps=1", "sim.precision=float64"]))
    rng = np.random.default_rng(0)
    n = 4
    vel = jnp.asarray(rng.normal(scale=1.0, size=(n,) + state.phys.point_vel.shape))
    pos = jnp.broadcast_to(state.phys.point_pos, vel.shape)
    final = jax.vmap(lambda p, v: rollout(scene, params, state.replace(phys=state.phys.replace(point_pos=p, point_vel=v)),
                                          300, 300)[0])(pos, vel)
    kpos, kvel = jax.jit(rope_net_kernel(scene, params, 300))(to_node_columns(pos), to_node_columns(vel))
    moved = float(jnp.abs(final.phys.point_pos - pos).max())
    assert moved > 1e-3
    # measured: ~1e-15 m (float64 round-off of a differently ordered sum)
    np.testing.assert_allclose(np.asarray(from_node_columns(kpos)), np.asarray(final.phys.point_pos), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(from_node_columns(kvel)), np.asarray(final.phys.point_vel), rtol=0, atol=1e-9)


def test_kernel_refuses_scenes_outside_its_physics():
    for overrides in (["sim.precision=float32"],                                  # RK4
                      ["sim.precision=float32", "sim.integrator=semi_implicit_euler",
                       "points=[{name: payload, mass: 0.2, pos: [0, 0, 0]}]",
                       "bodies=[{name: box, mass: 1.0, inertia: [0.1, 0.1, 0.1], pos: [0, 0, -2]}]"]):
        scene, params, _ = build(load_config("configs/rope_net.yaml", overrides))
        with pytest.raises(ValueError, match="only point masses, springs and anchors"):
            rope_net_kernel(scene, params, 10)
