"""scripts/perceive.py: VIO on a run folder end to end, and bad input rejected before any work.

The run folders hold the analytic flight of tests/test_vio.py, written as
scripts/simulate.py writes a run (config.yaml of configs/uav_vio_flight.yaml,
trajectory.csv at 200 Hz), so no simulation is needed.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest

from mysim_jax.io.trajectory import read_trajectory_csv, write_trajectory_csv
from mysim_jax.perception.metrics import read_tum

from conftest import ROOT
from test_vio import write_synthetic_run

SCRIPT = ROOT / "scripts" / "perceive.py"


def _main(*args):
    """Run the script's main() in this process (fast: no interpreter start-up)."""
    spec = importlib.util.spec_from_file_location("perceive_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main([str(a) for a in args])


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("run")
    write_synthetic_run(path, 2.0)
    return path


def test_perceive_end_to_end(run_dir, tmp_path):
    """2 s of flight at 192 x 108: every output is written, the TUM files hold one pose
    per image, the metrics match the files, and VIO stays on the flight (measured ATE
    3.4 mm unaligned, 2.4 mm aligned)."""
    out = tmp_path / "perception"
    res = subprocess.run([sys.executable, str(SCRIPT), str(run_dir), "--out", str(out), "--size", "192x108",
                          "--no-progress"], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert "VIO: ATE" in res.stdout and "dead reckoning: ATE" in res.stdout
    for name in ("trajectory_vio.tum", "trajectory_dead_reckoning.tum", "trajectory_true.tum", "metrics.json",
                 "vio_frames.csv", "estimation_paths.png", "estimation_error.png", "vio_features.png",
                 "features.mp4"):
        assert (out / name).is_file() and (out / name).stat().st_size > 100, name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 41 and metrics["body"] == "uav0" and metrics["camera"] == "cam_fixed"
    assert len(metrics["snapshots"]) == 4 and all((out / s).is_file() for s in metrics["snapshots"])
    vio, true = read_tum(out / "trajectory_vio.tum"), read_tum(out / "trajectory_true.tum")
    assert len(vio) == len(true) == 41
    np.testing.assert_allclose(vio.t, np.arange(41) * 0.05, atol=1e-9)
    cols = read_trajectory_csv(run_dir / "trajectory.csv")
    np.testing.assert_allclose(true.p[:, 0], cols["uav0_x"][::10], atol=1e-8)
    err = np.linalg.norm(vio.p - true.p, axis=1)
    e = metrics["errors"]["vio"]
    assert e["ate_rmse_m"] == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-6, abs=1e-9)
    assert e["ate_rmse_m"] < 0.03 and e["ate_aligned_rmse_m"] < 0.03
    assert metrics["summary"]["distance_m"] == pytest.approx(e["distance_m"])
    assert "ground truth" in metrics["initial_state"]
    frames = np.loadtxt(out / "vio_frames.csv", delimiter=",", skiprows=1)
    assert frames.shape[0] == 41 and frames[:, 5].sum() == metrics["keyframes"]
    # the error model is fitted to the files' errors
    vel = np.loadtxt(out / "velocity_vio.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(vel[:, 4:], np.stack([cols[f"uav0_v{k}"][::10] for k in "xyz"], axis=1), atol=1e-8)
    model = metrics["error_model"]
    assert model["position_m"]["pooled"]["sigma"] == pytest.approx(np.sqrt(np.mean((vio.p - true.p) ** 2)), rel=1e-5)
    assert model["velocity_m_s"]["pooled"]["sigma"] == pytest.approx(np.sqrt(np.mean((vel[:, 1:4] - vel[:, 4:]) ** 2)),
                                                                     rel=1e-5)


def _expect_bad(capsys, out, *args, message):
    code = _main(*args, "--out", out, "--no-progress")
    err = capsys.readouterr().err
    assert code == 2, err
    for part in ([message] if isinstance(message, str) else message):
        assert part in err, err
    assert not out.exists()


def test_bad_inputs_exit_2_before_any_work(run_dir, tmp_path, capsys):
    out = tmp_path / "never"
    _expect_bad(capsys, out, tmp_path / "nowhere", message="no such run folder")
    _expect_bad(capsys, out, run_dir, "--size", "0x360", message="image width must be a whole number")
    _expect_bad(capsys, out, run_dir, "--body", "uav7", message=["'uav7' is not a quadrotor", "uav0"])
    _expect_bad(capsys, out, run_dir, "--camera", "cam_front", message=["'cam_front' is not in the run",
                                                                         "cam_fixed"])
    _expect_bad(capsys, out, run_dir, "--camera-rate", "30", message="whole multiple of the run's output interval")
    (tmp_path / "a_file").write_text("x")
    code = _main(run_dir, "--out", tmp_path / "a_file", "--no-progress")
    assert code == 2 and "not a folder" in capsys.readouterr().err


def test_missing_columns_are_named(run_dir, tmp_path, capsys):
    """A trajectory without the body's accelerations cannot feed the IMU: the error says
    which columns are missing and what they are for."""
    bad = tmp_path / "no_acc"
    bad.mkdir()
    (bad / "config.yaml").write_text((run_dir / "config.yaml").read_text())
    cols = read_trajectory_csv(run_dir / "trajectory.csv")
    write_trajectory_csv(bad / "trajectory.csv", {k: v for k, v in cols.items() if not k.startswith("uav0_a")})
    _expect_bad(capsys, tmp_path / "never", bad,
                message=["uav0_ax, uav0_ay, uav0_az", "simulating the IMU"])


def test_camera_looking_at_the_sky_is_rejected(tmp_path, capsys):
    """A camera pitched 50 deg up sees no ground."""
    up = tmp_path / "sky"
    write_synthetic_run(up, 1.0, camera_quat=(np.cos(np.radians(25)), 0.0, -np.sin(np.radians(25)), 0.0))
    _expect_bad(capsys, tmp_path / "never", up, message=["sees nothing of the ground", "Pitch the camera down"])


def test_t_end_estimates_a_run_up_to_before_its_camera_loses_the_ground(run_dir, tmp_path, capsys):
    """A run whose camera ends below the ground (a crash) is refused with a hint to end it
    earlier; ``--t-end`` before that estimates the rows up to it."""
    crash = tmp_path / "crash"
    crash.mkdir()
    (crash / "config.yaml").write_text((run_dir / "config.yaml").read_text())
    cols = read_trajectory_csv(run_dir / "trajectory.csv")
    cols["cam_fixed_z"] = np.where(cols["time"] > 1.2, -0.1, cols["cam_fixed_z"])
    write_trajectory_csv(crash / "trajectory.csv", cols)
    _expect_bad(capsys, tmp_path / "never", crash, message=["at or below the ground", "t = 1.25 s", "--t-end S"])
    _expect_bad(capsys, tmp_path / "never", crash, "--t-end", "0", message="must be after the run's start")
    out = tmp_path / "until"
    code = _main(crash, "--t-end", "1.0", "--out", out, "--size", "192x108", "--no-progress", "--no-video",
                 "--no-replay")
    assert code == 0, capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 21
    assert read_tum(out / "trajectory_vio.tum").t[-1] == pytest.approx(1.0)
