"""Property-based fuzzing of configuration input (hypothesis, derandomised for CI).

The properties, over random edits of every shipped scene and random file contents:

* loading and building never raise anything but :class:`ConfigError` (no traceback),
  and the error names the source and at least one field or the file;
* whatever is accepted builds into finite arrays (masses, inertias, positions, spring
  constants, gains...) and an integration step of at least one sub-step;
* ``--set`` overrides, however malformed, end in the same two outcomes.

Edits replace a value anywhere in the scene (by path) with numbers out of range, NaN and
inf, booleans, strings, None, wrong shapes and deep nests; delete keys; add unknown
keys; or duplicate list entries (duplicate names). ``tests/test_bad_input.py`` holds the
hand-written corpus of the same categories through ``scripts/simulate.py``.
"""

from __future__ import annotations

import copy
import math

import jax
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, apply_override, config_from_dict, load_config

from conftest import CONFIGS
from yaml_edits import edit, yaml_paths

SCENES = {p.name: yaml.safe_load(p.read_text()) for p in sorted(CONFIGS.glob("*.yaml"))
          if not p.name.startswith("train_")}     # training files are not scenes
FUZZ = settings(derandomize=True, deadline=None, max_examples=250,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


PATHS = {name: yaml_paths(raw) for name, raw in SCENES.items()}

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e308, -1e308, 1e13, -1e13, 1e-300, 5e-324, 0.0, -0.0, -1.0, 1e12, 1e-12]),
    st.integers(min_value=-(2**70), max_value=2**70),
)
junk = st.one_of(
    numbers,
    st.booleans(),
    st.none(),
    st.sampled_from(["", "abc", "nan", "inf", "-inf", "1e400", "1e5", "auto", "ground", "r?_*", "a.b"]),
    st.text(max_size=12),
    st.lists(numbers, max_size=5),
    st.lists(st.booleans(), min_size=3, max_size=3),
    st.recursive(st.just(1.0), lambda inner: st.lists(inner, min_size=1, max_size=2), max_leaves=40),
    st.dictionaries(st.sampled_from(["name", "mass", "pos", "x", "bogus"]), numbers, max_size=3),
)


@st.composite
def edited_scenes(draw):
    name = draw(st.sampled_from(sorted(SCENES)))
    return name, edit(draw, SCENES[name], junk, ["bogus", "Mass", "ea", "t_stop"], duplicate=True)


def _assert_finite_build(config):
    with jax.enable_x64(config.sim.precision == "float64"):
        try:
            scene, params, state = build(config)
        except ConfigError as err:
            assert str(err).strip()
            return
    assert scene.substeps >= 1 and math.isfinite(scene.dt) and scene.dt > 0
    for leaf in jax.tree.leaves((params, state)):
        leaf = np.asarray(leaf)
        if leaf.dtype.kind == "f":
            assert np.isfinite(leaf).all(), "an accepted scene built a non-finite array"


@FUZZ
@given(edited_scenes())
def test_edited_scenes_are_rejected_clearly_or_build_finite(case):
    name, raw = case
    try:
        config = config_from_dict(raw, name)
    except ConfigError as err:
        text = str(err)
        assert text.startswith(name) and len(text.splitlines()) >= 1, text
        return
    _assert_finite_build(config)


@FUZZ
@given(st.sampled_from(sorted(SCENES)),
       st.lists(st.sampled_from([p for ps in PATHS.values() for p in ps]), min_size=1, max_size=2),
       st.lists(st.one_of(
           st.sampled_from(["1e308", "-1e308", "true", "no", "null", "[]", "{}", "[1, 2", "nan", ".inf", "'x'",
                            "[[[[[[]]]]]]", "1e-300", "0", "-1", "10000000000000", "{a: 1, a: 2}", "&a [*a]"]),
           st.text(max_size=10)), min_size=1, max_size=2))
def test_set_overrides_are_rejected_clearly_or_build_finite(name, paths, values):
    overrides = [".".join(map(str, p)) + "=" + v for p, v in zip(paths, values)]
    try:
        config = config_from_dict(SCENES[name], name, overrides)
    except ConfigError as err:
        assert str(err).strip()
        return
    _assert_finite_build(config)


@settings(derandomize=True, deadline=None, max_examples=150)
@given(st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode),
                 st.text(alphabet="{}[]:,-&*!|>'\"\n #ab1.", max_size=120).map(str.encode)))
def test_arbitrary_file_contents_are_rejected_clearly(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("fuzz") / "scene.yaml"
    path.write_bytes(data)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_apply_override_never_raises_other_errors():
    raw = copy.deepcopy(SCENES["rope_net.yaml"])
    for bad in ["", "=", "sim.t_end", ".=1", "points.9.mass=1", "points.x.mass=1", "sim.t_end.x=1",
                "ropes.0.EA.1=2", "name.x=1"]:
        with pytest.raises(ConfigError):
            apply_override(raw, bad)
