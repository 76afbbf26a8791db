"""Batch-last vectorisation: ``vmap`` for per-environment code, with the batch axis minor.

Every physics, control and task function in this package is written for one environment.
``jax.vmap`` batches them by putting the batch axis *first*: an environment's state
``(n, 3)`` becomes ``(B, n, 3)``, so the contiguous (minor) axes in memory are the tiny
per-environment ones. On a CPU every slice of a node range, every vector component, every
gather of a spring's end then reads short strided runs, and XLA cannot use SIMD across the
batch. The same physics written by hand with the batch *last* — ``(n, 3, B)``, every
operation element-wise over a contiguous batch — runs several times faster
(``scripts/bench.py`` measures both side by side; BENCHMARKS.md).

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
always correct, only that op pays for a transpose.

Choice of route. A batch-last array convention written into every physics function would
have given each function two layouts to get right (NumPy broadcasting aligns trailing
axes, so every per-element parameter would need explicit expansion); ``jax.vmap`` with
``in_axes=-1`` does not keep the batch last (its batching rules move the batch to the
front as soon as shapes differ, e.g. a shared ``(n,)`` parameter times an ``(n, B)``
state); ``jax.custom_batching.custom_vmap`` on the step still needs a batch-last
implementation to dispatch to. Transposing once per rollout and re-emitting each
primitive batch-last (this module) keeps the one readable per-environment implementation;
``scripts/bench.py`` (sections a and f) times it against ``jax.vmap`` and against a
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

import contextlib
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jcore

try:  # the name stack of re-emitted equations (JAX's own eval_jaxpr does the same)
    from jax._src import source_info_util as _source_info_util
except ImportError:  # pragma: no cover - a JAX without it loses only the scope names
    _source_info_util = None

__all__ = ["vmap", "chunk_for", "to_batch_last", "from_batch_last", "eval_batch_last", "FALLBACK_COUNTS"]

# ----------------------------------------------------------------------------------------
# values: (array, batched).  A batched value has shape aval.shape + (B,).
# ----------------------------------------------------------------------------------------

_ELEMENTWISE = frozenset("""
abs acos acosh add and asin asinh atan atan2 atanh cbrt ceil clamp complex conj
convert_element_type copy copy_p cos cosh digamma div eq erf erf_inv erfc exp exp2 expm1
floor ge gt igamma igammac imag integer_pow is_finite le lgamma log log1p logistic lt max
min mul ne neg nextafter not or polygamma population_count pow real reduce_precision rem
round rsqrt select_n shift_left shift_right_arithmetic shift_right_logical sign sin sinh
sqrt square stop_gradient sub tan tanh xor zeta bessel_i0e bessel_i1e regularized_incomplete_beta
random_gamma_grad
""".split())

_REDUCTIONS = frozenset("reduce_sum reduce_max reduce_min reduce_prod reduce_and reduce_or "
                        "reduce_xor argmax argmin".split())
_CUMULATIVE = frozenset("cumsum cumprod cummax cummin cumlogsumexp".split())

# How often each primitive took the fallback path while tracing (diagnostics; the
# benchmark prints it so a slow new primitive is visible).
FALLBACK_COUNTS: dict[str, int] = {}


def _bshape(aval_shape, size):
    return tuple(aval_shape) + (size,)


def _broadcast_to_batched(x, shape: tuple, size: int):
    """An unbatched ``x`` of shape ``shape`` (or a scalar) as a batched value ``shape + (B,)``."""
    x = jnp.asarray(x)
    dims = tuple(range(x.ndim)) if x.ndim == len(shape) else ()
    if x.ndim and x.ndim != len(shape):
        raise ValueError(f"cannot broadcast {x.shape} to {shape}")
    return lax.broadcast_in_dim(x, _bshape(shape, size), dims)


def _to_front(x):
    return jnp.moveaxis(x, -1, 0)


def _to_back(x):
    return jnp.moveaxis(x, 0, -1)


def _fallback(prim, vals, batched, params, size, count: bool = True):
    """JAX's own batching rule, with the batch moved to the front around this one op
    (``count``: record it in :data:`FALLBACK_COUNTS`)."""
    if count:
        FALLBACK_COUNTS[prim.name] = FALLBACK_COUNTS.get(prim.name, 0) + 1
    in_axes = [0 if b else None for b in batched]
    args = [_to_front(v) if b else v for v, b in zip(vals, batched)]

    bind_params = prim.get_bind_params(params)   # call primitives (custom_jvp, ...)

    def bind(*a):
        out = prim.bind(*a, **bind_params)
        return list(out) if prim.multiple_results else [out]

    outs = jax.vmap(bind, in_axes=in_axes, out_axes=0, axis_size=size)(*args)
    outs = [_to_back(o) for o in outs]
    return (outs, [True] * len(outs)) if prim.multiple_results else (outs[0], True)


# ---- rules: rule(prim, vals, batched, params, size, eqn) -> (out(s), out_batched) --------


def _elementwise(prim, vals, batched, params, size, eqn):
    # lax's element-wise primitives broadcast size-1 dimensions of equal-rank operands and
    # accept scalars: a shared operand gets a trailing size-1 batch axis (a free reshape),
    # a batched scalar leading size-1 axes. select_n and clamp need full shapes.
    shape = tuple(eqn.outvars[0].aval.shape)
    full = prim.name in ("select_n", "clamp")
    args = []
    for i, (v, b, var) in enumerate(zip(vals, batched, eqn.invars)):
        vshape = tuple(var.aval.shape)
        if full and not (prim.name == "select_n" and i == 0 and not b and not vshape):
            if b:
                v = v if vshape == shape else lax.broadcast_in_dim(v, _bshape(shape, size), (len(shape),))
            else:
                v = _broadcast_to_batched(v, shape, size)
        elif b and vshape != shape and not vshape:
            v = lax.reshape(v, (1,) * len(shape) + (size,))
        elif not b and vshape:
            v = lax.reshape(jnp.asarray(v), vshape + (1,))
        args.append(v)
    return prim.bind(*args, **params), True


def _broadcast_in_dim(prim, vals, batched, params, size, eqn):
    (x,) = vals[:1]
    if len(vals) > 1:      # dynamic shapes: not supported here
        return _fallback(prim, vals, batched, params, size)
    shape = tuple(params["shape"]) + (size,)
    dims = tuple(params["broadcast_dimensions"]) + (len(params["shape"]),)
    return lax.broadcast_in_dim(x, shape, dims), True


def _reshape(prim, vals, batched, params, size, eqn):
    if params.get("dimensions") is not None or len(vals) > 1:
        return _fallback(prim, vals, batched, params, size)
    return lax.reshape(vals[0], tuple(params["new_sizes"]) + (size,)), True


def _squeeze(prim, vals, batched, params, size, eqn):
    return lax.squeeze(vals[0], params["dimensions"]), True


def _slice(prim, vals, batched, params, size, eqn):
    x = vals[0]
    start = tuple(params["start_indices"]) + (0,)
    limit = tuple(params["limit_indices"]) + (size,)
    strides = None if params["strides"] is None else tuple(params["strides"]) + (1,)
    return lax.slice(x, start, limit, strides), True


def _same_axes(prim, vals, batched, params, size, eqn):
    """Ops whose parameters name leading axes only (reductions, cumulative ops, rev)."""
    if not all(batched):
        return _fallback(prim, vals, batched, params, size)
    out = prim.bind(*vals, **params)
    return (out, [True] * len(out)) if prim.multiple_results else (out, True)


def _transpose(prim, vals, batched, params, size, eqn):
    perm = tuple(params["permutation"])
    return lax.transpose(vals[0], perm + (len(perm),)), True


def _concatenate_like(prim, vals, batched, params, size, eqn):
    args = [v if b else _broadcast_to_batched(v, tuple(var.aval.shape), size)
            for v, b, var in zip(vals, batched, eqn.invars)]
    out = prim.bind(*args, **params)
    return (out, [True] * len(out)) if prim.multiple_results else (out, True)


def _pad(prim, vals, batched, params, size, eqn):
    x, pad_value = vals
    if batched[1]:
        return _fallback(prim, vals, batched, params, size)
    config = tuple(params["padding_config"]) + ((0, 0, 0),)
    return lax.pad(x, pad_value, config), True


def _dynamic_slice(prim, vals, batched, params, size, eqn):
    x, *idx = vals
    if any(batched[1:]) or len(idx) != len(eqn.invars[0].aval.shape):
        return _fallback(prim, vals, batched, params, size)
    zero = jnp.zeros((), dtype=jnp.asarray(idx[0]).dtype) if idx else jnp.int32(0)
    return lax.dynamic_slice(x, tuple(idx) + (zero,), tuple(params["slice_sizes"]) + (size,)), True


def _dynamic_update_slice(prim, vals, batched, params, size, eqn):
    x, upd, *idx = vals
    if any(batched[2:]):
        return _fallback(prim, vals, batched, params, size)
    if not batched[0]:
        x = _broadcast_to_batched(x, tuple(eqn.invars[0].aval.shape), size)
    if not batched[1]:
        upd = _broadcast_to_batched(upd, tuple(eqn.invars[1].aval.shape), size)
    zero = jnp.zeros((), dtype=jnp.asarray(idx[0]).dtype) if idx else jnp.int32(0)
    return lax.dynamic_update_slice(x, upd, tuple(idx) + (zero,)), True


def _dot_general(prim, vals, batched, params, size, eqn):
    lhs, rhs = vals
    (lc, rc), (lb, rb) = params["dimension_numbers"]
    lhs_nd = len(eqn.invars[0].aval.shape)
    rhs_nd = len(eqn.invars[1].aval.shape)
    out_nd = len(eqn.outvars[0].aval.shape)
    kw = dict(precision=params.get("precision"), preferred_element_type=params.get("preferred_element_type"))
    if batched[0] and batched[1]:
        # the batch is a dot batch dimension: it comes out first, move it last
        dn = ((lc, rc), (tuple(lb) + (lhs_nd,), tuple(rb) + (rhs_nd,)))
        out = lax.dot_general(lhs, rhs, dn, **kw)
        return jnp.moveaxis(out, len(lb), -1), True
    if batched[1]:
        # the batch is rhs's last free dimension: it comes out last
        return lax.dot_general(lhs, rhs, params["dimension_numbers"], **kw), True
    # lhs batched: the batch is lhs's last free dimension, followed by rhs's free dims
    out = lax.dot_general(lhs, rhs, params["dimension_numbers"], **kw)
    rhs_free = rhs_nd - len(rc) - len(rb)
    return (out if rhs_free == 0 else jnp.moveaxis(out, out_nd - rhs_free, -1)), True


def _batched_indices(indices):
    """Per-environment indices ``idx_shape + (B,)`` (index vector last per environment) as
    ``idx_shape[:-1] + (B, vector)``: the batch becomes the indices' last batch dimension."""
    return jnp.moveaxis(indices, -1, -2)


