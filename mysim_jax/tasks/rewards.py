"""Rewards, success and failure of the capture task, on one snapshot of one environment.

The paper (Table rewards) names eight terms and their weights but gives no formulas.
Here is each one, per UAV ``i`` (every term is dimensionless and lies in ``[-1, 0]`` or
``[0, 1]``, so the weight alone sets its share; the sign is part of the term, the weights
are non-negative). Notation: ``p_i, v_i, ω_i`` a UAV's position, velocity and body rate;
``s_i`` its slot (its start offset from the formation's centre, horizontal); ``p_t, v_t``
the target's position and velocity; ``c_net, v_net`` the mean position and velocity of the
net's knots; ``c_uav`` the mean UAV position; ``(·)_xy`` the horizontal part; scales
``L_d, V_a, Ω, L_s, D, V_s`` from ``env.reward_scales``.

* **distance** ``−tanh(|(p_i − s_i − p_t)_xy| / L_d)``: the UAV's distance to where it must
  be for the net's centre to lie under the target. Zero when the whole formation is
  centred under the target, so it rewards positioning the net, not crowding the target
  (a UAV right above the target would put the net beside it).
* **alignment** ``−tanh(|(v_i − v_t)_xy| / V_a)``: moving with the target. Once the net
  is under a moving target, staying under it means matching its horizontal velocity.
* **spin** ``−tanh(|ω_i| / Ω)``: body rates, which shake the net and blur cameras.
* **effort** ``−mean_k (ω_k / ω_max)³`` over the four rotors: rotor power grows with the
  cube of rotor speed, so this is the fraction of full power the UAV draws.
* **swing** ``−tanh(|(c_net − c_uav)_xy| / L_s)`` (shared): a net swinging like a
  pendulum under the team hangs off the formation's centre, and then the team's placing
  (distance) no longer puts the net where the target arrives.
* **safe** ``−Σ_{j≠i} max(0, 1 − |p_i − p_j| / D)``: a linear penalty for every teammate
  closer than ``D`` (zero beyond it), so it only acts near a collision.
* **collision** ``+1`` (shared) while the target touches a net line: its centre is within
  its radius (+ the line radius and ``contact_margin``) of a line segment.
* **stability** ``+exp(−|v_t − v_net| / V_s)`` (shared) while the target is inside the
  net's outline and below the tether attachments, after it has first touched the net:
  a caught target that comes to rest in the net rather than bouncing out.

Two terminal terms beyond the paper, weight 0 by default: **success** ``+1`` on the step
the episode succeeds, **failure** ``−1`` on a step it fails (not on a timeout).
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from mysim_jax import vecmath
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


@struct.dataclass
class Checks:
    """Per-step flags of one environment."""

    touching: jnp.ndarray       # () bool, target touches a net line
    inside: jnp.ndarray         # () bool, inside the net's outline (horizontally)
    below: jnp.ndarray          # () bool, below every tether attachment
    slow: jnp.ndarray           # () bool, slow relative to the net
    above_ground: jnp.ndarray   # () bool
    failures: dict              # failure name -> () bool (FAILURES)

    @property
    def held(self):
        return self.inside & self.below & self.slow & self.above_ground


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


def tilt_cosine(quat):
    """``cos`` of the angle between each body's z axis and world z ``(n,)``."""
    z = jnp.zeros(quat.shape[:-1] + (3,), dtype=quat.dtype).at[..., 2].set(1.0)
    return quat_rotate(quat, z)[..., 2]


def checks(snap: Snapshot, *, target_radius, line_radius, contact_margin, success, failure) -> Checks:
    """Flags of one snapshot. ``success`` / ``failure``: the SuccessConfig / FailureConfig
    thresholds (static floats)."""
    p_t = snap.target_pos
    gap = jnp.min(segment_distance(p_t, snap.line_a, snap.line_b)) - target_radius - line_radius
    touching = gap <= contact_margin
    inside = inside_polygon(p_t[:2], snap.border[:, :2])
    below = p_t[2] < jnp.min(snap.attach[:, 2])
    v_rel = vecmath.safe_norm(snap.target_vel - jnp.mean(snap.knot_vel, axis=0))
    slow = v_rel < success.max_relative_speed
    above = p_t[2] - target_radius > success.ground_clearance

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
    return Checks(touching=touching & finite, inside=inside & finite, below=below & finite, slow=slow & finite,
                  above_ground=above & finite, failures=failures)


def reward_terms(snap: Snapshot, flags: Checks, *, slots, scales, touched_before, succeeded, failed) -> dict:
    """Unweighted terms ``name -> (n,)`` (module docstring). ``slots`` (n, 3) m;
    ``scales`` a RewardScales; ``touched_before`` (): the target touched the net at an
    earlier or this step; ``succeeded`` / ``failed`` (): the episode ends so this step."""
    n = snap.uav_pos.shape[0]
    dtype = snap.uav_pos.dtype
    ones = jnp.ones((n,), dtype=dtype)
    p_t, v_t = snap.target_pos, snap.target_vel
    # horizontal parts as 3-vectors with z = 0 (vecmath works on 3-vectors)
    offset = (snap.uav_pos - slots - p_t).at[:, 2].set(0.0)
    dv = (snap.uav_vel - v_t).at[:, 2].set(0.0)
    c_net = jnp.mean(snap.knot_pos, axis=0)
    v_net = jnp.mean(snap.knot_vel, axis=0)
    c_uav = jnp.mean(snap.uav_pos, axis=0)
    d = vecmath.safe_norm(snap.uav_pos[:, None, :] - snap.uav_pos[None, :, :])
    crowd = jnp.where(jnp.eye(n, dtype=bool), 0.0, jnp.maximum(0.0, 1.0 - d / scales.safe_distance))
    resting = flags.inside & flags.below & touched_before
    terms = {
        "distance": -jnp.tanh(vecmath.safe_norm(offset) / scales.distance),
        "alignment": -jnp.tanh(vecmath.safe_norm(dv) / scales.alignment),
        "spin": -jnp.tanh(vecmath.safe_norm(snap.uav_angvel) / scales.spin),
        "effort": -jnp.mean(snap.rotor_fraction ** 3, axis=-1),
        "swing": -jnp.tanh(vecmath.safe_norm((c_net - c_uav).at[2].set(0.0)) / scales.swing) * ones,
        "safe": -jnp.sum(crowd, axis=-1),
        "collision": flags.touching.astype(dtype) * ones,
        "stability": jnp.where(resting, jnp.exp(-vecmath.safe_norm(v_t - v_net) / scales.stability), 0.0) * ones,
        "success": succeeded.astype(dtype) * ones,
        "failure": -failed.astype(dtype) * ones,
    }
    return {k: jnp.where(jnp.isfinite(v), v, 0.0).astype(dtype) for k, v in terms.items()}
