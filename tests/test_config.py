"""Bad input gets a clear error naming the field, before anything compiles."""

import dataclasses
import re

import jax
import numpy as np
import pytest
import yaml

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict, dump_config, load_config
from mysim_jax.dynamics.stability import NETWORK_STEP_SAFETY, scene_network_stable_step
from mysim_jax.sim import rollout

from conftest import CONFIGS, scene_files


def _raw():
    return yaml.safe_load((CONFIGS / "rope_net.yaml").read_text())


def _err(raw=None, overrides=(), build_too=False):
    raw = _raw() if raw is None else raw
    with pytest.raises(ConfigError) as info:
        cfg = config_from_dict(raw, "scene.yaml", list(overrides))
        if build_too:
            with jax.enable_x64(True):
                build(cfg)
    return str(info.value)


def test_all_configs_load_and_round_trip():
    """Every scene file (training files, configs/train_*.yaml and detector.yaml, are other
    kinds: their tests are in test_mappo.py and test_detector.py)."""
    for path in scene_files():
        cfg = load_config(path)
        again = config_from_dict(yaml.safe_load(dump_config(cfg)), "dumped")
        assert again == cfg, path.name


def test_unknown_key_is_named():
    msg = _err(overrides=["sim.dtt=1e-4"])
    assert "sim.dtt: unknown key" in msg
    raw = _raw()
    raw["ropes"][2]["stiffnes"] = 3
    assert "ropes.2.stiffnes: unknown key" in _err(raw)


def test_wrong_type_and_shape():
    assert "sim.dt" in _err(overrides=["sim.dt=fast"])
    raw = _raw()
    raw["points"][0]["pos"] = [0.0, 0.0]
    msg = _err(raw)
    assert "points.0.pos" in msg
    assert "sim.integrator" in _err(overrides=["sim.integrator=euler"])
    assert "sim.precision" in _err(overrides=["sim.precision=float16"])


@pytest.mark.parametrize(
    "override, field",
    [
        ("points.0.mass=-0.2", "points.0.mass"),
        ("points.0.mass=0", "points.0.mass"),
        ("ropes.1.length=0", "ropes.1.length"),
        ("ropes.1.EA=-1e5", "ropes.1.EA"),
        ("ropes.3.mass=-1", "ropes.3.mass"),
        ("ropes.0.n_masses=-1", "ropes.0.n_masses"),
        ("ropes.0.damping=-1", "ropes.0.damping"),
        ("sim.dt=-1e-4", "sim.dt"),
        ("sim.t_end=0", "sim.t_end"),
    ],
)
def test_non_positive_physical_values(override, field):
    assert field in _err(overrides=[override])


def test_step_above_stability_limit_names_dt_and_spring():
    msg = _err(overrides=["sim.integrator=semi_implicit_euler", "sim.dt=1e-3"], build_too=True)
    # the network limit is NETWORK_STEP_SAFETY x the bound (1.37e-4 s), so 1e-3 s needs 9 sub-steps
    assert "sim.dt" in msg and "stability limit" in msg and "r0[0]" in msg and "substeps >= 9" in msg
    # substeps fix it (8 do not); the adaptive solvers have no explicit limit
    assert "substeps >= 9" in _err(overrides=["sim.integrator=semi_implicit_euler", "sim.dt=1e-3", "sim.substeps=8"],
                                   build_too=True)
    for ov in (["sim.substeps=9"], ["sim.integrator=tsit5"]):
        with jax.enable_x64(True):
            build(config_from_dict(_raw(), "x", ["sim.integrator=semi_implicit_euler", "sim.dt=1e-3"] + ov))


def _network_limit(overrides):
    """The largest step the config check accepts on the rope net (parsed from its error)."""
    msg = _err(overrides=["sim.integrator=semi_implicit_euler", "sim.dt=1", "sim.output_dt=1"] + overrides,
               build_too=True)
    return float(re.search(r"spring network .* is stable only below ([0-9.e+-]+) s", msg).group(1))


def _network_limits(cfg):
    """``(accepted, initial)``: the largest step the check accepts, and the network limit with
    each spring acting only along its initial direction (what the check used to accept)."""
    scene, params, state = build(cfg)
    p = jax.tree.map(lambda x: np.asarray(x, float), params)
    args = (scene.integrator, scene, p.point_mass, p.body_mass, p.body_inertia, p.marker_pos,
            p.spring_stiffness, p.spring_damping)
    node_pos = np.concatenate([np.asarray(state.phys.point_pos, float), p.anchor_pos])   # no bodies here
    return (NETWORK_STEP_SAFETY * scene_network_stable_step(*args)[0],
            scene_network_stable_step(*args, node_pos=node_pos)[0])


