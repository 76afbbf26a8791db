"""The map of gradient quality on the capture task: for every segment of an episode
(:mod:`.segments`) and every horizon, the gradient of the smooth objective ``J``
(:mod:`.objective`) with respect to (a) the scripted team's parameters ``u``
(:mod:`.team`) and (b) a rollout's actions (open loop, around the scripted team's
actions), by reverse mode (:mod:`.rollout`) and by Gaussian smoothing
(:mod:`.smoothing`), over a batch of episodes.

Per (level, segment, horizon, kind) the statistics (:func:`gradient_stats`):

* ``norm_mean``, ``norm_median``, ``norm_max``: the autodiff gradient's norm [m per unit
  of ``u`` (relative change), or m per unit of normalised action];
* ``cv``: its spread over episodes relative to their mean gradient, ``sqrt(mean_e |g_e -
  mean g|^2) / |mean g|``; ``norm_cv``: the norms' standard deviation over their mean;
* ``cosine_mean``, ``cosine_median``: the cosine of each episode's autodiff gradient with
  its smoothing estimate; ``cosine_linear``: the cosine the same smoothing samples give
  for an exactly linear objective with the autodiff gradient (the ceiling ``cosine``
  can reach with that many samples in that many dimensions);
* ``nonfinite``: episodes whose gradient has a NaN or an infinity (left out of the rest),
  ``nan`` of them with a NaN;
* ``growth_per_s``: on rows without a fix, how fast the backward pass grows: the slope
  of ``ln |lam_k|`` (the state's cotangent, :mod:`.rollout`) against the time back from
  the horizon's end, fitted over the steps where it is finite and nonzero, median over
  episodes [1/s] (``|lam|`` grows ``e`` times per ``1 / growth_per_s`` seconds).

Rows with ``fix`` ``truncate<m>`` repeat the autodiff gradient with the backward pass
truncated to ``m`` policy steps (:mod:`.rollout`), against the same smoothing estimate.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.grad.engine import GradientEngine, take, to_numpy, window_keys
from mysim_jax.grad.rollout import horizon_values
from mysim_jax.grad.segments import SEGMENTS, segment_starts
from mysim_jax.grad.smoothing import antithetic_estimate, check_smoothing, directions, linear_reference

KINDS = ("team", "actions")


@dataclass(frozen=True)
class MapSettings:
    """What the map measures on one level (times in s)."""

    horizons: tuple[float, ...] = (0.1, 0.2, 0.5, 1.0, 2.0, 6.0)
    episodes: int = 6
    pairs: int = 8                  # antithetic pairs of the smoothing estimate
    sigma_team: float = 0.05        # smoothing scale on u (5 % of each team field)
    sigma_actions: float = 0.05     # smoothing scale on normalised actions (0.25 m/s at 5 m/s)
    truncate: tuple[int, ...] = ()  # policy steps of the truncated backward passes measured
    segments: tuple[str, ...] = SEGMENTS
    seed: int = 0


def check_settings(settings: MapSettings, policy_dt: float | None = None, t_end: float | None = None) -> None:
    """ValueError naming the setting for bad input; with the environment's policy period
    and episode length, also horizons shorter than one policy step or longer than the
    episode."""
    s = settings
    if not s.horizons:
        raise ValueError("horizons: give at least one horizon (s)")
    for h in s.horizons:
        if not (isinstance(h, (int, float)) and np.isfinite(h) and h > 0.0):
            raise ValueError(f"horizon {h!r}: expected a positive number of seconds")
        if policy_dt is not None and h < 0.5 * policy_dt:
            raise ValueError(f"horizon {h:g} s: shorter than one policy step ({policy_dt:g} s)")
        if t_end is not None and h > t_end + 1e-9:
            raise ValueError(f"horizon {h:g} s: longer than the episode (sim.t_end {t_end:g} s)")
    if not (isinstance(s.episodes, int) and s.episodes >= 1):
        raise ValueError(f"episodes: {s.episodes!r}, expected an int >= 1")
    check_smoothing(s.sigma_team, s.pairs)
    check_smoothing(s.sigma_actions, s.pairs)
    for m in s.truncate:
        if not (isinstance(m, int) and m >= 1):
            raise ValueError(f"truncate: {m!r}, expected a number of policy steps >= 1")
    unknown = [g for g in s.segments if g not in SEGMENTS]
    if unknown or not s.segments:
        raise ValueError(f"segments: {unknown or 'none'}; the segments are {', '.join(SEGMENTS)}")


def level_settings(settings: MapSettings, cap: float | None) -> MapSettings:
    """``settings`` without the horizons above ``cap`` [s] (None: all of them); ValueError
    when that leaves none."""
    if cap is None:
        return settings
    kept = tuple(h for h in settings.horizons if h <= cap + 1e-9)
    if not kept:
        raise ValueError(f"horizon cap {cap:g} s: below every horizon ({', '.join(f'{h:g}' for h in settings.horizons)})")
    return dataclasses.replace(settings, horizons=kept)


def horizon_steps(horizons, policy_dt: float) -> list[int]:
    """Each horizon [s] in policy steps (rounded, at least 1), without repeats, sorted."""
    return sorted({max(1, int(round(h / policy_dt))) for h in horizons})


def gradient_stats(ad, zo, eps) -> dict:
    """The statistics of the module docstring from the autodiff gradients ``ad`` ``(batch,
    *shape)``, the smoothing estimates ``zo`` ``(batch, *shape)`` and their directions
    ``eps`` ``(batch, n_pairs, *shape)`` (NumPy or JAX arrays)."""
    ad, zo, eps = (np.asarray(a, np.float64) for a in (ad, zo, eps))
    flat = ad.reshape(ad.shape[0], -1)
    zflat = zo.reshape(zo.shape[0], -1)
    finite = np.isfinite(flat).all(axis=1)
    out = {"episodes": int(finite.sum()), "nonfinite": int((~finite).sum()),
           "nan": int(np.isnan(flat).any(axis=1).sum())}
    if not finite.any():
        return out
    flat, zflat, eps = flat[finite], zflat[finite], eps[finite]
    norms = np.linalg.norm(flat, axis=1)
    mean = flat.mean(axis=0)
    spread = np.sqrt(np.mean(np.sum((flat - mean) ** 2, axis=1)))
    lin = np.stack([np.asarray(linear_reference(jnp.asarray(g), jnp.asarray(e.reshape(e.shape[0], -1))))
                    for g, e in zip(flat, eps)])
    cos = _cosines(flat, zflat)
    out.update(norm_mean=float(norms.mean()), norm_median=float(np.median(norms)), norm_max=float(norms.max()),
               cv=float(spread / max(np.linalg.norm(mean), 1e-30)),
               norm_cv=float(norms.std() / max(norms.mean(), 1e-30)),
               zo_norm_mean=float(np.linalg.norm(zflat, axis=1).mean()),
               cosine_mean=float(cos.mean()), cosine_median=float(np.median(cos)),
               cosine_linear=float(_cosines(flat, lin).mean()))
    return out


def growth_rate(norms, dt: float):
    """The median over episodes of the slope of ``ln norms`` ``(batch, n + 1)`` (from the
    horizon's end back) per second of ``dt`` per entry; None with fewer than two usable
    entries in every episode."""
    slopes = []
    for row in np.asarray(norms, np.float64):
        ok = np.isfinite(row) & (row > 0)
        if ok.sum() >= 2:
            t = np.arange(row.size)[ok] * dt
            slopes.append(np.polyfit(t, np.log(row[ok]), 1)[0])
    return float(np.median(slopes)) if slopes else None


def _cosines(a, b):
    den = np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-30)
    return np.sum(a * b, axis=1) / den


def episode_keys(seed: int, episodes: int):
    """The episodes' keys ``(episodes,)``: episode ``i`` from ``fold_in(PRNGKey(seed), i)``."""
    base = jax.random.PRNGKey(seed)
    return jnp.stack([jax.random.fold_in(base, i) for i in range(episodes)])


def smoothing_values(engine: GradientEngine, s0, keys, key, steps, settings: MapSettings, nominal_actions):
    """The smoothing estimates at every horizon of ``steps`` for every window: ``{kind:
    (estimates, eps)}`` with ``estimates[h]`` ``(batch, *shape)`` and ``eps`` ``(batch,
    n_pairs, *shape)`` (shape ``(n_params,)`` for ``team``, ``(n, n_agents, 3)`` for
    ``actions``, ``n`` the longest horizon). The perturbed runs of both kinds are one
    batch: ``2 * n_pairs`` per window and kind."""
    s, n_max = settings, max(steps)
    batch, pairs, n_params = keys.shape[0], s.pairs, engine.problem.team.size
    dtype = nominal_actions.dtype
    k_team, k_act = jax.random.split(key)
    eps_team = jax.vmap(lambda k: directions(k, pairs, (n_params,), dtype))(jax.random.split(k_team, batch))
    eps_act = jax.vmap(lambda k: directions(k, pairs, nominal_actions.shape[1:], dtype))(
        jax.random.split(k_act, batch))
    rep = np.repeat(np.arange(batch), 2 * pairs)                   # episode of each run
    sign = np.tile(np.repeat([1.0, -1.0], pairs), batch)           # + first, then -
    pair = np.tile(np.tile(np.arange(pairs), 2), batch)
    u = jnp.concatenate([s.sigma_team * sign[:, None] * eps_team[rep, pair], jnp.zeros((rep.size, n_params))])
    actions = jnp.concatenate([nominal_actions[rep], nominal_actions[rep] + s.sigma_actions
                               * sign[:, None, None, None] * eps_act[rep, pair]])
    closed = np.repeat([True, False], rep.size)
    both = np.concatenate([rep, rep])
    rows = engine.rollouts(take(s0, both), keys[both], closed, u.astype(dtype), actions.astype(dtype), n_max)[0]
    team_rows, act_rows = take(rows, np.arange(rep.size)), take(rows, np.arange(rep.size, 2 * rep.size))
    return {"team": (_estimates(team_rows, steps, batch, pairs, eps_team, s.sigma_team, False), eps_team),
            "actions": (_estimates(act_rows, steps, batch, pairs, eps_act, s.sigma_actions, True), eps_act)}


def _estimates(rows, steps, batch, pairs, eps, sigma, per_step: bool):
    values = jax.vmap(lambda r: horizon_values(r, steps))(rows).reshape(batch, 2, pairs, len(steps))
    est = {}
    for i, h in enumerate(steps):
        e = eps[:, :, :h] if per_step else eps
        est[h] = jax.vmap(lambda vp, vm, ee: antithetic_estimate(vp, vm, ee, sigma))(
            values[:, 0, :, i], values[:, 1, :, i], e)
    return est


def measure_window(engine: GradientEngine, s0, keys, key, steps, settings: MapSettings, progress=None) -> list[dict]:
    """The map's rows for windows starting at the states ``s0`` ``(batch, ...)``: for every
    horizon of ``steps`` (policy steps) and both kinds, the statistics of
    :func:`gradient_stats` (and a row per truncation of :attr:`MapSettings.truncate`
    shorter than the horizon). ``progress(n)`` is called after each horizon."""
    n_max, batch = max(steps), keys.shape[0]
    dtype = s0.sim.phys.body_pos.dtype
    u0 = jnp.zeros((batch, engine.problem.team.size), dtype)
    a0 = jnp.zeros((batch, n_max, *engine.env.action_shape), dtype)
    nominal, actions, states = engine.rollouts(s0, keys, np.ones(batch, bool), u0, a0, n_max, keep_states=True)
    window = jax.tree.map(lambda a, b: jnp.concatenate([a[None], jnp.swapaxes(b, 0, 1)]), s0, states)
    objective = np.asarray(jax.vmap(lambda r: horizon_values(r, steps))(nominal))
    smoothed = smoothing_values(engine, s0, keys, key, steps, settings, actions)
    out = []
    for i, n in enumerate(steps):
        fixes = [(None, "none")] + [(m, f"truncate{m}") for m in settings.truncate if m < n]
        for kind in KINDS:
            zo, eps = smoothed[kind]
            eps_n = eps if kind == "team" else eps[:, :, :n]
            for m, fix in fixes:
                norms = [] if m is None else None
                ad = engine.gradient(window, keys, u0, actions, n, closed_loop=kind == "team", truncate=m,
                                     norms=norms)
                row = {"steps": n, "kind": kind, "fix": fix, "objective_mean": float(objective[:, i].mean())}
                row.update(gradient_stats(to_numpy(ad), to_numpy(zo[n]), to_numpy(eps_n)))
                if norms is not None:
                    row["growth_per_s"] = growth_rate(np.stack(norms, axis=1), engine.env.policy_dt)
                out.append(row)
        if progress is not None:
            progress(1)
    return out


def measure_level(engine: GradientEngine, settings: MapSettings, level: str, progress=None) -> list[dict]:
    """The map's rows on one level (its environment in ``engine``), every segment of
    ``settings`` (module docstring). ``progress(n)`` advances a bar of ``len(segments) *
    len(steps)`` units."""
    env = engine.env
    check_settings(settings, env.policy_dt, env.max_steps * env.policy_dt)
    steps = horizon_steps(settings.horizons, env.policy_dt)
    keys = episode_keys(settings.seed, settings.episodes)
    rows, states = engine.episodes(keys)
    starts = segment_starts(np.asarray(rows.touching), np.asarray(rows.taut))
    out = []
    for g, segment in enumerate(settings.segments):
        start, valid = starts[segment]
        idx = np.flatnonzero(valid)
        base = {"level": level, "segment": segment, "windows": int(idx.size)}
        if idx.size == 0:
            out += [dict(base, steps=n, kind=kind, fix="none", episodes=0) for n in steps for kind in KINDS]
            if progress is not None:
                progress(len(steps))
            continue
        s0 = jax.tree.map(lambda a: a[start[idx], idx], states)
        wkeys = window_keys(keys[idx], start[idx])
        key = jax.random.fold_in(jax.random.PRNGKey(settings.seed), 1000 + g)
        base["start_mean_s"] = float(start[idx].mean() * env.policy_dt)
        contact, touched = starts["contact"]
        base["after_contact"] = int(np.sum(touched[idx] & (start[idx] >= contact[idx]))) if segment != "contact" else 0
        out += [dict(base, **r) for r in measure_window(engine, s0, wkeys, key, steps, settings, progress)]
    for r in out:
        r["horizon_s"] = r["steps"] * env.policy_dt
    return out
