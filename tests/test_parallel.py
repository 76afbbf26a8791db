"""The environment axis on several devices and hosts (mysim_jax/core/parallel.py).

A JAX process's device count is fixed when jax is imported, so the two-device and
two-process runs happen in child processes (tests/parallel_worker.py) started with their
own environment; this process keeps its one device, its default 32-bit mode and its
``XLA_FLAGS`` (the last test checks that).

What "equal" means here. An environment's numbers do not depend on the device that
computes it, so a sharded run must equal, **bit for bit**, one device running the same
per-device block of environments. Against one device running the *whole* batch at once the
results agree only to round-off: XLA compiles the batched rollout differently for a batch
of 8 than for a block of 4 (vectorisation), so the last bits of a few operations differ
from the first steps on (the same happens on one device alone, batch 8 against two
batches of 4, without any sharding). In the rope-net rollout the positions then differ by
an ulp or two (1e-7 m at 0.65 m); the rope masses oscillate at ω = sqrt(EA / (l m)) ≈
3.5e3 rad/s, so a position difference δx shows as ω δx ≈ 4e-4 m/s in the velocities.
Those runs are compared with these tolerances, which say nothing about sharding; the
bitwise comparison is the one that tests sharding.
"""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import ROOT, TEST_XLA_FLAGS
from mysim_jax.core import parallel
from mysim_jax.mappo.config import reach_training_text

WORKER = ROOT / "tests" / "parallel_worker.py"
XLA_FLAGS_AT_IMPORT = os.environ.get("XLA_FLAGS")
DEVICES_AT_IMPORT = jax.device_count()
TIMEOUT = 240   # s per child process; they take a few seconds to ~40 s on 2 shared cores


def child_env(**extra) -> dict:
    """This process's environment for a child: our ``mysim_jax`` first on the path, no
    64-bit switch, no inherited ``XLA_FLAGS`` but the code generator's unless given, one
    thread pool per child."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    env["JAX_PLATFORMS"] = "cpu"
    env.update(extra)
    # the code generator the suite compiles with (tests/conftest.py), so that children and
    # this process compile the same code
    codegen = [f for f in os.environ.get("XLA_FLAGS", "").split()
               if f.split("=")[0] in {t.split("=")[0] for t in TEST_XLA_FLAGS}]
    flags = " ".join([*env.get("XLA_FLAGS", "").split(), *codegen])
    if flags:
        env["XLA_FLAGS"] = flags
    return env


def run_worker(tmp_path, *args, **env):
    out = str(tmp_path / args[0])
    res = subprocess.run([sys.executable, str(WORKER), *args, out], env=child_env(**env), cwd=ROOT,
                         capture_output=True, text=True, timeout=TIMEOUT)
    assert res.returncode == 0, res.stderr[-4000:]
    return load(out)


def load(out: str):
    with np.load(out + ".npz") as z:
        arrays = {k: z[k] for k in z.files}
    return arrays, json.loads(open(out + ".json").read())


def runs(arrays, prefix: str) -> dict:
    """``{leaf path: array}`` of one run in a worker's output."""
    return {k[len(prefix) + 1:]: v for k, v in arrays.items() if k.startswith(prefix + "/")}


def assert_bitwise(a: dict, b: dict):
    assert a.keys() == b.keys() and a
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k, strict=True)


def max_abs_difference(a: dict, b: dict) -> float:
    assert a.keys() == b.keys() and a
    return max(float(np.max(np.abs(a[k].astype(float) - b[k].astype(float)), initial=0.0)) for k in a)


# rope-net rollout against one device running the whole batch (module docstring)
ROUND_OFF = {"point_pos": 1e-6, "point_vel": 5e-4, "time": 0.0}


def assert_round_off(a: dict, b: dict):
    assert a.keys() == b.keys() and a
    for k in a:
        if a[k].size:
            np.testing.assert_allclose(a[k], b[k], rtol=0, atol=ROUND_OFF[k.rsplit(".", 1)[-1]], err_msg=k)


def concatenate(*parts: dict) -> dict:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


TWO_WAY = {"specs": ["P('env',)"], "n_devices": [2]}