def _gather(prim, vals, batched, params, size, eqn):
    operand, indices = vals
    dn = params["dimension_numbers"]
    if batched[1]:
        # per-environment indices: the batch is a batching dimension of the operand and of
        # the indices (XLA's batched gather); it lands on the output's last non-offset
        # position, which is the last axis since the offset dims keep their places
        idx_nd = len(eqn.invars[1].aval.shape)
        if idx_nd == 0:
            return _fallback(prim, vals, batched, params, size)
        slice_sizes = tuple(params["slice_sizes"])
        if batched[0]:
            op_nd = len(eqn.invars[0].aval.shape)
            dn = dn._replace(operand_batching_dims=tuple(dn.operand_batching_dims) + (op_nd,),
                             start_indices_batching_dims=tuple(dn.start_indices_batching_dims) + (idx_nd - 1,))
            slice_sizes = slice_sizes + (1,)
        out = lax.gather(operand, _batched_indices(indices), dn, slice_sizes,
                         indices_are_sorted=False, unique_indices=params["unique_indices"],
                         mode=params["mode"], fill_value=params["fill_value"])
        return out, True
    out_nd = len(eqn.outvars[0].aval.shape)
    # the batch is one more window (offset) dimension, the last of the output
    new_dn = dn._replace(offset_dims=tuple(dn.offset_dims) + (out_nd,))
    out = lax.gather(operand, indices, new_dn, tuple(params["slice_sizes"]) + (size,),
                     indices_are_sorted=params["indices_are_sorted"], unique_indices=params["unique_indices"],
                     mode=params["mode"], fill_value=params["fill_value"])
    return out, True


