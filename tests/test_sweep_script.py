"""scripts/sweep.py end to end on a small grid (mysim_jax/tasks/grid.py): the CSV, the JSON
and the plots agree; every point with one seed flies the episodes scripts/evaluate.py flies
(run_two_teams with that seed's key); bad input is one line, exit code 2, nothing written.

One sweep runs (the scene's cheap level ``train``, 4 episodes, both teams): two grid points
of one scene times two seeds, so one program compiles."""

import csv
import importlib.util
import json
import subprocess
import sys

import jax
import numpy as np
import pytest

from mysim_jax.config.env import FAILURES
from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.tasks.capture import make_env
from mysim_jax.tasks.evaluate import random_policy, run_two_teams, scripted_policy
from mysim_jax.tasks.grid import parse_axis, split_values

from conftest import CONFIGS, ROOT

SCRIPT = ROOT / "scripts" / "sweep.py"
SCENE = CONFIGS / "capture_env_falling.yaml"
HOLD = "env.success.hold_time"
BASE = [str(SCENE), "--set", "level=train", "--policy", "scripted", "--episodes", "4", "--batch", "4"]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep") / "out"
    res = subprocess.run([sys.executable, str(SCRIPT), *BASE, "--compare", "random", "--vary", f"{HOLD}=0.5,0.5",
                          "--vary", "seed=3,4", "--no-progress", "--out", str(out)],
                         capture_output=True, text=True, cwd=ROOT)
    return res, out


