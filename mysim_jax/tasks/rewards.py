"""Rewards, success and failure of the capture task, on one snapshot of one environment.

**Rewards rank outcomes.** A step's reward is

    r = F + c + o,    F = γ Φ(s') − Φ(s)   (Φ(s') = 0 when the episode ends in s')

with ``F`` potential-based shaping (Ng, Harada & Russell 1999), ``c`` a per-step cost and
``o`` the outcome, paid once on the step that ends the episode. Shaping of this form adds
``−Φ(s_0)`` to every discounted return whatever the team does, so it guides learning but
cannot change which policy is optimal; and because ``Φ`` and the cost are bounded, no
episode's accumulated shaping and cost can outweigh its outcome when the outcome weights
exceed the bound :func:`~mysim_jax.config.env.return_bounds` computes (a scene whose
weights do not is refused when it is loaded). So for every team a caught episode returns
more than any missed one, and a missed one more than any crashed one.

The paper (Table rewards) names eight terms and their weights but gives no formulas; here
seven of them are the terms of the potential ``Φ = Σ_k w_k φ_k`` and the eighth (effort)
is the cost. Per UAV ``i`` (every ``φ_k`` is dimensionless and lies in ``[-1, 0]`` or
``[0, 1]``; ``safe`` in ``[-(n - 1), 0]``), the weights are non-negative and the sign is
part of the term. Notation: ``p_i, v_i, ω_i`` a UAV's position, velocity and body rate;
``s_i`` its slot (its start offset from the formation's centre, horizontal); ``p_t, v_t``
the target's position and velocity; ``c`` the predicted catch point
(:func:`~mysim_jax.tasks.intercept.predict_catch`: where the falling target comes down
to the net's height, drag included; the target itself once it is there); ``c_net,
v_net`` the mean position and velocity of the net's knots; ``c_uav`` the mean UAV
position; ``(·)_xy`` the horizontal part; scales ``L_d, V_a, Ω, L_s, D, V_s`` from
``env.reward_scales``.

* **distance** ``φ = −tanh(|(p_i − s_i − c)_xy| / L_d)``: the UAV's distance to its slot
  under the catch point, where it must be for the net's centre to meet the target.
* **alignment** ``φ = −tanh(|(v_i − v_t)_xy| / V_a)``: moving with the target.
* **spin** ``φ = −tanh(|ω_i| / Ω)``: body rates, which shake the net and blur cameras.
* **swing** ``φ = −tanh(|(c_net − c_uav)_xy| / L_s)`` (shared): a net swinging like a
  pendulum under the team hangs off the formation's centre.
* **safe** ``φ = −Σ_{j≠i} max(0, 1 − |p_i − p_j| / D)``: teammates closer than ``D``.
* **collision** ``φ = +1`` (shared) while the target touches a net line: its centre is
  within its radius (+ the line radius and ``contact_margin``) of a line segment.
* **stability** ``φ = +exp(−|v_t − v_net| / V_s)`` (shared) while the target is inside
  the net's outline, above the net and below the tether attachments, after it has first
  touched the net.
* **effort** (cost, every step) ``c = −mean_k (ω_k / ω_max)³`` over the four rotors:
  rotor power grows with the cube of rotor speed, so this is the fraction of full power
  the UAV draws.

Outcomes (beyond the paper, which has none): **success** ``+1`` on the step the target
has been held for ``hold_time`` (an evading target with entanglement,
:mod:`mysim_jax.effects.entanglement`, is held only once its entanglement reaches
``success.min_entanglement``: a drone still flying can sit in the net's outline without
being caught); **miss** ``−1`` on the step the target reaches the
ground; **crash** ``−1`` on the step a UAV fails (ground, tilt, altitude, a collision, a
non-finite state), whatever the target does then. A timeout is a truncation, not an
outcome: it pays nothing (a learner bootstraps the value there).
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from mysim_jax.core import vecmath
from mysim_jax.dynamics.quaternion import quat_rotate


@struct.dataclass
class Snapshot:
    """What the rewards and checks read from one environment (world frame)."""

    uav_pos: jnp.ndarray        # (n, 3) m
    uav_vel: jnp.ndarray        # (n, 3) m/s
    uav_quat: jnp.ndarray       # (n, 4) body -> world
    uav_angvel: jnp.ndarray     # (n, 3) rad/s, body frame
    rotor_fraction: jnp.ndarray  # (n, 4) motor speed / maximum speed
    target_pos: jnp.ndarray     # (3,) m
    target_vel: jnp.ndarray     # (3,) m/s
    knot_pos: jnp.ndarray       # (n_knots, 3) m
    knot_vel: jnp.ndarray       # (n_knots, 3) m/s
    border: jnp.ndarray         # (n_border, 3) m, border knots in order around the net
    attach: jnp.ndarray         # (n_tethers, 3) m, tether attachment markers
    line_a: jnp.ndarray         # (n_lines, 3) m, ends of the net's line segments
    line_b: jnp.ndarray         # (n_lines, 3) m
    # () in [0, 1], the evading target's entanglement (mysim_jax.effects.entanglement);
    # None in scenes without it
    entanglement: jnp.ndarray | None = None


@struct.dataclass
class Checks:
    """Per-step flags of one environment."""

    touching: jnp.ndarray       # () bool, target touches a net line
    inside: jnp.ndarray         # () bool, inside the net's outline (horizontally)
    above_net: jnp.ndarray      # () bool, above the net where it is (not under it)
    below: jnp.ndarray          # () bool, below every tether attachment
    slow: jnp.ndarray           # () bool, slow relative to the net
    above_ground: jnp.ndarray   # () bool
    failures: dict              # failure name -> () bool (FAILURES)
    # () bool, entangled at least success.min_entanglement (True in scenes without entanglement)
    entangled: jnp.ndarray

    @property
    def held(self):
        return self.inside & self.above_net & self.below & self.slow & self.above_ground & self.entangled

    @property
    def in_net(self):
        """Inside the outline, above the net and below the attachments: where a caught
        target lies (held asks, besides, that it is slow and off the ground)."""
        return self.inside & self.above_net & self.below


def inside_polygon(point, polygon):
    """Is ``point`` (2,) inside the closed polygon ``polygon`` (m, 2)? Crossing number."""
    a = polygon
    b = jnp.roll(polygon, -1, axis=0)
    straddles = (a[:, 1] > point[1]) != (b[:, 1] > point[1])
    dy = jnp.where(straddles, b[:, 1] - a[:, 1], 1.0)
    x_cross = a[:, 0] + (point[1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
    crossings = jnp.sum(straddles & (point[0] < x_cross))
    return crossings % 2 == 1


def segment_distance(p, a, b):
    """Distance ``(m,)`` from point ``p`` (3,) to the segments ``a -> b`` (m, 3)."""
    ab = b - a
    t = jnp.clip(vecmath.dot(p - a, ab) / jnp.maximum(vecmath.dot(ab, ab), 1e-12), 0.0, 1.0)
    return vecmath.safe_norm(a + t[:, None] * ab - p)


# knots around the target whose mean height is "the net under it"
NET_SURFACE_KNOTS = 3


def above_net(p, knot_pos, k: int = NET_SURFACE_KNOTS):
    """Is the point ``p`` (3,) above the net: higher than the mean height of the ``k``
    knots nearest to it horizontally (``knot_pos`` (n_knots, 3))? A target resting in the
    net lies above the knots under it; one under the net (the net draped over it, or
    hanging above it) has them above its centre."""
    d2 = jnp.sum((knot_pos[:, :2] - p[:2]) ** 2, axis=-1)
    index = jnp.arange(knot_pos.shape[0])
    height = jnp.zeros((), knot_pos.dtype)
    # the k nearest one by one, as masks (no top_k or gathers: batch-last has no rule for them)
    for _ in range(k):
        nearest = index == jnp.argmin(d2)
        height = height + jnp.sum(jnp.where(nearest, knot_pos[:, 2], 0.0))
        d2 = jnp.where(nearest, jnp.inf, d2)
    return p[2] > height / k


def tilt_cosine(quat):
    """``cos`` of the angle between each body's z axis and world z ``(n,)``."""
    z = jnp.zeros(quat.shape[:-1] + (3,), dtype=quat.dtype).at[..., 2].set(1.0)
    return quat_rotate(quat, z)[..., 2]