def _scatter(prim, vals, batched, params, size, eqn):
    operand, indices, updates = vals
    idx_nd = len(eqn.invars[1].aval.shape)
    if batched[1] and idx_nd == 0:
        return _fallback(prim, vals, batched, params, size)
    if not batched[0]:
        operand = _broadcast_to_batched(operand, tuple(eqn.invars[0].aval.shape), size)
    if not batched[2]:
        updates = _broadcast_to_batched(updates, tuple(eqn.invars[2].aval.shape), size)
    dn = params["dimension_numbers"]
    if batched[1]:
        # per-environment indices: the batch is a batching dimension of operand, indices
        # and updates (XLA's batched scatter); in the updates it is the last non-window
        # position, i.e. the last axis, as the window dims keep their places
        op_nd = len(eqn.invars[0].aval.shape)
        dn = dn._replace(operand_batching_dims=tuple(dn.operand_batching_dims) + (op_nd,),
                         scatter_indices_batching_dims=tuple(dn.scatter_indices_batching_dims) + (idx_nd - 1,))
        new_params = dict(params, dimension_numbers=dn, indices_are_sorted=False)
        return prim.bind(operand, _batched_indices(indices), updates, **new_params), True
    # the batch is one more window dimension, the last of the updates
    upd_nd = len(eqn.invars[2].aval.shape)
    new_dn = dn._replace(update_window_dims=tuple(dn.update_window_dims) + (upd_nd,))
    return prim.bind(operand, indices, updates, **dict(params, dimension_numbers=new_dn)), True


