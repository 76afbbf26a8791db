"""The ``contact:`` block: bad input is a clear error naming the field (before anything
compiles), the paper scenes get exactly the pairs the issue asks for, and the stability
estimate covers contact stiffness (``substeps: auto`` or a named error)."""

import jax
import pytest
import yaml

from mysim_jax.build import AUTO_SUBSTEP_SAFETY, build
from mysim_jax.config.scene import ConfigError, config_from_dict, load_config
from mysim_jax.dynamics.stability import stable_step
from mysim_jax.sim import force_stages

from conftest import CONFIGS


# The collision scenes default to tsit5 at float64 tolerances; float32 needs tolerances it
# can resolve (config.py rejects rtol/atol below 1e-6 in float32).
FLOAT32 = ["sim.precision=float32", "sim.rtol=1e-5", "sim.atol=1e-5"]


def _raw(name="collision_light"):
    return yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())


def _err(raw=None, overrides=(), build_too=False):
    raw = _raw() if raw is None else raw
    with pytest.raises(ConfigError) as info:
        cfg = config_from_dict(raw, "scene.yaml", list(overrides))
        if build_too:
            with jax.enable_x64(True):
                build(cfg)
    return str(info.value)


@pytest.mark.parametrize(
    "override, field",
    [
        ("contact.groups.0.radius=-0.03", "contact.groups.0.radius"),
        ("contact.groups.2.radius=0", "contact.groups.2.radius"),
        ("contact.stiffness=-1e8", "contact.stiffness"),
        ("contact.damping=-1", "contact.damping"),
        ("contact.damping_depth=0", "contact.damping_depth"),
        ("contact.exponent=0.5", "contact.exponent"),
        ("contact.friction.mu_static=-0.1", "contact.friction.mu_static"),
        ("contact.friction.v_static=0", "contact.friction.v_static"),
        ("contact.smoothing.depth=0", "contact.smoothing.depth"),
        ("contact.model=soft", "contact.model"),
        ("contact.stifness=1e8", "contact.stifness"),
    ],
)
def test_bad_contact_values_name_the_field(override, field):
    assert field in _err(overrides=[override])


def test_bad_contact_references_name_the_field():
    raw = _raw()
    raw["contact"]["pairs"][1] = ["ball", "nett"]
    msg = _err(raw)
    assert "contact.pairs.1.1: unknown contact group 'nett'" in msg
    raw = _raw()
    raw["contact"]["groups"][2]["members"] = ["r?_*", "rope9_*"]
    assert "contact.groups.2.members.1: 'rope9_*' matches no point mass" in _err(raw)
    raw = _raw()
    raw["contact"]["groups"][1]["members"] = ["a0"]
    assert "contact.groups.1.members.0: 'a0' is an anchor" in _err(raw)
    raw = _raw()
    raw["contact"]["groups"].append({"name": "big", "members": ["payload"], "radius": 0.1})
    assert "contact.groups.3.radius: 'payload' already has a sphere of radius 0.03" in _err(raw)
    raw = _raw()
    raw["contact"]["groups"][0]["name"] = "ground"
    assert "contact.groups.0.name: 'ground' is reserved" in _err(raw)
    raw = _raw()
    raw["contact"]["friction"]["v_dynamic"] = 0.005
    assert "v_dynamic" in _err(raw)


def test_paper_scenes_have_exactly_the_requested_pairs():
    for name in ("collision_light", "collision_heavy"):
        cfg = load_config(CONFIGS / f"{name}.yaml", FLOAT32)
        scene, params, _ = build(cfg)
        cs = scene.contact
        pairs = {frozenset(p.split("|")) for p in cs.pair_names()}
        rope_masses = {f"r{i}_{j}" for i in range(4) for j in range(5)}
        assert pairs == {frozenset(("ball", "payload"))} | {frozenset(("ball", m)) for m in rope_masses}
        assert cs.n_ground == 0 and cs.friction and cs.model == "sharp"
        assert set(cs.sphere_names) == {"ball", "payload"} | rope_masses
        assert all(abs(float(r) - 0.03) < 1e-9 for r in params.contact.radius)
        assert [n for n, _ in force_stages(scene)] == ["spring_forces", "contact_forces"]
        masses = dict(zip(scene.point_names, params.point_mass.tolist()))
        expected = (0.2, 0.2) if name.endswith("light") else (10.0, 20.0)
        assert (masses["payload"], masses["ball"]) == pytest.approx(expected, rel=1e-6)
    # the rope net without a contact block traces no contact code
    scene, _, _ = build(load_config(CONFIGS / "rope_net.yaml", ["sim.precision=float32"]))
    assert scene.contact is None and "contact_forces" not in dict(force_stages(scene))


def test_ground_and_self_pairs():
    raw = _raw()
    raw["contact"]["groups"].append({"name": "all", "members": ["*"], "radius": 0.03})
    raw["contact"]["pairs"] = [["all", "ground"], ["net", "net"], ["ball", "payload"], ["payload", "ball"]]
    scene, _, _ = build(config_from_dict(raw, "t", FLOAT32))
    cs = scene.contact
    assert cs.n_ground == 22                      # every object touches the ground
    assert cs.n_pairs == 20 * 19 // 2 + 1         # rope masses pairwise once, ball-payload once


def test_fixed_step_above_the_contact_limit_is_named_and_auto_substeps_fix_it():
    ov = ["sim.integrator=semi_implicit_euler", "sim.substeps=10"]
    msg = _err(overrides=ov, build_too=True)
    assert "sim.dt" in msg and "contact 'payload|ball'" in msg and "k = 1e+08" in msg and "auto" in msg
    for integrator in ("semi_implicit_euler", "rk4"):
        with jax.enable_x64(True):
            scene, _, _ = build(load_config(CONFIGS / "collision_light.yaml",
                                            [f"sim.integrator={integrator}", "sim.substeps=auto"]))
        # the contact of two 0.2 kg spheres: omega² = k (1/m + 1/m), eta = c (1/m + 1/m)
        limit = stable_step(integrator, (1e8 * 10.0) ** 0.5, 1e4 * 10.0)
        assert scene.substep <= AUTO_SUBSTEP_SAFETY * limit < scene.dt / (scene.substeps - 1)
        assert 5e-6 < scene.substep < 2e-5            # "about 1e-5 s" (issue #3)
    with jax.enable_x64(True):
        scene, _, _ = build(load_config(CONFIGS / "collision_light.yaml"))   # adaptive default
    assert scene.substeps == 1 and scene.integrator == "tsit5"
