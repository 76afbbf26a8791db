"""A training run on disk: what ``scripts/train.py`` does, as library code (the folder's
files and the checked run: :mod:`mysim_jax.mappo.run_files`; what it writes at the end:
:mod:`mysim_jax.mappo.run_outputs`).

**What trains** is :mod:`mysim_jax.mappo.algorithm`'s, with the same keys: the start
(networks, environments, the warm start of ``algo.init``), then PPO iterations (the
curriculum inside them), run a chunk at a time (:meth:`Trainer.advance`, one compiled
``lax.scan`` of :func:`chunk_length` iterations; every checkpoint and selection falls on
a chunk's end). Between chunks the host writes the metrics, flies the selection episodes
(model selection keeps the best policy; it does not change what trains), checkpoints and
checks the optional time guard. With ``run.seeds`` N > 1, the N seeds ``run.seed``,
``run.seed + 1``, ... train side by side in one program (every step ``jax.vmap``-ped over
a leading seed axis of the state), each as it would alone.

A run folder ``OUT`` holds

* ``train.yaml`` — the resolved training file, its ``env.scene`` pointing at
  ``scene.yaml`` (the resolved training scene, overrides and level applied) and, when the
  final evaluation runs on another fidelity level (``env.eval_level``, default ``full``) or
  with other overrides (``env.eval_set``), its ``env.eval_scene`` at ``scene_eval.yaml``:
  the folder is self-contained and ``--resume OUT`` needs nothing else;
* ``metrics.csv`` — one row per iteration (env steps, wall time, return, success rate,
  losses, ...), and the same scalars as TensorBoard events under ``tb/``;
* ``curves.png`` — learning curves;
* ``checkpoints/<iteration>/`` — orbax checkpoints of the whole trainer state (every
  seed's), every ``run.checkpoint_every`` iterations and at the end;
* ``policy/`` — the final deterministic policy (``scripts/evaluate.py --policy OUT/policy``);
* ``eval/`` — the final evaluation, the report of ``scripts/evaluate.py``
  (:func:`mysim_jax.tasks.report.write_evaluation`);
* ``summary.json`` — iterations, env steps, training wall time and throughput, the
  evaluation's success rate.

With several seeds, each seed's ``metrics.csv``, ``tb/``, ``curves.png``, ``policy/``,
``eval/``, ``bc.json`` and ``summary.json`` are in ``OUT/seed_<seed>/``, and ``OUT``
adds ``seeds.json`` and ``seeds.md`` (each seed's evaluation and the mean, spread and
range over seeds) and ``curves.png`` (every seed's curves).

**Resuming** continues from the last complete checkpoint: rows of ``metrics.csv`` after it
are dropped and recomputed, so a run killed at any moment (SIGKILL included) loses at most
``checkpoint_every`` iterations, and the resumed run's states equal those of an uninterrupted
run bit for bit (same machine and JAX build).
"""

from __future__ import annotations

import json
import math
import shutil
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
from mysim_jax.core.config_base import ConfigError
from mysim_jax.core.precision import use_precision
from mysim_jax.mappo import bc
from mysim_jax.mappo.algorithm import curriculum_of, run_keys, warm_start
from mysim_jax.mappo.checkpoint import Checkpoints, load_policy
from mysim_jax.mappo.config import TrainConfig, check_memory_needs, init_policy_path
from mysim_jax.mappo.policies import PolicyError, check_trained_on, widen_policy
from mysim_jax.mappo.run_files import (CSV_FIELDS, Prepared, describe_run, load_run_config, prepare, read_rows,
                                       write_rows, write_run_files)
from mysim_jax.mappo.run_outputs import (EVAL_RESUME, FinalEvaluation, SeedRun, Trained, summary, write_seed,
                                          write_seeds_table)
from mysim_jax.mappo.toy import ReachEnv
from mysim_jax.mappo.networks import deterministic_policy
from mysim_jax.mappo.shac import make_trainer
from mysim_jax.mappo.trainer import Trainer
from mysim_jax.tasks.capture import make_env
from mysim_jax.tasks.evaluate import Evaluator
from mysim_jax.tasks.runner import first_done, run_batch, shared_key
from mysim_jax.tasks.sweep import wilson_interval

# a run from a training file: prepare (or load_run_config) -> train_run; the first three
# live with the run folder's files (mysim_jax.mappo.run_files)
__all__ = ["Prepared", "prepare", "load_run_config", "describe_run", "make_environment", "make_eval_environment",
           "make_select_environment",
           "training_mesh", "train_run", "evaluate_builtin"]


