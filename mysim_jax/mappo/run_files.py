"""A training run's folder on disk: the checked run (:class:`Prepared`), the files that make
the folder self-contained (``train.yaml``, ``scene.yaml``, ``scene_eval.yaml``,
``scene_select.yaml``, a copy of the starting policy), its ``metrics.csv``, and a chain's second run (``run.then``,
:func:`prepare_then`). The run itself is :mod:`mysim_jax.mappo.run`, a chain
:mod:`mysim_jax.mappo.chain`.
Imports no JAX: a training file is checked, and a run folder read, without it."""

from __future__ import annotations

import csv
import shutil
from dataclasses import dataclass
from pathlib import Path

import yaml

from mysim_jax.config.scene import dump_config
from mysim_jax.core.config_base import ConfigError, read_yaml_file
from mysim_jax.io.output import check_output_dir
from mysim_jax.mappo.config import (TrainConfig, check_memory, describe, init_policy_path, load_eval_scene,
                                    load_scene, load_select_scene, load_train_config, train_config_from_dict)

TRAIN_FILE = "train.yaml"
INIT_POLICY_DIR = "init_policy"      # a copy of algo.init_policy's folder
SCENE_FILE = "scene.yaml"
EVAL_SCENE_FILE = "scene_eval.yaml"
SELECT_SCENE_FILE = "scene_select.yaml"
CSV_FIELDS = ("iteration", "env_steps", "wall_s", "iteration_s", "episodes", "mean_return", "success_rate",
              "mean_length", "step_reward", "policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction",
              "explained_variance", "grad_norm", "action_std", "lr", "updates_applied", "policy_coef",
              "anchor_coef", "anchor_loss", "select_success", "select_return", "curriculum_stage",
              "curriculum_fraction")
# a chain's second run (run.then; mysim_jax/mappo/chain.py trains it)
THEN_DIR = "then"                    # the second run's folder, inside the first's
START = "../policy"                  # its starting policy, relative to its train.yaml
NETWORK_FIELDS = ("hidden", "activation", "normalize_obs", "residual")


@dataclass
class Prepared:
    """A checked run: its configs and where it writes (nothing compiled yet)."""

    config: TrainConfig
    scene: object | None           # SceneConfig, or None for a builtin environment
    out: Path
    resume: bool
    source: str
    eval_scene: object | None = None   # the scene of the final evaluation (None: ``scene``)
    profile: str | None = None         # the training file's profile applied (``--profile``)
    then: Prepared | None = None       # ``run.then``'s run, trained next (mysim_jax/mappo/chain.py)
    select_scene: object | None = None  # the scene model selection flies (None: ``scene``)

    @property
    def evaluates_elsewhere(self) -> bool:
        """Whether the final evaluation runs on another scene than training."""
        return (self.scene is not None and self.eval_scene is not None
                and dump_config(self.eval_scene) != dump_config(self.scene))


def then_path(config, source: str | Path) -> Path | None:
    """``run.then``'s file, resolved relative to the training file ``source`` (None
    without one)."""
    if config.run.then is None:
        return None
    p = Path(config.run.then)
    return p if p.is_absolute() else Path(source).parent / p


THEN_SET = "then."
"""Prefix of a ``--set`` override meant for a chain's second file (``then.algo.lr=3e-4``)."""
CHAIN_SET = {"run.seed": "a chain has one seed: set run.seed, the first file's, which the second run takes",
             "algo.init_policy": "the second run starts from the first run's policy"}


def split_then(overrides) -> tuple[list[str], list[str]]:
    """``(the first file's overrides, the second file's)``: an override whose key starts with
    :data:`THEN_SET` is the second file's, the prefix removed."""
    own, then = [], []
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if key.startswith(THEN_SET):
            then.append(item.strip()[len(THEN_SET):])
        else:
            own.append(item)
    return own, then


