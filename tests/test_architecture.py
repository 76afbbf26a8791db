"""The package's structure: its layers and cycles (import-linter, ``[tool.importlinter]`` in
pyproject.toml) and where imports may sit."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "mysim_jax"

# Imports that stay inside functions, each for the reason its line's comment (or its helper's
# docstring) gives: optional extras (bpy and the modules that ship with it, gtsam, plotly;
# mysim_jax/core/extras.py).
LAZY_IMPORTS = {
    ("io/blender_import.py", "bpy"), ("io/blender_import.py", "bmesh"), ("io/blender_import.py", "mathutils"),
    ("io/blender_import.py", "bpy_extras"),
    ("perception/imu_preintegration.py", "gtsam"),
    ("io/replay.py", "plotly"),
}


def test_the_layers_and_the_cycle_contract_hold():
    """Every module imports only from its layer or the layers below, and no package's modules
    import each other in a cycle (import-linter reads the contracts from pyproject.toml)."""
    res = subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports; "
                          "sys.exit(lint_imports(no_cache=True, no_logo=True))"],
                         cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "2 kept, 0 broken" in res.stdout, res.stdout[-2000:]


def _function_level_imports():
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for node in ast.walk(fn):
                    if isinstance(node, ast.Import):
                        yield path, node, node.names[0].name
                    elif isinstance(node, ast.ImportFrom):
                        yield path, node, node.module


def test_imports_sit_at_module_level_except_the_listed_lazy_ones():
    """An import inside a function hides a dependency from the layer check and from a reader;
    the few that stay (optional extras) are listed above and say why on their line or in
    their helper's docstring."""
    unexpected, unexplained = [], []
    for path, node, module in _function_level_imports():
        rel = path.relative_to(PACKAGE).as_posix()
        if (rel, module) not in LAZY_IMPORTS and (rel, module.split(".")[0]) not in LAZY_IMPORTS:
            unexpected.append(f"{rel}:{node.lineno} {module}")
            continue
        lines = path.read_text().splitlines()
        around = "\n".join(lines[max(node.lineno - 6, 0):node.lineno])
        if "#" not in around and '"""' not in around:
            unexplained.append(f"{rel}:{node.lineno} {module}")
    assert not unexpected, "imports inside functions (move them to the top of the module): " + ", ".join(unexpected)
    assert not unexplained, "lazy imports without a comment saying why: " + ", ".join(unexplained)


def test_no_function_is_longer_than_80_lines_without_saying_why():
    """Long functions mix concerns; one that is kept whole says why in its docstring
    ("Kept whole: ..."). Scripts count too: their logic belongs in the library."""
    long = []
    for path in sorted(PACKAGE.rglob("*.py")) + sorted((ROOT / "scripts").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > 80 and "kept whole" not in (ast.get_docstring(node) or "").lower():
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({length} lines)")
    assert not long, "functions over 80 lines: " + ", ".join(long)


def test_effect_data_is_reached_through_the_effects_typed_accessors():
    """No code spells an effect's name to index its parts (``params.effects["target"]``,
    ``dict(scene.effects)[...]``): it asks the effect (``TARGET.params(params)``,
    docs/effects.md), whose base class (core/effect.py) is the one place that indexes."""
    pattern = re.compile(r"\.effects\[|dict\([\w.]+\.effects\)\[|\.effects\.get\(")
    paths = [p for p in sorted(PACKAGE.rglob("*.py")) + sorted((ROOT / "scripts").glob("*.py"))
             if p != PACKAGE / "core" / "effect.py"]
    found = [f"{path.relative_to(ROOT)}:{i}" for path in paths
             for i, line in enumerate(path.read_text().splitlines(), 1) if pattern.search(line)]
    assert not found, "effect data indexed by name (use the effect's accessors): " + ", ".join(found)


def test_validating_the_scene_files_imports_no_jax():
    """The config layer is JAX-free: every scene file in configs/ (not the detector and
    training files, which have loaders of their own) validates, overrides and all, without
    importing JAX or any effect (the effect registry's library entries are paths, imported
    only for a file with an ``effects:`` block)."""
    scenes = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "configs").glob("*.yaml")
                    if not p.name.startswith(("detector", "train_")))
    code = ("import sys\n"
            "from mysim_jax.config.scene import load_config\n"
            f"for path in {scenes!r}:\n"
            "    load_config(path)\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'flax')"
            " or m.startswith('mysim_jax.effects') or m == 'mysim_jax.net.drag')\n"
            "assert not bad, bad\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert len(scenes) > 10 and res.returncode == 0, res.stderr[-2000:]
