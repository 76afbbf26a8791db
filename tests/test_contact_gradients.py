"""Gradients of a trajectory through a contact event (issue #3), float64.

The light collision scene with the ball started 2 cm above the payload, moving down at
1 m/s: it hits at ~0.02 s and bounces. Loss = the ball's z plus 0.1 s times its vertical
velocity at 0.05 s, differentiated (reverse mode through the RK4 ``lax.scan``) with respect
to the contact stiffness k, the contact damping c and the ball's mass. Compared with
central finite differences of the same discrete trajectory.
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

FD_REL_STEP = 1e-6


def _loss_fn(model):
    scene, params, state = build(load_config(CONFIGS / "collision_light.yaml", [
        f"contact.model={model}", "sim.integrator=rk4", "sim.substeps=auto", "sim.t_end=0.05",
        "points.1.pos=[0, 0, 0.08]", "points.1.vel=[0, 0, -1]"]))
    n_steps = int(round(0.05 / scene.dt))      # sim.t_end above

    def loss(theta):
        k, c, m = theta
        p = params.replace(contact=params.contact.replace(stiffness=k, damping=c),
                           point_mass=params.point_mass.at[1].set(m))
        final, _ = rollout(scene, p, state, n_steps, n_steps)
        ball = final.phys.point_pos[1, 2] + 0.1 * final.phys.point_vel[1, 2]
        return ball, final.phys.point_vel[1, 2]

    return loss


@pytest.mark.parametrize("model", ["smooth", "sharp"])
def test_gradient_through_a_bounce(model):
    loss = _loss_fn(model)
    theta = jnp.array([1e8, 1e4, 0.2])
    value_and_grad = jax.jit(jax.value_and_grad(loss, has_aux=True))     # one compile for all
    (_, vz), grad = value_and_grad(theta)
    grad = np.asarray(grad)
    assert float(vz) > -1.0 - 9.81 * 0.05 + 0.5            # the trajectory went through the impact
    assert np.all(np.isfinite(grad)) and np.all(grad != 0.0)
    fd = np.empty(3)
    for i in range(3):
        step = np.zeros(3)
        step[i] = FD_REL_STEP * float(theta[i])
        up, down = value_and_grad(theta + step)[0][0], value_and_grad(theta - step)[0][0]
        fd[i] = (float(up) - float(down)) / (2 * step[i])
    rel_err = np.abs(grad - fd) / np.abs(fd)
    print(f"{model}: d loss / d(k, c, m) = {grad}, central FD (rel. step {FD_REL_STEP:g}) {fd}, "
          f"relative error {rel_err}")
    if model == "smooth":
        assert rel_err.max() < 1e-4
