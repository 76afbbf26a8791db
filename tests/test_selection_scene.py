"""``run.selection.set`` / ``run.selection.scene``: model selection on another scene than
training's, e.g. a run that trains on shifted conditions selecting on the nominal ones it
is judged on. The selection scene is ``env.scene`` with ``run.selection.set`` in place of
``env.set`` at the training level; the run folder resolves it into ``scene_select.yaml``.
Nothing here compiles a rollout."""

from __future__ import annotations

import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
import yaml

from mysim_jax.config.scene import dump_config, load_config
from mysim_jax.mappo.config import load_train_config

from conftest import run_script_main

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
ALLOCATION = [f"quadrotors.{i}.controller.saturation=attitude_priority" for i in range(4)]
EVADING_SECOND = CONFIGS / "train_capture_maneuvering_robust_anchored.yaml"


def test_the_evading_fine_tuning_selects_on_the_nominal_scene_at_the_training_level():
    """The second file of the evading chain trains on estimation errors, wider ranges and
    motor faults and keeps the policy best on the nominal scene (the first file's scene
    and overrides, with the allocation it trains with) at the level it trains on; the
    reference is built from the scene file and the first file's overrides, not from the
    second file's ``env.eval_set``."""
    from mysim_jax.mappo.run_files import load_run_config

    p = load_run_config(str(EVADING_SECOND))
    assert p.scene.env.perception is not None and p.scene.env.randomize.thrust_loss is not None
    first = load_train_config(CONFIGS / "train_capture_maneuvering.yaml")
    nominal = load_config(CONFIGS / first.env.scene, [*first.env.set, *ALLOCATION, "level=train"])
    assert p.select_scene is not None and p.select_scene.level == "train" == p.scene.level
    assert dump_config(p.select_scene) == dump_config(nominal)
    assert p.config.run.selection.episodes == 500


def test_the_run_folder_resolves_the_selection_scene(tmp_path):
    """The chain's second run folder holds ``scene_select.yaml`` and a ``train.yaml`` that
    names it (``run.selection.set`` resolved away); prepared again for ``--resume`` it
    selects on the same scene. A file without a selection scene writes none."""
    from mysim_jax.mappo.run_files import prepare, write_run_files

    p = prepare(str(CONFIGS / "train_capture_maneuvering.yaml"), [], str(tmp_path / "chain"))
    assert p.select_scene is None and p.then.select_scene is not None
    write_run_files(p)
    assert not (tmp_path / "chain" / "scene_select.yaml").exists()
    then = tmp_path / "chain" / "then"
    selection = yaml.safe_load((then / "train.yaml").read_text())["run"]["selection"]
    assert selection["set"] is None and selection["scene"] == "scene_select.yaml"
    assert selection["episodes"] == 500
    assert (then / "scene_select.yaml").read_text() == dump_config(p.then.select_scene)
    # the second run starts from the first's policy: a kept one stands in for it
    shutil.copytree(ROOT / "docs" / "train" / "maneuvering" / "policy", tmp_path / "chain" / "policy")
    again = prepare(None, [], None, resume=str(then))
    assert dump_config(again.select_scene) == dump_config(p.then.select_scene)


def test_the_selection_evaluator_flies_the_selection_scene(tmp_path, monkeypatch):
    """The run builds its selection episodes' evaluator on the selection scene's
    environment, not on training's (stopped there, before anything trains)."""
    import mysim_jax.mappo.run as run

    seen = {}

    class Stop(Exception):
        pass

    def spy(env, params, *args, **kwargs):
        seen["env"], seen["params"] = env, params
        raise Stop

    monkeypatch.setattr(run, "Evaluator", spy)
    sets = ["algo.num_envs=4", "algo.num_steps=2", "algo.total_env_steps=8", "algo.num_minibatches=2",
            "run.selection.episodes=2", f"algo.init_policy={ROOT / 'docs' / 'train' / 'maneuvering' / 'policy'}"]
    p = run.prepare(str(EVADING_SECOND), sets, str(tmp_path / "run"))
    with pytest.raises(Stop):
        run.train_run(p, progress=False, evaluate=False, log=lambda *a: None)
    from mysim_jax.tasks.capture import make_env

    _, expected = make_env(p.select_scene, discount=p.config.algo.gamma)
    _, training = make_env(p.scene, discount=p.config.algo.gamma)
    same = [np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
            zip(jax.tree.leaves(seen["params"]), jax.tree.leaves(expected))]
    assert len(same) == len(jax.tree.leaves(expected)) and all(same)
    assert not all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
                   zip(jax.tree.leaves(seen["params"]), jax.tree.leaves(training)))
    assert not seen["env"].perception and make_env(p.scene)[0].perception


@pytest.mark.parametrize("sets, message", [
    (["run.selection.set=[oops]"], "run.selection.set: --set 'oops': expected key=value"),
    (["run.selection.set=['env.rewards.nonsense=1']"], "run.selection.set: "),
    (["run.selection.scene=gone.yaml"], "give at most one of set"),
    (["run.selection.set=null", "run.selection.scene=gone.yaml"], "run.selection.scene: no such file"),
])
def test_bad_selection_scenes_are_refused_before_anything_is_written(tmp_path, capsys, sets, message):
    """A bad selection scene is a one-line error naming the field, exit code 2, before any
    compilation and without a run folder."""
    args = [EVADING_SECOND, "--out", tmp_path / "run"]
    code, _, err, compiled = run_script_main("train", [*args, *[a for s in sets for a in ("--set", s)]], capsys)
    assert code == 2 and message in err, err
    assert not compiled and not (tmp_path / "run").exists()


def test_a_selection_scene_applies_to_a_scene_file_only(tmp_path, capsys):
    from mysim_jax.mappo.config import reach_training_text

    path = tmp_path / "reach.yaml"
    path.write_text(reach_training_text("reach", 32 * 16, checkpoint_every=2, eval_episodes=10))
    code, _, err, compiled = run_script_main(
        "train", [path, "--set", "run.selection.set=['env.rewards.spin=0.1']"], capsys)
    assert code == 2 and "run.selection.set" in err and "builtin" in err and not compiled