# --- two devices in one process -----------------------------------------------------------


@pytest.fixture(scope="module")
def two_devices(tmp_path_factory):
    return run_worker(tmp_path_factory.mktemp("devices"), "devices",
                      XLA_FLAGS="--xla_force_host_platform_device_count=2")


@pytest.mark.parametrize("kind", ["jax", "batching"])
def test_rope_net_rollout_sharded_over_two_devices(two_devices, kind):
    """8 rope-net environments with different initial velocities, a 300-step rollout
    batched with ``jax.vmap`` or ``batching.vmap``, sharded over 2 devices."""
    arrays, facts = two_devices
    assert facts["device_count"] == 2
    # input and output really are split over the two devices, 4 environments on each
    for placed in (facts[kind], facts[kind]["input"]):
        assert {k: placed[k] for k in TWO_WAY} == TWO_WAY
        assert placed["shard_rows"] == [[4, 4]] and placed["shard_devices"] == [[0, 1]]
    assert facts[kind]["collectives"] == []
    sharded, single = runs(arrays, f"{kind}/sharded"), runs(arrays, f"{kind}/single")
    # bit for bit what one device computes for each device's block of environments
    assert_bitwise(sharded, concatenate(runs(arrays, f"{kind}/block0"), runs(arrays, f"{kind}/block1")))
    # this process holds both shards: local_envs puts them back in environment order
    assert_bitwise(runs(arrays, f"{kind}/local"), sharded)
    # the environments did differ, and moved
    pos = sharded["[1].phys.point_pos"]
    assert pos.shape == (8, 10, 21, 3) and np.ptp(pos[:, -1, 0, 0]) > 1e-3
    # against one device running all 8 at once: round-off (module docstring)
    assert_round_off(sharded, single)
    print(f"{kind}: sharded vs one device, batch 8: max |difference| {max_abs_difference(sharded, single):.3g}")


def test_sharded_vmap_and_batching_vmap_agree(two_devices):
    """The same rollout batched batch-first and batch-last, both sharded, agree (round-off)."""
    arrays, _ = two_devices
    assert_round_off(runs(arrays, "jax/sharded"), runs(arrays, "batching/sharded"))


def test_batch_not_divisible_by_devices_is_a_clear_error(two_devices):
    _, facts = two_devices
    for name in ("shard_envs", "sharded"):
        message = facts["errors"][name]
        assert message is not None, f"{name} accepted 7 environments on 2 devices"
        assert "(7, 21, 3)" in message and "not divisible by 2 devices" in message, message


def test_capture_env_steps_sharded_over_two_devices(tmp_path):
    """Reset and two policy steps of 4 capture environments (the scene's level ``train``),
    params replicated, keys sharded: the same as one device running the 4 environments."""
    arrays, facts = run_worker(tmp_path, "capture", XLA_FLAGS="--xla_force_host_platform_device_count=2")
    assert {k: facts["sharded"][k] for k in TWO_WAY} == TWO_WAY
    assert facts["sharded"]["shard_rows"] == [[2, 2]]
    sharded, single = runs(arrays, "sharded"), runs(arrays, "single")
    rewards = sharded["[1][1]"]
    assert rewards.shape == (4, 2, 4) and np.all(np.isfinite(rewards))
    # two policy steps are short enough for float32 round-off to stay at a few ulp of each
    # value (motor speeds are O(1e3) rad/s, so compare relative to each leaf's scale)
    for k in sharded:
        scale = max(1.0, float(np.max(np.abs(single[k].astype(float)), initial=0.0)))
        np.testing.assert_allclose(sharded[k].astype(float), single[k].astype(float), rtol=0, atol=1e-5 * scale,
                                   err_msg=k)
    print(f"capture: sharded vs one device: max |difference| {max_abs_difference(sharded, single):.3g}")