# s: a hold of ``hold_time`` counts although its duration was summed in float32 steps
HOLD_TOLERANCE = 1e-6


def hold_reached(held_time, hold_time):
    """Has the target been held long enough? ``held_time`` (s) from its first held sample
    (NumPy or JAX values): the one rule of the environment and of
    :func:`mysim_jax.tasks.outcome.capture_outcome`."""
    return held_time >= hold_time - HOLD_TOLERANCE


def held_flags(target_pos, target_vel, border, knot_pos, knot_vel, attach, entanglement, *, target_radius,
               success) -> dict:
    """The conditions of "held" at one instant (module docstring of
    :mod:`mysim_jax.tasks.outcome`), ``name -> () bool``: ``inside``, ``above_net``,
    ``below``, ``slow``, ``above_ground``, ``entangled``. ``target_pos``/``target_vel`` (3,);
    ``border`` (n_border, 3) the border knots in order around the net; ``knot_pos``/
    ``knot_vel`` (n_knots, 3); ``attach`` (n_tethers, 3) the tether attachment markers, or
    None (no tethers: always below); ``entanglement`` () in [0, 1] or None (no entanglement:
    always entangled). ``success``: the thresholds ``max_relative_speed``,
    ``ground_clearance``, ``min_entanglement`` (static floats). The environment's step and
    the saved-run verdict both call this."""
    below = jnp.asarray(True) if attach is None else target_pos[2] < jnp.min(attach[:, 2])
    v_rel = vecmath.safe_norm(target_vel - jnp.mean(knot_vel, axis=0))
    return {
        "inside": inside_polygon(target_pos[:2], border[:, :2]),
        "above_net": above_net(target_pos, knot_pos),
        "below": below,
        "slow": v_rel < success.max_relative_speed,
        "above_ground": target_pos[2] - target_radius > success.ground_clearance,
        "entangled": (jnp.asarray(True) if entanglement is None
                      else entanglement >= success.min_entanglement - 1e-6),
    }


