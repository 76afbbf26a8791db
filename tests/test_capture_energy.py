"""Energy balance of the capture scene with the controllers off (float64).

Scene: ``configs/capture_falling.yaml`` with the quadrotors' controllers off
(``controller: null``, constant motor commands: the hover speeds with a ±5 % yaw pattern and
a ±0.1 % pitch pattern, so rotor torques do work and the UAVs spin up), the ``team:``
block removed, RK4 with dt = 2e-5 s and one sub-step, 0.3 s. The target starts 5 cm above
the flat net, off centre, at 5 m/s down (0.3 m/s sideways), so it strikes the net at
once and drags the slack net down with it. Everything else is the scene's: the net and
its elastic tethers (tension-only), line drag, target drag, and contact, with one pair
added: ``[target, net]`` (the target against spheres on every net mass), so that
sphere–sphere contact is exercised next to the scene's sphere–capsule ``[target, lines]``
pairs. The ground and UAV pairs stay in the scene; the test checks they never touch.

Balance: E(t) + W_diss(t) − W_in(t) = E(0), with (tests/capture_energy_reference.py, plain
NumPy, none of the package's force, energy, marker, contact or rotor functions):

* E: kinetic energy of the points and bodies (rotational with the body inertia),
  gravitational potential, elastic energy of every spring (½ k (s − s̄)² while taut) and
  of every contact (k δⁿ⁺¹/(n + 1));
* W_diss: ∫ of the dissipated power of the spring dampers (with the tension clip: the
  dissipation is the spring's force power minus its elastic energy rate), of contact
  (normal damper and friction, same construction), line drag Σ c_i |v_i|³ (c_i recomputed
  from the net config's lumping) and target drag ½ ρ C_d π r² |v|³;
* W_in: ∫ of the rotor thrust power F·v and the rotor torque power τ·ω (arm and reaction
  torques), from the constant commands and the rotor geometry of the config.

The powers are integrated by the trapezoid rule over every saved step. Independent of
the package: all the laws above, the lumped point masses and line drag constants (the
test also checks the masses equal the built Params), the target drag constant, the rotor
layout and the marker kinematics. Taken from the built scene: the topology (names,
spring end nodes, marker bodies) and, from the Params, the spring constants and marker
offsets.

Measured (float64, this machine): the largest imbalance over the run is 1.4e-4 of the
largest kinetic energy (1.64 J), i.e. 2.3e-4 J, against 1.5 J dissipated; the test
allows 1.5e-3. The quadrature part of it is about 4e-5 (the trapezoid at 2h differs from
the one at h by 1.2e-4; the test allows 7.5e-4 there). The rest is integration error, about first order in the step, from the net's 0.08 g line
masses in contact and from the tension-only dampers. Measured on a milder variant
(target at 3 m/s, 2 % yaw pattern, 0.1 s): 2.0e-4 at dt = 2e-5 and 5.0e-5 at 1e-5;
8.8e-5 / 4.8e-5 without line damping; 2.6e-5 / 4.1e-6 without damping and friction.
(1) Friction on a line mass is stiff in the slip velocity (relaxation rate f·μ/(m·|u|),
1e5–1e6 1/s): from a state in sliding contact, 10 RK4 steps of 1e-5 s reach the energy
of 200 steps of 5e-7 s to 2e-7 J, but the friction power sampled along them integrates
to 9 % more than the converged dissipation (1.13e-4 against 1.035e-4 J); it converges
only once h ≲ 1e-6 s. (2) A tension-only spring's force jumps from 0 to c·ṡ when it goes
taut while stretching (``spring_tension`` in mysim_jax/dynamics/forces.py: no ramp,
unlike the contact damper), which makes each slack-to-taut event a first-order error of
the fixed-step integrator and of the quadrature.

Dropping any one term of W_diss or W_in (spring damping 0.16 J, contact 0.05 J, line drag
0.51 J, target drag 0.79 J, thrust −0.04 J, rotor torques 0.04 J) breaks the balance
by at least 10x the tolerance: every one of them is tested, not only the total.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from capture_energy_reference import EnergyModel, cumulative_trapezoid
from conftest import CONFIGS

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.sim import rollout

DT = 2.0e-5          # s, one RK4 sub-step per step, every step saved
T_END = 0.3          # s
CHUNK = 2500         # steps per compiled rollout call (states go to NumPy chunk by chunk)
TOLERANCE = 1.5e-3   # relative imbalance allowed (about 10x the measured 1.4e-4)
YAW_PATTERN = 0.05   # ± on the motor speeds of rotors 1, 3 vs 2, 4
PITCH_PATTERN = 0.001


@dataclasses.dataclass(frozen=True)
class ConstantMotors:
    """Policy: the same motor speeds ``(n_quads, 4)`` every step (hashable)."""

    speeds: tuple

    def __call__(self, scene, params, state):
        return jnp.asarray(self.speeds, dtype=state.phys.body_pos.dtype)


def _scene_config():
    raw = yaml.safe_load((CONFIGS / "capture_falling.yaml").read_text())
    raw.pop("team")
    for q in raw["quadrotors"]:
        q["controller"] = None
    raw["sim"].update(precision="float64", integrator="rk4", dt=DT, substeps=1, t_end=T_END, output_dt=DT)
    pos, vel = [0.1, 0.05, 3.2], [0.3, 0.0, -5.0]
    raw["target"]["spawn"] = {"position": {"low": pos, "high": pos}, "velocity": {"low": vel, "high": vel}}
    raw["contact"]["pairs"].append(["target", "net"])
    return config_from_dict(raw, "capture_falling.yaml (energy test)")


def _run():
    config = _scene_config()
    scene, params, state = build(config)
    assert scene.substep == DT and scene.quadrotor.controller == "none"
    assert all(q.rotors.time_constant is None for q in config.quadrotors)     # no motor lag
    hover = np.asarray(state.controller.motor_speed)
    speeds = hover * (1.0 + YAW_PATTERN * np.array([1.0, -1.0, 1.0, -1.0])
                      + PITCH_PATTERN * np.array([1.0, 1.0, -1.0, -1.0]))
    qp = params.quadrotor
    assert np.all(speeds > np.asarray(qp.omega_min)[:, None]) and np.all(speeds < np.asarray(qp.omega_max)[:, None])

    model = EnergyModel(config, scene, params, speeds, sphere_pair_group="net")
    np.testing.assert_allclose(model.point_mass, np.asarray(params.point_mass), rtol=1e-12)

    advance = jax.jit(rollout, static_argnums=(0, 3, 4, 5))
    policy = ConstantMotors(tuple(map(tuple, speeds.tolist())))
    leaves = ("point_pos", "point_vel", "body_pos", "body_quat", "body_vel", "body_angvel")

    def as_numpy(phys, first=False):
        return {k: np.asarray(getattr(phys, k), float)[None] if first else np.asarray(getattr(phys, k), float)
                for k in leaves}

    def clearances(p):
        """Smallest gap of the pairs the model does not count (ground, UAVs)."""
        bp = p["body_pos"]
        uav, tgt = bp[:, model.quad_body], bp[:, model.target]
        ground = min(p["point_pos"][..., 2].min() - 0.005, bp[..., 2].min() - 0.15)
        uav_gap = np.linalg.norm(uav[:, :, None] - uav[:, None], axis=-1) + 1e9 * np.eye(len(model.quad_body))
        return min(ground, uav_gap.min() - 0.3, np.linalg.norm(uav - tgt[:, None], axis=-1).min() - 0.3)

    first = as_numpy(state.phys, first=True)
    parts, gap = [model.evaluate(first)], clearances(first)
    n_steps = round(T_END / DT)
    for _ in range(n_steps // CHUNK):
        state, states = advance(scene, params, state, CHUNK, 1, policy)
        phys = as_numpy(states.phys)
        parts.append(model.evaluate(phys))
        gap = min(gap, clearances(phys))
    assert gap > 0.0
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


@pytest.mark.float64
def test_capture_energy_balance_with_controllers_off():
    r = _run()
    assert np.all(np.isfinite(r["energy"]))
    assert r["contact_depth"].max() > 1e-4          # the target was in contact, deeper than 0.1 mm
    assert r["spring_clipped"].max() > 0            # the tension clip was active at some time

    def work(key):
        return cumulative_trapezoid(r[key], DT)

    w_diss, w_in = work("dissipation"), work("input")
    imbalance = r["energy"] + w_diss - w_in - r["energy"][0]
    scale = r["kinetic"].max()
    rel = np.abs(imbalance).max() / scale
    assert rel < TOLERANCE, f"energy imbalance {rel:.3g} of the largest kinetic energy ({scale:.3g} J)"

    # quadrature error estimate: the trapezoid at 2h against h
    coarse = (r["energy"][::2] + cumulative_trapezoid(r["dissipation"][::2], 2 * DT)
              - cumulative_trapezoid(r["input"][::2], 2 * DT) - r["energy"][0])
    assert np.abs(coarse - imbalance[::2]).max() / scale < 0.5 * TOLERANCE

    # the balance tests something: the dissipated work is most of the energy lost, and
    # leaving out any single dissipated or input term breaks the balance by far
    drop = r["energy"][-1] - r["energy"][0]
    assert drop < 0.0 and w_diss[-1] > 0.5 * -drop
    assert np.abs(imbalance - w_diss).max() / scale > 100 * TOLERANCE
    for key, sign in (("spring_damping", 1), ("contact_damping", 1), ("line_drag", 1), ("target_drag", 1),
                      ("thrust", -1), ("rotor_torque", -1)):
        without = imbalance - sign * work(key)
        assert np.abs(without).max() / scale > 10 * TOLERANCE, key