@pytest.mark.float64
@pytest.mark.parametrize("ea", [1e5, 4e5])
def test_network_stability_limit_brackets_the_measured_blow_up(ea):
    """The check's limit sits below the blow-up, the initial-geometry estimate does not: a
    run perturbed off the symmetric plane (so every mode is excited) stays bounded at the
    largest accepted step and blows up at 1.1x the initial-geometry estimate, which the
    check rejects. (Randomised float32 batches: docs/stability.md.)"""
    ropes = [f"ropes.{i}.EA={ea:g}" for i in range(4)]
    base = ["sim.integrator=semi_implicit_euler", "sim.precision=float64"] + ropes

    def cfg(dt):   # about 1 s, on the output grid
        return config_from_dict(_raw(), "x", base + [f"sim.dt={dt!r}", f"sim.output_dt={dt!r}",
                                                     f"sim.t_end={round(1 / dt) * dt!r}"])

    limit, initial = _network_limits(cfg(1e-6))
    assert limit == pytest.approx(_network_limit(ropes), rel=5e-3)     # what the error message says
    assert initial > 1.2 * limit
    big = 1.1 * initial
    assert "spring network" in _err(overrides=base + [f"sim.dt={big!r}", f"sim.output_dt={big!r}",
                                                      f"sim.t_end={round(1 / big) * big!r}"], build_too=True)
    rng = np.random.default_rng(0)
    finite = {}
    for name, dt in (("accepted", limit), ("1.1x initial", 1.1 * initial)):
        # Scene.dt is static and the check is build-time only: build at the accepted step, step at dt
        scene, params, state = build(cfg(limit))
        scene = dataclasses.replace(scene, dt=dt)
        pos = state.phys.point_pos + 1e-6 * rng.standard_normal(state.phys.point_pos.shape)
        state = state.replace(phys=state.phys.replace(point_pos=pos))
        final, _ = jax.jit(lambda s: rollout(scene, params, s, int(1.0 / dt), int(1.0 / dt)))(state)
        finite[name] = bool(np.isfinite(np.asarray(final.phys.point_pos)).all()
                            and np.abs(np.asarray(final.phys.point_pos)).max() < 10.0)
    assert finite == {"accepted": True, "1.1x initial": False}, (limit, initial, finite)


def test_stability_limit_tracks_the_spring_constants():
    # ten times stiffer ropes: 1e-4 s is no longer stable for semi-implicit Euler
    ov = ["sim.integrator=semi_implicit_euler"] + [f"ropes.{i}.EA=1e7" for i in range(4)]
    assert "stability limit" in _err(overrides=ov, build_too=True)
    # with damping off the limit is 2/ω_max: four times the stiffness halves it
    soft = _network_limit([f"ropes.{i}.damping=0" for i in range(4)])
    stiff = _network_limit([f"ropes.{i}.damping=0" for i in range(4)] + [f"ropes.{i}.EA=4e5" for i in range(4)])
    assert stiff == pytest.approx(0.5 * soft, rel=5e-3)   # the message prints 3 digits
    # and the check's limit is NETWORK_STEP_SAFETY of 2/ω_max, ω_max² the top eigenvalue of the
    # rope net's scalar Laplacian: computed here from the rope's segment constants
    assert soft == pytest.approx(NETWORK_STEP_SAFETY * 2.0 / np.sqrt(_rope_net_laplacian_top()), rel=5e-3)


def _rope_net_laplacian_top():
    """Top eigenvalue of M^-½ L M^-½ for the rope net (payload + four 5-mass ropes, EA 1e5)."""
    m, n, ea, length = 0.2, 5, 1e5, 1.0
    k_in, k_end = ea / (length / n), ea / (length / (2 * n))
    size = 1 + 4 * n
    lap = np.zeros((size, size))

    def spring(i, j, k):
        for a in (i, j):
            if a >= 0:
                lap[a, a] += k
        if i >= 0 and j >= 0:
            lap[i, j] -= k
            lap[j, i] -= k

    for r in range(4):
        chain = [0] + [1 + r * n + j for j in range(n)] + [-1]      # payload, masses, anchor
        for j in range(n + 1):
            spring(chain[j], chain[j + 1], k_end if j in (0, n) else k_in)
    return np.linalg.eigvalsh(lap / m)[-1]


def test_float32_adaptive_tolerances_below_round_off_are_rejected():
    msg = _err(overrides=["sim.precision=float32", "sim.integrator=tsit5", "sim.rtol=1e-5", "sim.atol=1e-8"])
    assert "sim" in msg and "atol = 1e-08" in msg and "float64" in msg
    assert "rtol" in _err(overrides=["sim.precision=float32", "sim.integrator=tsit5", "sim.rtol=1e-9",
                                     "sim.atol=1e-5"])
    config_from_dict(_raw(), "x", ["sim.precision=float32", "sim.integrator=tsit5", "sim.rtol=1e-5",
                                   "sim.atol=1e-5"])