def prepare_then(config, source: str | Path, out: Path, overrides=()):
    """The second run of a chain whose first run is ``config`` (read from ``source``,
    writing ``out``), with ``overrides`` (``--set then.KEY=VALUE``, the prefix removed)
    applied to its file, checked: the file exists, starts from a policy (``algo.init:
    policy``; its ``algo.init_policy`` becomes ``../policy``, the first run's), has this
    file's networks, names no ``run.then`` itself, and the chain trains one seed (the first
    run's ``run.seed`` replaces the second file's; :mod:`mysim_jax.mappo.chain`). None when
    ``config`` has no ``run.then``. Raises ConfigError naming the problem; imports no JAX."""
    path = then_path(config, source)
    overrides = list(overrides)
    if path is None:
        if overrides:
            raise ConfigError(f"{source}: --set {THEN_SET}{overrides[0]}: this file has no run.then, so no second "
                              "file to set it in")
        return None
    where = f"{source}: run.then {config.run.then}"
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        if key in CHAIN_SET:
            raise ConfigError(f"{where}: --set {THEN_SET}{key}: {CHAIN_SET[key]}")
    if config.run.seeds > 1:
        raise ConfigError(f"{where}: a chain trains one seed (run.seeds {config.run.seeds} here); train each seed's "
                          "chain on its own (--set run.seed=N)")
    if not path.is_file():
        raise ConfigError(f"{where}: no such training file ({path}; paths are relative to the training file)")
    raw = read_yaml_file(path, "training file")
    algo = raw.get("algo") if isinstance(raw, dict) else None
    if not isinstance(algo, dict) or algo.get("init") != "policy":
        raise ConfigError(f"{where}: the file trained next starts from this run's policy: give it algo.init: policy "
                          f"(it has {(algo or {}).get('init', 'none') if isinstance(algo, dict) else 'no algo:'})")
    nxt = train_config_from_dict(raw, str(path), [f"algo.init_policy={START}", f"run.seed={config.run.seed}",
                                                  *overrides])
    if nxt.run.then is not None:
        raise ConfigError(f"{where}: that file names run.then {nxt.run.then} itself; a chain has two files")
    if nxt.run.seeds > 1:
        raise ConfigError(f"{where}: a chain trains one seed (run.seeds {nxt.run.seeds} there)")
    differ = [f"{k} {getattr(config.algo, k)!r} here, {getattr(nxt.algo, k)!r} there" for k in NETWORK_FIELDS
              if getattr(config.algo, k) != getattr(nxt.algo, k)]
    if differ:
        raise ConfigError(f"{where}: its networks must be this file's, which it starts from ({'; '.join(differ)})")
    scene = load_scene(nxt, path)
    return Prepared(nxt, scene, Path(out) / THEN_DIR, False, str(path), load_eval_scene(nxt, path, scene),
                    select_scene=load_select_scene(nxt, path))


def load_run_config(config_path: str, overrides=(), profile: str | None = None) -> Prepared:
    """A training file and its scene, checked, for use without a run folder (benchmarks,
    notebooks): ``out`` is the default ``runs/<name>``, unchecked and not created."""
    config = load_train_config(config_path, overrides, profile)
    scene = load_scene(config, config_path)
    return Prepared(config, scene, Path("runs") / config.name, False, str(config_path),
                    load_eval_scene(config, config_path, scene), profile,
                    select_scene=load_select_scene(config, config_path))


def prepare(config_path: str | None, overrides=(), out: str | None = None, resume: str | None = None,
            profile: str | None = None) -> Prepared:
    """Check a training file (with its profile ``profile`` applied, then ``overrides``) or a
    run folder to resume, and the output folder. Overrides whose key starts with ``then.``
    apply to a chain's second file (:func:`prepare_then`). Raises ConfigError or
    OutputError with a one-line message; imports no JAX."""
    overrides, then_overrides = split_then(overrides)
    if resume is not None:
        run = Path(resume)
        if not (run / TRAIN_FILE).is_file():
            raise ConfigError(f"--resume {resume}: not a training run folder (no {TRAIN_FILE} in it)")
        config = load_train_config(run / TRAIN_FILE, overrides)
        check_memory(config.algo, str(run / TRAIN_FILE))
        scene = load_scene(config, run / TRAIN_FILE)
        return Prepared(config, scene, run, True, str(run / TRAIN_FILE),
                        load_eval_scene(config, run / TRAIN_FILE, scene),
                        then=prepare_then(config, run / TRAIN_FILE, run, then_overrides),
                        select_scene=load_select_scene(config, run / TRAIN_FILE))
    if config_path is None:
        raise ConfigError("give a training file, or --resume RUN_DIR")
    config = load_train_config(config_path, overrides, profile)
    check_memory(config.algo, str(config_path))
    scene = load_scene(config, config_path)
    target = Path(out) if out is not None else Path("runs") / config.name
    check_output_dir(target)
    if (target / TRAIN_FILE).exists():
        raise ConfigError(f"--out {target}: holds a training run already; continue it with --resume {target}, "
                          "or choose another folder")
    return Prepared(config, scene, target, False, str(config_path), load_eval_scene(config, config_path, scene),
                    profile, prepare_then(config, config_path, target, then_overrides),
                    load_select_scene(config, config_path))