def _silent(*args, **kwargs) -> None:
    """The log of a process that is not the first (several processes print nothing)."""


def training_mesh(config, source: str):
    """The devices a run splits its environments over (``run.devices``): None for one
    device (always with several seeds), else a :func:`mysim_jax.core.parallel.env_mesh`. Raises ConfigError when more devices
    are asked for than JAX sees, or when ``algo.num_envs`` does not split into them."""
    available = jax.devices()
    n = len(available) if config.run.devices is None else config.run.devices
    if config.run.seeds > 1:           # several seeds: one program on one device
        return None
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

    use_precision(p.scene.sim.precision)

    return make_env(p.scene, discount=p.config.algo.gamma)


def make_eval_environment(p: Prepared, env, env_params):
    """``(env, env_params)`` of the final evaluation: ``env, env_params`` themselves when it
    runs on the training scene. Raises ConfigError when the evaluation scene's
    observations or actions differ in shape from training's (levels change physical
    values, not what the policy sees)."""
    if not p.evaluates_elsewhere:
        return env, env_params

    field = "env.eval_set" if p.config.env.eval_set is not None else "env.eval_level"
    return _like_training(p, p.eval_scene, env, f"{field}: the evaluation scene")


def make_select_environment(p: Prepared, env, env_params):
    """``(env, env_params)`` model selection flies: ``env, env_params`` themselves unless
    ``run.selection`` names another scene (``set`` or ``scene``). Raises ConfigError when
    its observations or actions differ in shape from training's."""
    if p.select_scene is None:
        return env, env_params
    return _like_training(p, p.select_scene, env, "run.selection: the selection scene")


def _like_training(p: Prepared, scene, env, what: str):
    """``make_env(scene)``, refused unless its observations and actions have training's shapes."""
    other, params = make_env(scene, discount=p.config.algo.gamma)
    if (other.obs_size, tuple(other.action_shape)) != (env.obs_size, tuple(env.action_shape)):
        raise ConfigError(f"{p.source}: {what}'s observations/actions "
                          f"({other.obs_size}, {tuple(other.action_shape)}) differ from training's "
                          f"({env.obs_size}, {tuple(env.action_shape)})")
    return other, params


def evaluate_builtin(env, env_params, policy, episodes: int, seed: int) -> dict:
    """Success rate of ``policy`` on the builtin environment: ``episodes`` episodes, each
    the first of an environment of :func:`mysim_jax.tasks.runner.run_batch` (keys split
    from ``seed``, each step's key given to both the policy and the environment), judged
    at its first ``done``."""
    def row(step, aux):
        return {"success": step.info["success"], "done": step.info["done"]}

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    _, rows = run_batch(env, env_params, policy, keys, env.max_steps, step_keys=shared_key, record=row,
                        vmap=jax.vmap)
    outcome, ended = jax.vmap(first_done)(rows)
    success = jax.device_get(outcome["success"] & ended)

    k = int(success.sum())
    lo, hi = wilson_interval(k, episodes)
    return {"episodes": episodes, "success": {"count": k, "rate": k / episodes, "interval95": [lo, hi]}}


def _selection_row(stats) -> dict:
    return {"select_success": float(stats.success.mean()), "select_return": float(stats.returns.mean())}


def _one(state, i: int | None):
    """Seed ``i``'s state of a state with a seed axis (``i`` None: ``state`` has none)."""
    return state if i is None else jax.tree.map(lambda x: x[i], state)


def _put(state, i: int | None, one):
    """``state`` with seed ``i``'s state replaced by ``one``."""
    return one if i is None else jax.tree.map(lambda x, y: x.at[i].set(y), state, one)


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
    seeds: list                # a SeedRun per seed (run.seeds)
    eval_env: object = None    # the evaluation scene's environment (capture scenes, when evaluating)
    eval_params: object = None
    select_env: object = None  # the scene model selection flies (run.selection; the training scene's by default)
    select_params: object = None
    evaluator: Evaluator | None = None    # model selection on fixed episodes
    select_key: object = None

    @property
    def c(self) -> TrainConfig:
        return self.p.config

    @property
    def stacked(self) -> bool:
        """The state holds several seeds along a leading axis (run.seeds > 1)."""
        return len(self.seeds) > 1

    @property
    def indices(self) -> list:
        """Each seed's index into the state's seed axis (None: the state has none)."""
        return list(range(len(self.seeds))) if self.stacked else [None]

    @property
    def selection(self):
        return self.c.run.selection if self.p.scene is not None else None

    def select(self, state, i=None):
        """Fly the selection episodes with seed ``i``'s current policy; keep it if it is the
        best: ``(state, stats)``."""
        one = _one(state, i)
        arrays = self.trainer.policy_arrays(one)
        if self.many:                 # on this process's device: the networks as host arrays
            arrays = jax.device_get(arrays)
        stats = self.evaluator(self.select_key, self.selection.episodes, arrays)
        one = self.trainer.keep_if_best(one, int(stats.success.sum()), float(stats.returns.mean()))
        return _put(state, i, one), stats

    def say(self, bar, msg: str) -> None:
        if bar is not None:
            bar.write(msg)
        else:
            self.log(msg)


