"""Independent reference for a rigid body on a tension-only lumped-mass rope (NumPy/SciPy).

Nothing here comes from ``mysim_jax``: the scene is read from the raw YAML dict (plain
Python, no config validation, no builder), and the equations of motion are written out
again from the documented physics:

* rope (``mysim_jax/net/rope.py`` docstring, paper Sec. 2.1): ``N`` point masses on the
  straight line from start to end at the cumulative rest lengths (scaled to the current
  end-to-end distance), at rest; rest lengths ``[L/2N, L/N, ..., L/N, L/2N]``, stiffness
  ``EA / s̄``, damping ``d / s̄``; tension ``T = k (s − s̄) + c ṡ`` applied while the
  segment is *taut*, i.e. ``s > s̄`` and ``T > 0``, and nothing otherwise;
* rigid body: quaternion scalar-first ``(w, x, y, z)`` rotating body → world, angular
  velocity in the body frame, ``q̇ = ½ q ⊗ (0, ω)``, Euler's equations
  ``J ω̇ = τ − ω × J ω``; the rope's end pulls at the marker ``r`` (body frame): force
  ``F`` on the centre of mass and torque ``r × (Rᵀ F)``; marker velocity
  ``v + R (ω × r)``; gravity on every mass.

The force law is piecewise smooth: a segment switching between slack and taut makes the
right-hand side jump (going taut at ``s = s̄`` with ``ṡ > 0`` the damper force ``c ṡ``
switches on at once) or kink (going slack when ``T`` reaches zero). A high-order solver
stepping over such a switch loses its order, so this reference is a *hybrid* integration:
each segment carries a discrete mode (taut / slack); within an interval the modes are
fixed and the right-hand side is smooth (a taut segment applies ``T u`` even if it would
stray past the switch, a slack one applies nothing); the switching function of every
segment, ``g = min(s − s̄, T)`` (taut ⇔ ``g > 0``), is watched by ``solve_ivp`` events,
one per segment, in the direction that leaves the current mode; at an event the solver
stops, the segment's mode flips and the integration restarts from the located state.
DOP853 at rtol 1e-12 then keeps its accuracy across every switch.

A segment that has just switched starts on its root (to the root finder's accuracy, on
either side of it), and ``solve_ivp`` only compares signs at step ends: a switching
function that starts at +1e-16 in the slack mode, dips and comes back within one step is
never seen, the segment stays slack while stretched, and the rope lets the body through
(this happened while writing the test: a segment stretched by metres). So the next switch
of such a segment is watched at a level ``SWITCH_GUARD`` = 1e-12 (m or N) beyond its start
value, strictly on the other side of the start.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp


def _qmul(p, q):
    """Hamilton product of two quaternions ``(w, x, y, z)``."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])