def test_mappo_with_environments_split_over_two_devices_equals_one_device(tmp_path):
    """Three MAPPO iterations on the reach task (32 environments, the same seed): with the
    environments split over two devices the parameters, observation statistics and
    metrics equal one device's to float32 round-off (measured: at most 1.8e-7 of a leaf's
    largest magnitude, or of 1), every device holds the parameters, the environments stay split, and
    the only collective in the compiled iteration gathers the rollout for the update. A
    batch of 33 environments is the clear error."""
    arrays, facts = run_worker(tmp_path, "trainer", XLA_FLAGS="--xla_force_host_platform_device_count=2")
    one, two = runs(arrays, "one"), runs(arrays, "two")
    assert one.keys() == two.keys() and any(k.startswith("params/") for k in one)
    for k in one:
        scale = max(1.0, float(np.max(np.abs(one[k].astype(float)), initial=0.0)))
        np.testing.assert_allclose(two[k], one[k], rtol=0, atol=2e-6 * scale, err_msg=k)
    assert not all(np.array_equal(one[k], two[k]) for k in one if k.startswith("params/"))   # computed apart
    assert facts["one"]["params_devices"] == [0]
    assert facts["two"]["params_devices"] == [0, 1] and facts["two"]["obs"] == "P('env',)"
    assert "all-gather" in facts["collectives"] and set(facts["collectives"]) <= {"all-gather", "all-reduce"}
    assert facts["error"].startswith("algo.num_envs 33 is not divisible by the 2 devices")
    print(f"mappo: two devices vs one: max |difference| {max_abs_difference(two, one):.3g}")


def test_train_script_on_two_devices_and_on_two_processes(tmp_path):
    """The commands for several devices and hosts in docs/training.md, on the reach task (32
    environments, 4 iterations, checkpoints every 2): train.py in one process with two
    forced host devices splits the environments over both (summary: 2 devices); two
    processes joined by jax.distributed on 127.0.0.1, one device each, train the same run
    into one folder written by process 0 (the other prints nothing) and end with the same
    policy and metrics bit for bit (the same partitioned program); the two-process run
    resumed from its first checkpoint ends with them again, bit for bit (one device agrees
    to round-off: the test above)."""
    import shutil

    cfg = tmp_path / "reach.yaml"
    cfg.write_text(reach_training_text("reach_two", 32 * 16 * 4, checkpoint_every=2, keep_checkpoints=2))
    script = [sys.executable, str(ROOT / "scripts" / "train.py")]
    quiet = ["--no-eval", "--no-progress"]

    def train(*args, **env):
        res = subprocess.run([*script, *args, *quiet], env=child_env(**env), cwd=ROOT, capture_output=True,
                             text=True, timeout=TIMEOUT)
        assert res.returncode == 0, res.stderr[-4000:]

    def train_two_processes(*args):
        port = free_port()
        first, second = run_processes([[*script, *args, *quiet, "--coordinator", f"127.0.0.1:{port}",
                                         "--num-processes", "2", "--process-id", str(i)] for i in range(2)])
        # process 1 prints nothing of ours (gloo, JAX's CPU collectives, announces its peers)
        assert [line for line in second.splitlines() if not line.startswith("[Gloo]")] == []
        assert first.count("\n") >= 2
        return first

    def policy(run):
        return (run / "policy" / "policy.msgpack").read_bytes()

    def metrics(run):
        return [{k: v for k, v in row.items() if k not in ("wall_s", "iteration_s")}
                for row in csv.DictReader((run / "metrics.csv").open())]

    devices, processes, resumed = (tmp_path / name for name in ("devices", "processes", "resumed"))
    train(str(cfg), "--out", str(devices), XLA_FLAGS="--xla_force_host_platform_device_count=2")
    summary = json.loads((devices / "summary.json").read_text())
    assert (summary["devices"], summary["processes"], summary["iterations"]) == (2, 1, 4)
    train_two_processes(str(cfg), "--out", str(processes))
    summary = json.loads((processes / "summary.json").read_text())
    assert (summary["devices"], summary["processes"]) == (2, 2)
    assert policy(processes) == policy(devices) and metrics(processes) == metrics(devices)
    shutil.copytree(processes, resumed)
    shutil.rmtree(resumed / "checkpoints" / "4")
    (resumed / "checkpoints" / "4.sha256.json").unlink()
    assert "resuming" in train_two_processes("--resume", str(resumed))
    assert policy(resumed) == policy(processes) and metrics(resumed) == metrics(processes)


