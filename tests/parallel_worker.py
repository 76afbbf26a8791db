"""Child processes of tests/test_parallel.py (run as a script, never imported by pytest's
main process for its jax state).

The device count of a JAX process is fixed when jax is first imported, so every check that
needs two devices runs here, in a fresh interpreter started by the test with its own
environment (``XLA_FLAGS=--xla_force_host_platform_device_count=2``, or
``jax.distributed`` for two processes). The test's own process keeps its single device.

Each command writes its results to ``OUT.npz`` (arrays, one entry per pytree leaf, named
``<run>/<leaf path>``) and ``OUT.json`` (facts about shardings and errors); the test does
the comparing::

    python tests/parallel_worker.py devices OUT       # rope net, jax.vmap and batching.vmap
    python tests/parallel_worker.py capture OUT       # capture environment, two policy steps
    python tests/parallel_worker.py host ID PORT OUT  # process ID of two, jax.distributed
    python tests/parallel_worker.py trainer OUT       # MAPPO on one device and on two
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

ROPE_NET_ENVS = 8          # environments in the rope-net batch
ROPE_NET_STEPS = 300       # physics steps of 1e-4 s per rollout
ROPE_NET_EVERY = 30        # save every 30th state
CAPTURE_ENVS = 4
CAPTURE_POLICY_STEPS = 2
COLLECTIVES = ("all-gather", "all-reduce", "all-to-all", "collective-permute", "reduce-scatter",
               "collective-broadcast", "send", "recv")


def rope_net_problem():
    """``(batched start states (B, ...), rollout(state) for one env)`` of the rope-net scene
    in float32 with semi-implicit Euler; the environments differ in their initial velocity
    (every point of environment ``b`` moves with the same velocity, ``b``-dependent)."""
    import jax
    import jax.numpy as jnp

    from mysim_jax.build import build
    from mysim_jax.config.scene import load_config
    from mysim_jax.sim import rollout

    scene, params, state = build(load_config(ROOT / "configs" / "rope_net.yaml",
                                             ["sim.precision=float32", "sim.integrator=semi_implicit_euler"]))
    b = ROPE_NET_ENVS
    start = jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), state)
    velocity = jnp.stack([jnp.linspace(-1.0, 1.0, b), jnp.linspace(0.3, -0.3, b), jnp.linspace(0.5, -0.5, b)], -1)
    point_vel = jnp.broadcast_to(velocity[:, None, :], start.phys.point_vel.shape).astype(start.phys.point_vel.dtype)
    start = start.replace(phys=start.phys.replace(point_vel=point_vel))

    def run(s):
        return rollout(scene, params, s, ROPE_NET_STEPS, ROPE_NET_EVERY)

    return start, run


def capture_problem():
    """``(env params, reset keys (B, 2), episode(key, params) for one env)``: reset, then
    ``CAPTURE_POLICY_STEPS`` policy steps of the scripted team in a ``lax.scan``, on the
    falling-target scene's cheap level ``train`` (sharding does not depend on the level)."""
    import jax
    import jax.numpy as jnp

    from mysim_jax.config.scene import load_config
    from mysim_jax.tasks.capture import make_env

    env, params = make_env(load_config(ROOT / "configs" / "capture_env_falling.yaml", ["level=train"]))

    def episode(key, params):
        _, state = env.reset(key, params)

        def policy_step(state, i):
            obs, state, reward, terminated, truncated, _ = env.step(
                jax.random.fold_in(key, i), state, env.scripted_actions(state, params), params)
            return state, (obs, reward, terminated, truncated)

        return jax.lax.scan(policy_step, state, jnp.arange(CAPTURE_POLICY_STEPS))

    keys = jax.random.split(jax.random.PRNGKey(0), CAPTURE_ENVS)
    return params, keys, episode


def flat(tree, prefix: str) -> dict:
    """``{prefix/<leaf path>: numpy array}`` for every leaf of ``tree``."""
    import jax
    import numpy as np

    return {f"{prefix}/{jax.tree_util.keystr(p)}": np.asarray(x) for p, x in jax.tree_util.tree_leaves_with_path(tree)}


def sharding_facts(tree) -> dict:
    """How the leaves of a result are placed: specs, devices, the shapes of the shards."""
    import jax

    leaves = [x for x in jax.tree.leaves(tree) if x.ndim]
    return {
        "specs": sorted({str(x.sharding.spec) for x in leaves}),
        "n_devices": sorted({len(x.sharding.device_set) for x in leaves}),
        "shard_rows": sorted({tuple(s.data.shape[0] for s in x.addressable_shards) for x in leaves}),
        "shard_devices": sorted({tuple(sorted(s.device.id for s in x.addressable_shards)) for x in leaves}),
    }


def collectives(run, *args) -> list[str]:
    """Collective operations in the compiled program of ``run`` (there should be none)."""
    text = run.lower(*args).compile().as_text()
    return [c for c in COLLECTIVES if f" {c}(" in text or f" {c}-start(" in text]