def checks(snap: Snapshot, *, target_radius, line_radius, contact_margin, success, failure) -> Checks:
    """Flags of one snapshot. ``success`` / ``failure``: the SuccessConfig / FailureConfig
    thresholds (static floats)."""
    p_t = snap.target_pos
    gap = jnp.min(segment_distance(p_t, snap.line_a, snap.line_b)) - target_radius - line_radius
    touching = gap <= contact_margin
    held = held_flags(p_t, snap.target_vel, snap.border, snap.knot_pos, snap.knot_vel, snap.attach,
                      snap.entanglement, target_radius=target_radius, success=success)

    z = snap.uav_pos[:, 2]
    n = snap.uav_pos.shape[0]
    d = vecmath.safe_norm(snap.uav_pos[:, None, :] - snap.uav_pos[None, :, :])
    d = jnp.where(jnp.eye(n, dtype=bool), jnp.inf, d)
    d_target = vecmath.safe_norm(snap.uav_pos - p_t)
    finite = jnp.all(jnp.isfinite(snap.uav_pos)) & jnp.all(jnp.isfinite(p_t)) & jnp.all(jnp.isfinite(snap.knot_pos))
    on_ground = z - failure.uav_radius < failure.ground_clearance
    failures = {
        "uav_ground": jnp.any(on_ground),
        "uav_tilt": jnp.any(tilt_cosine(snap.uav_quat) < jnp.cos(jnp.deg2rad(failure.max_tilt_deg))),
        # too low (but not yet on the ground: that is uav_ground) or too high
        "uav_altitude": jnp.any(((z < failure.min_altitude) & ~on_ground) | (z > failure.max_altitude)),
        "uav_uav_collision": jnp.any(d < 2.0 * failure.uav_radius),
        "uav_target_collision": jnp.any(d_target < failure.uav_radius + target_radius),
        "target_ground": p_t[2] - target_radius < failure.ground_clearance,
        "non_finite": ~finite,
    }
    # a non-finite state makes every comparison False; report it alone
    failures = {k: (v & finite) if k != "non_finite" else v for k, v in failures.items()}
    return Checks(touching=touching & finite, failures=failures, **{k: v & finite for k, v in held.items()})


