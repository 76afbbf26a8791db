"""Teams paired after the fact from kept evaluation folders (mysim_jax/tasks/pairing.py,
scripts/pair.py): the pairing reads the right outcomes, computes the paired difference on
them, and refuses folders whose episodes differ."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from mysim_jax.tasks.pairing import PairingError, pair_outcomes, read_outcomes

ROOT = Path(__file__).resolve().parents[1]


def _folder(path: Path, success, *, seed=7, env=None, compare=None, perception=None) -> Path:
    """A minimal scripts/evaluate.py folder: metrics.json, config.yaml, episodes.csv and,
    with ``compare``, the comparison files."""
    path.mkdir(parents=True)
    n = len(success)
    metrics = {"scene": "toy", "seed": seed, "episodes": n, "policy_dt": 0.1, "max_steps": 80,
               "policy": "runs/a/policy", "overrides": [], "perception": perception}
    (path / "metrics.json").write_text(json.dumps(metrics))
    env = {"randomize": {"target_mass": {"low": 0.2, "high": 0.4}}} if env is None else env
    (path / "config.yaml").write_text(yaml.safe_dump({"name": "toy", "env": {**env, "perception": perception}}))
    with (path / "episodes.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", "slot", "success"])
        for i in reversed(range(n)):        # row order is not episode order
            w.writerow([i, i % 3, int(success[i])])
    if compare is not None:
        (path / "comparison.json").write_text(json.dumps({"compare": "scripted"}))
        with (path / "comparison_episodes.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["episode", "outcome_policy", "outcome_compare"])
            for i in range(n):
                w.writerow([i, "success" if success[i] else "timeout", "success" if compare[i] else "target_ground"])
    return path


def test_pairing_counts_and_difference(tmp_path):
    """12 episodes: the first team catches 0-8, the second 3-11, the compare team 0-1. The
    counts are written out by hand; the interval is Newcombe's (Stat. Med. 1998, method 10),
    recomputed here from the Wilson intervals."""
    n = 12
    a = np.arange(n) < 9
    b = np.arange(n) >= 3
    c = np.arange(n) < 2
    first = _folder(tmp_path / "a", a)
    second = _folder(tmp_path / "b", b, compare=c, perception={"target_latency": 0.03})
    result = pair_outcomes([first, second, f"{second}:compare"])
    rows = result["teams"]
    assert [r["success"]["count"] for r in rows] == [9, 9, 2]
    assert rows[2]["team"] == "scripted" and rows[1]["perception"] and not rows[0]["perception"]
    d1, d2 = rows[1]["difference_first_minus_this"], rows[2]["difference_first_minus_this"]
    assert (d1["only_first"], d1["only_this"]) == (3, 3) and d1["points"] == 0.0
    assert (d2["only_first"], d2["only_this"]) == (7, 0) and math.isclose(d2["points"], 100 * 7 / 12)

    def wilson(k, m, z=1.96):
        p = k / m
        centre = (p + z * z / (2 * m)) / (1 + z * z / m)
        half = z * math.sqrt(p * (1 - p) / m + z * z / (4 * m * m)) / (1 + z * z / m)
        return centre - half, centre + half

    # a vs b: both 6, only a 3, only b 3, neither 0; phi = (6*0 - 9) / sqrt(9*3*9*3) = -1/3
    (l1, u1), (l2, u2) = wilson(9, 12), wilson(9, 12)
    phi = -9 / math.sqrt(9 * 3 * 9 * 3)
    p = 0.75
    low = -math.sqrt((p - l1) ** 2 - 2 * phi * (p - l1) * (u2 - p) + (u2 - p) ** 2)
    high = math.sqrt((u1 - p) ** 2 - 2 * phi * (u1 - p) * (p - l2) + (p - l2) ** 2)
    np.testing.assert_allclose(d1["interval95_points"], [100 * low, 100 * high], rtol=1e-12)


def test_folders_with_other_episodes_are_refused(tmp_path):
    a = np.ones(6, bool)
    base = _folder(tmp_path / "base", a)
    other_seed = _folder(tmp_path / "seed", a, seed=8)
    other_env = _folder(tmp_path / "env", a, env={"randomize": {"target_mass": {"low": 0.2, "high": 0.7}}})
    with pytest.raises(PairingError, match="differ in seed"):
        pair_outcomes([base, other_seed])
    with pytest.raises(PairingError, match=r"differ in env \(env.randomize\)"):
        pair_outcomes([base, other_env])
    with pytest.raises(PairingError, match="comparison_episodes.csv"):
        read_outcomes(f"{base}:compare")
    with pytest.raises(PairingError, match="no metrics.json"):
        read_outcomes(tmp_path / "missing")
    # the perception block may differ: it changes what the team sees, not the episodes
    assert pair_outcomes([base, _folder(tmp_path / "p", a, perception={"target_latency": 0.05})])
    # nor what the UAVs observe of their motors (tests/test_observe_top_thrust.py: the draws are the same)
    assert pair_outcomes([base, _folder(tmp_path / "m", a, env={**yaml.safe_load((base / "config.yaml").read_text())[
        "env"], "observe_top_thrust": True})])


def test_script_reproduces_the_kept_perception_gap_and_fails_cleanly(tmp_path):
    """On the kept full-level folders of the shipped evading team (docs/perception.md): the
    paired gap scripts/perception_gap.py compare gives, and a one-line error, exit 2, for
    folders of two scenes."""
    kept = ROOT / "docs/perception_gap"
    out = tmp_path / "pair.json"
    proc = subprocess.run([sys.executable, "scripts/pair.py", str(kept / "full_seed5961_true"),
                           str(kept / "full_seed5961_perceived"), f"{kept / 'full_seed5961_true'}:compare",
                           "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(out.read_text())["teams"]
    from mysim_jax.tasks.perception_gap import compare_evaluations

    gap = compare_evaluations(kept / "full_seed5961_true", kept / "full_seed5961_perceived")
    d = rows[1]["difference_first_minus_this"]
    assert d["points"] == pytest.approx(gap["gap"]["points"]) and d["interval95_points"] == pytest.approx(
        gap["gap"]["interval95_points"])
    assert rows[2]["success"]["count"] == json.loads(
        (kept / "full_seed5961_true/comparison.json").read_text())["success"]["compare"]["count"]
    bad = subprocess.run([sys.executable, "scripts/pair.py", str(kept / "full_seed5961_true"),
                          str(ROOT / "docs/robustness/falling_perceived_5963")],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "differ in scene" in bad.stderr
