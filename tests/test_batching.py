"""``mysim_jax.core.batching.vmap`` (batch axis last) against ``jax.vmap`` (batch axis first).

The two must compute the same function: on the library's rope-net rollout and on small
functions that exercise every batch-last rule (and the fallback) on their own (the
capture environment's step, with its PRNG draws and auto-reset, is checked under both
against single-environment steps in tests/test_capture_env.py). Speed is
not asserted here (BENCHMARKS.md); what is asserted is that the library's steps trace no
primitive through the slow fallback path except the PRNG ones.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.core import batching
from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.sim import rollout, step

ROPE32 = ["sim.precision=float32", "sim.integrator=semi_implicit_euler"]


def _rope_batch(n_env, overrides, seed=0):
    scene, params, state = build(load_config("configs/rope_net.yaml", overrides))
    rng = np.random.default_rng(seed)
    vel = rng.normal(scale=2.0, size=(n_env,) + state.phys.point_vel.shape)
    states = jax.tree.map(lambda x: jnp.broadcast_to(x, (n_env,) + x.shape), state)
    states = states.replace(phys=states.phys.replace(point_vel=jnp.asarray(vel, state.phys.point_vel.dtype)))
    return scene, params, states


@pytest.mark.parametrize("precision, n_steps, rtol, atol", [
    # measured: 1 ulp (6e-8 relative) after 10 float32 steps; 2 m/s random velocities on
    # EA = 1e5 N ropes amplify a reassociated float32 sum ~30x per 50 steps, so a long
    # float32 run is no test of equality. After 200 float64 steps: 1.7e-16 m in positions,
    # 7.4e-14 m/s in velocities.
    ("float32", 10, 3e-7, 1e-9),
    ("float64", 200, 0, 1e-12),
])
def test_rope_net_rollout_equals_jax_vmap(precision, n_steps, rtol, atol):
    with jax.enable_x64(precision == "float64"):
        scene, params, states = _rope_batch(16, ["sim.precision=" + precision, "sim.integrator=semi_implicit_euler"])

        def run(p, s):
            return rollout(scene, p, s, n_steps, n_steps // 2)

        ref = jax.jit(jax.vmap(run, in_axes=(None, 0)))(params, states)
        got = jax.jit(batching.vmap(run, in_axes=(None, 0)))(params, states)
        moved = np.abs(np.asarray(ref[0].phys.point_pos - states.phys.point_pos)).max()
        assert moved > 1e3 * atol
        for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got)):
            assert a.shape == b.shape and a.dtype == b.dtype
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=rtol, atol=atol)


def test_rope_net_batched_params_and_gradients_equal_jax_vmap():
    """A parameter sweep (params batched too) and the gradient through it, in float64."""
    with jax.enable_x64(True):
        scene, params, states = _rope_batch(4, ["sim.integrator=semi_implicit_euler"])
        stiff = params.spring_stiffness[None] * jnp.linspace(0.8, 1.2, 4)[:, None]

        def loss(k, batch_map):
            def one(k_env, s):
                final, _ = rollout(scene, params.replace(spring_stiffness=k_env), s, 100, 100)
                return final.phys.point_pos[0, 2]
            return jnp.sum(batch_map(one)(k, states))

        ref_val, ref_grad = jax.jit(jax.value_and_grad(lambda k: loss(k, jax.vmap)))(stiff)
        got_val, got_grad = jax.jit(jax.value_and_grad(lambda k: loss(k, batching.vmap)))(stiff)
        # measured: value and gradient agree to ~1e-16 relative
        np.testing.assert_allclose(float(got_val), float(ref_val), rtol=1e-13)
        np.testing.assert_allclose(np.asarray(got_grad), np.asarray(ref_grad), rtol=1e-10, atol=1e-18)
        assert np.abs(np.asarray(ref_grad)).max() > 0


@pytest.fixture(scope="module")
def capture_env():
    from mysim_jax.tasks.capture import make_env

    return make_env(load_config("configs/capture_env_falling.yaml"))


def test_library_steps_need_no_fallback_but_prng(capture_env):
    """The speed of the batch-last path rests on every physics primitive having a
    batch-last rule. The rope-net step falls back for nothing; the capture step only for
    its PRNG draws (once per policy step) and the controller's 4 x 4 rotor-allocation
    inverse (once per control period)."""
    env, params = capture_env
    batching.FALLBACK_COUNTS.clear()
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    _, states = jax.eval_shape(jax.vmap(env.reset, in_axes=(0, None)), keys, params)     # traced, not compiled
    actions = jnp.zeros((2,) + env.action_shape)
    jax.eval_shape(batching.vmap(lambda k, s, a: env.step(k, s, a, params)), keys, states, actions)
    slow = {name for name in batching.FALLBACK_COUNTS if not name.startswith("random_")}
    assert slow <= {"lu", "custom_linear_solve", "triangular_solve"}, f"on the fallback path: {sorted(slow)}"
    batching.FALLBACK_COUNTS.clear()
    scene, rparams, rstates = _rope_batch(2, ROPE32)
    jax.eval_shape(batching.vmap(lambda s: step(scene, rparams, s)), rstates)
    assert batching.FALLBACK_COUNTS == {}


# --- every rule on its own ----------------------------------------------------------------


def _f_elementwise(x, y):
    s = jnp.where(x[0] > 0, x, -x)                      # select_n, broadcast scalar predicate
    return jnp.clip(s * y[:, None] + 2.0, -1.5, 3.0) ** 2 + jnp.sin(s) / (1 + x[:, :1] ** 2)


def _f_indexing(x, y):
    idx = jnp.array([2, 0, 2, 1])
    g = x[idx]                                                     # gather, constant indices
    s = jnp.zeros((5, 3)).at[jnp.array([4, 4, 0, 1])].add(g)      # scatter-add
    m = s.at[jnp.array([1, 2])].multiply(2.0)                      # scatter-mul
    d = jax.lax.dynamic_slice(m, (1, 0), (2, 3))
    u = jax.lax.dynamic_update_slice(m, d * 3, (3, 0))
    p = jnp.pad(u, ((1, 2), (0, 1)))
    return jnp.concatenate([p.reshape(-1), y, jnp.ones(2)]), jnp.stack([y, y[::-1]], axis=-1).T


def _f_linear_algebra(x, y):
    a = jnp.arange(12.0).reshape(4, 3)
    return (a @ x[0], x @ a.T, x.T @ x, jnp.einsum("ij,ij->i", x, x), jnp.linalg.solve(x.T @ x + jnp.eye(3), y[:3]))


def _f_reductions(x, y):
    return (x.sum(0), x.max(1), jnp.argmax(x, 0), jnp.cumsum(x, 0), jnp.sort(y), jnp.any(x > 0.5, 1),
            jnp.prod(x, 0), jnp.transpose(x)[::-1])


def _f_loops(x, y):
    def body(c, xs):
        return c * 0.5 + xs.sum() + y[0], c[0] * xs   # carry becomes batched only inside
    c, ys = jax.lax.scan(body, jnp.zeros(3), x)
    w = jax.lax.while_loop(lambda v: v[0] < 10, lambda v: (v[0] + 1, v[1] * 1.1 + x[0]), (0, jnp.zeros(3)))
    w2 = jax.lax.while_loop(lambda v: v[0] < y[0] + 3, lambda v: (v[0] + 1, v[1] + 1), (0.0, 0))  # per-env count
    f = jax.lax.fori_loop(0, 4, lambda i, v: v + x[i], jnp.zeros(3))
    branch = jax.lax.cond(y.sum() > 0, lambda: x * 2, lambda: -x)   # per-env branch
    sw = jax.lax.switch(1, [lambda v: v, lambda v: v + y[0]], x)     # shared branch index
    return c, ys, w[1], w2, f, branch, sw


def _f_data_indices(x, y):
    idx = jnp.argsort(y)[:3]                                        # per-environment indices
    g = x[idx]                                                      # gather, batched indices
    t = jnp.take_along_axis(x, jnp.argsort(x, axis=0)[:2], axis=0)
    s = jnp.zeros((6, 3)).at[idx].add(g * 2.0)                      # scatter-add, batched indices
    seg = jax.ops.segment_sum(g, idx + 1, num_segments=5)
    same = jax.lax.cond(y.sum() > -100.0, lambda: g * 3.0, lambda: g)   # per-env, all take one branch
    return g, t, s, seg, same


def _f_random(key, x):
    k1, k2 = jax.random.split(key)
    return jax.random.normal(k1, (3,)) + x[0], jax.random.uniform(k2, ())


@pytest.mark.parametrize("fn", [_f_elementwise, _f_indexing, _f_linear_algebra, _f_reductions, _f_loops,
                                _f_data_indices])
@pytest.mark.parametrize("in_axes", [(0, 0), (0, None), (None, 0)])
def test_rules_equal_jax_vmap(fn, in_axes):
    rng = np.random.default_rng(1)
    n = 5
    x = jnp.asarray(rng.uniform(-1, 1, size=(n, 4, 3)), jnp.float32)
    y = jnp.asarray(rng.uniform(-1, 1, size=(n, 4)), jnp.float32)
    args = [x if in_axes[0] == 0 else x[0], y if in_axes[1] == 0 else y[0]]
    ref = jax.jit(jax.vmap(fn, in_axes=in_axes))(*args)
    got = jax.jit(batching.vmap(fn, in_axes=in_axes))(*args)
    assert jax.tree.structure(ref) == jax.tree.structure(got)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got)):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-5, atol=1e-6)


def test_prng_fallback_equals_jax_vmap():
    keys = jax.random.split(jax.random.PRNGKey(7), 4)
    x = jnp.arange(12.0).reshape(4, 3)
    ref = jax.vmap(_f_random)(keys, x)
    got = batching.vmap(_f_random)(keys, x)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got)):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a))


def test_bad_in_axes_and_batch_sizes_are_named():
    f = batching.vmap(lambda a, b: a + b, in_axes=(0, 1))
    with pytest.raises(ValueError, match="in_axes entries must be 0 or None"):
        f(jnp.ones((2, 3)), jnp.ones((3, 2)))
    with pytest.raises(ValueError, match="one common leading axis size, got \\[2, 4\\]"):
        batching.vmap(lambda a, b: a + b)(jnp.ones((2, 3)), jnp.ones((4, 3)))
    with pytest.raises(ValueError, match="in_axes has 1 entries for 2 arguments"):
        batching.vmap(lambda a, b: a + b, in_axes=[0])(jnp.ones((2, 3)), jnp.ones((2, 3)))


def test_custom_jvp_keeps_its_rule_under_grad():
    @jax.custom_jvp
    def clipped_sqrt(x):
        return jnp.sqrt(jnp.maximum(x, 0.0))

    @clipped_sqrt.defjvp
    def _jvp(primals, tangents):
        (x,), (t,) = primals, tangents
        return clipped_sqrt(x), t * 7.0          # a rule no differentiation of the body gives

    x = jnp.array([0.0, 1.0, 4.0])
    ref = jax.grad(lambda v: jax.vmap(clipped_sqrt)(v).sum())(x)
    got = jax.grad(lambda v: batching.vmap(clipped_sqrt)(v).sum())(x)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))
    np.testing.assert_array_equal(np.asarray(got), 7.0)


def test_chunked_batch_equals_one_block_and_chunk_for_scales_with_the_state():
    scene, params, states = _rope_batch(16, ROPE32)

    def run(s):
        return rollout(scene, params, s, 20, 20)[0]

    whole = jax.jit(batching.vmap(run))(states)
    blocks = jax.jit(batching.vmap(run, chunk=4))(states)
    odd = jax.jit(batching.vmap(run, chunk=5))(states)        # does not divide: one block
    for a, b, c in zip(jax.tree.leaves(whole), jax.tree.leaves(blocks), jax.tree.leaves(odd)):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a))
        np.testing.assert_array_equal(np.asarray(c), np.asarray(a))
    one = jax.tree.map(lambda x: x[0], states)
    assert batching.chunk_for(one) is None                     # a small state is not blocked
    big = {"x": jnp.zeros((1250,), jnp.float32)}               # 5 kB, like the capture env's state
    assert batching.chunk_for(big) == 128
    assert batching.chunk_for({"x": jnp.zeros((12500,), jnp.float32)}) == 16    # ten times larger: blocks of 16
    assert batching.chunk_for({"x": jnp.zeros((10 ** 6,), jnp.float32)}) == 8     # never below 8
    with pytest.raises(ValueError, match="chunk must be a positive int"):
        batching.vmap(run, chunk=0)


def test_the_private_jax_name_stack_hook_still_carries_scope_names():
    """``batching`` reaches into ``jax._src.source_info_util`` (its one private JAX import, in
    its evaluator ``batch_last_eval``) so that the equations it re-emits keep their
    ``jax.named_scope`` names in profiles and HLO. A JAX that moves it would drop the names
    silently; this says so instead."""
    import jax
    import jax.numpy as jnp

    from mysim_jax.core import batch_last_eval, batching

    def f(x):
        with jax.named_scope("springs"):
            return jnp.sin(x) * 2.0

    assert batch_last_eval._source_info_util is not None, \
        "jax._src.source_info_util moved: update mysim_jax/core/batch_last_eval.py"
    text = jax.jit(batching.vmap(f)).lower(jnp.ones((8, 3))).as_text(debug_info=True)
    assert "springs" in text
