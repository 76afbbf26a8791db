"""Gradient-based tuning of the PID gains through the whole closed-loop simulation.

Loss: the mean squared position error ``L = mean_t |r(t) − r_d(t)|²`` (m²) of every
controlled quadrotor over a horizon, sampled every ``every`` steps (``√L`` is the RMS
tracking error). ``jax.value_and_grad`` differentiates it through the controller, the
motor model, the rotor forces and the integrator, step by step.

Positive parametrisation: ``gain = gain₀ · exp(θ)`` per entry (θ starts at 0), so
gains stay positive and a step in θ is a relative change; entries that start at zero
(the paper's roll/pitch attitude integrators) stay zero.

Long horizons (``scripts/tune_pid.py --horizon-study`` measures them; its figures are in
docs/physics.md, "Gradient-based tuning"):

* gradient size: the closed loop is stable, so |∇L| grows with the horizon about as fast
  as the loss itself does: no exponential blow-up, finite everywhere. Full
  back-propagation through every step is used; truncated back-propagation
  (``truncate``) stays available, but its gradient points elsewhere than the full one
  on long horizons;
* memory: plain reverse mode stores every step's residuals, in proportion to the
  horizon (the study's XLA temporaries per horizon are in the same section): small
  enough for the shipped scenes' horizons, which is why it is the default; ``remat=True``
  (``--checkpoint``) puts each chunk of ``every`` steps under ``jax.checkpoint`` and
  stores one state per chunk, at the price of recomputing the steps and a slower
  compile, for long horizons or many vehicles;
* guards: Adam's per-coordinate steps are bounded by about the learning rate (a relative
  gain change of a few per cent per step), gradients are clipped to a global norm of 1
  (far above the norms measured on the shipped scenes, so only a spike is cut), and
  non-finite updates are skipped (``optax.apply_if_finite``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from mysim_jax.control.pid import PIDGains
from mysim_jax.tuning.tracking import position_errors
from mysim_jax.sim import step


def gains_of(params) -> PIDGains:
    return params.controller.gains


def with_gains(params, gains: PIDGains):
    """``params`` with the controller gains replaced."""
    return params.replace(controller=params.controller.replace(gains=gains))


def gains_from_log(theta: PIDGains, base: PIDGains) -> PIDGains:
    """``base · exp(θ)`` where ``base > 0``; zero where ``base == 0``."""
    return jax.tree.map(lambda t, b: jnp.where(b > 0, b * jnp.exp(t), 0.0), theta, base)


def training_rollout(scene, params, state, n_steps: int, every: int = 10, truncate: int | None = None,
                         remat: bool = False):
    """Like :func:`mysim_jax.sim.rollout` (states after every ``every``-th step).
    ``remat``: each chunk of ``every`` steps under ``jax.checkpoint`` (reverse mode then
    stores one state per chunk). ``truncate``: stop gradients through the carried state
    every ``truncate`` chunks (truncated back-propagation)."""
    if n_steps % every:
        raise ValueError(f"n_steps ({n_steps}) must be a multiple of every ({every})")

    def chunk(p, s):
        return jax.lax.scan(lambda c, _: (step(scene, p, c), None), s, None, length=every)[0]

    if remat:
        chunk = jax.checkpoint(chunk)

    def outer(s, k):
        if truncate is not None:
            s = jax.tree.map(lambda a: jnp.where(k % truncate == 0, jax.lax.stop_gradient(a), a), s)
        s = chunk(params, s)
        return s, s

    return jax.lax.scan(outer, state, jnp.arange(n_steps // every))


def tracking_loss(scene, params, state, n_steps: int, every: int = 10, truncate: int | None = None,
                  remat: bool = False):
    """Mean squared position error (m²) over ``n_steps`` steps, sampled every ``every``."""
    _, states = training_rollout(scene, params, state, n_steps, every, truncate, remat)
    err = position_errors(scene, params, states)
    return jnp.mean(jnp.sum(err * err, axis=-1))


def log_gain_loss(scene, params, state, n_steps: int, every: int = 10, truncate: int | None = None,
                  remat: bool = False):
    """``θ ↦ L`` with ``gains = gains₀ exp(θ)`` (gains₀ those in ``params``)."""
    base = gains_of(params)

    def loss(theta):
        p = with_gains(params, gains_from_log(theta, base))
        return tracking_loss(scene, p, state, n_steps, every, truncate, remat)

    return loss


def zeros_like_gains(params) -> PIDGains:
    return jax.tree.map(jnp.zeros_like, gains_of(params))


@dataclass
class TuningResult:
    """Outcome of :func:`tune` (host-side NumPy)."""

    gains: PIDGains                       # best gains found (lowest loss evaluated)
    initial_loss: float
    best_loss: float
    best_iteration: int
    losses: list[float] = field(default_factory=list)      # loss at each iteration's θ
    grad_norms: list[float] = field(default_factory=list)  # |∇θ L| before clipping


def tune(scene, params, state, n_steps: int, iterations: int = 40, learning_rate: float = 0.05,
         clip_norm: float = 1.0, every: int = 10, remat: bool = False, progress: bool = True) -> TuningResult:
    """Adam on the log-gains (global-norm clipping, non-finite updates skipped).

    Returns the best gains seen (each iteration evaluates the loss at its θ before the
    update; one extra evaluation scores the final θ).
    """
    loss_fn = log_gain_loss(scene, params, state, n_steps, every, remat=remat)
    value_and_grad = jax.jit(jax.value_and_grad(loss_fn))
    optimizer = optax.apply_if_finite(
        optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(learning_rate)), max_consecutive_errors=10
    )
    theta = zeros_like_gains(params)
    opt_state = optimizer.init(theta)
    base = gains_of(params)
    losses, norms = [], []
    best = (np.inf, -1, theta)
    bar = None
    if progress:
        bar = tqdm(total=iterations + 1, desc="tune gains", unit="it")
    for it in range(iterations + 1):
        loss, grad = value_and_grad(theta)
        loss = float(loss)
        losses.append(loss)
        norms.append(float(optax.tree.norm(grad)))
        if np.isfinite(loss) and loss < best[0]:
            best = (loss, it, theta)
        if bar is not None:
            bar.set_postfix(rms_m=f"{np.sqrt(loss):.4g}" if np.isfinite(loss) else "nan")
            bar.update(1)
        if it == iterations:
            break
        updates, opt_state = optimizer.update(grad, opt_state, theta)
        theta = optax.apply_updates(theta, updates)
    if bar is not None:
        bar.close()
    gains = jax.tree.map(np.asarray, gains_from_log(best[2], base))
    return TuningResult(gains=gains, initial_loss=losses[0], best_loss=best[0], best_iteration=best[1],
                        losses=losses, grad_norms=norms)


def gains_to_dict(gains: PIDGains, quad: int = 0) -> dict:
    """One quadrotor's gains as the ``controller`` section of a scene file."""
    def vec(a):
        return [float(x) for x in np.asarray(a)[quad]]

    return {
        "position": {"kp": vec(gains.position_kp), "ki": vec(gains.position_ki), "kd": vec(gains.position_kd)},
        "attitude": {"kp": vec(gains.attitude_kp), "ki": vec(gains.attitude_ki), "kd": vec(gains.attitude_kd)},
    }