def _seed_runs(p: Prepared) -> list[SeedRun]:
    """The run's seeds and their folders: the run folder itself for one seed,
    ``OUT/seed_<seed>/`` for several."""
    run = p.config.run
    if run.seeds == 1:
        return [SeedRun(run.seed, p.out)]
    return [SeedRun(run.seed + i, p.out / f"seed_{run.seed + i}") for i in range(run.seeds)]


def _open_session(p: Prepared, progress: bool, evaluate: bool, log) -> _Session:
    """Everything that can refuse the run, checked before the run folder is written and
    before anything compiles: the environments, a starting policy, the devices, the memory."""
    c = p.config
    lead = jax.process_index() == 0
    many = jax.process_count() > 1
    if many and c.run.seeds > 1:
        raise ConfigError(f"{p.source}: run.seeds {c.run.seeds} with several processes: several seeds train in "
                          "one program on one device")
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
    select_env, select_params = make_select_environment(p, env, env_params)
    if c.algo.init == "policy" and not p.resume:
        # the starting policy must fit this environment (shapes and meaning)
        folder = init_policy_path(c, p.source)
        try:
            where = f"{p.source}: algo.init_policy {folder}"
            check_trained_on(widen_policy(load_policy(folder)[0], None, env, env_params, where)[0], env, env_params,
                             where)
        except PolicyError as err:
            raise ConfigError(str(err)) from None
    curriculum = curriculum_of(c.env.curriculum) if p.scene is not None else None
    trainer = make_trainer(c.algo, env, env_params, mesh=training_mesh(c, p.source), curriculum=curriculum)
    needs = trainer.memory_needs()
    if c.run.seeds > 1:
        needs = {k: (b * c.run.seeds, f"{fields} x run.seeds") for k, (b, fields) in needs.items()}
    check_memory_needs(needs, p.source)
    if not p.resume and lead:
        write_run_files(p)
    seeds = _seed_runs(p)
    if lead:
        for one in seeds:
            one.out.mkdir(parents=True, exist_ok=True)
    return _Session(p=p, log=log, progress=progress, lead=lead, many=many, env=env, env_params=env_params,
                    trainer=trainer, ckpt=Checkpoints(p.out / "checkpoints", keep=c.run.keep_checkpoints),
                    seeds=seeds, eval_env=eval_env, eval_params=eval_params, select_env=select_env,
                    select_params=select_params)


def _keys(s: _Session):
    """``(k_init, k_warm)`` of the run (a leading seed axis with several seeds): seed
    ``run.seed + i``'s are those of a run of that one seed."""
    if not s.stacked:
        return run_keys(jax.random.PRNGKey(s.c.run.seed))
    seeds = jnp.asarray([one.seed for one in s.seeds], jnp.uint32)
    return jax.vmap(lambda seed: run_keys(jax.random.PRNGKey(seed)))(seeds)


def _fresh(s: _Session, k_init):
    """A fresh state (networks, environments, the curriculum's first stage): the start of a
    new run, and the structure a resumed run's checkpoint restores into."""
    if not s.stacked:
        return s.trainer.init(k_init)
    return jax.jit(jax.vmap(s.trainer._init_state))(k_init)