def test_missing_references_are_named():
    raw = _raw()
    raw["ropes"][1]["end"] = "a9"
    msg = _err(raw)
    assert "ropes.1.end: 'a9'" in msg
    raw = _raw()
    raw["ropes"][0]["start"] = "uav3.hook"
    assert "no body named 'uav3'" in _err(raw)
    raw = _raw()
    raw["bodies"] = [{"name": "box", "mass": 1.0, "inertia": [1, 1, 1], "markers": [{"name": "top"}]}]
    raw["joints"] = [{"name": "j", "type": "fixed", "marker_i": "box.bottom", "marker_j": "a0"}]
    assert "joints.0.marker_i" in _err(raw) and "has no marker 'bottom'" in _err(raw)
    raw["joints"][0]["marker_i"] = "box.top"
    config_from_dict(raw, "ok")


def test_duplicate_names_and_bad_inertia():
    raw = _raw()
    raw["anchors"][1]["name"] = "a0"
    assert "already used" in _err(raw)
    raw = _raw()
    raw["bodies"] = [{"name": "rod", "mass": 1.0, "inertia": [1.0, 1.0, 3.0]}]
    assert "bodies.0.inertia" in _err(raw) and "triangle" in _err(raw)
    raw["bodies"][0]["inertia"] = [1.0, -1.0, 1.0]
    assert "bodies.0.inertia" in _err(raw)
    raw["bodies"][0]["inertia"] = [1.0, 1.0, 1.0]
    raw["bodies"][0]["quat"] = [0, 0, 0, 0]
    assert "bodies.0.quat" in _err(raw)


def test_output_grid_must_match_dt():
    assert "output_dt" in _err(overrides=["sim.output_dt=1.5e-4"])


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nsim: {dt: [1, \n")
    with pytest.raises(ConfigError, match="broken YAML"):
        load_config(bad)
    bad.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(bad)


def test_override_errors():
    with pytest.raises(ConfigError, match="expected key=value"):
        config_from_dict(_raw(), "x", ["sim.dt"])
    with pytest.raises(ConfigError, match="no entry 7"):
        config_from_dict(_raw(), "x", ["ropes.7.EA=1"])
    cfg = config_from_dict(_raw(), "x", ["ropes.2.EA=2e5", "gravity=[0, 0, -1.62]"])
    assert cfg.ropes[2].EA == 2e5 and cfg.gravity == (0, 0, -1.62)


def test_an_override_list_puts_its_parts_in_the_order_they_apply():
    """``override_list``: ``first`` (a profile, gains), then ``--set``, then ``level=``, then
    the program's own values (None left out); applied, a later entry wins on the same key."""
    from mysim_jax.config.overrides import apply_overrides, override_list

    assert override_list(["a=1"], first=["a=0", "b=0"], level="train", then={"c": 2, "d": None}) == [
        "a=0", "b=0", "a=1", "level=train", "c=2"]
    assert override_list() == [] and override_list(level="fast") == ["level=fast"]
    raw = {"a": {"x": 1}}
    assert apply_overrides(raw, override_list(["a.x=3"], first=["a.x=2", "a.y=2"])) == {"a": {"x": 3, "y": 2}}
    assert raw == {"a": {"x": 1}}


def test_float64_without_x64_is_a_clear_error():
    if jax.config.jax_enable_x64:
        pytest.skip("x64 is globally enabled in this process (JAX_ENABLE_X64); nothing to check")
    with pytest.raises(ConfigError, match="jax_enable_x64"):
        build(load_config(CONFIGS / "rope_net.yaml"))


def test_an_override_changes_only_the_place_it_names_even_through_a_yaml_anchor(tmp_path):
    """capture_env_falling.yaml gives all four quadrotors one controller through a YAML
    anchor (&ctrl / *ctrl): the parsed file shares one dict among them, and an override of
    quadrotors.0 must not reach quadrotors.1-3."""
    text = (CONFIGS / "capture_env_falling.yaml").read_text()
    assert "&ctrl" in text and "*ctrl" in text
    c = load_config(CONFIGS / "capture_env_falling.yaml", ["quadrotors.0.controller.max_speed=3.0"])
    assert [q.controller.max_speed for q in c.quadrotors] == [3.0, 10.0, 10.0, 10.0]
    # the team-wide mode check then names the quadrotors left behind
    with pytest.raises(ConfigError, match="quadrotors.1.controller.setpoint_mode"):
        load_config(CONFIGS / "capture_env_falling.yaml", ["quadrotors.0.controller.setpoint_mode=velocity"])
