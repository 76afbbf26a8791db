"""Did the net catch the target? The verdict on a saved capture run.

The target is **held** at an output time when all of these hold:

* *inside the net's outline*: its horizontal position is inside the polygon of the
  net's border knots (at that time);
* *above the net*: its centre is higher than the mean height of the
  :data:`~mysim_jax.tasks.rewards.NET_SURFACE_KNOTS` knots nearest to it horizontally (it lies in the net, not under it);
* *below the tether attachments*: its centre is lower than every tethered UAV's
  attachment marker;
* *slow relative to the net*: its speed relative to the mean velocity of the knots is
  below ``max_relative_speed``;
* *above the ground*: its lowest point is at least ``ground_clearance`` above z = 0;
* *entangled* (an evading target with ``target.entanglement`` only): its entanglement
  (the trajectory's ``TARGET_entanglement`` column) is at least ``min_entanglement``.

A run **catches** the target when it is held over the last ``hold_time`` seconds of the
run. The conditions and the hold rule are the environment's own
(:func:`~mysim_jax.tasks.rewards.held_flags`, :func:`~mysim_jax.tasks.rewards.hold_reached`),
evaluated here at every output sample of the run's trajectory columns (in float64). The
same columns feed the plots (UAV–target distances, tether tensions).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core.npgeom import rotate
from mysim_jax.dynamics.forces import spring_tension
from mysim_jax.tasks.rewards import held_flags, hold_reached

MAX_RELATIVE_SPEED = 0.5   # m/s
GROUND_CLEARANCE = 0.05    # m
HOLD_TIME = 0.5            # s
MIN_ENTANGLEMENT = 1.0     # share of the propulsion lost (evading targets with entanglement)


@dataclass
class CaptureOutcome:
    """Per-output flags ``(n_out,)`` and the verdict."""

    time: np.ndarray
    inside: np.ndarray
    above_net: np.ndarray
    below: np.ndarray
    slow: np.ndarray
    above_ground: np.ndarray
    caught: bool
    first_held: float | None     # s, first time from which the target stays held to the end
    entangled: np.ndarray | None = None   # (n_out,) bool; None without entanglement

    @property
    def held(self) -> np.ndarray:
        held = self.inside & self.above_net & self.below & self.slow & self.above_ground
        return held if self.entangled is None else held & self.entangled

    def summary(self) -> dict:
        last = -1
        return {
            "caught": bool(self.caught),
            "held_from_s": self.first_held,
            "at_end": {"inside_net_outline": bool(self.inside[last]), "above_net": bool(self.above_net[last]),
                       "below_tether_attachments": bool(self.below[last]),
                       "slow_relative_to_net": bool(self.slow[last]), "above_ground": bool(self.above_ground[last]),
                       **({} if self.entangled is None else {"entangled": bool(self.entangled[last])})},
        }


def border_knots(net) -> list[str]:
    """Names of the net's border knots, in order around the square."""
    g = net.knots
    ring = [(0, j) for j in range(g)] + [(i, g - 1) for i in range(1, g)]
    ring += [(g - 1, j) for j in range(g - 2, -1, -1)] + [(i, 0) for i in range(g - 2, 0, -1)]
    return [net.knot_name(i, j) for i, j in ring]


def _xyz(columns, name, prefix=""):
    return np.stack([columns[f"{name}_{prefix}{a}"] for a in "xyz"], axis=-1)


def _attachments(columns, config):
    """World positions ``(n_out, n_tethers, 3)`` of the tethers' UAV markers."""
    net = config.net
    out = []
    for uav in net.tethers.uavs:
        q = np.stack([columns[f"{uav}_q{a}"] for a in "wxyz"], axis=-1)
        out.append(_xyz(columns, uav) + rotate(q, net.tethers.attach))
    return np.stack(out, axis=1)


