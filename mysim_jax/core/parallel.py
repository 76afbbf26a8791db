"""The environment axis on several devices and several hosts.

Every function in this package is written for one environment and batched at the top
(``jax.vmap``, or :func:`mysim_jax.core.batching.vmap` for batch-last speed on CPU). Environments
never talk to each other, so the batch splits across devices with nothing to exchange:
each device runs the whole rollout (or policy step) for its own block of environments.

This module does exactly that and nothing more:

* :func:`env_mesh` — a one-axis :class:`jax.sharding.Mesh` named ``"env"`` over the devices
  (all of them by default; in a multi-process run ``jax.devices()`` lists every process's
  devices, so the same call gives the global mesh).
* :func:`shard_envs` — place a batch-first pytree (every leaf ``(B, ...)``) with its leading
  axis split over ``"env"``; :func:`replicate` — place shared values (``Params``) on every
  device. :func:`shard_process_envs` — the multi-process form of :func:`shard_envs`: each
  process passes only its own consecutive block of environments. :func:`local_envs` — the
  block of a sharded result that lives on this process, as NumPy, batch-first.
* :func:`sharded` — jit a batched function so that each device runs it on its own block.

Why ``shard_map`` inside :func:`sharded`, not ``jit`` with in/out shardings alone. With
shardings alone the partitioner decides how to split every intermediate; for ``jax.vmap``
it keeps the batch axis split, but :func:`mysim_jax.core.batching.vmap` moves the batch to the
*last* axis internally and re-emits each primitive, and a propagation choice that gathers
along it would be a silent all-to-all inside every step. ``shard_map`` states the intent
instead: the function is traced for a per-device block of ``B / n_devices`` environments
and compiled once, with no collective anywhere in the program (``tests/test_parallel.py``
checks the compiled module for collectives). The batched function is unchanged: whatever
batches it (``jax.vmap``, ``batching.vmap``, a ``lax.scan`` around either) runs as written on
a smaller batch. The jitted result has its in- and out-shardings along ``"env"``, so
inputs already placed by :func:`shard_envs` are used where they are, and outputs stay
sharded (nothing is gathered to one device unless the caller asks for it).

Results: an environment's numbers do not depend on which device computes it, so a
sharded run equals, bit for bit, one device running each device's block of environments.
Against one device running the whole batch at once they agree to floating-point round-off
only: the per-device program is compiled for a smaller batch, and XLA may vectorise a
smaller batch differently (one device alone shows the same, without any sharding). In a
long rollout of stiff dynamics that round-off grows as the dynamics amplify it, exactly as
it would between two batch sizes on one device (``tests/test_parallel.py`` compares both).
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

__all__ = ["ENV_AXIS", "env_mesh", "shard_envs", "shard_process_envs", "replicate", "local_envs", "sharded"]

ENV_AXIS = "env"


def env_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis mesh named ``"env"`` over ``devices`` (default: ``jax.devices()``, which in
    a multi-process run after ``jax.distributed.initialize`` is every process's devices)."""
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("env_mesh needs at least one device")
    return Mesh(np.array(devices), (ENV_AXIS,))


