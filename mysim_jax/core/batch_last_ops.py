"""Batch-last rules of single primitives: each primitive re-emitted with the batch as a
trailing axis of its batched operands, and JAX's own batching rule as the fallback.

A value is ``(array, batched)``: a batched array has the per-environment shape followed by
the batch ``(B,)``, an unbatched one is shared by every environment. A rule takes
``(prim, vals, batched, params, size, eqn)`` and returns the output(s) and whether each is
batched. :data:`PRIMITIVE_RULES` maps primitive names to their rules; element-wise ops,
reductions and cumulative ops are handled by :func:`elementwise` and :func:`same_axes`
(by name, :data:`ELEMENTWISE`, :data:`REDUCTIONS`, :data:`CUMULATIVE`); a primitive with
no rule here goes through :func:`fallback`. The rules of primitives holding jaxprs (``jit``,
``scan``, ``while``, ``cond``) and the evaluator are in :mod:`mysim_jax.core.batch_last_eval`;
the public entry point is :func:`mysim_jax.core.batching.vmap`.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["PRIMITIVE_RULES", "ELEMENTWISE", "REDUCTIONS", "CUMULATIVE", "FALLBACK_COUNTS", "elementwise",
           "same_axes", "fallback", "broadcast_to_batched", "bshape", "to_front", "to_back"]

# ----------------------------------------------------------------------------------------
# values: (array, batched).  A batched value has shape aval.shape + (B,).
# ----------------------------------------------------------------------------------------

ELEMENTWISE = frozenset("""
abs acos acosh add and asin asinh atan atan2 atanh cbrt ceil clamp complex conj
convert_element_type copy copy_p cos cosh digamma div eq erf erf_inv erfc exp exp2 expm1
floor ge gt igamma igammac imag integer_pow is_finite le lgamma log log1p logistic lt max
min mul ne neg nextafter not or polygamma population_count pow real reduce_precision rem
round rsqrt select_n shift_left shift_right_arithmetic shift_right_logical sign sin sinh
sqrt square stop_gradient sub tan tanh xor zeta bessel_i0e bessel_i1e regularized_incomplete_beta
random_gamma_grad
""".split())

REDUCTIONS = frozenset("reduce_sum reduce_max reduce_min reduce_prod reduce_and reduce_or "
                       "reduce_xor argmax argmin".split())
CUMULATIVE = frozenset("cumsum cumprod cummax cummin cumlogsumexp".split())

# How often each primitive took the fallback path while tracing (diagnostics; the
# benchmark prints it so a slow new primitive is visible).
FALLBACK_COUNTS: dict[str, int] = {}


def bshape(aval_shape, size):
    return tuple(aval_shape) + (size,)


def broadcast_to_batched(x, shape: tuple, size: int):
    """An unbatched ``x`` of shape ``shape`` (or a scalar) as a batched value ``shape + (B,)``."""
    x = jnp.asarray(x)
    dims = tuple(range(x.ndim)) if x.ndim == len(shape) else ()
    if x.ndim and x.ndim != len(shape):
        raise ValueError(f"cannot broadcast {x.shape} to {shape}")
    return lax.broadcast_in_dim(x, bshape(shape, size), dims)


def to_front(x):
    return jnp.moveaxis(x, -1, 0)


def to_back(x):
    return jnp.moveaxis(x, 0, -1)


def fallback(prim, vals, batched, params, size, count: bool = True):
    """JAX's own batching rule, with the batch moved to the front around this one op
    (``count``: record it in :data:`FALLBACK_COUNTS`)."""
    if count:
        FALLBACK_COUNTS[prim.name] = FALLBACK_COUNTS.get(prim.name, 0) + 1
    in_axes = [0 if b else None for b in batched]
    args = [to_front(v) if b else v for v, b in zip(vals, batched)]

    bind_params = prim.get_bind_params(params)   # call primitives (custom_jvp, ...)

    def bind(*a):
        out = prim.bind(*a, **bind_params)
        return list(out) if prim.multiple_results else [out]

    outs = jax.vmap(bind, in_axes=in_axes, out_axes=0, axis_size=size)(*args)
    outs = [to_back(o) for o in outs]
    return (outs, [True] * len(outs)) if prim.multiple_results else (outs[0], True)


# ---- rules: rule(prim, vals, batched, params, size, eqn) -> (out(s), out_batched) --------


def elementwise(prim, vals, batched, params, size, eqn):
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
                v = v if vshape == shape else lax.broadcast_in_dim(v, bshape(shape, size), (len(shape),))
            else:
                v = broadcast_to_batched(v, shape, size)
        elif b and vshape != shape and not vshape:
            v = lax.reshape(v, (1,) * len(shape) + (size,))
        elif not b and vshape:
            v = lax.reshape(jnp.asarray(v), vshape + (1,))
        args.append(v)
    return prim.bind(*args, **params), True


def _broadcast_in_dim(prim, vals, batched, params, size, eqn):
    (x,) = vals[:1]
    if len(vals) > 1:      # dynamic shapes: not supported here
        return fallback(prim, vals, batched, params, size)
    shape = tuple(params["shape"]) + (size,)
    dims = tuple(params["broadcast_dimensions"]) + (len(params["shape"]),)
    return lax.broadcast_in_dim(x, shape, dims), True


def _reshape(prim, vals, batched, params, size, eqn):
    if params.get("dimensions") is not None or len(vals) > 1:
        return fallback(prim, vals, batched, params, size)
    return lax.reshape(vals[0], tuple(params["new_sizes"]) + (size,)), True


def _squeeze(prim, vals, batched, params, size, eqn):
    return lax.squeeze(vals[0], params["dimensions"]), True


def _slice(prim, vals, batched, params, size, eqn):
    x = vals[0]
    start = tuple(params["start_indices"]) + (0,)
    limit = tuple(params["limit_indices"]) + (size,)
    strides = None if params["strides"] is None else tuple(params["strides"]) + (1,)
    return lax.slice(x, start, limit, strides), True


def same_axes(prim, vals, batched, params, size, eqn):
    """Ops whose parameters name leading axes only (reductions, cumulative ops, rev)."""
    if not all(batched):
        return fallback(prim, vals, batched, params, size)
    out = prim.bind(*vals, **params)
    return (out, [True] * len(out)) if prim.multiple_results else (out, True)


def _transpose(prim, vals, batched, params, size, eqn):
    perm = tuple(params["permutation"])
    return lax.transpose(vals[0], perm + (len(perm),)), True


def _concatenate_like(prim, vals, batched, params, size, eqn):
    args = [v if b else broadcast_to_batched(v, tuple(var.aval.shape), size)
            for v, b, var in zip(vals, batched, eqn.invars)]
    out = prim.bind(*args, **params)
    return (out, [True] * len(out)) if prim.multiple_results else (out, True)


def _pad(prim, vals, batched, params, size, eqn):
    x, pad_value = vals
    if batched[1]:
        return fallback(prim, vals, batched, params, size)
    config = tuple(params["padding_config"]) + ((0, 0, 0),)
    return lax.pad(x, pad_value, config), True


def _dynamic_slice(prim, vals, batched, params, size, eqn):
    x, *idx = vals
    if any(batched[1:]) or len(idx) != len(eqn.invars[0].aval.shape):
        return fallback(prim, vals, batched, params, size)
    zero = jnp.zeros((), dtype=jnp.asarray(idx[0]).dtype) if idx else jnp.int32(0)
    return lax.dynamic_slice(x, tuple(idx) + (zero,), tuple(params["slice_sizes"]) + (size,)), True


def _dynamic_update_slice(prim, vals, batched, params, size, eqn):
    x, upd, *idx = vals
    if any(batched[2:]):
        return fallback(prim, vals, batched, params, size)
    if not batched[0]:
        x = broadcast_to_batched(x, tuple(eqn.invars[0].aval.shape), size)
    if not batched[1]:
        upd = broadcast_to_batched(upd, tuple(eqn.invars[1].aval.shape), size)
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
            return fallback(prim, vals, batched, params, size)
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
        return fallback(prim, vals, batched, params, size)
    if not batched[0]:
        operand = broadcast_to_batched(operand, tuple(eqn.invars[0].aval.shape), size)
    if not batched[2]:
        updates = broadcast_to_batched(updates, tuple(eqn.invars[2].aval.shape), size)
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
    args = [v if b else broadcast_to_batched(v, tuple(var.aval.shape), size)
            for v, b, var in zip(vals, batched, eqn.invars)]
    out = prim.bind(*args, **params)
    return list(out), [True] * len(out)


def _passthrough(prim, vals, batched, params, size, eqn):
    out = prim.bind(*vals, **params) if prim.name != "sharding_constraint" else vals[0]
    return out, batched[0]


PRIMITIVE_RULES: dict[str, Callable] = {
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": _reshape,
    "squeeze": _squeeze,
    "slice": _slice,
    "transpose": _transpose,
    "concatenate": _concatenate_like,
    "stack": _concatenate_like,
    "split": same_axes,
    "rev": same_axes,
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
}