def potential_terms(snap: Snapshot, flags: Checks, *, catch_point, slots, scales, touched) -> dict:
    """The unweighted potential terms ``φ_k`` ``name -> (n,)`` of one state (module
    docstring; :data:`~mysim_jax.config.env.SHAPING_TERMS`). ``catch_point`` (3,) m;
    ``slots`` (n, 3) m; ``scales`` a RewardScales; ``touched`` (): the target has touched
    the net in this episode (this state included)."""
    n = snap.uav_pos.shape[0]
    dtype = snap.uav_pos.dtype
    ones = jnp.ones((n,), dtype=dtype)
    v_t = snap.target_vel
    # horizontal parts as 3-vectors with z = 0 (vecmath works on 3-vectors)
    offset = (snap.uav_pos - slots - catch_point).at[:, 2].set(0.0)
    dv = (snap.uav_vel - v_t).at[:, 2].set(0.0)
    c_net = jnp.mean(snap.knot_pos, axis=0)
    v_net = jnp.mean(snap.knot_vel, axis=0)
    c_uav = jnp.mean(snap.uav_pos, axis=0)
    d = vecmath.safe_norm(snap.uav_pos[:, None, :] - snap.uav_pos[None, :, :])
    crowd = jnp.where(jnp.eye(n, dtype=bool), 0.0, jnp.maximum(0.0, 1.0 - d / scales.safe_distance))
    resting = flags.in_net & touched
    terms = {
        "distance": -jnp.tanh(vecmath.safe_norm(offset) / scales.distance),
        "alignment": -jnp.tanh(vecmath.safe_norm(dv) / scales.alignment),
        "spin": -jnp.tanh(vecmath.safe_norm(snap.uav_angvel) / scales.spin),
        "swing": -jnp.tanh(vecmath.safe_norm((c_net - c_uav).at[2].set(0.0)) / scales.swing) * ones,
        "safe": -jnp.sum(crowd, axis=-1),
        "collision": flags.touching.astype(dtype) * ones,
        "stability": jnp.where(resting, jnp.exp(-vecmath.safe_norm(v_t - v_net) / scales.stability), 0.0) * ones,
    }
    return {k: jnp.where(jnp.isfinite(v), v, 0.0).astype(dtype) for k, v in terms.items()}


def cost_terms(snap: Snapshot) -> dict:
    """The unweighted per-step costs ``name -> (n,)`` (``effort``)."""
    effort = -jnp.mean(snap.rotor_fraction ** 3, axis=-1)
    return {"effort": jnp.where(jnp.isfinite(effort), effort, 0.0).astype(snap.uav_pos.dtype)}


def outcome_terms(n: int, dtype, *, succeeded, missed, crashed) -> dict:
    """The unweighted outcome terms ``name -> (n,)``: ``success`` +1, ``miss`` −1,
    ``crash`` −1 on the step that ends the episode that way (0 otherwise)."""
    ones = jnp.ones((n,), dtype=dtype)
    return {"success": succeeded.astype(dtype) * ones, "miss": -missed.astype(dtype) * ones,
            "crash": -crashed.astype(dtype) * ones}