def capture_outcome(columns, config, max_relative_speed=None, ground_clearance=None, hold_time=None,
                    min_entanglement=None) -> CaptureOutcome:
    """Evaluate a capture run from its trajectory columns (:mod:`mysim_jax.io.trajectory`).
    A threshold left None is the scene's ``env.success`` value when it has an ``env:``
    block (the environment's own verdict), else this module's default."""
    success = config.env.success if getattr(config, "env", None) is not None else None

    def pick(value, name, default):
        return value if value is not None else getattr(success, name) if success is not None else default

    max_relative_speed = pick(max_relative_speed, "max_relative_speed", MAX_RELATIVE_SPEED)
    ground_clearance = pick(ground_clearance, "ground_clearance", GROUND_CLEARANCE)
    hold_time = pick(hold_time, "hold_time", HOLD_TIME)
    min_entanglement = pick(min_entanglement, "min_entanglement", MIN_ENTANGLEMENT)
    net, target = config.net, config.target
    time = np.asarray(columns["time"])
    knots = [net.knot_name(i, j) for i in range(net.knots) for j in range(net.knots)]
    entanglement = None
    if target.entanglement is not None:
        column = f"{target.name}_entanglement"
        if column not in columns:
            raise ValueError(f"the target has entanglement (target.entanglement) but the trajectory has no "
                             f"'{column}' column: it comes from a stepped run (scripts/simulate.py writes it)")
        entanglement = np.asarray(columns[column], np.float64)
    thresholds = SimpleNamespace(max_relative_speed=max_relative_speed, ground_clearance=ground_clearance,
                                 min_entanglement=min_entanglement)
    # the environment's own conditions (rewards.held_flags), over the output samples, in float64
    with jax.enable_x64(True):
        samples = (_xyz(columns, target.name), _xyz(columns, target.name, "v"),
                   np.stack([_xyz(columns, k) for k in border_knots(net)], axis=1),
                   np.stack([_xyz(columns, k) for k in knots], axis=1),
                   np.stack([_xyz(columns, k, "v") for k in knots], axis=1),
                   _attachments(columns, config) if net.tethers is not None else None, entanglement)
        flags = jax.vmap(partial(held_flags, target_radius=target.radius, success=thresholds))(
            *[None if a is None else jnp.asarray(a, jnp.float64) for a in samples])
        flags = {k: np.broadcast_to(np.asarray(v), time.shape) for k, v in flags.items()}
    inside, over_net, below, slow, above = (flags[k] for k in ("inside", "above_net", "below", "slow", "above_ground"))
    entangled = flags["entangled"] if entanglement is not None else None
    held = inside & over_net & below & slow & above
    if entangled is not None:
        held = held & entangled
    first = None
    if held[-1]:
        not_held = np.flatnonzero(~held)
        start = 0 if not_held.size == 0 else not_held[-1] + 1
        first = float(time[start])
    caught = first is not None and bool(hold_reached(time[-1] - first, hold_time))
    return CaptureOutcome(time=time, inside=inside, above_net=over_net, below=below, slow=slow, above_ground=above,
                          caught=bool(caught), first_held=first, entangled=entangled)


def tether_tensions(columns, scene, params, config) -> dict[str, np.ndarray]:
    """Tension ``(n_out,)`` [N] in the knot end segment of every tether (the scene's spring
    law, :func:`~mysim_jax.dynamics.forces.spring_tension`, at the saved positions and
    velocities), keyed by the tethered UAV's name."""
    net = config.net
    out = {}
    if net.tethers is None:
        return out
    k_all = np.asarray(params.spring_stiffness, float)
    c_all = np.asarray(params.spring_damping, float)
    rest_all = np.asarray(params.spring_rest_length, float)
    knots = net.tether_knots()
    for n, uav in enumerate(net.tethers.uavs):
        idx = scene.spring_names.index(f"{net.name}_t{n}[0]")
        a = net.knot_name(*knots[n])
        if net.tethers.n_masses > 0:
            b = f"{net.name}_t{n}_0"
            p_b, v_b = _xyz(columns, b), _xyz(columns, b, "v")
        else:
            # a tether without interior masses is one segment from the knot to the UAV's
            # marker: its end moves with the body (angular velocity saved in the body frame)
            q = np.stack([columns[f"{uav}_q{c}"] for c in "wxyz"], axis=-1)
            r = np.broadcast_to(np.asarray(net.tethers.attach, float), q.shape[:-1] + (3,))
            p_b = _xyz(columns, uav) + rotate(q, r)
            v_b = _xyz(columns, uav, "v") + rotate(q, np.cross(_xyz(columns, uav, "w"), r))
        d = p_b - _xyz(columns, a)
        dv = v_b - _xyz(columns, a, "v")
        length = np.linalg.norm(d, axis=-1)
        rate = np.einsum("ij,ij->i", dv, d / np.maximum(length, 1e-12)[:, None])
        out[uav] = np.asarray(spring_tension(k_all[idx], c_all[idx], rest_all[idx], length, rate,
                                             (scene.spring_tension_only[idx],)))
    return out


def uav_target_distances(columns, config) -> dict[str, np.ndarray]:
    """Distance ``(n_out,)`` [m] from every quadrotor's centre to the target's centre."""
    p = _xyz(columns, config.target.name)
    return {q.body: np.linalg.norm(_xyz(columns, q.body) - p, axis=-1) for q in config.quadrotors}


def thrust_fraction(columns, scene, params, config, window: float = 1.0) -> dict[str, float]:
    """Mean rotor thrust over the last ``window`` seconds as a fraction of the maximum
    thrust ``Σ c_i ω_max²``, per quadrotor (from the saved motor commands): the share of
    the lift each UAV spends, e.g. hovering with the net hanging from it."""
    qp = params.quadrotor
    lift = np.asarray(qp.lift_coefficient, float)
    omega_max = np.asarray(qp.omega_max, float)
    time = np.asarray(columns["time"])
    last = time >= time[-1] - window - 1e-9
    out = {}
    for qi, q in enumerate(config.quadrotors):
        speeds = np.stack([columns[f"{q.body}_rotor{k + 1}"] for k in range(4)], axis=-1)[last]
        thrust = (speeds ** 2 * lift[qi]).sum(axis=-1)
        out[q.body] = float(thrust.mean() / (lift[qi].sum() * omega_max[qi] ** 2))
    return out
