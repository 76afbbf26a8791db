"""scripts/tune_pid.py and scripts/simulate.py on quadrotor scenes, end to end."""

import json
import subprocess
import sys

import numpy as np
import yaml

from mysim_jax.io.trajectory import read_trajectory_csv

from conftest import CONFIGS, ROOT


def _run(script, *args):
    return subprocess.run([sys.executable, str(ROOT / "scripts" / script), *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT)


def test_tune_then_simulate_with_the_tuned_gains(tmp_path):
    tune_dir, sim_dir = tmp_path / "tune", tmp_path / "sim"
    # plumbing, not physics: a lighter pipeline (first-order integrator, no attitude feed-forward) compiles faster
    light = ["--set", "sim.integrator=semi_implicit_euler", "--set", "quadrotors.0.controller.feedforward=acceleration"]
    res = _run("tune_pid.py", CONFIGS / "uav_track_small.yaml", "--out", tune_dir, "--iterations", "2",
               "--horizon", "0.2", "--set", "sim.t_end=0.3", "--no-progress", *light)
    assert res.returncode == 0, res.stderr
    for name in ("gains.yaml", "tuned_config.yaml", "loss_curve.png", "metrics.json", "config.yaml"):
        assert (tune_dir / name).is_file(), name
    metrics = json.loads((tune_dir / "metrics.json").read_text())
    assert len(metrics["tuned_gains"]) == 1 and metrics["iterations"] == 2
    before_after = metrics["evaluation"]["uav_track_small"]["uav0"]
    assert before_after["before"]["rms_position_error_m"] > 0
    gains = yaml.safe_load((tune_dir / "gains.yaml").read_text())["controller"]
    assert gains["position"]["kp"] != [0.4, 0.4, 1.25]          # the gains moved

    res = _run("simulate.py", CONFIGS / "uav_track_small.yaml", "--out", sim_dir, "--gains", tune_dir / "gains.yaml",
               "--set", "sim.t_end=1.0", "--no-progress", *light)
    assert res.returncode == 0, res.stderr
    resolved = yaml.safe_load((sim_dir / "config.yaml").read_text())["quadrotors"][0]["controller"]
    np.testing.assert_allclose(resolved["position"]["kp"], gains["position"]["kp"], rtol=1e-12)
    np.testing.assert_allclose(resolved["attitude"]["kd"], gains["attitude"]["kd"], rtol=1e-12)
    cols = read_trajectory_csv(sim_dir / "trajectory.csv")
    names = list(cols)
    assert names[1:17] == [f"uav0_{k}" for k in ("x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz",
                                                  "ax", "ay", "az", "wx", "wy", "wz")]
    assert {"uav0_ref_x", "uav0_ref_y", "uav0_ref_z", "uav0_ref_yaw", "uav0_rotor1", "uav0_rotor4"} <= set(names)
    assert len(cols["time"]) == 101
    err = np.linalg.norm(np.stack([cols[f"uav0_{a}"] - cols[f"uav0_ref_{a}"] for a in "xyz"], -1), axis=-1)
    tracking = json.loads((sim_dir / "metrics.json").read_text())["tracking"]["uav0"]
    np.testing.assert_allclose(tracking["rms_position_error_m"], np.sqrt(np.mean(err ** 2)), rtol=1e-6)
    np.testing.assert_allclose(tracking["max_position_error_m"], err.max(), rtol=1e-6)
    # the reference starts at the vehicle and moves 0.5 m-scale within the second
    assert cols["uav0_ref_x"][0] == 0.0 and np.ptp(cols["uav0_ref_x"]) > 0.05
    for png in ("uav0_path.png", "uav0_position.png"):
        assert (sim_dir / png).stat().st_size > 10_000


def test_scripts_reject_bad_input_before_compiling(tmp_path):
    res = _run("tune_pid.py", CONFIGS / "rope_net.yaml", "--out", tmp_path / "x")
    assert res.returncode == 2 and "no controlled quadrotor" in res.stderr
    res = _run("simulate.py", CONFIGS / "uav_track_small.yaml", "--out", tmp_path / "y", "--gains", tmp_path / "no.yaml")
    assert res.returncode == 2 and "no.yaml: no such gains file" in res.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("controller:\n  position: {kp: [1, 2], ki: [0, 0, 0], kd: [0, 0, 0]}\n"
                   "  attitude: {kp: [1, 1, 1], ki: [0, 0, 0], kd: [0, 0, 0]}\n")
    res = _run("simulate.py", CONFIGS / "uav_track_small.yaml", "--out", tmp_path / "z", "--gains", bad)
    assert res.returncode == 2 and "controller.position.kp" in res.stderr
    res = _run("simulate.py", CONFIGS / "uav_track_small.yaml", "--out", tmp_path / "w",
               "--set", "quadrotors.0.rotors.arm_length=[0.1, 0.1, -0.1, 0.1]")
    assert res.returncode == 2 and "quadrotors.0.rotors.arm_length.2" in res.stderr
    assert not any((tmp_path / d).exists() for d in ("x", "y", "z", "w"))