def devices(out: str) -> None:
    import jax

    from mysim_jax.core import batching, parallel

    assert jax.device_count() == 2, jax.devices()
    start, run = rope_net_problem()
    mesh = parallel.env_mesh()
    half = ROPE_NET_ENVS // 2
    arrays, facts = {}, {"device_count": jax.device_count()}
    for kind, vmap in (("jax", jax.vmap), ("batching", batching.vmap)):
        single = jax.jit(vmap(run))                  # one device (the default), the whole batch
        arrays |= flat(single(start), f"{kind}/single")
        for i in range(2):                           # one device, each device's block alone
            block = jax.tree.map(lambda x: x[i * half:(i + 1) * half], start)
            arrays |= flat(single(block), f"{kind}/block{i}")
        sharded = parallel.sharded(vmap(run), mesh)
        placed = parallel.shard_envs(start, mesh)
        result = sharded(placed)
        arrays |= flat(result, f"{kind}/sharded")
        arrays |= flat(parallel.local_envs(result), f"{kind}/local")    # both shards are local here
        facts[kind] = sharding_facts(result) | {"input": sharding_facts(placed),
                                                 "collectives": collectives(sharded, placed)}
    # bad input: 7 environments over 2 devices
    odd = jax.tree.map(lambda x: x[:7], start)
    facts["errors"] = {}
    for name, call in (("shard_envs", lambda: parallel.shard_envs(odd, mesh)),
                       ("sharded", lambda: parallel.sharded(jax.vmap(run), mesh)(odd))):
        try:
            call()
            facts["errors"][name] = None
        except ValueError as e:
            facts["errors"][name] = str(e)
    _write(out, arrays, facts)


def capture(out: str) -> None:
    import jax

    from mysim_jax.core import parallel

    assert jax.device_count() == 2, jax.devices()
    params, keys, episode = capture_problem()
    batched = jax.vmap(episode, in_axes=(0, None))
    mesh = parallel.env_mesh()
    arrays = flat(jax.jit(batched)(keys, params), "single")
    sharded = parallel.sharded(batched, mesh, in_axes=(0, None))
    result = sharded(parallel.shard_envs(keys, mesh), parallel.replicate(params, mesh))
    arrays |= flat(result, "sharded")
    _write(out, arrays, {"sharded": sharding_facts(result)})


def host(process_id: int, port: int, out: str) -> None:
    import jax

    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2,
                               process_id=process_id, initialization_timeout=60)
    try:
        from mysim_jax.core import parallel

        start, run = rope_net_problem()
        mesh = parallel.env_mesh()                  # every process's devices
        n_local = ROPE_NET_ENVS // jax.process_count()
        mine = jax.tree.map(lambda x: x[process_id * n_local:(process_id + 1) * n_local], start)
        placed = parallel.shard_process_envs(mine, mesh)
        result = parallel.sharded(jax.vmap(run), mesh)(placed)
        facts = {"process_index": jax.process_index(), "process_count": jax.process_count(),
                 "device_count": jax.device_count(), "local_device_count": jax.local_device_count(),
                 "global_shape": list(result[1].phys.point_pos.shape),
                 "rows": [[s.index[0].start, s.index[0].stop] for s in result[1].phys.point_pos.addressable_shards]}
        _write(out, flat(parallel.local_envs(result), "local"), facts | {"sharded": sharding_facts(result)})
    finally:
        jax.distributed.shutdown()


def trainer(out: str) -> None:
    """MAPPO on the reach task: 3 iterations on one device and with the environments split
    over both (the same total batch and seed); the compiled iteration's collectives; the
    error for a batch that does not split."""
    import re

    import jax

    from mysim_jax.core import parallel
    from mysim_jax.mappo.config import AlgoConfig
    from mysim_jax.mappo.toy import ReachEnv
    from mysim_jax.mappo.trainer import Trainer

    assert jax.device_count() == 2, jax.devices()
    env = ReachEnv()
    config = AlgoConfig(num_envs=32, num_steps=16, num_minibatches=4, total_env_steps=32 * 16 * 3)
    arrays, facts = {}, {}
    for name, mesh in (("one", None), ("two", parallel.env_mesh())):
        t = Trainer(config, env, env.default_params(), mesh=mesh)
        ts = t.init(jax.random.PRNGKey(0))
        for _ in range(3):
            ts, metrics = t.iteration(ts)
        arrays |= flat(ts.params, f"{name}/params")
        arrays |= flat(ts.obs_stats, f"{name}/obs_stats")
        arrays |= flat(metrics, f"{name}/metrics")
        facts[name] = {"obs": str(ts.obs.sharding.spec) if mesh is not None else None,
                       "params_devices": sorted(d.id for d in jax.tree.leaves(ts.params)[0].devices())}
        if mesh is not None:
            text = t._iteration_jit.lower(t.place(ts), t.knobs()).compile().as_text()
            facts["collectives"] = sorted(set(re.findall(r"(all-reduce|all-gather|all-to-all|reduce-scatter|"
                                                         r"collective-permute)\(", text)))
    try:
        Trainer(AlgoConfig(num_envs=33, num_steps=16, num_minibatches=3, total_env_steps=33 * 16),
                env, env.default_params(), mesh=parallel.env_mesh())
        facts["error"] = None
    except ValueError as e:
        facts["error"] = str(e)
    _write(out, arrays, facts)


def _write(out: str, arrays: dict, facts: dict) -> None:
    import numpy as np

    np.savez(out + ".npz", **arrays)
    Path(out + ".json").write_text(json.dumps(facts, indent=1, default=str))


if __name__ == "__main__":
    command, *args = sys.argv[1:]
    if command == "devices":
        devices(*args)
    elif command == "capture":
        capture(*args)
    elif command == "trainer":
        trainer(*args)
    elif command == "host":
        host(int(args[0]), int(args[1]), args[2])
    else:
        raise SystemExit(f"unknown command {command!r}")