def describe_run(p: Prepared) -> str:
    """One line: what will run, and where it writes."""
    what = f"builtin:{p.config.env.builtin}" if p.scene is None else f"{p.scene.name} (level {p.scene.level})"
    if p.evaluates_elsewhere:
        what += f", evaluated at level {p.eval_scene.level}"
        if p.config.env.eval_set is not None:
            what += " with env.eval_set"
    if p.select_scene is not None:
        what += ", selecting on run.selection's scene"
    if p.profile is not None:
        what += f", profile {p.profile}"
    line = f"{p.config.name} on {what}: {describe(p.config)}; writing {p.out}/" + (" (resuming)" if p.resume else "")
    if p.then is not None:
        line += f"; then {p.then.config.name} from its policy: {describe(p.then.config)}; writing {p.then.out}/"
    return line


def write_run_files(p: Prepared, copy_start: bool = True) -> None:
    """The run folder's ``train.yaml`` (resolved: the profile applied, the scene in
    ``scene.yaml``), its scenes and a copy of the starting policy (``copy_start``; the
    second run of a chain starts from the first's, ``algo.init_policy`` as given), and with
    ``run.then`` the next run's folder (its ``train.yaml`` and scenes)."""
    p.out.mkdir(parents=True, exist_ok=True)
    data = p.config.model_dump(mode="json")
    # resolved: the profile's values are in the file; its description names it
    data["profiles"] = {}
    if p.profile is not None:
        data["description"] = f"{data['description']} (profile {p.profile})".lstrip()
    if p.scene is not None:
        (p.out / SCENE_FILE).write_text(dump_config(p.scene))
        # the scene resolved into scene.yaml; the rest of the section (the curriculum) kept
        data["env"] = {**data["env"], "scene": SCENE_FILE, "set": [], "level": None, "eval_level": None,
                       "eval_scene": None, "eval_set": None}
        if p.evaluates_elsewhere:
            (p.out / EVAL_SCENE_FILE).write_text(dump_config(p.eval_scene))
            data["env"]["eval_scene"] = EVAL_SCENE_FILE
        if p.select_scene is not None:
            (p.out / SELECT_SCENE_FILE).write_text(dump_config(p.select_scene))
            data["run"]["selection"] = {**data["run"]["selection"], "set": None, "scene": SELECT_SCENE_FILE}
    if p.then is not None:
        data["run"]["then"] = f"{THEN_DIR}/{TRAIN_FILE}"
        write_run_files(p.then, copy_start=False)
    if p.config.algo.init_policy is not None and copy_start:
        # the starting policy travels with the run (--resume needs nothing outside the folder)
        start = init_policy_path(p.config, p.source)
        if start.resolve() != (p.out / INIT_POLICY_DIR).resolve():
            shutil.copytree(start, p.out / INIT_POLICY_DIR, dirs_exist_ok=True)
        data["algo"]["init_policy"] = INIT_POLICY_DIR
    text = yaml.safe_dump(data, sort_keys=False)
    # the run folder is valid by construction; check it anyway before relying on it
    train_config_from_dict(yaml.safe_load(text), str(p.out / TRAIN_FILE))
    (p.out / TRAIN_FILE).write_text(text)


def read_rows(path: Path, upto: int) -> list[dict]:
    """The rows of ``metrics.csv`` at ``path`` up to iteration ``upto`` (none when it is missing)."""
    if not path.exists():
        return []
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if r.get("iteration", "").isdigit() and int(r["iteration"]) <= upto]
    return rows


def write_rows(path: Path, rows: list[dict]) -> None:
    """``metrics.csv`` at ``path``, replaced whole (written beside it, then renamed)."""
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)


def read_metrics(run_dir: Path) -> list[dict]:
    """Every row of a run folder's ``metrics.csv``."""
    return read_rows(Path(run_dir) / "metrics.csv", 10**9)