def _rotmat(q):
    """Rotation matrix of a (normalised here) quaternion ``(w, x, y, z)``, body → world."""
    w, x, y, z = (float(a) for a in q)
    n = 1.0 / (w * w + x * x + y * y + z * z) ** 0.5
    w, x, y, z = w * n, x * n, y * n, z * n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _cross(a, b):
    """Cross product of two 3-vectors (np.cross is slow for single vectors)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


# Level (in units of g: metres or newtons) beyond its start value that a just-switched
# segment's switching function must cross to switch again: far below anything resolved.
SWITCH_GUARD = 1e-12


class TetheredBodyReference:
    """One rigid body, one anchor and one rope from the anchor to a marker on the body.

    ``raw`` is the scene as a plain dict (``yaml.safe_load`` of the scene file). State
    vector: rope positions ``(N, 3)``, rope velocities ``(N, 3)``, body position, quaternion
    (4), velocity, body-frame angular velocity.
    """

    def __init__(self, raw: dict):
        (body,) = raw["bodies"]
        (anchor,) = raw["anchors"]
        (rope,) = raw["ropes"]
        assert rope["start"] == anchor["name"] and rope["model"] == "tension_only"
        body_name, marker_name = rope["end"].split(".")
        assert body_name == body["name"]
        marker = next(m for m in body["markers"] if m["name"] == marker_name)
        self.g = np.asarray(raw.get("gravity", [0.0, 0.0, -9.81]), float)
        self.body_mass = float(body["mass"])
        self.inertia = np.diag(np.asarray(body["inertia"], float))
        self.inertia_inv = np.linalg.inv(self.inertia)
        self.r = np.asarray(marker["pos"], float)
        self.anchor = np.asarray(anchor["pos"], float)
        n = self.n = int(rope["n_masses"])
        length = float(rope["length"])
        self.rope_mass = float(rope["mass"])
        self.rest = np.array([length / (2 * n)] + [length / n] * (n - 1) + [length / (2 * n)])
        self.k = float(rope["EA"]) / self.rest
        self.c = float(rope.get("damping", 0.0)) / self.rest

        q0 = np.asarray(body.get("quat", [1.0, 0.0, 0.0, 0.0]), float)
        p0 = np.asarray(body["pos"], float)
        end = p0 + _rotmat(q0) @ self.r
        frac = np.cumsum(self.rest)[:-1] / length
        x0 = self.anchor + frac[:, None] * (end - self.anchor)
        self.y0 = np.concatenate([
            x0.ravel(), np.zeros(3 * n), p0, q0 / np.linalg.norm(q0),
            np.asarray(body.get("vel", [0.0, 0.0, 0.0]), float),
            np.asarray(body.get("angvel", [0.0, 0.0, 0.0]), float),
        ])

    # --- state layout ---------------------------------------------------------------------
    def unpack(self, y):
        n = self.n
        x = y[:3 * n].reshape(n, 3)
        v = y[3 * n:6 * n].reshape(n, 3)
        o = 6 * n
        return x, v, y[o:o + 3], y[o + 3:o + 7], y[o + 7:o + 10], y[o + 10:o + 13]

    def segments(self, y):
        """Per segment: unit vector (anchor side → body side), length, rate, raw tension
        ``k (s − s̄) + c ṡ``; and the body's rotation matrix."""
        x, v, p, q, vb, w = self.unpack(y)
        rot = _rotmat(q)
        r_world = rot @ self.r
        n = self.n
        nodes_x = np.empty((n + 2, 3))
        nodes_x[0] = self.anchor
        nodes_x[1:-1] = x
        nodes_x[-1] = p + r_world
        nodes_v = np.zeros((n + 2, 3))
        nodes_v[1:-1] = v
        nodes_v[-1] = vb + rot @ _cross(w, self.r)
        d = nodes_x[1:] - nodes_x[:-1]
        s = np.sqrt((d * d).sum(axis=1))
        u = d / s[:, None]
        rate = ((nodes_v[1:] - nodes_v[:-1]) * u).sum(axis=1)
        tension = self.k * (s - self.rest) + self.c * rate
        return u, s, rate, tension, rot

    def switching(self, y):
        """``g = min(s − s̄, T)`` per segment: taut exactly where ``g > 0``."""
        _, s, _, tension, _ = self.segments(y)
        return np.minimum(s - self.rest, tension)

    def tension(self, y):
        """Tension of every segment under the true (max / slack) law."""
        _, s, _, tension, _ = self.segments(y)
        return np.where(s > self.rest, np.maximum(tension, 0.0), 0.0)

    def rhs(self, y, taut):
        """Time derivative with the segment modes ``taut`` (bool per segment) held fixed."""
        x, v, p, q, vb, w = self.unpack(y)
        u, _, _, tension, rot = self.segments(y)
        f = np.where(taut, tension, 0.0)[:, None] * u      # pull on the anchor-side node
        node_force = np.zeros((self.n + 2, 3))
        node_force[:-1] += f
        node_force[1:] -= f
        acc = node_force[1:-1] / self.rope_mass + self.g
        f_marker = node_force[-1]
        body_acc = f_marker / self.body_mass + self.g
        torque = _cross(self.r, rot.T @ f_marker)
        angacc = self.inertia_inv @ (torque - _cross(w, self.inertia @ w))
        qdot = 0.5 * _qmul(q, np.concatenate([[0.0], w]))
        return np.concatenate([v.ravel(), acc.ravel(), vb, qdot, body_acc, angacc])

    # --- hybrid integration ---------------------------------------------------------------
    def solve(self, t_end, t_eval, rtol=1e-12, atol=1e-13, max_step=np.inf, max_events=100_000):
        """Integrate to ``t_end``; returns a dict with the states at ``t_eval`` (rows),
        the switch log ``[(t, segment, now_taut)]`` and the mode intervals
        ``[(t0, t1, taut_mask)]``."""
        t_eval = np.asarray(t_eval, float)
        taut = self.switching(self.y0) > 0.0
        t0, y0 = 0.0, self.y0.copy()
        ys = np.full((len(t_eval), len(y0)), np.nan)
        switches, intervals = [], []
        n_seg = self.n + 1
        n_rhs = 0
        while True:
            events = []
            cache = {"y": None, "g": None}

            def g_of(y, cache=cache):
                # solve_ivp evaluates every event function on the same state: compute once
                if cache["y"] is None or not np.array_equal(cache["y"], y):
                    cache["y"], cache["g"] = y.copy(), self.switching(y)
                return cache["g"]

            # a segment that has just switched starts on its root (to the root finder's
            # accuracy, maybe on the wrong side): watch for g crossing a level SWITCH_GUARD
            # beyond the start value, so that a dip and return within the first step is seen
            g0 = self.switching(y0)
            for j in range(n_seg):
                sign = -1.0 if taut[j] else 1.0              # leaving taut: g falls; leaving slack: g rises
                level = max(sign * g0[j], 0.0) + SWITCH_GUARD if sign * g0[j] > -SWITCH_GUARD else 0.0

                def ev(t, y, j=j, level=sign * level):
                    return g_of(y)[j] - level
                ev.terminal = True
                ev.direction = sign                          # only the crossing that leaves the mode
                events.append(ev)
            mode = taut.copy()
            sol = solve_ivp(lambda t, y: self.rhs(y, mode), (t0, t_end), y0, method="DOP853",
                            rtol=rtol, atol=atol, max_step=max_step, events=events,
                            dense_output=True)
            assert sol.status >= 0, sol.message
            n_rhs += sol.nfev
            t1 = sol.t[-1]
            inside = (t_eval >= t0) & (t_eval <= t1)
            if inside.any():
                ys[inside] = sol.sol(t_eval[inside]).T
            intervals.append((t0, t1, mode))
            if sol.status == 0:
                break
            fired = [j for j in range(n_seg) if len(sol.t_events[j])]
            for j in fired:
                taut[j] = not taut[j]
                switches.append((t1, j, bool(taut[j])))
            t0, y0 = t1, sol.y[:, -1].copy()
            assert len(switches) < max_events, "too many switches: chattering?"
        return {"t": t_eval, "y": ys, "switches": switches, "intervals": intervals, "nfev": n_rhs}
