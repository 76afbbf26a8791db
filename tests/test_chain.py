"""``run.then``: two training files trained one after the other (mysim_jax/mappo/chain.py),
on the builtin reach task (seconds to train). The chain is the two commands run one after
the other, bit for bit; a chain resumed after its first run continues with the second;
every bad second file is refused before anything is written."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
import yaml

from mysim_jax.core.config_base import ConfigError
from mysim_jax.mappo.config import reach_training_text

from conftest import run_script_main

ROOT = Path(__file__).resolve().parents[1]
TIMING = {"wall_s", "iteration_s"}


def _files(folder: Path, then: str | None = "second.yaml", **second_algo) -> Path:
    """``first.yaml`` (4 reach iterations, naming ``then``) and ``second.yaml`` (3
    iterations from a policy) in ``folder``; returns the first."""
    first = yaml.safe_load(reach_training_text("first", 32 * 16 * 4, checkpoint_every=2, eval_episodes=50))
    second = yaml.safe_load(reach_training_text("second", 32 * 16 * 3, checkpoint_every=2, eval_episodes=50))
    second["algo"].update({"init": "policy", "init_policy": "elsewhere", "lr": 3e-3,
                           "bc": {"std": 0.3, "critic_warmup": 1}, **second_algo})
    if then is not None:
        first["run"]["then"] = then
    (folder / "first.yaml").write_text(yaml.safe_dump(first))
    (folder / "second.yaml").write_text(yaml.safe_dump(second))
    return folder / "first.yaml"


def _rows(path: Path) -> list[dict]:
    with path.open() as f:
        return [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(f)]


def _same_policy(a: Path, b: Path) -> None:
    from mysim_jax.mappo.checkpoint import load_policy

    (_, x), (_, y) = load_policy(a), load_policy(b)
    for (k, u), (_, v) in zip(jax.tree_util.tree_leaves_with_path(x), jax.tree_util.tree_leaves_with_path(y)):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v), err_msg=str(k))


def test_a_chain_is_the_two_runs_one_after_the_other(tmp_path, capsys):
    """The chain in one command; then the first file alone and the second from its policy
    (``algo.init_policy`` set by hand): the same policies and metrics, bit for bit. A
    chain resumed once its first run had ended trains the second the same way."""
    first = _files(tmp_path)
    code, _, err, _ = run_script_main("train", [first, "--out", tmp_path / "chain", "--no-eval", "--no-progress"],
                                      capsys)
    assert code == 0, err
    chain = tmp_path / "chain"
    written = yaml.safe_load((chain / "then" / "train.yaml").read_text())
    assert written["algo"]["init_policy"] == "../policy" and written["name"] == "second"
    assert yaml.safe_load((chain / "train.yaml").read_text())["run"]["then"] == "then/train.yaml"

    (tmp_path / "alone_files").mkdir()
    alone = _files(tmp_path / "alone_files", then=None)
    code, _, err, _ = run_script_main("train", [alone, "--out", tmp_path / "a", "--no-eval", "--no-progress"],
                                      capsys)
    assert code == 0, err
    code, _, err, _ = run_script_main("train", [alone.parent / "second.yaml", "--set",
                                                f"algo.init_policy={tmp_path / 'a' / 'policy'}", "--out",
                                                tmp_path / "b", "--no-eval", "--no-progress"], capsys)
    assert code == 0, err
    _same_policy(chain / "policy", tmp_path / "a" / "policy")
    _same_policy(chain / "then" / "policy", tmp_path / "b" / "policy")
    assert _rows(chain / "then" / "metrics.csv") == _rows(tmp_path / "b" / "metrics.csv")
    # the second run changed the policy (it is not the first run's, passed through)
    from mysim_jax.mappo.checkpoint import load_policy

    a_actor = load_policy(chain / "policy")[1]["actor"]["params"]
    b_actor = load_policy(chain / "then" / "policy")[1]["actor"]["params"]
    assert any(float(np.max(np.abs(np.asarray(u) - np.asarray(v)))) > 1e-6 for u, v in
               zip(jax.tree.leaves(a_actor), jax.tree.leaves(b_actor)))

    # resumed after the first run: only the second trains again
    for name in ("then/checkpoints", "then/policy", "then/tb"):
        shutil.rmtree(chain / name)
    for name in ("then/metrics.csv", "then/summary.json", "then/curves.png"):
        (chain / name).unlink()
    code, out, err, _ = run_script_main("train", ["--resume", chain, "--no-eval", "--no-progress"], capsys)
    assert code == 0, err
    assert "the first run of the chain has ended" in out
    _same_policy(chain / "then" / "policy", tmp_path / "b" / "policy")


def test_a_chain_has_one_seed_the_first_runs(tmp_path, capsys):
    """``--set run.seed=3`` on a chain whose two files say another seed trains seed 3 in
    both runs: the second run's ``train.yaml`` records it, the log names it, and its
    metrics are not those of the files' own seed."""
    first = _files(tmp_path)
    own = yaml.safe_load((tmp_path / "second.yaml").read_text())["run"]["seed"]
    assert own == yaml.safe_load(first.read_text())["run"]["seed"] != 3
    runs = {}
    for seed in (own, 3):
        out = tmp_path / f"chain{seed}"
        code, stdout, err, _ = run_script_main("train", [first, "--set", f"run.seed={seed}", "--out", out,
                                                         "--no-eval", "--no-progress"], capsys)
        assert code == 0, err
        assert f"seed {seed} (the chain's)" in stdout
        assert yaml.safe_load((out / "then" / "train.yaml").read_text())["run"]["seed"] == seed
        runs[seed] = _rows(out / "then" / "metrics.csv")
    assert runs[own] != runs[3]