def _check_batch(tree, n: int, what: str) -> None:
    """A ValueError naming the first leaf whose leading (environment) axis does not split
    into ``n`` equal blocks."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        shape = np.shape(leaf)
        name = jax.tree_util.keystr(path) or "<leaf>"
        if not shape:
            raise ValueError(f"{what}: leaf {name} is a scalar (shape ()); batched leaves need a "
                             f"leading environment axis, shape (B, ...)")
        if shape[0] % n:
            raise ValueError(f"{what}: leaf {name} has shape {tuple(shape)}; its leading "
                             f"(environment) axis {shape[0]} is not divisible by {n} devices")


def shard_envs(tree, mesh: Mesh):
    """Place every leaf ``(B, ...)`` of ``tree`` with its leading axis split over ``"env"``.

    ``B`` must be divisible by the mesh's device count (a ValueError names the leaf shape
    otherwise). In a multi-process run every process must pass the same global ``tree``;
    use :func:`shard_process_envs` to pass only this process's block.
    """
    _check_batch(tree, mesh.size, "shard_envs")
    return jax.device_put(tree, NamedSharding(mesh, P(ENV_AXIS)))


def shard_process_envs(tree, mesh: Mesh):
    """A global batch from each process's own consecutive block of environments.

    Every leaf of ``tree`` is this process's ``(B_local, ...)`` block; process ``i`` holds
    environments ``[i * B_local, (i + 1) * B_local)`` of the global batch (in the order of
    the mesh's devices). ``B_local`` must be divisible by this process's device count in
    the mesh. With one process this is :func:`shard_envs`.
    """
    _check_batch(tree, len(mesh.local_devices), "shard_process_envs")
    sharding = NamedSharding(mesh, P(ENV_AXIS))
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), tree)


def replicate(tree, mesh: Mesh):
    """Place ``tree`` (shared values such as ``Params``) whole on every device of ``mesh``.

    In a multi-process run every process must pass the same values."""
    return jax.device_put(tree, NamedSharding(mesh, P()))


def local_envs(tree):
    """This process's block of a batch sharded along ``"env"``, as batch-first NumPy arrays
    (the addressable shards in order of their environment index)."""

    def block(x):
        shards = sorted(x.addressable_shards, key=lambda s: s.index[0].start or 0)
        return np.concatenate([np.asarray(s.data) for s in shards], axis=0)

    return jax.tree.map(block, tree)


def sharded(fn: Callable, mesh: Mesh, in_axes: int | None | Sequence[int | None] = 0) -> Callable:
    """Jit ``fn(*args)``, a function batched over environments, to run data-parallel on ``mesh``.

    ``in_axes`` says, per positional argument (or one value for all), whether the argument
    is batched along its leading axis (0: split over ``"env"``) or shared (None: replicated
    on every device). Every output leaf must be batched along its leading axis (it comes
    back split over ``"env"``). ``fn`` is written for any batch size — ``jax.vmap(f)``,
    ``mysim_jax.core.batching.vmap(f)``, or a rollout of either — and each device calls it on
    its own block of ``B / n_devices`` environments, with no communication between devices.

    A batched argument whose leading axis is not divisible by the device count is a
    ValueError naming the leaf's shape. The result is one ``jax.jit`` function: it compiles
    on its first call, and again only when shapes change.
    """

    if isinstance(in_axes, (list, tuple)):
        axes = tuple(in_axes)
        if any(ax not in (0, None) for ax in axes):
            raise ValueError(f"in_axes entries must be 0 or None, got {axes}")
        in_specs = tuple(P(ENV_AXIS) if ax == 0 else P() for ax in axes)
        in_shardings = tuple(NamedSharding(mesh, s) for s in in_specs)
    elif in_axes in (0, None):
        axes = None
        in_specs = P(ENV_AXIS) if in_axes == 0 else P()
        in_shardings = NamedSharding(mesh, in_specs)
    else:
        raise ValueError(f"in_axes must be 0, None or a sequence of them, got {in_axes!r}")
    # check_vma=False: fn may be traced through a custom interpreter (batching.vmap) that
    # binds primitives directly, so replicated and per-device values meet without the
    # varying-axis annotations shard_map's type check expects. fn uses no collective, so
    # the check has nothing to guard here.
    body = jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=P(ENV_AXIS), check_vma=False)
    jitted = jax.jit(body, in_shardings=in_shardings, out_shardings=NamedSharding(mesh, P(ENV_AXIS)))
    name = getattr(fn, "__name__", "fn")

    def run(*args):
        arg_axes = axes if axes is not None else (in_axes,) * len(args)
        if len(arg_axes) != len(args):
            raise ValueError(f"sharded({name}): in_axes has {len(arg_axes)} entries for {len(args)} arguments")
        for i, (arg, ax) in enumerate(zip(args, arg_axes)):
            if ax == 0:
                _check_batch(arg, mesh.size, f"sharded({name}) argument {i}")
        return jitted(*args)

    run.lower = jitted.lower   # inspect the compiled program: run.lower(*args).compile().as_text()
    return run


def jit_envs(fn: Callable, batch: int, in_axes: int | None | Sequence[int | None] = 0) -> Callable:
    """The library's batched paths whose results the host reads (evaluation, sweeps) jit
    through this: ``sharded(fn, env_mesh(jax.local_devices()), in_axes)`` when this process
    has several devices and ``batch`` splits evenly over them, else plain ``jax.jit(fn)``
    (one device, or a batch that does not split: it then runs on the default device). Only
    this process's devices: in a multi-process run each process computes its own call
    (the trainer's iteration, which spans every process, shards through its own mesh)."""
    devices = jax.local_devices()
    if len(devices) > 1 and batch % len(devices) == 0:
        return sharded(fn, env_mesh(devices), in_axes)
    return jax.jit(fn)