def _sort(prim, vals, batched, params, size, eqn):
    args = [v if b else _broadcast_to_batched(v, tuple(var.aval.shape), size)
            for v, b, var in zip(vals, batched, eqn.invars)]
    out = prim.bind(*args, **params)
    return list(out), [True] * len(out)


def _passthrough(prim, vals, batched, params, size, eqn):
    out = prim.bind(*vals, **params) if prim.name != "sharding_constraint" else vals[0]
    return out, batched[0]


def _closed_call(prim, vals, batched, params, size, eqn):
    closed = params["jaxpr"]
    outs, out_b = _eval(closed.jaxpr, closed.consts, vals, batched, size)
    return outs, out_b


def _fixpoint_carry(body_fn, carry_b: list[bool]) -> list[bool]:
    """Batched flags of a loop carry: batched on entry, or made batched by the body."""
    carry_b = list(carry_b)
    for _ in range(len(carry_b) + 1):
        out_b = body_fn(carry_b)
        new = [a or b for a, b in zip(carry_b, out_b)]
        if new == carry_b:
            return carry_b
        carry_b = new
    return carry_b


# Flags of loop bodies already worked out in the current top-level evaluation, by
# (id(jaxpr), in_b, size) -> (jaxpr, flags); the jaxpr is kept so its id is not reused.
# Nested loops otherwise redo their inner fix-points at every outer iteration (the
# tracing cost grows with the power of the nesting depth).
_FLAGS_MEMO: list[dict] = []


