"""Evaluating a per-environment jaxpr on batch-last values: the interpreter that re-emits
it equation by equation (:func:`eval_batch_last`), and the rules of the primitives that hold
jaxprs of their own (nested ``jit``, ``scan``, ``while``, ``cond``), which it evaluates
recursively.

The rules of single primitives are in :mod:`mysim_jax.core.batch_last_ops`; the public entry
point is :func:`mysim_jax.core.batching.vmap`, whose docstring describes the approach.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
from jax import lax
from jax.extend import core as jcore

from mysim_jax.core.batch_last_ops import (CUMULATIVE, ELEMENTWISE, PRIMITIVE_RULES, REDUCTIONS, broadcast_to_batched,
                                           bshape, elementwise, fallback, same_axes)

try:  # the name stack of re-emitted equations (JAX's own eval_jaxpr does the same)
    from jax._src import source_info_util as _source_info_util
except ImportError:  # pragma: no cover - a JAX without it loses only the scope names
    _source_info_util = None

__all__ = ["eval_batch_last"]


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

    avals = [jax.ShapeDtypeStruct(bshape(v.aval.shape, size) if b else v.aval.shape, v.aval.dtype)
             for v, b in zip(jaxpr.jaxpr.invars, in_b)]
    jax.eval_shape(f, *avals)
    return list(result["b"])


def _make_batched(vals, batched, want, invars, size):
    return [v if (b or not w) else broadcast_to_batched(v, tuple(var.aval.shape), size)
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
        return fallback(prim, vals, batched, params, size)   # a per-environment trip count
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
            return fallback(prim, [index] + list(a), batched, params, size, count=False)[0]

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
    **PRIMITIVE_RULES,
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
    if name in ELEMENTWISE:
        return elementwise(prim, vals, batched, params, size, eqn)
    if name in REDUCTIONS or name in CUMULATIVE:
        return same_axes(prim, vals, batched, params, size, eqn)
    if name == "bitcast_convert_type" and tuple(eqn.invars[0].aval.shape) == tuple(eqn.outvars[0].aval.shape):
        return elementwise(prim, vals, batched, params, size, eqn)     # same bit width
    rule = _RULES.get(name)
    if rule is None:
        return fallback(prim, vals, batched, params, size)
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
    outs = [o if b else broadcast_to_batched(o, tuple(v.aval.shape), size)
            for o, b, v in zip(outs, outs_b, closed.jaxpr.outvars)]
    return jax.tree.unflatten(jax.tree.structure(out_shape), outs)

