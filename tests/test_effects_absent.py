"""A scene without an effect traces none of its work.

Every effect's work sits under a ``jax.named_scope`` named after it. For each effect, the
traced step of a scene that has it contains equations under its scope, and the traced
step of the same scene without it (one config change) contains none, and fewer
equations in all: the effect is left out when the step is composed, not switched off by
a traced flag or a zero coefficient. The time each effect costs in the capture scene is
measured in BENCHMARKS.md, section (e).
"""

from __future__ import annotations

import jax
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.sim import step
from mysim_jax.tasks.scripted import team_policy

CAPTURE = "configs/capture_env_falling.yaml"
HOVER = "configs/uav_hover.yaml"


def _walk(jaxpr, scopes: dict[str, int]) -> int:
    """Count equations (recursively) and the equations under every scope name."""
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for name in {part for part in str(eqn.source_info.name_stack).split("/") if part}:
            scopes[name] = scopes.get(name, 0) + 1
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    n += _walk(sub.jaxpr, scopes)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    n += _walk(sub, scopes)
    return n


def _traced(config: str, overrides: list[str]) -> tuple[int, dict[str, int]]:
    cfg = load_config(config, ["sim.precision=float32"] + overrides)
    scene, params, state = build(cfg)
    # capture scenes fly on the scripted team's setpoints, the others on their references
    policy = team_policy(cfg, scene) if cfg.team is not None else None
    jaxpr = jax.make_jaxpr(lambda s: step(scene, params, s, None if policy is None else policy(scene, params, s)))(state)
    scopes: dict[str, int] = {}
    return _walk(jaxpr.jaxpr, scopes), scopes


# (effect, its scope, config, overrides with the effect, overrides without it)
CASES = [
    ("contact", "contact_forces", CAPTURE, [], ["contact=null"]),
    ("friction", "friction", CAPTURE, [], ["contact.friction=null"]),
    ("line drag", "line_drag", CAPTURE, [],
     ["net.line.drag_coefficient=0", "net.tethers.line.drag_coefficient=0"]),
    ("tethers (springs on body markers)", "markers", CAPTURE, [], ["net.tethers=null"]),
    ("target propulsion", "target_propulsion", "configs/capture_env_maneuvering.yaml", [],
     ["target.entanglement=null", "target.behaviour=falling", "target.propulsion=null"]),
    ("target drag", "target_drag", CAPTURE, [], ["target.drag_coefficient=0"]),
    ("entanglement", "entanglement_update", "configs/capture_env_maneuvering.yaml", [],
     ["target.entanglement=null"]),
    ("motor lag", "motor_lag", HOVER, ["quadrotors.0.rotors={time_constant: 0.02}"], []),
    ("body drag", "body_drag", HOVER, ["quadrotors.0.drag=[0.1, 0.1, 0.2]"], []),
    ("wind", "wind", HOVER, ["quadrotors.0.wind={force: [0.1, 0, 0]}"], []),
    ("gimbal", "gimbal_servo", "configs/uav_camera_flight.yaml", [], ["quadrotors.0.cameras=[]"]),
]


@pytest.mark.parametrize("effect, scope, config, with_it, without_it", CASES, ids=[c[0] for c in CASES])
def test_absent_effect_traces_none_of_its_work(effect, scope, config, with_it, without_it):
    n_with, scopes_with = _traced(config, with_it)
    n_without, scopes_without = _traced(config, without_it)
    assert scopes_with.get(scope, 0) > 0, f"{effect}: nothing traced under '{scope}' in the scene that has it"
    assert scope not in scopes_without, f"{effect}: {scopes_without[scope]} equations under '{scope}' without it"
    assert n_without < n_with
