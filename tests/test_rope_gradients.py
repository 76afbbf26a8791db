"""Gradients through the rope net (issue #2: the pipeline is differentiable), float64.

The paper's rope net, started with the payload pushed 2 cm sideways and 1 cm down so that
every spring and damper is working, run for 1000 RK4 steps of 1e-4 s (0.1 s). Loss = the
payload's z plus 0.01 s times its vertical velocity at the end, differentiated (reverse mode
through the ``lax.scan``) with respect to a factor on every rope stiffness, a factor on every
rope damping and the payload's mass. Compared with central finite differences of the same
discrete trajectory. (tests/test_rope_and_forces.py checks the semi-implicit Euler path,
w.r.t. stiffness only, from rest; this one covers RK4, damping and mass.)
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.sim import rollout

from conftest import CONFIGS

pytestmark = pytest.mark.float64

N_STEPS = 1000
FD_REL_STEP = 1e-6
# Measured: relative errors 1e-9 … 4e-8 (float64; FD truncation and round-off at this step).
REL_TOL = 1e-6


def test_gradient_through_1000_rope_net_steps_matches_central_differences():
    scene, params, state = build(load_config(CONFIGS / "rope_net.yaml", ["sim.substeps=1"]))
    payload = list(scene.point_names).index("payload")
    phys = state.phys.replace(point_pos=state.phys.point_pos.at[payload].add(jnp.array([0.02, 0.0, -0.01])))
    state = state.replace(phys=phys)

    def loss(theta):
        k, d, m = theta
        p = params.replace(spring_stiffness=k * params.spring_stiffness,
                           spring_damping=d * params.spring_damping,
                           point_mass=params.point_mass.at[payload].set(m))
        final, _ = rollout(scene, p, state, N_STEPS, N_STEPS)
        return final.phys.point_pos[payload, 2] + 0.01 * final.phys.point_vel[payload, 2]

    theta = jnp.array([1.0, 1.0, 0.2])
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    value, grad = value_and_grad(theta)
    grad = np.asarray(grad)
    assert np.isfinite(float(value)) and np.all(np.isfinite(grad)) and np.all(grad != 0.0)
    fd = np.empty(3)
    for i in range(3):
        step = np.zeros(3)
        step[i] = FD_REL_STEP * float(theta[i])
        up, down = value_and_grad(theta + step)[0], value_and_grad(theta - step)[0]
        fd[i] = (float(up) - float(down)) / (2 * step[i])
    rel_err = np.abs(grad - fd) / np.abs(fd)
    print(f"d loss / d(k factor, d factor, payload mass) = {grad}, central FD {fd}, relative error {rel_err}")
    assert np.all(rel_err < REL_TOL)