def horizon_study(scene, params, state, horizons_s, every: int = 10, truncate_s: float = 1.0,
                  repeats: int = 3, progress: bool = True) -> list[dict]:
    """Measure, per horizon: loss, |∇θ L| (the default, plain back-propagation), the same
    gradient with checkpointing (``remat``) and with truncated back-propagation (windows
    of ``truncate_s``), the time of one gradient evaluation (median of ``repeats``),
    the compile time and XLA's temporary memory."""
    rows = []
    theta = zeros_like_gains(params)
    bar = None
    if progress:
        bar = tqdm(total=len(list(horizons_s)), desc="horizon study", unit="horizon")
    for horizon in horizons_s:
        n = int(round(horizon / scene.dt / every)) * every
        row = {"horizon_s": n * scene.dt, "steps": n}
        grads = {}
        for name, kw in (("plain", {}), ("checkpointed", {"remat": True}),
                         ("truncated", {"truncate": max(1, int(round(truncate_s / scene.dt / every)))})):
            fn = jax.jit(jax.value_and_grad(log_gain_loss(scene, params, state, n, every, **kw)))
            t0 = time.perf_counter()
            compiled = fn.lower(theta).compile()
            compile_s = time.perf_counter() - t0
            loss, grad = compiled(theta)
            jax.block_until_ready(grad)
            grads[name] = np.concatenate([np.ravel(np.asarray(g)) for g in jax.tree.leaves(grad)])
            if name == "truncated":
                continue
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(compiled(theta))
                times.append(time.perf_counter() - t0)
            memory = compiled.memory_analysis()
            row[f"{name}_grad_time_s"] = float(np.median(times))
            row[f"{name}_compile_s"] = compile_s
            row[f"{name}_temp_mb"] = float(memory.temp_size_in_bytes / 1e6) if memory is not None else None
            if name == "plain":
                row["loss_m2"] = float(loss)
                row["rms_m"] = float(np.sqrt(loss))
                row["grad_norm"] = float(np.linalg.norm(grads[name]))
                row["finite"] = bool(np.isfinite(grads[name]).all())
        full = grads["plain"]
        row["checkpointed_max_rel_diff"] = float(
            np.abs(grads["checkpointed"] - full).max() / max(np.abs(full).max(), 1e-30))
        trunc = grads["truncated"]
        row["truncated_cosine"] = float(full @ trunc / max(np.linalg.norm(full) * np.linalg.norm(trunc), 1e-30))
        row["truncated_norm_ratio"] = float(np.linalg.norm(trunc) / max(np.linalg.norm(full), 1e-30))
        rows.append(row)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return rows
