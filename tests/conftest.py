"""Shared test setup.

Tests marked ``@pytest.mark.float64`` run inside ``jax.enable_x64(True)``; all others run
in JAX's default 32-bit mode, so the switch never leaks into float32 tests.

Compiled programs go to JAX's persistent compilation cache (a folder under the system's
temporary directory, shared by the pytest-xdist workers and the scripts the tests run as
subprocesses): many tests compile the same capture environment, and on this CPU a
compile takes longer than the test's own work. The scripts the tests start write every
program, however short its compile: each is a new process that would compile the same
few hundred small programs (array helpers, the reach task, the optimiser) again. The
pytest workers write only those over 1 s (JAX's default): their in-memory cache serves
their repeats, and writing thousands of small programs cost more than it saved (measured
on three small-program files, 86 s vs 95 s). JAX keys each entry by the program, the
compile options, the device and its own version, so a hit returns the program a compile
would. ``MYSIM_TEST_XLA_CACHE=off`` turns it off; another path moves it.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import jax
import pytest

# XLA's CPU code generator for the tests: its older LLVM emitters
# (``--xla_cpu_use_fusion_emitters=false``), not the MLIR fusion emitters XLA uses by
# default, and LLVM's optimisation level 1 instead of XLA's 2
# (``--xla_backend_optimization_level=1``). The suite's time is mostly XLA compiling, and
# both compile the same programs faster (docs/testing.md); the programs compute the same
# values to float round-off (the suite passes under both; ``scripts/bench.py --only j``
# compares the emitters' speed). The library itself keeps XLA's defaults, whose code runs
# faster. ``MYSIM_TEST_XLA_EMITTERS=default`` runs the suite with XLA's defaults. Set
# before any backend starts (XLA reads XLA_FLAGS then) and inherited by the scripts the
# tests start; a flag already in XLA_FLAGS is left as it is.
TEST_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=1")
if os.environ.get("MYSIM_TEST_XLA_EMITTERS", "older") != "default":
    _given = os.environ.get("XLA_FLAGS", "")
    _added = [f for f in TEST_XLA_FLAGS if f.split("=")[0] not in _given]
    os.environ["XLA_FLAGS"] = " ".join(f for f in (_given, *_added) if f)

_XLA_CACHE = os.environ.get("MYSIM_TEST_XLA_CACHE", str(Path(tempfile.gettempdir()) / "mysim_jax_test_xla_cache"))
if _XLA_CACHE != "off":
    # environment variables reach the scripts started as subprocesses (every program); the
    # config update covers this process, where jax is imported already (programs over 1 s)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _XLA_CACHE
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
# configs/ holds scene files and two other kinds: MAPPO training files (train_*.yaml) and
# the target detector's training file (detector*.yaml)
NOT_SCENES = ("train_", "detector")


def scene_files() -> list[Path]:
    """Every scene file in configs/, sorted."""
    return sorted(p for p in CONFIGS.glob("*.yaml") if not p.name.startswith(NOT_SCENES))


# The README runs the suite with pytest-xdist, ``--dist loadfile --no-loadscope-reorder``:
# each file runs on one worker, and files are handed out in collection order. Those that
# take longest go first (as measured with ``--durations=0`` on the 2-core machine), so that
# the workers finish together instead of one running a long file while the other idles.
# The order changes only scheduling; a file not listed runs after these, in name order.
LONGEST_FIRST = (
    "test_train_script.py",
    "test_evaluate_script.py",
    "test_capture_env.py",
    "test_capture_scene.py",
    "test_parallel.py",
    "test_batching.py",
    "test_bc.py",
    "test_mappo.py",
    "test_implicit_springs.py",
    "test_detector.py",
    "test_gradmap.py",
    "test_tune.py",
    "test_broad_phase.py",
    "test_stability.py",
    "test_tuning.py",
    "test_setpoint.py",
    "test_contact_hard_cases.py",
    "test_collision_scenes.py",
    "test_camera.py",
    "test_uav_scripts.py",
    "test_contact_capsules.py",
    "test_detector_refine.py",
    "test_joints.py",
    "test_contact_gradients.py",
    "test_capture_perception.py",
    "test_tethered_body.py",
    "test_bad_input.py",
    "test_rope_net_reference.py",
    "test_render.py",
    "test_capture_energy.py",
    "test_reward_ranking.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))     # stable: keeps each file's order


@pytest.fixture(autouse=True)
def _x64_for_marked_tests(request):
    if request.node.get_closest_marker("float64") is not None:
        with jax.enable_x64(True):
            yield
    else:
        yield


def sphere_extent(intr, R, p, centre, radius):
    """(u_min, v_min, u_max, v_max) px of a sphere's image, from 20000 points of its silhouette
    circle projected with ``mysim_jax.perception.camera.project`` (camera R, p; sphere centre, m)."""
    import numpy as np

    from mysim_jax.perception.camera import project

    c = centre - p
    D = np.linalg.norm(c)
    axis = c / D
    ring_centre = p + c * (1 - radius ** 2 / D ** 2)
    ring_radius = radius * np.sqrt(1 - radius ** 2 / D ** 2)
    e1 = np.cross(axis, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    phi = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    ring = ring_centre + ring_radius * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    uv, _ = project(intr, R, p, ring)
    return np.r_[uv.min(axis=0), uv.max(axis=0)]


# --- a script's main() in this process ---------------------------------------------------
# Starting an interpreter and importing JAX costs seconds, more than a script spends
# refusing bad input; the bad-input tests call the script's main() here instead and count
# the programs XLA compiled (or took from the cache) meanwhile, so "refused before anything
# compiles" is checked, not assumed.

_COMPILED: list[tuple[str, float]] = []


def _note_compile(event: str, duration: float, **kwargs) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _COMPILED.append((str(kwargs.get("fun_name")), duration))


jax.monitoring.register_event_duration_secs_listener(_note_compile)
_SCRIPTS: dict[str, object] = {}


def run_script_main(name: str, args, capsys) -> tuple[int, str, str, list[tuple[str, float]]]:
    """``scripts/NAME.py``'s ``main(args)`` in this process: its exit code (argparse's
    ``SystemExit`` too), what it printed to stdout and stderr, and the programs compiled
    while it ran (name, seconds)."""
    import importlib.util

    if name not in _SCRIPTS:
        spec = importlib.util.spec_from_file_location(f"_script_{name}", ROOT / "scripts" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        _SCRIPTS[name] = module
    capsys.readouterr()
    start, x64 = len(_COMPILED), jax.config.jax_enable_x64
    try:
        code = _SCRIPTS[name].main([str(a) for a in args])
    except SystemExit as exit_:
        code = exit_.code
    out, err = capsys.readouterr()
    # a script that switched JAX to 64 bits would leak the switch into the tests after it
    assert jax.config.jax_enable_x64 == x64, f"scripts/{name}.py {args}: changed jax_enable_x64 in the test process"
    return code, out, err, _COMPILED[start:]


def only_array_ops(compiled: list[tuple[str, float]]) -> bool:
    """True when what compiled is at most single array operations run eagerly (a type
    conversion, a random draw while a scene is built: milliseconds each), nothing of the
    simulation or the training: each of their programs takes seconds to compile."""
    return all(seconds < 0.5 for _, seconds in compiled)