def _restore(s: _Session, state) -> tuple[object, int, bool]:
    """The state to start from (the newest intact checkpoint when resuming), its iteration,
    and whether it was restored; each seed's metrics rows up to it."""
    start_iteration, restored = 0, False
    if s.p.resume:
        try:
            last, state = s.ckpt.restore_newest(state, log=s.log)
        except Exception:
            s.ckpt.close()               # orbax's threads end before the error reaches the script
            raise
        if last is not None:
            start_iteration = int(np.max(jax.device_get(state.iteration)))
            restored = True
    for one in s.seeds:
        one.rows = read_rows(one.out / "metrics.csv", start_iteration)
    if restored:
        s.log(f"resuming {s.p.out} at iteration {start_iteration} of {s.c.algo.num_iterations}")
    elif s.p.resume:
        s.log(f"{s.p.out}: no checkpoint yet, starting at iteration 0 of {s.c.algo.num_iterations}")
    return state, start_iteration, restored


def _start_selection(s: _Session, state) -> None:
    """Say where the curriculum stands (from the state: a resumed run's checkpoint holds it)
    and build the selection evaluator."""
    c, cur = s.c, s.trainer.curriculum
    if cur is not None:
        stages = sorted({cur.stage(_one(state.curriculum, i)) for i in s.indices})
        s.log(f"curriculum: stage {', '.join(str(k + 1) for k in stages)} of {len(cur.config.stages)} (the "
              "target's speed, jink and flee ranges x "
              f"{', '.join(f'{cur.config.stages[k]:g}' for k in stages)})")
    # model selection on fixed episodes (capture environments; the builtin task has its own evaluation)
    if s.selection is not None:
        s.evaluator = Evaluator(s.select_env, s.select_params, s.trainer.policy_fn(),
                                batch=min(s.selection.episodes, c.run.eval_batch), env_batching=s.trainer.env_batching)
        s.select_key = jax.random.PRNGKey(s.selection.seed)


def _warm_start(s: _Session, state, k_warm, t_start: float):
    """A new run: clone the scripted team (``algo.init: bc``) or start from a saved policy
    (``algo.init: policy``) (:func:`mysim_jax.mappo.algorithm.warm_start`, jitted; vmapped
    over seeds), fly the selection episodes once before training, and checkpoint iteration
    0. Returns the state."""
    c = s.c
    init_policy = None
    if c.algo.init == "policy":
        folder = init_policy_path(c, s.p.source)
        meta, arrays = widen_policy(*load_policy(folder), s.env, s.env_params, f"algo.init_policy {folder}")
        init_policy = (meta, arrays)
        if "widened_from_obs_size" in meta:
            s.log(f"the starting policy read {meta['widened_from_obs_size']} observation features; this environment "
                  f"appends {meta['obs_size'] - meta['widened_from_obs_size']} (zero weights to start)")
        s.log(f"starting from the policy {folder} (iteration {meta.get('selected_iteration')} of "
              f"{meta.get('train')}): exploration std {c.algo.bc.std:g}, critic warm-up "
              f"{c.algo.bc.critic_warmup} iterations")
    if c.algo.init == "bc":
        s.log(f"behaviour cloning the scripted team: {c.algo.bc.num_envs} environments x {c.algo.bc.steps} steps"
              + (f", {len(s.seeds)} seeds in one program" if s.stacked else ""))
    if c.algo.init != "none":
        t0 = time.perf_counter()

        def warm(ts, key):
            return warm_start(s.trainer, ts, key, init_policy)

        state, stats = jax.jit(jax.vmap(warm) if s.stacked else warm)(state, k_warm)
        state = jax.block_until_ready(s.trainer.place(state) if not s.stacked else state)
        wall = time.perf_counter() - t0
        if c.algo.init == "bc":
            for i, one in zip(s.indices, s.seeds):
                report = {**bc.report(s.trainer, _one(stats, i)), "wall_s": round(wall, 2)}
                if s.lead:
                    (one.out / "bc.json").write_text(json.dumps(report, indent=2))
                who = f"seed {one.seed}: " if s.stacked else ""
                s.log(f"{who}cloned in {wall:.0f} s: {report['pairs']:,} pairs, held-out RMSE "
                      f"{report['rmse_holdout']:.3f}, R2 {', '.join(f'{v:.3f}' for v in report['r2_holdout'])}")
    if s.evaluator is not None:
        for i, one in zip(s.indices, s.seeds):
            state, stats = s.select(state, i)
            one.rows = [{"iteration": 0, "env_steps": 0, "wall_s": round(time.perf_counter() - t_start, 3),
                         **_selection_row(stats)}]
            who = f" (seed {one.seed})" if s.stacked else ""
            s.log(f"selection episodes before training{who}: success {stats.success.mean():.1%}")
    if s.trainer.uses_anchor or s.evaluator is not None:
        if s.lead:
            for one in s.seeds:
                write_rows(one.out / "metrics.csv", one.rows)
        s.ckpt.save(0, state if s.stacked else s.trainer.place(state))
    return state


