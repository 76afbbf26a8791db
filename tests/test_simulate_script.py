"""scripts/simulate.py end to end: outputs, columns, errors."""

import json
import subprocess
import sys

import numpy as np
import yaml

from mysim_jax.io.trajectory import read_trajectory_csv

from conftest import CONFIGS, ROOT, run_script_main

SCRIPT = ROOT / "scripts" / "simulate.py"


def _run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, cwd=ROOT)


def test_rope_net_outputs(tmp_path):
    out = tmp_path / "rope"
    res = _run(CONFIGS / "rope_net.yaml", "--out", out, "--set", "sim.t_end=0.1", "--no-progress")
    assert res.returncode == 0, res.stderr
    cols = read_trajectory_csv(out / "trajectory.csv")
    names = list(cols)
    assert names[:10] == ["time", "payload_x", "payload_y", "payload_z", "payload_vx", "payload_vy",
                          "payload_vz", "payload_ax", "payload_ay", "payload_az"]
    assert "r3_4_az" in cols and len(names) == 1 + 21 * 9
    np.testing.assert_allclose(np.diff(cols["time"]), 1e-3, atol=1e-12)
    assert len(cols["time"]) == 101
    # at t = 0 the ropes are straight and unloaded: everything falls at g
    np.testing.assert_allclose(cols["payload_az"][0], -9.81, atol=1e-9)
    for name in ("position", "velocity", "acceleration"):
        assert (out / f"payload_{name}.png").stat().st_size > 10_000
    resolved = yaml.safe_load((out / "config.yaml").read_text())
    assert resolved["sim"]["t_end"] == 0.1 and resolved["sim"]["integrator"] == "rk4"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_outputs"] == 101
    # the interactive replay, by default: one self-contained HTML file of the run
    replay = (out / "replay.html").read_text()
    assert "Plotly.newPlot" in replay and "Plotly.addFrames" in replay and "rope_net" in replay
    assert f"{out}/replay.html" in res.stdout


def test_no_replay(tmp_path):
    out = tmp_path / "rope"
    res = _run(CONFIGS / "rope_net.yaml", "--out", out, "--set", "sim.t_end=0.002", "--no-progress", "--no-replay")
    assert res.returncode == 0, res.stderr
    assert (out / "trajectory.csv").exists() and not (out / "replay.html").exists()
    assert "replay.html" not in res.stdout


def test_bad_input_exits_with_a_clear_message(tmp_path, capsys):
    """Input errors found before the scene is built run the script's main() in this process
    (conftest.run_script_main); the step too large for stability is found after the script
    has switched JAX to the float64 rope net's precision, so it runs in a child process."""
    code, _, err, _ = run_script_main("simulate", [CONFIGS / "rope_net.yaml", "--out", tmp_path / "x", "--set",
                                                   "points.0.mass=-1"], capsys)
    assert code == 2 and "points.0.mass" in err
    code, _, err, _ = run_script_main("simulate", [tmp_path / "nope.yaml", "--out", tmp_path / "x"], capsys)
    assert code == 2 and "no such config file" in err
    res = _run(CONFIGS / "rope_net.yaml", "--out", tmp_path / "y", "--set", "sim.integrator=semi_implicit_euler",
               "--set", "sim.dt=1e-3")
    assert res.returncode == 2 and "sim.dt" in res.stderr and "stability" in res.stderr
    assert not (tmp_path / "y").exists()   # nothing written, nothing compiled
