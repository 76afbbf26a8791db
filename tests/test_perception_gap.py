"""The perception gap: env.perception blocks from measured error models, scripts/evaluate.py
--perception, and scripts/perception_gap.py's comparison of two evaluations."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from mysim_jax.config.scene import load_config
from mysim_jax.config.env import PerceptionConfig
from mysim_jax.tasks.perception_gap import GapError, compare_evaluations, perception_block
from mysim_jax.tasks.sweep import paired_difference_interval

from conftest import CONFIGS, ROOT, only_array_ops, run_script_main

GAP = ROOT / "scripts" / "perception_gap.py"
SMALL = ["net.knots=3", "net.tethers.n_masses=1", "sim.t_end=0.4", "sim.precision=float32",
         "output.plot=[target,uav0]"]


def fit(sigma, tau):
    return {"dt_s": 0.05, "axes": [], "pooled": {"sigma": sigma, "rho": 0.0, "correlation_time_s": tau}}


def model(p, v):
    return {"position_m": fit(*p), "velocity_m_s": fit(*v)}


def test_perception_block_combines_uavs_and_validates():
    block = perception_block([model((0.03, 8.0), (0.03, 0.05)), model((0.04, 4.0), (0.01, 0.07))],
                             model((0.2, 0.5), (0.3, 0.2)))
    assert block["uav_position"] == {"sigma": pytest.approx(np.sqrt((0.03 ** 2 + 0.04 ** 2) / 2)),
                                     "correlation_time": pytest.approx(6.0)}
    assert block["target_velocity"] == {"sigma": 0.3, "correlation_time": 0.2}
    assert PerceptionConfig(**block).uav_velocity.correlation_time == pytest.approx(0.06)
    with pytest.raises(GapError, match="no 'velocity_m_s' fit"):
        perception_block([{"position_m": fit(0.1, 1.0)}], model((0.2, 0.5), (0.3, 0.2)))
    with pytest.raises(GapError, match="infinite correlation time"):
        perception_block([model((0.03, float("inf")), (0.03, 0.05))], model((0.2, 0.5), (0.3, 0.2)))


def write_eval(folder, success, perception=None, **meta):
    folder.mkdir(parents=True)
    n = len(success)
    metrics = {"scene": "s", "policy": "p", "episodes": n, "batch": n, "seed": 0, "perception": perception, **meta}
    (folder / "metrics.json").write_text(json.dumps(metrics))
    with (folder / "episodes.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", "slot", "success"])
        for episode in np.random.default_rng(0).permutation(n):          # any row order, any slot
            w.writerow([episode, episode % 7, int(success[episode])])


def test_compare_pairs_the_episodes_by_number(tmp_path):
    rng = np.random.default_rng(3)
    a = rng.random(400) < 0.9
    b = a & (rng.random(400) < 0.95)
    write_eval(tmp_path / "true", a)
    write_eval(tmp_path / "perceived", b, perception={"uav_position": {"sigma": 0.1}})
    res = compare_evaluations(tmp_path / "true", tmp_path / "perceived")
    d, lo, hi = paired_difference_interval(a, b)
    assert res["true_states"]["count"] == a.sum() and res["perceived_states"]["count"] == b.sum()
    assert res["gap"]["points"] == pytest.approx(100 * d) and res["gap"]["interval95_points"] == pytest.approx(
        [100 * lo, 100 * hi])
    assert res["gap"]["caught_only_on_true"] == int(np.sum(a & ~b)) and res["gap"]["caught_only_on_perceived"] == 0
    out = tmp_path / "gap.json"
    proc = subprocess.run([sys.executable, str(GAP), "compare", str(tmp_path / "true"), str(tmp_path / "perceived"),
                           "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert "gap: +" in proc.stdout and json.loads(out.read_text())["episodes"] == 400


@pytest.mark.parametrize("case, message", [
    ({"seed": 1}, "differ in seed"),
    ({"policy": "q"}, "differ in policy"),
    ({"perception": None}, "evaluated on true states; the second folder must use --perception"),
])
def test_compare_refuses_evaluations_of_different_episodes(tmp_path, case, message):
    write_eval(tmp_path / "true", np.ones(40, bool))
    perception = case.pop("perception", {"uav_position": {"sigma": 0.1}})
    write_eval(tmp_path / "perceived", np.ones(40, bool), perception=perception, **case)
    with pytest.raises(GapError, match=message):
        compare_evaluations(tmp_path / "true", tmp_path / "perceived")


def test_fit_writes_a_block_that_evaluate_accepts(tmp_path):
    paths = []
    for i, m in enumerate((model((0.03, 8.0), (0.03, 0.05)), model((0.2, 0.5), (0.3, 0.2)))):
        paths.append(tmp_path / f"m{i}.json")
        paths[-1].write_text(json.dumps({"error_model": m}))
    out = tmp_path / "perception.yaml"
    proc = subprocess.run([sys.executable, str(GAP), "fit", "--uav", str(paths[0]), "--target", str(paths[1]),
                           "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    block = yaml.safe_load(out.read_text())
    config = load_config(CONFIGS / "capture_falling.yaml", SMALL + ["env.perception=" + json.dumps(block)])
    assert config.env.perception.target_position.sigma == pytest.approx(0.2)
    bad = subprocess.run([sys.executable, str(GAP), "fit", "--uav", str(tmp_path / "none.json"), "--target",
                          str(paths[1]), "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "none.json: no such file" in bad.stderr


@pytest.mark.parametrize("content, message", [
    (None, "no such file"),
    ("[1, 2]", "expected a mapping"),
    ("uav_position: {sigma: -1}", "env.perception.uav_position.sigma"),
    ("uav_positon: {sigma: 0.1}", "uav_positon"),
])
def test_evaluate_rejects_a_bad_perception_file_before_compiling(tmp_path, capsys, content, message):
    """evaluate.py's main() in this process (conftest.run_script_main)."""
    path = tmp_path / "perception.yaml"
    if content is not None:
        path.write_text(content)
    sets = [a for s in SMALL for a in ("--set", s)]
    code, _, err, compiled = run_script_main("evaluate", [CONFIGS / "capture_falling.yaml", "--policy", "scripted",
                                                          "--episodes", 2, "--out", tmp_path / "out", "--perception",
                                                          path, *sets], capsys)
    assert code == 2 and message in err, err
    assert only_array_ops(compiled)
    assert not (tmp_path / "out").exists()