def _flags_of(jaxpr: jcore.ClosedJaxpr, in_b: list[bool], size: int) -> list[bool]:
    """Which outputs of ``jaxpr`` are batched for inputs batched as ``in_b`` (abstract)."""
    memo = _FLAGS_MEMO[-1] if _FLAGS_MEMO else None
    key = (id(jaxpr), tuple(bool(b) for b in in_b), size)
    if memo is not None and key in memo and memo[key][0] is jaxpr:
        return list(memo[key][1])
    flags = _flags_of_uncached(jaxpr, in_b, size)
    if memo is not None:
        memo[key] = (jaxpr, tuple(flags))
    return flags


def _flags_of_uncached(jaxpr: jcore.ClosedJaxpr, in_b: list[bool], size: int) -> list[bool]:
    result = {}

    def f(*args):
        outs, ob = _eval(jaxpr.jaxpr, jaxpr.consts, list(args), in_b, size)
        result["b"] = ob
        return outs

    avals = [jax.ShapeDtypeStruct(_bshape(v.aval.shape, size) if b else v.aval.shape, v.aval.dtype)
             for v, b in zip(jaxpr.jaxpr.invars, in_b)]
    jax.eval_shape(f, *avals)
    return list(result["b"])


def _make_batched(vals, batched, want, invars, size):
    return [v if (b or not w) else _broadcast_to_batched(v, tuple(var.aval.shape), size)
            for v, b, w, var in zip(vals, batched, want, invars)]


def _scan(prim, vals, batched, params, size, eqn):
    jaxpr = params["jaxpr"]
    nc, nk = params["num_consts"], params["num_carry"]
    consts_b, carry_b, xs_b = batched[:nc], batched[nc:nc + nk], batched[nc + nk:]
    # inside the body xs are sliced along axis 0; a batched xs (length, ..., B) stays batch-last
    carry_b = _fixpoint_carry(lambda cb: _flags_of(jaxpr, list(consts_b) + cb + list(xs_b), size)[:nk], carry_b)
    body_in_b = list(consts_b) + carry_b + list(xs_b)
    out_b = _flags_of(jaxpr, body_in_b, size)
    ys_b = out_b[nk:]
    consts, carry, xs = vals[:nc], vals[nc:nc + nk], vals[nc + nk:]
    carry = _make_batched(carry, batched[nc:nc + nk], carry_b, eqn.invars[nc:nc + nk], size)

    def body(c, x):
        outs, ob = _eval(jaxpr.jaxpr, jaxpr.consts, list(consts) + list(c) + list(x), body_in_b, size)
        return list(outs[:nk]), list(outs[nk:])

    length = params["length"]
    carry_out, ys = lax.scan(body, list(carry), list(xs), length=length, reverse=params["reverse"],
                             unroll=params["unroll"])
    # a batched y stacked by scan is (length, ..., B): batch-last already
    return list(carry_out) + list(ys), carry_b + ys_b


def _while(prim, vals, batched, params, size, eqn):
    cond_j, body_j = params["cond_jaxpr"], params["body_jaxpr"]
    cn, bn = params["cond_nconsts"], params["body_nconsts"]
    cconsts, bconsts, init = vals[:cn], vals[cn:cn + bn], vals[cn + bn:]
    cconsts_b, bconsts_b, init_b = batched[:cn], batched[cn:cn + bn], batched[cn + bn:]
    carry_b = _fixpoint_carry(lambda cb: _flags_of(body_j, list(bconsts_b) + cb, size), list(init_b))
    if _flags_of(cond_j, list(cconsts_b) + carry_b, size)[0]:
        return _fallback(prim, vals, batched, params, size)   # a per-environment trip count
    init = _make_batched(init, init_b, carry_b, eqn.invars[cn + bn:], size)

    def cond(c):
        return _eval(cond_j.jaxpr, cond_j.consts, list(cconsts) + list(c), list(cconsts_b) + carry_b, size)[0][0]

    def body(c):
        outs, _ = _eval(body_j.jaxpr, body_j.consts, list(bconsts) + list(c), list(bconsts_b) + carry_b, size)
        return list(outs)

    return list(lax.while_loop(cond, body, list(init))), carry_b