# --- two processes (multi-host) -------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_processes(commands, env=None) -> list[str]:
    """Start every command at once (processes that wait for each other, e.g. joined by
    ``jax.distributed``), wait for all, assert each exited 0; their standard outputs."""
    procs = [subprocess.Popen(cmd, env=env or child_env(), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for cmd in commands]
    try:
        logs = [p.communicate(timeout=TIMEOUT) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, (_, err) in zip(procs, logs):
        assert p.returncode == 0, err[-4000:]
    return [out for out, _ in logs]


def test_rope_net_rollout_on_two_processes(tmp_path):
    """Two processes joined by ``jax.distributed`` on 127.0.0.1, one CPU device each, run the
    8-environment rollout as one global array; each writes its half."""
    port = free_port()
    outs = [str(tmp_path / f"host{i}") for i in range(2)]
    run_processes([[sys.executable, str(WORKER), "host", str(i), str(port), outs[i]] for i in range(2)])
    halves = [load(out) for out in outs]
    for i, (arrays, facts) in enumerate(halves):
        assert facts["process_index"] == i and facts["process_count"] == 2
        assert facts["device_count"] == 2 and facts["local_device_count"] == 1
        assert facts["global_shape"] == [8, 10, 21, 3] and facts["rows"] == [[4 * i, 4 * i + 4]]
        assert {k: facts["sharded"][k] for k in TWO_WAY} == TWO_WAY
        assert runs(arrays, "local")["[1].phys.point_pos"].shape == (4, 10, 21, 3)
    together = concatenate(*(runs(arrays, "local") for arrays, _ in halves))

    # the same rollout in this process, on its one device
    sys.path.insert(0, str(WORKER.parent))
    try:
        from parallel_worker import rope_net_problem
    finally:
        sys.path.remove(str(WORKER.parent))
    start, run = rope_net_problem()
    single = jax.jit(jax.vmap(run))

    def flat(tree):
        return {jax.tree_util.keystr(p): np.asarray(x) for p, x in jax.tree_util.tree_leaves_with_path(tree)}

    blocks = [flat(single(jax.tree.map(lambda x: x[4 * i:4 * i + 4], start))) for i in range(2)]
    assert_bitwise(together, concatenate(*blocks))
    assert_round_off(together, flat(single(start)))


# --- this process (one device) --------------------------------------------------------------


def test_one_device_mesh_and_argument_checks():
    mesh = parallel.env_mesh()
    assert mesh.axis_names == ("env",) and mesh.size == jax.device_count()
    tree = {"a": jnp.arange(6.0).reshape(3, 2), "b": jnp.ones((3,))}
    placed = parallel.shard_envs(tree, mesh)
    assert placed["a"].sharding.spec == jax.sharding.PartitionSpec("env")
    out = parallel.sharded(lambda t, w: jax.vmap(lambda a, b: a * w + b[None])(t["a"], t["b"]),
                           mesh, in_axes=(0, None))(placed, parallel.replicate(jnp.float32(2.0), mesh))
    np.testing.assert_array_equal(np.asarray(out), np.arange(6.0).reshape(3, 2) * 2 + 1)
    np.testing.assert_array_equal(parallel.local_envs(out), np.asarray(out))
    with pytest.raises(ValueError, match=r"scalar \(shape \(\)\)"):
        parallel.shard_envs({"t": jnp.float32(0.0)}, mesh)
    with pytest.raises(ValueError, match="in_axes entries must be 0 or None"):
        parallel.sharded(lambda x: x, mesh, in_axes=(1,))
    with pytest.raises(ValueError, match="in_axes has 2 entries for 1 arguments"):
        parallel.sharded(lambda x, y: x, mesh, in_axes=(0, None))(jnp.ones(2))


def test_main_process_untouched():
    """The two-device flag and any 64-bit switch stayed in the children."""
    assert os.environ.get("XLA_FLAGS") == XLA_FLAGS_AT_IMPORT
    assert jax.device_count() == DEVICES_AT_IMPORT
    assert not jax.config.jax_enable_x64
    assert jnp.zeros(1).dtype == jnp.float32