def test_then_overrides_set_the_second_file(tmp_path, capsys):
    """``--set then.KEY=VALUE`` changes the second file alone, as its ``train.yaml``
    records; ``--set KEY=VALUE`` the first alone."""
    first = _files(tmp_path)
    out = tmp_path / "chain"
    code, stdout, err, _ = run_script_main("train", [first, "--set", "algo.lr=2e-3", "then.algo.lr=7e-4",
                                                     "then.run.eval_baseline=false", "--out", out, "--no-eval",
                                                     "--no-progress"], capsys)
    assert code == 0, err
    one, two = (yaml.safe_load((out / f).read_text()) for f in ("train.yaml", "then/train.yaml"))
    assert one["algo"]["lr"] == 2e-3 and two["algo"]["lr"] == 7e-4
    assert one["run"]["eval_baseline"] != two["run"]["eval_baseline"] is False
    rows = _rows(out / "then" / "metrics.csv")
    assert float(rows[0]["lr"]) == pytest.approx(7e-4)          # the first iteration's, before the decay


@pytest.mark.parametrize("sets, message", [
    (["then.run.seed=3"], "--set then.run.seed: a chain has one seed"),
    (["then.algo.init_policy=elsewhere"], "--set then.algo.init_policy: the second run starts from the first"),
    (["then.algo.lrr=1e-3"], "second.yaml: invalid training configuration\n  algo.lrr: unknown key"),
    (["run.then=null", "then.algo.lr=1e-3"], "--set then.algo.lr=1e-3: this file has no run.then"),
])
def test_bad_then_overrides_are_refused_before_anything_is_written(tmp_path, capsys, sets, message):
    first = _files(tmp_path)
    out = tmp_path / "out"
    code, _, err, _ = run_script_main("train", [first, "--set", *sets, "--out", out, "--no-eval", "--no-progress"],
                                      capsys)
    assert code == 2 and message in err, err
    assert not out.exists()


@pytest.mark.parametrize("change, message", [
    ({"then": "missing.yaml"}, "run.then missing.yaml: no such training file"),
    ({"second_algo": {"init": "none", "init_policy": None}}, "give it algo.init: policy"),
    ({"second_algo": {"hidden": [32, 32]}}, "its networks must be this file's, which it starts from (hidden [128, 128] here, [32, 32] there)"),
    ({"second_run": {"then": "first.yaml"}}, "a chain has two files"),
    ({"first_run": {"seeds": 2}}, "a chain trains one seed"),
])
def test_a_bad_second_file_is_refused_before_anything_is_written(tmp_path, capsys, change, message):
    first = _files(tmp_path, then=change.get("then", "second.yaml"), **change.get("second_algo", {}))
    for key, name in (("first_run", "first.yaml"), ("second_run", "second.yaml")):
        if key in change:
            raw = yaml.safe_load((tmp_path / name).read_text())
            raw["run"].update(change[key])
            (tmp_path / name).write_text(yaml.safe_dump(raw))
    out = tmp_path / "out"
    code, _, err, _ = run_script_main("train", [first, "--out", out, "--no-eval", "--no-progress"], capsys)
    assert code == 2 and message in err, err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_a_second_file_of_another_environment_is_refused_before_anything_is_written(tmp_path, capsys):
    """The first run on the reach task, the second on the falling capture scene: the
    first's policy could not fly it (8 observations there, 52 here), found before the first
    run starts."""
    first = _files(tmp_path)
    raw = yaml.safe_load((tmp_path / "second.yaml").read_text())
    raw["env"] = {"scene": str(ROOT / "configs" / "capture_env_falling.yaml"), "level": "train"}
    (tmp_path / "second.yaml").write_text(yaml.safe_dump(raw))
    out = tmp_path / "out"
    code, _, err, _ = run_script_main("train", [first, "--out", out, "--no-eval", "--no-progress"], capsys)
    assert code == 2 and "run.then second.yaml: this run's policy" in err and "trained on observations" in err, err
    assert not out.exists()
    # the library's prepare() refuses too (the script's check is not the only one)
    from mysim_jax.mappo.run import prepare

    (tmp_path / "x").mkdir()
    _files(tmp_path / "x", then="nope.yaml")
    with pytest.raises(ConfigError, match="no such training file"):
        prepare(str(tmp_path / "x" / "first.yaml"), [], str(tmp_path / "y"))
