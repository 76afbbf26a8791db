"""A light install: ``pip install -e .`` holds what simulation, the environment and training
need; perception, the HTML replay and the benchmark's references are extras
(``pyproject.toml``, ``mysim_jax/core/extras.py``). Importing the simulation and training
path imports none of them, and a missing extra is a one-line error naming what to install."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXTRA_MODULES = ("gtsam", "evo", "allantools", "plotly", "mujoco", "scipy", "bpy")

# makes importing the extras fail, as on a machine that installed only the base
BLOCK = f"""
import sys
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {EXTRA_MODULES!r}:
            raise ImportError(f"blocked by the test: {{name}}")
        return None
sys.meta_path.insert(0, _Block())
import importlib.util
_find = importlib.util.find_spec
importlib.util.find_spec = lambda name, *a: None if name.split(".")[0] in {EXTRA_MODULES!r} else _find(name, *a)
"""


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_base_dependencies_hold_no_extra():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    base = " ".join(project["dependencies"]).lower()
    for name in ("gtsam", "evo", "allantools", "plotly", "mujoco", "scipy", "bpy"):
        assert name not in base, f"{name} is a base dependency"
    extras = project["optional-dependencies"]
    assert {"perception", "plots", "gpu", "test", "bench", "blender"} <= set(extras)
    assert any("jax[cuda12]" in d for d in extras["gpu"])
    # the README's test command installs every extra the tests use
    readme = (ROOT / "README.md").read_text()
    command = readme.split("<!-- ci:test-command -->", 1)[1].split("```", 2)[1]
    for extra in ("test", "perception", "plots", "blender"):
        assert extra in command.split('-e ".[', 1)[1].split("]", 1)[0].split(","), extra


def test_the_simulation_and_training_path_imports_no_extra():
    """The modules scripts/simulate.py, train.py and evaluate.py use, imported with every
    extra blocked: they import, and none of the extras is loaded."""
    code = BLOCK + """
import importlib.util
for script in ("train", "evaluate", "simulate"):
    spec = importlib.util.spec_from_file_location(script, f"scripts/{script}.py")
    spec.loader.exec_module(importlib.util.module_from_spec(spec))
import mysim_jax.sim, mysim_jax.build, mysim_jax.tasks.capture, mysim_jax.tasks.evaluate, mysim_jax.tasks.report
import mysim_jax.tasks.run_scene, mysim_jax.tasks.pettingzoo_env, mysim_jax.mappo.run, mysim_jax.mappo.policies
import mysim_jax.tuning.gains
print(sorted(m for m in sys.modules if m.split(".")[0] in %r))
""" % (EXTRA_MODULES,)
    res = _run(code)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().splitlines()[-1] == "[]"


def test_a_missing_extra_says_what_to_install(tmp_path):
    code = BLOCK + f"""
import importlib.util
spec = importlib.util.spec_from_file_location("perceive", "scripts/perceive.py")
m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)
code = m.main(["--track", "configs/capture_falling_gimbals.yaml", "--out", {str(tmp_path / 'o')!r}])
from mysim_jax.core.extras import MissingExtra
from mysim_jax.io.replay import write_replay_html
try:
    write_replay_html({{}}, None, {str(tmp_path / 'r.html')!r})
except MissingExtra as err:
    print("replay:", err)
sys.exit(code)
"""
    res = _run(code)
    assert res.returncode == 2
    assert "scripts/perceive.py needs gtsam, evo, allantools, not installed: pip install -e '.[perception]'" \
        in res.stderr
    assert "replay: the HTML replay (replay.html) needs plotly, not installed: pip install -e '.[plots]'" \
        in res.stdout
    assert not (tmp_path / "o").exists() and not (tmp_path / "r.html").exists()
