"""Property-based fuzzing of training files (hypothesis, derandomised for CI).

Random edits of the shipped training files (``configs/train_*.yaml``, their profiles
included) go through what ``scripts/train.py`` does before it compiles anything
(:func:`mysim_jax.mappo.run.prepare`: the training file, its scene and its evaluation
scene, the output folder) and then :func:`~mysim_jax.mappo.run.describe_run`. The
property: either a :class:`ConfigError` whose message names the file and a field, or a
run that is ready to start (described in one line); never another exception. Starting
the run itself (compiling) is left out: that is ``tests/test_train_script.py``'s, once
per path.

Edits are those of ``tests/test_fuzz_config.py`` (values replaced by out-of-range
numbers, NaN, booleans, strings, None, lists and nests; keys deleted; unknown keys), on
any key of the training file, the ``--set`` overrides of its ``env:`` block and its
profiles included.
"""

from __future__ import annotations

import re

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mysim_jax.core.config_base import ConfigError
from mysim_jax.io.output import OutputError
from mysim_jax.mappo.run import describe_run, prepare

from conftest import CONFIGS
from yaml_edits import edit

FILES = {p.name: yaml.safe_load(p.read_text()) for p in sorted(CONFIGS.glob("train_*.yaml"))}
FUZZ = settings(derandomize=True, deadline=None, max_examples=120,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e308, -1e308, 1e13, 0.0, -1.0, 1e-300, 0.5, 2.0]),
    st.integers(min_value=-(2**70), max_value=2**70),
)
junk = st.one_of(
    numbers, st.booleans(), st.none(),
    st.sampled_from(["", "abc", "nan", "-inf", "1e400", "bc", "none", "full", "train", "trian",
                     "algo.lr=-1", "env.level=nope", "quadrotors.0.mass=0", "gone.yaml", "=", "a.b=c"]),
    st.text(max_size=12),
    st.lists(numbers, max_size=4),
    st.recursive(st.just(1.0), lambda inner: st.lists(inner, min_size=1, max_size=2), max_leaves=20),
    st.dictionaries(st.sampled_from(["lr", "every", "bogus", "episodes"]), numbers, max_size=2),
)


@st.composite
def edited_files(draw):
    name = draw(st.sampled_from(sorted(FILES)))
    raw = edit(draw, FILES[name], junk, ["bogus", "LR", "num_env", "eval_every"])
    profile = None
    if isinstance(raw, dict) and isinstance(raw.get("profiles"), dict) and raw["profiles"] and draw(st.booleans()):
        profile = draw(st.sampled_from(sorted(map(str, raw["profiles"]))))
    return name, raw, profile


# a field path as the messages write it: "algo.lr", "env.set.3", "run.selection.every", ...
FIELD = re.compile(r"\b[a-z_]+(\.[A-Za-z0-9_]+)+\b|\b(name|description|env|algo|run|profiles)\b")


@FUZZ
@given(edited_files())
def test_edited_training_files_are_refused_naming_a_field_or_ready_to_start(tmp_path_factory, case):
    name, raw, profile = case
    folder = tmp_path_factory.mktemp("fuzz_train")
    path = folder / name
    # the scene files are found beside the training file
    for scene in CONFIGS.glob("*.yaml"):
        if not scene.name.startswith("train_"):
            (folder / scene.name).write_bytes(scene.read_bytes())
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    try:
        prepared = prepare(str(path), [], str(folder / "run"), None, profile)
    except (ConfigError, OutputError) as err:
        text = str(err)
        assert text.strip() and "Traceback" not in text
        assert str(path) in text or FIELD.search(text), text
        return
    line = describe_run(prepared)
    assert line.strip() and "\n" not in line
    assert not (folder / "run").exists()                 # nothing written before the run starts


@pytest.mark.parametrize("name", sorted(FILES))
def test_the_shipped_training_files_are_ready_to_start(tmp_path, name):
    prepared = prepare(str(CONFIGS / name), [], str(tmp_path / "run"), None, None)
    assert describe_run(prepared).strip()
