"""Batch-last vectorisation: ``vmap`` for per-environment code, with the batch axis minor.

Every physics, control and task function in this package is written for one environment.
``jax.vmap`` batches them by putting the batch axis *first*: an environment's state
``(n, 3)`` becomes ``(B, n, 3)``, so the contiguous (minor) axes in memory are the tiny
per-environment ones. On a CPU every slice of a node range, every vector component, every
gather of a spring's end then reads short strided runs, and XLA cannot use SIMD across the
batch. The same physics written by hand with the batch *last* — ``(n, 3, B)``, every
operation element-wise over a contiguous batch — runs faster (``scripts/bench.py`` times
both side by side: BENCHMARKS.md, sections (a) and (f)).

:func:`vmap` closes that gap without rewriting the physics. It traces the per-environment
function once into a jaxpr and evaluates that jaxpr on batched arrays whose batch axis is
the **last** one: each primitive is re-emitted with the batch appended as a trailing
dimension (element-wise ops, slices, reshapes, broadcasts, reductions, ``dot_general``,
gathers and scatters (per-environment indices become XLA batching dimensions),
``scan``/``while``/``cond`` bodies, nested ``jit``; a per-environment ``cond`` runs one
branch when the whole batch takes it), so the compiled step works on contiguous batch rows as a
hand-written batch-last kernel does. Equations keep their ``jax.named_scope`` names. Primitives without a batch-last rule here (linear-algebra
factorisations, PRNG primitives, ...) fall back to JAX's
own batching rule with the batch moved to the front and back again around that one op:
always correct, only that op pays for a transpose. The rules of single primitives are in
:mod:`mysim_jax.core.batch_last_ops`, the evaluator (and the rules of ``jit``, ``scan``,
``while``, ``cond``) in :mod:`mysim_jax.core.batch_last_eval`; this module is the public
API.

Choice of route. A batch-last array convention written into every physics function would
have given each function two layouts to get right (NumPy broadcasting aligns trailing
axes, so every per-element parameter would need explicit expansion); ``jax.vmap`` with
``in_axes=-1`` does not keep the batch last (its batching rules move the batch to the
front as soon as shapes differ, e.g. a shared ``(n,)`` parameter times an ``(n, B)``
state); ``jax.custom_batching.custom_vmap`` on the step still needs a batch-last
implementation to dispatch to. Transposing once per rollout and re-emitting each
primitive batch-last (this module and the two above) keeps the one readable
per-environment implementation; ``scripts/bench.py`` (sections a and f) times it against ``jax.vmap`` and against a
hand-written batch-last kernel in the same run. Inputs and outputs keep the usual
batch-first convention (``in_axes`` 0 or None, outputs batched along axis 0), so the
layout change is one transpose at the edges of the batched call: batch around a whole
rollout, not around a single step.

Results equal ``jax.vmap``'s up to floating-point reassociation inside XLA's fusions
(``tests/test_batching.py`` compares them on the library's scenes and on synthetic
functions covering every rule). The function is differentiable: ``jax.grad`` through
:func:`vmap` differentiates the re-emitted primitives. ``custom_jvp``/``custom_vjp``
functions inside keep their custom rules (they take the fallback path).
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import numpy as np
from jax import lax

from mysim_jax.core.batch_last_eval import eval_batch_last
from mysim_jax.core.batch_last_ops import FALLBACK_COUNTS, to_back, to_front

__all__ = ["vmap", "chunk_for", "to_batch_last", "from_batch_last", "eval_batch_last", "FALLBACK_COUNTS",
           "BATCHINGS", "resolve_batching", "batch"]

BATCHINGS = ("batch_last", "vmap")
"""How batched code can be compiled: ``batch_last`` (:func:`vmap`, the batch axis last) or
``vmap`` (``jax.vmap``, the batch axis first). ``auto`` picks one by platform
(:func:`resolve_batching`)."""


def to_batch_last(tree):
    """Move the leading (batch) axis of every leaf to the end."""
    return jax.tree.map(to_back, tree)


def from_batch_last(tree):
    """Move the trailing (batch) axis of every leaf to the front."""
    return jax.tree.map(to_front, tree)


def vmap(fun: Callable, in_axes: int | None | Sequence[int | None] = 0, chunk: int | None = None) -> Callable:
    """Like ``jax.vmap(fun, in_axes)`` (out_axes 0), computed with the batch axis last.

    ``in_axes`` is 0 (batched along the leading axis) or None (shared) for each positional
    argument, or one value for all. The batched arguments are transposed to batch-last
    once, the per-environment ``fun`` is evaluated primitive by primitive on batch-last
    arrays (see the module docstring), and the outputs are transposed back. Use it around
    a whole rollout (a ``lax.scan`` of steps), so that the transposes happen once per
    rollout and every step inside runs batch-last.

    ``chunk``: run the batch as consecutive blocks of ``chunk`` environments
    (``lax.map`` over blocks, each block batch-last), so that one block's working set
    stays in the CPU's caches for the whole rollout. It pays for scenes whose
    per-environment state is large (the capture scene: see BENCHMARKS.md, section e);
    ``chunk_for`` picks it from the state's size. A batch that ``chunk`` does not divide,
    or no larger than ``chunk``, runs as one block. Results do not depend on it.
    """
    if chunk is not None and (not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be a positive int or None, got {chunk!r}")
    whole = _vmap_whole(fun, in_axes)
    if chunk is None:
        return whole

    def chunked_fun(*args):
        axes = in_axes if isinstance(in_axes, (list, tuple)) else (in_axes,) * len(args)
        if len(axes) != len(args):
            raise ValueError(f"in_axes has {len(axes)} entries for {len(args)} arguments")
        sizes = {leaf.shape[0] for a, ax in zip(args, axes) if ax == 0 for leaf in jax.tree.leaves(a)}
        size = next(iter(sizes)) if len(sizes) == 1 else None
        if size is None or size <= chunk or size % chunk:
            return whole(*args)
        n_blocks = size // chunk
        batched = [a for a, ax in zip(args, axes) if ax == 0]
        blocks = jax.tree.map(lambda x: x.reshape((n_blocks, chunk) + x.shape[1:]), batched)

        def one(block):
            it = iter(block)
            return whole(*[next(it) if ax == 0 else a for a, ax in zip(args, axes)])

        out = lax.map(one, blocks)
        return jax.tree.map(lambda x: x.reshape((size,) + x.shape[2:]), out)

    return chunked_fun


def resolve_batching(choice: str, platform: str | None = None) -> str:
    """``choice`` (``auto`` or one of :data:`BATCHINGS`) made definite for ``platform``
    (``"cpu"``, ``"gpu"``, ``"tpu"``, ...; default: JAX's default backend). ``auto`` is
    ``batch_last`` on a CPU, which is what it is for: contiguous batch rows for the CPU's
    vector units and caches (the module docstring; BENCHMARKS.md, sections a and f, time it
    against ``jax.vmap`` on a CPU). On any other platform ``auto`` is ``vmap``: a GPU or TPU
    compiler assigns the memory layouts of a ``jax.vmap`` program itself, and no benchmark
    of the project has measured batch-last there."""
    if choice == "auto":
        platform = jax.default_backend() if platform is None else platform
        return "batch_last" if platform == "cpu" else "vmap"
    if choice not in BATCHINGS:
        raise ValueError(f"batching must be auto, {' or '.join(BATCHINGS)}; got {choice!r}")
    return choice


def batch(fun: Callable, batching: str, in_axes: int | None | Sequence[int | None] = 0,
          chunk: int | None = None) -> Callable:
    """``fun`` batched the way ``batching`` (one of :data:`BATCHINGS`) says: ``batch_last``
    is :func:`vmap` ``(fun, in_axes, chunk)``, ``vmap`` is ``jax.vmap(fun, in_axes)``
    (``chunk`` unused: one block). Either way the arguments and results are batch-first
    (``in_axes`` 0 or None) and the results equal to round-off."""
    if batching == "batch_last":
        return vmap(fun, in_axes, chunk)
    if batching == "vmap":
        return jax.vmap(fun, in_axes=tuple(in_axes) if isinstance(in_axes, list) else in_axes)
    raise ValueError(f"batching must be {' or '.join(BATCHINGS)}; got {batching!r}")


def tree_nbytes(tree) -> int:
    """Bytes of a pytree's array leaves, concrete or abstract (``jax.eval_shape`` output)."""
    return sum(_leaf_nbytes(leaf) for leaf in jax.tree.leaves(tree))


def _leaf_nbytes(leaf) -> int:
    """Bytes of one array leaf from its shape and dtype: works for concrete arrays and for
    abstract ones (``jax.ShapeDtypeStruct`` from ``jax.eval_shape``), which hold no data.
    Non-array leaves (None, Python scalars without a dtype) count nothing."""
    shape, dtype = getattr(leaf, "shape", None), getattr(leaf, "dtype", None)
    if shape is None or dtype is None:
        return 0
    return int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize


def chunk_for(state, cache_bytes: int = 16 << 20, per_env_factor: float = 16.0) -> int | None:
    """A block size for :func:`vmap`'s ``chunk``: the largest power of two ``c`` with
    ``c × per_env_factor × (bytes of one environment's state) <= cache_bytes``, or None
    when that is 1024 or more (a small state runs unblocked: a longer batch row amortises
    each operation's overhead). ``state`` is one environment's (unbatched) pytree of arrays
    or of their shapes (``jax.eval_shape`` output: only shapes and dtypes are read);
    ``per_env_factor`` stands for the step's temporaries, several times the state. The
    defaults are calibrated on the capture environment: BENCHMARKS.md, section (e), times
    its batches in the blocks this picks, and section (f) the rope net blocked against
    unblocked."""
    nbytes = tree_nbytes(state)
    if nbytes == 0:
        return None
    c = 1
    while 2 * c * per_env_factor * nbytes <= cache_bytes:
        c *= 2
    return None if c >= 1024 else max(c, 8)


def _vmap_whole(fun: Callable, in_axes) -> Callable:
    def batched_fun(*args):
        axes = in_axes if isinstance(in_axes, (list, tuple)) else (in_axes,) * len(args)
        if len(axes) != len(args):
            raise ValueError(f"in_axes has {len(axes)} entries for {len(args)} arguments")
        sizes = {leaf.shape[0] for a, ax in zip(args, axes) if ax is not None for leaf in jax.tree.leaves(a)}
        if any(ax not in (0, None) for ax in axes):
            raise ValueError(f"in_axes entries must be 0 or None, got {axes}")
        if len(sizes) != 1:
            raise ValueError(f"batched arguments need one common leading axis size, got {sorted(sizes)}")
        (size,) = sizes
        moved = [to_batch_last(a) if ax == 0 else a for a, ax in zip(args, axes)]
        out = eval_batch_last(fun, moved, [ax == 0 for ax in axes], size)
        return from_batch_last(out)

    return batched_fun
