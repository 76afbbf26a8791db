"""A training run on disk: what ``scripts/train.py`` does, as library code (the folder's
files and the checked run: :mod:`mysim_jax.mappo.run_files`; its curves:
:mod:`mysim_jax.io.training_plots`).

A run folder ``OUT`` holds

* ``train.yaml`` — the resolved training file, its ``env.scene`` pointing at
  ``scene.yaml`` (the resolved training scene, overrides and level applied) and, when the
  final evaluation runs on another fidelity level (``env.eval_level``, default ``full``),
  its ``env.eval_scene`` at ``scene_eval.yaml``: the folder is self-contained and
  ``--resume OUT`` needs nothing else;
* ``metrics.csv`` — one row per iteration (env steps, wall time, return, success rate,
  losses, ...), and the same scalars as TensorBoard events under ``tb/``;
* ``curves.png`` — learning curves;
* ``checkpoints/<iteration>/`` — orbax checkpoints of the whole trainer state, every
  ``run.checkpoint_every`` iterations and at the end;
* ``policy/`` — the final deterministic policy (``scripts/evaluate.py --policy OUT/policy``);
* ``eval/`` — the final evaluation, the report of ``scripts/evaluate.py``
  (:func:`mysim_jax.tasks.report.write_evaluation`);
* ``summary.json`` — iterations, env steps, training wall time and throughput, the
  evaluation's success rate.

**Resuming** continues from the last complete checkpoint: rows of ``metrics.csv`` after it
are dropped and recomputed, so a run killed at any moment (SIGKILL included) loses at most
``checkpoint_every`` iterations, and the resumed run's states equal those of an uninterrupted
run bit for bit (same machine and JAX build).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Callable

import jax
from jax.experimental import multihost_utils
import jax.numpy as jnp
import numpy as np
from tensorboardX import SummaryWriter
from tqdm.auto import tqdm

from mysim_jax.core import parallel
from mysim_jax.core.machine import machine
from mysim_jax.core.config_base import ConfigError
from mysim_jax.io.training_plots import plot_curves
from mysim_jax.mappo import bc
from mysim_jax.mappo.checkpoint import Checkpoints, load_policy, save_policy
from mysim_jax.mappo.config import TrainConfig, check_memory_needs, init_policy_path
from mysim_jax.mappo.curriculum import Curriculum
from mysim_jax.mappo.policies import PolicyError, check_trained_on
from mysim_jax.mappo.run_files import (CSV_FIELDS, EVAL_SCENE_FILE, SCENE_FILE, Prepared, describe_run,
                                       load_run_config, prepare, read_rows, write_rows, write_run_files)
from mysim_jax.mappo.toy import ReachEnv
from mysim_jax.mappo.trainer import Trainer, deterministic_policy, deterministic_policy_fn
from mysim_jax.tasks.capture import make_env, scaled_target_ranges
from mysim_jax.tasks.contract import environment_contract
from mysim_jax.tasks.evaluate import Evaluator
from mysim_jax.tasks.report import comparison_line, summary_line, write_comparison, write_evaluation
from mysim_jax.tasks.sweep import wilson_interval

# a run from a training file: prepare (or load_run_config) -> train_run; the first three
# live with the run folder's files (mysim_jax.mappo.run_files)
__all__ = ["Prepared", "prepare", "load_run_config", "describe_run", "make_environment", "make_eval_environment",
           "training_mesh", "train_run", "evaluate_builtin"]


def _silent(*args, **kwargs) -> None:
    """The log of a process that is not the first (several processes print nothing)."""


def training_mesh(config, source: str):
    """The devices a run splits its environments over (``run.devices``): None for one
    device, else a :func:`mysim_jax.core.parallel.env_mesh`. Raises ConfigError when more devices
    are asked for than JAX sees, or when ``algo.num_envs`` does not split into them."""
    available = jax.devices()
    n = len(available) if config.run.devices is None else config.run.devices
    if n > len(available):
        raise ConfigError(f"{source}: run.devices {n}: JAX sees {len(available)} device(s) here "
                          f"({available[0].platform})")
    if config.algo.num_envs % n:
        raise ConfigError(f"{source}: algo.num_envs {config.algo.num_envs} is not divisible by the {n} devices the "
                          f"environments are split over (run.devices{'' if config.run.devices else ': every device'}); "
                          "choose a multiple, or set run.devices")
    return None if n == 1 else parallel.env_mesh(available[:n])


def make_environment(p: Prepared):
    """``(env, env_params)`` of the run."""
    if p.scene is None:
        env = ReachEnv()
        return env, env.default_params()

    if p.scene.sim.precision == "float64":
        jax.config.update("jax_enable_x64", True)

    return make_env(p.scene)


def make_eval_environment(p: Prepared, env, env_params):
    """``(env, env_params)`` of the final evaluation: ``env, env_params`` themselves when it
    runs on the training scene. Raises ConfigError when the evaluation scene's
    observations or actions differ in shape from training's (levels change physical
    values, not what the policy sees)."""
    if not p.evaluates_elsewhere:
        return env, env_params

    eval_env, eval_params = make_env(p.eval_scene)
    if (eval_env.obs_size, tuple(eval_env.action_shape)) != (env.obs_size, tuple(env.action_shape)):
        raise ConfigError(f"{p.source}: env.eval_level: the evaluation scene's observations/actions "
                          f"({eval_env.obs_size}, {tuple(eval_env.action_shape)}) differ from training's "
                          f"({env.obs_size}, {tuple(env.action_shape)})")
    return eval_env, eval_params


def evaluate_builtin(env, env_params, policy, episodes: int, seed: int) -> dict:
    """Success rate of ``policy`` on the builtin environment (``episodes`` episodes)."""
    def one_episode(key):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, env_params)

        def body(carry, k):
            obs, state, finished, success = carry
            a = policy(k, obs, state, env_params)
            obs, state, _, _, _, info = env.step(k, state, a, env_params)
            success = success | (info["success"] & ~finished)
            return (obs, state, finished | info["done"], success), None

        (_, _, _, success), _ = jax.lax.scan(body, (obs, state, jnp.bool_(False), jnp.bool_(False)),
                                             jax.random.split(k1, env.max_steps))
        return success

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    success = jax.device_get(jax.jit(jax.vmap(one_episode))(keys))

    k = int(success.sum())
    lo, hi = wilson_interval(k, episodes)
    return {"episodes": episodes, "success": {"count": k, "rate": k / episodes, "interval95": [lo, hi]}}


def _selection_row(stats) -> dict:
    return {"select_success": float(stats.success.mean()), "select_return": float(stats.returns.mean())}


@dataclass
class _Session:
    """What the stages of one training run share (:func:`train_run`)."""

    p: Prepared
    log: Callable
    progress: bool
    lead: bool                 # this process writes the run folder, logs and evaluates
    many: bool                 # several processes (jax.distributed) train the run together
    env: object
    env_params: object
    trainer: Trainer
    ckpt: Checkpoints
    eval_env: object = None    # the evaluation scene's environment (capture scenes, when evaluating)
    eval_params: object = None
    curriculum: Curriculum | None = None
    evaluator: Evaluator | None = None    # model selection on fixed episodes
    select_key: object = None

    @property
    def c(self) -> TrainConfig:
        return self.p.config

    @property
    def selection(self):
        return self.c.run.selection if self.p.scene is not None else None

    def select(self, state):
        """Fly the selection episodes with the current policy; keep it if it is the best."""
        arrays = self.trainer.policy_arrays(state)
        if self.many:                 # on this process's device: the networks as host arrays
            arrays = jax.device_get(arrays)
        stats = self.evaluator(self.select_key, self.selection.episodes, arrays)
        state = self.trainer.keep_if_best(state, int(stats.success.sum()), float(stats.returns.mean()))
        return state, stats

    def say(self, bar, msg: str) -> None:
        if bar is not None:
            bar.write(msg)
        else:
            self.log(msg)


def _open_session(p: Prepared, progress: bool, evaluate: bool, log) -> _Session:
    """Everything that can refuse the run, checked before the run folder is written and
    before anything compiles: the environments, a starting policy, the devices, the memory."""
    c = p.config
    lead = jax.process_index() == 0
    many = jax.process_count() > 1
    if not lead:
        log = _silent
        progress = False
    env, env_params = make_environment(p)
    eval_env = eval_params = None
    if evaluate and p.scene is not None:
        eval_env, eval_params = make_eval_environment(p, env, env_params)
        if c.run.eval_batch > c.run.eval_episodes:
            log(f"note: run.eval_batch {c.run.eval_batch} is more than run.eval_episodes {c.run.eval_episodes}: "
                f"the final evaluation runs {c.run.eval_episodes} side by side")
    if c.algo.init == "policy" and not p.resume:
        # the starting policy must fit this environment (shapes and meaning)
        folder = init_policy_path(c, p.source)
        try:
            check_trained_on(load_policy(folder)[0], env, env_params, f"{p.source}: algo.init_policy {folder}")
        except PolicyError as err:
            raise ConfigError(str(err)) from None
    trainer = Trainer(c.algo, env, env_params, mesh=training_mesh(c, p.source))
    check_memory_needs(trainer.memory_needs(), p.source)
    if not p.resume and lead:
        write_run_files(p)
    return _Session(p=p, log=log, progress=progress, lead=lead, many=many, env=env, env_params=env_params,
                    trainer=trainer, ckpt=Checkpoints(p.out / "checkpoints", keep=c.run.keep_checkpoints),
                    eval_env=eval_env, eval_params=eval_params,
                    curriculum=Curriculum(c.env.curriculum) if p.scene is not None and c.env.curriculum else None)


def _restore(s: _Session, state) -> tuple[object, int, bool, list[dict]]:
    """The state to start from (the newest intact checkpoint when resuming), its iteration,
    whether it was restored, and the metrics rows up to it."""
    start_iteration, restored = 0, False
    if s.p.resume:
        try:
            last, state = s.ckpt.restore_newest(state, log=s.log)
        except Exception:
            s.ckpt.close()               # orbax's threads end before the error reaches the script
            raise
        if last is not None:
            start_iteration, restored = int(state.iteration), True
    rows = read_rows(s.p.out / "metrics.csv", start_iteration)
    if s.p.resume:
        s.log(f"resuming {s.p.out} at iteration {start_iteration} of {s.c.algo.num_iterations}")
    return state, start_iteration, restored, rows


def _start_curriculum(s: _Session, state):
    """``state`` with the curriculum at its first stage and the training episodes drawn from
    that stage's ranges (a fresh run; a resumed one's checkpoint replaces both)."""
    if s.curriculum is None:
        return state
    cs = s.curriculum.start()
    return s.trainer.with_episode_ranges(state.replace(curriculum=cs),
                                         scaled_target_ranges(s.env_params.ranges, s.curriculum.fraction(cs)))


def _start_selection(s: _Session, state) -> None:
    """Say where the curriculum stands (from the state: a resumed run's checkpoint holds it)
    and build the selection evaluator."""
    c = s.c
    if s.curriculum is not None:
        fraction = s.curriculum.fraction(state.curriculum)
        s.log(f"curriculum: stage {int(state.curriculum.stage) + 1} of {len(c.env.curriculum.stages)} (the target's "
              f"speed, jink and flee ranges x {fraction:g})")
    # model selection on fixed episodes (capture environments; the builtin task has its own evaluation)
    if s.selection is not None:
        s.evaluator = Evaluator(s.env, s.env_params, s.trainer.policy_fn(),
                                batch=min(s.selection.episodes, c.run.eval_batch))
        s.select_key = jax.random.PRNGKey(s.selection.seed)


def _warm_start(s: _Session, state, k_bc, t_start: float, rows: list[dict]):
    """A new run: clone the scripted team (``algo.init: bc``) or start from a saved policy
    (``algo.init: policy``), fly the selection episodes once before training, and
    checkpoint iteration 0. Returns ``(state, rows)``."""
    c = s.c
    if c.algo.init == "policy":
        folder = init_policy_path(c, s.p.source)
        meta, arrays = load_policy(folder)
        state = bc.from_policy(s.trainer, state, meta, arrays, f"algo.init_policy {folder}")
        s.log(f"starting from the policy {folder} (iteration {meta.get('selected_iteration')} of "
              f"{meta.get('train')}): exploration std {c.algo.bc.std:g}, critic warm-up "
              f"{c.algo.bc.critic_warmup} iterations")
    if c.algo.init == "bc":
        s.log(f"behaviour cloning the scripted team: {c.algo.bc.num_envs} environments x {c.algo.bc.steps} steps")
        state, report = bc.clone(s.trainer, state, k_bc)
        if s.lead:
            (s.p.out / "bc.json").write_text(json.dumps(report, indent=2))
        s.log(f"cloned in {report['collect_s'] + report['fit_s']:.0f} s: {report['pairs']:,} pairs, held-out RMSE "
              f"{report['rmse_holdout']:.3f}, R2 {', '.join(f'{v:.3f}' for v in report['r2_holdout'])}")
    if s.evaluator is not None:
        state, stats = s.select(state)
        rows = [{"iteration": 0, "env_steps": 0, "wall_s": round(time.perf_counter() - t_start, 3),
                 **_selection_row(stats)}]
        s.log(f"selection episodes before training: success {stats.success.mean():.1%}")
    if s.trainer.uses_anchor or s.evaluator is not None:
        if s.lead:
            write_rows(s.p.out / "metrics.csv", rows)
        s.ckpt.save(0, s.trainer.place(state))
    return state, rows


def _iteration_row(s: _Session, state, iteration: int, dt: float, m: dict, bar):
    """One iteration's metrics row, and the state with the curriculum advanced on the
    iteration's success: ``(state, row)``."""
    row = {"iteration": iteration, "env_steps": iteration * s.c.algo.batch_size,
           "iteration_s": round(dt, 4), "lr": s.trainer.learning_rate(iteration - 1),
           **{k: m[k] for k in CSV_FIELDS if k in m}}
    cur = s.curriculum
    if cur is not None:
        row.update(curriculum_stage=cur.stage(state.curriculum), curriculum_fraction=cur.fraction(state.curriculum))
        cs, moved = cur.update(state.curriculum, m["success_rate"])
        state = state.replace(curriculum=cs)
        if moved:
            state = s.trainer.with_episode_ranges(state, scaled_target_ranges(s.env_params.ranges, cur.fraction(cs)))
            s.say(bar, f"curriculum: stage {int(cs.stage) + 1} of {len(s.c.env.curriculum.stages)} from "
                       f"iteration {iteration + 1} (ranges x {cur.fraction(cs):g})")
    return state, row


def _show_progress(s: _Session, bar, row: dict, m: dict, dt: float) -> None:
    if bar is None:
        return
    bar.update(1)
    sel = f", selection {row['select_success']:.0%}" if "select_success" in row else ""
    if "curriculum_stage" in row:
        sel += f", stage {row['curriculum_stage'] + 1}"
    bar.set_postfix_str(f"return {m['mean_return']:.2f}, success {m['success_rate']:.0%}{sel}, "
                        f"{s.c.algo.batch_size / dt:,.0f} team steps/s")


@dataclass
class _Trained:
    state: object
    rows: list
    iteration: int
    iteration_times: list
    stopped_early: bool


def _train_loop(s: _Session, state, rows: list[dict], start_iteration: int, previous_wall: float,
                t_start: float) -> _Trained:
    """PPO iterations until the planned number or the time limit; rows, TensorBoard,
    selection and checkpoints as configured."""
    c = s.c
    writer = SummaryWriter(str(s.p.out / "tb"), purge_step=start_iteration + 1) if s.lead else None
    bar = None
    if s.progress:
        bar = tqdm(total=c.algo.num_iterations, initial=start_iteration, desc=f"training {c.name}", unit="it")
    limit_s = None if c.run.time_limit_min is None else 60.0 * c.run.time_limit_min
    iteration_times, stopped_early, iteration = [], False, start_iteration
    while iteration < c.algo.num_iterations:
        t0 = time.perf_counter()
        state, m = s.trainer.iteration(state)
        m = {k: float(v) for k, v in jax.device_get(m).items()}
        dt = time.perf_counter() - t0
        iteration += 1
        if iteration > start_iteration + 1:     # the first call of a process compiles
            iteration_times.append(dt)
        last_iteration = iteration == c.algo.num_iterations
        over_time = limit_s is not None and previous_wall + time.perf_counter() - t_start > limit_s
        if s.many and limit_s is not None:      # the first process's clock decides for all
            over_time = bool(multihost_utils.broadcast_one_to_all(np.bool_(over_time)))
        state, row = _iteration_row(s, state, iteration, dt, m, bar)
        if s.evaluator is not None and (iteration % s.selection.every == 0 or last_iteration or over_time):
            state, stats = s.select(state)
            row.update(_selection_row(stats))
        row["wall_s"] = round(previous_wall + time.perf_counter() - t_start, 3)
        rows.append(row)
        for k, v in row.items():
            if k != "iteration" and writer is not None:
                writer.add_scalar(f"train/{k}", float(v), iteration)
        _show_progress(s, bar, row, m, dt)
        if iteration % c.run.checkpoint_every == 0 or last_iteration or over_time:
            if s.lead:
                write_rows(s.p.out / "metrics.csv", rows)
                writer.flush()
            s.ckpt.save(iteration, s.trainer.place(state))
        if over_time and not last_iteration:
            stopped_early = True
            s.log(f"time limit of {c.run.time_limit_min:g} min reached after iteration {iteration}")
            break
    if bar is not None:
        bar.close()
    if writer is not None:
        writer.close()
    s.ckpt.close()
    return _Trained(state, rows, iteration, iteration_times, stopped_early)


def _summary(s: _Session, run: _Trained, train_wall: float) -> dict:
    """``summary.json`` before the final evaluation."""
    c, rows, iteration = s.c, run.rows, run.iteration
    n_agents, _ = s.env.action_shape
    # None (JSON null) when no iteration after the first ran in this process (it compiles)
    per_iteration = float(np.median(run.iteration_times)) if run.iteration_times else None
    summary = {
        "name": c.name, "config": s.p.source, "iterations": iteration, "planned_iterations": c.algo.num_iterations,
        # what ended training: the step budget (algo.total_env_steps), or the optional time
        # guard (run.time_limit_min), which makes the result depend on the machine's speed
        "stopped_by": "time_limit" if run.stopped_early else "step_budget",
        "stopped_by_time_limit": run.stopped_early, "env_steps": iteration * c.algo.batch_size,
        "planned_env_steps": c.algo.num_iterations * c.algo.batch_size,
        "agent_steps": iteration * c.algo.batch_size * n_agents,
        "training_wall_s_this_process": round(train_wall, 1),
        "training_wall_s_total": float(rows[-1]["wall_s"]) if rows else 0.0,
        "median_iteration_s": per_iteration,
        "env_steps_per_s_with_update": c.algo.batch_size / per_iteration if per_iteration else None,
        "final_train_success_rate": float(rows[-1]["success_rate"]) if rows and "success_rate" in rows[-1] else None,
        "init": c.algo.init,
        "init_policy": c.algo.init_policy,
        "machine": machine(),              # what the wall times above were measured on
        "devices": 1 if s.trainer.mesh is None else s.trainer.mesh.size,
        "processes": jax.process_count(),
    }
    bc_path = s.p.out / "bc.json"
    if bc_path.exists():
        summary["behaviour_cloning"] = json.loads(bc_path.read_text())
    if s.curriculum is not None:
        # the first iteration drawn from the full ranges (None: never reached), from the rows
        # so that a resumed run reports it too
        full = [int(float(r["iteration"])) for r in rows
                if r.get("curriculum_stage") not in ("", None)
                and int(float(r["curriculum_stage"])) == len(c.env.curriculum.stages) - 1]
        summary["curriculum"] = {"stages": list(c.env.curriculum.stages),
                                 "final_stage": s.curriculum.stage(run.state.curriculum),
                                 "full_range_from_iteration": full[0] if full else None}
    if s.selection is not None:
        score = [float(x) for x in jax.device_get(run.state.best_score)]
        summary["selection"] = {"episodes": s.selection.episodes, "seed": s.selection.seed,
                                "every": s.selection.every, "selected_iteration": int(run.state.best_iteration),
                                "successes": int(score[0]), "mean_return": score[1]}
    return summary


def _save_policy(s: _Session, run: _Trained, arrays) -> None:
    c = s.c
    n_agents, act = s.env.action_shape
    best_iteration = int(run.state.best_iteration)
    meta = {"kind": "mappo", "obs_size": int(s.env.obs_size), "action_shape": [n_agents, act],
            "hidden": list(c.algo.hidden), "activation": c.algo.activation, "normalize_obs": c.algo.normalize_obs,
            "residual": c.algo.residual,
            "env": "builtin:" + c.env.builtin if c.env.builtin else SCENE_FILE, "iteration": run.iteration,
            "selected_iteration": best_iteration if best_iteration >= 0 else run.iteration, "train": c.name}
    if s.p.scene is not None:
        # what the policy's observations and actions mean: evaluating it elsewhere is checked against it
        meta["environment"] = environment_contract(s.env, s.env_params)
    save_policy(s.p.out / "policy", arrays, meta)


def _evaluate_capture(s: _Session, arrays, summary: dict) -> None:
    """The policy (and, with ``run.eval_baseline``, the scripted team) on the same fresh
    episodes of the evaluation scene; ``eval/`` and the summary's evaluation entries."""
    c, p, eval_env = s.c, s.p, s.eval_env
    # on the evaluation scene (env.eval_level): the policy's residual base, if any, is that
    # scene's scripted team
    eval_base = eval_env.scripted_actions if c.algo.residual else None
    net = deterministic_policy_fn(s.trainer.actor, c.algo.normalize_obs, eval_base)
    eval_policy = deterministic_policy(s.trainer.actor, arrays, c.algo.normalize_obs, eval_base)

    # one compiled program flies both teams: the argument says whose actions are used
    def either(key, obs, state, params, args):
        arrays, scripted = args
        return jnp.where(scripted, eval_env.scripted_actions(state, params), net(key, obs, state, params, arrays))

    final = Evaluator(eval_env, s.eval_params, either, batch=c.run.eval_batch)
    eval_key = jax.random.PRNGKey(c.run.eval_seed)
    stats = final(eval_key, c.run.eval_episodes, (arrays, jnp.bool_(False)), progress=s.progress,
                  desc="evaluation")
    eval_scene = p.eval_scene if p.evaluates_elsewhere else p.scene
    eval_file = EVAL_SCENE_FILE if p.evaluates_elsewhere else SCENE_FILE
    metrics = write_evaluation(p.out / "eval", eval_scene, eval_env, s.eval_params, eval_policy,
                               policy_name=str(p.out / "policy"), episodes=c.run.eval_episodes,
                               batch=c.run.eval_batch, seed=c.run.eval_seed,
                               config_path=str(p.out / eval_file), progress=s.progress, animate=False, stats=stats)
    s.log(summary_line(p.scene.name, f"trained (MAPPO), evaluated at level {eval_scene.level}"
                       if p.evaluates_elsewhere else "trained (MAPPO)", metrics, p.out / "eval"))
    summary["evaluation"] = {k: metrics[k] for k in ("episodes", "success", "failures", "timeout",
                                                     "mean_return", "mean_length_steps", "wall_s")}
    summary["evaluation"]["level"] = eval_scene.level
    summary["evaluation"]["scene"] = eval_file
    summary["training_level"] = p.scene.level
    if c.run.eval_baseline:
        base_stats = final(eval_key, c.run.eval_episodes, (arrays, jnp.bool_(True)), progress=s.progress,
                           desc="scripted team")
        comparison = write_comparison(p.out / "eval", stats, base_stats, names=("trained", "scripted"),
                                      seed=c.run.eval_seed)
        s.log(comparison_line(comparison))
        summary["baseline"] = comparison


def train_run(p: Prepared, progress: bool = True, evaluate: bool = True, log=print) -> dict:
    """Train (or resume) the run ``p`` to its end, evaluate, write everything. Returns
    ``summary.json``'s dict. With several processes (jax.distributed) every one computes;
    the first writes the run folder, the logs and the evaluation, and decides when to stop."""
    s = _open_session(p, progress, evaluate, log)
    c = s.c
    k_init, k_bc = jax.random.split(jax.random.PRNGKey(c.run.seed))
    t_compile = time.perf_counter()
    # a fresh state (with the curriculum's first stage): the start of a new run, and the
    # structure a resumed run's checkpoint restores into
    state, start_iteration, restored, rows = _restore(s, _start_curriculum(s, s.trainer.init(k_init)))
    previous_wall = float(rows[-1]["wall_s"]) if rows else 0.0
    _start_selection(s, state)
    t_start = time.perf_counter()
    if not restored:
        state, rows = _warm_start(s, state, k_bc, t_start, rows)
    run = _train_loop(s, state, rows, start_iteration, previous_wall, t_start)
    train_wall = time.perf_counter() - t_compile
    arrays = jax.device_get(s.trainer.run_policy(run.state)) if s.many else s.trainer.run_policy(run.state)
    if not s.lead:
        # the others end here; the first process writes and evaluates, then all leave together
        multihost_utils.sync_global_devices("mysim_jax run written")
        return {}
    write_rows(p.out / "metrics.csv", run.rows)
    best_iteration = int(run.state.best_iteration)
    plot_curves(run.rows, p.out / "curves.png", c.name, best_iteration if best_iteration >= 0 else None,
                (run.iteration, c.algo.num_iterations) if run.stopped_early else None)
    _save_policy(s, run, arrays)
    summary = _summary(s, run, train_wall)
    if evaluate:
        t_eval = time.perf_counter()
        if p.scene is None:
            base = s.env.scripted_actions if c.algo.residual else None
            policy = deterministic_policy(s.trainer.actor, arrays, c.algo.normalize_obs, base)
            summary["evaluation"] = evaluate_builtin(s.env, s.env_params, policy, c.run.eval_episodes,
                                                     c.run.eval_seed)
        else:
            _evaluate_capture(s, arrays, summary)
        summary["evaluation_wall_s"] = round(time.perf_counter() - t_eval, 1)
    (p.out / "summary.json").write_text(json.dumps(summary, indent=2))
    if s.many:
        multihost_utils.sync_global_devices("mysim_jax run written")
    return summary