def chunk_length(c: TrainConfig, selection) -> int:
    """Iterations the run loop advances at a time (one compiled scan): every checkpoint
    and selection falls on a chunk's end (the greatest common divisor of their intervals),
    at most the run's length."""
    every = c.run.checkpoint_every if selection is None else math.gcd(c.run.checkpoint_every, selection.every)
    return max(1, min(every, c.algo.num_iterations))


def _chunk_rows(s: _Session, first: int, n: int, m: dict, wall0: float, dt: float, bar) -> None:
    """The rows of iterations ``first + 1 .. first + n`` (metrics ``m`` stacked ``(n,)``,
    per seed ``(seeds, n)``) appended to each seed's rows; a curriculum stage change said."""
    cur = s.trainer.curriculum
    for i, one in zip(s.indices, s.seeds):
        for j in range(n):
            it = first + j + 1
            mj = {k: float(v[j] if i is None else v[i, j]) for k, v in m.items()}
            row = {"iteration": it, "env_steps": it * s.c.algo.batch_size, "iteration_s": round(dt / n, 4),
                   "lr": s.trainer.learning_rate(it - 1), **{k: mj[k] for k in CSV_FIELDS if k in mj},
                   "wall_s": round(wall0 + dt * (j + 1) / n, 3)}
            if cur is not None:
                row["curriculum_stage"] = int(mj["curriculum_stage"])
                previous = one.rows[-1].get("curriculum_stage") if one.rows else None
                if previous not in (None, "") and int(float(previous)) != row["curriculum_stage"]:
                    who = f"seed {one.seed}: " if s.stacked else ""
                    s.say(bar, f"{who}curriculum: stage {row['curriculum_stage'] + 1} of {len(cur.config.stages)} "
                               f"from iteration {it} (ranges x {row['curriculum_fraction']:g})")
            one.rows.append(row)


def _show_progress(s: _Session, bar, n: int, dt: float) -> None:
    if bar is None:
        return
    bar.update(n)
    last = [one.rows[-1] for one in s.seeds]
    mean = lambda k: float(np.mean([float(r[k]) for r in last]))      # noqa: E731
    sel = ""
    if all("select_success" in r for r in last):
        sel = f", selection {mean('select_success'):.0%}"
    if "curriculum_stage" in last[0]:
        sel += f", stage {int(last[0]['curriculum_stage']) + 1}"
    seeds = f" (mean of {len(last)} seeds)" if s.stacked else ""
    bar.set_postfix_str(f"return {mean('mean_return'):.2f}, success {mean('success_rate'):.0%}{sel}{seeds}, "
                        f"{len(last) * s.c.algo.batch_size * n / dt:,.0f} team steps/s")