def _script():
    spec = importlib.util.spec_from_file_location("sweep_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_outputs_agree(sweep):
    res, out = sweep
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    # one line per point as it finishes, then where the files are
    assert [line[:6] for line in lines[:4]] == ["[1/4] ", "[2/4] ", "[3/4] ", "[4/4] "], res.stdout
    assert len(lines) == 5 and "4 points x 4 episodes" in lines[4] and "sweep.csv" in lines[4]
    with (out / "sweep.csv").open() as f:
        rows = list(csv.DictReader(f))
    # 2 x 2 points, each with the policy's row then the compared team's
    assert [(r["point"], r[HOLD], r["seed"], r["team"], r["spec"]) for r in rows] == [
        (str(p), "0.5", str(s), t, spec) for p, s in enumerate((3, 4, 3, 4))
        for t, spec in (("policy", "scripted"), ("compare", "random"))]
    expected = {"episodes", "successes", "success_rate", "success_low95", "success_high95", "timeout_rate",
                "mean_length_steps", "mean_return", "difference", "difference_low95", "difference_high95",
                *(f"failure_{f}" for f in FAILURES)}
    assert expected <= set(rows[0])
    record = json.loads((out / "sweep.json").read_text())
    assert len(record["rows"]) == len(rows)
    for jrow, crow in zip(record["rows"], rows):
        assert list(jrow) == list(crow)
        assert {k: "" if v is None else str(v) for k, v in jrow.items()} == crow
    assert (record["episodes"], record["batch"], record["seeds"], record["policy"], record["compare"]) == (
        4, 4, [3, 4], "scripted", "random")
    assert record["sets"] == ["level=train"] and "--vary seed=3,4" in record["command"] and record["machine"]
    assert record["plots"] == ["success_env_success_hold_time.png", "success_seed.png"]
    for name in record["plots"]:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (out.parent / ".out.resume").exists()        # the points' progress files are removed


def test_rates_and_intervals(sweep):
    _, out = sweep
    record = json.loads((out / "sweep.json").read_text())
    for row in record["rows"]:
        assert row["success_rate"] == row["successes"] / row["episodes"]
        assert 0 <= row["success_low95"] <= row["success_rate"] <= row["success_high95"] <= 1
        assert row["success_high95"] - row["success_low95"] > 0.3            # 4 episodes: a wide interval
        assert sum(row[f"failure_{f}"] for f in FAILURES) >= row["episodes"] - row["successes"] - round(
            row["timeout_rate"] * row["episodes"])
    for policy, compare in zip(record["rows"][::2], record["rows"][1::2]):
        d = policy["difference"]
        assert d == pytest.approx(policy["success_rate"] - compare["success_rate"])
        assert policy["difference_low95"] <= d <= policy["difference_high95"]
        assert compare["difference"] is None
    # the scripted team catches on the cheap level, the random one does not
    assert all(r["successes"] >= 3 for r in record["rows"][::2])
    assert all(r["successes"] == 0 for r in record["rows"][1::2])


def test_same_seed_same_episodes(sweep):
    """Points 0 and 2 (and 1 and 3) are one scene and one seed: identical outcomes; the two
    seeds draw other episodes; and seed 4's numbers are those of run_two_teams (what
    scripts/evaluate.py --seed 4 --compare runs) on that scene."""
    _, out = sweep
    rows = json.loads((out / "sweep.json").read_text())["rows"]
    outcome = [{k: v for k, v in r.items() if k not in ("point", "wall_s")} for r in rows]
    assert outcome[0:2] == outcome[4:6] and outcome[2:4] == outcome[6:8]
    assert [(r["mean_length_steps"], r["mean_return"]) for r in rows[0:2]] != [
        (r["mean_length_steps"], r["mean_return"]) for r in rows[2:4]]
    env, params = make_env(load_config(SCENE, ["level=train", f"{HOLD}=0.5"]))
    stats = run_two_teams(env, params, scripted_policy(env), random_policy(env), 4, 4, jax.random.PRNGKey(4),
                          progress=False)
    for row, s in zip(rows[2:4], stats):
        assert row["successes"] == int(np.sum(s.success))
        assert row["mean_length_steps"] == float(np.mean(s.length))
        assert row["mean_return"] == float(np.mean(s.returns))
        assert [row[f"failure_{f}"] for f in FAILURES] == [int(np.sum(s.failures[f])) for f in FAILURES]


@pytest.mark.parametrize("args, message", [
    ([*BASE, "--vary", "env.bogus=1,2"], ["--vary env.bogus=1", "env.bogus: unknown key"]),
    ([*BASE, "--vary", f"{HOLD}="], [f"--vary {HOLD}: no values"]),
    ([*BASE, "--vary", f"{HOLD}=0.5,,0.4"], ["value 2 is empty"]),
    ([*BASE, "--vary", "target.mass=0.5"], ["--vary target.mass=0.5", "env.randomize.target_mass draws it"]),
    ([*BASE, "--vary", "level=train,full"], ["--vary level: also set by --set level=train"]),
    ([*BASE, "--vary", "seed=1,x"], ["'x' is not a seed"]),
    ([str(CONFIGS / "no_such_scene.yaml"), *BASE[1:], "--vary", f"{HOLD}=0.5"], ["no_such_scene.yaml",
                                                                                 "no such config file"]),
    ([*BASE, "--vary", f"{HOLD}=0.5", "--compare", "nope.py"], ["--compare nope.py", "no such file"]),
])
def test_bad_input_is_one_line_exit_2_nothing_written(args, message, tmp_path, capsys):
    out = tmp_path / "never"
    code = _script().main([*args, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("error: ") and "\n" not in err, err
    assert all(m in err for m in message), err
    assert not out.exists()


def test_a_team_that_cannot_fly_one_point_stops_the_sweep_before_it_runs(tmp_path, capsys):
    """The trained policy flies at 10 Hz: the 25 Hz point is refused (naming the point and
    the difference) before the 10 Hz point runs."""
    out = tmp_path / "never"
    code = _script().main([str(ROOT / "docs" / "train" / "falling" / "scene.yaml"), "--policy",
                           str(ROOT / "docs" / "train" / "falling" / "policy"), "--vary", "env.policy_rate=10,25",
                           "--episodes", "2", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("error: at env.policy_rate=25: --policy") and "\n" not in err, err
    assert "policy rate" in err and "--allow-mismatch" in err
    assert not out.exists()


def test_values_split_on_top_level_commas_only():
    assert split_values("0.5,0.4") == ["0.5", "0.4"]
    assert split_values("{low: 0.1, high: 0.1},{low: 0.3, high: 0.3}") == ["{low: 0.1, high: 0.1}",
                                                                         "{low: 0.3, high: 0.3}"]
    assert split_values("{force: [1, 0, 0]}, null") == ["{force: [1, 0, 0]}", "null"]
    assert split_values("'a,b',[[1, 2], [3]],\"c, d\"") == ["'a,b'", "[[1, 2], [3]]", '"c, d"']
    for broken in ("[1, 2", "1]", "{a: [1}", "'a,b"):
        with pytest.raises(ConfigError, match="unbalanced|not opened"):
            split_values(broken)
    axis = parse_axis("quadrotors.0.wind={force: [1, 0, 0]},null")
    assert axis.key == "quadrotors.0.wind" and axis.values == ({"force": [1, 0, 0]}, None)
    assert parse_axis("seed=2026,2027").values == (2026, 2027)