def _cond(prim, vals, batched, params, size, eqn):
    branches = params["branches"]
    ops, ops_b = vals[1:], batched[1:]
    if batched[0]:
        # a per-environment branch. When every environment of the batch (block) takes the
        # same branch, only that branch runs; otherwise all run and each environment
        # selects its own (JAX's rule). The result is the same either way.
        index = vals[0]
        first = index[..., 0]

        def uniform(*a):
            outs, ob = _switch_unbatched_index(branches, first, list(a), list(ops_b), size)
            return _make_batched(outs, ob, [True] * len(outs), eqn.outvars, size)

        def mixed(*a):
            return _fallback(prim, [index] + list(a), batched, params, size, count=False)[0]

        outs = lax.cond(jnp.all(index == first), uniform, mixed, *ops)
        return list(outs), [True] * len(outs)
    return _switch_unbatched_index(branches, vals[0], list(ops), list(ops_b), size)


def _switch_unbatched_index(branches, index, ops, ops_b, size):
    out_b = [any(bs) for bs in zip(*[_flags_of(br, list(ops_b), size) for br in branches])]

    def run(br):
        def f(*a):
            outs, ob = _eval(br.jaxpr, br.consts, list(a), list(ops_b), size)
            return _make_batched(outs, ob, out_b, br.jaxpr.outvars, size)
        return f

    return list(lax.switch(index, [run(br) for br in branches], *ops)), out_b


_RULES: dict[str, Callable] = {
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": _reshape,
    "squeeze": _squeeze,
    "slice": _slice,
    "transpose": _transpose,
    "concatenate": _concatenate_like,
    "stack": _concatenate_like,
    "split": _same_axes,
    "rev": _same_axes,
    "pad": _pad,
    "dynamic_slice": _dynamic_slice,
    "dynamic_update_slice": _dynamic_update_slice,
    "dot_general": _dot_general,
    "gather": _gather,
    "scatter": _scatter,
    "scatter-add": _scatter,
    "scatter_add": _scatter,
    "scatter-mul": _scatter,
    "scatter_mul": _scatter,
    "scatter-min": _scatter,
    "scatter_min": _scatter,
    "scatter-max": _scatter,
    "scatter_max": _scatter,
    "sort": _sort,
    "sharding_constraint": _passthrough,
    "jit": _closed_call,
    "pjit": _closed_call,
    "closed_call": _closed_call,
    "scan": _scan,
    "while": _while,
    "cond": _cond,
}


def _apply(eqn, vals, batched, size):
    prim, params = eqn.primitive, eqn.params
    name = prim.name
    if name in _ELEMENTWISE:
        return _elementwise(prim, vals, batched, params, size, eqn)
    if name in _REDUCTIONS or name in _CUMULATIVE:
        return _same_axes(prim, vals, batched, params, size, eqn)
    if name == "bitcast_convert_type" and tuple(eqn.invars[0].aval.shape) == tuple(eqn.outvars[0].aval.shape):
        return _elementwise(prim, vals, batched, params, size, eqn)     # same bit width
    rule = _RULES.get(name)
    if rule is None:
        return _fallback(prim, vals, batched, params, size)
    return rule(prim, vals, batched, params, size, eqn)


def _source_context(eqn):
    """Re-emit ``eqn`` under its original name stack (the ``jax.named_scope`` stages), so
    that a profile of the batch-last step reads like the per-environment code."""
    if _source_info_util is None:
        return contextlib.nullcontext()
    name_stack = _source_info_util.current_name_stack() + eqn.source_info.name_stack
    return _source_info_util.user_context(eqn.source_info.traceback, name_stack=name_stack)


