"""``env.eval_set``: a training file that trains on shifted conditions (estimation errors,
wider ranges, faults) and is judged on the nominal ones. The evaluation scene is
``env.scene`` with ``env.eval_set`` in place of ``env.set`` at ``env.eval_level``; the run
folder resolves it into ``scene_eval.yaml``. Nothing here compiles."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from mysim_jax.config.scene import dump_config, load_config
from mysim_jax.mappo.config import load_eval_scene, load_scene, load_train_config

from conftest import run_script_main

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
ALLOCATION = [f"quadrotors.{i}.controller.saturation=attitude_priority" for i in range(4)]


def _scenes(path: Path, overrides=()):
    config = load_train_config(path, list(overrides))
    scene = load_scene(config, path)
    return scene, load_eval_scene(config, path, scene)


@pytest.mark.parametrize("second, first, extra", [
    ("train_capture_falling_robust_scaled.yaml", "train_capture_falling.yaml", []),
    ("train_capture_maneuvering_robust_anchored.yaml", "train_capture_maneuvering.yaml", ALLOCATION),
])
def test_the_fine_tuned_teams_are_judged_on_the_nominal_scene(second, first, extra):
    """The fine-tuning files train on estimation errors, wider ranges and motor faults and
    evaluate on the first file's evaluation scene (true states, the scene's own ranges, no
    fault), the evading team with the allocation it trains with: the scene the
    robustness issue's nominal target is judged on."""
    trained, evaluated = _scenes(CONFIGS / second)
    assert trained.env.perception is not None and trained.env.randomize.thrust_loss is not None
    assert evaluated.level == "full" and evaluated.env.perception is None
    assert evaluated.env.randomize.thrust_loss is None
    config = load_train_config(CONFIGS / first)
    nominal = load_config(CONFIGS / config.env.scene, [*config.env.set, *extra, "level=full"])
    assert dump_config(evaluated) == dump_config(nominal)


def test_the_run_folder_resolves_the_evaluation_scene(tmp_path):
    """``train.yaml`` of the run folder points at ``scene_eval.yaml`` (the scene of
    ``env.eval_set``, resolved) and has no ``env.eval_set`` left; the folder prepared again
    for ``--resume`` evaluates on the same scene."""
    from mysim_jax.mappo.run_files import prepare, write_run_files

    path = CONFIGS / "train_capture_falling_robust_scaled.yaml"
    p = prepare(str(path), [], str(tmp_path / "run"))
    assert p.evaluates_elsewhere and p.eval_scene.env.perception is None
    write_run_files(p)
    written = yaml.safe_load((tmp_path / "run" / "train.yaml").read_text())["env"]
    assert written["eval_set"] is None and written["eval_scene"] == "scene_eval.yaml"
    assert (tmp_path / "run" / "scene_eval.yaml").read_text() == dump_config(p.eval_scene)
    again = prepare(None, [], None, resume=str(tmp_path / "run"))
    assert dump_config(again.eval_scene) == dump_config(p.eval_scene)


@pytest.mark.parametrize("sets, message", [
    (["env.eval_level=null"], "eval_set needs eval_level"),
    (["env.eval_level=null", "env.eval_scene=elsewhere.yaml"], "give at most one of eval_set"),
    (["env.eval_set=[oops]"], "env.eval_set: --set 'oops': expected key=value"),
    (["env.eval_set=['env.rewards.nonsense=1']"], "env.eval_set: "),
])
def test_bad_eval_sets_are_refused_before_anything_is_written(tmp_path, capsys, sets, message):
    """A bad ``env.eval_set`` is a one-line error naming the field, exit code 2, before any
    compilation and without a run folder."""
    args = [CONFIGS / "train_capture_falling_robust_scaled.yaml", "--out", tmp_path / "run"]
    code, _, err, compiled = run_script_main("train", [*args, *[a for s in sets for a in ("--set", s)]], capsys)
    assert code == 2 and message in err, err
    assert not compiled and not (tmp_path / "run").exists()


def test_eval_set_applies_to_a_scene_file_only(tmp_path, capsys):
    from mysim_jax.mappo.config import reach_training_text

    path = tmp_path / "reach.yaml"
    path.write_text(reach_training_text("reach", 32 * 16, checkpoint_every=2, eval_episodes=10))
    code, _, err, compiled = run_script_main("train", [path, "--set", "env.eval_set=['env.rewards.spin=0.1']"],
                                             capsys)
    assert code == 2 and "eval_set" in err and "builtin" in err and not compiled