def _train_loop(s: _Session, state, start_iteration: int, previous_wall: float, t_start: float) -> Trained:
    """PPO iterations until the planned number or the time limit, a chunk of iterations
    (:func:`chunk_length`, one compiled scan) at a time; rows, TensorBoard, selection and
    checkpoints between chunks."""
    c = s.c
    writers = ([SummaryWriter(str(one.out / "tb"), purge_step=start_iteration + 1) for one in s.seeds]
               if s.lead else [])
    bar = None
    if s.progress:
        bar = tqdm(total=c.algo.num_iterations, initial=start_iteration, desc=f"training {c.name}", unit="it")
    limit_s = None if c.run.time_limit_min is None else 60.0 * c.run.time_limit_min
    length = chunk_length(c, s.selection)
    iteration_times, stopped_early, iteration, chunks = [], False, start_iteration, 0
    while iteration < c.algo.num_iterations:
        # to the next multiple of the chunk length (a run stopped elsewhere by the time guard
        # and resumed gets back in step), and not past the run's end
        n = min(length - iteration % length, c.algo.num_iterations - iteration)
        wall0 = previous_wall + time.perf_counter() - t_start
        t0 = time.perf_counter()
        state, m = s.trainer.advance(state, n, length, seeds=s.stacked)
        m = {k: np.asarray(v)[..., :n] for k, v in jax.device_get(m).items()}
        dt = time.perf_counter() - t0
        chunks += 1
        if chunks > 1:                  # a process's first chunk compiles
            iteration_times.append(dt / n)
        _chunk_rows(s, iteration, n, m, wall0, dt, bar)
        iteration += n
        last_iteration = iteration == c.algo.num_iterations
        over_time = limit_s is not None and previous_wall + time.perf_counter() - t_start > limit_s
        if s.many and limit_s is not None:      # the first process's clock decides for all
            over_time = bool(multihost_utils.broadcast_one_to_all(np.bool_(over_time)))
        if s.evaluator is not None and (iteration % s.selection.every == 0 or last_iteration or over_time):
            for i, one in zip(s.indices, s.seeds):
                state, stats = s.select(state, i)
                one.rows[-1].update(_selection_row(stats))
                one.rows[-1]["wall_s"] = round(previous_wall + time.perf_counter() - t_start, 3)
        for one, writer in zip(s.seeds, writers):
            for row in one.rows[-n:]:
                for k, v in row.items():
                    if k != "iteration":
                        writer.add_scalar(f"train/{k}", float(v), int(row["iteration"]))
        _show_progress(s, bar, n, dt)
        if iteration % c.run.checkpoint_every == 0 or last_iteration or over_time:
            if s.lead:
                for one, writer in zip(s.seeds, writers):
                    write_rows(one.out / "metrics.csv", one.rows)
                    writer.flush()
            s.ckpt.save(iteration, state if s.stacked else s.trainer.place(state))
        if over_time and not last_iteration:
            stopped_early = True
            s.log(f"time limit of {c.run.time_limit_min:g} min reached after iteration {iteration}")
            break
    if bar is not None:
        bar.close()
    for writer in writers:
        writer.close()
    s.ckpt.close()
    for i, one in zip(s.indices, s.seeds):
        one.state = _one(state, i)
    return Trained(s.seeds, iteration, iteration_times, stopped_early)


def train_run(p: Prepared, progress: bool = True, evaluate: bool = True, log=print) -> dict:
    """Train (or resume) the run ``p`` to its end, evaluate, write everything. Returns
    ``summary.json``'s dict (with several seeds, the first seed's, with the table of all
    under ``"seeds"``). With several processes (jax.distributed) every one computes; the
    first writes the run folder, the logs and the evaluation, and decides when to stop."""
    s = _open_session(p, progress, evaluate, log)
    c = s.c
    k_init, k_warm = _keys(s)
    t_compile = time.perf_counter()
    state, start_iteration, restored = _restore(s, _fresh(s, k_init))
    rows0 = s.seeds[0].rows
    previous_wall = float(rows0[-1]["wall_s"]) if rows0 else 0.0
    _start_selection(s, state)
    t_start = time.perf_counter()
    if not restored:
        state = _warm_start(s, state, k_warm, t_start)
    run = _train_loop(s, state, start_iteration, previous_wall, t_start)
    train_wall = time.perf_counter() - t_compile
    policies = [jax.device_get(s.trainer.run_policy(one.state)) if s.many or s.stacked
                else s.trainer.run_policy(one.state) for one in run.seeds]
    if not s.lead:
        # the others end here; the first process writes and evaluates, then all leave together
        multihost_utils.sync_global_devices("mysim_jax run written")
        return {}
    final = FinalEvaluation(s) if evaluate and p.scene is not None else None
    summaries = []
    for one, arrays in zip(run.seeds, policies):
        write_seed(s, one, run, arrays)
        sm = summary(s, one, run, train_wall)
        if evaluate:
            t_eval = time.perf_counter()
            if p.scene is None:
                base = s.env.scripted_actions if c.algo.residual else None
                policy = deterministic_policy(s.trainer.actor, arrays, c.algo.normalize_obs, base)
                sm["evaluation"] = evaluate_builtin(s.env, s.env_params, policy, c.run.eval_episodes,
                                                    c.run.eval_seed)
            else:
                final(one, arrays, sm)
            sm["evaluation_wall_s"] = round(time.perf_counter() - t_eval, 1)
        (one.out / "summary.json").write_text(json.dumps(sm, indent=2))
        summaries.append(sm)
    shutil.rmtree(p.out / EVAL_RESUME, ignore_errors=True)     # the evaluations' progress, now written
    result = summaries[0]
    if s.stacked:
        table = write_seeds_table(p.out, c.name, summaries, run.seeds)
        s.log(f"{len(run.seeds)} seeds: {p.out / 'seeds.md'}")
        result = {**result, "seeds": table}
    if s.many:
        multihost_utils.sync_global_devices("mysim_jax run written")
    return result