def _eval(jaxpr: jcore.Jaxpr, consts, args, args_b, size: int):
    """Evaluate ``jaxpr`` on batch-last values; returns ``(outs, outs_batched)``."""
    env: dict[Any, tuple[Any, bool]] = {}

    def read(v):
        if isinstance(v, jcore.Literal):
            return v.val, False
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = (c, False)
    for v, a, b in zip(jaxpr.invars, args, args_b):
        env[v] = (a, bool(b))
    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        vals = [x for x, _ in ins]
        batched = [b for _, b in ins]
        with _source_context(eqn):
            if not any(batched):
                out = eqn.primitive.bind(*vals, **eqn.primitive.get_bind_params(eqn.params))
                outs = list(out) if eqn.primitive.multiple_results else [out]
                outs_b = [False] * len(outs)
            else:
                out, ob = _apply(eqn, vals, batched, size)
                if eqn.primitive.multiple_results:
                    outs, outs_b = list(out), list(ob) if isinstance(ob, (list, tuple)) else [ob] * len(out)
                else:
                    outs, outs_b = [out], [ob]
        for v, o, b in zip(eqn.outvars, outs, outs_b):
            env[v] = (o, b)
    outs = [read(v) for v in jaxpr.outvars]
    return [o for o, _ in outs], [b for _, b in outs]


def eval_batch_last(fun: Callable, batched_args: Sequence, batched: Sequence[bool], size: int):
    """Evaluate per-environment ``fun(*args)`` on batch-last arguments.

    ``batched_args[i]`` is a pytree whose leaves have the batch as their last axis when
    ``batched[i]`` is True (per-environment shape + ``(size,)``), or the per-environment
    value itself when False (shared by every environment). Returns the outputs as a pytree
    of batch-last arrays (every output leaf gets the batch axis, broadcast if it did not
    depend on a batched input).
    """
    leaves, in_b, avals = [], [], []
    for arg, b in zip(batched_args, batched):
        for leaf in jax.tree.leaves(arg):
            leaf = jnp.asarray(leaf) if not hasattr(leaf, "shape") else leaf
            leaves.append(leaf)
            in_b.append(bool(b))
            shape = leaf.shape[:-1] if b else leaf.shape
            avals.append(jax.ShapeDtypeStruct(shape, leaf.dtype))
    treedefs = [jax.tree.structure(arg) for arg in batched_args]

    def flat_fun(*flat):
        it = iter(flat)
        args = [jax.tree.unflatten(td, [next(it) for _ in range(td.num_leaves)]) for td in treedefs]
        return fun(*args)

    closed, out_shape = jax.make_jaxpr(flat_fun, return_shape=True)(*avals)
    _FLAGS_MEMO.append({})
    try:
        outs, outs_b = _eval(closed.jaxpr, closed.consts, leaves, in_b, size)
    finally:
        _FLAGS_MEMO.pop()
    outs = [o if b else _broadcast_to_batched(o, tuple(v.aval.shape), size)
            for o, b, v in zip(outs, outs_b, closed.jaxpr.outvars)]
    return jax.tree.unflatten(jax.tree.structure(out_shape), outs)


def to_batch_last(tree):
    """Move the leading (batch) axis of every leaf to the end."""
    return jax.tree.map(_to_back, tree)


def from_batch_last(tree):
    """Move the trailing (batch) axis of every leaf to the front."""
    return jax.tree.map(_to_front, tree)


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
    when that is 1024 or more (small states: blocks of a thousand environments and more
    run as fast unblocked, and a longer batch row amortises each operation's overhead).
    ``state`` is one environment's (unbatched) pytree of arrays or of their shapes
    (``jax.eval_shape`` output: only shapes and dtypes are read); ``per_env_factor`` stands for the
    step's temporaries, several times the state. The defaults are calibrated on the
    capture environment, whose blocks of a few hundred environments run fastest at
    batches of a thousand (``scripts/bench.py`` section e times blocked against unblocked:
    BENCHMARKS.md); the rope net, with a state a tenth the size, is not blocked."""
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
