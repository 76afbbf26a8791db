"""Fidelity levels of a scene file (``levels:``, ``--set level=NAME``) and lines without
interior masses (``masses_per_edge: 0``, ``n_masses: 0``)."""

import numpy as np
import pytest
import yaml

from mysim_jax.config.scene import ConfigError, config_from_dict, dump_config, load_config

from conftest import CONFIGS

SCENE = CONFIGS / "capture_env_falling.yaml"



def net_mass(net) -> float:
    """Total mass [kg] of a net and its tethers from the ``net:`` block, re-derived here:
    2 G (G - 1) lines of one mesh spacing, G^2 knots, every tether's line."""
    g = net.knots
    total = 2 * g * (g - 1) * net.line.mass_per_length * net.spacing + g * g * net.knot_mass
    if net.tethers is not None:
        total += len(net.tethers.uavs) * net.tethers.line.mass_per_length * net.tethers.length
    return total

def test_a_level_applies_its_values_and_later_overrides_win():
    full = load_config(SCENE)
    train = load_config(SCENE, ["level=train"])
    assert full.level == "full" and train.level == "train"
    assert full.net.masses_per_edge == 1 and train.net.masses_per_edge == 0
    assert train.contact.friction is None and train.sim.dt == pytest.approx(4e-3)
    assert load_config(SCENE, ["contact.stiffness=400", "level=train"]).contact.stiffness == 400.0
    # the dump holds the resolved values and reloads as they are, under the level's name
    again = config_from_dict(yaml.safe_load(dump_config(train)))
    assert again.level == "train" and again.sim.dt == pytest.approx(4e-3) and again.net.masses_per_edge == 0
    assert list(again.levels) == ["train"] and again.levels["train"].set == []
    assert again.model_dump(exclude={"levels"}) == train.model_dump(exclude={"levels"})
    # a dump dumped again keeps one "(resolved: ...)" note
    assert dump_config(again) == dump_config(train)


def test_a_resolved_file_refuses_to_give_another_level(tmp_path):
    """A run folder's scene.yaml holds the level train's values as its own: asking it for
    the level full would run train's physics under full's name, so it is an error naming
    the files to use; its own level (asked for or not) still loads."""
    path = tmp_path / "scene.yaml"
    path.write_text(dump_config(load_config(SCENE, ["level=train"])))
    assert load_config(path).level == "train"
    assert load_config(path, ["level=train", "sim.t_end=3"]).sim.t_end == 3.0
    with pytest.raises(ConfigError, match=r"level=full: this file is resolved at the level 'train'.*scene_eval.yaml"):
        load_config(path, ["level=full"])
    # the committed run folders are marked the same way
    run = CONFIGS.parent / "docs" / "train" / "maneuvering"
    with pytest.raises(ConfigError, match="resolved at the level 'train'"):
        load_config(run / "scene.yaml", ["level=full"])
    assert load_config(run / "scene_eval.yaml").level == "full"
    # a malformed own level is left to the usual checks (here the override replaces it)
    raw = yaml.safe_load(path.read_text())
    raw["level"] = [1, 2]
    assert config_from_dict(raw, "scene", ["level=train"]).level == "train"


def test_unknown_or_broken_levels_are_named():
    with pytest.raises(ConfigError, match="unknown fidelity level 'trian'.*full, train"):
        load_config(SCENE, ["level=trian"])
    raw = yaml.safe_load(SCENE.read_text())
    raw["levels"]["train"]["set"].append("contact.stiffnes=3")
    with pytest.raises(ConfigError, match="(?s)levels.train.*stiffnes"):
        config_from_dict(raw, "scene")          # loading the full level still checks it
    raw = yaml.safe_load(SCENE.read_text())
    raw["levels"]["full"] = {"set": ["sim.dt=1e-3"]}
    with pytest.raises(ConfigError, match="levels.full"):
        config_from_dict(raw, "scene")
    raw = yaml.safe_load(SCENE.read_text())
    raw["levels"] = 1.0                         # not a mapping: named, not a TypeError
    with pytest.raises(ConfigError, match="scene: levels: expected a mapping"):
        config_from_dict(raw, "scene")
    with pytest.raises(ConfigError, match="scene: level: expected the name"):
        config_from_dict(yaml.safe_load(SCENE.read_text()), "scene", ["level=[1, 2]"])


def test_lines_without_interior_masses_keep_the_net_s_mass_and_size():
    from mysim_jax.build import build

    for level in ("full", "train"):
        cfg = load_config(SCENE, [f"level={level}"])
        scene, params, _ = build(cfg)
        net = [i for i, n in enumerate(scene.point_names) if n.startswith("net_")]
        assert np.sum(np.asarray(params.point_mass)[net]) == pytest.approx(
            net_mass(cfg.net) - 0.5 * len(cfg.net.tethers.uavs) * cfg.net.tethers.line.mass_per_length
            * cfg.net.tethers.length / (cfg.net.tethers.n_masses + 1),   # the UAV ends' halves
            rel=1e-6)
        lines = [k for k, n in enumerate(scene.spring_names) if n.startswith(("net_h", "net_v"))]
        assert np.sum(np.asarray(params.spring_rest_length)[lines]) == pytest.approx(
            2 * cfg.net.knots * (cfg.net.knots - 1) * cfg.net.spacing, rel=1e-6)
    train = load_config(SCENE, ["level=train"])
    assert build(train)[0].n_points == train.net.knots ** 2


def test_the_touch_check_sees_the_lines_as_the_level_s_contact_does():
    from mysim_jax.tasks.capture import make_env

    def line_radius(overrides):
        config = load_config(SCENE, overrides)
        return make_env(config)[0].line_radius, config

    r, full = line_radius([])
    assert r == pytest.approx(0.5 * full.net.line.diameter)
    r, train = line_radius(["level=train"])
    assert r == pytest.approx(train.contact.groups[3].radius) and r > 0.01
    # the pair written the other way round counts; a scene that pairs the target with no
    # line falls back to the half diameter
    assert line_radius(["level=train", "contact.pairs.0=[lines, target]"])[0] == pytest.approx(0.02)
    r, apart = line_radius(["level=train", "contact.pairs=[[target, uavs], [net, ground]]"])
    assert r == pytest.approx(0.5 * apart.net.line.diameter)
