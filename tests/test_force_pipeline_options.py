"""``sim.accumulate`` and ``sim.gather``: how the force pipeline sums node forces and
gathers spring ends. The choices reach the built scene and give the same motion."""

import jax
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.core.config_base import ConfigError
from mysim_jax.sim import rollout

from conftest import CONFIGS


def _positions(*sets):
    scene, params, state = build(load_config(CONFIGS / "rope_net.yaml", ["sim.precision=float32", *sets]))
    final, _ = jax.jit(lambda p, s: rollout(scene, p, s, 200, every=200))(params, state)
    return scene, np.asarray(final.phys.point_pos)


def test_accumulate_and_gather_choices_reach_the_scene_and_move_the_net_alike():
    """The rope net in float32, 200 steps, with the defaults and with ``matmul`` / ``index``: the
    scene carries the choice and the nodes end where they end with the defaults, to
    float32 round-off (a sum in another order)."""
    default, pos = _positions()
    assert (default.accumulate, default.gather) == ("segment_sum", "slices")
    other, pos_other = _positions("sim.accumulate=matmul", "sim.gather=index")
    assert (other.accumulate, other.gather) == ("matmul", "index")
    np.testing.assert_allclose(pos_other, pos, atol=1e-6)     # measured: equal


@pytest.mark.parametrize("key, value", [("sim.accumulate", "dense"), ("sim.gather", "slice")])
def test_an_unknown_choice_is_an_error_naming_the_field(key, value):
    with pytest.raises(ConfigError, match=key.split(".")[1]):
        load_config(CONFIGS / "rope_net.yaml", [f"{key}={value}"])
