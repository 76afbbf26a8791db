"""Bad input through ``scripts/simulate.py``: every case is a clear error or a documented
acceptance, never a traceback, never exit 0 with non-finite output, never half-written.

A corpus of the input mistakes users make, one test per category: files that are not
UTF-8 YAML text (as the scene or as ``--gains``), YAML that nests or expands without
bound or repeats a key, unusable ``--out`` folders, numbers beyond the accepted range or
booleans where numbers belong, run lengths that do not fit the output grid, contact pairs
that list nothing, joints that cannot be solved, and runs that turn non-finite at run
time. The property-based half (random edits of every shipped scene) is in
``tests/test_fuzz_config.py``.

Input errors are checked in-process (``simulate.main``, exit code 2, before JAX is even
imported by the script); the two cases that run (exit code 3) use a subprocess, since a
float64 scene switches JAX to 64-bit mode for the rest of its process.
"""

from __future__ import annotations

import contextlib
import gzip
import importlib.util
import io
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from mysim_jax.io.trajectory import read_trajectory_csv

from conftest import CONFIGS, ROOT

SCRIPT = ROOT / "scripts" / "simulate.py"
ROPE = CONFIGS / "rope_net.yaml"
UAV = CONFIGS / "uav_track_small.yaml"


def _load_script():
    spec = importlib.util.spec_from_file_location("simulate_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


simulate_script = _load_script()


def _main(*args) -> tuple[int, str]:
    """Run ``simulate.py`` in-process; exit code and stderr. A traceback fails the test."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = simulate_script.main([str(a) for a in args])
    return code, err.getvalue()


def _rejected(tmp_path, *args, expect: str | tuple[str, ...]):
    """The run exits 2 with one error naming ``expect``, and writes nothing."""
    out = tmp_path / "out"
    before = set(os.listdir(tmp_path))
    code, err = _main(*args, "--out", out) if "--out" not in args else _main(*args)
    assert code == 2, err
    assert err.startswith("error: ") and "Traceback" not in err, err
    for text in (expect,) if isinstance(expect, str) else expect:
        assert text in err, err
    assert set(os.listdir(tmp_path)) == before, "an input error left files behind"


# --- files that are not UTF-8 YAML text -------------------------------------------------

def _bad_files(tmp_path):
    rope = ROPE.read_text()
    files = {
        "binary": (os.urandom(64) + b"\x00" + os.urandom(64), "binary data"),
        "utf16": (rope.encode("utf-16"), "UTF-16 text"),
        "utf32": (rope.encode("utf-32"), "UTF-32 text"),
        "latin1": ("name: café\n".encode("latin-1"), "not UTF-8 text (byte 0xe9"),
        "png": (b"\x89PNG\r\n\x1a\n" + bytes(range(1, 200)), "not UTF-8 text (byte 0x89"),
        "gzip": (gzip.compress(rope.encode()), "binary data"),
        "deep": (("a: " + "[" * 5000 + "]" * 5000 + "\n").encode(), "nested deeper than 64 levels"),
        "deep_map": (("a:\n" + "".join(" " * (i + 1) + "b:\n" for i in range(200))).encode(),
                     "nested deeper than 64 levels"),
        "alias_bomb": (("a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
            f"{k}: &{k} [{', '.join(['*' + p] * 10)}]\n" for p, k in zip("abcdefgh", "bcdefghi"))).encode(),
            "expands to more than 1,000,000 values"),
        "duplicate_key": ((rope + "\nsim: {t_end: 1, dt: 1.0e-4, output_dt: 1.0e-3}\n").encode(),
                          "found duplicate key 'sim'"),
        "broken": (b"name: [unclosed\n", "broken YAML"),
        "too_large": (b"# " + b"x" * (16 * 1024 * 1024 + 10) + b"\n", "too large"),
    }
    paths = {}
    for name, (data, expect) in files.items():
        path = tmp_path / f"{name}.yaml"
        path.write_bytes(data)
        paths[name] = (path, expect)
    return paths


def test_scene_files_that_are_not_utf8_yaml_text_are_named(tmp_path):
    files = tmp_path / "files"
    files.mkdir()
    for name, (path, expect) in _bad_files(files).items():
        _rejected(tmp_path, path, expect=(str(path), expect))
    _rejected(tmp_path, files, expect=(str(files), "is a directory, not a config file"))
    _rejected(tmp_path, "/dev/null", expect="/dev/null: is not a regular file")
    _rejected(tmp_path, tmp_path / "missing.yaml", expect="missing.yaml: no such config file")
    (files / "list.yaml").write_text("- 1\n- 2\n")
    _rejected(tmp_path, files / "list.yaml", expect="must be a YAML mapping")
    (files / "empty.yaml").write_text("")
    _rejected(tmp_path, files / "empty.yaml", expect="must be a YAML mapping")


def test_an_empty_scene_path_is_named_as_such(tmp_path):
    for empty in ("", "  "):
        _rejected(tmp_path, empty, expect="empty path given for the config file")


def test_a_value_of_the_wrong_form_is_named_by_its_path_and_the_forms_it_may_take(tmp_path):
    """An inertia is 3 numbers (the diagonal) or 3 x 3 numbers: the error says which form
    each problem was read as, with the path as written in the file."""
    code, err = _main(UAV, "--out", tmp_path / "o", "--set", "bodies.0.inertia=[1, 2]")
    assert code == 2
    assert "bodies.0.inertia (as 3 numbers): too few entries" in err
    assert "bodies.0.inertia (as 3 x 3 numbers): too few entries" in err
    assert "function-after" not in err and "tuple[" not in err
    code, err = _main(ROPE, "--out", tmp_path / "o", "--set", "sim.substeps=x")
    assert code == 2 and "sim.substeps (as int): " in err and "sim.substeps (as 'auto'): " in err
    assert "constrained-int" not in err


def test_gains_files_that_are_broken_are_named(tmp_path):
    files = tmp_path / "files"
    files.mkdir()
    bad = _bad_files(files)
    for name in ("binary", "utf16", "latin1", "deep", "duplicate_key", "broken"):
        path, expect = bad[name]
        _rejected(tmp_path, UAV, "--gains", path, expect=(str(path), "gains file", expect))
    _rejected(tmp_path, UAV, "--gains", files, expect=(str(files), "is a directory, not a gains file"))
    _rejected(tmp_path, UAV, "--gains", "/dev/null", expect="/dev/null: is not a regular file")
    (files / "scalar.yaml").write_text("3\n")
    _rejected(tmp_path, UAV, "--gains", files / "scalar.yaml", expect=("scalar.yaml", "YAML mapping"))
    (files / "bool.yaml").write_text("controller:\n  position: {kp: [1, 1, true], ki: [0, 0, 0], kd: [0, 0, 0]}\n"
                                     "  attitude: {kp: [1, 1, 1], ki: [0, 0, 0], kd: [0, 0, 0]}\n")
    _rejected(tmp_path, UAV, "--gains", files / "bool.yaml",
              expect=("bool.yaml: invalid gains file", "controller.position.kp.2", "boolean"))


# --- output folders -----------------------------------------------------------------------

def test_unusable_output_folders_are_refused_before_any_work(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    _rejected(tmp_path, ROPE, "--out", afile, expect="exists and is not a folder")
    _rejected(tmp_path, ROPE, "--out", "/dev/null", expect="exists and is not a folder")
    _rejected(tmp_path, ROPE, "--out", afile / "sub", expect="is an existing file, not a folder")
    _rejected(tmp_path, ROPE, "--out", tmp_path / ("x" * 300), expect="longer than the file system allows")
    _rejected(tmp_path, ROPE, "--out", "", expect="--out: empty path")
    _rejected(tmp_path, ROPE, "--out", "   ", expect="--out: empty path")
    # writable by their permission bits for root, yet no folder can be made there
    for special in ("/proc/x", "/sys/x"):
        _rejected(tmp_path, ROPE, "--out", special, expect="cannot make a folder in")


def test_an_unwritable_output_folder_is_refused(tmp_path, monkeypatch):
    """A folder without write permission. Root may write anywhere, so the permission is
    denied through ``os.access`` as the check sees it (and by chmod for other users)."""
    import mysim_jax.io.output as output

    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    real_access = os.access
    monkeypatch.setattr(output.os, "access",
                        lambda path, mode: False if os.fspath(path) == str(locked) else real_access(path, mode))
    try:
        _rejected(tmp_path, ROPE, "--out", locked / "run", expect="no permission to write into")
    finally:
        locked.chmod(0o700)


# --- values ---------------------------------------------------------------------------------

# (scene, override, what the error must name): numbers beyond the accepted range
BAD_VALUES = [
    (ROPE, "ropes.0.EA=1e308", "ropes.0.EA"),
    (ROPE, "points.0.pos=[1e308, 0, 0]", "points.0.pos.0"),
    (ROPE, "points.0.vel=[0, 0, -1e300]", "points.0.vel.2"),
    (ROPE, "gravity=[0, 0, -1e308]", "gravity.2"),
    (ROPE, "anchors.0.pos=[1e308, 0, 0]", "anchors.0.pos.0"),
    (ROPE, "sim.t_end=1e308", "sim.t_end"),
    (ROPE, "sim.dt=1e308", "sim.dt"),
    (ROPE, "sim.output_dt=1e308", "sim.output_dt"),
    (ROPE, "ropes.0.n_masses=1000000000000", "ropes.0.n_masses"),
    (ROPE, "ropes.1.damping=1e200", "ropes.1.damping"),
    (ROPE, "points.0.mass=1e-300", "points.0.mass"),
    (ROPE, "ropes.0.length=5e-324", "ropes.0.length"),
    (ROPE, "sim.max_steps=100000000000000", "sim.max_steps"),
    (ROPE, "sim.substeps=1000000000000", "sim.substeps"),
    (UAV, "quadrotors.0.rotors.omega_max=1e308", "quadrotors.0.rotors.omega_max"),
    (UAV, "bodies.0.inertia=[1e308, 1e308, 1e308]", "bodies.0.inertia"),
    (UAV, "bodies.0.inertia=[1e-300, 1e-300, 1e-300]", "bodies.0.inertia"),
    (UAV, "bodies.0.quat=[1e200, 0, 0, 0]", "bodies.0.quat.0"),
    (UAV, "quadrotors.0.controller.position.kp=[1e308, 1, 1]", "quadrotors.0.controller.position.kp.0"),
]
# booleans where numbers (or names) belong
BAD_VALUES += [(scene, override, (field, "boolean")) for scene, override, field in [
    (ROPE, "points.0.mass=true", "points.0.mass"),
    (ROPE, "points.0.mass=yes", "points.0.mass"),
    (ROPE, "ropes.0.n_masses=on", "ropes.0.n_masses"),
    (ROPE, "points.0.pos=[true, 0, 0]", "points.0.pos.0"),
    (ROPE, "sim.substeps=true", "sim.substeps"),
    (ROPE, "gravity=[0, 0, false]", "gravity.2"),
    (ROPE, "name=true", "name"),
    (UAV, "quadrotors.0.rotors.spin=[true, -1, 1, -1]", "quadrotors.0.rotors.spin.0"),
]]


@pytest.mark.parametrize("scene,override,expect", BAD_VALUES, ids=[f"{c.stem}:{o}" for c, o, _ in BAD_VALUES])
def test_bad_values_are_named(tmp_path, scene, override, expect):
    _rejected(tmp_path, scene, "--set", override, expect=expect)


GRID = [
    ("sim.t_end=5e-4", "shorter than one output interval"),
    ("sim.t_end=1.0005", "must be a whole multiple of output_dt"),
    ("sim.output_dt=1.5e-4", "must be a whole multiple of dt"),
    ("sim.output_dt=5e-5", "shorter than dt"),
    ("sim.t_end=1e6", "environment steps"),
]


@pytest.mark.parametrize("override,expect", GRID, ids=[g[0] for g in GRID])
def test_run_lengths_that_do_not_fit_the_output_grid(tmp_path, override, expect):
    _rejected(tmp_path, ROPE, "--set", override, expect=("sim", expect))


def test_an_adaptive_first_step_longer_than_the_run_is_refused(tmp_path):
    _rejected(tmp_path, ROPE, "--set", "sim.integrator=tsit5", "--set", "sim.dt=3", "--set", "sim.output_dt=3",
              expect=("sim", "t_end (2 s) is shorter than one output interval (3 s)"))


def test_a_run_too_large_to_save_is_refused(tmp_path):
    _rejected(tmp_path, ROPE, "--set", "sim.t_end=100000", "--set", "sim.output_dt=1.0e-3",
              "--set", "sim.dt=1.0e-3", "--set", "sim.integrator=tsit5",
              expect=("raise sim.output_dt or shorten sim.t_end",))


def test_an_output_interval_within_round_off_of_the_grid_runs_to_t_end(tmp_path):
    """Documented acceptance: ``output_dt`` within 1e-6 (relative) of a multiple of ``dt``
    is snapped to it, and the run still covers ``t_end`` exactly (it used to stop one
    output short)."""
    out = tmp_path / "out"
    code, err = _main(ROPE, "--out", out, "--set", "sim.t_end=0.02", "--set", "sim.output_dt=0.001000000001",
                      "--set", "sim.precision=float32", "--no-progress")
    assert code == 0, err
    cols = read_trajectory_csv(out / "trajectory.csv")
    assert len(cols["time"]) == 21 and cols["time"][-1] == pytest.approx(0.02, abs=1e-15)


# --- structure ----------------------------------------------------------------------------

def _collision_with(pairs, groups):
    raw = yaml.safe_load((CONFIGS / "collision_light.yaml").read_text())
    raw["contact"]["groups"] = groups
    raw["contact"]["pairs"] = pairs
    return raw


def test_contact_pairs_that_list_no_pair_are_named(tmp_path):
    path = tmp_path / "zero_pairs.yaml"
    path.write_text(yaml.safe_dump(_collision_with([["ball", "ball"]], [
        {"name": "ball", "members": ["ball"], "radius": 0.03}])))
    _rejected(tmp_path, path, expect=("contact.pairs.0", "lists no pair", "group 'ball' has 1 member"))
    path.write_text(yaml.safe_dump(_collision_with([["a", "b"]], [
        {"name": "a", "members": ["ball"], "radius": 0.03}, {"name": "b", "members": ["ball"], "radius": 0.03}])))
    _rejected(tmp_path, path, expect=("contact.pairs.0", "lists no pair"))


def _pendulum(joint_type, marker_quat):
    return {
        "name": "pendulum",
        "sim": {"t_end": 0.01, "dt": 1.0e-3, "output_dt": 1.0e-3, "integrator": "rk4"},
        "anchors": [{"name": "pivot", "pos": [0, 0, 0]}],
        "bodies": [{"name": "bob", "mass": 1.0, "inertia": [0.01, 0.01, 0.01], "pos": [0, 0, -0.5],
                    "markers": [{"name": "top", "pos": [0, 0, 0.5], "quat": marker_quat}]}],
        "joints": [{"name": "hinge", "type": joint_type, "marker_i": "pivot", "marker_j": "bob.top"}],
    }


def test_joints_that_cannot_be_solved_are_named(tmp_path):
    path = tmp_path / "joint.yaml"
    # universal joint: both z axes along world z (the frames must have perpendicular z axes)
    path.write_text(yaml.safe_dump(_pendulum("universal", [1, 0, 0, 0])))
    _rejected(tmp_path, path, expect=("joints.0 ('hinge')", "z axes", "parallel"))
    # the same joint assembled (marker turned 90 degrees about x) is accepted
    path.write_text(yaml.safe_dump(_pendulum("universal", [0.7071067811865476, 0.7071067811865476, 0, 0])))
    code, err = _main(path, "--out", tmp_path / "ok", "--no-progress")
    assert code == 0, err
    # fixed joint whose frames are a quarter turn apart about z: x_I . y_J = 1
    path.write_text(yaml.safe_dump(_pendulum("fixed", [0.7071067811865476, 0, 0, 0.7071067811865476])))
    _rejected(tmp_path, path, expect=("joints.0 ('hinge')", "singular configuration"))
    # two fixed joints between the same pair of frames: redundant rows
    raw = _pendulum("fixed", [1, 0, 0, 0])
    raw["joints"].append({"name": "again", "type": "fixed", "marker_i": "pivot", "marker_j": "bob.top"})
    path.write_text(yaml.safe_dump(raw))
    _rejected(tmp_path, path, expect=("'hinge'", "'again'", "more than once"))


def test_a_controlled_quadrotor_without_a_reference_or_a_team_is_refused(tmp_path):
    """Allowed by the schema (setpoints passed to step() drive it), but simulate.py would
    have nothing to fly: one line naming the field, before any work."""
    _rejected(tmp_path, UAV, "--set", "quadrotors.0.reference=null",
              expect=("quadrotors.0.reference: missing", "team: block"))


def test_joints_share_the_scene_names_and_are_refused_when_named_alike(tmp_path):
    path = tmp_path / "joint.yaml"
    raw = _pendulum("universal", [0.7071067811865476, 0.7071067811865476, 0, 0])
    raw["joints"].append(dict(raw["joints"][0]))                       # two joints 'hinge'
    path.write_text(yaml.safe_dump(raw))
    _rejected(tmp_path, path, expect="joints.1: name 'hinge' is already used by joints.0")
    raw = _pendulum("universal", [0.7071067811865476, 0.7071067811865476, 0, 0])
    raw["joints"][0]["name"] = "bob"                                   # a joint named like the body
    path.write_text(yaml.safe_dump(raw))
    _rejected(tmp_path, path, expect="joints.0: name 'bob' is already used by bodies.0")


# --- runs that turn non-finite -----------------------------------------------------------------

def _run_subprocess(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args), "--no-progress"],
                          capture_output=True, text=True, cwd=ROOT)


def test_a_run_that_turns_non_finite_stops_names_the_body_and_keeps_the_finite_part(tmp_path):
    """A body spun at 1e12 rad/s (accepted: every number is in range) overflows float32
    within a step; the run stops with exit code 3, says when and in which body, and OUT
    holds the finite rows with ``status: failed``."""
    out = tmp_path / "spin"
    res = _run_subprocess(UAV, "--out", out, "--set", "bodies.0.angvel=[1e12, 1e12, 1e12]", "--set", "sim.t_end=0.1")
    assert res.returncode == 3, res.stderr
    assert "Traceback" not in res.stderr
    assert "turned non-finite between t = 0 s and 0.01 s" in res.stderr and "body 'uav0'" in res.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "failed" and "uav0" in metrics["failure"]
    cols = read_trajectory_csv(out / "trajectory.csv")
    assert len(cols["time"]) == metrics["n_outputs"] == 1
    assert all(np.isfinite(v).all() for v in cols.values())


def test_an_adaptive_solve_that_runs_out_of_steps_says_so(tmp_path):
    out = tmp_path / "steps"
    res = _run_subprocess(CONFIGS / "collision_light.yaml", "--out", out, "--set", "sim.max_steps=100",
                          "--set", "sim.t_end=0.1")
    assert res.returncode == 3, res.stderr
    assert "Traceback" not in res.stderr
    assert "gave up after t = " in res.stderr and "raise sim.max_steps" in res.stderr
    cols = read_trajectory_csv(out / "trajectory.csv")
    assert 1 < len(cols["time"]) < 101 and all(np.isfinite(v).all() for v in cols.values())
    assert json.loads((out / "metrics.json").read_text())["status"] == "failed"


def test_a_solve_that_gives_up_on_its_first_interval_keeps_the_initial_row(tmp_path):
    """One solver step allowed: no output interval is reached, and OUT holds the t = 0 row
    (the initial state), as the message says. In-process: float32 keeps the process in
    32-bit mode."""
    out = tmp_path / "first"
    code, err = _main(CONFIGS / "collision_light.yaml", "--out", out, "--set", "sim.max_steps=1",
                      "--set", "sim.t_end=0.1", "--set", "sim.precision=float32", "--set", "sim.rtol=1e-5",
                      "--set", "sim.atol=1e-5", "--no-progress")
    assert code == 3 and "Traceback" not in err, err
    assert "gave up after t = 0 s" in err and "wrote the finite part" in err
    cols = read_trajectory_csv(out / "trajectory.csv")
    assert list(cols["time"]) == [0.0] and json.loads((out / "metrics.json").read_text())["n_outputs"] == 1
    from mysim_jax.config.scene import load_config

    ball = load_config(CONFIGS / "collision_light.yaml").points[1]                  # released at z = 0.5 m
    np.testing.assert_allclose([cols[f"{ball.name}_{a}"][0] for a in "xyz"], ball.pos, rtol=0, atol=1e-7)


def test_a_failed_run_leaves_nothing_half_written(tmp_path, monkeypatch):
    """Outputs go to a hidden temporary folder first: if writing fails half-way (here:
    the plot step raises), OUT does not appear and no temporary folder is left."""
    import mysim_jax.tasks.run_scene as run_scene

    def broken(*args, **kwargs):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(run_scene, "plot_kinematics", broken)
    with pytest.raises(OSError, match="disk full"):
        _main(ROPE, "--out", tmp_path / "run", "--set", "sim.t_end=0.01", "--set", "sim.precision=float32",
              "--no-progress")
    assert os.listdir(tmp_path) == []


def test_validating_every_shipped_scene_does_not_import_jax():
    """Config checks run before JAX is imported (scripts report bad input in a fraction of
    a second); a module that pulls JAX into the config path breaks that. Training files are
    checked with their scenes (``load_run_config``), and a run folder's metrics read."""
    code = ("import sys, glob, os\nfrom mysim_jax.config.scene import load_config\n"
            "from mysim_jax.mappo.run_files import load_run_config, read_metrics\n"
            "from mysim_jax.perception.detect.config import load_config as load_detector_config\n"
            "for f in sorted(glob.glob('configs/*.yaml')):\n"
            "    name = os.path.basename(f)\n"
            "    (load_run_config if name.startswith('train_') else\n"
            "     load_detector_config if name.startswith('detector') else load_config)(f)\n"
            "assert read_metrics('docs/train/falling')\n"
            "print('jax' in sys.modules)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "False"


def test_simulate_reports_an_infinite_state_and_keeps_no_non_finite_row():
    """Library use: ``simulate`` given a state holding inf (not NaN) stops at t = 0, names
    the point and the quantity, and returns no rows rather than rows with inf in them."""
    import jax.numpy as jnp

    from mysim_jax.build import build
    from mysim_jax.config.scene import load_config
    from mysim_jax.driver import simulate

    config = load_config(ROPE, ["sim.precision=float32", "sim.t_end=0.01"])
    scene, params, state = build(config)
    vel = state.phys.point_vel.at[3, 2].set(jnp.inf)
    traj = simulate(scene, params, state.replace(phys=state.phys.replace(point_vel=vel)), config.run_settings(),
                    progress=False)
    assert not traj.ok and "at t = 0 s" in traj.failure and "point 'r0_2' (vel)" in traj.failure
    assert len(traj.time) == 0 and traj.phys.point_pos.shape == (0, 21, 3) and traj.acc.point_acc.shape[0] == 0


def test_saved_outputs_larger_than_the_memory_are_refused_before_the_run():
    """simulate.py's check (before anything compiles): the saved outputs' estimate
    (rows x columns x (the scene's float size + 8 bytes of CSV column)) against the memory
    the machine has, naming the fields that size it."""
    from mysim_jax.config.scene import ConfigError, check_output_memory, load_config

    config = load_config(ROPE)
    rows, columns = config.output_size()
    assert rows == config.sim.n_outputs + 1
    n_points = len(config.points) + sum(r.n_masses for r in config.ropes)
    assert columns == 1 + 9 * n_points + 16 * len(config.bodies) + 8 * len(config.quadrotors)
    need = config.output_memory_bytes()
    assert need == rows * columns * {"float32": 4 + 8, "float64": 8 + 8}[config.sim.precision]
    check_output_memory(config, "rope_net.yaml", available=need)
    with pytest.raises(ConfigError, match=r"^rope_net.yaml: sim: the run's saved outputs need about .* rows of "
                                          r".* columns\); this machine has .* raise sim.output_dt or shorten sim.t_end$"):
        check_output_memory(config, "rope_net.yaml", available=need - 1)
