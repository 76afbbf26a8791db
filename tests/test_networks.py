"""The MAPPO networks' initialisation under ``jax.vmap`` (seeds trained in one program)."""

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.mappo.networks import Actor, Critic


def _qr_operands(jaxpr) -> list[tuple[int, ...]]:
    """Shapes of the matrices every QR factorisation in ``jaxpr`` (and its sub-jaxprs) gets."""
    shapes = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("qr", "geqrf"):
            shapes += [v.aval.shape for v in eqn.invars]
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    shapes += _qr_operands(inner)
    return shapes


def test_vmapped_init_factorises_one_matrix_at_a_time_with_the_same_values():
    """Three seeds' networks initialised under ``jax.vmap``: every QR factorisation gets
    one matrix (a batched one splits over XLA's CPU thread pool, and two at once, the
    actor's and the critic's, deadlocked a 2-core machine), and each seed's weights equal
    those of its key initialised alone, bit for bit."""
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    for net, x in ((Actor(action_dim=3, hidden=(16, 16)), jnp.zeros((5,))), (Critic(hidden=(16, 16)), jnp.zeros((7,)))):
        init = jax.vmap(lambda k: net.init(k, x))
        shapes = _qr_operands(jax.make_jaxpr(init)(keys).jaxpr)
        assert len(shapes) == 3 and all(len(s) == 2 for s in shapes), shapes
        together = init(keys)
        for i, key in enumerate(keys):
            alone = net.init(key, x)
            for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(jax.tree.map(lambda t: t[i], together))):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
