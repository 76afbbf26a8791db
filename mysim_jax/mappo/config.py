"""Training configuration files: ``env:``, ``algo:`` and ``run:`` sections.

A training file names the environment and the algorithm's settings::

    name: train_capture_falling
    env:
      scene: capture_env_falling.yaml   # a capture scene file, relative to this file
      set: ["env.rewards.success=10"]   # overrides of the scene file (as simulate.py --set)
    algo:                               # MAPPO (mysim_jax/mappo/trainer.py); all have defaults
      num_envs: 256
      num_steps: 16
      total_env_steps: 1000000
      ...
    run:
      seed: 0
      checkpoint_every: 5               # iterations
      eval_episodes: 1000

A file may name ``profiles``: each a list of overrides (``key=value``, as ``--set``) that
``scripts/train.py --profile NAME`` applies before the command line's ``--set``, so one
file holds recipes that differ in several values at once (the default capture file's
``scratch`` learns without cloning). Every profile is checked when the file is loaded.

Instead of ``scene``, ``env.builtin: reach`` selects a small built-in task
(:mod:`mysim_jax.mappo.toy`) that trains in seconds, for tests and smoke runs.

Sizes derived from these (the batch, the minibatch, the number of iterations) are
properties, computed rather than stored. Everything is checked here, before JAX is
imported: unknown keys, a minibatch count that does not divide the batch, a non-positive
learning rate, a missing scene file, each as a :class:`~mysim_jax.core.config_base.ConfigError`
naming the field.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationError, model_validator
import yaml

from mysim_jax.config.capture_checks import env_problems
from mysim_jax.config.env import drawn_value_problems
from mysim_jax.config.overrides import apply_overrides, override_list
from mysim_jax.config.scene import load_config
from mysim_jax.core.config_base import (ConfigError, Name, PosFloat, StrictModel, available_memory_bytes,
                                        format_validation_error, read_yaml_file)

PosInt = Annotated[int, Field(gt=0)]
NonNegInt = Annotated[int, Field(ge=0)]
Fraction = Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)]
BUILTIN_ENVS = ("reach",)


class CurriculumConfig(StrictModel):
    """A curriculum over the evading target's difficulty (``env.curriculum``).

    Stage ``i`` multiplies the scene's ranges of the target's top speed, jink and flee
    accelerations (``env.randomize.max_speed``, ``jink_acceleration``,
    ``flee_acceleration``, or the nominal ``target.propulsion`` values when a range is not
    given) by ``stages[i]``: a fraction in (0, 1], increasing, the last one 1 (the full
    range). New training episodes are drawn from the current stage's ranges; model
    selection and the final evaluation always use the full ranges. The curriculum moves to
    the next stage once the training success rate, averaged over the last ``window``
    iterations in the stage, reaches ``advance_success``, or after ``max_iterations``
    iterations in the stage, whichever comes first (either may be left out, not both).
    The stage and its fraction are columns of ``metrics.csv`` and drawn in ``curves.png``.
    """

    stages: Annotated[list[Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)]], Field(min_length=1)]
    advance_success: Fraction | None = 0.8
    window: PosInt = 5
    max_iterations: PosInt | None = None

    @model_validator(mode="after")
    def _reaches_the_full_range(self):
        st = self.stages
        if any(b <= a for a, b in zip(st, st[1:])):
            raise ValueError(f"stages {st} must increase from stage to stage")
        if st[-1] != 1.0:
            raise ValueError(f"stages {st} never reach the full range: the last stage must be 1.0")
        if self.advance_success is None and self.max_iterations is None:
            raise ValueError("give advance_success, max_iterations or both: with neither the curriculum "
                             "never leaves its first stage")
        return self


class EnvSection(StrictModel):
    """Which environment to train on: a capture scene file (with overrides), or a built-in
    toy task."""

    scene: str | None = None
    set: list[str] = []
    builtin: Literal["reach"] | None = None
    # the scene's fidelity level training runs on (``levels:`` of the scene file; the
    # same as ``level=NAME`` at the end of ``set``). None: what ``set`` picks, else the
    # file's own values (the level ``full``)
    level: Name | None = None
    # the scene's fidelity level the final evaluation (and its scripted baseline) runs on.
    # None: evaluate on the training scene as it is
    eval_level: Name | None = "full"
    # a resolved scene file (relative to the training file) to evaluate on instead; run
    # folders use it (their scene.yaml is the training scene, resolved)
    eval_scene: str | None = None
    # the evaluation scene's overrides of ``scene`` in place of ``set`` (at ``eval_level``):
    # a run that trains on shifted conditions (estimation errors, wider ranges, faults) and
    # is judged on the nominal ones. None: ``set``
    eval_set: list[str] | None = None
    # the evading target's difficulty from gentle to the full range (CurriculumConfig)
    curriculum: CurriculumConfig | None = None

    @model_validator(mode="after")
    def _one_source(self):
        if (self.scene is None) == (self.builtin is None):
            raise ValueError("give exactly one of scene (a capture scene file) and builtin "
                             f"({', '.join(BUILTIN_ENVS)})")
        if self.builtin is not None and self.set:
            raise ValueError("set (scene overrides) applies to a scene file, not to a builtin environment")
        if self.builtin is not None and self.level is not None:
            raise ValueError("level (a fidelity level) applies to a scene file, not to a builtin environment")
        if self.builtin is not None and self.curriculum is not None:
            raise ValueError("curriculum scales a capture scene's evading target, not a builtin environment")
        if self.builtin is not None and self.eval_scene is not None:
            raise ValueError("eval_scene applies to a scene file, not to a builtin environment")
        if self.eval_scene is not None and self.eval_level is not None:
            raise ValueError("give at most one of eval_level (a level of env.scene) and eval_scene (a scene file); "
                             "set eval_level: null with eval_scene")
        if self.eval_set is not None:
            if self.builtin is not None:
                raise ValueError("eval_set (the evaluation scene's overrides) applies to a scene file, not to a "
                                 "builtin environment")
            if self.eval_scene is not None:
                raise ValueError("give at most one of eval_set (overrides of env.scene to evaluate on) and "
                                 "eval_scene (a resolved scene file)")
            if self.eval_level is None:
                raise ValueError("eval_set needs eval_level, the level of env.scene the evaluation runs on "
                                 "(e.g. eval_level: full)")
        return self


class BCConfig(StrictModel):
    """Behaviour cloning of the scripted team before PPO (``algo.init: bc``;
    :mod:`mysim_jax.mappo.bc`).

    The dataset is collected with the vmapped environment: ``num_envs`` environments run
    ``steps`` policy steps with the scripted team's action plus Gaussian noise of ``noise``
    (normalised action units; the states a slightly perturbed team visits, labelled with the
    scripted team's action there: DART, Laskey et al. 2017). The actor's mean is fitted to
    the labels by ``epochs`` passes of Adam (``lr``, minibatches of ``minibatch_size``),
    ``holdout`` of the environments kept apart to measure the fit. PPO then starts from the
    clone with exploration ``std``; its first ``critic_warmup`` iterations train only the
    critic (the policy is held), and an anchor ``anchor_coef · |μ(o) − μ_clone(o)|²`` (the
    squared distance of the policy's mean from the clone's, per action dimension) pulls the
    policy back towards the clone, its weight decaying linearly to zero over
    ``anchor_iterations`` PPO iterations. ``dagger_rounds`` > 0 then lets the clone fly as
    many more times (``num_envs`` x ``steps`` each, with the same noise), labels the states
    it visits with the scripted team's actions and refits on all the data (DAgger).
    ``freeze_obs_norm`` keeps the actor's observation normalisation at the clone's (the
    statistics of the cloning data, part of the function that was fitted) instead of
    updating it with every rollout: a rollout's states are not the cloning data's (the
    environments start in step, so the first iterations see only the episodes' first
    steps), and the updated statistics change what the unchanged actor does. Like the rest
    of ``bc:`` it applies with ``algo.init: bc`` only (a file that sets it can still be
    run from scratch with ``--set algo.init=none``), except the settings of the start
    itself (``std``, ``critic_warmup``, ``anchor_coef``, ``anchor_iterations``,
    ``freeze_obs_norm``), which ``algo.init: policy`` uses too, the saved policy in the
    clone's place."""

    num_envs: PosInt = 128
    steps: PosInt = 48
    noise: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.2
    epochs: PosInt = 60
    minibatch_size: PosInt = 512
    lr: PosFloat = 1e-3
    holdout: Annotated[float, Field(gt=0, lt=1)] = 0.1
    std: PosFloat = 0.2
    critic_warmup: NonNegInt = 2
    anchor_coef: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 1.0
    anchor_iterations: PosInt = 100
    dagger_rounds: NonNegInt = 0
    freeze_obs_norm: bool = False


class ShacConfig(StrictModel):
    """SHAC's own settings (``algo.name: shac``, :mod:`mysim_jax.mappo.shac`); the rest of
    ``algo:`` (environments, the rollout's ``num_steps``, ``lr`` of the actor, ``gamma``,
    ``gae_lambda`` of the critic's targets, the critic's ``update_epochs`` x
    ``num_minibatches``, ``max_grad_norm``, networks, warm starts) means what it means for PPO."""

    critic_lr: PosFloat | None = None      # the critic's Adam step (None: algo.lr)
    # policy steps the actor's gradient crosses: the rollout's num_steps are cut into windows
    # of this many, each bootstrapped by the critic at its end (None: one window, num_steps)
    horizon: PosInt | None = None
    # the critic's value at a window's end enters the actor's loss with its gradient through
    # the state (SHAC); false: as a constant, so the actor follows the window's rewards alone
    value_gradient: bool = True


class AlgoConfig(StrictModel):
    """The trainer's settings (:mod:`mysim_jax.mappo.trainer`; ``name: shac``:
    :mod:`mysim_jax.mappo.shac`). ``num_envs`` environments step
    side by side for ``num_steps`` policy steps per iteration; the ``batch_size`` team
    transitions of an iteration are split into ``num_minibatches`` minibatches and used
    for ``update_epochs`` epochs."""

    # ppo: MAPPO's clipped update (mysim_jax.mappo.trainer); shac: short-horizon actor-critic,
    # the actor's gradient taken through windows of shac.horizon steps of the simulator
    # (mysim_jax.mappo.shac)
    name: Literal["ppo", "shac"] = "ppo"
    num_envs: PosInt = 256
    num_steps: PosInt = 16                 # policy steps per environment per iteration
    total_env_steps: PosInt = 1_000_000    # team (policy) steps over all environments
    update_epochs: PosInt = 4
    num_minibatches: PosInt = 4
    lr: PosFloat = 3e-4
    lr_schedule: Literal["constant", "linear"] = "linear"   # linear: decays to 0 at the last update
    gamma: Fraction = 0.99
    gae_lambda: Annotated[float, Field(ge=0, le=1)] = 0.95
    # an episode cut by the environment's time limit: true bootstraps it with the value of
    # its last state (the limit is an artefact of training: the task goes on); false ends it
    # there with nothing more (the limit is part of the task, as when a time-out counts as
    # a miss and the observation carries the time left)
    bootstrap_time_limit: bool = True
    clip_eps: PosFloat = 0.2               # policy ratio clipping
    value_clip_eps: PosFloat = 0.2         # value clipping (in normalised value units)
    vf_coef: PosFloat = 0.5
    ent_coef: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.0
    max_grad_norm: PosFloat = 0.5
    hidden: list[PosInt] = [128, 128]      # hidden layer widths of both networks
    activation: Literal["tanh", "relu"] = "tanh"
    # the policy's initial action standard deviation, in normalised action units (an action
    # of 1 is the whole half-range: max_speed in velocity mode); PureJaxRL and MAPPO start at 1
    init_std: PosFloat = 1.0
    # stop an iteration's epochs once a minibatch's approximate KL divergence from the
    # rollout's policy exceeds 1.5 x target_kl (None: never)
    target_kl: PosFloat | None = None
    normalize_obs: bool = True             # running mean / std of observations and states
    value_norm: bool = True                # running mean / std of the value targets
    residual: bool = False                 # act = the scripted team's action + the policy's
    # how the rollout batches the environment step: batch_last (mysim_jax.core.batching.vmap,
    # the batch axis last in memory, in cache-sized blocks: for CPUs) or vmap (jax.vmap, the
    # batch axis first); auto: batch_last on a CPU, vmap on a GPU or TPU
    # (batching.resolve_batching). The two differ by float round-off only (which PPO's
    # updates amplify over a run, as they do any round-off)
    batching: Literal["auto", "batch_last", "vmap"] = "auto"
    # bc: clone the scripted team first (bc:); policy: start from the saved policy
    # init_policy (fine-tuning it: the same networks, its observation normalisation, a
    # fresh critic warmed up for bc.critic_warmup iterations, the anchor on it)
    init: Literal["none", "bc", "policy"] = "none"
    init_policy: str | None = None         # a policy folder (policy.json), relative to the training file
    bc: BCConfig = BCConfig()
    shac: ShacConfig = ShacConfig()

    @model_validator(mode="after")
    def _sizes(self):
        if self.batch_size % self.num_minibatches:
            raise ValueError(f"num_minibatches = {self.num_minibatches} does not divide the batch "
                             f"num_envs x num_steps = {self.num_envs} x {self.num_steps} = {self.batch_size}")
        if self.total_env_steps < self.batch_size:
            raise ValueError(f"total_env_steps = {self.total_env_steps} is less than one iteration's batch "
                             f"(num_envs x num_steps = {self.batch_size})")
        if not self.hidden:
            raise ValueError("hidden: give at least one layer width")
        if (self.init == "policy") != (self.init_policy is not None):
            raise ValueError("init: policy starts from a saved policy: give its folder as init_policy"
                             if self.init == "policy" else
                             f"init_policy {self.init_policy!r} is used only with init: policy (init is {self.init!r})")
        if self.name == "ppo" and self.shac != ShacConfig():
            raise ValueError("shac: settings of algo.name: shac, and algo.name is ppo")
        if self.name == "shac":
            if self.shac.horizon is not None and self.num_steps % self.shac.horizon:
                raise ValueError(f"shac.horizon {self.shac.horizon} does not divide num_steps {self.num_steps}: the "
                                 "rollout is cut into whole gradient windows")
            unused = [f"{f} {getattr(self, f)}" for f, default in (("target_kl", None), ("clip_eps", 0.2),
                                                                     ("ent_coef", 0.0)) if getattr(self, f) != default]
            if unused:
                raise ValueError(f"algo.name: shac has no policy ratio to clip, KL limit to stop at or entropy "
                                 f"bonus; PPO's {', '.join(unused)} would be ignored: set target_kl to null and "
                                 "leave clip_eps and ent_coef at their defaults (0.2, 0)")
        return self

    @property
    def batch_size(self) -> int:
        """Team transitions per iteration."""
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    @property
    def num_iterations(self) -> int:
        """Whole iterations in ``total_env_steps`` (rounded down)."""
        return self.total_env_steps // self.batch_size

    @property
    def num_updates(self) -> int:
        """Gradient steps over the whole run (for the learning-rate schedule)."""
        return self.num_iterations * self.update_epochs * self.num_minibatches


class SelectionConfig(StrictModel):
    """Model selection during training: every ``every`` iterations (and before the first,
    and after the last) the deterministic policy is evaluated on ``episodes`` fixed episodes
    (drawn from ``seed``, the same ones every time, apart from the final evaluation's), and
    the best so far (most successes, then the highest mean return) is the run's policy.
    The episodes fly the training scene unless ``set`` or ``scene`` names another: a run
    that trains on shifted conditions (estimation errors, wider ranges, faults) and is
    judged on the nominal ones can select on those."""

    every: PosInt = 10
    episodes: PosInt = 128
    seed: NonNegInt = 777
    # the selection scene's overrides of env.scene in place of env.set, at env.level (the
    # training level), e.g. env.eval_set's: select on the conditions the run is judged on.
    # None: the training scene
    set: list[str] | None = None
    # a resolved scene file (relative to the training file) to select on instead; run
    # folders use it (scene_select.yaml)
    scene: str | None = None

    @model_validator(mode="after")
    def _one_scene(self):
        if self.set is not None and self.scene is not None:
            raise ValueError("give at most one of set (overrides of env.scene to select on) and scene (a resolved "
                             "scene file)")
        return self


class RunConfig(StrictModel):
    """Bookkeeping of a run."""

    seed: NonNegInt = 0
    # seeds trained side by side in one program (jax.vmap over the run): seed, seed + 1, ...
    # each in its own folder OUT/seed_<seed>/, with a table of them in OUT/seeds.md
    seeds: PosInt = 1
    checkpoint_every: PosInt = 10          # iterations between checkpoints
    keep_checkpoints: PosInt = 2
    # an optional guard: stop training after this many minutes (then evaluate). A run it
    # stops says so (summary.json stopped_by, curves.png); its result then depends on the
    # machine's speed, so reported runs stop on algo.total_env_steps instead
    time_limit_min: PosFloat | None = None
    eval_episodes: PosInt = 1000
    eval_batch: PosInt = 250
    eval_seed: NonNegInt = 12345           # evaluation episodes are drawn apart from training's
    # compare with the scripted team on the same evaluation episodes (capture scenes only)
    eval_baseline: bool = True
    selection: SelectionConfig | None = SelectionConfig()   # None: the last policy is the run's
    # devices the environments are split over (algo.num_envs must be divisible by their
    # number); None: every device JAX sees (one on a plain CPU machine)
    devices: PosInt | None = None
    # a training file to train next, from this run's final policy (relative to this file;
    # its algo.init must be policy, its algo.init_policy is replaced by this run's policy/),
    # into OUT/then/: the chain's team is the last run's (mysim_jax/mappo/chain.py)
    then: str | None = None


class TrainConfig(StrictModel):
    """A whole training file (module docstring)."""

    name: Name
    description: str = ""
    env: EnvSection
    algo: AlgoConfig = AlgoConfig()
    run: RunConfig = RunConfig()
    # named override lists (``--profile NAME``); a run folder's file holds none (it is resolved)
    profiles: dict[Name, list[str]] = {}

    @model_validator(mode="after")
    def _curriculum_fits_the_run(self):
        cur = self.env.curriculum
        if cur is not None and cur.advance_success is None:
            needed = cur.max_iterations * (len(cur.stages) - 1)
            if needed >= self.algo.num_iterations:
                raise ValueError(
                    f"env.curriculum.max_iterations: {len(cur.stages) - 1} stage changes of {cur.max_iterations} "
                    f"iterations need {needed + 1} iterations to reach the full range, and the run has "
                    f"{self.algo.num_iterations} (algo.total_env_steps / batch): lower max_iterations or give "
                    "advance_success")
        return self

    @model_validator(mode="after")
    def _residual_needs_a_team(self):
        if self.algo.init == "bc" and self.algo.residual:
            raise ValueError("algo.init: bc and algo.residual: true both start from the scripted team; choose one")
        if self.algo.residual and self.env.builtin is not None:
            raise ValueError("algo.residual: the builtin environment has no scripted team to add a residual to")
        if self.algo.init == "bc" and self.env.builtin is not None:
            raise ValueError("algo.init: bc clones the scripted team, which the builtin environment does not have")
        return self

    @model_validator(mode="after")
    def _selection_scene_needs_a_scene(self):
        sel = self.run.selection
        if self.env.builtin is not None and sel is not None and (sel.set is not None or sel.scene is not None):
            raise ValueError("run.selection.set / run.selection.scene apply to a scene file, not to a builtin "
                             "environment")
        return self

    @model_validator(mode="after")
    def _seeds_on_one_device(self):
        if self.run.seeds > 1 and self.run.devices not in (None, 1):
            raise ValueError(f"run.seeds {self.run.seeds} with run.devices {self.run.devices}: several seeds train "
                             "in one program on one device; split environments over devices with one seed")
        return self


def init_policy_path(config: TrainConfig, train_path: str | Path) -> Path | None:
    """``algo.init_policy``'s folder, resolved relative to the training file's folder (None
    without one)."""
    if config.algo.init_policy is None:
        return None
    p = Path(config.algo.init_policy)
    return p if p.is_absolute() else Path(train_path).parent / p


def check_init_policy(config: TrainConfig, train_path: str | Path) -> None:
    """ConfigError unless ``algo.init_policy`` (when given) is a saved MAPPO policy whose
    networks are this file's (``algo.hidden``, ``activation``, ``normalize_obs``,
    ``residual``); reads its ``policy.json`` only."""
    path = init_policy_path(config, train_path)
    if path is None:
        return
    where = f"{train_path}: algo.init_policy {config.algo.init_policy}"
    if not (path / "policy.json").is_file():
        raise ConfigError(f"{where}: no saved policy there (no {path / 'policy.json'}; paths are relative to the "
                          "training file)")
    try:
        meta = json.loads((path / "policy.json").read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{where}: cannot read policy.json: {exc}") from None
    kind = meta.get("kind") if isinstance(meta, dict) else None
    if kind != "mappo":
        raise ConfigError(f"{where}: policy.json is not a MAPPO policy (kind {kind!r})")
    a = config.algo
    ours = {"hidden": list(a.hidden), "activation": a.activation, "normalize_obs": a.normalize_obs,
            "residual": a.residual}
    differ = [f"{k} {meta.get(k)!r} there, {v!r} here" for k, v in ours.items() if meta.get(k) != v]
    if differ:
        raise ConfigError(f"{where}: its networks differ from this file's algo settings ({'; '.join(differ)}): "
                          "set them as the policy has them")


def train_config_from_dict(raw: Any, source: str = "<dict>", overrides=(), profile: str | None = None) -> TrainConfig:
    """Validate a raw training file: the overrides of ``profile`` (one of its
    ``profiles``) first, then ``overrides``. Each profile is checked on its own too, so a
    broken one is found whichever is run."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: a training file must be a YAML mapping at the top level")
    profiles = raw.get("profiles") or {}
    if not isinstance(profiles, dict):
        raise ConfigError(f"{source}: profiles: give a mapping of profile names to lists of key=value overrides")
    for name, values in profiles.items():
        if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
            raise ConfigError(f"{source}: profiles.{name}: give a list of key=value overrides (as --set)")
        try:
            applied = apply_overrides(raw, values)
        except ConfigError as err:
            raise ConfigError(f"{source}: profiles.{name}: {err}") from None
        if name != profile:
            _validate(applied, f"{source} (profile {name})")
    if profile is not None and profile not in profiles:
        known = ", ".join(map(str, profiles)) or "none"
        raise ConfigError(f"{source}: --profile {profile}: the file has no such profile (it has: {known})")
    chosen = override_list(overrides, first=profiles[profile] if profile is not None else ())
    return _validate(apply_overrides(raw, chosen), source if profile is None else f"{source} (profile {profile})")


def _validate(raw: dict, source: str) -> TrainConfig:
    try:
        return TrainConfig.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(f"{source}: invalid training configuration\n{format_validation_error(err)}") from None


def load_train_config(path: str | Path, overrides=(), profile: str | None = None) -> TrainConfig:
    """Read, override (``profile``'s overrides, then ``overrides``) and validate a training
    file; its scene file is checked too (:func:`load_scene`)."""
    config = train_config_from_dict(read_yaml_file(path, "training file"), str(path), overrides, profile)
    load_eval_scene(config, path, load_scene(config, path))
    load_select_scene(config, path)
    check_init_policy(config, path)
    return config


def capture_scenes(path: str | Path, levels, overrides=()) -> dict:
    """``{level: SceneConfig}`` of a capture scene file, or of a training file's scene (its
    ``env.set`` first), with ``overrides`` and ``level=LEVEL`` applied, for each level of
    ``levels`` (repeats once). Raises ConfigError naming the problem, e.g. a scene that is
    not a capture environment (no ``env:``, ``net:`` or ``target:``)."""
    raw = read_yaml_file(path, "config file")
    sets, scene = list(overrides), path
    if isinstance(raw, dict) and isinstance(raw.get("env"), dict) and "scene" in raw["env"]:
        train = load_train_config(path)
        scene, sets = scene_path(train, path), [*train.env.set, *overrides]
    configs = {level: load_config(scene, override_list(sets, level=level)) for level in dict.fromkeys(levels)}
    for level, config in configs.items():
        if config.env is None or config.net is None or config.target is None:
            raise ConfigError(f"{path}: level {level}: not a capture environment (needs env:, net: and target:)")
    return configs


def scene_path(config: TrainConfig, train_path: str | Path) -> Path | None:
    """The scene file, resolved relative to the training file's folder."""
    if config.env.scene is None:
        return None
    p = Path(config.env.scene)
    return p if p.is_absolute() else Path(train_path).parent / p


def load_eval_scene(config: TrainConfig, train_path: str | Path, scene=None):
    """The scene the final evaluation runs on (``env.eval_scene``, or ``env.scene`` at
    ``env.eval_level``, or the training scene ``scene``), or None for a builtin
    environment. Raises ConfigError naming the field."""
    if config.env.scene is None:
        return None
    if config.env.eval_scene is not None:
        p = Path(config.env.eval_scene)
        path = p if p.is_absolute() else Path(train_path).parent / p
        if not path.exists():
            raise ConfigError(f"{train_path}: env.eval_scene: no such file {path} "
                              "(paths are relative to the training file)")
        return _check_learner_discount(config, load_config(path), f"{train_path}: env.eval_scene")
    if config.env.eval_level is None:
        return scene if scene is not None else load_scene(config, train_path)
    if config.env.eval_set is not None:
        return load_scene(config, train_path, level=config.env.eval_level, sets=config.env.eval_set,
                          field="env.eval_set")
    try:
        return load_scene(config, train_path, level=config.env.eval_level)
    except ConfigError as err:
        raise ConfigError(f"{train_path}: env.eval_level: {err}") from None


def load_select_scene(config: TrainConfig, train_path: str | Path):
    """The scene model selection flies when it is not the training scene
    (``run.selection.scene``, or ``env.scene`` with ``run.selection.set`` in place of
    ``env.set`` at ``env.level``), else None. Raises ConfigError naming the field."""
    sel = config.run.selection
    if config.env.scene is None or sel is None or (sel.set is None and sel.scene is None):
        return None
    if sel.scene is not None:
        p = Path(sel.scene)
        path = p if p.is_absolute() else Path(train_path).parent / p
        if not path.exists():
            raise ConfigError(f"{train_path}: run.selection.scene: no such file {path} "
                              "(paths are relative to the training file)")
        return _check_learner_discount(config, load_config(path), f"{train_path}: run.selection.scene")
    return load_scene(config, train_path, sets=sel.set, field="run.selection.set")


def load_scene(config: TrainConfig, train_path: str | Path, level: str | None = None, sets=None,
               field: str = "env.set"):
    """The validated :class:`~mysim_jax.config.scene.SceneConfig` of ``env.scene`` with
    ``env.set`` applied (``sets`` instead when given, named ``field`` in errors; then
    ``level=LEVEL`` when ``level`` is given), or None for a builtin environment. Raises
    ConfigError naming ``env.scene`` when the file is missing or is not a capture scene
    with an ``env:`` block."""
    sets = config.env.set if sets is None else sets
    path = scene_path(config, train_path)
    if path is None:
        return None
    if not path.exists():
        raise ConfigError(f"{train_path}: env.scene: no such file {path} (paths are relative to the training file)")
    raw = read_yaml_file(path, "config file")
    missing = [b for b in ("net", "target", "quadrotors", "env") if not (isinstance(raw, dict) and raw.get(b) is not None)
               and b not in _set_blocks(sets)]
    if missing:
        raise ConfigError(f"{train_path}: env.scene: {path} is not a capture environment: it has no "
                          f"{' and no '.join(missing)} block")
    level = config.env.level if level is None else level
    level_set = override_list(level=level)
    try:
        scene = load_config(path, [*sets, *level_set])
    except ConfigError as err:
        if str(err).startswith("--set ") or field != "env.set":   # not key=value, or from env.eval_set
            raise ConfigError(f"{train_path}: {field}: {err}") from None
        raise
    missing = [b for b, v in (("net", scene.net), ("target", scene.target), ("quadrotors", scene.quadrotors),
                              ("env", scene.env)) if not v]
    if missing:
        raise ConfigError(f"{train_path}: env.scene: {path} is not a capture environment: it has no "
                          f"{' and no '.join(missing)} block")
    ignored = drawn_value_problems(scene, sets, where=f"{train_path}: {field}:")
    if ignored:
        raise ConfigError("; ".join(ignored))
    if config.env.curriculum is not None and scene.target.behaviour != "maneuvering":
        raise ConfigError(f"{train_path}: env.curriculum scales an evading target's speed, jink and flee ranges; "
                          f"the target of {path} is '{scene.target.behaviour}' (remove env.curriculum or use a "
                          "scene with target.behaviour: maneuvering)")
    return _check_learner_discount(config, scene, f"{train_path}: env.scene")


def _check_learner_discount(config: TrainConfig, scene, where: str):
    """``scene``, its reward ranking checked with ``algo.gamma``: the shaping's discount in
    training is the learner's (potential-based shaping keeps the optimal policy only with
    the discount the learner optimises; the run passes it to ``make_env(discount=)``)."""
    gamma = config.algo.gamma
    problems = [] if gamma == scene.env.discount else env_problems(scene, discount=gamma)
    if problems:
        raise ConfigError(f"{where}: with the learner's discount algo.gamma = {gamma:g} as the shaping's: "
                          + "; ".join(problems))
    return scene


def _set_blocks(overrides) -> set[str]:
    """Top-level blocks an override list sets (``env={}`` or ``env.x=1`` set ``env``)."""
    return {ov.split("=", 1)[0].split(".", 1)[0].strip() for ov in overrides if "=" in ov}


def network_memory_bytes(algo: AlgoConfig) -> int:
    """A lower bound on the memory the two networks take while training (float32): the
    weights between hidden layers (the input and output layers left out, as they depend
    on the environment) of actor and critic, each held as parameters, gradients and
    Adam's two moments, plus one minibatch's activations through them, kept for the
    backward pass."""
    h = algo.hidden
    weights = sum(a * b + b for a, b in zip(h, h[1:])) + sum(h)
    activations = algo.minibatch_size * sum(h)
    return 4 * 2 * (4 * weights + 2 * activations)


def check_memory(algo: AlgoConfig, source: str, available: int | None = None) -> None:
    """Refuse sizes that cannot fit in the machine's memory, before anything compiles."""
    available = available_memory_bytes() if available is None else available
    need = network_memory_bytes(algo)
    if available is not None and need > available:
        raise ConfigError(
            f"{source}: algo.hidden {list(algo.hidden)} (with algo.num_envs x num_steps / num_minibatches = "
            f"{algo.minibatch_size:,} per minibatch) needs at least {need / 2**30:,.1f} GiB for the two networks "
            f"(weights, gradients, Adam's moments and activations, float32); this machine has "
            f"{available / 2**30:,.1f} GiB available: use narrower layers")


def check_memory_needs(needs: dict, source: str, available: int | None = None) -> None:
    """Refuse a run whose estimated memory exceeds what the machine has. ``needs`` maps a
    part's name to ``(bytes, the fields that size it)`` (e.g. from
    :meth:`mysim_jax.mappo.trainer.Trainer.memory_needs`); the error names every part,
    largest first, and the fields of the largest."""
    available = available_memory_bytes() if available is None else available
    total = sum(b for b, _ in needs.values())
    if available is None or total <= available:
        return
    parts = sorted(needs.items(), key=lambda kv: -kv[1][0])
    listed = ", ".join(f"{name} {b / 2**30:,.1f} GiB ({fields})" for name, (b, fields) in parts)
    raise ConfigError(f"{source}: the run needs about {total / 2**30:,.1f} GiB ({listed}); this machine has "
                      f"{available / 2**30:,.1f} GiB available: lower {parts[0][1][1]}")


def reach_training_text(name: str, total_env_steps: int, **run) -> str:
    """A small training file (YAML text) for the builtin reach task, as the tests and
    ``scripts/resume_soak.py`` train it: 32 environments x 16 steps, lr 3e-3, initial
    policy std 0.5; ``run`` gives the ``run:`` section's values (seed 1 unless given)."""
    algo = {"num_envs": 32, "num_steps": 16, "total_env_steps": int(total_env_steps), "lr": 3.0e-3, "init_std": 0.5}
    return yaml.safe_dump({"name": name, "env": {"builtin": "reach"}, "algo": algo, "run": {"seed": 1, **run}},
                          sort_keys=False, default_flow_style=None)


def describe(config: TrainConfig) -> str:
    """Derived sizes, one line."""
    a = config.algo
    guard = ("" if config.run.time_limit_min is None else
             f"; time guard run.time_limit_min = {config.run.time_limit_min:g} min (stops earlier on a slow machine)")
    seeds = "" if config.run.seeds == 1 else (f"; seeds {config.run.seed}-{config.run.seed + config.run.seeds - 1}"
                                               " in one program")
    return (f"{a.num_iterations} iterations of {a.num_envs} envs x {a.num_steps} steps = {a.batch_size:,} team steps "
            f"({a.num_minibatches} minibatches of {a.minibatch_size:,}, {a.update_epochs} epochs); "
            f"{a.num_iterations * a.batch_size:,} team steps in all (the step budget, algo.total_env_steps){guard}{seeds}")

